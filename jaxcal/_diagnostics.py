"""The refinement's residuals tested at its solution (pure; the stages run them:
`jaxcal.stages._residual_tests`).

- `line_delay_test`, `lens_test`, `intrinsics_test`, `score_tests`: score (Lagrange-multiplier)
  tests of parameters the refinement held: a rolling shutter's line delay on a global-shutter
  solution, the first camera's radial distortion beyond the given lens, its focal lengths and
  principal point beyond the given ones; one reverse pass of the corner model for all three
  (`score_tests`).
- `view_information`: each view's information $J_v^TJ_v$ at the solution, for sandwiches that
  group views (`jaxcal._lsq.hac_covariance`).
- `residual_correlation` (NumPy): each corner's residual against its own in later frames.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, Float

from ._correction import INTRINSIC_NAMES
from ._refine import RefineProblem, RefineResult, layout
from ._reprojection import num_other_cameras, reprojection_residuals


def view_information(
    problem: RefineProblem, res: RefineResult, free: np.ndarray
) -> Float[Array, "views f f"]:
    """Per view the final solve's information $J_v^TJ_v$ over the free parameters (`free`, a
    concrete mask: their order), at the solution with its final weights; pure. What a sandwich
    that groups views needs beside `RefineResult.view_scores` (`jaxcal._lsq.hac_covariance`)."""
    flat, unravel = ravel_pytree(res.params)
    idx = np.flatnonzero(np.asarray(free, bool))

    def residuals(x):
        return reprojection_residuals(unravel(flat.at[idx].set(x)), problem, res.weights)

    J = jax.jacfwd(residuals)(flat[idx])  # (views, corners, 2, f)
    J = J.reshape(J.shape[0], -1, idx.size)
    return jnp.einsum("vkn,vkm->vnm", J, J)


class ShutterTest(eqx.Module):
    """The score test of a global-shutter refinement for a rolling shutter (`line_delay_test`).

    - `line_delay_s`: per camera, the line delay (s per row) one Gauss-Newton step
      from the solution would add, the others' parameters following; `(cameras,)`.
    - `sigmas`: each delay over its standard deviation (the test's statistic:
      about a standard normal's size when the shutter is global).
    """

    line_delay_s: Float[Array, " cameras"]
    sigmas: Float[Array, " cameras"]


def line_delay_test(
    problem: RefineProblem, res: RefineResult, rows: Float[Array, "views corners"] | None = None
) -> ShutterTest:
    """Do a global-shutter refinement's residuals lie along the image rows, as a rolling
    shutter's would? The score (Lagrange-multiplier) test of a line delay per camera
    at the solution `res` of `problem` (no line delay modelled).

    Timed at their rows $y$ (`rows`, default the detected ones), the corners'
    residuals gain $J_\\ell \\ell$ for line delays $\\ell$: each corner's image
    velocity $\\partial u / \\partial t$ times its row. With the final weights, the
    residuals $r$ and the free parameters' Jacobian $J$ (whose normal matrix's
    inverse is `res.cov_model` over $\\hat\\sigma^2$), the delay one Gauss-Newton step
    gives and its covariance are $\\hat\\ell = -D^{-1} J_\\ell^T r$ and
    $\\hat\\sigma^2 D^{-1}$, with $D = J_\\ell^T J_\\ell - J_\\ell^T J\\,(J^TJ)^{-1} J^T J_\\ell$
    (the part of $J_\\ell$ the other parameters cannot absorb: a delay common to
    a view's corners is the clock's). One forward and one reverse pass of the
    global-shutter model; pure.
    """
    J_ell, r = _delay_columns(problem, res, rows)
    return _shutter(J_ell, _pulled(problem, res, J_ell), r, res)


def _delay_columns(problem: RefineProblem, res: RefineResult, rows=None):
    """`(J_ell (N, cameras), r (N,))`: the residuals' derivative along each camera's line delay
    (per us per row, corners timed at `rows`, default the detected ones) and the residuals."""
    C = 1 + num_other_cameras(problem)
    y = problem.data.pixels[..., 1] if rows is None else rows

    def at_times(t_cam):
        timed = eqx.tree_at(lambda p: p.data.t_cam, problem, t_cam)
        return reprojection_residuals(res.params, timed, res.weights)

    t_cam = problem.data.t_cam
    r, velocity = jax.jvp(at_times, (t_cam,), (jnp.ones_like(t_cam),))  # (V, P, 2), px and px/s
    camera = jnp.zeros_like(problem.data.target) if problem.data.camera is None else problem.data.camera
    per_camera = jax.nn.one_hot(camera, C, dtype=r.dtype)  # (V, C)
    J_ell = 1e-6 * jnp.einsum("vkd,vk,vc->vkdc", velocity, y, per_camera).reshape(-1, C)  # per us per row
    return J_ell, r.reshape(-1)


def _pulled(problem: RefineProblem, res: RefineResult, columns):
    """$J^T$ `columns` `(n, m)`: the model's reverse pass at the solution, once per column."""
    flat, unravel = ravel_pytree(res.params)
    _, pullback = jax.vjp(
        lambda x: reprojection_residuals(unravel(x), problem, res.weights).reshape(-1), flat
    )
    return jax.vmap(lambda col: pullback(col)[0], in_axes=1, out_axes=1)(columns)


def _step(J_x, G, r, res):
    """The score test's Gauss-Newton step along the columns `J_x` (`G` = $J^TJ_x$): `(step, D)`,
    $D = J_x^TJ_x - G^T(J^TJ)^{-1}G$, step $= -D^{-1}J_x^Tr$."""
    sigma2 = jnp.maximum(res.sigma_px**2, 1e-30)
    D = J_x.T @ J_x - G.T @ (res.cov_model / sigma2) @ G
    return -jnp.linalg.pinv(D, hermitian=True) @ (J_x.T @ r), D


def _shutter(J_ell, G, r, res) -> "ShutterTest":
    ell_us, D = _step(J_ell, G, r, res)
    sigma2 = jnp.maximum(res.sigma_px**2, 1e-30)
    std_us = jnp.sqrt(jnp.maximum(jnp.diag(jnp.linalg.pinv(D, hermitian=True)), 0.0) * sigma2)
    return ShutterTest(
        line_delay_s=1e-6 * ell_us, sigmas=jnp.abs(ell_us) / jnp.where(std_us > 0, std_us, 1.0)
    )


class LensTest(eqx.Module):
    """The score test of a refinement for radial distortion beyond its lens (`lens_test`).

    - `distortion`: the $(k_1, k_2)$ increments one Gauss-Newton step from the solution
      would add, the other parameters following; `(2,)`.
    - `sigmas`: the score statistic $\\hat d^T D \\hat d / \\hat\\sigma^2$ ($\\chi^2$ on two
      degrees of freedom when the lens is right) as a standard normal's size.
    """

    distortion: Float[Array, "2"]
    sigmas: Float[Array, ""]


#: The held intrinsics each test frees (`INTRINSIC_NAMES`): the radial distortion's first two
#: coefficients, and the pinhole's focal lengths and principal point.
RADIAL = ("k1", "k2")
PINHOLE = ("fx", "fy", "cx", "cy")


def lens_test(problem: RefineProblem, res: RefineResult) -> LensTest:
    """Do a refinement's residuals grow with the distance from the first camera's centre, as
    a radial distortion's would? The score (Lagrange-multiplier) test of $k_1, k_2$ at the
    solution `res` of `problem`, where they were held (the metadata's lens).

    As `line_delay_test`: with $J_d$ the residuals' derivative along the two coefficients,
    $D = J_d^TJ_d - J_d^TJ\\,(J^TJ)^{-1}J^TJ_d$ (what the free parameters cannot absorb of them),
    the step is $\\hat d = -D^{-1}J_d^Tr$ with covariance $\\hat\\sigma^2 D^{-1}$, and the statistic
    $S = \\hat d^TD\\hat d / \\hat\\sigma^2 \\sim \\chi^2_2$ under a right lens, reported as the
    standard normal quantile of its p-value (`sigmas`). Pure.
    """
    J_d, r = _held_columns(problem, res, RADIAL)
    return _lens(J_d, _pulled(problem, res, J_d), r, res)


class IntrinsicsTest(eqx.Module):
    """The score test of a refinement for focal lengths and a principal point beyond its given
    ones (`intrinsics_test`).

    - `step`: the $(f_x, f_y, c_x, c_y)$ increments (px) one Gauss-Newton step from the solution
      would add, the other parameters following; `(4,)`.
    - `chi2`: the score statistic $\\hat d^T D \\hat d / \\hat\\sigma^2$ ($\\chi^2$ on four degrees
      of freedom when the intrinsics are right; the stage states it as a normal's size).
    - `sensitivity`: how the solution moves per px of each held intrinsic,
      $-(J^TJ)^{-1}J^TJ_k$ over the flattened parameters (zero where held); `(n, 4)`.
    """

    step: Float[Array, "4"]
    chi2: Float[Array, ""]
    sensitivity: Float[Array, "n 4"]


def intrinsics_test(problem: RefineProblem, res: RefineResult) -> IntrinsicsTest:
    """Do a refinement's residuals point to other focal lengths or another principal point than
    the first camera's given ones (the metadata's `K`, held)? The score test of `lens_test` on
    $(f_x, f_y, c_x, c_y)$: a wrong focal length scales the image about its centre, which the
    camera's distance and the link lengths absorb only in part. Pure."""
    J_k, r = _held_columns(problem, res, PINHOLE)
    return _intrinsics(J_k, _pulled(problem, res, J_k), r, res)


def score_tests(
    problem: RefineProblem, res: RefineResult, rows: Float[Array, "views corners"] | None = None
) -> tuple[ShutterTest, LensTest, IntrinsicsTest]:
    """`(line_delay_test(problem, res, rows), lens_test(problem, res), intrinsics_test(problem,
    res))` with one reverse pass of the model for all three (the stage's program). Pure."""
    J_ell, r = _delay_columns(problem, res, rows)
    J_dk, _ = _held_columns(problem, res, RADIAL + PINHOLE)
    G = _pulled(problem, res, jnp.concatenate([J_ell, J_dk], axis=1))
    C, R = J_ell.shape[1], len(RADIAL)
    J_d, J_k, G_d, G_k = J_dk[:, :R], J_dk[:, R:], G[:, C : C + R], G[:, C + R :]
    return _shutter(J_ell, G[:, :C], r, res), _lens(J_d, G_d, r, res), _intrinsics(J_k, G_k, r, res)


def _held_columns(problem: RefineProblem, res: RefineResult, names: tuple[str, ...]):
    """`(J (N, len(names)), r (N,))`: the residuals' derivative along the first camera's
    intrinsics `names` (`INTRINSIC_NAMES`) and the residuals."""
    flat, unravel = ravel_pytree(res.params)
    intr = np.asarray(layout(problem, res.params).index("intr"))
    rows = intr[[INTRINSIC_NAMES.index(n) for n in names]]

    def along(x):
        return reprojection_residuals(unravel(x), problem, res.weights).reshape(-1)

    E = jnp.zeros((flat.shape[0], len(names))).at[rows, np.arange(len(names))].set(1.0)
    r = along(flat)
    return jax.vmap(lambda e: jax.jvp(along, (flat,), (e,))[1], in_axes=1, out_axes=1)(E), r


def _statistic(J_x, G, r, res):
    """`(step, chi2)`: the score test's step along `J_x` and its statistic $\\hat d^TD\\hat d/\\hat\\sigma^2$."""
    d, D = _step(J_x, G, r, res)
    return d, jnp.maximum(d @ D @ d / jnp.maximum(res.sigma_px**2, 1e-30), 0.0)


def _lens(J_d, G, r, res) -> LensTest:
    d, chi2 = _statistic(J_d, G, r, res)
    # chi^2 on 2 dof: p = exp(-S/2); its normal quantile, sqrt(S) beyond a few sigmas' precision.
    sigmas = jnp.sqrt(2.0) * jax.scipy.special.erfinv(jnp.maximum(1.0 - 2.0 * jnp.exp(-0.5 * chi2), 0.0))
    sigmas = jnp.where(chi2 > 60.0, jnp.sqrt(jnp.maximum(chi2 - 2.0 * jnp.log(chi2) - 2.0, 0.0)), sigmas)
    return LensTest(distortion=d, sigmas=sigmas)


def _intrinsics(J_k, G, r, res) -> IntrinsicsTest:
    step, chi2 = _statistic(J_k, G, r, res)
    bread = res.cov_model / jnp.maximum(res.sigma_px**2, 1e-30)  # (J^T J)^+ over the free parameters
    return IntrinsicsTest(step=step, chi2=chi2, sensitivity=-bread @ G)


def residual_correlation(
    residuals: np.ndarray, used: np.ndarray, pairs: tuple[np.ndarray, ...]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pooled autocorrelation of each corner's residual along the capture (NumPy; outside jit).

    Pairs at lag $k$ are the same corner of the same target and camera in views $k$ frames
    apart along one run of the capture (`pairs[k - 1]`: rows `(view_a, corner_a, view_b,
    corner_b)`), both used by the final solve. With the products $p = r_a \\cdot r_b$ of their
    residuals (px, both coordinates), the lag's correlation is
    $\\rho_k = \\sum p / \\sqrt{\\sum |r_a|^2 \\sum |r_b|^2}$ and its self-normalised statistic
    $z_k = \\sum p / \\sqrt{\\sum p^2}$, a standard normal's when the errors are independent
    (whatever their law or size: the products of independent zero-mean errors are uncorrelated);
    the $z_k$ of different lags are then independent, so $\\sum_k z_k^2$ is Ljung-Box's $Q$ on $K$
    degrees of freedom. The fit itself makes neighbouring residuals of one corner slightly
    anti-correlated ($-\\sigma^2 H_{ab}$, the hat matrix's entry: about the free parameters over
    the corners), which only makes the one-sided test of errors that repeat conservative.

    **Returns:** `(rho (K,), z (K,), pairs used (K,))`.
    """
    r, used = np.asarray(residuals, np.float64), np.asarray(used, bool)
    rho, z, count = [], [], []
    for P in pairs:
        P = np.asarray(P, int).reshape(-1, 4)
        P = P[used[P[:, 0], P[:, 1]] & used[P[:, 2], P[:, 3]]]
        a, b = r[P[:, 0], P[:, 1]], r[P[:, 2], P[:, 3]]
        prod = np.sum(a * b, axis=-1)
        den = np.sqrt(np.sum(a * a) * np.sum(b * b))
        rho.append(float(prod.sum() / den) if den > 0 else 0.0)
        z.append(float(prod.sum() / np.sqrt(np.sum(prod * prod))) if prod.size and np.any(prod) else 0.0)
        count.append(len(P))
    return np.asarray(rho), np.asarray(z), np.asarray(count, int)
