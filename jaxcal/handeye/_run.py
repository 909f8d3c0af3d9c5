"""Hand-eye calibration of a capture on disk: detection, intrinsics, checks, solve, k-fold, verdict.

`calibrate_hand_eye_capture(path)` is what `jaxcal handeye DATASET` runs. The
stages hand records down: `load_hand_eye_capture` -> `detect_frames` per
camera -> `calibrate_intrinsics` where K is unknown ->
`hand_eye_from_detections` (PnP, symmetric targets resolved, distortion
removed, padded to a bucket, and the robot-versus-camera rotation-angle check
that refuses mismatched data before any solve) -> `calibrate_hand_eye` (one
compiled program per bucket, kept across calls and, through the persistent
compilation cache, across processes) -> `kfold_spread` -> `assess_hand_eye`.
"""

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import lru_cache
from pathlib import Path

import jax
import numpy as np

from ._cache import enable_compilation_cache
from ._exported import stored_jit, warm_start
from ._handeye import (
    ROBOT_SIGMA_OPTIONS,
    ROBOT_SIGMA_START,
    HandEyeResult,
    HandEyeVerdict,
    KFoldSpread,
    assess_hand_eye,
    calibrate_hand_eye,
    describe_robot_noise,
    implausible_robot_noise,
    kfold_spread,
    pose_difference,
    robot_correction_rms,
    robot_noise,
)
from ._handeye.solve import HAND_EYE_OPTIONS
from ._npgeom import matrix_to_quaternion, quaternion_to_matrix
from .errors import CalibrationError, HandEyeInputError
from .io.handeye import HandEyeCapture, load_hand_eye_capture
from .vision import HandEyeObservations, calibrate_intrinsics, detect_frames, hand_eye_from_detections

#: Outlier threshold of `calibrate_hand_eye` (times the median group RMS); reported with rejections.
OUTLIER_THRESHOLD = 3.0


@lru_cache(maxsize=4)
def hand_eye_solver(max_steps: int = 200) -> Callable:
    """`jax.jit(calibrate_hand_eye)` at `max_steps` as `solve(data, reject_outliers, estimate_robot_noise)`,
    one per value (shapes are bucketed by the caller; both flags are traced, so every setting shares
    the program of its data: with noisy robot poses, estimated or given, one program)."""

    def hand_eye(data, reject, estimate):
        return calibrate_hand_eye(
            data,
            reject_outliers=reject,
            estimate_robot_noise=estimate,
            options=replace(HAND_EYE_OPTIONS, max_steps=max_steps),
            outlier_threshold=OUTLIER_THRESHOLD,
        )

    # Runs many times per process (k-fold, bootstrap): XLA's optimisations pay for themselves.
    return stored_jit(hand_eye, "hand_eye", (max_steps, OUTLIER_THRESHOLD), compiler_options=None)


@dataclass(frozen=True, eq=False)
class CameraIntrinsics:
    """`K` (3, 3) px and `dist` (OpenCV) of a camera; `source` `"given"` or
    `"self-calibrated"` (then `rms_px` is OpenCV's calibration RMS)."""

    K: np.ndarray
    dist: np.ndarray
    source: str
    rms_px: float | None = None


@dataclass(frozen=True, eq=False)
class HandEyeRun:
    """A capture's hand-eye calibration and everything said about it.

    - `capture`, `intrinsics` (per camera), `detected` `(cameras, frames)`.
    - `observations`: what `hand_eye_from_detections` built (padded data, PnP poses, checks).
    - `result`: the `HandEyeResult` (NumPy leaves; padded frames beyond
      `observations.frames`); `kfold`: the k-fold spread or None.
    - `verdict`: status (`"ok"` / `"suspect"`), reasons and notes.
    - `rejected`: `{frame index: reason}` of the frames the solve rejected.
    - `truth_error`: synthetic captures: per camera the error of
      `T_robot_cam` against the truth, `(translation m, rotation rad)`, else None.
    - `seconds`: wall time per stage.
    """

    capture: HandEyeCapture
    intrinsics: tuple[CameraIntrinsics, ...]
    detected: np.ndarray
    observations: HandEyeObservations
    result: HandEyeResult
    kfold: "KFoldSpread | None"
    verdict: HandEyeVerdict
    rejected: dict
    truth_error: "np.ndarray | None"
    max_steps: int
    seconds: dict = field(default_factory=dict)

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


def _intrinsics(capture, detections, log) -> tuple[CameraIntrinsics, ...]:
    out = []
    for cam, dets in zip(capture.cameras, detections):
        if cam.K is not None:
            out.append(CameraIntrinsics(np.asarray(cam.K), np.asarray(cam.dist), "given"))
            continue
        views = [d.get(capture.target.name) for d in dets]
        K, dist, rms = calibrate_intrinsics(views, capture.target, (cam.width, cam.height))
        log(
            f"camera {cam.name}: intrinsics self-calibrated from {sum(v is not None for v in views)} views ({rms:.3f} px RMS)"
        )
        out.append(CameraIntrinsics(K, dist, "self-calibrated", float(rms)))
    return tuple(out)


def _distortions(dists) -> np.ndarray:
    """Every camera's OpenCV coefficients zero-padded to the longest, `(cameras, n)`."""
    n = max(len(d) for d in dists)
    return np.stack([np.pad(np.asarray(d, np.float64), (0, n - len(d))) for d in dists])


def _rejection_reasons(result, observations, threshold: float) -> dict:
    """`{frame: reason}` for every rejected frame, from the final per-view RMS."""
    rejected = np.asarray(result.rejected)
    rms = np.asarray(result.group_rms) * observations.sigma_px
    kept = np.where(rejected, np.nan, rms)
    median = float(np.nanmedian(kept)) if np.isfinite(kept).any() else float("nan")
    out = {}
    for f in np.flatnonzero(rejected.any(0)):
        cams = np.flatnonzero(rejected[:, f])
        worst = float(np.nanmax(rms[cams, f]))
        out[int(f)] = (
            f"reprojection RMS {worst:.3g} px against a median of {median:.3g} px over the kept views "
            f"(rejected above {threshold:g}x the median); its robot pose does not fit the others"
        )
    return out


def _truth_error(capture, result) -> "np.ndarray | None":
    if not capture.truth or "T_robot_cam" not in capture.truth:
        return None
    X = np.stack([np.asarray(capture.truth["T_robot_cam"][c.name]) for c in capture.cameras])
    e = pose_difference(np.asarray(result.T_robot_cam), X)
    return np.stack([np.linalg.norm(e[:, :3], axis=1), np.linalg.norm(e[:, 3:], axis=1)], axis=1)


#: Whitened residual RMS above which the poses and images are taken not to fit (`assess_hand_eye`'s
#: `max_residual_ratio`) and `_diagnose_misfit` tries the common misreadings of the input.
MISFIT_RATIO = 3.0


def _misreadings(capture: HandEyeCapture) -> list[tuple[str, np.ndarray, bool]]:
    """The input mistakes that keep every relative rotation angle, so that the input check
    passes and only the fit can see them: `(what to fix, T_base_ee, eye_in_hand)` each."""
    T = np.asarray(capture.T_base_ee, np.float64)
    other = "eye_to_hand" if capture.eye_in_hand else "eye_in_hand"
    out = [
        (
            f"handeye.json field 'arrangement' is {other!r} (or the poses are inverted: poses.csv must hold "
            "the flange in the base frame, T_base_ee, not T_ee_base)",
            T,
            not capture.eye_in_hand,
        )
    ]
    if capture.pose_format == "xyz_quat":
        q = np.stack([matrix_to_quaternion(R) for R in T[:, :3, :3]])  # as read: x, y, z, w
        for shift, holds in ((-1, "w, x, y, z"), (1, "y, z, w, x")):
            R = quaternion_to_matrix(np.roll(q, shift, axis=-1))
            Ta = T.copy()
            Ta[:, :3, :3] = R
            out.append(
                (
                    f"the columns that poses.csv's header names qx, qy, qz, qw hold {holds} (label the "
                    "columns in the order the values are written)",
                    Ta,
                    capture.eye_in_hand,
                )
            )
    return out


def _misfit(result) -> bool:
    """The poses and images do not fit: the reprojection RMS is over `MISFIT_RATIO` times the
    detector's noise, the robot noise estimated to absorb it is beyond any robot's, or (robot
    noise given) the robot corrections are over `MISFIT_RATIO` times it."""
    given = result.robot_sigma is not None and not bool(np.all(np.asarray(result.robot_sigma_estimated)))
    return (
        float(result.residual_rms) > MISFIT_RATIO
        or implausible_robot_noise(result)
        or (given and robot_correction_rms(result) > MISFIT_RATIO)
    )


def _fits(result) -> bool:
    ratio = float(result.residual_rms)
    return np.isfinite(ratio) and ratio <= MISFIT_RATIO and not implausible_robot_noise(result)


def _diagnose_misfit(
    capture: HandEyeCapture, observe: Callable, result, solve: Callable, estimate: bool
) -> str | None:
    """When the poses and images do not fit one hand-eye transform, re-solve under each common
    misreading of the input (`_misreadings`; `observe(T_base_ee, eye_in_hand)` builds the data)
    and name the one that fits, if one does: an arrangement swapped or poses inverted, a
    quaternion's components in another order. Same compiled solver: the arrangement is data
    and the shapes are the bucket's."""
    given = float(result.residual_rms)
    for fix, T, eye_in_hand in _misreadings(capture):
        try:
            alt = observe(T, eye_in_hand)
        except HandEyeInputError:
            continue
        r = jax.tree.map(np.asarray, solve(alt.data, True, estimate))
        if _fits(r) and (float(r.residual_rms) < 0.1 * given or implausible_robot_noise(result)):
            noise = (
                f"; {describe_robot_noise(r)} that way against {describe_robot_noise(result)}"
                if estimate
                else ""
            )
            return (
                f"the data fit if {fix}: reprojection RMS {float(r.pixel_rms):.3g} px that way against "
                f"{float(result.pixel_rms):.3g} px as given{noise}"
            )
    return None


def _robot_noise_hint(verdict, data, result, solve, log) -> HandEyeVerdict:
    """With the robot noise given and a poor fit (a misfit, or frames rejected): re-solve with the
    noise estimated (the same compiled program) and, when that fits, say that the robot poses are
    noisier than given, by how much, and which options set it."""
    if result.robot_sigma is None or bool(np.all(np.asarray(result.robot_sigma_estimated))):
        return verdict
    rejected = int(np.asarray(result.rejected).any(0).sum())
    if not (_misfit(result) or rejected):
        return verdict
    r = jax.tree.map(np.asarray, solve(data, True, True))
    kept = int(np.asarray(r.rejected).any(0).sum())
    if not _fits(r) or (kept >= max(rejected, 1) and not _misfit(result)):
        return verdict
    given, est = robot_noise(result), robot_noise(r)
    if est[0] <= given[0] and est[1] <= given[1]:
        return verdict
    text = (
        f"the robot poses are noisier than given ({given[0]:.3g} mm / {given[1]:.3g} deg per axis): "
        f"estimated from the data, {est[0]:.3g} mm / {est[1]:.3g} deg, with which the reprojection RMS is "
        f"{float(r.pixel_rms):.3g} px ({float(result.pixel_rms):.3g} px as given) and {kept} frame(s) are "
        f"rejected ({rejected} as given); leave {ROBOT_SIGMA_OPTIONS} out to use the estimate"
    )
    log(text)
    if _misfit(result):
        return replace(verdict, reasons=verdict.reasons + (text,))
    return replace(verdict, notes=verdict.notes + (text,))


def _input_hints(verdict, capture, intrinsics, observe, data, result, solve, log) -> HandEyeVerdict:
    """The verdict with what the input itself explains: robot poses noisier than given
    (`_robot_noise_hint`), the misreading that fits when the poses and images do not
    (`_diagnose_misfit`), and intrinsics self-calibrated from the capture, which make any
    result suspect."""
    estimate = bool(np.all(np.asarray(result.robot_sigma_estimated)))
    verdict = _robot_noise_hint(verdict, data, result, solve, log)
    if _misfit(result):
        found = _diagnose_misfit(capture, observe, result, solve, estimate)
        if found:
            log(f"the poses fit the images once read differently: {found}")
            verdict = replace(verdict, reasons=verdict.reasons + (found,))
    guessed = [c.name for c, k in zip(capture.cameras, intrinsics) if k.source == "self-calibrated"]
    if guessed:
        # The solve, its standard deviations and the k-fold spread all hold K exact: a focal length
        # calibrated from the same few views moves the camera along its axis unseen (a rendered
        # 16-frame capture: 6.7-7.2 mm off with 0.1 mm std and k-fold spread). Not trustworthy as is.
        verdict = replace(
            verdict,
            status="suspect",
            reasons=verdict.reasons
            + (
                f"camera {', '.join(guessed)}: intrinsics self-calibrated from these images; the standard "
                "deviations and the k-fold spread hold K exact and leave out its error, which can dominate "
                "(a rendered 16-frame capture: 7 mm off against 0.1 mm std); give K from a separate intrinsics "
                "calibration",
            ),
        )
    return verdict


def _detect(capture: HandEyeCapture, workers, progress) -> list:
    """`detect_frames` of the capture's target, per camera (with its K and distortion where given)."""
    return [
        detect_frames(
            paths,
            [capture.target],
            K=cam.K,
            dist=cam.dist if cam.K is not None else None,
            workers=workers,
            progress=progress,
            pool="thread",
        )
        for cam, paths in zip(capture.cameras, capture.images)
    ]


def calibrate_hand_eye_capture(
    capture,
    *,
    robot_sigma_translation: float | None = None,
    robot_sigma_rotation: float | None = None,
    estimate_robot_noise: bool = True,
    sigma_px: float | None = None,
    folds: int = 10,
    max_steps: int = 200,
    workers: int | None = None,
    progress: bool = False,
    log: Callable[[str], None] = lambda text: None,
) -> HandEyeRun:
    """Hand-eye calibration of a capture (see the module docstring); impure (files, OpenCV).

    **Arguments:**
    - `capture`: a capture directory (`jaxcal.io.handeye` format) or a loaded `HandEyeCapture`.
    - `robot_sigma_translation` (m), `robot_sigma_rotation` (rad): robot pose
      noise (each pose then gets a correction with that prior), used as given;
      None (both): estimated from the data (`calibrate_hand_eye`'s
      `estimate_robot_noise`), or with `estimate_robot_noise=False` exact poses.
    - `sigma_px`: the detector's pixel noise; None: estimated from PnP's residuals.
    - `folds`: k of the k-fold spread (0: skip it).
    - `max_steps`: Levenberg-Marquardt steps per stage.
    - `workers`, `progress`: marker detection (see `jaxcal.vision.detect_frames`).
    - `log`: called with progress messages.

    **Returns:** a `HandEyeRun`.

    **Raises:** `DatasetError` (the capture), `VisionError` (images, intrinsics),
    `HandEyeInputError` (too few views, degenerate motion, robot poses that do
    not match the images), `CalibrationError` (no view of the target at all).
    """
    enable_compilation_cache()
    # The solver the last run on this capture called is read while this one loads and detects.
    with warm_start(f"handeye {Path(getattr(capture, 'root', capture)).resolve()}"):
        return _calibrate_capture(
            capture, robot_sigma_translation, robot_sigma_rotation, estimate_robot_noise, sigma_px, folds,
            max_steps, workers, progress, log,
        )  # fmt: skip


def _calibrate_capture(
    capture, robot_sigma_translation, robot_sigma_rotation, estimate_robot_noise, sigma_px, folds, max_steps,
    workers, progress, log,
) -> HandEyeRun:  # fmt: skip
    seconds = {}
    t0 = time.perf_counter()
    if not isinstance(capture, HandEyeCapture):
        capture = load_hand_eye_capture(capture)
    target = capture.target
    detections = _detect(capture, workers, progress)
    detected = np.array([[target.name in d for d in dets] for dets in detections])
    seconds["detect"] = time.perf_counter() - t0
    for cam, row in zip(capture.cameras, detected):
        log(f"camera {cam.name}: {target.kind} found in {int(row.sum())} of {len(row)} images")
        if not row.any():
            raise CalibrationError(
                f"{capture.root}: target {target.name!r} ({target.kind}) not found in any image of camera "
                f"{cam.name!r}; check handeye.json field 'target'"
            )
    t0 = time.perf_counter()
    intrinsics = _intrinsics(capture, detections, log)
    estimate = estimate_robot_noise and robot_sigma_translation is None and robot_sigma_rotation is None
    if estimate:  # the estimate's start (and the noisy-pose solve's structure)
        robot_sigma_translation, robot_sigma_rotation = ROBOT_SIGMA_START

    def observe(T_base_ee, eye_in_hand: bool, sigma_px: float | None) -> HandEyeObservations:
        return hand_eye_from_detections(
            detections,
            target,
            T_base_ee,
            np.stack([i.K for i in intrinsics]),
            _distortions([i.dist for i in intrinsics]),
            eye_in_hand=eye_in_hand,
            sigma_px=sigma_px,
            frame_names=capture.frames,
            robot_sigma_translation=robot_sigma_translation,
            robot_sigma_rotation=robot_sigma_rotation,
        )

    observations = observe(capture.T_base_ee, capture.eye_in_hand, sigma_px)
    seconds["prepare"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    solve = hand_eye_solver(max_steps)
    result = jax.tree.map(np.asarray, solve(observations.data, True, estimate))
    seconds["solve"] = time.perf_counter() - t0
    log(describe_robot_noise(result))
    t0 = time.perf_counter()
    # The folds leave the rejected groups out already: plain solves (the robot noise estimated
    # again in each, as the whole estimator is being replicated), same compiled program.
    kfold = (
        kfold_spread(lambda d: solve(d, False, estimate), observations.data, result, folds=folds)
        if folds
        else None
    )
    seconds["kfold"] = time.perf_counter() - t0
    verdict = assess_hand_eye(
        result,
        kfold=kfold,
        consistency=observations.consistency,
        frame_names=capture.frames,
        camera_names=[f"camera {c.name}" for c in capture.cameras],
        max_steps=max_steps,
    )
    t0 = time.perf_counter()
    verdict = _input_hints(
        verdict,
        capture,
        intrinsics,
        lambda T, eih: observe(T, eih, observations.sigma_px),
        observations.data,
        result,
        solve,
        log,
    )
    seconds["hints"] = time.perf_counter() - t0
    return HandEyeRun(
        capture=capture,
        intrinsics=intrinsics,
        detected=detected,
        observations=observations,
        result=result,
        kfold=kfold,
        verdict=verdict,
        rejected=_rejection_reasons(result, observations, OUTLIER_THRESHOLD),
        truth_error=_truth_error(capture, result),
        max_steps=max_steps,
        seconds=seconds,
    )
