"""Levenberg-Marquardt for a few global and many small local unknowns, by the Schur complement.

**Problem.** Minimise $\\tfrac12\\sum_{b=1}^{B}\\|r_b(g, l_b)\\|^2$ over global
parameters $g \\in \\mathbb{R}^{n_g}$ ($n_g$ small) and local parameters
$l_b \\in \\mathbb{R}^{p}$, one block per residual group: group $b$'s
residuals $r_b \\in \\mathbb{R}^{m}$ depend on $g$ and on its own $l_b$ only
(an arc fit without encoders: $g$ the axis and marker zero poses, $l_b$ the
joint angle of frame $b$, $p = 1$; a hand-eye calibration with per-pose robot
corrections: $p = 6$). With $p = 0$ it is plain Levenberg-Marquardt on the
normal equations of $g$ (the hand-eye pixel solve with exact robot poses: a
dozen unknowns, thousands of residuals, where this loop's few operations per
step beat optimistix's general one).

**Normal equations by blocks.** With $A_b = \\partial r_b/\\partial g$
($m \\times n_g$) and $C_b = \\partial r_b/\\partial l_b$ ($m \\times p$), the
damped Gauss-Newton step $(J^TJ + \\lambda I)\\,\\delta = -J^Tr$ reads

$$\\begin{bmatrix} H + \\lambda I & W \\\\ W^T & U + \\lambda I \\end{bmatrix}
\\begin{bmatrix} \\delta_g \\\\ \\delta_l \\end{bmatrix}
= -\\begin{bmatrix} \\epsilon_g \\\\ \\epsilon_l \\end{bmatrix},$$

$H = \\sum_b A_b^TA_b$, $W_b = A_b^TC_b$, $U_b = C_b^TC_b$ (block diagonal),
$\\epsilon_g = \\sum_b A_b^Tr_b$, $\\epsilon_b = C_b^Tr_b$. Eliminating the
local blocks ($V_b = U_b + \\lambda I$) leaves the reduced camera system of
bundle adjustment,

$$S\\,\\delta_g = -\\epsilon_g + \\sum_b W_b V_b^{-1}\\epsilon_b, \\qquad
S = H + \\lambda I - \\sum_b W_b V_b^{-1} W_b^T,$$

then back-substitution $\\delta_{l_b} = -V_b^{-1}(\\epsilon_b + W_b^T\\delta_g)$.
Time and memory are $O(B\\,m\\,(n_g + p)^2 + n_g^3)$: linear in the number of
blocks, where the dense Jacobian is $Bm \\times (n_g + Bp)$ and its QR cubic.
The $p \\times p$ blocks are solved by an unrolled Cholesky factorisation
(elementwise arithmetic vectorised over blocks, no LAPACK call), the
$n_g \\times n_g$ system by one LAPACK Cholesky: each step has one
decomposition, so batched programs stay free of unordered decompositions
(`jaxcal._linalg`).

**Iteration.** Exactly `jaxcal._lsq`'s Levenberg-Marquardt (optimistix's
0.1, whose trust region also takes a step that passes the termination test,
`jaxcal._lsq.ConvergedStepTrustRegion`): damping
$\\lambda = 1/\\Delta$ on every parameter with the trust-region size $\\Delta$
starting at 1; a step is accepted when the actual decrease of
$\\tfrac12\\|r\\|^2$ is at least 0.01 of the Gauss-Newton prediction
$\\tfrac12(\\|J\\delta + r\\|^2 - \\|r\\|^2)$ (the first evaluation always is),
$\\Delta$ grows by 3.5 when it is above 0.99 and shrinks by 0.25 when a step is
rejected; it stops at an accepted step with
$\\max_i |\\Delta y_i| / (a_{tol} + r_{tol}|y_i|) < 1$ and
$\\max_j |\\Delta r_j| / (a_{tol} + r_{tol}|r_j|) < 1$
(`optimistix`'s Cauchy termination with the max norm, over $g$ and $l$
together). On the same problem it takes the same steps as
`jaxcal._lsq.solve(fn, y0, args, LMOptions(rtol, atol))` up to
floating-point round-off (the normal equations here, QR there). The status
is `optx.RESULTS.successful` or `optx.RESULTS.nonlinear_max_steps_reached`.
Unlike optimistix there is no implicit adjoint: the solution is not meant to
be differentiated with respect to `args` (forward mode runs through the
loop; reverse mode through `lax.while_loop` is not supported by JAX).

**Covariance.** At $\\lambda = 0$ the inverse of the normal matrix has the
blocks $\\Sigma_{gg} = S^{-1}$ (the marginal covariance of $g$),
$\\Sigma_{g l_b} = -S^{-1}W_bU_b^{-1}$ and
$\\Sigma_{l_b l_b} = U_b^{-1} + U_b^{-1}W_b^TS^{-1}W_bU_b^{-1}$: unscaled
(multiply by $\\hat\\sigma^2$ for a noise level estimated from the residuals).
$S^{-1}$ is a pseudo-inverse (Jacobi-scaled, eigenvalues under
$10\\,n_g\\,\\epsilon$ of the largest dropped); a block pivot under
`1e-12` times its coordinate's largest diagonal entry of $U$ over all
blocks is an unobserved local direction and gets zero variance.

**API** (every array float64; `B` blocks, `m` residuals per block, `p` local
parameters per block; all functions pure, jittable and vmappable):

- `linearise(g, l, args) -> (r, J_g, J_l)`: the caller's model: residuals
  `(B, m)`, $\\partial r_b/\\partial g$ `(B, m, n_g)`,
  $\\partial r_b/\\partial l_b$ `(B, m, p)`. Closed forms are cheapest;
  `jacobian_by_jvp(fn)` builds one from a residual function
  `fn(g, l, args) -> (B, m)` with $n_g + p$ forward-mode products (coordinate
  $j$ of every block perturbed at once: the block structure is the colouring).
- `block_least_squares(linearise, g0, l0, args, *, rtol, atol, max_steps,
  g_mask=None, l_mask=None) -> BlockSolution`: `g0` `(n_g,)`, `l0` `(B, p)`;
  masks (bool, same shapes) freeze parameters at their start (default: all
  free). Weights (IRLS) belong in `linearise` (scale $r_b$ and both
  Jacobians by $\\sqrt{w}$).
- `normal_least_squares(normal, x0, args, *, rtol, atol, max_steps) ->
  NormalSolution`: the same iteration with no local unknowns on normal
  equations the model forms itself, `normal(x, args) -> (r, NormalEquations(H,
  e, aux))`: the loop keeps $J^TJ$ and $J^Tr$ (predicted decrease
  $e^T\\delta + \\tfrac12\\delta^TH\\delta$), not the Jacobian, so a model
  reduces its Jacobian however is cheapest (`jaxcal._lsq.solve_normal`, the
  hand-eye pixel solve).
- `block_covariance(J_g, J_l, *, g_mask=None, l_mask=None) -> BlockCovariance`:
  the blocks above (zero for frozen parameters).
- `full_covariance(J_g, J_l, *, g_mask=None, l_mask=None) -> (n, n)`: all of
  $(J^TJ)^{+}$, $n = n_g + Bp$, ordered $(g, l_1, \\dots, l_B)$, local
  cross-blocks included.
- `block_leverage(J_g, J_l, cov) -> (B, m)`: the diagonal of the hat matrix
  $J\\Sigma J^T$ (sums to the number of identifiable parameters).
"""

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

# optimistix's ClassicalTrustRegion constants (Gould et al., "Sensitivity of
# trust region algorithms to their parameters"), kept equal to reproduce its steps.
_HIGH_CUTOFF, _LOW_CUTOFF = 0.99, 0.01
_HIGH_CONSTANT, _LOW_CONSTANT = 3.5, 0.25
#: Block pivots under this fraction of their coordinate's largest diagonal are unobserved.
_BLOCK_RTOL = 1e-12

Linearise = Callable[[Array, Array, Any], tuple[Array, Array, Array]]


class BlockSolution(eqx.Module):
    """A solved block least-squares problem.

    - `g` `(n_g,)`, `l` `(B, p)`: the solution (the last accepted iterate).
    - `result`: `optx.RESULTS.successful` or `nonlinear_max_steps_reached`.
    - `num_steps`: iterations taken (accepted and rejected, as optimistix counts).
    - `residuals` `(B, m)`, `jac_g` `(B, m, n_g)`, `jac_l` `(B, m, p)`: the
      linearisation at the solution (frozen columns zero), ready for
      `block_covariance`.
    """

    g: Float[Array, " n_g"]
    l: Float[Array, "B p"]
    result: optx.RESULTS
    num_steps: Int[Array, ""]
    residuals: Float[Array, "B m"]
    jac_g: Float[Array, "B m n_g"]
    jac_l: Float[Array, "B m p"]


class BlockCovariance(eqx.Module):
    """Blocks of $(J^TJ)^{+}$ (unscaled): `gg` `(n_g, n_g)`, the marginal
    covariance of $g$; `gl` `(B, n_g, p)`, each block's cross-covariance
    with $g$; `ll` `(B, p, p)`, each block's own covariance."""

    gg: Float[Array, "n_g n_g"]
    gl: Float[Array, "B n_g p"]
    ll: Float[Array, "B p p"]


def jacobian_by_jvp(fn: Callable[[Array, Array, Any], Array]) -> Linearise:
    """A `linearise` for `block_least_squares` from a residual function
    `fn(g, l, args) -> (B, m)` whose block `b` depends on `g` and `l[b]` only.

    $n_g + p$ Jacobian-vector products: one per global coordinate, and one per
    local coordinate $j$ with $\\dot l_b = e_j$ in every block at once (block
    $b$'s residuals see only their own $\\dot l_b$).
    """

    def linearise(g, l, args):
        r, lin = jax.linearize(lambda gg, ll: fn(gg, ll, args), g, l)
        n_g, p = g.shape[0], l.shape[-1]
        tg = jnp.concatenate([jnp.eye(n_g), jnp.zeros((p, n_g))])
        tl = jnp.concatenate(
            [jnp.zeros((n_g,) + l.shape), jnp.broadcast_to(jnp.eye(p)[:, None, :], (p,) + l.shape)]
        )
        cols = jax.vmap(lin)(tg, tl)  # (n_g + p, B, m)
        return r, jnp.moveaxis(cols[:n_g], 0, -1), jnp.moveaxis(cols[n_g:], 0, -1)

    return linearise


def small_cholesky_solve(V: Float[Array, "*B p p"], R: Float[Array, "*B p c"], tol) -> Float[Array, "*B p c"]:
    """$V^{+} R$ for symmetric positive semi-definite `V`, by an unrolled Cholesky factorisation.

    Elementwise over the leading axes (no LAPACK call). A pivot at or under
    `tol` (`(p,)`, per coordinate, or a scalar) drops its direction: its row of
    the factor is zero and the solution has no component along it (for a
    direction with a zero row and column in `V`, exactly the pseudo-inverse).
    """
    p = V.shape[-1]
    tol = jnp.broadcast_to(jnp.asarray(tol, V.dtype), (p,))
    L = [[None] * p for _ in range(p)]
    inv = [None] * p
    for j in range(p):
        s = V[..., j, j] - sum((L[j][q] ** 2 for q in range(j)), jnp.zeros_like(V[..., j, j]))
        ok = s > tol[j]
        d = jnp.sqrt(jnp.where(ok, s, 1.0))
        inv[j] = jnp.where(ok, 1.0 / d, 0.0)
        L[j][j] = jnp.where(ok, d, 0.0)
        for i in range(j + 1, p):
            off = V[..., i, j] - sum((L[i][q] * L[j][q] for q in range(j)), jnp.zeros_like(s))
            L[i][j] = off * inv[j]
    # Forward substitution L y = R, then back substitution L^T x = y.
    y = [None] * p
    for i in range(p):
        acc = R[..., i, :] - sum((L[i][q][..., None] * y[q] for q in range(i)), jnp.zeros_like(R[..., i, :]))
        y[i] = acc * inv[i][..., None]
    x = [None] * p
    for i in reversed(range(p)):
        acc = y[i] - sum((L[q][i][..., None] * x[q] for q in range(i + 1, p)), jnp.zeros_like(y[i]))
        x[i] = acc * inv[i][..., None]
    return jnp.stack(x, axis=-2)


def _normal_blocks(r, Jg, Jl):
    """$H$, $W_b$, $U_b$, $\\epsilon_g$, $\\epsilon_b$ of the normal equations."""
    H = jnp.einsum("bmi,bmj->ij", Jg, Jg)
    W = jnp.einsum("bmi,bmj->bij", Jg, Jl)
    U = jnp.einsum("bmi,bmj->bij", Jl, Jl)
    eg = jnp.einsum("bmi,bm->i", Jg, r)
    el = jnp.einsum("bmi,bm->bi", Jl, r)
    return H, W, U, eg, el


def _scaled_cholesky_solve(S: Float[Array, "n n"], rhs: Float[Array, " n"]) -> Float[Array, " n"]:
    """$S^{-1}$ rhs for a positive definite `S` by a Jacobi-scaled Cholesky factorisation."""
    d = 1.0 / jnp.sqrt(jnp.diagonal(S))  # S's diagonal is at least the damping lambda > 0
    return d * jax.scipy.linalg.cho_solve(
        jax.scipy.linalg.cho_factor(S * d[:, None] * d[None, :], lower=True), d * rhs
    )


def _damped_step(r, Jg, Jl, lam):
    """$(\\delta_g, \\delta_l)$ solving $(J^TJ + \\lambda I)\\delta = -J^Tr$ by the Schur complement."""
    n_g, p = Jg.shape[-1], Jl.shape[-1]
    if p == 0:  # no local unknowns: the plain normal equations
        H = jnp.einsum("bmi,bmj->ij", Jg, Jg)
        return _scaled_cholesky_solve(H + lam * jnp.eye(n_g), -jnp.einsum("bmi,bm->i", Jg, r)), jnp.zeros(
            Jl.shape[:1] + (0,), Jg.dtype
        )
    H, W, U, eg, el = _normal_blocks(r, Jg, Jl)
    V = U + lam * jnp.eye(p)
    # One solve for both right-hand sides: V^{-1} [W^T | eps_b].
    X = small_cholesky_solve(V, jnp.concatenate([jnp.swapaxes(W, -1, -2), el[..., None]], axis=-1), 0.0)
    Y, z = X[..., :n_g], X[..., n_g]
    S = H + lam * jnp.eye(n_g) - jnp.einsum("bij,bjk->ik", W, Y)
    dg = _scaled_cholesky_solve(0.5 * (S + S.T), -eg + jnp.einsum("bij,bj->i", W, z))
    return dg, -z - jnp.einsum("bjk,k->bj", Y, dg)


def _max_ratio(diff, ref, rtol, atol):
    return jnp.max(jnp.abs(diff) / (atol + rtol * jnp.abs(ref)), initial=0.0)


class _State(eqx.Module):
    y: Any  # the last accepted iterate
    y_eval: Any  # where the next evaluation is
    r: Array  # residuals at `y`
    model: Any  # the linear model of the residuals at `y`
    step_size: Array
    first: Array
    terminate: Array
    num_steps: Array


def _levenberg_marquardt(evaluate, predict, step, y0, *, rtol, atol, max_steps, first=None, settled=None):
    """optimistix's Levenberg-Marquardt iteration (the module docstring) over a linear model.

    `evaluate(y) -> (r, model)`: the residuals at `y` and whatever linear model of
    them the step needs (the Jacobian blocks, or the normal equations);
    `predict(model, r, dy)`: the model's change of $\\tfrac12\\|r\\|^2$ for the step
    `dy`; `step(model, r, lam) -> dy`: the damped Gauss-Newton step. `y` is a
    pytree of arrays. `first`: `evaluate(y0)` when the caller has it already (the
    first iteration then costs no evaluation; the same iterates). `settled`: also
    stop at an accepted point whose next step the model predicts to lower the cost
    by less than $\\tfrac12 \\text{settled}^2 \\hat\\sigma^2$ ($\\hat\\sigma^2$ the mean
    squared residual there): a step that moves the estimate by less than
    `settled` standard deviations, not worth an evaluation. **Returns:**
    `(y, result, num_steps, r, model)` at the last accepted iterate.
    """
    r_struct, model_struct = jax.eval_shape(evaluate, y0)
    zeros = lambda t: jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), t)  # noqa: E731
    dtype = jax.tree.leaves(y0)[0].dtype
    tiny = jnp.finfo(dtype).eps
    state = _State(
        y=y0,
        y_eval=y0,
        # optimistix starts from zero residuals and Jacobian: the first evaluation is always accepted.
        r=zeros(r_struct),
        model=zeros(model_struct),
        step_size=jnp.asarray(1.0, dtype),
        first=jnp.asarray(True),
        terminate=jnp.asarray(False),
        num_steps=jnp.asarray(0),
    )

    def body(s: _State) -> _State:
        r_e, model_e = evaluate(s.y_eval)
        dy = jax.tree.map(jnp.subtract, s.y_eval, s.y)
        # Trust-region test (optimistix's ClassicalTrustRegion), with the model at the accepted point.
        predicted = predict(s.model, s.r, dy)
        actual = 0.5 * jnp.sum(r_e**2) - 0.5 * jnp.sum(s.r**2)
        good = (actual < _HIGH_CUTOFF * predicted) & (predicted < 0) & ~s.first
        y_ratio = jnp.max(
            jnp.stack(
                [_max_ratio(d, y, rtol, atol) for d, y in zip(jax.tree.leaves(dy), jax.tree.leaves(s.y_eval))]
            )
        )
        converged = (y_ratio < 1) & (_max_ratio(r_e - s.r, r_e, rtol, atol) < 1)
        # As `jaxcal._lsq.ConvergedStepTrustRegion`: a step that passes the
        # termination test is taken whatever its cost change (no stall at the optimum).
        classical = (actual <= _LOW_CUTOFF * predicted) | s.first
        take = converged & ~classical & ~s.first
        accept = classical | take
        mul = jnp.where(classical, jnp.where(good, _HIGH_CONSTANT, 1.0), jnp.where(take, 1.0, _LOW_CONSTANT))
        step_size = mul * s.step_size
        y, r, model = jax.tree.map(
            lambda new, old: jnp.where(accept, new, old), (s.y_eval, r_e, model_e), (s.y, s.r, s.model)
        )
        lam = jnp.where(
            step_size > tiny, 1.0 / jnp.where(step_size > tiny, step_size, 1.0), jnp.finfo(dtype).max
        )
        dy_next = step(model, r, lam)
        terminate = accept & converged
        if settled is not None:
            small = -predict(model, r, dy_next) <= 0.5 * settled**2 * jnp.mean(r**2)
            terminate = terminate | (accept & ~s.first & small)
        return _State(
            y=y,
            y_eval=jax.tree.map(jnp.add, y, dy_next),
            r=r,
            model=model,
            step_size=step_size,
            first=jnp.asarray(False),
            terminate=terminate,
            num_steps=s.num_steps + 1,
        )

    if first is not None:  # the first iteration, which always accepts its evaluation
        r0, model0 = first
        state = _State(
            y=y0,
            y_eval=jax.tree.map(jnp.add, y0, step(model0, r0, jnp.asarray(1.0, dtype))),
            r=r0,
            model=model0,
            step_size=jnp.asarray(1.0, dtype),
            first=jnp.asarray(False),
            terminate=_max_ratio(r0, r0, rtol, atol) < 1,
            num_steps=jnp.asarray(1),
        )

    def cond(s: _State):
        return ~s.terminate & (s.num_steps < max_steps)

    s = jax.lax.while_loop(cond, body, state)
    result = optx.RESULTS.where(
        s.terminate, optx.RESULTS.successful, optx.RESULTS.nonlinear_max_steps_reached
    )
    return s.y, result, s.num_steps, s.r, s.model


def block_least_squares(
    linearise: Linearise,
    g0: Float[Array, " n_g"],
    l0: Float[Array, "B p"],
    args: Any = None,
    *,
    rtol: float,
    atol: float,
    max_steps: int = 256,
    g_mask: Bool[Array, " n_g"] | None = None,
    l_mask: Bool[Array, "B p"] | None = None,
) -> BlockSolution:
    """Levenberg-Marquardt on block-structured residuals (see the module docstring).

    **Arguments:**
    - `linearise`: `(g, l, args) -> (r (B, m), J_g (B, m, n_g), J_l (B, m, p))`.
    - `g0` `(n_g,)`, `l0` `(B, p)`: the start.
    - `args`: passed to `linearise` (a pytree; weights go here).
    - `rtol`, `atol`: optimistix's termination tolerances (on the parameters
      and on the residuals).
    - `max_steps`: iterations before `nonlinear_max_steps_reached` (at least 1).
    - `g_mask`, `l_mask`: which parameters are free (default all).

    **Returns:** a `BlockSolution`.
    """
    if max_steps < 1:
        raise ValueError(f"block_least_squares: max_steps must be at least 1, got {max_steps}")
    g0 = jnp.asarray(g0)
    l0 = jnp.asarray(l0)
    if g0.ndim != 1 or l0.ndim != 2:
        raise ValueError(
            f"block_least_squares: g0 must be (n_g,) and l0 (B, p), got {g0.shape} and {l0.shape}"
        )
    gm = jnp.ones(g0.shape, g0.dtype) if g_mask is None else jnp.asarray(g_mask, g0.dtype)
    lm = jnp.ones(l0.shape, l0.dtype) if l_mask is None else jnp.asarray(l_mask, l0.dtype)

    def evaluate(y):
        r, Jg, Jl = linearise(*y, args)
        return r, (Jg * gm, Jl * lm[:, None, :])

    def predict(model, r, dy):
        (Jg, Jl), (dg, dl) = model, dy
        pred_r = r + jnp.einsum("bmi,i->bm", Jg, dg) + jnp.einsum("bmj,bj->bm", Jl, dl)
        return 0.5 * (jnp.sum(pred_r**2) - jnp.sum(r**2))

    (g, l), result, num_steps, r, (Jg, Jl) = _levenberg_marquardt(
        evaluate,
        predict,
        lambda model, r, lam: _damped_step(r, *model, lam),
        (g0, l0),
        rtol=rtol,
        atol=atol,
        max_steps=max_steps,
    )
    return BlockSolution(g=g, l=l, result=result, num_steps=num_steps, residuals=r, jac_g=Jg, jac_l=Jl)


class NormalEquations(eqx.Module):
    """A linearisation reduced to its normal equations: $H = J^TJ$ `(n, n)`, $e = J^Tr$ `(n,)`,
    and `aux`, whatever else the model keeps of the same point (a pytree of arrays, e.g. per-group
    gradients for a cluster-robust covariance; None)."""

    H: Float[Array, "n n"]
    e: Float[Array, " n"]
    aux: Any = None


class NormalSolution(eqx.Module):
    """A solved `normal_least_squares` problem: `x` `(n,)` (the last accepted iterate),
    `result`, `num_steps` (as `BlockSolution`'s), and the residuals and `NormalEquations`
    at `x`."""

    x: Float[Array, " n"]
    result: optx.RESULTS
    num_steps: Int[Array, ""]
    residuals: Array
    normal: NormalEquations


def normal_least_squares(
    normal: Callable[[Array, Any], tuple[Array, NormalEquations]],
    x0: Float[Array, " n"],
    args: Any = None,
    *,
    rtol: float,
    atol: float,
    max_steps: int = 256,
    first: tuple[Array, NormalEquations] | None = None,
    settled: float | None = None,
) -> NormalSolution:
    """`block_least_squares`' iteration without local unknowns, on the normal equations the model forms.

    `normal(x, args) -> (r, NormalEquations)`: the residuals (any shape) and
    $J^TJ$, $J^Tr$ at `x`. The loop keeps only these $n \\times n$ terms (not
    the Jacobian): the predicted decrease is $e^T\\delta + \\tfrac12\\delta^TH\\delta$,
    mathematically the same as from $J$, and a model may reduce its Jacobian
    to them however is cheapest (by groups, with a robust loss's rank-one
    terms; `jaxcal._handeye.jacobian`). Same steps as `block_least_squares`
    with $p = 0$ to round-off. `first`: `normal(x0, args)` when the caller has
    formed it already (e.g. for an identifiability search at the start);
    `settled`: see `_levenberg_marquardt`.
    **Returns:** a `NormalSolution`.
    """
    if max_steps < 1:
        raise ValueError(f"normal_least_squares: max_steps must be at least 1, got {max_steps}")
    x0 = jnp.asarray(x0)
    if x0.ndim != 1:
        raise ValueError(f"normal_least_squares: x0 must be (n,), got {x0.shape}")

    def evaluate(x):
        return normal(x, args)

    def predict(ne, r, dx):
        return jnp.dot(ne.e, dx) + 0.5 * jnp.dot(dx, ne.H @ dx)

    def step(ne, r, lam):
        return _scaled_cholesky_solve(ne.H + lam * jnp.eye(x0.shape[0], dtype=x0.dtype), -ne.e)

    x, result, num_steps, r, ne = _levenberg_marquardt(
        evaluate, predict, step, x0, rtol=rtol, atol=atol, max_steps=max_steps, first=first, settled=settled
    )
    return NormalSolution(x=x, result=result, num_steps=num_steps, residuals=r, normal=ne)


def _psd_pinv(S: Float[Array, "n n"]) -> Float[Array, "n n"]:
    """Pseudo-inverse of a symmetric positive semi-definite matrix, Jacobi-scaled
    (so it does not depend on the parameters' units); eigenvalues under
    $10\\,n\\,\\epsilon$ of the largest are dropped, zero rows get zero variance."""
    n = S.shape[0]
    d = jnp.sqrt(jnp.maximum(jnp.diagonal(S), 0.0))
    scale = jnp.where(d > 0, 1.0 / jnp.where(d > 0, d, 1.0), 0.0)
    A = S * scale[:, None] * scale[None, :]
    w, Q = jnp.linalg.eigh(A)
    keep = w > 10 * n * np.finfo(np.dtype(S.dtype)).eps * jnp.max(w)
    inv_w = jnp.where(keep, 1.0 / jnp.where(keep, w, 1.0), 0.0)
    B = Q * scale[:, None]
    return (B * inv_w[None, :]) @ B.T


def _covariance_parts(jac_g, jac_l, g_mask, l_mask):
    """$S^{+}$ (masked), $Y_b = U_b^{+}W_b^T$, $U_b^{+}$ and the masks as floats."""
    n_g, p = jac_g.shape[-1], jac_l.shape[-1]
    gm = jnp.ones(n_g) if g_mask is None else jnp.asarray(g_mask, jac_g.dtype)
    lm = jnp.ones(jac_l.shape[:1] + (p,)) if l_mask is None else jnp.asarray(l_mask, jac_l.dtype)
    Jg = jac_g * gm
    Jl = jac_l * lm[:, None, :]
    H = jnp.einsum("bmi,bmj->ij", Jg, Jg)
    W = jnp.einsum("bmi,bmj->bij", Jg, Jl)
    U = jnp.einsum("bmi,bmj->bij", Jl, Jl)
    tol = _BLOCK_RTOL * jnp.max(jnp.diagonal(U, axis1=-2, axis2=-1), axis=0, initial=0.0)
    tol = jnp.maximum(tol, jnp.finfo(U.dtype).tiny)
    # U^{+} [W^T | I]: the eliminated blocks and their own inverses, in one solve.
    rhs = jnp.concatenate([jnp.swapaxes(W, -1, -2), jnp.broadcast_to(jnp.eye(p), U.shape)], axis=-1)
    X = small_cholesky_solve(U, rhs, tol)
    Y, Uinv = X[..., :n_g], X[..., n_g:]
    S = H - jnp.einsum("bij,bjk->ik", W, Y)
    C = _psd_pinv(0.5 * (S + S.T)) * gm[:, None] * gm[None, :]
    return C, Y, Uinv, gm, lm


def block_covariance(
    jac_g: Float[Array, "B m n_g"],
    jac_l: Float[Array, "B m p"],
    *,
    g_mask: Bool[Array, " n_g"] | None = None,
    l_mask: Bool[Array, "B p"] | None = None,
) -> BlockCovariance:
    """The blocks of $(J^TJ)^{+}$ without forming it (see the module docstring).

    **Arguments:** the Jacobian blocks at the solution (e.g. a `BlockSolution`'s
    `jac_g`, `jac_l`; weighted, whitened); `g_mask`, `l_mask`: free parameters
    (frozen ones get zero rows and columns).

    **Returns:** a `BlockCovariance` (unscaled: multiply by the residual variance).
    """
    C, Y, Uinv, _, lm = _covariance_parts(jac_g, jac_l, g_mask, l_mask)
    gl = -jnp.einsum("ij,bkj->bik", C, Y)  # -S^{-1} W_b U_b^{-1} = -(U_b^{-1} W_b^T S^{-1})^T
    ll = Uinv + jnp.einsum("bij,jk,blk->bil", Y, C, Y)
    gl = gl * lm[:, None, :]
    ll = ll * lm[:, :, None] * lm[:, None, :]
    return BlockCovariance(gg=C, gl=gl, ll=ll)


def full_covariance(
    jac_g: Float[Array, "B m n_g"],
    jac_l: Float[Array, "B m p"],
    *,
    g_mask: Bool[Array, " n_g"] | None = None,
    l_mask: Bool[Array, "B p"] | None = None,
) -> Float[Array, "n n"]:
    """All of $(J^TJ)^{+}$, $n = n_g + Bp$, parameters ordered $(g, l_1, \\dots, l_B)$.

    The blocks of `block_covariance` and the cross-covariances of different
    local blocks, $\\Sigma_{l_b l_c} = Y_b S^{-1} Y_c^T$ ($b \\ne c$,
    $Y_b = U_b^{-1}W_b^T$): with $Y$ the $Bp \\times n_g$ stack,
    $\\Sigma_{ll} = \\mathrm{blockdiag}(U_b^{-1}) + Y S^{-1} Y^T$. $O((Bp)^2 n_g)$
    after the one $n_g \\times n_g$ decomposition: no $n \\times n$ factorisation.
    """
    C, Y, Uinv, _, lm = _covariance_parts(jac_g, jac_l, g_mask, l_mask)
    B, p, n_g = Y.shape
    Yf = (Y * lm[..., None]).reshape(B * p, n_g)
    Uinv = Uinv * lm[:, :, None] * lm[:, None, :]
    diag = jnp.einsum("bc,bij->bicj", jnp.eye(B, dtype=Uinv.dtype), Uinv).reshape(B * p, B * p)
    gl = -C @ Yf.T
    ll = diag + Yf @ C @ Yf.T
    return jnp.block([[C, gl], [gl.T, ll]])


def block_leverage(
    jac_g: Float[Array, "B m n_g"], jac_l: Float[Array, "B m p"], cov: BlockCovariance
) -> Float[Array, "B m"]:
    """Leverages: the diagonal of the hat matrix $J(J^TJ)^{+}J^T$, per residual.

    For residual row $a$ of block $b$:
    $h = a_g\\Sigma_{gg}a_g^T + 2\\,a_g\\Sigma_{gl_b}a_l^T + a_l\\Sigma_{l_bl_b}a_l^T$.
    """
    hg = jnp.einsum("bmi,ij,bmj->bm", jac_g, cov.gg, jac_g)
    hx = jnp.einsum("bmi,bij,bmj->bm", jac_g, cov.gl, jac_l)
    hl = jnp.einsum("bmi,bij,bmj->bm", jac_l, cov.ll, jac_l)
    return hg + 2.0 * hx + hl
