"""The pixel solve with noisy robot poses, by blocks (`jaxcal._schur`).

**Structure.** With `robot_sigma`, the pixel solve's unknowns are the global
$g = (\\xi_{X_1}, \\dots, \\xi_{X_C}, \\xi_Y)$ ($n_g = 6C + 6$) and one robot
correction $\\delta_f \\in \\mathbb{R}^6$ per frame. Frame $f$'s residuals,

$$r_f = \\big(r_{1f}, \\dots, r_{Cf},\\ \\delta_f/\\sigma_{robot}\\big),$$

every camera's whitened reprojection errors at pose $f$ (each group scaled by
its Cauchy weight in the robust stage, a function of that group's residuals
only) and the correction's prior, depend on $g$ and $\\delta_f$ alone: the
Jacobian is $[A_f \\mid C_f]$ per frame with $C_f$ block diagonal across
frames. `jaxcal._schur.block_least_squares` eliminates the $6 \\times 6$ blocks
$U_f = C_f^TC_f$ and solves the $n_g \\times n_g$ Schur complement: each
Levenberg-Marquardt step costs $O(F\\,m\\,(n_g + 6)^2 + n_g^3)$ where the dense
solve (`optx.LevenbergMarquardt`, a QR of the $Fm \\times (n_g + 6F)$
Jacobian) costs $O(F^3 m)$, and the Jacobian takes $n_g + 6$ forward-mode
products instead of $n_g + 6F$. The iteration is optimistix's (same damping,
acceptance and termination, `jaxcal._schur`), so both solvers return the same
optimum to round-off (`tests/test_handeye.py`).

**Covariance.** The summary needs all of $(J^TJ)^{-1}$ over
$(g, \\delta_1, \\dots, \\delta_F)$ (`HandEyeResult.cov`, the order of
`ravel_pytree(HandEyeParams)`), which `jaxcal._schur.full_covariance` builds
from the blocks with one $n_g \\times n_g$ decomposition, and the per-frame
gradients $J_f^Tr_f$ of the frame-robust covariance: frame $f$'s rows only
touch $g$ and $\\delta_f$, so its gradient is $(A_f^Tr_f, C_f^Tr_f)$ placed
at $g$ and at $\\delta_f$.
"""

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._lsq import LMOptions
from .._schur import block_least_squares, full_covariance, jacobian_by_jvp
from .model import (
    HandEyeParams,
    hand_eye_residuals,
    predicted_board_poses,
    robust_residuals,
    robust_weighting,
)


def split(params: HandEyeParams) -> tuple[Float[Array, " n_g"], Float[Array, "frames 6"]]:
    """$(g, l)$: the cameras' and the board's deltas, and the robot corrections."""
    return jnp.concatenate([params.cam_robot.reshape(-1), params.robot_board]), params.robot


def join(g: Float[Array, " n_g"], l: Float[Array, "frames 6"]) -> HandEyeParams:
    """The inverse of `split`."""
    C = (g.shape[0] - 6) // 6
    return HandEyeParams(cam_robot=g[: 6 * C].reshape(C, 6), robot_board=g[6 * C :], robot=l)


def frame_residuals(g, l, args) -> Float[Array, "frames m"]:
    """`robust_residuals` grouped per frame: every camera's, then the prior, `(frames, C k + 6)`."""
    r, prior = robust_residuals(join(g, l), args)
    C, F = r.shape[:2]
    return jnp.concatenate([jnp.swapaxes(r, 0, 1).reshape(F, -1), prior], axis=-1)


#: The reference linearisation: $n_g + 6$ forward-mode products of `frame_residuals`.
linearise_by_jvp = jacobian_by_jvp(frame_residuals)


def _wedge_vee(M):
    """The axial vector of the skew part of `M` (`(..., 3, 3)`)."""
    return 0.5 * jnp.stack(
        [M[..., 2, 1] - M[..., 1, 2], M[..., 0, 2] - M[..., 2, 0], M[..., 1, 0] - M[..., 0, 1]], -1
    )


# Nested jit, traced once per signature (see `jaxcal._arcmodel.arc_terms`).
@jax.jit
def linearise(g, l, args):
    """`frame_residuals` and its Jacobian blocks, by the chain rule through the board poses.

    Forward-mode products are taken of the $C F$ board poses $A_{cf}$ only
    ($n_g + 6$ of them, the robot corrections coloured across frames), as
    left twists $(\\dot v, \\dot w)$: $\\dot A A^{-1} = [\\dot w]_\\times$ on
    the rotation, $\\dot v = \\dot t - \\dot w \\times t$. A corner
    $p = R P + t$ then moves by $\\dot p = \\dot v + \\dot w \\times p$, its
    pixel by the pinhole's derivative,
    $\\dot x_n = (\\dot x - x_n \\dot z)/z$ (zero where $z$ is clamped),
    $\\dot u = f_x \\dot x_n + s\\,\\dot y_n$, $\\dot v = f_y \\dot y_n$, over
    $\\sigma_{px}$. The Cauchy weight $w(x)$ of a group with mean square
    $x = \\|r\\|^2/n$ adds $\\dot{(w r)} = w \\dot r + (2 w'(x)/n)\\,(r \\cdot \\dot r)\\, r$,
    and the prior $\\delta_f/\\sigma_{robot}$ has the constant block
    $\\mathrm{diag}(1/\\sigma_{robot})$. The same numbers as `linearise_by_jvp`
    (to round-off, `tests/test_handeye.py`) at a fraction of the cost: the
    products run over poses, not over every corner.
    """
    ref, data, loss_scale, robust = args
    F, p = l.shape
    n_g = g.shape[0]
    A, lin = jax.linearize(lambda gg, ll: predicted_board_poses(join(gg, ll), ref, data), g, l)
    tg = jnp.concatenate([jnp.eye(n_g), jnp.zeros((p, n_g))])
    tl = jnp.concatenate([jnp.zeros((n_g, F, p)), jnp.broadcast_to(jnp.eye(p)[:, None, :], (p, F, p))])
    dA = jax.vmap(lin)(tg, tl)  # (n, C, F, 4, 4), n = n_g + 6
    R, t = A[..., :3, :3], A[..., :3, 3]
    w = _wedge_vee(jnp.einsum("ncfij,cfkj->ncfik", dA[..., :3, :3], R))
    v = dA[..., :3, 3] - jnp.cross(w, t)
    P = jnp.einsum("cfij,pj->cfpi", R, data.board_points) + t[:, :, None, :]  # (C, F, P, 3)
    dP = v[..., None, :] + jnp.cross(w[..., None, :], P)  # (n, C, F, P, 3)
    z = P[..., 2]
    ok = z > 1e-9
    zc = jnp.where(ok, z, 1e-9)
    dz = jnp.where(ok, dP[..., 2], 0.0)
    dxn = (dP[..., 0] - P[..., 0] / zc * dz) / zc
    dyn = (dP[..., 1] - P[..., 1] / zc * dz) / zc
    K = data.K[:, None, None]
    du = K[..., 0, 0] * dxn + K[..., 0, 1] * dyn
    dv = K[..., 1, 1] * dyn
    m = data.mask & ref.active[..., None]
    dr = jnp.where(m[..., None], jnp.stack([du, dv], -1) / data.sigma_px, 0.0)  # (n, C, F, P, 2)
    dr = jnp.moveaxis(dr.reshape(dr.shape[:3] + (-1,)), 0, -1)  # (C, F, k, n)
    r, prior = hand_eye_residuals(join(g, l), (ref, data))  # (C, F, k), (F, 6)
    r, J = robust_weighting(r, dr, ref, data, loss_scale, robust)
    r_frames = jnp.concatenate([jnp.swapaxes(r, 0, 1).reshape(F, -1), prior], axis=-1)
    J = jnp.swapaxes(J, 0, 1).reshape(F, -1, n_g + p)  # (F, C k, n)
    J_prior = jnp.concatenate(
        [jnp.zeros((F, p, n_g)), jnp.broadcast_to(jnp.diag(1.0 / data.robot_sigma), (F, p, p))], axis=-1
    )
    J = jnp.concatenate([J, J_prior], axis=1)
    return r_frames, J[..., :n_g], J[..., n_g:]


def solve_by_blocks(params0: HandEyeParams, args, options: LMOptions):
    """Levenberg-Marquardt on `robust_residuals` by blocks. **Returns:** `(params, result,
    num_steps, (r, J_g, J_l))`, the last its linearisation at `params` (`linearise`'s)."""
    g0, l0 = split(params0)
    sol = block_least_squares(
        linearise, g0, l0, args, rtol=options.rtol, atol=options.atol, max_steps=options.max_steps
    )
    return join(sol.g, sol.l), sol.result, sol.num_steps, (sol.residuals, sol.jac_g, sol.jac_l)


def block_bread(params: HandEyeParams, ref, data, lin=None):
    """The plain residuals' $(J^TJ)^{+}$, the per-frame gradients and $\\|r\\|^2$ at `params`;
    `lin`: their `linearise` at `params`, where the solver has it.

    **Returns:** `(bread (n, n), grads (frames, n), ssr)`, parameters in
    `ravel_pytree(params)` order.
    """
    g, l = split(params)
    args = (ref, data, jnp.asarray(1.0), jnp.asarray(False))
    r, Jg, Jl = linearise(g, l, args) if lin is None else lin
    bread = full_covariance(Jg, Jl)
    F = l.shape[0]
    grad_g = jnp.einsum("fmi,fm->fi", Jg, r)
    grad_l = jnp.einsum("fg,fmi,fm->fgi", jnp.eye(F, dtype=r.dtype), Jl, r).reshape(F, 6 * F)
    return bread, jnp.concatenate([grad_g, grad_l], axis=-1), jnp.sum(r**2)
