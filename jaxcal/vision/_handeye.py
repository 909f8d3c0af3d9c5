"""From detections to hand-eye data: PnP per view, symmetric targets resolved, distortion removed, padded."""

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from .._cache import enable_compilation_cache
from .._handeye import (
    HandEyePixels,
    MotionConsistency,
    make_hand_eye_pixels,
    pad_hand_eye,
    rotation_angle,
    validate_hand_eye,
)
from ..errors import VisionError
from ..markers import TargetSpec
from ._detect import Detection, target_points
from ._pose import CIRCLE_KINDS, PoseEstimate, circle_centre_shift, estimate_pose

_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-10)
#: Floor on the estimated pixel noise (px): below it, numerical noise, not the detector's.
MIN_SIGMA_PX = 0.01


def _view_sigma(pose: PoseEstimate) -> float:
    """A view's pixel noise from its PnP residual, $\\sqrt{n\\,\\mathrm{rms}^2 / (2n - 6)}$ (no floor)."""
    n = pose.n_points
    return float(np.sqrt(n * pose.rms_px**2 / max(2 * n - 6, 1)))


@dataclass(frozen=True, eq=False)
class HandEyeObservations:
    """Hand-eye data built from detections, and what was learnt on the way.

    - `data`: `HandEyePixels`, undistorted, padded (`pad_hand_eye`): its first
      `frames` frames are the capture's, in order.
    - `frames`: the number of real frames; `frame_names`: their labels.
    - `sigma_px`: the pixel noise given to the solver: as given, or the median
      over views of PnP's residual estimate (`_view_sigma`), px, at least `MIN_SIGMA_PX`.
    - `poses`: per camera, per frame, PnP's `PoseEstimate` (distortion
      modelled) or None where the target was not found.
    - `consistency`: the robot-versus-camera rotation-angle check.
    - `turned`: `(camera, frame, degrees)` of the views whose ids were turned to
      resolve a symmetric target (see `jaxcal.markers`).
    """

    data: HandEyePixels
    frames: int
    frame_names: tuple[str, ...]
    sigma_px: float
    poses: tuple[tuple["PoseEstimate | None", ...], ...]
    consistency: MotionConsistency
    turned: tuple[tuple[int, int, int], ...]


def _per_camera(detections, target: TargetSpec) -> list[list[Detection | None]]:
    """Detections as [camera][frame]; one camera's list may be given bare, and
    `detect_frames` dicts (target name -> Detection) are read for `target`."""
    seq = list(detections)
    if not seq or isinstance(seq[0], (Detection, dict)) or seq[0] is None:
        seq = [seq]
    out = []
    for c, cam in enumerate(seq):
        row = []
        for f, d in enumerate(cam):
            if isinstance(d, dict):
                d = d.get(target.name)
            if d is not None and not isinstance(d, Detection):
                raise VisionError(
                    f"detections: camera {c}, frame {f}: expected a Detection or None, got {type(d).__name__}"
                )
            row.append(d)
        out.append(row)
    return out


def _turn(target: TargetSpec, perm: np.ndarray) -> np.ndarray:
    """$M$ with $M p_k = p_{perm[k]}$: the plate turned about its normal through the points' centre."""
    a = np.radians(target.rotation_angle(perm))
    c = target_points(target).mean(0)
    M = np.eye(4)
    M[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    M[:3, 3] = c - M[:3, :3] @ c
    return M


def _resolve_turns(poses, T_base_ee, target: TargetSpec) -> list[int]:
    """For one camera: which of `target.rotations()` each view's ids need, from the robot's motion.

    Turning the plate by $M$ changes a view's pose to $A M^{-1}$ and its
    relative rotations to the others; the choice whose relative rotation
    angles agree best (median over the other views) with the robot's
    (`jaxcal._handeye.consistency`) is kept, view by view, three sweeps; then
    the turn most views got is taken off every view (the plate's frame is
    defined up to a common turn). A wrong turn of 180 degrees changes those
    angles by up to 180 degrees, so the choice is clear.
    """
    perms = target.rotations()
    seen = [f for f, p in enumerate(poses) if p is not None]
    turn = {f: 0 for f in seen}
    if len(perms) == 1 or len(seen) < 2:
        return [turn.get(f, 0) for f in range(len(poses))]
    Minv = [np.linalg.inv(_turn(target, p))[:3, :3] for p in perms]
    cand = {f: [poses[f].T_cam_target[:3, :3] @ Mi for Mi in Minv] for f in seen}
    RB = np.asarray(T_base_ee)[:, :3, :3]
    robot = np.degrees(rotation_angle(np.einsum("fji,gjk->fgik", RB, RB)))
    for _ in range(3):
        for f in seen:
            others = [g for g in seen if g != f]
            cost = [
                np.median(
                    [abs(np.degrees(rotation_angle(cand[g][turn[g]].T @ R)) - robot[g, f]) for g in others]
                )
                for R in cand[f]
            ]
            turn[f] = int(np.argmin(cost))
    # Any common turn is as consistent: keep OpenCV's labels where most views have them.
    angles = [target.rotation_angle(p) for p in perms]
    common = angles[np.bincount([turn[f] for f in seen], minlength=len(perms)).argmax()]
    turn = {f: angles.index((angles[k] - common) % 360) for f, k in turn.items()}
    return [turn.get(f, 0) for f in range(len(poses))]


def _undistort(pixels: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    if not np.any(dist):
        return pixels
    out = cv2.undistortPointsIter(pixels.reshape(-1, 1, 2), K, dist, None, K, _UNDISTORT_CRITERIA)
    return out.reshape(-1, 2)


#: Steps of `circle_centre_shift` and PnP: the shift is redrawn at the pose the shifted blobs
#: give (the first step leaves a pose error of second order, the second none that counts).
CIRCLE_STEPS = 2


def _views(det, target: TargetSpec, T: np.ndarray, K: np.ndarray, dist: np.ndarray):
    """Every camera's views: PnP (`estimate_pose`), the turn of a symmetric target that agrees
    with the robot's motion (`_resolve_turns`, then PnP again on the turned ids), a circle
    grid's blobs moved to their circles' centres (`circle_centre_shift`, then PnP again) and the
    undistorted pixels. **Returns:** `(pixels (cameras, frames, points, 2)` (NaN where unseen),
    `poses` per camera and frame (None where unseen or PnP failed), `turned` `(camera, frame,
    deg)`, `sigmas` each view's pixel-noise estimate`)`."""
    C, F = len(det), T.shape[0]
    pixels = np.full((C, F, len(target_points(target)), 2), np.nan)
    poses, turned, sigmas = [], [], []
    perms = target.rotations()
    for c in range(C):
        row = [None if d is None else estimate_pose(d, target, K[c], dist[c]) for d in det[c]]
        turns = _resolve_turns(row, T, target)
        for f, d in enumerate(det[c]):
            if d is None or row[f] is None:
                row[f] = None
                continue
            ids, found = d.ids, d.pixels
            if turns[f]:
                ids = perms[turns[f]][ids]
                row[f] = estimate_pose(Detection(ids, found), target, K[c], dist[c])
                turned.append((c, f, target.rotation_angle(perms[turns[f]])))
            if row[f] is not None and target.kind in CIRCLE_KINDS:  # from the blobs to the circles' centres
                for _ in range(CIRCLE_STEPS):
                    shift = circle_centre_shift(target, ids, row[f].T_cam_target, K[c], dist[c])
                    row[f] = estimate_pose(Detection(ids, d.pixels - shift), target, K[c], dist[c]) or row[f]
                found = d.pixels - shift
            pixels[c, f, ids] = _undistort(found, K[c], dist[c])
            sigmas.append(_view_sigma(row[f]))
        poses.append(tuple(row))
    return pixels, poses, turned, sigmas


def hand_eye_from_detections(
    detections,
    target: TargetSpec,
    T_base_ee,
    K,
    dist=None,
    *,
    eye_in_hand: bool,
    sigma_px: float | None = None,
    frame_names: Sequence[str] | None = None,
    robot_sigma_translation: float | None = None,
    robot_sigma_rotation: float | None = None,
    pad: bool = True,
) -> HandEyeObservations:
    """Hand-eye data from the detector's output, with no glue left to the caller.

    Per view: PnP with the distortion model (`estimate_pose`) for the pose
    and the pixel-noise estimate; for a symmetric target (`TargetSpec.symmetric`)
    the ids are turned so that every view agrees with the robot's motion
    (`_resolve_turns`); a circle grid's blob centres are moved to the images of
    the circles' centres (`circle_centre_shift`); the pixels are undistorted (`cv2.undistortPointsIter`
    onto the same `K`), laid out densely with a mask, padded to a bucket of
    frames and points, and checked (`validate_hand_eye`, including the
    robot-versus-camera rotation-angle check that refuses mismatched data).

    **Arguments:**
    - `detections`: per camera, per frame, a `Detection` or None; or
      `detect_frames`' dicts (target name -> `Detection`); one camera's list may
      be passed bare.
    - `target`: the target detected.
    - `T_base_ee`: `(frames, 4, 4)` flange poses in the base frame (m).
    - `K`: `(3, 3)` or `(cameras, 3, 3)` px; `dist`: OpenCV coefficients,
      `(n,)` or `(cameras, n)`, or None.
    - `eye_in_hand`: the cameras ride on the flange.
    - `sigma_px`: pixel noise (px); None: estimated from PnP's residuals.
    - `frame_names`: labels for messages (default: indices).
    - `robot_sigma_translation` (m), `robot_sigma_rotation` (rad): robot pose
      noise, or None for exact robot poses.
    - `pad`: pad to a bucket (`pad_hand_eye`) so captures share compiled solvers.

    **Returns:** `HandEyeObservations`.

    **Raises:** `VisionError` for unusable input (a symmetric target seen by
    several cameras), and the `jaxcal.HandEyeInputError`s of `validate_hand_eye`.
    """
    enable_compilation_cache()  # the solve that follows compiles once per bucket, then comes from disk
    det = _per_camera(detections, target)
    C = len(det)
    T = np.asarray(T_base_ee, np.float64)
    F = T.shape[0] if T.ndim == 3 else -1
    if any(len(d) != F for d in det):
        raise VisionError(
            f"detections: {[len(d) for d in det]} frames per camera but {F} robot poses (T_base_ee)"
        )
    K = np.broadcast_to(np.asarray(K, np.float64), (C, 3, 3))
    dist = np.zeros((C, 5)) if dist is None else np.asarray(dist, np.float64)
    dist = np.broadcast_to(dist, (C, dist.shape[-1]))
    if target.symmetric and C > 1:
        raise VisionError(
            f"target {target.name!r} is symmetric (it looks the same turned by "
            f"{sorted(target.rotation_angle(p) for p in target.rotations()[1:])} deg), which the robot's motion "
            "resolves per camera but not across several: use an asymmetric target (a chessboard with an odd "
            "number of columns + rows, an asymmetric circle grid, ChArUco or an ArUco grid)"
        )
    names = tuple(str(n) for n in frame_names) if frame_names is not None else tuple(str(f) for f in range(F))
    points = target_points(target)
    pixels, poses, turned, sigmas = _views(det, target, T, K, dist)
    if sigma_px is None:
        sigma_px = max(float(np.median(sigmas)), MIN_SIGMA_PX) if sigmas else 1.0
    data = make_hand_eye_pixels(
        T,
        pixels,
        K,
        points,
        eye_in_hand=eye_in_hand,
        sigma_px=sigma_px,
        robot_sigma_translation=robot_sigma_translation,
        robot_sigma_rotation=robot_sigma_rotation,
        validate=False,
    )
    consistency = validate_hand_eye(data, frame_names=names)
    if pad:
        data = pad_hand_eye(data)
    return HandEyeObservations(data, F, names, float(sigma_px), tuple(poses), consistency, tuple(turned))
