"""The hand-eye product's pipeline: `calibrate_hand_eye_capture` calls the steps in order and
assembles their records into a `HandEyeRun`; `jaxcal.io.handeye_results` writes its outputs."""

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from .._cache import enable_compilation_cache
from .._exported import warm_start
from .._handeye import HandEyeResult, HandEyeVerdict, KFoldSpread, pose_difference
from .._progress import working
from ..io._files import resolved
from ..io.handeye import HandEyeCapture, true_T_robot_cam
from ..records import Intrinsics
from ..vision import HandEyeObservations
from ._noise import NoiseChoice, robot_noise_setting
from ._observe import observe
from ._solve import solve
from ._verdict import judge


@dataclass(frozen=True, eq=False)
class HandEyeRun:
    """A capture's hand-eye calibration and everything said about it.

    - `capture`, `intrinsics` (per camera, `jaxcal.records.Intrinsics`), `detected` `(cameras, frames)`.
    - `observations`: what `hand_eye_from_detections` built (padded data, PnP poses, checks).
    - `result`: the `HandEyeResult` of the robot-noise model kept (NumPy leaves; padded frames beyond
      `observations.frames`); `kfold`: its k-fold spread (with the held-out reprojection) or None.
    - `noise`: the robot-noise models solved, their held-out reprojection and the one kept.
    - `verdict`: status (`"ok"` / `"suspect"`), reasons and notes.
    - `rejected`: `{frame index: reason}` of the frames the solve rejected.
    - `truth_error`: synthetic captures: per camera the error of
      `T_robot_cam` against the truth, `(translation m, rotation rad)`, else None.
    - `seconds`: wall time per step.
    - `checks`: per camera name, the images' scale against the robot's and the lens test
      (`jaxcal.handeye._verdict.input_hints`).
    """

    capture: HandEyeCapture
    intrinsics: tuple[Intrinsics, ...]
    detected: np.ndarray
    observations: HandEyeObservations
    result: HandEyeResult
    kfold: "KFoldSpread | None"
    verdict: HandEyeVerdict
    rejected: dict[int, str]
    truth_error: "np.ndarray | None"
    max_steps: int
    noise: NoiseChoice
    seconds: dict[str, float] = field(default_factory=dict)
    checks: dict[str, dict] = field(default_factory=dict)

    @property
    def frames(self) -> int:
        return self.observations.frames

    @property
    def T_robot_cam(self) -> np.ndarray:
        """`(cameras, 4, 4)`: each camera's pose on the robot: `T_ee_cam` (eye-in-hand) or `T_base_cam`."""
        return np.asarray(self.result.T_robot_cam)

    @property
    def exit_code(self) -> int:
        """0 when ok, 3 when suspect (the `jaxcal handeye` exit code)."""
        return 0 if self.verdict.ok else 3


def truth_error(capture: HandEyeCapture, result) -> "np.ndarray | None":
    """Synthetic captures: per camera `(translation m, rotation rad)` of `T_robot_cam` against the truth."""
    true = true_T_robot_cam(capture)
    if true is None:
        return None
    X = np.stack([true[c.name] for c in capture.cameras])
    e = pose_difference(np.asarray(result.T_robot_cam), X)
    return np.stack([np.linalg.norm(e[:, :3], axis=1), np.linalg.norm(e[:, 3:], axis=1)], axis=1)


def calibrate_hand_eye_capture(
    capture,
    *,
    robot_noise: str | None = None,
    robot_sigma_translation: float | None = None,
    robot_sigma_rotation: float | None = None,
    estimate_robot_noise: bool | None = None,
    sigma_px: float | None = None,
    folds: int = 10,
    max_steps: int = 200,
    workers: int | None = None,
    progress: bool = False,
    log: Callable[[str], None] = lambda text: None,
) -> HandEyeRun:
    """Hand-eye calibration of a capture on disk; impure (files, OpenCV). What `jaxcal handeye` runs:

    ```
    observe (load, detect, intrinsics, PnP and input checks) -> solve (and k-fold) -> judge -> HandEyeRun
    ```

    **Arguments:**
    - `capture`: a capture directory (`jaxcal.io.handeye` format) or a loaded `HandEyeCapture`.
    - `robot_noise`: the model of the robot's reported poses (`jaxcal.handeye._noise`): `"exact"`
      (no corrections), `"estimate"` (a correction per pose, the noise estimated from the data,
      `calibrate_hand_eye`'s `estimate_robot_noise`), `"given"` (a correction per pose with the
      prior `robot_sigma_translation` (m), `robot_sigma_rotation` (rad) per axis), each used exactly
      as asked; or `"auto"`: the one of them that predicts frames left out best (the estimate unless
      another is better by `jaxcal._selection`'s rule; needs `folds`, else the estimate). None: `"given"`
      when the sigmas are given, else `"auto"`.
    - `estimate_robot_noise`: the previous release's switch, kept: True `"estimate"`, False `"exact"`
      (`"given"` with the sigmas).
    - `sigma_px`: the detector's pixel noise; None: estimated from PnP's residuals.
    - `folds`: k of the k-fold spread and of the held-out comparison (0: skip them).
    - `max_steps`: Levenberg-Marquardt steps per stage.
    - `workers`, `progress`: marker detection (see `jaxcal.vision.detect_frames`).
    - `log`: called with progress messages.

    **Returns:** a `HandEyeRun` (`jaxcal.write_hand_eye_outputs` writes it).

    **Raises:** `ValueError` (robot-noise arguments that disagree), `DatasetError` (the capture), `VisionError` (images, intrinsics),
    `HandEyeInputError` (too few views, degenerate motion, robot poses that do
    not match the images), `CalibrationError` (no view of the target at all).
    """
    noise = robot_noise_setting(
        robot_noise, robot_sigma_translation, robot_sigma_rotation, estimate_robot_noise
    )
    enable_compilation_cache()
    # The solver the last run on this capture called is read while this one loads and detects.
    with warm_start(f"handeye {resolved(getattr(capture, 'root', capture))}"):
        observed = observe(
            capture,
            noise=noise,
            sigma_px=sigma_px,
            workers=workers,
            progress=progress,
            log=log,
        )
        log("solving (the first run on a capture of this size compiles its programs) ...")
        with working(progress, "solving", say=log):
            solved = solve(observed, folds=folds, max_steps=max_steps, log=log)
        verdict, hint_seconds, checks = judge(observed, solved, max_steps=max_steps, log=log)
    return HandEyeRun(
        capture=observed.capture,
        intrinsics=observed.intrinsics,
        detected=observed.detected,
        observations=observed.observations,
        result=solved.result,
        kfold=solved.kfold,
        verdict=verdict,
        rejected=solved.rejected,
        truth_error=truth_error(observed.capture, solved.result),
        max_steps=max_steps,
        noise=solved.noise,
        seconds={**observed.seconds, **solved.seconds, **hint_seconds},
        checks=checks,
    )
