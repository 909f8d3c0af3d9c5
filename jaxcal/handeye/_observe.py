"""Hand-eye's first two steps: load the capture, then observe it (detect the target, the
intrinsics given or self-calibrated, PnP and the hand-eye data with its input checks)."""

import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from ..errors import CalibrationError, HandEyeInputError, InconsistentPosesError
from ..io.handeye import HandEyeCapture, load_hand_eye_capture, rpy_to_matrix
from ..records import Intrinsics
from ..vision import HandEyeObservations, calibrate_intrinsics, detect_frames, hand_eye_from_detections
from ._noise import RobotNoiseSetting


def load(capture) -> HandEyeCapture:
    """The capture: a loaded `HandEyeCapture` as is, or a directory read by `load_hand_eye_capture`."""
    return capture if isinstance(capture, HandEyeCapture) else load_hand_eye_capture(capture)


def detect(capture: HandEyeCapture, workers, progress, log) -> tuple[tuple, np.ndarray]:
    """`detect_frames` of the capture's target per camera (with its K and distortion where given):
    the detections `[camera][frame]` and `detected` `(cameras, frames)`.

    **Raises:** `CalibrationError` when a camera sees the target in no image."""
    target = capture.target
    detections = tuple(
        detect_frames(
            paths,
            [target],
            K=cam.K,
            dist=cam.dist if cam.K is not None else None,
            workers=workers,
            progress=progress,
            pool="thread",
        )
        for cam, paths in zip(capture.cameras, capture.images)
    )
    detected = np.array([[target.name in d for d in dets] for dets in detections])
    for cam, row in zip(capture.cameras, detected):
        log(f"camera {cam.name}: {target.kind} found in {int(row.sum())} of {len(row)} images")
        if not row.any():
            raise CalibrationError(
                f"{capture.root}: target {target.name!r} ({target.kind}) not found in any image of camera "
                f"{cam.name!r}; check handeye.json field 'target'"
            )
    return detections, detected


def camera_intrinsics(capture: HandEyeCapture, detections, log) -> tuple[Intrinsics, ...]:
    """Each camera's `Intrinsics`: `"given"` (the capture's K and distortion) or `"self-calibrated"`
    from its views of the target (then `rms_px` is OpenCV's calibration RMS)."""
    out = []
    for cam, dets in zip(capture.cameras, detections):
        if cam.K is not None:
            out.append(Intrinsics(source="given", K=np.asarray(cam.K), distortion=np.asarray(cam.dist)))
            continue
        views = [d.get(capture.target.name) for d in dets]
        K, dist, rms = calibrate_intrinsics(views, capture.target, (cam.width, cam.height))
        log(
            f"camera {cam.name}: intrinsics self-calibrated from {sum(v is not None for v in views)} views ({rms:.3f} px RMS)"
        )
        out.append(Intrinsics(source="self-calibrated", rms_px=float(rms), K=K, distortion=dist))
    return tuple(out)


def distortions(dists) -> np.ndarray:
    """Every camera's OpenCV coefficients zero-padded to the longest, `(cameras, n)`."""
    n = max(len(d) for d in dists)
    return np.stack([np.pad(np.asarray(d, np.float64), (0, n - len(d))) for d in dists])


@dataclass(frozen=True, eq=False)
class Observed:
    """What `observe` saw of a capture.

    - `capture`; `detections` `[camera][frame]` (`detect_frames`'s dicts), `detected` `(cameras, frames)`.
    - `intrinsics`: per camera, given or self-calibrated.
    - `observations`: the hand-eye data `hand_eye_from_detections` built (PnP, checks, padding).
    - `noise`: the robot-noise model asked for (`_noise.RobotNoiseSetting`); `observations` hold
      the robot poses as exact, and the solve gives them each model's noise (`_noise.model_data`).
    - `seconds`: `detect` (loading included) and `prepare`.
    """

    capture: HandEyeCapture
    detections: tuple
    detected: np.ndarray
    intrinsics: tuple[Intrinsics, ...]
    observations: HandEyeObservations
    noise: RobotNoiseSetting
    seconds: dict[str, float]

    def reobserve(self, T_base_ee, eye_in_hand: bool) -> HandEyeObservations:
        """The same detections and intrinsics with other robot poses or arrangement (a misreading
        of the input), at the pixel noise observed, the robot poses exact."""
        return _observations(self, T_base_ee, eye_in_hand, self.observations.sigma_px)


def _observations(observed, T_base_ee, eye_in_hand: bool, sigma_px) -> HandEyeObservations:
    capture, intrinsics = observed.capture, observed.intrinsics
    return hand_eye_from_detections(
        observed.detections,
        capture.target,
        T_base_ee,
        np.stack([i.K for i in intrinsics]),
        distortions([i.distortion for i in intrinsics]),
        eye_in_hand=eye_in_hand,
        sigma_px=sigma_px,
        frame_names=capture.frames,
    )


def observe(
    capture,
    *,
    noise: RobotNoiseSetting,
    sigma_px: float | None,
    workers,
    progress: bool,
    log: Callable[[str], None],
) -> Observed:
    """Load (`load`), detect (`detect`), the intrinsics (`camera_intrinsics`) and the hand-eye
    data with its input checks (`hand_eye_from_detections`; see `calibrate_hand_eye_capture`
    for the arguments), the robot poses exact; `noise` is what the solve will make of them."""
    t0 = time.perf_counter()
    capture = load(capture)
    detections, detected = detect(capture, workers, progress, log)
    seconds = {"detect": time.perf_counter() - t0}
    t0 = time.perf_counter()
    intrinsics = camera_intrinsics(capture, detections, log)
    observed = Observed(capture, detections, detected, intrinsics, None, noise, seconds)
    try:
        observations = _observations(observed, capture.T_base_ee, capture.eye_in_hand, sigma_px)
    except InconsistentPosesError as e:
        raise InconsistentPosesError(_read_otherwise(observed, str(e), sigma_px)) from None
    observed = replace(observed, observations=observations)
    seconds["prepare"] = time.perf_counter() - t0
    return observed


def rotation_readings(capture: HandEyeCapture) -> list[tuple[str, np.ndarray]]:
    """The rotations of `capture`'s poses read otherwise than its `poses.format` says, where the
    relative rotation angles then change (so that the input check tells): `(what to fix,
    T_base_ee)` each, from the values as written (`HandEyeCapture.rotations`): Euler angles as
    intrinsic x-y-z (R = Rx Ry Rz) or in the columns' reverse order; a rotation vector as roll,
    pitch, yaw."""
    T = np.asarray(capture.T_base_ee, np.float64)
    v = capture.rotations
    if v is None or len(v) != len(T):  # a capture built in code
        return []
    if capture.pose_format == "xyz_rpy":
        alternatives = [
            (
                "the angles are intrinsic x-y-z (R = Rx(roll) Ry(pitch) Rz(yaw)), not xyz_rpy's fixed axes "
                "(R = Rz(yaw) Ry(pitch) Rx(roll)): convert them, or write the poses as matrices or quaternions",
                np.swapaxes(rpy_to_matrix(-v), -1, -2),
            ),
            (
                "the columns poses.csv's header names roll, pitch, yaw hold yaw, pitch, roll (label the columns "
                "in the order the values are written)",
                rpy_to_matrix(v[:, ::-1]),
            ),
        ]
    elif capture.pose_format == "xyz_rotvec":
        alternatives = [
            (
                "the columns rx, ry, rz hold roll, pitch, yaw (fixed axes): set handeye.json field "
                "'poses.format' to 'xyz_rpy' (and the header to x, y, z, roll, pitch, yaw)",
                rpy_to_matrix(v),
            )
        ]
    else:
        return []
    out = []
    for fix, Ra in alternatives:
        Ta = T.copy()
        Ta[:, :3, :3] = Ra
        out.append((fix, Ta))
    return out


def _read_otherwise(observed: Observed, message: str, sigma_px) -> str:
    """The input check's refusal `message`, with the reading of the rotations under which the poses
    and images agree (`rotation_readings`), when one does and the refusal found no shifted rows."""
    if "The data fit shifted" in message:
        return message
    for fix, T in rotation_readings(observed.capture):
        try:
            _observations(observed, T, observed.capture.eye_in_hand, sigma_px)
        except HandEyeInputError:
            continue
        return f"{message}. They agree when read otherwise: {fix}"
    return message
