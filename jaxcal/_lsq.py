"""The least-squares kit every jaxcal solver shares.

Every estimator in jaxcal is a Levenberg-Marquardt solve of whitened
residuals (optimistix), followed by the Gauss-Newton covariance of the free
parameters and, for the kinematic problems, a rank-revealing search for the
parameters the data cannot see. This module writes each of those once:

- `solve`: optimistix's Levenberg-Marquardt with jaxcal's options (`LMOptions`),
  returning optimistix's own `Solution` (its `result` codes, its `num_steps`).
- `solve_normal`: the same iteration on the normal equations by
  `jaxcal._schur`'s lean loop, for the large one-off programs (the
  refinement, the clock fit, the hand-eye pose solves) whose compile time a
  user waits for: a smaller program, the same steps and optimum.
- `freeze`: parameters held at their start value (a pytree or flat mask).
- `independent_columns`: the greedy, column-pivoted Gram-Schmidt of a
  Jacobian in a fixed priority order (which parameters are identifiable).
- `covariance`: $\\hat\\sigma^2 (J^T J)^+$ over the free parameters, from one
  SVD (`jaxcal._linalg.gauss_newton_covariance`, safe to batch on a CPU),
  with the residual-variance scaling $\\hat\\sigma^2 = \\|r\\|^2 / (m - n)$.
- `normal_pinv`, `normal_inverse`: $\\sigma^2 H^{+}$ (over the free parameters) and
  $\\sigma^2 H^{-1}$ of a normal matrix a solver hands over (`normal_inverse` also for
  NumPy): every covariance jaxcal computes goes through this module.
- `cluster_covariance`: the cluster-robust (sandwich) covariance
  $B (\\sum_g J_g^T r_g r_g^T J_g) B$ of errors shared within clusters (a view's corners).
- `larger_covariance_np`: NumPy, the larger of two covariances along every direction.
- `hac_covariance`, `newey_west_lags`: the Bartlett-kernel (HAC) sandwich of errors correlated
  between neighbouring clusters (views along the capture), adjusted to be unbiased with
  independent errors, and the rule of thumb for its lags.
- `closed_form_jvp`: a residual function whose derivative with respect to
  its parameters is a hand-written Jacobian (checked against autodiff in the
  tests) and with respect to the data is autodiff.
- `BATCHED_ENTRY_POINTS`: the vmapped programs whose LAPACK calls must stay
  ordered (see `jaxcal._linalg`); the tests run the checker on each.
"""

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jax.custom_derivatives import SymbolicZero
from jax.extend.core import jaxpr_as_fun
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, Bool, Float, PyTree

from ._linalg import gauss_newton_covariance
from ._schur import NormalEquations, normal_least_squares

#: Every vmapped program jaxcal runs, by import path: each must keep its
#: decompositions ordered (`jaxcal._linalg.concurrent_decompositions` returns
#: `[]`). `tests/test_linalg.py` checks every entry.
BATCHED_ENTRY_POINTS = (
    "jaxcal._arcfit.fit_arc",
    "jaxcal._axisfit.fit_axes",
    "jaxcal._montecarlo.run_trial",
    "jaxcal._pointfit.cross_validate",
    "jaxcal._refine.refine",
    "jaxcal.calibrate_hand_eye",
)


class LMOptions(eqx.Module):
    """Levenberg-Marquardt settings (see `optimistix.LevenbergMarquardt`).

    The residuals jaxcal solves are whitened, so `atol` is in units of the
    noise: a step that moves every prediction by less than `atol` standard
    deviations stops the solve. `normal_cholesky` solves each step's normal
    equations by Cholesky (for tall, Jacobi-scaled, well-conditioned
    Jacobians: far faster than lineax's default QR on a CPU).
    """

    rtol: float = 1e-8
    atol: float = 3e-2
    max_steps: int = eqx.field(static=True, default=100)
    throw: bool = eqx.field(static=True, default=False)
    normal_cholesky: bool = eqx.field(static=True, default=False)

    def solver(self) -> optx.LevenbergMarquardt:
        linear_solver = lx.Normal(lx.Cholesky()) if self.normal_cholesky else lx.QR()
        lm = optx.LevenbergMarquardt(rtol=self.rtol, atol=self.atol, linear_solver=linear_solver)
        return eqx.tree_at(lambda s: s.search, lm, ConvergedStepTrustRegion(rtol=self.rtol, atol=self.atol))


def within_tolerance(diff: PyTree, ref: PyTree, rtol, atol) -> Bool[Array, ""]:
    """optimistix's Cauchy test with the max norm: every `|diff| < atol + rtol |ref|`."""
    d, r = ravel_pytree(diff)[0], ravel_pytree(ref)[0]
    return jnp.max(jnp.abs(d) / (atol + rtol * jnp.abs(r)), initial=0.0) < 1


class ConvergedStepTrustRegion(optx.ClassicalTrustRegion):
    """optimistix's trust region, which also accepts a step that passes the
    termination test (parameters and residuals both within `atol + rtol|.|`),
    whatever the sign of its cost change; the solve then stops there.

    At the optimum the predicted reduction of a Gauss-Newton step is ~0 and the
    actual change is the residuals' evaluation error (1e-12 of the cost for an
    arc fit whose intermediate terms are 1e5 noise sigmas): the classical test
    rejects step after step, shrinking the radius, until `max_steps`. A fit
    warm-started at its answer (the last round of an iteratively reweighted
    fit) "failed" that way after 100 steps under one XLA compiler and converged
    in 3 under another. The steps accepted here move the answer by less than
    the tolerance the solve was asked for."""

    rtol: float = eqx.field(kw_only=True, default=1e-8)
    atol: float = eqx.field(kw_only=True, default=3e-2)

    def step(self, first_step, y, y_eval, f_info, f_eval_info, state):
        step_size, accept, result, new_state = super().step(first_step, y, y_eval, f_info, f_eval_info, state)
        converged = within_tolerance(
            jax.tree.map(jnp.subtract, y_eval, y), y_eval, self.rtol, self.atol
        ) & within_tolerance(
            jax.tree.map(jnp.subtract, f_eval_info.residual, f_info.residual),
            f_eval_info.residual,
            self.rtol,
            self.atol,
        )
        take = converged & ~accept & ~first_step
        step_size = jnp.where(take, state.step_size, step_size)
        new_state = eqx.tree_at(lambda s: s.step_size, new_state, step_size)
        return step_size, accept | take, result, new_state


def solve(fn: Callable, y0: PyTree, args: Any, options: LMOptions) -> optx.Solution:
    """`optx.least_squares(fn, LM, y0, args)`: optimistix's `Solution`, whose
    `result` and `stats["num_steps"]` the callers report as they are."""
    return optx.least_squares(
        fn, options.solver(), y0, args, max_steps=options.max_steps, throw=options.throw
    )


def solve_normal(fn: Callable, y0: PyTree, args: Any, options: LMOptions) -> optx.Solution:
    """`solve`'s Levenberg-Marquardt iteration on the normal equations $(J^TJ + \\lambda I)\\delta = -J^Tr$
    (Jacobi-scaled Cholesky), by `jaxcal._schur.normal_least_squares`: the Jacobian by forward
    mode over the flattened parameters, reduced at once to $J^TJ$ and $J^Tr$ (the loop keeps
    no Jacobian).

    Optimistix's trust region and termination test (`ConvergedStepTrustRegion`), so the same
    steps and the same optimum as `solve` up to round-off (`tests/test_schur.py`), in a program
    that traces in about half the time and compiles faster than optimistix's general one
    (`benchmarks/compile.py`; docs/performance.md). For tall, well-conditioned (whitened,
    scaled) Jacobians, where the
    normal equations are the right linear solve anyway (`options.normal_cholesky` is
    implied). **Returns:** an `optx.Solution`
    (`value`, `result`, `stats["num_steps"]`) like `solve`'s.
    """
    flat0, unravel = ravel_pytree(y0)

    def normal(x, a):
        r, J = value_and_jacfwd(lambda z: ravel_pytree(fn(unravel(z), a))[0], x)
        return r, NormalEquations(H=J.T @ J, e=J.T @ r)

    sol = normal_least_squares(
        normal, flat0, args, rtol=options.rtol, atol=options.atol, max_steps=options.max_steps
    )
    value = unravel(sol.x)
    if options.throw:
        value = eqx.error_if(
            value, sol.result != optx.RESULTS.successful, "Levenberg-Marquardt did not converge"
        )
    stats = {"num_steps": sol.num_steps, "max_steps": options.max_steps}
    return optx.Solution(value=value, result=sol.result, aux=None, stats=stats, state=None)


def value_and_jacfwd(f: Callable, x: Array) -> tuple[Array, Array]:
    """`(f(x), jax.jacfwd(f)(x))` from one forward-mode pass: the residuals are the pass's
    primal output, not a second evaluation, so a program that needs both traces, lowers
    and compiles the model once rather than twice."""
    J, r = jax.jacfwd(lambda z: (lambda y: (y, y))(f(z)), has_aux=True)(x)
    return r, J


def traced(f: Callable, *args) -> tuple[Callable, PyTree]:
    """`f` traced once at `args` (arrays or `jax.ShapeDtypeStruct`s): `(g, zeros)`, `g(*a)`
    replaying the trace (the same program as `f(*a)`) and `zeros` an output of `f`'s structure,
    shapes and dtypes. For a `lax.cond` that either runs `f` or passes values through, and for
    a loop's carry: the branch replays `f`'s jaxpr rather than running its Python again."""
    closed, shape = jax.make_jaxpr(f, return_shape=True)(*args)
    fun = jaxpr_as_fun(closed)
    tree = jax.tree.structure(shape)

    def g(*a):
        return jax.tree.unflatten(tree, fun(*jax.tree.leaves(a)))

    return g, jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), shape)


def start_and_solution(evaluate: Callable, x0: Array, solve: Callable) -> tuple[Any, Any, Any]:
    """`(e0, out, e1)`: `e0 = evaluate(x0)`, `out = solve(e0)` (a tuple whose first entry is
    the solution `x`) and `e1 = evaluate(x)`, with `evaluate` in the program once.

    A solver that needs its model's Jacobian at the start (a scaling, an identifiability
    search) and at the solution (the covariance) would otherwise hold two copies of it, and a
    program traces, lowers, compiles and loads in proportion to its size. Here the two
    evaluations are the two steps of a `lax.scan`; the first also solves (`lax.cond`, whose
    predicate is the step, so only one branch runs, batched or not)."""
    evaluate_, e_zeros = traced(evaluate, x0)
    solve_, out_zeros = traced(solve, e_zeros)

    def step(carry, first):
        x, out = carry
        e = evaluate_(x)
        out = jax.lax.cond(first, solve_, lambda _: out, e)
        return (jnp.where(first, out[0], x), out), e

    (_, out), es = jax.lax.scan(step, (x0, out_zeros), jnp.array([True, False]))
    return jax.tree.map(lambda a: a[0], es), out, jax.tree.map(lambda a: a[1], es)


def freeze(tree: PyTree, free: PyTree) -> PyTree:
    """`tree` with the entries where `free` is 0 (or False) set to zero: the
    parameters are corrections about a start, so zero holds them there."""
    return jax.tree.map(lambda x, f: x * jnp.asarray(f, x.dtype), tree, free)


def independent_columns(
    J: Float[Array, "m n"],
    order: np.ndarray,
    *,
    tol: float,
    candidates: Bool[Array, " n"] | None = None,
) -> tuple[Bool[Array, " n"], Float[Array, " n"]]:
    """Which parameters the Jacobian determines, by greedy column selection.

    The columns are normalised and visited in `order`; a column (among the
    `candidates`) is kept when its component orthogonal to the span of the
    kept ones is above `tol` (a column-pivoted, rank-revealing Gram-Schmidt
    with a fixed pivot order, re-orthogonalised once). Pure and vmappable.

    **Returns:** `(free, independence)`: each column's relative distance from
    the span of the columns kept before it.
    """
    norms = jnp.linalg.norm(J, axis=0)
    Jn = J / jnp.where(norms > 0, norms, 1.0)
    m, n = J.shape
    cand = jnp.ones(n, bool) if candidates is None else jnp.asarray(candidates, bool)
    order = jnp.asarray(order)

    def body(i, carry):
        basis, keep, indep, count = carry
        j = order[i]
        col = Jn[:, j]
        resid = col - basis @ (basis.T @ col)
        resid = resid - basis @ (basis.T @ resid)  # re-orthogonalise
        r = jnp.linalg.norm(resid)
        ok = (r > tol) & (norms[j] > 0) & cand[j]
        basis = jnp.where(ok, basis.at[:, count].set(resid / jnp.where(ok, r, 1.0)), basis)
        return basis, keep.at[j].set(ok), indep.at[j].set(r), count + ok

    init = (jnp.zeros((m, n), J.dtype), jnp.zeros(n, bool), jnp.zeros(n, J.dtype), jnp.asarray(0))
    _, keep, indep, _ = jax.lax.fori_loop(0, n, body, init)
    return keep, indep


def independent_columns_normal(
    H: Float[Array, "n n"],
    order: np.ndarray,
    *,
    tol: float,
    candidates: Bool[Array, " n"] | None = None,
) -> tuple[Bool[Array, " n"], Float[Array, " n"]]:
    """`independent_columns` from the normal matrix $H = J^TJ$ alone: the same
    greedy selection on the Gram matrix of the normalised columns, $O(n^2)$ a
    column instead of $O(mn)$. A column's squared distance from the kept span
    is $G_{jj} - \\|Q^T G_{:j}\\|^2$ (the basis kept as coefficients $Q$ of the
    columns), so distances under about $10^{-7}$ lose their digits: for the
    thresholds of `jaxcal.stages.kinds.STRICT_TOL`, not `DEFAULT_TOL`."""
    d = jnp.sqrt(jnp.maximum(jnp.diag(H), 0.0))
    inv = jnp.where(d > 0, 1.0 / jnp.where(d > 0, d, 1.0), 0.0)
    G = H * inv[:, None] * inv[None, :]
    n = H.shape[0]
    cand = jnp.ones(n, bool) if candidates is None else jnp.asarray(candidates, bool)
    order = jnp.asarray(order)

    def body(i, carry):
        Q, keep, indep, count = carry
        j = order[i]
        p = Q.T @ G[:, j]  # inner products of the basis with column j
        r = jnp.sqrt(jnp.maximum(G[j, j] - p @ p, 0.0))
        ok = (r > tol) & (d[j] > 0) & cand[j]
        q = (jnp.zeros(n, H.dtype).at[j].set(1.0) - Q @ p) / jnp.where(ok, r, 1.0)
        Q = jnp.where(ok, Q.at[:, count].set(q), Q)
        return Q, keep.at[j].set(ok), indep.at[j].set(r), count + ok

    init = (jnp.zeros((n, n), H.dtype), jnp.zeros(n, bool), jnp.zeros(n, H.dtype), jnp.asarray(0))
    _, keep, indep, _ = jax.lax.fori_loop(0, n, body, init)
    return keep, indep


def covariance_normal(
    H: Float[Array, "n n"], free: Bool[Array, " n"], sigma2: Float[Array, ""] | float = 1.0
) -> Float[Array, "n n"]:
    """`covariance` from the normal matrix $H = J^TJ$: $\\sigma^2 (DHD)^{+}$ scaled back
    ($D$ the inverse column norms of the free columns; frozen ones get zero rows and
    columns), the pseudo-inverse cut where `gauss_newton_covariance` cuts (singular
    values of the scaled $J$ under $\\sqrt{10 n \\epsilon}$ of the largest)."""
    f = jnp.asarray(free, H.dtype)
    H = H * f[:, None] * f[None, :]
    d = jnp.sqrt(jnp.maximum(jnp.diag(H), 0.0))
    inv = jnp.where(d > 0, 1.0 / jnp.where(d > 0, d, 1.0), 0.0)
    w, V = jnp.linalg.eigh(H * inv[:, None] * inv[None, :])
    sv = jnp.sqrt(jnp.maximum(w, 0.0))
    rtol = float(np.sqrt(10 * H.shape[0] * np.finfo(np.dtype(H.dtype)).eps))
    keep = sv > rtol * jnp.max(sv)
    inv_w = jnp.where(keep, 1.0 / jnp.where(keep, w, 1.0), 0.0)
    A = V * inv[:, None]
    return sigma2 * (A * inv_w[None, :]) @ A.T


def normal_pinv(
    H: Float[Array, "n n"], free: Float[Array, " n"] | None = None, sigma2: Float[Array, ""] | float = 1.0
) -> Float[Array, "n n"]:
    """The covariance $\\sigma^2 H^{+}$ of a normal matrix $H = J^TJ$ that may be singular, by a
    Hermitian pseudo-inverse (`jnp.linalg.pinv`'s cut: eigenvalues under $10 n \\epsilon$ of the
    largest): pure, jittable. With `free` (1 free, 0 frozen), the inverse over the free
    parameters only: $(H + \\mathrm{diag}(1 - f))^{+}$ with the frozen rows and columns then
    zeroed, so a frozen (zero) column neither enters the cut nor takes a variance. Unlike
    `covariance`, no column scaling: for normal matrices whose columns share one unit (whitened,
    m and rad of one pose) or whose solver hands over $H$ rather than $J$."""
    if free is None:
        cov = jnp.linalg.pinv(H, hermitian=True)
    else:
        cov = jnp.linalg.pinv(H + jnp.diag(1.0 - free), hermitian=True) * free[:, None] * free[None, :]
    return cov if isinstance(sigma2, float) and sigma2 == 1.0 else sigma2 * cov


def normal_inverse(H, sigma2=1.0):
    """The covariance $\\sigma^2 H^{-1}$ of a full-rank normal matrix $H = J^TJ$ (a Gauss-Newton
    fit of a few well-determined parameters: a pose, a drift twist): NumPy in, NumPy out
    (`np.linalg.inv`, for the host-side fits), JAX otherwise (jittable). The caller has
    checked the rank (or a singular $H$ is a bug there): no cut, unlike `normal_pinv`."""
    inv = np.linalg.inv(H) if isinstance(H, np.ndarray) else jnp.linalg.inv(H)
    return inv if isinstance(sigma2, float) and sigma2 == 1.0 else sigma2 * inv


def residual_variance(r: Float[Array, "..."], n_obs, n_free) -> Float[Array, ""]:
    """$\\hat\\sigma^2 = \\|r\\|^2 / \\max(m - n, 1)$ of whitened residuals."""
    return jnp.sum(r**2) / jnp.maximum(n_obs - n_free, 1.0)


def covariance(
    J: Float[Array, "m n"], free: Bool[Array, " n"] | None = None, sigma2: Float[Array, ""] | float = 1.0
) -> tuple[Float[Array, "n n"], Float[Array, " n"], Float[Array, "n n"]]:
    """The Gauss-Newton covariance $\\sigma^2 (J^T J)^+$ of the free columns
    (frozen ones: zero rows and columns), with the singular values and right
    singular vectors of the column-normalised `J`, from one SVD."""
    if free is not None:
        J = J * jnp.asarray(free, J.dtype)[None, :]
    cov, sv, Vt = gauss_newton_covariance(J)
    return sigma2 * cov, sv, Vt


def instantiate(t):
    """Materialise a symbolic zero tangent (`float0` for integer and boolean inputs)."""
    if not isinstance(t, SymbolicZero):
        return t
    if t.dtype == jax.dtypes.float0:
        return np.zeros(t.shape, jax.dtypes.float0)
    return jnp.zeros(t.shape, t.dtype)


def closed_form_jvp(
    primal: Callable[[Any, Any], Array],
    terms: Callable[[Any, Any], tuple[Array, Array]],
    autodiff: Callable[[Any, Any], Array],
) -> Callable[[Any, Any], Array]:
    """A residual function `f(params, args)` with a hand-written Jacobian.

    `primal(params, args)` computes the residuals; `terms(params, args)`
    returns them with their Jacobian with respect to the flattened `params`
    (`ravel_pytree` order), shaped `(r.size, n)` or `r.shape + (n,)`;
    `autodiff(params, args)` computes the same residuals in plain,
    differentiable JAX (the oracle the tests check `terms` against). The
    derivative with respect to `params` is `J @ t` (one small matrix product,
    so a solver that materialises the linearisation pays nothing per basis
    tangent); with respect to `args` (e.g. implicit differentiation through a
    fit) it is autodiff of `autodiff`.
    """

    @jax.custom_jvp
    def f(params, args):
        return primal(params, args)

    def jvp(primals, tangents):
        params, args = primals
        t_params, t_args = tangents
        is_zero = lambda x: isinstance(x, SymbolicZero)  # noqa: E731
        inst = lambda tree: jax.tree.map(instantiate, tree, is_leaf=is_zero)  # noqa: E731
        if not all(is_zero(t) for t in jax.tree.leaves(t_args, is_leaf=is_zero)):
            return jax.jvp(autodiff, (params, args), (inst(t_params), inst(t_args)))
        r, J = terms(params, args)
        t = ravel_pytree(inst(t_params))[0]
        return r, (J.reshape(-1, t.shape[0]) @ t).reshape(r.shape)

    f.defjvp(jvp, symbolic_zeros=True)
    f.__doc__ = primal.__doc__
    return f


def cluster_covariance(
    bread: Float[Array, "n n"], scores: Float[Array, "views n"], n_obs=None
) -> Float[Array, "n n"]:
    """The cluster-robust (sandwich) covariance of a least-squares solve: pure, jittable.

    $\\Sigma_{cl} = c\\, B \\big(\\sum_g s_g s_g^T\\big) B$, $B = (J^TJ)^+$ the solve's
    bread (its Gauss-Newton covariance over $\\hat\\sigma^2$, `covariance` with
    `sigma2=1`), $s_g = J_g^T r_g$ the gradient of cluster $g$'s residuals at the
    solution, and the small-sample factor $c = \\frac{G}{G-1}\\frac{N-1}{N-K}$ ($G$
    clusters with a non-zero gradient, $N$ observations, $K$ free parameters: the CR1
    correction, Cameron and Miller 2015, section VI.A). Unlike $\\hat\\sigma^2 B$ it does
    not take the errors within a cluster to be independent: errors shared by a view's
    corners (the detector's view-coherent shift, a pose error) enter through
    $s_g s_g^T$ at their size, where $\\hat\\sigma^2 B$ sees them as a little extra noise
    per corner. With independent errors of variance $\\sigma^2$ its expectation is
    $\\sigma^2 B$. What the solution absorbs of an error common to many clusters leaves
    no trace in the residuals, so no residual-based covariance sees it.

    **Arguments:** `bread` `(n, n)` (zero rows and columns where frozen); `scores`
    `(clusters, n)`, per cluster $J_g^Tr_g$ (all-zero rows, e.g. padding, are not
    clusters); `n_obs`: $N$ (default: no $(N-1)/(N-K)$ factor).

    **Returns:** `(n, n)`.
    """
    s = jnp.asarray(scores)
    G = jnp.sum(jnp.any(s != 0.0, axis=1))
    K = jnp.sum(jnp.diag(bread) > 0)
    c = G / jnp.maximum(G - 1.0, 1.0)
    if n_obs is not None:
        c = c * (n_obs - 1.0) / jnp.maximum(n_obs - K, 1.0)
    return c * (bread @ (s.T @ s) @ bread)


def larger_covariance(
    J: Float[Array, "m n"],
    sv: Float[Array, " n"],
    Vt: Float[Array, "n n"],
    sigma2: Float[Array, ""],
    other: Float[Array, "n n"],
    margin: Float[Array, ""] | float = 0.0,
) -> Float[Array, "n n"]:
    """The model's covariance $\\hat\\sigma^2 (J^TJ)^+$, replaced by `other` along the
    directions where `other` is larger by more than the factor $1 +$ `margin`: pure, jittable.

    With $(J^TJ)^+ = LL^T$ from `covariance`'s SVD of the column-scaled `J` (`sv`, `Vt`:
    $L = DVS^{-1}$) and $L^+\\,\\mathrm{other}\\,L^{+T} / \\hat\\sigma^2 = Q\\Lambda Q^T$ (one
    `eigh`, after the SVD), it is $\\hat\\sigma^2 LQ\\,\\mathrm{diag}(\\lambda')\\,Q^TL^T$,
    $\\lambda' = \\lambda$ where $\\lambda > 1 +$ `margin`, else 1 (the generalised
    eigenvalues of `other` against the model's). A `margin` of twice a sandwich's
    sampling spread ($2\\sqrt{2/G}$ for $G$ clusters) keeps the model's covariance where the
    errors are independent and the sandwich only scatters about it. Directions the SVD
    cut as unidentifiable stay out, as in `covariance`.
    """
    n = J.shape[1]
    rtol = float(np.sqrt(10 * n * np.finfo(np.dtype(J.dtype)).eps))
    norms = jnp.linalg.norm(J, axis=0)
    scale = jnp.where(norms > 0, 1.0 / jnp.where(norms > 0, norms, 1.0), 0.0)
    keep = sv > rtol * sv[0]
    L = (Vt.T * scale[:, None]) * jnp.where(keep, 1.0 / jnp.where(keep, sv, 1.0), 0.0)[None, :]
    L_pinv = jnp.where(keep, sv, 0.0)[:, None] * Vt * norms[None, :]
    lam, Q = jnp.linalg.eigh(L_pinv @ other @ L_pinv.T / jnp.maximum(sigma2, 1e-300))
    ratio = jnp.where(lam > 1.0 + margin, lam, 1.0)
    LQ = L @ Q
    return sigma2 * (LQ * ratio[None, :]) @ LQ.T


def larger_covariance_np(a: np.ndarray, b: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """NumPy: the covariance that is, along every direction of $a$'s generalised eigenvectors, the
    larger of `a` and `b` by more than the factor $1 +$ `margin` (else `a`'s): $L Q \\Lambda' Q^T L^T$ with
    $a = L L^T$, $L^{-1} b L^{-T} = Q \\Lambda Q^T$, $\\lambda' = \\lambda$ where $\\lambda > 1 +$ `margin`,
    else 1 (`larger_covariance`'s rule on two covariances; $a$'s null space stays out)."""
    lam, V = np.linalg.eigh(0.5 * (a + a.T))
    keep = lam > lam.max() * 1e-14
    L = V[:, keep] * np.sqrt(lam[keep])
    Li = np.linalg.pinv(L)
    mu, Q = np.linalg.eigh(Li @ (0.5 * (b + b.T)) @ Li.T)
    M = L @ Q
    return M @ np.diag(np.where(mu > 1.0 + margin, mu, 1.0)) @ M.T


def newey_west_lags(clusters: int) -> int:
    """The Bartlett kernel's lags $L = \\lfloor 4 (G/100)^{2/9} \\rfloor$ for $G$ ordered
    clusters (Newey and West 1994's rule of thumb; 4 for 240 views)."""
    return int(np.floor(4.0 * (max(int(clusters), 1) / 100.0) ** (2.0 / 9.0)))


def hac_covariance(
    bread: Float[Array, "n n"],
    scores: Float[Array, "clusters n"],
    information: Float[Array, "clusters n n"],
    lags: int,
) -> tuple[Float[Array, "n n"], Float[Array, ""]]:
    """A least-squares solve's covariance under errors correlated between neighbouring clusters
    (views in capture order): a Bartlett-kernel HAC sandwich, bias-adjusted: pure, jittable.

    $\\hat S = \\sum_{u,v} k_{uv}\\, s_u s_v^T$, $s_g = J_g^Tr_g$ in the clusters' order (all-zero rows,
    e.g. padding, are skipped: the kernel counts the used clusters' positions), Bartlett weights
    $k_{uv} = \\max(0, 1 - |u - v|/(L + 1))$ ($L$ = `lags`; PSD, so $\\hat S$ is). Residuals $r = Me$,
    $M = I - JBJ^T$, lose what the solution absorbs, the more the wider the kernel: with independent
    errors of variance $\\sigma^2$, $E[\\hat S] = \\sigma^2 (J^TJ - D)$, $D = \\sum_{u,v} k_{uv} A_u B A_v$
    ($A_g = J_g^TJ_g$ = `information`, $B$ = `bread` $= (J^TJ)^+$). The covariance is
    $W T (W^T\\hat S W) T W^T$ with $WW^T = B$ and $T = (W^T(J^TJ - D)W)^{-1/2}$, so that it is
    unbiased, $\\sigma^2 B$, when the errors are independent (the CR2 idea of Bell and McCaffrey
    2002, for a kernel); with correlated errors it keeps the kernel's truncation and the part of
    the correlation the solution absorbs as biases (both downwards). `lags = 0` is the per-cluster
    sandwich so adjusted.

    **Returns:** `(cov (n, n), effective clusters)`: $G_{eff} = \\mathrm{tr}(K)^2 / \\mathrm{tr}(K^2)$,
    the sandwich's relative spread along a fixed direction being about $\\sqrt{2/G_{eff}}$.
    """
    s = jnp.asarray(scores)
    used = jnp.any(s != 0.0, axis=1)
    pos = jnp.cumsum(used) - 1.0
    K = jnp.clip(1.0 - jnp.abs(pos[:, None] - pos[None, :]) / (lags + 1.0), 0.0, None)
    K = K * used[:, None] * used[None, :]
    A = jnp.asarray(information) * used[:, None, None]
    # A factor W W^T = B of the column-scaled bread (the result does not depend on which).
    d = jnp.sqrt(jnp.maximum(jnp.diag(bread), 0.0))
    inv = jnp.where(d > 0, 1.0 / jnp.where(d > 0, d, 1.0), 0.0)
    lam, U = jnp.linalg.eigh(bread * inv[:, None] * inv[None, :])
    rtol = float(np.sqrt(10 * bread.shape[0] * np.finfo(np.dtype(bread.dtype)).eps))
    lam = jnp.where(lam > bread.shape[0] * np.finfo(np.dtype(bread.dtype)).eps * jnp.max(lam), lam, 0.0)
    W = d[:, None] * U * jnp.sqrt(lam)[None, :]
    At = jnp.einsum("pi,gpq,qj->gij", W, A, W)  # W^T A_g W; W^T D W = sum_uv k_uv At_u At_v
    E = jnp.sum(At, axis=0) - jnp.einsum("uij,ujk->ik", At, jnp.einsum("uv,vjk->ujk", K, At))
    E = 0.5 * (E + E.T)
    mu, Q = jnp.linalg.eigh(E)
    keep = mu > rtol * jnp.max(mu)
    T = (Q * jnp.where(keep, 1.0 / jnp.sqrt(jnp.where(keep, mu, 1.0)), 0.0)[None, :]) @ Q.T
    sw = s @ W
    WT = W @ T
    cov = WT @ (sw.T @ K @ sw) @ WT.T
    return cov, jnp.trace(K) ** 2 / jnp.maximum(jnp.sum(K**2), 1e-300)
