"""Classic hand-eye calibration, solved on image features (seed method 4) and by TCP touch (seed 5).

Two arrangements share one algebra. Per robot pose $f$ the board's pose in
camera $c$ is

$$T^{cam_c}_{board}(f) = X_c\\, B_f\\, Y,$$

- eye-to-hand (camera fixed, board on the end effector): $X_c = T_{cam\\_base}$,
  $B_f = T_{base\\_ee}(f)$, $Y = T_{ee\\_board}$;
- eye-in-hand (camera on the end effector, board fixed): $X_c = T_{cam\\_ee}$,
  $B_f = T_{base\\_ee}(f)^{-1}$, $Y = T_{base\\_board}$.

This is the robot-world-hand-eye form $A W = X B$ with $A = T^{cam}_{board}$
and $W = Y^{-1}$. Instead of pairing motions (Tsai-Lenz $AX = XB$), the
estimator keeps one unique transform per camera and one shared object
transform and minimises the difference between predicted and measured image
features directly (the reprojection error of every board corner), which is
the maximum-likelihood estimate under pixel noise. A pose-level variant
(measured $T^{cam}_{board}$ from PnP, as OpenCV's protocol gives) whitens the
pose error instead. Robot poses may be treated as noisy: with pixels, one
correction per pose with a Gaussian prior; with poses, the corrections are
marginalised (each frame's pose error whitened by $\\Sigma_A + J \\Sigma_r J^T$,
`_robot_jacobian`), so the solve keeps its 6 (cameras + 1) unknowns.

Pipeline (all pure, jittable and vmappable):
1. Closed-form start. Board poses from pixels by a planar homography (Zhang's
   decomposition); then rotations from the top eigenvector of
   $\\sum_c n_c S_c^T S_c$, $S_c$ the mean over frames of the $9\\times 9$
   matrices $R_{B_f} \\otimes R_{A_{cf}}$ (Shah's Kronecker method, extended
   to several cameras sharing $W$), and translations by linear least squares.
2. Robust Levenberg-Marquardt: a Cauchy loss per (camera, frame) group.
3. Outliers: groups whose whitened residual RMS exceeds `outlier_threshold`
   times the median are rejected and reported.
4. Plain Levenberg-Marquardt on the remaining groups (the ML estimate), and a
   covariance from the Jacobian.

Every pose is optimised as a 6-vector tangent delta about its start,
$X = X_0 \\exp(\\xi)$ with $\\xi = (v, w)$ (translation first, m and rad).
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, Bool, Float, Int

from ._geometry import make_pose, matmul, pose_inverse, se3_exp, so3_exp, so3_log
from ._linalg import after, nearest_rotation
from .errors import (
    DegenerateMotionError,
    HandEyeInputError,
    LengthMismatchError,
    NonFiniteError,
    NotARotationError,
    ShapeError,
    TooFewPosesError,
)

MIN_POSES = 3
MIN_ROTATION_DEG = 5.0
MIN_AXIS_SEPARATION_DEG = 5.0
MIN_POINTS_PER_VIEW = 4
_ROTATION_TOL = 1e-6

# --------------------------------------------------------------------------- errors


# --------------------------------------------------------------------------- data


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
    - `robot_sigma`, `eye_in_hand`: as in `HandEyePixels`; noisy robot poses
      are marginalised out of the pose errors rather than solved for.
    """

    T_base_ee: Float[Array, "frames 4 4"]
    T_cam_board: Float[Array, "cameras frames 4 4"]
    mask: Bool[Array, "cameras frames"]
    sigma: Float[Array, "6"]
    robot_sigma: Float[Array, "6"] | None
    eye_in_hand: Bool[Array, ""]


HandEyeData = HandEyePixels | HandEyePoses


def _sigma6(translation, rotation) -> Float[Array, "6"]:
    return jnp.concatenate(
        [jnp.full(3, translation, dtype=jnp.float64), jnp.full(3, rotation, dtype=jnp.float64)]
    )


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
    """
    T = jnp.asarray(np.asarray(T_base_ee, dtype=np.float64))
    px = np.asarray(pixels, dtype=np.float64)
    K = np.asarray(K, dtype=np.float64)
    if px.ndim == 3:
        px = px[None]
        mask = None if mask is None else np.asarray(mask)[None]
    if px.ndim != 4 or px.shape[-1] != 2:
        raise ShapeError(
            f"pixels must have shape (frames, points, 2) or (cameras, frames, points, 2), got {px.shape}"
        )
    if K.ndim == 2:
        K = np.broadcast_to(K, (px.shape[0], 3, 3))
    mask = np.all(np.isfinite(px), axis=-1) if mask is None else np.asarray(mask, bool)
    data = HandEyePixels(
        T_base_ee=T,
        pixels=jnp.asarray(px),
        mask=jnp.asarray(mask),
        K=jnp.asarray(K),
        board_points=jnp.asarray(np.asarray(board_points, dtype=np.float64)),
        sigma_px=jnp.asarray(sigma_px, jnp.float64),
        robot_sigma=_robot_sigma(robot_sigma_translation, robot_sigma_rotation),
        eye_in_hand=jnp.asarray(eye_in_hand, bool),
    )
    if validate:
        validate_hand_eye(data)
    return data


def make_hand_eye_poses(
    T_base_ee,
    T_cam_board,
    mask=None,
    *,
    eye_in_hand: bool = False,
    sigma_translation: float = 1e-3,
    sigma_rotation: float = 1e-3,
    robot_sigma_translation: float | None = None,
    robot_sigma_rotation: float | None = None,
    validate: bool = True,
) -> HandEyePoses:
    """Build `HandEyePoses`, adding a camera axis if absent, and validate it.

    **Arguments:**
    - `T_base_ee`: `(frames, 4, 4)` robot poses.
    - `T_cam_board`: `(frames, 4, 4)` or `(cameras, frames, 4, 4)` measured board poses.
    - `mask`: `(frames,)` or `(cameras, frames)` bools; default: finite poses.
    - `sigma_translation` (m), `sigma_rotation` (rad): board pose noise.
    - `robot_sigma_translation`, `robot_sigma_rotation`, `eye_in_hand`,
      `validate`: see `make_hand_eye_pixels`.
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
    data = HandEyePoses(
        T_base_ee=jnp.asarray(np.asarray(T_base_ee, dtype=np.float64)),
        T_cam_board=jnp.asarray(A),
        mask=jnp.asarray(mask),
        sigma=_sigma6(sigma_translation, sigma_rotation),
        robot_sigma=_robot_sigma(robot_sigma_translation, robot_sigma_rotation),
        eye_in_hand=jnp.asarray(eye_in_hand, bool),
    )
    if validate:
        validate_hand_eye(data)
    return data


# --------------------------------------------------------------------------- input checks


def _so3_log_np(R: np.ndarray) -> np.ndarray:
    s = 0.5 * np.stack(
        [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1
    )
    c = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    sn = np.linalg.norm(s, axis=-1)
    theta = np.arctan2(sn, c)
    # Near pi the antisymmetric part vanishes: take the axis from R + I instead.
    near_pi = (sn < 1e-6) & (c < 0)
    scale = np.where(sn < 1e-12, 1.0, theta / np.where(sn < 1e-12, 1.0, sn))
    w = scale[..., None] * s
    if np.any(near_pi):
        B = (R[near_pi] + np.eye(3)) / 2.0
        col = np.argmax(np.linalg.norm(B, axis=-2), axis=-1)
        axis = B[np.arange(len(col)), :, col]
        w[near_pi] = np.pi * axis / np.linalg.norm(axis, axis=-1, keepdims=True)
    return w


def _at(i: int, shape: tuple) -> tuple[int, ...]:
    """The index tuple of flat index `i` (plain ints, for messages)."""
    return tuple(int(k) for k in np.unravel_index(i, shape))


def check_rotations(T, name: str) -> None:
    """Raise a `ValueError` naming `name` unless every `T[..., :3, :3]` is a rotation.

    The tolerance is `1e-6` on $\\|R^T R - I\\|_\\infty$ and on $|\\det R - 1|$;
    non-finite entries and a bottom row other than `(0, 0, 0, 1)` are errors too.
    """
    T = np.asarray(T, dtype=np.float64)
    if T.shape[-2:] != (4, 4):
        raise ShapeError(f"{name}: expected 4x4 poses, got shape {T.shape}")
    flat = T.reshape(-1, 4, 4)
    bad = ~np.all(np.isfinite(flat), axis=(-1, -2))
    if bad.any():
        raise NonFiniteError(f"{name}: non-finite pose at index {_at(np.flatnonzero(bad)[0], T.shape[:-2])}")
    R = flat[:, :3, :3]
    orth = np.max(np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)), axis=(-1, -2))
    det = np.linalg.det(R)
    bad = (orth > _ROTATION_TOL) | (np.abs(det - 1.0) > _ROTATION_TOL)
    if bad.any():
        i = np.flatnonzero(bad)[0]
        raise NotARotationError(
            f"{name}: pose {_at(i, T.shape[:-2])} is not a rotation "
            f"(det = {det[i]:.6g}, max |R^T R - I| = {orth[i]:.3g})"
        )
    bottom = np.max(np.abs(flat[:, 3] - np.array([0.0, 0.0, 0.0, 1.0])), axis=-1)
    if np.any(bottom > _ROTATION_TOL):
        i = np.flatnonzero(bottom > _ROTATION_TOL)[0]
        raise NotARotationError(
            f"{name}: pose {_at(i, T.shape[:-2])} has bottom row {flat[i, 3]}, not (0, 0, 0, 1)"
        )


def check_motion_diversity(T_base_ee, name: str = "robot poses") -> None:
    """Raise a `ValueError` unless the poses rotate about two non-parallel axes (seed 4).

    Every pair of poses gives a relative rotation $R_i^T R_j$ (end-effector
    frame). At least one must turn by `MIN_ROTATION_DEG` or more, and among
    those turning that much, one axis must differ by at least
    `MIN_AXIS_SEPARATION_DEG` (sign-agnostic) from the axis of the largest.
    """
    R = np.asarray(T_base_ee, dtype=np.float64)[..., :3, :3]
    n = R.shape[0]
    i, j = np.triu_indices(n, 1)
    rel = np.swapaxes(R[i], -1, -2) @ R[j]
    w = _so3_log_np(rel)
    ang = np.degrees(np.linalg.norm(w, axis=-1))
    big = ang >= MIN_ROTATION_DEG
    if not big.any():
        raise DegenerateMotionError(
            f"{name}: the largest rotation between two poses is {ang.max() if ang.size else 0.0:.2f} deg; "
            f"hand-eye calibration needs rotations of at least {MIN_ROTATION_DEG:g} deg about at least two "
            "non-parallel axes"
        )
    axes = w[big] / np.linalg.norm(w[big], axis=-1, keepdims=True)
    ref = axes[np.argmax(ang[big])]
    sep = np.degrees(np.arccos(np.clip(np.abs(axes @ ref), 0.0, 1.0)))
    if sep.max() < MIN_AXIS_SEPARATION_DEG:
        raise DegenerateMotionError(
            f"{name}: every rotation of at least {MIN_ROTATION_DEG:g} deg is about one axis "
            f"(end-effector frame {np.array2string(ref, precision=3)}, within {sep.max():.2f} deg); "
            f"add a rotation of at least {MIN_ROTATION_DEG:g} deg about a second, non-parallel axis"
        )


def validate_hand_eye(data: HandEyeData) -> None:
    """Raise a `ValueError` naming the problem if `data` cannot give a hand-eye calibration.

    Checks: shapes and matching lengths (robot poses against frames, cameras
    against intrinsics), rotations that are rotations, non-finite observed
    values, at least `MIN_POSES` observed poses (with `MIN_POINTS_PER_VIEW`
    corners for pixels), and the motion diversity of `check_motion_diversity`.
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
        if np.shape(data.board_points) != (P, 3):
            raise ShapeError(f"board_points has shape {np.shape(data.board_points)}, pixels imply {(P, 3)}")
        if not np.all(np.isfinite(np.asarray(data.board_points))):
            raise NonFiniteError("board_points: non-finite entries")
        bad = mask & ~np.all(np.isfinite(px), axis=-1)
        if bad.any():
            c, f, p = (int(k) for k in np.argwhere(bad)[0])
            raise NonFiniteError(f"pixels: non-finite detected corner at camera {c}, frame {f}, point {p}")
        views = mask.sum(-1) >= MIN_POINTS_PER_VIEW
        what = f"frames with at least {MIN_POINTS_PER_VIEW} detected corners"
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
        views = mask
        what = "frames with a measured board pose"
    check_rotations(T, "T_base_ee")
    unseen = np.flatnonzero(~views.any(1))
    if unseen.size:
        raise TooFewPosesError(f"camera {unseen[0]} has no usable view ({what}); its pose cannot be solved")
    seen = views.any(0)
    if int(seen.sum()) < MIN_POSES:
        raise TooFewPosesError(f"only {int(seen.sum())} {what}, at least {MIN_POSES} robot poses are needed")
    check_motion_diversity(T[seen])


# --------------------------------------------------------------------------- model


class HandEyeParams(eqx.Module):
    """Unknowns: tangent deltas of $X_c$, of $Y$ and (optionally) of every robot pose."""

    cam_robot: Float[Array, "cameras 6"]
    robot_board: Float[Array, "6"]
    robot: Float[Array, "frames 6"] | None


class HandEyeReference(eqx.Module):
    """Start of the parameterisation (closed form), the active mask and the pose-error whitening.

    `whiten` (pose data with noisy robot poses only): per frame, $L_f^{-1}$ with
    $L_f L_f^T = S_f$ the covariance of the frame's stacked pose errors
    (see `_robot_jacobian`), `(frames, 6 cameras, 6 cameras)`; None otherwise.
    """

    X0: Float[Array, "cameras 4 4"]
    Y0: Float[Array, "4 4"]
    active: Bool[Array, "cameras frames"]
    whiten: Float[Array, "frames n n"] | None = None


def _corrected_robot(T_base_ee, delta):
    """Robot poses with independent corrections: $R = \\exp(w) R_{meas}$, $t = t_{meas} + v$."""
    if delta is None:
        return T_base_ee
    R = matmul(jax.vmap(so3_exp)(delta[:, 3:]), T_base_ee[:, :3, :3])
    return jax.vmap(make_pose)(R, T_base_ee[:, :3, 3] + delta[:, :3])


def _B(T_base_ee, eye_in_hand: Bool[Array, ""]):
    return jnp.where(eye_in_hand, jax.vmap(pose_inverse)(T_base_ee), T_base_ee)


def _transforms(params: HandEyeParams, ref: HandEyeReference):
    X = matmul(ref.X0, jax.vmap(se3_exp)(params.cam_robot))
    Y = ref.Y0 @ se3_exp(params.robot_board)
    return X, Y


def predicted_board_poses(params: HandEyeParams, ref: HandEyeReference, data: HandEyeData):
    """$T^{cam_c}_{board}(f) = X_c B_f Y$, `(cameras, frames, 4, 4)`."""
    X, Y = _transforms(params, ref)
    B = _B(_corrected_robot(data.T_base_ee, params.robot), data.eye_in_hand)
    return matmul(matmul(X[:, None], B[None]), Y)


def _observation_residuals(params, ref, data) -> Float[Array, "cameras frames k"]:
    """Whitened observation residuals grouped per (camera, frame), zero where inactive."""
    A_pred = predicted_board_poses(params, ref, data)
    if isinstance(data, HandEyePixels):
        R, t = A_pred[..., :3, :3], A_pred[..., :3, 3]
        p = jnp.einsum("cfij,pj->cfpi", R, data.board_points) + t[:, :, None, :]
        z = p[..., 2:]
        z = jnp.where(z > 1e-9, z, 1e-9)
        xy = p[..., :2] / z
        K = data.K[:, None, None]
        uv = jnp.stack(
            [
                K[..., 0, 0] * xy[..., 0] + K[..., 0, 1] * xy[..., 1] + K[..., 0, 2],
                K[..., 1, 1] * xy[..., 1] + K[..., 1, 2],
            ],
            axis=-1,
        )
        m = data.mask & ref.active[..., None]
        meas = jnp.where(m[..., None], data.pixels, 0.0)
        e = jnp.where(m[..., None], (uv - meas) / data.sigma_px, 0.0)
        return e.reshape(e.shape[:2] + (-1,))
    e = _pose_errors(A_pred, ref, data)
    if ref.whiten is None:
        return e / data.sigma
    C, F = e.shape[:2]
    w = jnp.einsum("fij,fj->fi", ref.whiten, jnp.swapaxes(e, 0, 1).reshape(F, 6 * C))
    return jnp.swapaxes(w.reshape(F, C, 6), 0, 1)


def _pose_errors(A_pred, ref, data: "HandEyePoses") -> Float[Array, "cameras frames 6"]:
    """Unwhitened pose errors (translation m, camera-frame rotation vector rad), zero where inactive."""
    m = data.mask & ref.active
    A = jnp.where(m[..., None, None], data.T_cam_board, jnp.eye(4))
    e_t = A_pred[..., :3, 3] - A[..., :3, 3]
    e_r = so3_log(matmul(A_pred[..., :3, :3], jnp.swapaxes(A[..., :3, :3], -1, -2)))
    return jnp.where(m[..., None], jnp.concatenate([e_t, e_r], axis=-1), 0.0)


def _robot_jacobian(params, ref, data: "HandEyePoses"):
    """Noisy robot poses marginalised out of the pose errors (the Schur complement, exact to first order).

    A robot correction $\\delta_f$ (as in `_corrected_robot`) moves frame $f$'s
    stacked pose errors by $J_f \\delta_f$; minimising over $\\delta_f$ with its
    prior $\\mathcal N(0, \\Sigma_r)$ leaves $e_f^T S_f^{-1} e_f$ with
    $S_f = \\Sigma_A + J_f \\Sigma_r J_f^T$ (Gauss-Markov). Returns `(J_f, S_f)`
    at `params`; the per-frame blocks come from six forward-mode derivatives,
    one correction direction shared by all frames.
    """
    C, F = data.mask.shape
    X, Y = _transforms(params, ref)

    def errors(d):
        T = _corrected_robot(data.T_base_ee, jnp.broadcast_to(d, (F, 6)))
        return _pose_errors(matmul(matmul(X[:, None], _B(T, data.eye_in_hand)[None]), Y), ref, data)

    J = jax.jacfwd(errors)(jnp.zeros(6))  # (C, F, 6, 6): d e_cf / d delta_f
    J = jnp.swapaxes(J, 0, 1).reshape(F, 6 * C, 6)
    S = jnp.einsum("fia,a,fja->fij", J, data.robot_sigma**2, J) + jnp.diag(jnp.tile(data.sigma**2, C))
    return J, S


def _robot_whitening(params, ref, data: "HandEyePoses") -> Float[Array, "frames n n"]:
    """$L_f^{-1}$ with $L_f L_f^T = S_f$ (see `_robot_jacobian`), so $S_f^{-1} = L_f^{-T} L_f^{-1}$."""
    _, S = _robot_jacobian(params, ref, data)
    L = jnp.linalg.cholesky(S)
    eye = jnp.broadcast_to(jnp.eye(S.shape[-1]), S.shape)
    return jax.scipy.linalg.solve_triangular(L, eye, lower=True)


def _with_whitening(params, ref, data):
    if isinstance(data, HandEyePoses) and data.robot_sigma is not None:
        whiten = jax.lax.stop_gradient(_robot_whitening(params, ref, data))
        return HandEyeReference(X0=ref.X0, Y0=ref.Y0, active=ref.active, whiten=whiten)
    return ref


def _robot_correction(params, ref, data: "HandEyePoses") -> Float[Array, "frames 6"]:
    """The MAP robot corrections given the fit, $\\hat\\delta_f = -\\Sigma_r J_f^T S_f^{-1} e_f$,
    with `ref.whiten` the whitening at `params` (no new factorisation)."""
    J, _ = _robot_jacobian(params, ref, data)
    e = _pose_errors(predicted_board_poses(params, ref, data), ref, data)
    C, F = e.shape[:2]
    e = jnp.swapaxes(e, 0, 1).reshape(F, 6 * C)
    S_inv_e = jnp.einsum("fki,fkj,fj->fi", ref.whiten, ref.whiten, e)
    return -data.robot_sigma * jnp.einsum("fia,fi->fa", J, S_inv_e)


def _prior_residuals(params, data):
    return None if params.robot is None else params.robot / data.robot_sigma


def hand_eye_residuals(params: HandEyeParams, args: tuple[HandEyeReference, HandEyeData]):
    """Whitened residuals: observations `(cameras, frames, k)` and the robot prior `(frames, 6)` or None.

    Pixels: $(\\hat u - u)/\\sigma_{px}$ per corner; poses: the translation
    error (m) and the rotation vector of $\\hat R R^T$ (rad) over their sigmas.
    """
    ref, data = args
    return _observation_residuals(params, ref, data), _prior_residuals(params, data)


def _group_sizes(ref, data) -> Float[Array, "cameras frames"]:
    if isinstance(data, HandEyePixels):
        return 2.0 * jnp.sum(data.mask & ref.active[..., None], axis=-1)
    return 6.0 * (data.mask & ref.active)


def _robust_residuals(params, args):
    """Cauchy loss per (camera, frame) group where `robust`, as residuals: $r\\sqrt{\\rho(s)/s}$.

    With $x = s/n$ the group's mean square and $b$ the loss scale,
    $\\rho = n b^2 \\log(1 + x/b^2)$, so LM on these residuals minimises the
    Cauchy cost. A group far off (a wrong robot pose, a misdetection) gets
    weight $\\approx 1/(1 + x/b^2)$ in the gradient. Where not `robust`, the
    plain whitened residuals (`hand_eye_residuals`).
    """
    ref, data, loss_scale, robust = args
    r, prior = hand_eye_residuals(params, (ref, data))
    n = jnp.maximum(_group_sizes(ref, data), 1.0)
    x = jnp.sum(r**2, axis=-1) / n
    b2 = loss_scale**2
    small = x < 1e-12
    safe_x = jnp.where(small, 1.0, x)
    w = jnp.where(small, 1.0 - x / (2.0 * b2), jnp.sqrt(b2 * jnp.log1p(safe_x / b2) / safe_x))
    return r * jnp.where(robust, w, 1.0)[..., None], prior


# --------------------------------------------------------------------------- closed-form initialisation


def _plane_frame(points: Float[Array, "points 3"]) -> tuple[Float[Array, "4 4"], Float[Array, "points 2"]]:
    """`T_board_plane` (plane frame: z along the normal) and the points' plane coordinates."""
    c = jnp.mean(points, axis=0)
    _, V = jnp.linalg.eigh((points - c).T @ (points - c))
    e1, e2 = V[:, 2], V[:, 1]
    R = jnp.stack([e1, e2, jnp.cross(e1, e2)], axis=1)
    ab = (points - c) @ R[:, :2]
    return make_pose(R, c), ab


def _homography_pose(uv, w, K, ab, T_board_plane):
    """`T_cam_board` from one view by a normalised DLT homography and Zhang's decomposition."""
    # Normalised image coordinates (K is upper triangular: no factorisation needed).
    y = (uv[:, 1] - K[1, 2]) / K[1, 1]
    xy = jnp.stack([(uv[:, 0] - K[0, 2] - K[0, 1] * y) / K[0, 0], y], axis=1)
    wsum = jnp.maximum(jnp.sum(w), 1.0)
    mean_xy = jnp.sum(xy * w[:, None], 0) / wsum
    s_xy = jnp.sqrt(2.0) / jnp.maximum(jnp.sqrt(jnp.sum(jnp.sum((xy - mean_xy) ** 2, -1) * w) / wsum), 1e-12)
    mean_ab = jnp.sum(ab * w[:, None], 0) / wsum
    s_ab = jnp.sqrt(2.0) / jnp.maximum(jnp.sqrt(jnp.sum(jnp.sum((ab - mean_ab) ** 2, -1) * w) / wsum), 1e-12)
    x_n, a_n = (xy - mean_xy) * s_xy, (ab - mean_ab) * s_ab
    one, zero = jnp.ones_like(a_n[:, :1]), jnp.zeros((a_n.shape[0], 3))
    a1 = jnp.concatenate([a_n, one], axis=1)
    rows = (
        jnp.concatenate(
            [
                jnp.concatenate([a1, zero, -x_n[:, :1] * a1], axis=1),
                jnp.concatenate([zero, a1, -x_n[:, 1:] * a1], axis=1),
            ],
            axis=0,
        )
        * jnp.concatenate([w, w])[:, None]
    )
    _, V = jnp.linalg.eigh(rows.T @ rows)
    Hn = V[:, 0].reshape(3, 3)
    T_img_inv = jnp.array([[1.0 / s_xy, 0.0, mean_xy[0]], [0.0, 1.0 / s_xy, mean_xy[1]], [0.0, 0.0, 1.0]])
    T_pl = jnp.array([[s_ab, 0.0, -s_ab * mean_ab[0]], [0.0, s_ab, -s_ab * mean_ab[1]], [0.0, 0.0, 1.0]])
    H = T_img_inv @ Hn @ T_pl
    lam = 2.0 / (jnp.linalg.norm(H[:, 0]) + jnp.linalg.norm(H[:, 1]))
    lam = jnp.where(H[2, 2] < 0, -lam, lam)  # the board is in front of the camera
    r1, r2, t = lam * H[:, 0], lam * H[:, 1], lam * H[:, 2]
    R = nearest_rotation(jnp.stack([r1, r2, jnp.cross(r1, r2)], axis=1))
    return make_pose(R, t) @ pose_inverse(T_board_plane)


def board_poses_from_pixels(
    data: HandEyePixels,
) -> tuple[Float[Array, "cameras frames 4 4"], Bool[Array, "cameras frames"]]:
    """Per-view board poses by homography (closed form), and which views had enough corners."""
    T_bp, ab = _plane_frame(data.board_points)
    w = data.mask.astype(jnp.float64)
    uv = jnp.where(data.mask[..., None], data.pixels, 0.0)
    pose = jax.vmap(
        lambda uv_c, w_c, K: jax.vmap(lambda u, ww: _homography_pose(u, ww, K, ab, T_bp))(uv_c, w_c)
    )
    A = pose(uv, w, data.K)
    ok = jnp.sum(data.mask, axis=-1) >= MIN_POINTS_PER_VIEW
    return jnp.where(ok[..., None, None], A, jnp.eye(4)), ok


def solve_axzb(
    A: Float[Array, "cameras frames 4 4"],
    B: Float[Array, "frames 4 4"],
    weight: Float[Array, "cameras frames"],
) -> tuple[Float[Array, "cameras 4 4"], Float[Array, "4 4"]]:
    """Closed form of $A_{cf} = X_c B_f Y$ for every camera's $X_c$ and the shared $Y$.

    Rotations (Shah's Kronecker method, several cameras sharing $W = Y^{-1}$):
    $R_{X_c} = R_{A} R_W R_B^T$ is linear in $R_W$, $\\mathrm{vec} R_{X_c} =
    M_{cf}\\,\\mathrm{vec} R_W$ with orthogonal $M_{cf}$; minimising
    $\\sum \\|M_{cf} w - x_c\\|^2$ at fixed $\\|w\\|$ gives $w$ = the top
    eigenvector of $\\sum_c n_c S_c^T S_c$ ($S_c$ the weighted mean of
    $M_{cf}$) and $x_c = S_c w$, both projected on SO(3). Translations:
    $R_A t_W - t_{X_c} = R_{X_c} t_B - t_A$ by least squares. Exact on
    noise-free data with rotations about two non-parallel axes.
    """
    C, F = weight.shape
    RA, RB = A[..., :3, :3], B[:, :3, :3]
    M = jnp.einsum("cfik,fjl->cfijkl", RA, RB).reshape(C, F, 9, 9)
    n_c = jnp.sum(weight, axis=1)
    S = jnp.einsum("cf,cfab->cab", weight, M) / jnp.maximum(n_c, 1e-300)[:, None, None]
    G = jnp.einsum("c,cba,cbd->ad", n_c, S, S)
    _, V = jnp.linalg.eigh(G)
    w = V[:, -1]
    w = jnp.where(jnp.linalg.det(w.reshape(3, 3)) < 0, -w, w)
    # R_W and every R_X in one batched SVD (see _linalg).
    R = nearest_rotation(jnp.concatenate([w[None], S @ w]).reshape(1 + C, 3, 3))
    R_W, R_X = R[0], R[1:]
    # Translations: unknowns (t_W, t_X1..t_XC).
    sel = jnp.eye(C)[:, None, :, None, None] * jnp.eye(3)  # (C, 1, C, 3, 3)
    J = jnp.concatenate(
        [RA[:, :, None], -jnp.broadcast_to(sel, (C, F, C, 3, 3))], axis=2
    )  # (C, F, 1 + C, 3, 3): blocks [R_A, -E_c]
    J = jnp.moveaxis(J, 2, 3).reshape(C, F, 3, 3 * (1 + C))
    b = jnp.einsum("cij,fj->cfi", R_X, B[:, :3, 3]) - A[..., :3, 3]
    Jw = J * jnp.sqrt(weight)[..., None, None]
    bw = b * jnp.sqrt(weight)[..., None]
    Jf, bf = Jw.reshape(-1, 3 * (1 + C)), bw.reshape(-1)
    z = jnp.linalg.solve(Jf.T @ Jf + 1e-12 * jnp.eye(3 * (1 + C)), Jf.T @ bf)
    W = make_pose(R_W, z[:3])
    X = jax.vmap(make_pose)(R_X, z[3:].reshape(C, 3))
    return X, pose_inverse(W)


def initialise_hand_eye(data: HandEyeData) -> tuple[Float[Array, "cameras 4 4"], Float[Array, "4 4"]]:
    """Closed-form start `(X, Y)`: homography board poses (pixels) then `solve_axzb`."""
    if isinstance(data, HandEyePixels):
        A, ok = board_poses_from_pixels(data)
    else:
        ok = data.mask
        A = jnp.where(ok[..., None, None], data.T_cam_board, jnp.eye(4))
    return solve_axzb(A, _B(data.T_base_ee, data.eye_in_hand), ok.astype(jnp.float64))


# --------------------------------------------------------------------------- solve


class HandEyeResult(eqx.Module):
    """A hand-eye calibration.

    **Fields:**
    - `T_cam_robot`: per camera, `(cameras, 4, 4)`: $T_{cam\\_base}$ (eye-to-hand)
      or $T_{cam\\_ee}$ (eye-in-hand); `T_robot_cam` its inverse
      ($T_{base\\_cam}$ or $T_{ee\\_cam}$, the camera's pose on the robot).
    - `T_robot_board`: $T_{ee\\_board}$ (eye-to-hand) or $T_{base\\_board}$ (eye-in-hand).
    - `std_cam_robot`, `std_robot_cam` `(cameras, 6)`, `std_robot_board` `(6,)`:
      standard deviations of (translation (m), rotation vector (rad)) of each
      transform, both in its parent frame: $\\delta t = \\hat t - t$ and
      $\\hat R = \\exp(\\delta w) R$. From $(J^T J)^{-1}$ of the whitened
      residuals (robot corrections marginalised), scaled by the residual
      variance when `scale_covariance`.
    - `T_base_ee`: the robot poses used (corrected when `robot_sigma` was given).
    - `residual_rms`: RMS of the whitened observation residuals over the kept
      groups (about 1 when the noise model is honest); `pixel_rms` (px, NaN for
      pose data).
    - `group_rms`: whitened RMS per (camera, frame) `(cameras, frames)`, NaN where unobserved.
    - `rejected`: (camera, frame) groups rejected as outliers; `num_rejected`.
    - `result`, `num_steps`: optimistix's own result code and step count (final solve).
    """

    T_cam_robot: Float[Array, "cameras 4 4"]
    T_robot_cam: Float[Array, "cameras 4 4"]
    T_robot_board: Float[Array, "4 4"]
    std_cam_robot: Float[Array, "cameras 6"]
    std_robot_cam: Float[Array, "cameras 6"]
    std_robot_board: Float[Array, "6"]
    cov: Float[Array, "n n"]
    T_base_ee: Float[Array, "frames 4 4"]
    residual_rms: Float[Array, ""]
    pixel_rms: Float[Array, ""]
    group_rms: Float[Array, "cameras frames"]
    rejected: Bool[Array, "cameras frames"]
    num_rejected: Int[Array, ""]
    result: optx.RESULTS
    num_steps: Int[Array, ""]
    eye_in_hand: Bool[Array, ""]

    def _named(self, want_eye_in_hand: bool, name: str, value):
        # Read outside jit (the flag may be batched under vmap: all trials share it).
        eye_in_hand = bool(np.all(np.asarray(self.eye_in_hand)))
        if eye_in_hand != want_eye_in_hand:
            kind = "eye-in-hand" if eye_in_hand else "eye-to-hand"
            raise AttributeError(f"{name} is not defined for an {kind} calibration")
        return value

    @property
    def T_cam_base(self) -> Float[Array, "cameras 4 4"]:
        """Eye-to-hand: base -> camera."""
        return self._named(False, "T_cam_base", self.T_cam_robot)

    @property
    def T_base_cam(self) -> Float[Array, "cameras 4 4"]:
        """Eye-to-hand: the camera's pose in the base frame."""
        return self._named(False, "T_base_cam", self.T_robot_cam)

    @property
    def T_ee_board(self) -> Float[Array, "4 4"]:
        """Eye-to-hand: the board's pose on the end effector."""
        return self._named(False, "T_ee_board", self.T_robot_board)

    @property
    def T_cam_ee(self) -> Float[Array, "cameras 4 4"]:
        """Eye-in-hand: end effector -> camera."""
        return self._named(True, "T_cam_ee", self.T_cam_robot)

    @property
    def T_ee_cam(self) -> Float[Array, "cameras 4 4"]:
        """Eye-in-hand: the camera's pose on the end effector."""
        return self._named(True, "T_ee_cam", self.T_robot_cam)

    @property
    def T_base_board(self) -> Float[Array, "4 4"]:
        """Eye-in-hand: the board's pose in the base frame."""
        return self._named(True, "T_base_board", self.T_robot_board)

    def rejected_frames(self) -> np.ndarray:
        """Indices of the frames rejected in any camera (NumPy; call outside jit)."""
        return np.flatnonzero(np.asarray(self.rejected).any(axis=0))


def _pose_error(T, T_hat):
    return jnp.concatenate([T[:3, 3] - T_hat[:3, 3], so3_log(T[:3, :3] @ T_hat[:3, :3].T)])


def _lm(fn, params0, args, rtol, atol, max_steps, throw):
    solver = optx.LevenbergMarquardt(rtol=rtol, atol=atol)
    return optx.least_squares(fn, solver, params0, args, max_steps=max_steps, throw=throw)


def calibrate_hand_eye(
    data: HandEyeData,
    *,
    reject_outliers: bool | Bool[Array, ""] = True,
    outlier_threshold: float = 3.0,
    min_outlier_scale: float = 0.1,
    loss_scale: float = 2.0,
    rtol: float = 1e-8,
    atol: float = 1e-6,
    max_steps: int = 50,
    throw: bool = False,
    scale_covariance: bool = True,
) -> HandEyeResult:
    """Hand-eye calibration (eye-to-hand or eye-in-hand, one or more cameras); pure, jittable, vmappable.

    Minimises $\\sum_{c,f} \\|r_{cf}\\|^2 + \\sum_f \\|\\delta_f/\\sigma_{robot}\\|^2$
    over $X_c$, $Y$ (and robot corrections $\\delta_f$), with $r_{cf}$ the
    whitened reprojection errors of camera $c$ at robot pose $f$ (or the
    whitened pose error for `HandEyePoses`). See the module docstring for the
    pipeline. Validate inputs first (`make_hand_eye_*` do).

    **Arguments:**
    - `data`: `HandEyePixels` or `HandEyePoses`.
    - `reject_outliers`: solve with a Cauchy loss first, reject (camera, frame)
      groups whose whitened RMS exceeds `outlier_threshold` times
      max(median group RMS, `min_outlier_scale`), then re-solve without them.
    - `loss_scale`: Cauchy scale $b$ (whitened units) of the robust solve.
    - `rtol`, `atol`, `max_steps`, `throw`: optimistix's (tolerances on the
      tangent deltas in m/rad and on the whitened residuals).
    - `scale_covariance`: multiply the covariance by $\\|r\\|^2/(m - n)$.

    **Returns:** a `HandEyeResult`.
    """
    X0, Y0 = initialise_hand_eye(data)
    C, F = data.mask.shape[:2]
    params0 = HandEyeParams(
        cam_robot=jnp.zeros((C, 6)),
        robot_board=jnp.zeros(6),
        # Pose data: noisy robot poses are marginalised (`_robot_jacobian`); pixels: solved for.
        robot=None if data.robot_sigma is None or isinstance(data, HandEyePoses) else jnp.zeros((F, 6)),
    )
    observed = jnp.any(data.mask, axis=-1) if isinstance(data, HandEyePixels) else data.mask

    def stage(carry, robust):
        # One Levenberg-Marquardt, traced once and run per stage: robust (Cauchy)
        # then plain on the groups the robust stage kept.
        params, active = carry
        ref = _with_whitening(params, HandEyeReference(X0=X0, Y0=Y0, active=active), data)
        sol = _lm(_robust_residuals, params, (ref, data, loss_scale, robust), rtol, atol, max_steps, False)
        rms = _group_rms(sol.value, ref, data)
        scale = jnp.maximum(jnp.nanmedian(rms), min_outlier_scale)
        reject = robust & active & (rms > outlier_threshold * scale)
        return (sol.value, active & ~reject), (sol.result, sol.stats["num_steps"])

    # `reject_outliers` is traced, so both settings share one compiled solver; when False
    # the first stage is plain too and the second starts from its optimum.
    stages = jnp.stack([jnp.asarray(reject_outliers, bool), jnp.asarray(False)])
    (params, active), (results, steps) = jax.lax.scan(stage, (params0, observed), stages)
    result, num_steps = jax.tree.map(lambda x: x[-1], results), steps[-1]
    if throw:
        params = result.error_if(params, result != optx.RESULTS.successful)
    ref = _with_whitening(params, HandEyeReference(X0=X0, Y0=Y0, active=active), data)
    return _summarise(params, ref, data, observed & ~active, result, num_steps, scale_covariance)


def _group_rms(params, ref, data) -> Float[Array, "cameras frames"]:
    r, _ = hand_eye_residuals(params, (ref, data))
    n = _group_sizes(ref, data)
    return jnp.where(n > 0, jnp.sqrt(jnp.sum(r**2, axis=-1) / jnp.maximum(n, 1.0)), jnp.nan)


def _summarise(params, ref, data, rejected, result, num_steps, scale_covariance) -> HandEyeResult:
    flat, unravel = ravel_pytree(params)

    def flat_res(x):
        r, prior = hand_eye_residuals(unravel(x), (ref, data))
        return jnp.concatenate([r.reshape(-1)] + ([] if prior is None else [prior.reshape(-1)]))

    J = jax.jacfwd(flat_res)(flat)
    r_all = flat_res(flat)
    cov = jnp.linalg.pinv(J.T @ J, hermitian=True)
    n_obs = jnp.sum(_group_sizes(ref, data))
    n_prior = 0 if params.robot is None else params.robot.size
    dof = jnp.maximum(n_obs + n_prior - flat.size, 1.0)
    if scale_covariance:
        cov = cov * (jnp.sum(r_all**2) / dof)

    X, Y = _transforms(params, ref)
    Xi = jax.vmap(pose_inverse)(X)

    def errors(x):
        Xx, Yx = _transforms(unravel(x), ref)
        Xix = jax.vmap(pose_inverse)(Xx)
        return jnp.concatenate(
            [
                jax.vmap(_pose_error)(Xx, X).reshape(-1),
                jax.vmap(_pose_error)(Xix, Xi).reshape(-1),
                _pose_error(Yx, Y),
            ]
        )

    G = jax.jacfwd(errors)(flat)
    std = jnp.sqrt(jnp.maximum(jnp.einsum("ia,ab,ib->i", G, cov, G), 0.0))
    C = X.shape[0]
    r_obs, _ = hand_eye_residuals(params, (ref, data))
    ssr_obs = jnp.sum(r_obs**2)
    is_px = isinstance(data, HandEyePixels)
    return HandEyeResult(
        T_cam_robot=X,
        T_robot_cam=Xi,
        T_robot_board=Y,
        std_cam_robot=std[: 6 * C].reshape(C, 6),
        std_robot_cam=std[6 * C : 12 * C].reshape(C, 6),
        std_robot_board=std[12 * C :],
        cov=cov,
        T_base_ee=_corrected_robot(
            data.T_base_ee,
            _robot_correction(params, ref, data) if ref.whiten is not None else params.robot,
        ),
        residual_rms=jnp.sqrt(ssr_obs / jnp.maximum(n_obs, 1.0)),
        pixel_rms=jnp.sqrt(ssr_obs / jnp.maximum(n_obs, 1.0)) * data.sigma_px
        if is_px
        else jnp.asarray(jnp.nan),
        group_rms=_group_rms(
            params,
            # Its own whitening, factorised after the covariance's (see _linalg).
            _with_whitening(
                after(params, cov), HandEyeReference(ref.X0, ref.Y0, ref.active | rejected), data
            ),
            data,
        ),
        rejected=rejected,
        num_rejected=jnp.sum(rejected),
        result=result,
        num_steps=num_steps,
        eye_in_hand=data.eye_in_hand,
    )


# --------------------------------------------------------------------------- TCP touch (seed 5)


class TouchData(eqx.Module):
    """Board points measured by the camera and touched by the robot's tool centre point.

    For point $k$: the camera measures $p_k$ (camera frame, m) while the end
    effector is at $C_k$ (eye-in-hand; identity for a fixed camera), and the
    TCP touches it with the end effector at $D_k$. Both expressions of the
    point in the base frame agree:

    $$C_k X p_k = D_k\\, t_{tcp},$$

    $X = T_{base\\_cam}$ (eye-to-hand) or $T_{ee\\_cam}$ (eye-in-hand).

    **Fields:**
    - `points_cam` `(points, 3)` (m); `T_base_ee_touch` `(points, 4, 4)`.
    - `T_base_ee_camera` `(points, 4, 4)` for eye-in-hand, None for eye-to-hand.
    - `tcp`: the TCP offset in the end-effector frame (m) if known, else None (solved).
    - `mask` `(points,)`; `sigma`: the 3D point noise (m), touch and camera together.
    """

    points_cam: Float[Array, "points 3"]
    T_base_ee_touch: Float[Array, "points 4 4"]
    T_base_ee_camera: Float[Array, "points 4 4"] | None
    tcp: Float[Array, "3"] | None
    mask: Bool[Array, " points"]
    sigma: Float[Array, ""]


def make_touch_data(
    points_cam,
    T_base_ee_touch,
    T_base_ee_camera=None,
    tcp=None,
    mask=None,
    *,
    sigma: float = 1e-4,
    validate: bool = True,
) -> TouchData:
    """Build `TouchData` (see its fields); a single 4x4 `T_base_ee_camera` is used for every point."""
    P = np.asarray(points_cam, dtype=np.float64)
    D = np.asarray(T_base_ee_touch, dtype=np.float64)
    Cm = None
    if T_base_ee_camera is not None:
        Cm = np.asarray(T_base_ee_camera, dtype=np.float64)
        if Cm.ndim == 2:
            Cm = np.broadcast_to(Cm, (P.shape[0], 4, 4))
    mask = np.ones(P.shape[0], bool) if mask is None else np.asarray(mask, bool)
    data = TouchData(
        points_cam=jnp.asarray(P),
        T_base_ee_touch=jnp.asarray(D),
        T_base_ee_camera=None if Cm is None else jnp.asarray(Cm),
        tcp=None if tcp is None else jnp.asarray(np.asarray(tcp, dtype=np.float64)),
        mask=jnp.asarray(mask),
        sigma=jnp.asarray(sigma, jnp.float64),
    )
    if validate:
        validate_touch(data)
    return data


def validate_touch(data: TouchData) -> None:
    """Raise a `ValueError` naming the problem if `data` cannot give a TCP-touch calibration.

    Shapes and lengths, finite values, rotations, at least 3 non-collinear
    points (5 when the TCP offset is unknown), and, when it is unknown, touch
    orientations about two non-parallel axes (else the offset is confounded
    with the camera translation).
    """
    P, D, mask = np.asarray(data.points_cam), np.asarray(data.T_base_ee_touch), np.asarray(data.mask)
    if P.ndim != 2 or P.shape[1] != 3:
        raise ShapeError(f"points_cam must have shape (points, 3), got {P.shape}")
    N = P.shape[0]
    if D.shape != (N, 4, 4):
        raise LengthMismatchError(
            f"{N} camera points but T_base_ee_touch has shape {D.shape} (lengths must match)"
        )
    if data.T_base_ee_camera is not None and np.shape(data.T_base_ee_camera) != (N, 4, 4):
        raise LengthMismatchError(
            f"{N} camera points but T_base_ee_camera has shape {np.shape(data.T_base_ee_camera)} (lengths must match)"
        )
    if mask.shape != (N,):
        raise ShapeError(f"mask has shape {mask.shape}, expected {(N,)}")
    if data.tcp is not None and np.shape(data.tcp) != (3,):
        raise ShapeError(f"tcp must have shape (3,), got {np.shape(data.tcp)}")
    bad = mask & ~np.all(np.isfinite(P), axis=-1)
    if bad.any():
        raise NonFiniteError(f"points_cam: non-finite point {np.flatnonzero(bad)[0]}")
    check_rotations(D[mask], "T_base_ee_touch")
    if data.T_base_ee_camera is not None:
        check_rotations(np.asarray(data.T_base_ee_camera)[mask], "T_base_ee_camera")
    need = 3 if data.tcp is not None else 5
    n = int(mask.sum())
    if n < need:
        raise TooFewPosesError(f"only {n} touched points, at least {need} are needed")
    Pm = P[mask] - P[mask].mean(0)
    sv = np.linalg.svd(Pm, compute_uv=False)
    if sv[1] < 1e-6 * max(sv[0], 1e-12):
        raise DegenerateMotionError(
            "points_cam: the touched points are collinear; the camera rotation is not identifiable"
        )
    if data.tcp is None:
        check_motion_diversity(
            D[mask], "T_base_ee_touch (an unknown TCP offset needs varied touch orientations)"
        )


class TouchParams(eqx.Module):
    robot_cam: Float[Array, "6"]
    tcp: Float[Array, "3"] | None


class TouchResult(eqx.Module):
    """A TCP-touch hand-eye calibration.

    **Fields:**
    - `T_robot_cam`: $T_{base\\_cam}$ (eye-to-hand) or $T_{ee\\_cam}$ (eye-in-hand).
    - `tcp`: the TCP offset in the end-effector frame (m), solved or as given.
    - `std_robot_cam` `(6,)` (translation m, rotation rad, parent frame as in
      `HandEyeResult`), `std_tcp` `(3,)` (zero when given).
    - `rms`: RMS distance between the two expressions of each point (m).
    - `result`, `num_steps`: optimistix's.
    """

    T_robot_cam: Float[Array, "4 4"]
    tcp: Float[Array, "3"]
    std_robot_cam: Float[Array, "6"]
    std_tcp: Float[Array, "3"]
    rms: Float[Array, ""]
    result: optx.RESULTS
    num_steps: Int[Array, ""]
    eye_in_hand: bool = eqx.field(static=True)

    @property
    def T_base_cam(self) -> Float[Array, "4 4"]:
        if self.eye_in_hand:
            raise AttributeError("T_base_cam is not defined for an eye-in-hand calibration")
        return self.T_robot_cam

    @property
    def T_ee_cam(self) -> Float[Array, "4 4"]:
        if not self.eye_in_hand:
            raise AttributeError("T_ee_cam is not defined for an eye-to-hand calibration")
        return self.T_robot_cam


def _touch_C(data: TouchData):
    if data.T_base_ee_camera is None:
        return jnp.broadcast_to(jnp.eye(4), data.T_base_ee_touch.shape)
    return data.T_base_ee_camera


def initialise_touch(data: TouchData) -> tuple[Float[Array, "4 4"], Float[Array, "3"]]:
    """Closed-form `(X, tcp)`: linear least squares in the plane frame of the points.

    With $p_k = c + U(a_k, b_k, d_k)$ ($U$ the points' principal axes), the
    unknowns $g_1, g_2 = R_X U e_{1,2}$, $s = R_X c + t_X$ and $t_{tcp}$ enter
    $R_{C_k}(a_k g_1 + b_k g_2 + s) - R_{D_k} t_{tcp} = t_{D_k} - t_{C_k}$
    linearly ($d_k$, zero for a planar board, is dropped). Then
    $R_X = \\mathrm{proj}[g_1, g_2, g_1 \\times g_2] U^T$, and $t_X$, $t_{tcp}$
    are re-solved at that rotation.
    """
    w = data.mask.astype(jnp.float64)
    P = jnp.where(data.mask[:, None], data.points_cam, 0.0)
    c = jnp.sum(P * w[:, None], 0) / jnp.maximum(jnp.sum(w), 1.0)
    _, V = jnp.linalg.eigh(((P - c) * w[:, None]).T @ (P - c))
    U = jnp.stack([V[:, 2], V[:, 1], jnp.cross(V[:, 2], V[:, 1])], axis=1)
    ab = (P - c) @ U[:, :2]
    Cm, D = _touch_C(data), data.T_base_ee_touch
    RC, RD = Cm[:, :3, :3], D[:, :3, :3]
    known = data.tcp is not None
    rhs = D[:, :3, 3] - Cm[:, :3, 3]
    blocks = [RC * ab[:, :1, None], RC * ab[:, 1:, None], RC]
    if known:
        rhs = rhs + jnp.einsum("kij,j->ki", RD, data.tcp)
    else:
        blocks.append(-RD)
    A = jnp.concatenate(blocks, axis=2) * jnp.sqrt(w)[:, None, None]
    n = A.shape[2]
    A, b = A.reshape(-1, n), (rhs * jnp.sqrt(w)[:, None]).reshape(-1)
    z = jnp.linalg.solve(A.T @ A + 1e-12 * jnp.eye(n), A.T @ b)
    g1, g2 = z[0:3], z[3:6]
    R = nearest_rotation(jnp.stack([g1, g2, jnp.cross(g1, g2)], axis=1)) @ U.T
    # Translation (and tcp) at that rotation: R_C (R p + t) - R_D tcp = t_D - t_C.
    rhs2 = rhs - jnp.einsum("kij,jl,kl->ki", RC, R, P)
    blocks2 = [RC] if known else [RC, -RD]
    A2 = jnp.concatenate(blocks2, axis=2) * jnp.sqrt(w)[:, None, None]
    n2 = A2.shape[2]
    A2, b2 = A2.reshape(-1, n2), (rhs2 * jnp.sqrt(w)[:, None]).reshape(-1)
    z2 = jnp.linalg.solve(A2.T @ A2 + 1e-12 * jnp.eye(n2), A2.T @ b2)
    tcp = data.tcp if known else z2[3:6]
    return make_pose(R, z2[:3]), tcp


def touch_residuals(params: TouchParams, args) -> Float[Array, "points 3"]:
    """$(C_k X p_k - D_k t_{tcp})/\\sigma$ in the base frame, zero where masked."""
    X0, data = args
    X = X0 @ se3_exp(params.robot_cam)
    tcp = data.tcp if params.tcp is None else params.tcp
    P = jnp.where(data.mask[:, None], data.points_cam, 0.0)
    q_cam = jnp.einsum(
        "kij,kj->ki",
        _touch_C(data),
        jnp.concatenate([P @ X[:3, :3].T + X[:3, 3], jnp.ones_like(P[:, :1])], 1),
    )
    D = data.T_base_ee_touch
    q_tcp = jnp.einsum("kij,j->ki", D[:, :3, :3], tcp) + D[:, :3, 3]
    return jnp.where(data.mask[:, None], (q_cam[:, :3] - q_tcp) / data.sigma, 0.0)


def calibrate_touch(
    data: TouchData,
    *,
    rtol: float = 1e-8,
    atol: float = 1e-6,
    max_steps: int = 50,
    throw: bool = False,
    scale_covariance: bool = True,
) -> TouchResult:
    """TCP-touch hand-eye calibration (seed 5), eye-to-hand or eye-in-hand; pure and jittable.

    Closed-form start (`initialise_touch`), then Levenberg-Marquardt on
    `touch_residuals` over $X = X_0 \\exp(\\xi)$ and, when `data.tcp` is None,
    the TCP offset. Covariance from the Jacobian as in `calibrate_hand_eye`.
    """
    X0, tcp0 = initialise_touch(data)
    params0 = TouchParams(robot_cam=jnp.zeros(6), tcp=None if data.tcp is not None else tcp0)
    sol = _lm(touch_residuals, params0, (X0, data), rtol, atol, max_steps, throw)
    params = sol.value
    flat, unravel = ravel_pytree(params)
    J = jax.jacfwd(lambda x: touch_residuals(unravel(x), (X0, data)).reshape(-1))(flat)
    r = touch_residuals(params, (X0, data))
    cov = jnp.linalg.pinv(J.T @ J, hermitian=True)
    n_obs = 3.0 * jnp.sum(data.mask)
    if scale_covariance:
        cov = cov * (jnp.sum(r**2) / jnp.maximum(n_obs - flat.size, 1.0))
    X = X0 @ se3_exp(params.robot_cam)

    def errors(x):
        p = unravel(x)
        e = _pose_error(X0 @ se3_exp(p.robot_cam), X)
        return e if p.tcp is None else jnp.concatenate([e, p.tcp])

    G = jax.jacfwd(errors)(flat)
    std = jnp.sqrt(jnp.maximum(jnp.einsum("ia,ab,ib->i", G, cov, G), 0.0))
    return TouchResult(
        T_robot_cam=X,
        tcp=data.tcp if params.tcp is None else params.tcp,
        std_robot_cam=std[:6],
        std_tcp=jnp.zeros(3) if params.tcp is None else std[6:9],
        rms=jnp.sqrt(jnp.sum(r**2) / jnp.maximum(jnp.sum(data.mask), 1.0)) * data.sigma,
        result=sol.result,
        num_steps=sol.stats["num_steps"],
        eye_in_hand=data.T_base_ee_camera is not None,
    )
