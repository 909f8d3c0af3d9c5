"""Stage 1, setup: the dataset, the nominal robot, the capture kind, the
cameras and targets the fits use, and the options, resolved once."""

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .._kinematics import KinematicModel
from .._links import arm_targets
from .._robust import LOSSES
from ..errors import CalibrationError
from ..fleet_prior import FleetPrior
from ..io.dataset import CameraInfo, Dataset, DeviceInfo, TargetInfo, load_dataset
from .kinds import CaptureKind, device_poses, single_joint_share
from .limits import Limits

#: `Options.clock`: estimate the clock offset where possible, always, or take the metadata's.
CLOCK_MODES = ("auto", "estimate", "given")


@dataclass(frozen=True)
class Options:
    """What the caller asked for (see `jaxcal.calibrate`)."""

    camera: str | None = None
    workers: int | None = None
    progress: bool = True
    clock: str = "auto"
    validate: bool = True
    refine: bool = True
    other_cameras: bool = True
    log: Callable[[str], None] | None = None
    refine_intrinsics: bool | None = None
    estimate_line_delay: bool = False
    limits: Limits = Limits()
    arc_loss: str | None = "cauchy"
    device_is_base: bool = False
    terms: tuple[str, ...] | str = "auto"
    cv_folds: int = 5
    identifiability_tol: float | None = None
    #: The fleet's prior on the robot's parameters (point fits only).
    prior: FleetPrior | None = None

    def say(self, text: str) -> None:
        if self.log is not None:
            self.log(text)


@dataclass(frozen=True, eq=False)
class Setup:
    """A calibration problem, resolved.

    - `dataset`, `nominal`: the loaded dataset and its nominal robot.
    - `kind`: the `CaptureKind`.
    - `camera`: the camera of the two-stage fit (for tracker data the measuring
      device, `DeviceInfo`: the observations' source); `extra_cameras`: further
      fixed cameras the refinement adds.
    - `targets`: the targets the fits use, in mount order (eye-to-hand: those on
      the flange; eye-in-hand: the board's pattern named after the camera,
      riding on the flange, its mount $T_{flange,cam}$; markers on every
      link: every arm target, flange first).
    - `board`: eye-in-hand, the fixed board the camera films.
    - `target_link`, `per_joint`: markers on every link, each target's link
      index and per joint the targets whose poses give its arc.
    - `notes`: what the user should know about how the capture is used.
    - `identifiability_tol`: the identifiability search's independence threshold
      (`Options.identifiability_tol`, else the kind's, `CaptureKind.identifiability_tol`).
    """

    dataset: Dataset
    nominal: KinematicModel
    kind: CaptureKind
    camera: CameraInfo | DeviceInfo
    targets: tuple[TargetInfo, ...]
    board: TargetInfo | None
    target_link: np.ndarray | None
    per_joint: tuple | None
    extra_cameras: tuple[CameraInfo, ...]
    notes: tuple[str, ...]
    #: Seconds per step: free-form.
    timings: dict[str, float]
    identifiability_tol: float

    @property
    def root(self):
        return self.dataset.root

    @property
    def metadata_path(self):
        return self.dataset.root / "metadata.json"

    @property
    def fit_targets(self) -> tuple[TargetInfo, ...]:
        """The targets of the axis fit: with markers on every link each arc has
        its own marker, so the axis fit uses the lines and the flange marker's
        mount only (the refinement sees them all)."""
        return self.targets[:1] if self.kind.sequential else self.targets


def _choose_camera(ds: Dataset, name: str | None, flange: str) -> CameraInfo:
    fixed = [c for c in ds.cameras if c.mount == "world"]
    on_hand = [c for c in ds.cameras if c.mount == flange]
    if name is None:
        if not fixed and not on_hand:
            raise CalibrationError(
                f"{ds.root / 'metadata.json'}: no camera is fixed (mount 'world') or on the flange link "
                f"{flange!r} (mounts: {sorted({c.mount for c in ds.cameras})})"
            )
        return fixed[0] if fixed else on_hand[0]
    try:
        cam = ds.camera(name)
    except KeyError:
        raise CalibrationError(
            f"camera {name!r} is not in {ds.root / 'metadata.json'} (cameras: {[c.name for c in ds.cameras]})"
        ) from None
    if cam.mount not in ("world", flange):
        raise CalibrationError(
            f"camera {name!r} rides on {cam.mount!r}; the joint-sweep method needs a fixed camera or "
            f"one on the flange link {flange!r}"
        )
    return cam


def _flange_targets(ds: Dataset, flange: str) -> tuple[TargetInfo, ...]:
    targets = tuple(t for t in ds.targets if t.link == flange)
    if not targets:
        links = sorted({t.link for t in ds.targets})
        raise CalibrationError(
            f"{ds.root / 'metadata.json'}: no target rides on the flange link {flange!r} (targets are on "
            f"{links}); the joint-sweep method films a target on the flange"
        )
    return targets


def _eye_in_hand_target(ds: Dataset, camera: CameraInfo, flange: str) -> tuple[TargetInfo, TargetInfo]:
    """The fixed board an eye-in-hand `camera` films, and the pseudo-target of
    the fits: the board's pattern, named after the camera, riding on the
    flange (its "mount" is $T_{flange,cam}$, found by the fits)."""
    boards = [t for t in ds.targets if t.link == "world"]
    if not boards:
        raise CalibrationError(
            f"{ds.root / 'metadata.json'}: camera {camera.name!r} rides on the flange {flange!r} but no target is "
            f"fixed in the world (link 'world'); targets are on {sorted({t.link for t in ds.targets})}"
        )
    board = boards[0]
    return board, TargetInfo(dataclasses.replace(board.spec, name=camera.name), flange, None)


#: Why tracker data stop at the two-stage fit (a note in the result).
TWO_STAGE_IS_FINAL = (
    "tracker data: no corners to reproject, so the two-stage fit is the result. For single-joint sweeps it "
    "is, to first order, the maximum-likelihood point fit: each sweep's arc parameters (axis line, rate, zero "
    "position) summarise its samples, and the axis fit weighs them by their covariance; a refinement over "
    "every sample with the full forward kinematics would fit the same model to the same information"
)


def device_kind(ds: Dataset, device_is_base: bool = False) -> CaptureKind:
    """The capture kind of a tracker dataset: single-joint sweeps, or stop-and-shoot poses
    (`kinds.device_poses`)."""
    s = ds.samples
    return CaptureKind.of(
        camera_on_flange=False,
        segments=ds.segments,
        encoders=ds.encoder_t is not None or s.q is not None,
        link_targets=False,
        device=True,
        device_is_base=device_is_base,
        device_poses=device_poses(
            ds.segments, s.has_joint, single_joint_share(s.q), int(np.count_nonzero(s.joint < 0))
        ),
    )


def _device_setup(ds: Dataset, nominal: KinematicModel, options: Options, t0: float) -> Setup:
    """A tracker dataset: the device in the camera's role, its point in the target's."""
    flange = nominal.link_names[-1]
    point = ds.point
    if point.link != flange:
        raise CalibrationError(
            f"{ds.root / 'metadata.json'}: device.link is {point.link!r}; the joint-sweep method measures a "
            f"point on the flange link {flange!r}"
        )
    kind = device_kind(ds, options.device_is_base)
    if options.prior is not None and not kind.fits_points:
        raise CalibrationError(
            f"{ds.root}: a fleet's prior (--prior) applies to stop-and-shoot poses; these samples are joint "
            "sweeps (the arc fits take them)"
        )
    if kind.fits_points and ds.samples.q is None:
        raise CalibrationError(
            f"{ds.root / ds.device.file}: stop-and-shoot samples (no 'joint' cell names a sweeping joint"
            + (", every motion segment has joint null" if ds.segments else "")
            + ") need the joint positions of every sample: add a column per robot.joints entry"
        )
    notes = [TWO_STAGE_IS_FINAL] if options.refine and not kind.fits_points else []
    if options.device_is_base:
        notes.append(
            f"device_is_base: the frame of {ds.device.name!r} is the robot's base frame (T_device_base = identity, "
            "not estimated): the base height d1 and joint 1's origin become identifiable"
        )
    return Setup(
        dataset=ds,
        nominal=nominal,
        kind=kind,
        camera=ds.device,
        targets=(point,),
        board=None,
        target_link=None,
        per_joint=None,
        extra_cameras=(),
        notes=tuple(notes),
        timings={"load_s": time.perf_counter() - t0},
        identifiability_tol=_tolerance(options, kind),
    )


def _line_delay_estimated(camera: CameraInfo) -> CameraInfo:
    """`Options.estimate_line_delay`: a camera whose line delay the metadata leaves null is
    taken for a rolling shutter whose delay the refinement estimates."""
    if camera.line_delay_s is None and not camera.estimate_line_delay:
        return dataclasses.replace(camera, estimate_line_delay=True)
    return camera


def _tolerance(options: Options, kind: CaptureKind) -> float:
    """The identifiability search's threshold: the caller's, else the capture kind's."""
    return kind.identifiability_tol if options.identifiability_tol is None else options.identifiability_tol


def _refuse_tracker_options(ds: Dataset, options: Options) -> None:
    """The options of measured points, refused for a dataset filmed by cameras."""
    if options.device_is_base:
        raise CalibrationError(
            f"{ds.root / 'metadata.json'}: device_is_base applies to tracker data (a 'device' in the metadata); "
            "this dataset is filmed by cameras, whose pose is estimated"
        )
    if options.prior is not None:
        raise CalibrationError(
            f"{ds.root}: a fleet's prior (--prior) applies to measured points (a tracker, motion capture, "
            "the controller's tool point) at stop-and-shoot poses, not to camera captures"
        )


def setup(dataset, options: Options) -> Setup:
    """Load `dataset` (a path or a `Dataset`) and resolve the capture kind,
    the camera, the targets and the further cameras (see `Setup`)."""
    t0 = time.perf_counter()
    if options.arc_loss not in LOSSES:
        raise CalibrationError(f"arc_loss must be one of {LOSSES}, got {options.arc_loss!r}")
    tol = options.identifiability_tol
    if tol is not None and not 0.0 < tol < 1.0:
        raise CalibrationError(
            f"identifiability_tol must be in (0, 1) (a column's distance from the span of those kept "
            f"before it, columns normalised), got {tol!r}"
        )
    ds = dataset if isinstance(dataset, Dataset) else load_dataset(dataset)
    nominal = ds.load_model()
    if tuple(nominal.joint_names) != tuple(ds.joint_names):
        raise CalibrationError(
            f"{ds.root / 'metadata.json'}: robot.joints {list(ds.joint_names)} differ from the chain in "
            f"{ds.robot_urdf} ({list(nominal.joint_names)})"
        )
    if ds.device is not None:
        return _device_setup(ds, nominal, options, t0)
    _refuse_tracker_options(ds, options)
    flange = nominal.link_names[-1]
    cam = _choose_camera(ds, options.camera, flange)
    link_targets = any(t.link not in (flange, "world") for t in ds.targets)
    kind = CaptureKind.of(
        camera_on_flange=cam.mount == flange,
        segments=ds.segments,
        encoders=ds.encoder_t is not None,
        link_targets=link_targets,
    )
    notes = []
    board = target_link = per_joint = None
    extra: list[CameraInfo] = []
    if kind.unsupported:
        raise CalibrationError(f"{ds.root}: {kind.unsupported}")
    if not kind.has_arcs:
        notes.append(
            "pose-based capture (arbitrary motion, no plate on the links): the refinement starts from the nominal "
            "robot and a closed-form hand-eye estimate of the camera and the mount"
        )
    if kind.fixed_board:
        board, target = _eye_in_hand_target(ds, cam, flange)
        targets = (target,)
        others = [t.name for t in ds.targets if t.name != board.name]
        if others:
            notes.append(f"eye-in-hand: board {board.name!r} is the reference; not used: {others}")
    elif kind.sequential:
        try:
            arm, target_link, per_joint = arm_targets(ds, nominal)
        except ValueError as e:
            raise CalibrationError(f"{ds.root / 'metadata.json'}: {e}") from None
        targets, per_joint = tuple(arm), tuple(per_joint)
        notes.append(
            "arbitrary motion, markers on every link: sequential initialisation (each joint's axis from its "
            "child link's marker, the earlier joints undone with their encoders), then the refinement over all "
            "markers"
        )
    else:
        targets = _flange_targets(ds, flange)
        if options.refine and options.other_cameras:
            extra = [c for c in ds.cameras if c.mount == "world" and c.name != cam.name]
    if len(ds.cameras) > 1:
        notes.append(
            f"two-stage fit from camera {cam.name!r}; "
            + (
                f"the refinement adds {[c.name for c in extra]}"
                if extra
                else "the other cameras are not used (other_cameras=False, or none is fixed)"
            )
        )
    ignored = [t.name for t in ds.targets if t.link != flange]
    if ignored and kind.flange_targets_only:
        notes.append(f"targets not on the flange are not used by the two-stage method: {ignored}")
    if extra and not kind.refines_other_cameras:
        notes.append(
            f"no encoder log: the refinement uses camera {cam.name!r} only (not {[c.name for c in extra]})"
        )
        extra = []
    if options.estimate_line_delay:
        cam, extra = _line_delay_estimated(cam), [_line_delay_estimated(c) for c in extra]
    return Setup(
        dataset=ds,
        nominal=nominal,
        kind=kind,
        camera=cam,
        targets=targets,
        board=board,
        target_link=target_link,
        per_joint=per_joint,
        extra_cameras=tuple(extra),
        notes=tuple(notes),
        timings={"load_s": time.perf_counter() - t0},
        identifiability_tol=_tolerance(options, kind),
    )
