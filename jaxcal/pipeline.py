"""From a dataset on disk to a calibrated robot: `jaxcal.calibrate(dataset)`.

A short orchestrator over the stages of `jaxcal.stages` (see
`docs/architecture.md`): setup (the dataset, the capture kind, cameras and
targets) -> observe (intrinsics, detection, PnP with covariance) ->
synchronise (clock offset, frames on the controller clock, sweeps) ->
two-stage (arc fits, axis fit) -> refine (every corner; not for a measuring
device's samples) -> validate
(synthetic datasets) -> the result. The command line (`jaxcal calibrate`,
`jaxcal demo`) and the Python API share this one code path.
"""

import dataclasses
import time

from . import stages
from ._cache import enable_compilation_cache
from ._exported import warm_start
from ._progress import watchdog
from .errors import CalibrationError as CalibrationError  # re-exported
from .errors import SuspectResultError
from .fleet_prior import as_prior, check_not_a_unit
from .io._files import resolved
from .io.dataset import Dataset
from .stages import CalibrationResult as CalibrationResult  # re-exported
from .stages import Limits


def calibrate(
    dataset,
    *,
    camera: str | None = None,
    workers: int | None = None,
    progress: bool = True,
    clock: str = "auto",
    validate: bool = True,
    refine: bool = True,
    other_cameras: bool = True,
    refine_intrinsics: bool | None = None,
    estimate_line_delay: bool = False,
    limits: Limits | None = None,
    arc_loss: str | None = "cauchy",
    device_is_base: bool = False,
    terms: tuple[str, ...] | str = "auto",
    cv_folds: int = 5,
    identifiability_tol: float | None = None,
    prior=None,
    strict: bool = False,
    log=None,
) -> CalibrationResult:
    """Calibrate the robot and camera of `dataset` (a path or a loaded `Dataset`).

    **Arguments:**
    - `camera`: which fixed camera the two-stage fit uses (default the first
      one mounted in the world, else the one on the flange). The refinement
      adds every other fixed camera (`other_cameras=False`: only this one):
      one robot model, one `T_cam_base` per camera, all cameras on the
      dataset's one clock.
    - `workers`: threads for detection (default all cores).
    - `clock`: the camera-controller clock offset. `"auto"` (default):
      estimated whenever there is an encoder log and moving joints, a
      metadata offset that disagrees is a warning, otherwise the metadata's;
      `"estimate"`: estimated, an error when it cannot be; `"given"`: the
      metadata's offset as it is (estimated only when the metadata has none).
    - `refine_intrinsics`: free the first camera's intrinsics in the
      refinement (focal lengths, principal point and the distortion the data
      support; default: when they were self-calibrated because the metadata
      has no `K`).
    - `estimate_line_delay`: take every camera whose `line_delay_s` the
      metadata leaves null for a rolling shutter and estimate its line delay in
      the refinement (as `line_delay_s: "estimate"` does for one camera).
    - `validate`: with a synthetic dataset's `truth.json`, add the validation block.
    - `refine`: after the two-stage fit, minimise the reprojection error of
      every detected corner over all parameters (`jaxcal._refine`); `False`
      stops at the two-stage result.
    - `arc_loss`: the robust loss of the arc fits and the clock fit
      (`"cauchy"`, `"huber"` or `None` for plain least squares): samples far
      off their arc are down-weighted, then rejected and named in the result
      (`arcs[j]["outliers"]`) before the inlier solve that gives the std.
    - `device_is_base`: tracker data only (a `device` in the metadata): the
      device frame is the robot's base frame (the controller's own logged
      tool point, or a tracker registered to the base), so `T_device_base`
      is the identity and not estimated; the base height d1 and joint 1's
      origin become identifiable. Without it `T_device_base` is estimated
      (it takes `T_cam_base`'s place) and they are held at nominal.
    - `terms`: non-geometric joint terms to try after the geometric fit, the same
      names for every capture (`jaxcal._terms`): `"compliance"` (each joint yields
      under the gravity torque of the links it carries, from the robot file's masses
      plus the metadata's `robot.payload`), `"backlash"` (lost motion: the link lags
      its motor's last motion, or rests against the flank gravity preloads it to),
      `"harmonic1"`, `"harmonic2"` (a joint's once- and twice-per-turn transmission
      error). Each is kept only when `cv_folds`-fold cross-validation improves: on a
      camera capture the reprojection error of views left out in blocks of
      consecutive frames, on stop-and-shoot tracker data the samples' distances.
      `"auto"` (default): the capture kind's (`CaptureKind.default_terms`:
      compliance and backlash for camera captures with an encoder log, none for
      tracker data); `()`: none (the rigid arm).
    - `cv_folds`: folds of that cross-validation (also reported for the
      geometric model; 0 skips it, and then no term can be kept).
    - `identifiability_tol`: the identifiability search's threshold, in (0, 1): a
      parameter is freed only when its (normalised) Jacobian column lies farther
      than this from the span of those freed before it, in the search's order;
      larger holds more. Default: the capture kind's (1e-6 for single-joint sweeps
      with encoders, 1e-3 otherwise). Whatever it is, a stop-and-shoot parameter
      the samples cannot see (alone it would be known no better than a third of its
      plausible correction, `limits`) is held and named.
    - `prior`: a fleet's `fleet.json` (its folder, or a `jaxcal.fleet.FleetPrior`): a Gaussian
      prior of a stop-and-shoot point fit on the robot's parameters (`jaxcal.fleet`).
    - `limits`: the plausibility checks' limits (`jaxcal.stages.Limits`); a
      result that fails one has `status == "suspect"` and its `reasons`.
    - `strict`: raise `SuspectResultError` instead of returning a suspect or failed result.
    - `log`: a callable taking one line of progress text (default silent).

    Compiled solvers are kept (`jaxcal._cache`): a second call on data of the same shapes
    skips compilation.

    **Returns:** a `CalibrationResult`. Raises a `jaxcal.JaxcalError`
    (`CalibrationError`, `DatasetError`, `VisionError`; all `ValueError`)
    naming the problem.
    """
    if clock not in stages.CLOCK_MODES:
        raise ValueError(f"clock must be one of {', '.join(map(repr, stages.CLOCK_MODES))}, got {clock!r}")
    enable_compilation_cache()
    t_start = time.perf_counter()
    options = stages.Options(
        camera=camera,
        workers=workers,
        progress=progress,
        clock=clock,
        validate=validate,
        refine=refine,
        other_cameras=other_cameras,
        log=log,
        refine_intrinsics=refine_intrinsics,
        estimate_line_delay=estimate_line_delay,
        limits=stages.Limits() if limits is None else limits,
        arc_loss=arc_loss,
        device_is_base=device_is_base,
        terms=terms if isinstance(terms, str) else tuple(terms),
        cv_folds=int(cv_folds),
        identifiability_tol=identifiability_tol,
        prior=as_prior(prior),
    )
    # The programs the last calibration of this dataset called are read while it loads and detects.
    root = dataset.root if isinstance(dataset, Dataset) else dataset  # a Path's own `.root` is "/"
    check_not_a_unit(options.prior, root)
    with warm_start(f"calibrate {resolved(root)}"), watchdog(log) as beat:
        return _stages(dataset, dataclasses.replace(options, log=beat.log), strict, t_start, beat.stage)


def _stages(dataset, options, strict: bool, t_start: float, at=lambda stage: None) -> CalibrationResult:
    """The stages in order; `at(name)` names each as it starts (`jaxcal._progress.watchdog`)."""
    at("reading the dataset")
    setup = stages.setup(dataset, options)
    at("detecting the targets" if setup.kind.images else "reading the samples")
    obs = stages.observe(setup, options)
    at("the clock offset")
    sync = stages.synchronise(setup, obs, options)
    at("the two-stage fit" if setup.kind.has_arcs else "the point fit")
    two = stages.two_stage(setup, obs, sync, options)
    # The verdict's arm-rigidity test: its terms need only the two-stage fit; their program compiles
    # now beside the refinement's and runs after it (`stages.start_arm_score`).
    arm_score = stages.start_arm_score(setup, sync, two) if setup.kind.has_arcs else None
    # Tracker data have no corners: the two-stage fit is the result (see `stages.TWO_STAGE_IS_FINAL`).
    at("the refinement")
    refined = (
        stages.refine(setup, obs, sync, two, options)
        if options.refine and setup.kind.refines_corners
        else None
    )
    if refined is not None and refined.terms is not None and refined.terms.kept and setup.kind.has_arcs:
        # The non-geometric terms the refinement kept correct the encoder log: the clock fit, the arcs and
        # the axes again on where the joints stood, so that the verdict tests what the terms leave.
        at("the clock offset and the two-stage fit again, with the terms")
        sync = stages.synchronise(setup, obs, options, refined.terms)
        two = stages.two_stage(setup, obs, sync, options)
        arm_score = stages.start_arm_score(setup, sync, two)
    # The arm test's last part: the arcs fitted again at the refinement's clock.
    if arm_score is not None:
        at("the arm's rigidity test")
        arm_score = stages.finish_arm_score(setup, sync, two, refined, arm_score)
    # The validation against the truth needs no verdict (`stages.run_ahead`: inline, see its docstring).
    at("the validation against truth.json")
    validation = (
        stages.run_ahead("validation", stages.validate, setup, sync, two, refined, options)
        if options.validate and setup.dataset.truth is not None
        else None
    )
    at("the verdict")
    verdict = stages.verdict(setup, obs, sync, two, refined, options.limits, arm_score)
    if strict and verdict.status != "ok":
        raise SuspectResultError(
            f"{setup.root}: the calibration is {verdict.status}: " + "; ".join(verdict.reasons)
        )
    at("the result")
    validation = None if validation is None else validation.result()
    return stages.assemble(setup, obs, sync, two, refined, verdict, validation, t_start)
