"""The typed records of the after-calibration products: `jaxcal certify`, `jaxcal check`, `jaxcal verify`.

Two kinds of record live here:

- **What the products read of a calibration** (`CalibrationReference`, with its
  `PointFitModel`; `HandEyeReference` of a `jaxcal handeye` result): the few blocks of
  `result.json` they use, typed. `jaxcal.io.checks` reads them (it is the only module that
  knows the file's keys).
- **What the products write**: `Certificate`, `DriftCheck` and `Verification` with
  their typed blocks. `jaxcal.io.checks` writes them as `certificate.json`,
  the `jaxcal check --json` file and the `jaxcal verify --json` file (and reads them back).

As in `jaxcal.records`, a block's field names are its JSON keys (a block is a `Record`,
so that `c.summary["p95_mm"]` still reads as it did when the blocks were dicts; new code
reads attributes, `c.summary.p95_mm`); the top-level records, whose JSON shape differs
from their fields (arrays per pose, the drift's twist split in two), are mapped in
`jaxcal.io.checks`.
"""

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ._kinematics import KinematicModel
from .markers import TargetSpec
from .records import NAMED, Intrinsics, Named, PriorUse, Record, ResidualStats, optional

#: Exit status of `jaxcal check` when drift is detected.
EXIT_DRIFT = 3
#: Exit status of `jaxcal verify` when the measured errors lie outside what the calibration predicts.
EXIT_OUTSIDE_PREDICTION = 3


# --------------------------------------------------------------------------- what the products read


@dataclass(frozen=True, eq=False)
class PointFitModel:
    """What a stop-and-shoot result's `point_fit` block says to predict the measured point at
    any configuration: the nominal model, the non-geometric `terms`, the parameter vector `x`
    with its `free` mask and `covariance`, the fit's residual variance factor, the median
    per-axis noise `sigma_m` (m), the references the corrections are relative to and the
    links' inertials; with measured orientations (`orientation`) their median per-axis noise
    `sigma_rad` (rad); the samples fitted (None in results written before the key); whether the
    dataset gave the point's nominal mount (`mount_given`; else `T_flange_point0` is a start)."""

    nominal: KinematicModel
    terms: tuple[str, ...]
    x: np.ndarray
    free: np.ndarray
    covariance: np.ndarray
    residual_variance_factor: float
    sigma_m: float
    T_device_base0: np.ndarray
    T_flange_point0: np.ndarray
    masses: np.ndarray
    coms: np.ndarray
    orientation: bool = False
    sigma_rad: float | None = None
    samples: int | None = None
    mount_given: bool = True
    #: The fleet's prior the fit took, or None.
    prior: PriorUse | None = None

    @property
    def dof(self) -> int | None:
        """The fit's residual degrees of freedom (what its variance factor was estimated on)."""
        if self.samples is None:
            return None
        return (6 if self.orientation else 3) * self.samples - int(np.sum(self.free))


@dataclass(frozen=True, eq=False)
class CalibrationReference:
    """What `certify`, `check` and `verify` read of a calibration's `result.json` (`file`).

    Every block may be missing (an older or a partial file): the product that needs it
    says so, naming the file."""

    file: Path
    #: The calibration's dataset (its path as `result.json` gives it).
    dataset: str | None = None
    #: `jaxcal calibrate`'s set-up label (`tracker ...`, `eye-to-hand`, ...) and capture in words.
    setup: str = ""
    capture: str | None = None
    #: The camera (or tracker) calibrated, the tracker device, the targets, the eye-in-hand board.
    camera: str | None = None
    device: str | None = None
    targets: tuple[str, ...] = ()
    board: str | None = None
    #: Whether the fixed frame is a measuring device's (`T_device_base`).
    device_frame: bool = False
    #: The calibrated model's joints.
    joint_names: tuple[str, ...] | None = None
    intrinsics: Intrinsics | None = None
    #: The clock offset used (s), and the refinement's robust pixel noise scale (px).
    clock_offset_s: float | None = None
    sigma_px: float | None = None
    #: A stop-and-shoot result's point fit.
    point_fit: PointFitModel | None = None
    #: Which covariance the result carries (`jaxcal.io.result.COVARIANCE_MODELS`; None: written before).
    covariance_model: str | None = None
    #: The calibration's verdict (`ok`, `suspect`, `failed`; None: not given) and its first reason.
    status: str | None = None
    reason: str = ""

    @property
    def tracker(self) -> bool:
        """Whether a tracker calibrated it (with or without a point fit)."""
        return self.setup.startswith("tracker") or self.device_frame


@dataclass(frozen=True, eq=False)
class HandEyeCameraReference:
    """A camera of a `jaxcal handeye` result as `jaxcal check` reads it: its size, the intrinsics
    it was calibrated with, $T_{cam,robot}$, and the joint covariance of the camera's and the
    target's tangent deltas `(12, 12)` (the model's and the frame-robust one; None in results
    written before `jaxcal check` read hand-eye results)."""

    name: str
    width: int
    height: int
    K: np.ndarray
    distortion: np.ndarray
    T_cam_robot: np.ndarray
    covariance: np.ndarray | None
    covariance_frames: np.ndarray | None


@dataclass(frozen=True, eq=False)
class HandEyeReference:
    """What `jaxcal check` reads of a `jaxcal handeye` result (`file`): the arrangement
    (`eye_in_hand` or `eye_to_hand`), the cameras, the target with its pose
    $T_{robot,target}$, the robot pose noise the solve used (`(translation mm, rotation
    deg)` per axis; for exact poses the noise their held-out frames read as, `result.json`'s
    `held_out`, or None) and the corner noise `sigma_px`."""

    file: Path
    arrangement: str
    cameras: tuple[HandEyeCameraReference, ...]
    target: TargetSpec
    T_robot_target: np.ndarray
    robot_noise: tuple[float, float] | None
    sigma_px: float

    @property
    def eye_in_hand(self) -> bool:
        return self.arrangement == "eye_in_hand"

    @property
    def camera_names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.cameras)

    def camera(self, name: str) -> HandEyeCameraReference | None:
        """The camera called `name`, or None."""
        return next((c for c in self.cameras if c.name == name), None)


# --------------------------------------------------------------------------- jaxcal check


@dataclass(frozen=True, eq=False)
class JointOffset(Record):
    """A joint's zero offset change a check estimated, and its std (deg)."""

    joint: str
    estimate_deg: float
    std_deg: float


@dataclass(frozen=True, eq=False)
class Detectable(Record):
    """The smallest translation (mm) and rotation (deg) a check detects with the quoted power,
    along its worst and best directions, and the non-centrality of that power."""

    noncentrality: float
    translation_mm_worst: float
    translation_mm_best: float
    rotation_deg_worst: float
    rotation_deg_best: float


@dataclass(frozen=True, eq=False)
class DriftResidual(Record):
    """The drift fit's whitened residual sum of squares, its degrees of freedom and p-value; a
    camera check adds its estimated corner noise variance factor (and the calibration
    covariance's), a hand-eye check each view's coherent pose error (mm, deg)."""

    sum_of_squares: float
    dof: int
    p_value: float
    view_sigma_mm: float | None = optional()
    view_sigma_deg: float | None = optional()
    noise_variance_factor: float | None = optional()
    calibration_covariance_factor: float | None = optional()
    #: A tracker capture with orientations: theirs, against the prediction moved by the drift.
    rotation_sum_of_squares: float | None = optional()
    rotation_dof: int | None = optional()
    rotation_p_value: float | None = optional()

    @property
    def fits_rigidly(self) -> bool:
        """A rigid move explains the capture: the residuals (and the orientations') are not both
        improbable (p < 0.001) and over twice their degrees of freedom."""
        rot = self.rotation_sum_of_squares
        return not (self.p_value < 1e-3 and self.sum_of_squares > 2.0 * self.dof) and (
            rot is None or not (self.rotation_p_value < 1e-3 and rot > 2.0 * self.rotation_dof)
        )


@dataclass(frozen=True, eq=False)
class DriftCheck:
    """What `check` found (`jaxcal.drift`; lengths in mm, angles in deg).

    - `theta`, `cov`: the drift $(v, \\omega[, \\delta q])$ (m, rad) and its covariance.
    - `statistic`, `dof`, `threshold`, `p_value`, `detected`: the test at level `alpha`
      (chi-square, or Fisher's F on `dof_noise` degrees of freedom when the noise scale
      was estimated).
    - `translation_mm`, `rotation_deg`: the device's motion, each `(size, std)`.
    - `joint_offsets_deg`: per joint its offset change when fitted, else None.
    - `detectable`: the smallest change detected with the quoted power; `residual`: the
      fit's whitened residuals; `rotation_residual_deg`: with orientations, their angles from
      the calibrated prediction moved by the drift (deg), else None.
    - `T_device_base`: the calibrated fixed pose moved by the estimated drift (`frame`
      names it: `T_device_base`, `T_cam_base`, eye-in-hand `T_flange_cam`, hand-eye
      `T_base_cam` / `T_ee_cam`); `what` moved: `"device"` or `"camera"`.
    - `message`, `advice`: what to tell the user.
    """

    result: str
    capture: str
    samples: int
    theta: np.ndarray
    cov: np.ndarray
    statistic: float
    dof: int
    threshold: float
    p_value: float
    detected: bool
    translation_mm: tuple[float, float]
    rotation_deg: tuple[float, float]
    joint_offsets_deg: tuple[JointOffset, ...] | None
    detectable: Detectable
    residual: DriftResidual
    T_device_base: np.ndarray
    message: str
    advice: str
    alpha: float
    what: str = "device"
    frame: str = "T_device_base"
    dof_noise: int | None = None
    rotation_residual_deg: ResidualStats | None = None

    @property
    def exit_code(self) -> int:
        """`EXIT_DRIFT` when a drift is detected or the capture fits no rigid move of the calibration."""
        return EXIT_DRIFT if self.detected or not self.residual.fits_rigidly else 0

    @property
    def test(self) -> str:
        """`chi2`, or `F` when the noise scale was estimated."""
        return "chi2" if self.dof_noise is None else "F"


# --------------------------------------------------------------------------- jaxcal certify


@dataclass(frozen=True, eq=False)
class Region(Record):
    """The region a certificate covers: `kind` `cartesian_box` (the box `(x0, y0, z0, x1, y1, z1)`,
    m, base frame, and the configurations drawn), `joint_box` (per joint `(lo, hi)`, rad or m)
    or `poses`."""

    kind: str
    box_m: tuple[float, ...] | None = optional()
    drawn: int | None = optional()
    ranges: tuple[tuple[float, float], ...] | None = optional()


@dataclass(frozen=True, eq=False)
class WorstPose(Record):
    """The region's pose of the largest 95 % bound: its index, configuration (rad, or m),
    tool point (m, base frame) and predicted RMS error (mm)."""

    index: int
    q: tuple[float, ...]
    point_m: tuple[float, ...]
    rms_mm: float


@dataclass(frozen=True, eq=False)
class CertificateSummary(Record):
    """A certificate over its region (mm): the mean and RMS of the predicted per-pose RMS error,
    the region's 95th percentile, the largest per-pose 95 % bound, the unexplained scatter in
    it, and the worst pose."""

    poses: int
    mean_mm: float
    rms_mm: float
    p95_mm: float
    max_bound95_mm: float
    unexplained_scatter_mm: float
    worst: WorstPose


@dataclass(frozen=True, eq=False)
class Extrapolation(Record):
    """How far a region leaves the calibrated workspace (`jaxcal.certification.extrapolation`)."""

    #: Per joint the calibration's `(lo, hi)` (rad, or m), and how far the region goes beyond.
    calibrated_joint_range: tuple[tuple[float, float], ...]
    joint_excess: tuple[Named, ...] = field(metadata={NAMED: True})
    share_of_poses_outside_joint_ranges: float
    max_joint_excess: float
    #: None when the calibration's points are flat (no hull).
    share_of_points_outside_hull: float | None
    max_distance_outside_hull_mm: float | None
    #: The predicted RMS error over the calibration's configurations (mm) and the region's over it.
    calibrated_rms_mm: float
    error_ratio: float | None
    extrapolated: bool


@dataclass(frozen=True, eq=False)
class CertificateRotation(Record):
    """A certificate's orientation part (deg), for a calibration that fitted measured orientations:
    the mean and RMS of the point frame's predicted per-pose RMS angle error, the region's 95th
    percentile, the largest per-pose 95 % bound and the unexplained angular scatter in it."""

    mean_deg: float
    rms_deg: float
    p95_deg: float
    max_bound95_deg: float
    unexplained_scatter_deg: float


@dataclass(frozen=True, eq=False)
class Certificate:
    """A certificate (distances in mm; see `jaxcal.certification`).

    - `q`: the region's configurations `(C, joints)`; `points`: the calibrated tool
      point there, base frame (m); `rms_mm`, `bound95_mm`: per pose the predicted
      RMS error and its 95 % bound.
    - `summary`: over the region; `extrapolation`: None when the calibration's
      configurations are unknown; `caveats`, `notes`.
    - `covariance_model`: the calibration's covariance it propagated
      (`jaxcal.io.result.COVARIANCE_MODELS`; None for results written before the key).
    - `rotation`, `rms_deg`, `bound95_deg`: with measured orientations, the point frame's
      orientation error over the region and per pose (deg); None otherwise.
    """

    result: str
    kind: str
    frame: str
    region: Region
    joint_names: tuple[str, ...]
    q: np.ndarray
    points: np.ndarray
    rms_mm: np.ndarray
    bound95_mm: np.ndarray
    summary: CertificateSummary
    extrapolation: Extrapolation | None
    caveats: tuple[str, ...] = ()
    notes: tuple[str, ...] = ()
    covariance_model: str | None = None
    rotation: CertificateRotation | None = None
    rms_deg: np.ndarray | None = None
    bound95_deg: np.ndarray | None = None


# --------------------------------------------------------------------------- jaxcal verify


@dataclass(frozen=True, eq=False)
class VerificationSummary(Record):
    """A verification over its samples (mm): the calibrated and nominal errors (`nominal`: the
    nominal robot in the calibration's fitted device frame, `jaxcal.verification`), the
    predicted RMS, measured over predicted, the share inside the predicted 95 % bound, and the
    parameters' part of the predicted RMS; with orientations the same of the angles (deg)."""

    samples: int
    calibrated_mm: ResidualStats
    nominal_mm: ResidualStats
    predicted_rms_mm: float
    measured_over_predicted: float
    inside_95_bound: float
    parameter_part_rms_mm: float
    calibrated_deg: ResidualStats | None = optional()
    nominal_deg: ResidualStats | None = optional()
    predicted_rms_deg: float | None = optional()
    measured_over_predicted_deg: float | None = optional()
    inside_95_bound_deg: float | None = optional()


@dataclass(frozen=True, eq=False)
class PredictionTest(Record):
    """Whether a dataset's errors are what the calibration predicts (`jaxcal.verification`): the
    errors of `samples` samples, `components` each (3 positions, or with orientations 6), whitened
    by their predicted joint covariance, give the `statistic` (their sum of squares) on `dof`
    degrees of freedom, F-distributed against the noise scale's `dof_noise` (chi-square when
    None), its `p_value`, and the whitened measured / predicted RMS `ratio` with its `ratio_limit`;
    the share of samples whose whitened error lies inside its 95 % bound (`inside`), the least the
    one-sided binomial test accepts (`inside_limit`) and its `p_inside`. Each test at level `alpha`;
    the calibration `holds` when neither rejects."""

    samples: int
    components: int
    statistic: float
    dof: int
    dof_noise: int | None
    ratio: float
    ratio_limit: float
    p_value: float
    inside: float
    inside_limit: float
    p_inside: float
    alpha: float
    holds: bool


@dataclass(frozen=True, eq=False)
class CrossValidation(Record):
    """K-fold cross-validation's distances (mm) on the verified dataset, with orientations their
    angles (deg): the calibration's own folds and observations, so that on its dataset the
    figures are `jaxcal calibrate`'s."""

    folds: int
    mean: float
    rms: float
    max: float
    mean_deg: float | None = optional()
    rms_deg: float | None = optional()
    max_deg: float | None = optional()


@dataclass(frozen=True, eq=False)
class Verification:
    """What `verify` found (distances in mm; `jaxcal.verification`).

    - `errors_mm`, `nominal_mm`: per sample, the distance of the measured point
      from the calibrated and from the nominal prediction.
    - `predicted_mm`: per sample, the RMS distance the calibration predicts
      (parameter covariance and the fit's residual scatter).
    - `errors_deg`, `nominal_deg`, `predicted_deg`: the same of the orientations' angles
      (deg) when the calibration fitted orientations and the dataset has them, else None.
    - `summary`: over the samples; `cv`: with `cv=K`, the K-fold cross-validation;
      `test`: whether the errors are what the calibration predicts (`exit_code`).
    """

    result: str
    dataset: str
    samples: np.ndarray
    errors_mm: np.ndarray
    nominal_mm: np.ndarray
    predicted_mm: np.ndarray
    summary: VerificationSummary
    cv: CrossValidation | None = None
    notes: tuple[str, ...] = ()
    test: PredictionTest | None = None
    errors_deg: np.ndarray | None = None
    nominal_deg: np.ndarray | None = None
    predicted_deg: np.ndarray | None = None

    @property
    def exit_code(self) -> int:
        """`EXIT_OUTSIDE_PREDICTION` when the test rejects the calibration's prediction, else 0."""
        return 0 if self.test is None or self.test.holds else EXIT_OUTSIDE_PREDICTION
