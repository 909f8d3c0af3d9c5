"""The typed rows and blocks of a `CalibrationResult` (`jaxcal.stages.result`).

Each block of `result.json` that used to be a dict is a frozen dataclass here,
every field typed and documented, so that a renamed field fails in the editor
and in `tests/test_architecture.py`, not in a user's report.

A field's name is its `result.json` key (`jaxcal.io.result` writes and reads
the file; only the blocks whose JSON shape differs from the record, such as
`reduction_ratios` keyed by joint, are mapped there). Two field markers
decide the JSON shape:

- `optional()`: a key written only when the value is not None (`given_s` when
  the metadata gave a clock offset, the refined figures when the refinement ran);
- `named()`: a tuple of `Named` rows written as a `{name: value}` object
  (per-joint counts, per-parameter std).

Every record is also a read-only mapping of its JSON block (`result.clock["offset_s"]`,
`for k in result.validation`), so that notebooks written against the dict
results keep working; new code reads attributes (`result.clock.offset_s`).

This module imports nothing from jaxcal: the stages build the records and the
`io` layer writes them, both from below it in the import graph.
"""

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from ._records_base import (  # noqa: F401 (re-exported: every record module's vocabulary)
    KEYED,
    NAMED,
    OPTIONAL,
    Named,
    Record,
    from_plain,
    keyed,
    named,
    optional,
    plain,
    row_of,
)


@dataclass(frozen=True)
class Judgement:
    """What both products' verdicts say first (`jaxcal.stages.Verdict`, `jaxcal.HandEyeVerdict`):
    `status` (`ok`, `suspect`, or for the calibration `failed`) and the `reasons` it is not ok
    (empty when ok). Each verdict adds its own: the calibration its checks with value and limit,
    hand-eye its notes."""

    status: str
    reasons: tuple[str, ...]

    @property
    def ok(self) -> bool:
        """Whether the status is `ok`."""
        return self.status == "ok"


def named_rows(d: Mapping | None) -> tuple[Named, ...] | None:
    """`Named` rows from a `{name: value}` mapping (None stays None)."""
    return None if d is None else tuple(Named(str(k), plain(v)) for k, v in d.items())


@dataclass(frozen=True, eq=False)
class Clock(Record):
    """The camera-controller clock offset (controller time = camera time + offset)."""

    #: The offset used (s): the refined one when the refinement estimated it.
    offset_s: float
    #: Its 1-sigma std (s); None when it was not estimated.
    std_s: float | None
    #: Whether the data estimated it (else the metadata's offset, or 0, was used).
    estimated: bool
    #: The camera clock's rate error against the controller's (ppm, from the metadata).
    drift_ppm: float
    #: The metadata's offset (s) when one was given and the estimate replaced it.
    given_s: float | None = optional()
    #: The two-stage (arc-fit) offset and std (s) when the refinement refined the offset.
    offset_s_two_stage: float | None = optional()
    std_s_two_stage: float | None = optional()


@dataclass(frozen=True, eq=False)
class FrameCounts(Record):
    """How the two-stage camera's frames (or a device's samples) were used."""

    images: int
    target_found: int
    no_target: int
    #: Frames outside the encoder log's time span, and inside one of its glitches.
    outside_encoder_log: int
    in_encoder_glitch: int
    #: Frames with a target, inside the log, in no single-joint sweep.
    not_in_a_sweep: int
    #: Per joint the frames its arc fit used (`poses` for a pose-based capture).
    used_per_joint: tuple[Named, ...] = named()
    #: Capture indices missing between the camera's first and last frame.
    dropped_capture_indices: tuple[int, ...] = ()
    #: Frame rows whose PnP pose was an outlier (left out).
    pnp_outliers: tuple[int, ...] = ()
    #: Tracker data: the device's samples.
    samples: int | None = optional()

    def used(self, joint: str) -> int:
        """The frames (or samples) `joint`'s fit used (`"poses"` for a pose-based capture)."""
        return int(next(int(r.value) for r in self.used_per_joint if r.name == joint))


@dataclass(frozen=True, eq=False)
class SolverInfo(Record):
    """The solvers' outcomes (optimistix result names and step counts)."""

    #: Every solver converged.
    success: bool
    #: Per joint whether its arc fit converged (empty without arcs).
    arc_fits_ok: tuple[bool, ...]
    #: The axis fit's result name, or why it did not run.
    axis_fit: str
    axis_fit_steps: int | None = optional()
    axis_fit_residual_rms: float | None = optional()
    #: Stop-and-shoot tracker data: the point fit's result and steps.
    point_fit: str | None = optional()
    point_fit_steps: int | None = optional()
    #: The refinement's result, steps and whether every robust round converged (when it ran).
    refinement: str | None = optional()
    refinement_steps: int | None = optional()
    refinement_rounds_ok: bool | None = optional()


@dataclass(frozen=True, eq=False)
class RatioRow(Record):
    """One joint's reduction ratio (motor rad per joint rad; per m for a prismatic joint)."""

    joint: str
    nominal: float
    #: None when the capture cannot see it (no encoder log, no refinement).
    estimate: float | None
    std: float | None
    identifiable: bool
    #: A prismatic joint: the ratio's unit, and the scale (true per commanded travel) with its std.
    ratio_unit: str | None = optional()
    scale: float | None = optional()
    scale_std: float | None = optional()


@dataclass(frozen=True, eq=False)
class ParameterRow(Record):
    """One physical parameter (`jaxcal._correction.physical_parameters`)."""

    #: `joint.origin.tx`, `T_cam_base.rx`, `marker.mount.tz`, `joint.rate`...
    name: str
    #: `m`, `rad`, `1` ...
    unit: str
    #: Its group in the correction vector (`correction`, `camera`, `mount`, ...).
    group: str
    nominal: float
    estimate: float
    std: float
    #: Whether the data estimated it (else held at nominal).
    free: bool


def parameter_rows(rows) -> tuple[ParameterRow, ...]:
    """`ParameterRow`s from `physical_parameters`' rows (rows already typed pass through)."""
    return tuple(r if isinstance(r, ParameterRow) else ParameterRow(**r) for r in rows)


@dataclass(frozen=True, eq=False)
class Intrinsics(Record):
    """A camera's intrinsics: given, self-calibrated, or refined with the robot (the calibration's
    first camera; each camera of a hand-eye capture, `jaxcal.handeye`)."""

    #: `metadata`, `self-calibrated (ChArUco)`, or `none (...)` for tracker data; hand-eye:
    #: `given` or `self-calibrated`.
    source: str
    #: Self-calibration's reprojection RMS (px).
    rms_px: float | None = optional()
    #: The camera matrix (3, 3) and OpenCV distortion coefficients (None for tracker data).
    K: np.ndarray | None = optional()
    distortion: np.ndarray | None = optional()
    #: When the refinement freed them: True, the std per freed coefficient, those held,
    #: and the start values.
    refined: bool | None = optional()
    std: tuple[Named, ...] | None = named(is_optional=True)
    held_in_refinement: tuple[str, ...] | None = optional()
    K_start: np.ndarray | None = optional()
    distortion_start: np.ndarray | None = optional()


@dataclass(frozen=True, eq=False)
class SolveOutcome(Record):
    """One solve's optimistix result name (`successful`, ...) and its step count."""

    result: str
    steps: int


@dataclass(frozen=True, eq=False)
class ArcOutlier(Record):
    """A sample a robust arc fit rejected."""

    #: The target (marker) and the frame (capture index) it was seen in, at camera time `timestamp_s`.
    target: str
    frame: int
    timestamp_s: float
    #: Its whitened residual, in noise units.
    residual: float
    #: Tracker data: the sample's index and its line in the samples file.
    sample: int | None = optional()
    line: str | None = optional()


@dataclass(frozen=True, eq=False)
class ArcRow(Record):
    """One joint's arc fit (the first error function): its fit, axis and ratio."""

    joint: str
    #: `revolute` or `prismatic`.
    type: str
    frames: int
    position_rms_mm: float
    #: None for points measured without an orientation.
    rotation_rms_deg: float | None
    #: Whitened residual RMS (noise units).
    residual_rms: float
    #: The axis direction and a point on it (m; None for a prismatic joint), camera frame.
    direction_cam: tuple[float, ...]
    point_cam_m: tuple[float, ...] | None
    ratio_nominal: float
    #: Reduction ratio and std (None without an encoder log); refined when the refinement ran.
    ratio: float | None
    ratio_std: float | None
    ratio_identifiable: bool
    #: A prismatic joint: `rad/m`, the scale (true per commanded travel), its std, the travel (mm).
    ratio_unit: str | None = optional()
    scale: float | None = optional()
    scale_std: float | None = optional()
    travel_mm: float | None = optional()
    solver: SolveOutcome | None = None
    #: The robust fit's noise scale, and the samples it rejected.
    robust_scale: float | None = None
    outliers: tuple[ArcOutlier, ...] = ()
    #: When the refinement refined the ratios: the arc fit's ratio and std.
    ratio_two_stage: float | None = optional()
    ratio_std_two_stage: float | None = optional()


@dataclass(frozen=True, eq=False)
class PoseError(Record):
    """A pose's error against the truth: translation (mm) and rotation (deg)."""

    trans_mm: float
    rot_deg: float
    #: What the truth was compared in, and the error without that gauge.
    gauge: str | None = optional()
    raw_trans_mm: float | None = optional()
    raw_rot_deg: float | None = optional()


@dataclass(frozen=True, eq=False)
class JointError(Record):
    """One joint's calibrated parameters against the truth."""

    joint: str
    axis_direction_deg: float
    #: A revolute joint's axis position error (mm).
    axis_position_mm: float | None = optional()
    #: The reduction ratio's error (%), None when it was not estimated.
    ratio_percent: float | None = None
    #: The zero offset's error: deg (revolute) or mm (prismatic). A zero offset trades with the
    #: joint origins' rotations about the axis and, along parallel axes, with the next origins'
    #: offsets, which the estimator holds at nominal (its gauge) and the truth perturbs: with sweeps
    #: it is taken against the truth as the estimator sees it (the same axis fit on exact sweeps of
    #: the truth), an error to hold against its standard deviation; without sweeps it is the raw
    #: difference, which is not.
    zero_offset_deg: float | None = optional()
    zero_offset_mm: float | None = optional()


@dataclass(frozen=True, eq=False)
class CameraPoseError(Record):
    """A further camera's pose relative to the first against the truth, at the start and refined."""

    camera: str
    start: PoseError
    refined: PoseError


@dataclass(frozen=True, eq=False)
class ValidationReport(Record):
    """A synthetic dataset's calibration against its `truth.json` (`result.json`'s `validation`)."""

    #: Random configurations of the end-effector comparison, and the point compared.
    configurations: int
    ee_point: str
    #: End-effector error RMS and max (mm): nominal model, calibrated, two-stage.
    ee_rms_mm_before: float
    ee_max_mm_before: float
    ee_rms_mm_after: float
    ee_max_mm_after: float
    ee_rms_mm_two_stage: float
    ee_max_mm_two_stage: float
    #: Whether "after" is the refinement's.
    refined: bool
    T_cam_base_error: PoseError
    parameter_errors: tuple[JointError, ...] = keyed("joint")
    true_ratios: tuple[float, ...] = ()
    true_clock_offset_s: float | None = None
    T_cam_base_error_two_stage: PoseError | None = optional()
    #: The clock offset's error (ms), None when the truth has none.
    clock_offset_error_ms: float | None = None
    other_cameras: tuple[CameraPoseError, ...] | None = keyed("camera", is_optional=True)


@dataclass(frozen=True, eq=False)
class EEErrors(Record):
    """Per validation configuration the end-effector error (mm) of each model."""

    before: np.ndarray
    two_stage: np.ndarray
    after: np.ndarray


@dataclass(frozen=True, eq=False)
class Correlation(Record):
    """Two refined parameters correlated beyond 0.95."""

    a: str
    b: str
    rho: float


@dataclass(frozen=True, eq=False)
class WeakDirection(Record):
    """A direction of the parameters the corners barely see: its singular value
    against the largest, and the parameters it moves most (their weights)."""

    singular_value_ratio: float
    parameters: tuple[Named, ...] = named()


@dataclass(frozen=True, eq=False)
class TwoStageStart(Record):
    """The two-stage figures the refinement started from."""

    T_cam_base: np.ndarray
    std_cam: np.ndarray
    T_flange_target: np.ndarray
    clock_offset_s: float
    #: Per joint the arc fit's reduction ratio (None without an encoder log).
    ratios: tuple[Named, ...] = named()


@dataclass(frozen=True, eq=False)
class ViewAngle(Record):
    """Without an encoder log: one sweep view's joint angle, estimated from its image."""

    frame: int
    joint: str
    angle_deg: float
    std_deg: float


@dataclass(frozen=True, eq=False)
class JointAngles(Record):
    """The per-view joint angles of a capture without an encoder log."""

    note: str
    views: tuple[ViewAngle, ...]


@dataclass(frozen=True, eq=False)
class LineDelay(Record):
    """A rolling-shutter camera's line delay (s per row), as given or estimated."""

    camera: str
    line_delay_s: float
    #: Its std (s; None when given).
    std_s: float | None
    estimated: bool
    #: The delay times the image height (s).
    readout_s: float


@dataclass(frozen=True, eq=False)
class ShutterTest(Record):
    """The rolling shutter a global-shutter refinement's residuals point to (a score test)."""

    camera: str
    line_delay_s: float
    readout_s: float
    #: The delay's size in its standard deviations.
    sigmas: float


@dataclass(frozen=True, eq=False)
class PriorUse(Record):
    """How much a fleet's prior (`jaxcal.fleet`) gave a point fit: the `file` it came from, the
    `units` it was learnt on and, per parameter it covers (`names`), the prior's share of the
    posterior's information (`share`: the diagonal of $C P$, the posterior covariance times
    the prior's precision; the data gave the rest: 0, the data alone; 1, the prior alone)."""

    file: str
    units: int
    names: tuple[str, ...]
    share: tuple[float, ...]
    #: The prior itself (its mean and covariance over `names`): `jaxcal verify --cv` fits with it.
    mean: np.ndarray
    covariance: np.ndarray
    #: Per parameter, the data-alone fit's distance from the prior's mean in the standard deviation
    #: of that difference ($\sqrt{\Sigma_{ii} + D_{ii}}$, $D$ the data-alone fit's covariance); NaN
    #: where the data alone do not estimate the parameter.
    z: tuple[float, ...] = ()
    #: The same over the parameters the data alone estimate, together: $\chi^2$ with `dof` degrees
    #: of freedom under a unit of the prior's fleet (`jaxcal.stages._prior.prior_use`).
    chi2: float | None = optional()
    dof: int | None = optional()


@dataclass(frozen=True, eq=False)
class ModelRow(Record):
    """One model the cross-validation of the non-geometric terms compared: its terms, free
    parameters, cross-validated errors (a tracker's point distances in mm and, with measured
    orientations, angles in deg; a camera's reprojection errors in px; when cross-validation
    ran), whether it was kept and why."""

    terms: tuple[str, ...]
    free: int
    cv_mean_mm: float | None = optional()
    cv_rms_mm: float | None = optional()
    cv_max_mm: float | None = optional()
    kept: bool = False
    cv_mean_px: float | None = optional()
    cv_rms_px: float | None = optional()
    cv_max_px: float | None = optional()
    #: Why the model was kept or not, in words (camera captures).
    why: str | None = optional()
    cv_mean_deg: float | None = optional()
    cv_rms_deg: float | None = optional()
    cv_max_deg: float | None = optional()
    #: A model with a term: its gain over the model it was tried against, in standard errors of
    #: the paired held-out distances (`jaxcal._selection.paired_z`; tracker samples).
    cv_gain_z: float | None = optional()


@dataclass(frozen=True, eq=False)
class TermRow(Record):
    """A non-geometric coefficient (`jaxcal._terms`): its estimate, std and whether it was free."""

    name: str
    estimate: float
    std: float
    free: bool


@dataclass(frozen=True, eq=False)
class TermsSummary(Record):
    """The non-geometric terms of a calibration (`result.json`'s `terms`): the families tried
    and kept, the models cross-validation compared (the geometric one first), the kept
    coefficients with their std, the folds (and, for camera views, the consecutive frames
    left out together), the payload the gravity torques included, and notes (what was not
    tried, and why)."""

    tried: tuple[str, ...]
    kept: tuple[str, ...]
    models: tuple[ModelRow, ...]
    coefficients: tuple[TermRow, ...]
    folds: int
    block_frames: int | None = optional()
    payload_kg: float | None = optional()
    notes: tuple[str, ...] = ()


@dataclass(frozen=True, eq=False)
class LensTest(Record):
    """The radial distortion a refinement's residuals point to, beyond the lens it was given (a
    score test on $k_1, k_2$; `jaxcal._diagnostics.lens_test`)."""

    camera: str
    k1: float
    k2: float
    #: The radial shift they imply at the image's corner (px).
    shift_px: float
    #: Their size in standard deviations (the two-degree-of-freedom score statistic as a normal's).
    sigmas: float


@dataclass(frozen=True, eq=False)
class IntrinsicsTest(Record):
    """The focal lengths and principal point a refinement's residuals point to, beyond those it was
    given (a score test on $f_x, f_y, c_x, c_y$; `jaxcal._diagnostics.intrinsics_test`): their
    increments (px)."""

    camera: str
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    #: The shift they imply at the image's farthest corner (px).
    shift_px: float
    #: Their size in standard deviations (the four-degree-of-freedom score statistic as a normal's).
    sigmas: float


@dataclass(frozen=True, eq=False)
class ErrorCorrelation(Record):
    """Whether the refinement's residuals repeat along the capture and between the views of one
    pose (`jaxcal._diagnostics.residual_correlation`, `jaxcal.stages._residual_tests`)."""

    #: Per lag $k = 1..K$ (frames along a run of the capture): the pooled correlation of each
    #: corner's residual with its own $k$ frames later, its self-normalised $z$, and the pairs.
    autocorrelation: tuple[float, ...]
    z: tuple[float, ...]
    pairs: tuple[int, ...]
    #: Ljung-Box's $Q = \sum_k z_k^2$ on $K$ degrees of freedom, and its p-value.
    q_statistic: float
    dof: int
    p_value: float
    #: The one-sided test of errors that repeat, $\sum_{k \le L} z_k / \sqrt{L}$ over Newey-West's
    #: $L$ lags (sigmas).
    sigmas: float
    #: Between the views of one pose (several cameras or targets in one frame): the score test
    #: of their shared error (sigmas; None: one view per pose).
    pose_sigmas: float | None = optional()
    #: Where either is significant: the kernel (HAC) sandwich's lags (poses along the capture),
    #: which the covariance now takes where it is larger.
    kernel_lags: int | None = optional()


@dataclass(frozen=True, eq=False)
class RefinementSummary(Record):
    """The reprojection refinement (`result.json`'s `refinement`)."""

    solver: SolveOutcome
    #: The robust pixel noise scale and the inliers' RMS (px).
    sigma_px: float
    inlier_rms_px: float
    corners: int
    outlier_corners: int
    #: Frames whose corners stay outliers.
    outlier_frames: tuple[int, ...]
    correlations: tuple[Correlation, ...]
    condition_number: float
    weak_directions: tuple[WeakDirection, ...]
    views: int
    frames: int
    free_parameters: int
    #: Parameters held at the start (not identifiable), and those the refinement froze beyond the two-stage's.
    held_at_start: tuple[str, ...]
    frozen_beyond_two_stage: tuple[str, ...]
    #: Per free parameter its std (SI units; the clock offset in ms).
    std: tuple[Named, ...] = named()
    two_stage: TwoStageStart | None = None
    #: The robust loss, in words.
    loss: str = ""
    joint_angles: JointAngles | None = optional()
    views_per_camera: tuple[Named, ...] = named()
    line_delay: tuple[LineDelay, ...] | None = optional()
    rolling_shutter_test: tuple[ShutterTest, ...] | None = optional()
    lens_test: LensTest | None = optional()
    intrinsics_test: IntrinsicsTest | None = optional()
    error_correlation: ErrorCorrelation | None = optional()


@dataclass(frozen=True, eq=False)
class ClockEstimate(Record):
    """The refined clock offset and its std (s)."""

    offset_s: float
    std_s: float


@dataclass(frozen=True, eq=False)
class RefinedIntrinsics(Record):
    """The first camera's intrinsics refined with the robot: K, distortion, the std of
    each freed coefficient and the coefficients held."""

    K: np.ndarray
    distortion: np.ndarray
    std: tuple[Named, ...] = named()
    held: tuple[str, ...] = ()


@dataclass(frozen=True, eq=False)
class OtherCamera(Record):
    """A further fixed camera refined with the robot: its pose with std, views, start and intrinsics."""

    camera: str
    T_cam_base: np.ndarray
    #: 1-sigma twist (m, rad).
    std_cam: np.ndarray
    views: int
    T_cam_base_start: np.ndarray
    K: np.ndarray
    distortion: np.ndarray


@dataclass(frozen=True, eq=False)
class ResidualStats(Record):
    """Mean, RMS and max of a set of distances (mm)."""

    mean: float
    rms: float
    max: float


@dataclass(frozen=True, eq=False)
class PointOutlier(Record):
    """A stop-and-shoot sample the robust point fit rejected: the sample (its index and its
    line in the samples file), its distance from the calibrated model's point (mm), and its
    deletion residual in robust sigmas (the 2-D radius of the same tail probability;
    `jaxcal._pointfit.sample_radii`)."""

    sample: int
    line: str
    distance_mm: float
    radius: float


@dataclass(frozen=True, eq=False)
class RepeatedPose(Record):
    """A stop-and-shoot sample whose joint positions repeat an earlier sample's (`of_sample`):
    merged into that pose, whose point is the mean of its samples, weighted as one pose."""

    sample: int
    line: str
    of_sample: int


@dataclass(frozen=True, eq=False)
class ResultFile:
    """The typed blocks of a `result.json`, read back (`jaxcal.io.result.read_result`)."""

    #: `ok`, `suspect` or `failed`, and why.
    status: str
    reasons: tuple[str, ...]
    ratios: tuple[RatioRow, ...]
    parameters: tuple[ParameterRow, ...]
    frozen: tuple[str, ...]
    arcs: tuple[ArcRow, ...]
    frames: FrameCounts
    clock: Clock
    intrinsics: Intrinsics
    solver: SolverInfo
    refinement: RefinementSummary | None
    validation: ValidationReport | None
    warnings: tuple[str, ...]
    #: Seconds per step: free-form.
    timings: dict[str, float]
    #: The non-geometric terms tried, kept and estimated (None when none was tried).
    terms: TermsSummary | None = None


@dataclass(frozen=True, eq=False)
class PoseFigures(Record):
    """A pose as `result.json` gives it: the matrix, translation, quaternion and 1-sigma std."""

    matrix: np.ndarray
    xyz_m: np.ndarray
    quaternion_xyzw: np.ndarray
    std_xyz_mm: np.ndarray
    std_rot_deg: np.ndarray
