"""Hand-eye measurements: image features (`HandEyePixels`) or board poses (`HandEyePoses`), built and checked."""

import equinox as eqx
import numpy as np
from jaxtyping import Array, Bool, Float

from .._device import to_device
from ..errors import (
    HandEyeInputError,
    LengthMismatchError,
    NonFiniteError,
    NotPositiveDefiniteError,
    ShapeError,
    TooFewPosesError,
)
from .checks import (
    MIN_POINTS_PER_VIEW,
    MIN_POSES,
    check_intrinsics,
    check_motion_diversity,
    check_rotations,
    check_sigma,
    plane_frame,
    spanning_views,
)
from .consistency import (
    CONSISTENCY_TOL_DEG,
    MotionConsistency,
    check_motion_consistency,
    homography_rotations,
)


class HandEyePixels(eqx.Module):
    """Board corners seen by one or more cameras at every robot pose, padded and masked.

    **Fields:**
    - `T_base_ee`: end-effector poses reported by the robot, `(frames, 4, 4)` (m).
    - `pixels`: detected corners (undistorted, px), `(cameras, frames, points, 2)`;
      entries where `mask` is False may hold anything, NaN included.
    - `mask`: which corners were detected, `(cameras, frames, points)`.
    - `K`: pinhole intrinsics, `(cameras, 3, 3)`.
    - `board_points`: corners in the board frame (m), `(points, 3)`; the
      closed-form start assumes they are (nearly) coplanar.
    - `sigma_px`: pixel noise standard deviation (px).
    - `robot_sigma`: robot pose noise `(translation m x3, rotation rad x3)`,
      or None for exact robot poses.
    - `eye_in_hand`: False for a fixed camera and the board on the end effector
      (an array, so both arrangements share one compiled solver).
    """

    T_base_ee: Float[Array, "frames 4 4"]
    pixels: Float[Array, "cameras frames points 2"]
    mask: Bool[Array, "cameras frames points"]
    K: Float[Array, "cameras 3 3"]
    board_points: Float[Array, "points 3"]
    sigma_px: Float[Array, ""]
    robot_sigma: Float[Array, "6"] | None
    eye_in_hand: Bool[Array, ""]


class HandEyePoses(eqx.Module):
    """Board poses measured in the camera frame (e.g. by PnP) at every robot pose.

    **Fields:**
    - `T_base_ee`: end-effector poses reported by the robot, `(frames, 4, 4)` (m).
    - `T_cam_board`: measured board poses, `(cameras, frames, 4, 4)`.
    - `mask`: which board poses were measured, `(cameras, frames)`.
    - `sigma`: pose noise `(translation m x3, rotation rad x3)`; the translation
      error is in the camera frame, the rotation error a camera-frame rotation vector.
    - `cov`: per-view covariances of that error, `(cameras, frames, 6, 6)`
      (m, rad; e.g. `jaxcal.vision.PoseEstimate.cov`), used instead of `sigma`;
      None to use `sigma`. Entries where `mask` is False are ignored (set
      positive definite).
    - `robot_sigma`, `eye_in_hand`: as in `HandEyePixels`; noisy robot poses
      are marginalised out of the pose errors rather than solved for.
    """

    T_base_ee: Float[Array, "frames 4 4"]
    T_cam_board: Float[Array, "cameras frames 4 4"]
    mask: Bool[Array, "cameras frames"]
    sigma: Float[Array, "6"]
    cov: Float[Array, "cameras frames 6 6"] | None
    robot_sigma: Float[Array, "6"] | None
    eye_in_hand: Bool[Array, ""]


HandEyeData = HandEyePixels | HandEyePoses


def _sigma6(translation, rotation) -> Float[Array, "6"]:
    return to_device(np.r_[np.full(3, translation, np.float64), np.full(3, rotation, np.float64)])


def _robot_sigma(translation, rotation):
    if (translation is None) != (rotation is None):
        raise HandEyeInputError("robot_sigma_translation and robot_sigma_rotation must be given together")
    return None if translation is None else _sigma6(translation, rotation)


def make_hand_eye_pixels(
    T_base_ee,
    pixels,
    K,
    board_points,
    mask=None,
    *,
    eye_in_hand: bool = False,
    sigma_px: float = 1.0,
    robot_sigma_translation: float | None = None,
    robot_sigma_rotation: float | None = None,
    validate: bool = True,
    frame_names=None,
) -> HandEyePixels:
    """Build `HandEyePixels`, adding a camera axis if absent, and validate it.

    **Arguments:**
    - `T_base_ee`: `(frames, 4, 4)` robot poses (a list of 4x4 matrices works).
    - `pixels`: `(frames, points, 2)` or `(cameras, frames, points, 2)` (px).
    - `K`: `(3, 3)` or `(cameras, 3, 3)`.
    - `board_points`: `(points, 3)` (m, board frame).
    - `mask`: matching `(..., frames, points)` bools; default: finite pixels.
    - `eye_in_hand`, `sigma_px`: see `HandEyePixels`.
    - `robot_sigma_translation` (m), `robot_sigma_rotation` (rad): robot pose
      noise; leave both None for exact robot poses.
    - `validate`: run `validate_hand_eye` (raises `ValueError` on bad input).
    - `frame_names`: labels of the frames for its messages (default: indices).
    """
    T = to_device(np.asarray(T_base_ee, dtype=np.float64))
    px = np.asarray(pixels, dtype=np.float64)
    K = np.asarray(K, dtype=np.float64)
    if px.ndim == 3:
        px = px[None]
        mask = None if mask is None else np.asarray(mask)[None]
    if px.ndim != 4 or px.shape[-1] != 2:
        raise ShapeError(
            f"pixels must have shape (frames, points, 2) or (cameras, frames, points, 2), got {px.shape}"
        )
    if K.shape[-2:] != (3, 3) or K.ndim not in (2, 3):
        raise ShapeError(f"K must have shape (3, 3) or (cameras, 3, 3), got {K.shape}")
    if K.ndim == 2:
        K = np.broadcast_to(K, (px.shape[0], 3, 3))
    mask = np.all(np.isfinite(px), axis=-1) if mask is None else np.asarray(mask, bool)
    data = HandEyePixels(
        T_base_ee=T,
        pixels=to_device(px),
        mask=to_device(mask),
        K=to_device(K),
        board_points=to_device(np.asarray(board_points, dtype=np.float64)),
        sigma_px=to_device(sigma_px, np.float64),
        robot_sigma=_robot_sigma(robot_sigma_translation, robot_sigma_rotation),
        eye_in_hand=to_device(eye_in_hand, bool),
    )
    if validate:
        validate_hand_eye(data, frame_names=frame_names)
    return data


def make_hand_eye_poses(
    T_base_ee,
    T_cam_board,
    mask=None,
    *,
    eye_in_hand: bool = False,
    sigma_translation: float = 1e-3,
    sigma_rotation: float = 1e-3,
    cov=None,
    robot_sigma_translation: float | None = None,
    robot_sigma_rotation: float | None = None,
    validate: bool = True,
    frame_names=None,
) -> HandEyePoses:
    """Build `HandEyePoses`, adding a camera axis if absent, and validate it.

    **Arguments:**
    - `T_base_ee`: `(frames, 4, 4)` robot poses.
    - `T_cam_board`: `(frames, 4, 4)` or `(cameras, frames, 4, 4)` measured board poses.
    - `mask`: `(frames,)` or `(cameras, frames)` bools; default: finite poses.
    - `sigma_translation` (m), `sigma_rotation` (rad): board pose noise.
    - `cov`: per-view 6x6 covariances of the board pose error instead,
      `(frames, 6, 6)` or `(cameras, frames, 6, 6)` (translation m, camera-frame
      rotation rad: `jaxcal.vision.PoseEstimate.cov`, whose error convention this is).
    - `robot_sigma_translation`, `robot_sigma_rotation`, `eye_in_hand`,
      `validate`, `frame_names`: see `make_hand_eye_pixels`.
    """
    A = np.asarray(T_cam_board, dtype=np.float64)
    if A.ndim == 3:
        A = A[None]
        mask = None if mask is None else np.asarray(mask)[None]
    if A.ndim != 4 or A.shape[-2:] != (4, 4):
        raise ShapeError(
            f"T_cam_board must have shape (frames, 4, 4) or (cameras, frames, 4, 4), got {A.shape}"
        )
    mask = np.all(np.isfinite(A), axis=(-1, -2)) if mask is None else np.asarray(mask, bool)
    sigma = _sigma6(sigma_translation, sigma_rotation)
    if cov is not None:
        cov = _pose_covariances(cov, A.shape[:2], mask, np.asarray(sigma))
    data = HandEyePoses(
        T_base_ee=to_device(np.asarray(T_base_ee, dtype=np.float64)),
        T_cam_board=to_device(A),
        mask=to_device(mask),
        sigma=sigma,
        cov=None if cov is None else to_device(cov),
        robot_sigma=_robot_sigma(robot_sigma_translation, robot_sigma_rotation),
        eye_in_hand=to_device(eye_in_hand, bool),
    )
    if validate:
        validate_hand_eye(data, frame_names=frame_names)
    return data


def validate_hand_eye(
    data: HandEyeData, *, frame_names=None, tolerance_deg: float = CONSISTENCY_TOL_DEG
) -> MotionConsistency:
    """Raise a `ValueError` naming the problem if `data` cannot give a hand-eye calibration.

    Checks: shapes and matching lengths (robot poses against frames, cameras
    against intrinsics), rotations that are rotations, non-finite observed
    values, at least `MIN_POSES` observed poses (with `MIN_POINTS_PER_VIEW`
    corners for pixels), the motion diversity of `check_motion_diversity`, and
    that the robot's relative rotation angles agree with the camera's
    (`check_motion_consistency`: refused when most pairs of frames disagree by
    more than `tolerance_deg`).

    **Returns:** the `MotionConsistency` (which frames disagree with most others).
    """
    T = np.asarray(data.T_base_ee)
    if T.ndim != 3 or T.shape[-2:] != (4, 4):
        raise ShapeError(f"T_base_ee must have shape (frames, 4, 4), got {T.shape}")
    F = T.shape[0]
    if isinstance(data, HandEyePixels):
        px, mask = np.asarray(data.pixels), np.asarray(data.mask)
        C, Fp, P = px.shape[:3]
        if Fp != F:
            raise LengthMismatchError(
                f"{F} robot poses (T_base_ee) but {Fp} frames of pixels (lengths must match)"
            )
        if mask.shape != px.shape[:3]:
            raise ShapeError(f"mask has shape {mask.shape}, pixels imply {px.shape[:3]}")
        if np.shape(data.K) != (C, 3, 3):
            raise ShapeError(f"K has shape {np.shape(data.K)}, expected {(C, 3, 3)} for {C} cameras")
        check_intrinsics(np.asarray(data.K))
        check_sigma("sigma_px", data.sigma_px)
        if np.shape(data.board_points) != (P, 3):
            raise ShapeError(f"board_points has shape {np.shape(data.board_points)}, pixels imply {(P, 3)}")
        if not np.all(np.isfinite(np.asarray(data.board_points))):
            raise NonFiniteError("board_points: non-finite entries")
        bad = mask & ~np.all(np.isfinite(px), axis=-1)
        if bad.any():
            c, f, p = (int(k) for k in np.argwhere(bad)[0])
            raise NonFiniteError(f"pixels: non-finite detected corner at camera {c}, frame {f}, point {p}")
        views = spanning_views(plane_frame(np.asarray(data.board_points))[1], mask)
        what = f"frames with at least {MIN_POINTS_PER_VIEW} detected corners not on one line"
        rotations = lambda: homography_rotations(px, mask, data.K, data.board_points)[0]
    else:
        A, mask = np.asarray(data.T_cam_board), np.asarray(data.mask)
        C, Fa = A.shape[:2]
        if Fa != F:
            raise LengthMismatchError(
                f"{F} robot poses (T_base_ee) but {Fa} board poses (T_cam_board) (lengths must match)"
            )
        if mask.shape != (C, F):
            raise ShapeError(f"mask has shape {mask.shape}, T_cam_board implies {(C, F)}")
        # Index messages by (camera, frame): unmeasured poses are replaced by the identity.
        check_rotations(np.where(mask[..., None, None], A, np.eye(4)), "T_cam_board")
        check_sigma("sigma_translation and sigma_rotation", data.sigma)
        if data.cov is not None:
            _check_covariances(np.asarray(data.cov), mask)
        views = mask
        what = "frames with a measured board pose"
        rotations = lambda: A[..., :3, :3]
    check_rotations(T, "T_base_ee")
    if data.robot_sigma is not None:
        check_sigma("robot_sigma_translation and robot_sigma_rotation", data.robot_sigma)
    unseen = np.flatnonzero(~views.any(1))
    if unseen.size:
        raise TooFewPosesError(f"camera {unseen[0]} has no usable view ({what}); its pose cannot be solved")
    seen = views.any(0)
    if int(seen.sum()) < MIN_POSES:
        raise TooFewPosesError(f"only {int(seen.sum())} {what}, at least {MIN_POSES} robot poses are needed")
    check_motion_diversity(T[seen])
    return check_motion_consistency(
        rotations(), views, T, tolerance_deg=tolerance_deg, frame_names=frame_names
    )


def _pose_covariances(cov, shape, mask, sigma) -> np.ndarray:
    """`cov` as `(cameras, frames, 6, 6)`, unmeasured entries replaced by `diag(sigma^2)`."""
    cov = np.asarray(cov, dtype=np.float64)
    if cov.ndim == 3:
        cov = cov[None]
    if cov.shape != (*shape, 6, 6):
        raise ShapeError(
            f"cov must have shape (frames, 6, 6) or (cameras, frames, 6, 6) = {(*shape, 6, 6)}, got {cov.shape}"
        )
    return np.where(mask[..., None, None], cov, np.diag(sigma**2))


def _check_covariances(cov, mask) -> None:
    bad = mask & ~np.all(np.isfinite(cov), axis=(-1, -2))
    if bad.any():
        c, f = (int(k) for k in np.argwhere(bad)[0])
        raise NonFiniteError(f"cov: non-finite covariance at camera {c}, frame {f}")
    sym = np.max(np.abs(cov - np.swapaxes(cov, -1, -2)), axis=(-1, -2)) > 1e-9 * np.max(
        np.abs(cov), axis=(-1, -2)
    )
    eig = np.linalg.eigvalsh(0.5 * (cov + np.swapaxes(cov, -1, -2)))
    bad = mask & (sym | (eig[..., 0] <= 0.0))
    if bad.any():
        c, f = (int(k) for k in np.argwhere(bad)[0])
        raise NotPositiveDefiniteError(
            f"cov: the covariance at camera {c}, frame {f} is not symmetric positive definite "
            f"(smallest eigenvalue {eig[c, f, 0]:.3g})"
        )


#: Frame counts are padded up to one of these (then to multiples of 64), so that
#: captures of similar size share one compiled solver.
FRAME_BUCKETS = (8, 16, 24, 32, 48, 64, 96, 128)
#: Board point counts are padded up to a multiple of this.
POINT_BUCKET = 16


def bucket(n: int, sizes=FRAME_BUCKETS, step: int = 64) -> int:
    """The smallest of `sizes` that holds `n`, else `n` rounded up to a multiple of `step`."""
    for s in sizes:
        if n <= s:
            return s
    return -(-n // step) * step


def pad_hand_eye(data: HandEyeData, frames: int | None = None, points: int | None = None) -> HandEyeData:
    """`data` padded with unobserved frames (identity robot poses) and, for pixels, board points
    (copies of the first: coplanar, masked), so that new captures reuse compiled programs.

    Padding changes no estimate: padded entries are masked out of every
    residual, and a padded frame's robot correction (noisy robot poses) meets
    only its prior, so it stays zero and leaves the degrees of freedom as they were.

    **Arguments:** `frames` (default `bucket(frames)`), `points` (pixels; default
    the next multiple of `POINT_BUCKET`). **Returns:** the padded data (NumPy-built, outside jit).
    """
    F = data.T_base_ee.shape[0]
    Fp = bucket(F) if frames is None else int(frames)
    if Fp < F:
        raise ShapeError(f"cannot pad {F} frames to {Fp}")
    pad_f = Fp - F
    T = np.concatenate([np.asarray(data.T_base_ee), np.broadcast_to(np.eye(4), (pad_f, 4, 4))])
    if isinstance(data, HandEyePixels):
        C, _, P = data.mask.shape
        Pp = -(-P // POINT_BUCKET) * POINT_BUCKET if points is None else int(points)
        if Pp < P:
            raise ShapeError(f"cannot pad {P} board points to {Pp}")
        px = np.zeros((C, Fp, Pp, 2))
        px[:, :F, :P] = np.where(np.asarray(data.mask)[..., None], np.asarray(data.pixels), 0.0)
        mask = np.zeros((C, Fp, Pp), bool)
        mask[:, :F, :P] = np.asarray(data.mask)
        board = np.asarray(data.board_points)
        board = np.concatenate([board, np.broadcast_to(board[:1], (Pp - P, 3))])
        return HandEyePixels(
            T_base_ee=to_device(T),
            pixels=to_device(px),
            mask=to_device(mask),
            K=data.K,
            board_points=to_device(board),
            sigma_px=data.sigma_px,
            robot_sigma=data.robot_sigma,
            eye_in_hand=data.eye_in_hand,
        )
    C = data.mask.shape[0]
    A = np.concatenate([np.asarray(data.T_cam_board), np.broadcast_to(np.eye(4), (C, pad_f, 4, 4))], axis=1)
    mask = np.concatenate([np.asarray(data.mask), np.zeros((C, pad_f), bool)], axis=1)
    cov = None
    if data.cov is not None:
        filler = np.broadcast_to(np.diag(np.asarray(data.sigma) ** 2), (C, pad_f, 6, 6))
        cov = to_device(np.concatenate([np.asarray(data.cov), filler], axis=1))
    return HandEyePoses(
        T_base_ee=to_device(T),
        T_cam_board=to_device(A),
        mask=to_device(mask),
        sigma=data.sigma,
        cov=cov,
        robot_sigma=data.robot_sigma,
        eye_in_hand=data.eye_in_hand,
    )
