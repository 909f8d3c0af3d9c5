"""Robust weights for residual groups of any size: a $k$-vector per sample.

The refinement down-weights each corner by the norm of its 2-vector pixel
residual, in robust sigmas, against thresholds `c` and `reject` that are
radii of the 2-D (Rayleigh) distribution. A sample with a $k$-vector
residual (an arc-fit frame: position, or position and rotation, $k = 3$ or
6) is judged by its **deletion residual**: the residual it would have if the
fit had not used it. With $r_i$ its whitened residual, $J_i$ its Jacobian
block, $w_i$ its weight in the fit and $C = (J^T W J)^{+}$ the fit's unscaled
covariance, let $G_i = J_i C J_i^T$ ($k \\times k$; $w_i G_i$ is the sample's
block of the hat matrix, its trace the leverage). Removing the sample from the
linearised fit moves its prediction to $r_{(i)} = (I - w_i G_i)^{-1} r_i$,
whose variance is $\\sigma^2 (I + G_{(i)})$, $G_{(i)} = G_i (I - w_i G_i)^{-1}$;
so

$$d_i^2 = r_i^T \\big[(I - w_i G_i)(I + (1 - w_i) G_i)\\big]^{+} r_i$$

is $\\sigma^2 \\chi^2_\\nu$ for a clean sample, exactly in the linear Gaussian
model, with $\\nu$ the rank of the bracket: $k$, less one for each direction
the sample alone determines (the joint angle of a one-marker frame without
encoders). For $w_i = 1$ this is the externally studentised residual
$r_i^T (I - H_{ii})^{-1} r_i$; for an excluded sample ($w_i = 0$),
$r_i^T (I + G_i)^{-1} r_i$, its prediction error against the predictive
variance. A sample with high leverage (a sweep's end, which decides the
arc's angle scale) pulls the fit towards itself and keeps its own residual
small (masking); its deletion residual does not. Only the per-sample blocks
$G_i$ are formed (never the $N \\times N$ hat matrix), so the cost stays
linear in the samples.

So that `c` and `reject` mean what they mean in the refinement, each norm is
mapped to the Rayleigh radius with the same tail probability,

$$z^{eq} = \\sqrt{-2 \\ln Q\\big(\\tfrac{\\nu}{2}, \\tfrac{z^2}{2}\\big)}, \\qquad z = d / s,$$

with $Q$ the regularised upper incomplete gamma function ($\\chi^2_\\nu$'s
survival function is $Q(\\nu/2, x/2)$; for $\\nu = 2$, $z^{eq} = z$), and
the scale $s$ is the median over the samples of $d_i / m(\\nu_i)$, with
$m(\\nu)$ the median of $\\chi_\\nu$ (the refinement's Rayleigh median
$\\sqrt{2 \\ln 2}$ for $\\nu = 2$). `reject = 3.7` then rejects a clean
sample with probability $e^{-3.7^2/2} = 1.1 \\times 10^{-3}$ whatever $k$.
"""

from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jax.scipy.special import gammainc, gammaincc, gammaln
from jaxtyping import Array, Bool, Float, Int, PyTree

from ._lsq import traced
from ._schur import small_cholesky_solve

LOSSES = ("cauchy", "huber", None)
#: Degrees of freedom are clipped to at least this (tiny problems, where a
#: sample's leverage approaches its size, carry no outlier information).
MIN_DOF = 1.0


def check_loss(loss: str | None) -> None:
    """Raise a `ValueError` unless `loss` is one of `LOSSES`."""
    if loss not in LOSSES:
        raise ValueError(f"loss must be one of {LOSSES}, got {loss!r}")


def loss_weights(
    z: Float[Array, "..."], loss: str | None, c: float | Float[Array, ""]
) -> Float[Array, "..."]:
    """IRLS weights of residual radii `z` (robust sigmas).

    Cauchy: $w = 1/(1 + (z/c)^2)$; Huber: $w = \\min(1, c/z)$; `None`: 1.
    """
    check_loss(loss)
    if loss is None:
        return jnp.ones_like(z)
    if loss == "cauchy":
        return 1.0 / (1.0 + (z / c) ** 2)
    return jnp.minimum(1.0, c / jnp.maximum(z, 1e-12))


def chi_median(nu: Float[Array, "..."]) -> Float[Array, "..."]:
    """Median of the $\\chi_\\nu$ distribution (the norm of a $\\nu$-vector of unit normals).

    Wilson-Hilferty's start $x_0 = \\tfrac{\\nu}{2}(1 - \\tfrac{2}{9\\nu})^3$ for the
    median of $\\chi^2_\\nu / 2$, then four Newton steps on $P(\\nu/2, x) = 1/2$
    (the density is $x^{a-1}e^{-x}/\\Gamma(a)$): machine precision for
    $\\nu \\ge 1$. Returns $\\sqrt{2x}$.
    """
    a = 0.5 * nu
    x = a * (1.0 - 2.0 / (9.0 * nu)) ** 3

    def newton(_, x):
        density = jnp.exp((a - 1.0) * jnp.log(x) - x - gammaln(a))
        return jnp.maximum(x - (gammainc(a, x) - 0.5) / density, 1e-3 * x)

    # A loop, not four copies: XLA's incomplete gamma function is large, and unrolled it made
    # this a third of a robust fit's compilation (5.8 against 2.0 s on a loaded 2-core machine).
    return jnp.sqrt(2.0 * jax.lax.fori_loop(0, 4, newton, x))


def rayleigh_equivalent(z: Float[Array, "..."], nu: Float[Array, "..."]) -> Float[Array, "..."]:
    """The Rayleigh radius with the tail probability of `z` under $\\chi_\\nu$ (see the module docstring).

    $-\\ln Q(a, x)$ from `gammaincc` while it is representable, else from its
    asymptotic form $x - (a - 1)\\ln x + \\ln\\Gamma(a)$ (relative error
    $(a-1)/x < 1\\%$ there).
    """
    a = 0.5 * nu
    x = 0.5 * z**2
    big = x > 600.0
    xs = jnp.where(big, 1.0, x)
    direct = -jnp.log(gammaincc(a, xs))
    asymptotic = x - (a - 1.0) * jnp.log(jnp.where(big, x, 1.0)) + gammaln(a)
    return jnp.sqrt(2.0 * jnp.maximum(jnp.where(big, asymptotic, direct), 0.0))


def robust_scale(
    e: Float[Array, "*samples"], nu: Float[Array, "*samples"], mask: Bool[Array, "*samples"]
) -> Float[Array, ""]:
    """The noise scale $s$: the median over observed samples of $e_i / m(\\nu_i)$ (at least 1e-9)."""
    u = e / chi_median(nu)
    return jnp.maximum(jnp.nanmedian(jnp.where(mask, u, jnp.nan)), 1e-9)


#: A direction of a sample's residual whose deletion variance is more than
#: 1 / `DELETION_TOL` times its fitted one (the sample decides it almost alone)
#: carries no outlier information and is left out of the deletion residual
#: (it would mostly amplify the solver's convergence error).
DELETION_TOL = 1e-3


def deletion_residuals(
    r: Float[Array, "*samples k"],
    G: Float[Array, "*samples k k"],
    w: Float[Array, "*samples"],
    mask: Bool[Array, "*samples"],
) -> tuple[Float[Array, "*samples"], Float[Array, "*samples"]]:
    """Each sample's deletion residual norm $d_i$ and its degrees of freedom (see the module docstring).

    $d_i^2 = r_i^T M_i^{+} r_i$ with $M_i = (I - w_i G_i)(I + (1 - w_i) G_i)$,
    symmetric positive semi-definite (a polynomial in $G_i$, whose eigenvalues
    $g$ lie in $[0, 1/w_i]$), solved by an unrolled Cholesky factorisation
    (elementwise over the samples: no LAPACK call, linear in their number);
    a pivot at or under `DELETION_TOL` drops its direction, and $\\nu$ is $k$
    less the directions dropped (at least `MIN_DOF`).

    **Arguments:**
    - `r`: whitened residuals; `G`: $J_i C J_i^T$ with $J_i$ the sample's
      (unweighted, whitened) Jacobian block and $C = (J^T W J)^{+}$ the fit's
      unscaled covariance under the weights `w` it was solved with; `mask`:
      observed samples.

    **Returns:** `(d, nu)`, 0 and `k` where unobserved; constants for
    differentiation (IRLS holds weights fixed).
    """
    r, G, w = jax.lax.stop_gradient((r, G, w))
    k = r.shape[-1]
    eye = jnp.broadcast_to(jnp.eye(k, dtype=r.dtype), G.shape)
    wG = w[..., None, None] * G
    M = (eye - wG) @ (eye + G - wG)
    M = 0.5 * (M + jnp.swapaxes(M, -1, -2))
    M = jnp.where(mask[..., None, None], M, eye)
    # One factorisation for M^+ r and M^+ M, whose trace is the rank (the pivots kept).
    X = small_cholesky_solve(M, jnp.concatenate([r[..., None], M], axis=-1), DELETION_TOL)
    d2 = jnp.maximum(jnp.sum(r * X[..., 0], axis=-1), 0.0)
    nu = jnp.clip(jnp.trace(X[..., 1:], axis1=-2, axis2=-1), MIN_DOF, float(k))
    return jnp.where(mask, jnp.sqrt(d2), 0.0), jnp.where(mask, nu, float(k))


def sample_weights(
    e: Float[Array, "*samples"],
    nu: Float[Array, "*samples"],
    mask: Bool[Array, "*samples"],
    *,
    loss: str | None,
    c: float | Float[Array, ""],
    reject: float | Float[Array, ""],
    hard: Bool[Array, ""] | bool,
) -> tuple[Float[Array, "*samples"], Float[Array, "*samples"], Float[Array, ""]]:
    """IRLS weights of samples with residual norms `e` of `nu` degrees of freedom.

    **Arguments:**
    - `e`: each sample's residual norm, $\\sigma\\chi_\\nu$ when clean (a
      deletion residual, `deletion_residuals`); `nu`: its degrees of freedom
      (clipped to `[MIN_DOF, inf)`); `mask`: observed samples.
    - `loss`, `c`: the soft weights; `reject`, `hard`: where `hard`, the
      weights are 1 within `reject` and 0 beyond (the inlier solve).

    **Returns:** `(weights, z_eq, s)`: the weights (0 where unobserved), each
    sample's Rayleigh-equivalent radius in robust sigmas, and the scale.
    All three are constants for differentiation (IRLS holds weights fixed).
    """
    e, nu = jax.lax.stop_gradient((e, nu))
    nu = jnp.maximum(nu, MIN_DOF)
    s = robust_scale(e, nu, mask)
    z = jnp.where(mask, rayleigh_equivalent(e / s, nu), 0.0)
    soft = loss_weights(z, loss, c)
    inl = (z < reject).astype(e.dtype)
    w = jnp.where(hard, inl, soft) * mask
    return w, z, s


def round_plan(loss: str | None, rounds: int, reject) -> np.ndarray:
    """Which rounds are the hard inlier solve (static): `rounds` soft IRLS
    rounds and, with `reject`, one inlier solve; one plain round without a loss."""
    if loss is None:
        return np.zeros(1, bool)
    if rounds < 1:
        raise ValueError(f"rounds must be at least 1 with a robust loss, got {rounds}")
    return np.array([False] * rounds + ([True] if reject is not None else []))


class Rounds(NamedTuple):
    """What `irls_rounds` returns: the last round's `value`, every round's steps
    summed (`num_steps`), whether every solve converged (`ok`), the last round's
    `weights`, `result` (`successful`, else the first failing round's code),
    and each round's `round_results` and `round_steps`."""

    value: PyTree
    num_steps: Int[Array, ""]
    ok: Bool[Array, ""]
    weights: PyTree
    result: optx.RESULTS
    round_results: optx.RESULTS
    round_steps: Int[Array, " rounds"]


def irls_rounds(
    solve: Callable[[PyTree, PyTree], tuple[PyTree, optx.RESULTS, Int[Array, ""]]],
    weights_at: Callable[[PyTree, Bool[Array, ""]], PyTree],
    y0: PyTree,
    hard_flags: np.ndarray,
) -> Rounds:
    """Iteratively reweighted least squares as one `lax.scan` (one compiled solver).

    Round $i$ takes the weights `weights_at(y, hard_flags[i])` of the previous
    solution `y` (soft IRLS weights, or with `hard` the 0/1 inlier weights; see
    `round_plan`) and solves with them: `solve(y, w) -> (y_new, result, steps)`.
    A round whose solution is not finite keeps the previous one.
    """

    def body(carry, hard):
        y, steps, ok = carry
        w = weights_at(y, hard)
        new, result, n = solve(y, w)
        return (_finite_or(new, y), steps + n, ok & (result == optx.RESULTS.successful)), (w, result, n)

    (y, steps, ok), (ws, results, round_steps) = jax.lax.scan(
        body, (y0, jnp.asarray(0), jnp.asarray(True)), jnp.asarray(hard_flags)
    )
    return Rounds(
        y, steps, ok, jax.tree.map(lambda w: w[-1], ws), _overall(ok, results), results, round_steps
    )


def _finite_or(new: PyTree, y: PyTree) -> PyTree:
    """A round's solution `new`, or the previous one `y` where `new` is not finite."""
    finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in jax.tree.leaves(new)]))
    return jax.tree.map(lambda a, b: jnp.where(finite, a, b), new, y)


def _overall(ok, results: optx.RESULTS) -> optx.RESULTS:
    """`successful` when every round was, else the first failing round's code."""
    first_bad = jnp.argmax(results != optx.RESULTS.successful)
    return optx.RESULTS.where(ok, optx.RESULTS.successful, jax.tree.map(lambda r: r[first_bad], results))


def irls_rounds_reweighted(
    solve: Callable[[PyTree, PyTree], tuple[PyTree, optx.RESULTS, Int[Array, ""]]],
    weights_at: Callable[[PyTree, PyTree, Bool[Array, ""]], PyTree],
    y0: PyTree,
    w0: PyTree,
    hard_flags: np.ndarray,
) -> Rounds:
    """`irls_rounds` whose `weights_at(y, w, hard)` also sees the weights `w`
    that `y` was solved with (`w0` for the start `y0`): what a deletion
    residual needs (`deletion_residuals`)."""

    def solve_(yw, w):
        new, result, n = solve(yw[0], w)
        return (new, w), result, n

    out = irls_rounds(solve_, lambda yw, hard: weights_at(yw[0], yw[1], hard), (y0, w0), hard_flags)
    return out._replace(value=out.value[0])


def irls_rounds_evaluated(
    solve: Callable[[PyTree, PyTree], tuple[PyTree, optx.RESULTS, Int[Array, ""]]],
    weights_at: Callable[[PyTree, PyTree, Bool[Array, ""]], tuple[PyTree, PyTree]],
    y0: PyTree,
    w0: PyTree,
    hard_flags: np.ndarray,
    at_last: Callable[[PyTree], PyTree] = lambda y: y,
) -> tuple[Rounds, PyTree]:
    """`irls_rounds_reweighted` whose `weights_at(y, w, hard) -> (weights, aux)` also returns
    what it computed on the way (residuals, a covariance), and the `aux` of one more
    evaluation: at `at_last(y)`, `y` the last round's solution, with the weights it was solved
    with. That is what a summary at the solution needs; here it is a last step of the same
    scan, which does not solve, so the evaluation is in the program once rather than twice.
    The rounds and their results are `irls_rounds_reweighted`'s."""
    solve_, (_, result0, steps0) = traced(solve, y0, jax.tree.map(jnp.zeros_like, w0))
    n = len(hard_flags)
    flags = (jnp.asarray(np.append(hard_flags, False)), jnp.asarray(np.arange(n + 1) < n))

    def body(carry, xs):
        y, w_prev, steps, ok = carry
        hard, solving = xs
        point = jax.tree.map(lambda a, b: jnp.where(solving, a, b), y, at_last(y))
        w, aux = weights_at(point, w_prev, hard)

        def run(y, w):
            new, result, n = solve_(y, w)
            return _finite_or(new, y), result, n

        new, result, n = jax.lax.cond(solving, run, lambda y, w: (y, result0, steps0), y, w)
        w_used = jax.tree.map(lambda a, b: jnp.where(solving, a, b), w, w_prev)
        ok = ok & (~solving | (result == optx.RESULTS.successful))
        return (new, w_used, steps + n, ok), (result, n, aux)

    init = (y0, w0, jnp.asarray(0), jnp.asarray(True))
    (y, w, steps, ok), (results, round_steps, auxes) = jax.lax.scan(body, init, flags)
    results, round_steps = jax.tree.map(lambda r: r[:n], (results, round_steps))
    rounds = Rounds(y, steps, ok, w, _overall(ok, results), results, round_steps)
    return rounds, jax.tree.map(lambda a: a[-1], auxes)
