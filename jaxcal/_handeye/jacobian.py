"""The closed-form Jacobian of the pixel residuals with exact robot poses.

With $X_c = X_{0,c} \\exp(\\xi_c)$ and $Y = Y_0 \\exp(\\eta)$ a board corner
$b$ (homogeneous) is seen by camera $c$ at robot pose $f$ at
$p = X_c B_f Y b$, so

$$\\frac{\\partial p}{\\partial \\xi_{c,k}} = X_{0,c}\\,
\\frac{\\partial \\exp(\\xi_c)}{\\partial \\xi_{c,k}}\\, B_f Y b,\\qquad
\\frac{\\partial p}{\\partial \\eta_k} = X_c B_f Y_0\\,
\\frac{\\partial \\exp(\\eta)}{\\partial \\eta_k}\\, b,$$

the derivatives of the exponential being one 6-vector's autodiff each (cheap:
they do not grow with the corners). The pinhole
$u = (f_x x + s y + c_x, f_y y + c_y)$, $(x, y) = (p_1, p_2)/p_3$ adds
$\\partial u / \\partial p$, and the robust loss of a (camera, frame) group
$r \\mapsto w(\\bar s)\\,r$, $\\bar s = \\|r\\|^2/n$, adds
$w J + r\\, w'(\\bar s)\\,(2/n)\\, r^T J$.

Levenberg-Marquardt forms this Jacobian every step (`solve_pixels`) and reduces
it at once to the 12 x 12 normal equations (`pixel_normal`), the robust loss
applied there by its rank-one terms per group: the loop never holds, weights or
copies the 3,500 x 12 Jacobian, whose passes (and XLA's slow fused reductions
over them) were most of a step. The solve takes about half the time of autodiff's
Jacobian through optimistix (`benchmarks/handeye.py --parts speed`; the figures
are in docs/performance.md).
`tests/test_handeye.py` checks both against autodiff.
"""

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._geometry import matmul, se3_exp
from .._lsq import LMOptions
from .._schur import NormalEquations, normal_least_squares
from .blocks import join, split
from .model import HandEyeParams, robot_motion, robust_factors, robust_weighting

_d_exp = jax.jacfwd(se3_exp)  # (4, 4, 6) at one twist


# Nested jit, traced once per signature (see `jaxcal._arcmodel.arc_terms`).
@jax.jit
def pixel_terms(params, args) -> tuple[Float[Array, "cameras frames k"], Float[Array, "cameras frames k n"]]:
    """`robust_residuals`' observation residuals (pixels, exact robot poses: `params.robot`
    is None) and their Jacobian over the flattened `(cam_robot, robot_board)`."""
    ref, data, loss_scale, robust = args
    return robust_weighting(*_plain_terms(params, ref, data), ref, data, loss_scale, robust)


def _plain_terms(params, ref, data):
    """The whitened residuals `(cameras, frames, k)` and their Jacobian `(cameras, frames, k, n)`
    before the robust loss."""
    C, F, P = data.mask.shape
    EX, dEX = jax.vmap(se3_exp)(params.cam_robot), jax.vmap(_d_exp)(params.cam_robot)
    EY, dEY = se3_exp(params.robot_board), _d_exp(params.robot_board)
    X, Y = matmul(ref.X0, EX), ref.Y0 @ EY
    B = robot_motion(data.T_base_ee, data.eye_in_hand)
    b = jnp.concatenate([data.board_points, jnp.ones((P, 1), data.board_points.dtype)], axis=-1)
    BY = matmul(B, Y[None])
    # The contractions over the 4-vectors and the 3x6 blocks as unrolled multiply-adds (as
    # `matmul_unrolled`): as fast as `einsum` here, and faster than broadcast-and-sum
    # reductions.
    q = jnp.einsum("fij,pj->fpi", BY, b)  # (F, P, 4): the corners X acts on
    XB = matmul(X[:, None], B[None])  # (C, F, 4, 4)
    p = jnp.einsum("cfij,pj->cfpi", XB[..., :3, :], jnp.einsum("ij,pj->pi", Y, b))  # (C, F, P, 3)
    MX = jnp.einsum("cij,cjlk->cilk", ref.X0[:, :3, :], dEX)[:, None, None]  # (C, 1, 1, 3, 4, 6)
    dp_x = sum(MX[..., l, :] * q[None, :, :, None, l, None] for l in range(4))  # (C, F, P, 3, 6)
    NY = jnp.einsum("cfij,jlk->cfilk", matmul(XB, ref.Y0[None, None])[..., :3, :], dEY)[:, :, None]
    dp_y = sum(NY[..., l, :] * b[None, None, :, None, l, None] for l in range(4))  # (C, F, P, 3, 6)

    # The pinhole, as `model._observation_residuals` computes it (depth clamped at 1 nm).
    z = p[..., 2]
    front = z > 1e-9
    z = jnp.where(front, z, 1e-9)
    x, y = p[..., 0] / z, p[..., 1] / z
    K = data.K[:, None, None]
    fx, s, fy = K[..., 0, 0], K[..., 0, 1], K[..., 1, 1]
    uv = jnp.stack([fx * x + s * y + K[..., 0, 2], fy * y + K[..., 1, 2]], axis=-1)
    dz = jnp.where(front, 1.0, 0.0) / z
    zero = jnp.zeros_like(z)
    D = jnp.stack(
        [
            jnp.stack([fx / z, s / z, -(fx * x + s * y) * dz], axis=-1),
            jnp.stack([zero, fy / z, -fy * y * dz], axis=-1),
        ],
        axis=-2,
    )  # (C, F, P, 2, 3)
    m = (data.mask & ref.active[..., None])[..., None]
    e = jnp.where(m, (uv - jnp.where(m, data.pixels, 0.0)) / data.sigma_px, 0.0)
    white = jnp.where(m, 1.0 / data.sigma_px, 0.0)[..., None]
    J_x = sum(D[..., j, None] * dp_x[..., None, j, :] for j in range(3)) * white  # (C, F, P, 2, 6)
    J_y = sum(D[..., j, None] * dp_y[..., None, j, :] for j in range(3)) * white
    one_hot = jnp.eye(C, dtype=J_x.dtype)[:, None, None, None, :, None]  # camera c's own columns
    J_x = (J_x[..., None, :] * one_hot).reshape(C, F, P, 2, 6 * C)
    return e.reshape(C, F, 2 * P), jnp.concatenate([J_x, J_y], axis=-1).reshape(C, F, 2 * P, 6 * C + 6)


# Nested jit, traced once per signature (see `jaxcal._arcmodel.arc_terms`).
@jax.jit
def pixel_normal(params, args) -> tuple[Float[Array, "cameras frames k"], NormalEquations]:
    """`pixel_terms` reduced to the normal equations, group by group: the robust residuals
    $\\tilde r = w r$, $J^TJ$ and $J^T\\tilde r$ of their Jacobian
    $\\tilde J = wJ + c\\,r\\,p^T$ ($p = J^Tr$ per group, `model.robust_factors`), and
    `aux`, each (camera, frame) group's gradient $\\tilde J^T\\tilde r$ `(cameras, frames, n)`.

    Per group $\\tilde J^T\\tilde J = w^2 J^TJ + (2wc + c^2\\|r\\|^2)\\,pp^T$ and
    $\\tilde J^T\\tilde r = (w^2 + wc\\|r\\|^2)\\,p$: the robust loss costs
    $n \\times n$ terms per group instead of a pass over the whole Jacobian.
    """
    ref, data, loss_scale, robust = args
    r, J = _plain_terms(params, ref, data)
    w, c = robust_factors(r, ref, data, loss_scale, robust)
    s = jnp.sum(r**2, axis=-1)
    p = jnp.einsum("cfkn,cfk->cfn", J, r)
    G = (w**2 + w * c * s)[..., None] * p
    H = jnp.einsum("cfkn,cfkm,cf->nm", J, J, w**2) + jnp.einsum("cfn,cfm,cf->nm", p, p, (2.0 * w + c * s) * c)
    return r * w[..., None], NormalEquations(H=H, e=jnp.sum(G, axis=(0, 1)), aux=G)


def solve_pixels(params0: HandEyeParams, args, options: LMOptions):
    """Levenberg-Marquardt on `robust_residuals` (pixels, exact robot poses) with the
    closed-form Jacobian. **Returns:** `(params, result, num_steps, (r, H, G))`, the last
    `pixel_normal` at `params` (its residuals, $J^TJ$ and the groups' gradients).

    `jaxcal._schur.normal_least_squares`: optimistix's iteration (the same steps and
    optimum as `jaxcal._lsq.solve` on these residuals, to round-off;
    `tests/test_handeye.py`) on the $n \\times n$ normal equations that
    `pixel_normal` forms, with a fraction of its per-step operations: the same steps in
    less than half optimistix's time (docs/performance.md, Hand-eye)."""
    g0, _ = split(params0)
    sol = normal_least_squares(
        lambda g, a: pixel_normal(join(g, None), a),
        g0,
        args,
        rtol=options.rtol,
        atol=options.atol,
        max_steps=options.max_steps,
    )
    return join(sol.x, None), sol.result, sol.num_steps, (sol.residuals, sol.normal.H, sol.normal.aux)
