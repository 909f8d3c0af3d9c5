"""The hand-eye model: parameters, predicted board poses, whitened and robust residuals.

Per robot pose $f$ the board's pose in camera $c$ is $A_{cf} = X_c B_f Y$
(see the package docstring). Every pose is optimised as a 6-vector tangent
delta about its closed-form start, $X = X_0 \\exp(\\xi)$, $\\xi = (v, w)$
(translation first, m and rad).
"""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from .._geometry import make_pose, matmul, matmul_unrolled, pose_inverse, se3_exp, so3_exp, so3_log
from .._linalg import after
from .data import HandEyeData, HandEyePixels, HandEyePoses


class HandEyeParams(eqx.Module):
    """Unknowns: tangent deltas of $X_c$, of $Y$ and (optionally) of every robot pose."""

    cam_robot: Float[Array, "cameras 6"]
    robot_board: Float[Array, "6"]
    robot: Float[Array, "frames 6"] | None


class HandEyeReference(eqx.Module):
    """Start of the parameterisation (closed form), the active mask and the pose-error whitening.

    `whiten` (pose data with per-frame covariances or noisy robot poses only):
    per frame, $L_f^{-1}$ with $L_f L_f^T = S_f$ the covariance of the frame's
    stacked pose errors (see `pose_error_covariance`), `(frames, 6 cameras,
    6 cameras)`; None otherwise.
    """

    X0: Float[Array, "cameras 4 4"]
    Y0: Float[Array, "4 4"]
    active: Bool[Array, "cameras frames"]
    whiten: Float[Array, "frames n n"] | None = None


def corrected_robot(T_base_ee, delta):
    """Robot poses with independent corrections: $R = \\exp(w) R_{meas}$, $t = t_{meas} + v$."""
    if delta is None:
        return T_base_ee
    R = matmul_unrolled(jax.vmap(so3_exp)(delta[:, 3:]), T_base_ee[:, :3, :3])
    return jax.vmap(make_pose)(R, T_base_ee[:, :3, 3] + delta[:, :3])


def robot_motion(T_base_ee, eye_in_hand: Bool[Array, ""]):
    return jnp.where(eye_in_hand, jax.vmap(pose_inverse)(T_base_ee), T_base_ee)


def transforms(params: HandEyeParams, ref: HandEyeReference):
    X = matmul(ref.X0, jax.vmap(se3_exp)(params.cam_robot))
    Y = ref.Y0 @ se3_exp(params.robot_board)
    return X, Y


# Nested jit, traced once per signature (see `jaxcal._arcmodel.arc_terms`).
@jax.jit
def predicted_board_poses(params: HandEyeParams, ref: HandEyeReference, data: HandEyeData):
    """$T^{cam_c}_{board}(f) = X_c B_f Y$, `(cameras, frames, 4, 4)`."""
    X, Y = transforms(params, ref)
    B = robot_motion(corrected_robot(data.T_base_ee, params.robot), data.eye_in_hand)
    # Unrolled: under the block solver's batched forward-mode products, `matmul`'s
    # broadcast-and-sum became one slow fused reduction (a quarter of a step).
    return matmul_unrolled(matmul_unrolled(X[:, None], B[None]), Y)


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


def _pose_errors(A_pred, ref, data: HandEyePoses) -> Float[Array, "cameras frames 6"]:
    """Unwhitened pose errors (translation m, camera-frame rotation vector rad), zero where inactive."""
    m = data.mask & ref.active
    A = jnp.where(m[..., None, None], data.T_cam_board, jnp.eye(4))
    e_t = A_pred[..., :3, 3] - A[..., :3, 3]
    e_r = so3_log(matmul(A_pred[..., :3, :3], jnp.swapaxes(A[..., :3, :3], -1, -2)))
    return jnp.where(m[..., None], jnp.concatenate([e_t, e_r], axis=-1), 0.0)


def board_covariance(data: HandEyePoses) -> Float[Array, "frames n n"]:
    """$\\Sigma_A$ per frame: the block diagonal of every camera's board-pose covariance,
    `(frames, 6 cameras, 6 cameras)`; from `data.cov` when given, else $\\mathrm{diag}(\\sigma^2)$."""
    C, F = data.mask.shape
    if data.cov is None:
        return jnp.broadcast_to(jnp.diag(jnp.tile(data.sigma**2, C)), (F, 6 * C, 6 * C))
    return jnp.einsum("cd,cfij->fcidj", jnp.eye(C), data.cov).reshape(F, 6 * C, 6 * C)


def robot_jacobian(params, ref, data: HandEyePoses) -> Float[Array, "frames n 6"]:
    """How a robot correction $\\delta_f$ (as in `corrected_robot`) moves frame $f$'s
    stacked pose errors, $J_f$ `(frames, 6 cameras, 6)`, at `params`: six
    forward-mode derivatives, one correction direction shared by all frames."""
    C, F = data.mask.shape
    X, Y = transforms(params, ref)

    def errors(d):
        T = corrected_robot(data.T_base_ee, jnp.broadcast_to(d, (F, 6)))
        return _pose_errors(matmul(matmul(X[:, None], robot_motion(T, data.eye_in_hand)[None]), Y), ref, data)

    J = jax.jacfwd(errors)(jnp.zeros(6))  # (C, F, 6, 6): d e_cf / d delta_f
    return jnp.swapaxes(J, 0, 1).reshape(F, 6 * C, 6)


def pose_error_covariance(params, ref, data: HandEyePoses) -> Float[Array, "frames n n"]:
    """$S_f$, the covariance of frame $f$'s stacked pose errors (the Schur complement, exact to first order).

    Noisy robot poses are marginalised: minimising over a correction
    $\\delta_f \\sim \\mathcal N(0, \\Sigma_r)$ leaves $e_f^T S_f^{-1} e_f$ with
    $S_f = \\Sigma_{A,f} + J_f \\Sigma_r J_f^T$ (Gauss-Markov; `robot_jacobian`),
    $\\Sigma_{A,f}$ from `board_covariance`. Exact robot poses: $S_f = \\Sigma_{A,f}$.
    """
    S = board_covariance(data)
    if data.robot_sigma is None:
        return S
    J = robot_jacobian(params, ref, data)
    return S + jnp.einsum("fia,a,fja->fij", J, data.robot_sigma**2, J)


def pose_whitening(params, ref, data: HandEyePoses) -> Float[Array, "frames n n"]:
    """$L_f^{-1}$ with $L_f L_f^T = S_f$ (see `pose_error_covariance`), so $S_f^{-1} = L_f^{-T} L_f^{-1}$."""
    # Ordered after whatever gave `params` and the start (see _linalg): with exact robot
    # poses S does not depend on them, and its factorisation could run beside theirs.
    S = after(pose_error_covariance(params, ref, data), params, ref.X0)
    L = jnp.linalg.cholesky(S)
    eye = jnp.broadcast_to(jnp.eye(S.shape[-1]), S.shape)
    return jax.scipy.linalg.solve_triangular(L, eye, lower=True)


def needs_whitening(data: HandEyeData) -> bool:
    """Pose data whose errors are correlated: per-frame covariances, or noisy robot poses."""
    return isinstance(data, HandEyePoses) and (data.robot_sigma is not None or data.cov is not None)


def with_whitening(params, ref, data):
    """`ref` with the pose-error whitening at `params` (`pose_whitening`) where `needs_whitening`."""
    if needs_whitening(data):
        whiten = jax.lax.stop_gradient(pose_whitening(params, ref, data))
        return HandEyeReference(X0=ref.X0, Y0=ref.Y0, active=ref.active, whiten=whiten)
    return ref


def robot_correction(params, ref, data: HandEyePoses) -> Float[Array, "frames 6"]:
    """The MAP robot corrections given the fit, $\\hat\\delta_f = -\\Sigma_r J_f^T S_f^{-1} e_f$,
    with `ref.whiten` the whitening at `params` (no new factorisation)."""
    J = robot_jacobian(params, ref, data)
    e = _pose_errors(predicted_board_poses(params, ref, data), ref, data)
    C, F = e.shape[:2]
    e = jnp.swapaxes(e, 0, 1).reshape(F, 6 * C)
    S_inv_e = jnp.einsum("fki,fkj,fj->fi", ref.whiten, ref.whiten, e)
    return -data.robot_sigma * jnp.einsum("fia,fi->fa", J, S_inv_e)


def _prior_residuals(params, data):
    return None if params.robot is None else params.robot / data.robot_sigma


# Nested jit, traced once per signature (see `jaxcal._arcmodel.arc_terms`).
@jax.jit
def hand_eye_residuals(params: HandEyeParams, args: tuple[HandEyeReference, HandEyeData]):
    """Whitened residuals: observations `(cameras, frames, k)` and the robot prior `(frames, 6)` or None.

    Pixels: $(\\hat u - u)/\\sigma_{px}$ per corner; poses: the translation
    error (m) and the rotation vector of $\\hat R R^T$ (rad) over their sigmas.
    """
    ref, data = args
    return _observation_residuals(params, ref, data), _prior_residuals(params, data)


def group_sizes(ref, data) -> Float[Array, "cameras frames"]:
    if isinstance(data, HandEyePixels):
        return 2.0 * jnp.sum(data.mask & ref.active[..., None], axis=-1)
    return 6.0 * (data.mask & ref.active)


# Nested jit, traced once per signature (see `jaxcal._arcmodel.arc_terms`).
@jax.jit
def robust_residuals(params, args):
    """Cauchy loss per (camera, frame) group where `robust`, as residuals: $r\\sqrt{\\rho(s)/s}$.

    With $x = s/n$ the group's mean square and $b$ the loss scale,
    $\\rho = n b^2 \\log(1 + x/b^2)$, so LM on these residuals minimises the
    Cauchy cost. A group far off (a wrong robot pose, a misdetection) gets
    weight $\\approx 1/(1 + x/b^2)$ in the gradient. Where not `robust`, the
    plain whitened residuals (`hand_eye_residuals`).
    """
    ref, data, loss_scale, robust = args
    r, prior = hand_eye_residuals(params, (ref, data))
    n = jnp.maximum(group_sizes(ref, data), 1.0)
    w = cauchy_weight(jnp.sum(r**2, axis=-1) / n, loss_scale**2)
    return r * jnp.where(robust, w, 1.0)[..., None], prior


def robust_factors(r, ref, data, loss_scale, robust):
    """`(w, c)` per (camera, frame) group of `r (cameras, frames, k)`: the Cauchy weight
    $w(x)$ of the group's mean square $x = \\|r\\|^2/n$ (`robust_residuals`) and
    $c = 2 w'(x)/n$, so that the weighted residuals $w r$ have the derivative
    $w\\,\\dot r + c\\,(r \\cdot \\dot r)\\, r$; `(1, 0)` where not `robust`."""
    n = jnp.maximum(group_sizes(ref, data), 1.0)
    w, dw = jax.jvp(
        lambda x: cauchy_weight(x, loss_scale**2), (jnp.sum(r**2, -1) / n,), (jnp.ones(r.shape[:2]),)
    )
    return jnp.where(robust, w, 1.0), jnp.where(robust, 2.0 * dw / n, 0.0)


def robust_weighting(r, dr, ref, data, loss_scale, robust):
    """The robust loss on grouped residuals `r (cameras, frames, k)` and their
    derivatives `dr (cameras, frames, k, n)`: $(w r,\\ w\\,\\dot r + c\\,
    (r \\cdot \\dot r)\\, r)$ (`robust_factors`)."""
    w, c = robust_factors(r, ref, data, loss_scale, robust)
    proj = jnp.sum(r[..., None] * dr, axis=-2)  # (cameras, frames, n)
    return r * w[..., None], w[..., None, None] * dr + c[..., None, None] * r[..., None] * proj[:, :, None, :]


def cauchy_weight(x, b2):
    """$\\sqrt{\\rho(s)/s} = \\sqrt{b^2\\log(1 + x/b^2)/x}$ of a group with mean square $x$
    (its series $1 - x/(2b^2)$ near zero)."""
    small = x < 1e-12
    safe_x = jnp.where(small, 1.0, x)
    return jnp.where(small, 1.0 - x / (2.0 * b2), jnp.sqrt(b2 * jnp.log1p(safe_x / b2) / safe_x))
