"""Levenberg-Marquardt by blocks (`jaxcal._schur`): against optimistix's dense solve."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest
from helpers import tree_allclose

from jaxcal import _lsq
from jaxcal._linalg import concurrent_decompositions
from jaxcal._schur import (
    NormalEquations,
    block_covariance,
    block_least_squares,
    block_leverage,
    full_covariance,
    jacobian_by_jvp,
    normal_least_squares,
    small_cholesky_solve,
)


def _model(g, l, args):
    """A nonlinear block model: $u_b = A_b \\sin g + C_b l_b$, $r_b = u_b + 0.3\\,(A_b g) \\odot (C_b l_b) - y_b$."""
    A, C, y = args
    ag = jnp.einsum("bmi,i->bm", A, g)
    cl = jnp.einsum("bmj,bj->bm", C, l)
    return jnp.einsum("bmi,i->bm", A, jnp.sin(g)) + cl + 0.3 * ag * cl - y


def _problem(seed, *, blocks=12, m=5, n_g=4, p=2, noise=0.05):
    """A random block problem: truth, data, and a start 0.2 away."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(blocks, m, n_g))
    C = rng.normal(size=(blocks, m, p))
    g = 0.5 * rng.normal(size=n_g)
    l = rng.normal(size=(blocks, p))
    y = np.asarray(_model(g, l, (A, C, np.zeros((blocks, m))))) + noise * rng.normal(size=(blocks, m))
    args = (jnp.asarray(A), jnp.asarray(C), jnp.asarray(y))
    g0 = jnp.asarray(g + 0.2 * rng.normal(size=n_g))
    l0 = jnp.asarray(l + 0.2 * rng.normal(size=(blocks, p)))
    return args, g0, l0


def _dense_jacobian(g, l, args):
    flat = jnp.concatenate([g, l.ravel()])
    n_g = g.shape[0]
    return jax.jacfwd(lambda x: _model(x[:n_g], x[n_g:].reshape(l.shape), args).ravel())(flat)


LIN = jacobian_by_jvp(_model)


@pytest.mark.parametrize("p", [1, 2, 6])
def test_takes_optimistix_steps(p):
    """Same iterates as `optx.least_squares` with `LevenbergMarquardt` on the
    flat problem: the same number of steps and the same solution (with
    tolerances above round-off: below, whether a step of 1e-17 is accepted is
    decided by round-off, in either solver)."""
    args, g0, l0 = _problem(p, p=p)
    for rtol, atol in [(1e-6, 1e-6), (1e-3, 1e-3)]:
        ours = jax.jit(
            lambda g, l, a: block_least_squares(LIN, g, l, a, rtol=rtol, atol=atol, max_steps=100)
        )(g0, l0, args)
        ref = optx.least_squares(
            lambda y, a: _model(y[0], y[1], a),
            _lsq.LMOptions(rtol, atol).solver(),
            (g0, l0),
            args,
            max_steps=100,
        )
        assert ours.result == optx.RESULTS.successful
        assert int(ours.num_steps) == int(ref.stats["num_steps"])
        np.testing.assert_allclose(ours.g, ref.value[0], rtol=1e-9, atol=1e-10)
        np.testing.assert_allclose(ours.l, ref.value[1], rtol=1e-9, atol=1e-10)
        np.testing.assert_allclose(ours.residuals, _model(ours.g, ours.l, args), atol=1e-12)


def test_solve_normal_takes_optimistix_steps_on_a_pytree():
    """`_lsq.solve_normal` (one block, no local unknowns, on the flattened pytree)
    iterates as `_lsq.solve`, optimistix's Levenberg-Marquardt, and a step cap is
    reported with optimistix's code."""
    args, g0, l0 = _problem(7, p=2)
    fn = lambda y, a: _model(y[0], y[1], a)  # noqa: E731
    for rtol, atol in [(1e-6, 1e-6), (1e-3, 1e-3)]:
        options = _lsq.LMOptions(rtol, atol, 100, normal_cholesky=True)
        ours = jax.jit(lambda y, a: _lsq.solve_normal(fn, y, a, options))((g0, l0), args)
        ref = _lsq.solve(fn, (g0, l0), args, options)
        assert ours.result == optx.RESULTS.successful
        assert int(ours.stats["num_steps"]) == int(ref.stats["num_steps"]) > 3
        assert tree_allclose(ours.value, ref.value, rtol=1e-9, atol=1e-10)
    capped = _lsq.solve_normal(fn, (g0, l0), args, _lsq.LMOptions(1e-6, 1e-6, 2))
    assert capped.result == optx.RESULTS.nonlinear_max_steps_reached and int(capped.stats["num_steps"]) == 2


def test_jacobian_by_jvp_equals_the_dense_jacobian():
    args, g0, l0 = _problem(3, p=3)
    r, Jg, Jl = LIN(g0, l0, args)
    J = np.asarray(_dense_jacobian(g0, l0, args)).reshape(r.shape + (-1,))
    n_g = g0.shape[0]
    np.testing.assert_allclose(Jg, J[..., :n_g], atol=1e-13)
    B, p = l0.shape
    local = J[..., n_g:].reshape(r.shape + (B, p))
    np.testing.assert_allclose(Jl, local[np.arange(B), :, np.arange(B)], atol=1e-13)
    off = local.copy()
    off[np.arange(B), :, np.arange(B)] = 0.0
    assert np.all(off == 0.0)  # the block structure the solver relies on


@pytest.mark.parametrize("masked", [False, True])
def test_covariance_and_leverage_equal_the_dense_inverse(masked):
    args, g0, l0 = _problem(4, p=2, blocks=9)
    sol = block_least_squares(LIN, g0, l0, args, rtol=1e-10, atol=1e-10, max_steps=100)
    g_mask = np.ones(g0.shape, bool)
    l_mask = np.ones(l0.shape, bool)
    if masked:
        g_mask[1] = False
        l_mask[3, 0] = False
        l_mask[5] = False  # a whole block frozen
    cov = block_covariance(sol.jac_g, sol.jac_l, g_mask=g_mask, l_mask=l_mask)
    J = np.asarray(_dense_jacobian(sol.g, sol.l, args))
    free = np.concatenate([g_mask, l_mask.ravel()])
    dense = np.zeros((free.size, free.size))
    Jf = J[:, free]
    dense[np.ix_(free, free)] = np.linalg.inv(Jf.T @ Jf)
    n_g = g0.shape[0]
    B, p = l0.shape
    scale = np.abs(dense).max()
    np.testing.assert_allclose(cov.gg, dense[:n_g, :n_g], atol=1e-10 * scale)
    blocks = dense[n_g:, n_g:].reshape(B, p, B, p)[np.arange(B), :, np.arange(B)]
    np.testing.assert_allclose(cov.ll, blocks, atol=1e-10 * scale)
    cross = dense[:n_g, n_g:].reshape(n_g, B, p).transpose(1, 0, 2)
    np.testing.assert_allclose(cov.gl, cross, atol=1e-10 * scale)
    # All of it, local cross-blocks included.
    full = full_covariance(sol.jac_g, sol.jac_l, g_mask=g_mask, l_mask=l_mask)
    np.testing.assert_allclose(full, dense, atol=1e-10 * scale)
    # Leverages: the hat matrix's diagonal, summing to the number of free parameters.
    Jm = np.asarray(sol.jac_g) * g_mask, np.asarray(sol.jac_l) * l_mask[:, None, :]
    h = block_leverage(*Jm, cov)
    np.testing.assert_allclose(h.ravel(), np.diag(J @ dense @ J.T), atol=1e-10)
    assert float(jnp.sum(h)) == pytest.approx(free.sum(), abs=1e-9)


def test_unobserved_blocks_get_zero_variance():
    """A block whose residuals do not see its parameters (padding) is not a
    singular system: its variance is zero and the rest is unchanged."""
    args, g0, l0 = _problem(5, p=1, blocks=8)
    sol = block_least_squares(LIN, g0, l0, args, rtol=1e-10, atol=1e-10, max_steps=100)
    Jl = sol.jac_l.at[2].set(0.0)
    cov = block_covariance(sol.jac_g, Jl)
    assert np.all(np.isfinite(cov.gg)) and float(cov.ll[2, 0, 0]) == 0.0 and np.all(cov.gl[2] == 0.0)
    frozen = block_covariance(sol.jac_g, sol.jac_l, l_mask=np.arange(8)[:, None] != 2)
    np.testing.assert_allclose(cov.gg, frozen.gg, rtol=1e-12)


def testsmall_cholesky_solve():
    rng = np.random.default_rng(6)
    X = rng.normal(size=(7, 5, 5))
    V = X @ np.swapaxes(X, -1, -2) + 0.1 * np.eye(5)
    R = rng.normal(size=(7, 5, 3))
    np.testing.assert_allclose(
        small_cholesky_solve(jnp.asarray(V), jnp.asarray(R), 0.0), np.linalg.solve(V, R), rtol=1e-10
    )
    # A zero row and column: the pseudo-inverse (the direction is dropped).
    V[:, 2, :] = V[:, :, 2] = 0.0
    keep = [0, 1, 3, 4]
    expect = np.zeros_like(R)
    expect[:, keep] = np.linalg.solve(V[:, keep][:, :, keep], R[:, keep])
    np.testing.assert_allclose(
        small_cholesky_solve(jnp.asarray(V), jnp.asarray(R), 1e-12), expect, rtol=1e-10
    )


def test_max_steps_reports_optimistix_code():
    args, g0, l0 = _problem(7)
    sol = block_least_squares(LIN, g0, l0, args, rtol=1e-10, atol=1e-10, max_steps=1)
    assert sol.result == optx.RESULTS.nonlinear_max_steps_reached and int(sol.num_steps) == 1
    with pytest.raises(ValueError, match="max_steps must be at least 1"):
        block_least_squares(LIN, g0, l0, args, rtol=1e-10, atol=1e-10, max_steps=0)


def test_vmap_equals_loop_and_has_no_unordered_decompositions():
    problems = [_problem(10 + i, p=6, blocks=6, m=8) for i in range(3)]
    stack = lambda xs: jax.tree.map(lambda *a: jnp.stack(a), *xs)  # noqa: E731
    args, g0, l0 = (
        stack([x[0] for x in problems]),
        stack([x[1] for x in problems]),
        stack([x[2] for x in problems]),
    )

    def solve_and_cov(g, l, a):
        sol = block_least_squares(LIN, g, l, a, rtol=1e-9, atol=1e-9, max_steps=60)
        return sol, block_covariance(sol.jac_g, sol.jac_l)

    batched = jax.jit(jax.vmap(solve_and_cov))(g0, l0, args)
    for i, (a, g, l) in enumerate(problems):
        one = jax.jit(solve_and_cov)(g, l, a)
        row = jax.tree.map(lambda x, i=i: x[i], batched)
        # Batched reductions round differently, and at these tolerances (1e-9) the
        # last steps are decided by rounding: the step counts may differ (11 against
        # 13 seen), the solutions may not.
        assert one[0].result == row[0].result == optx.RESULTS.successful
        steps = lambda sol: sol.num_steps  # noqa: E731
        one, row = (eqx.tree_at(lambda t: steps(t[0]), t, 0) for t in (one, row))
        assert tree_allclose(one, row, atol=1e-10)
    assert concurrent_decompositions(jax.vmap(solve_and_cov), g0, l0, args) == []


def _exp_normal(x, args):
    """Normal equations of a small nonlinear fit: $r_i = a e^{b t_i} + c - y_i$."""
    t, y = args
    f = lambda z: z[0] * jnp.exp(z[1] * t) + z[2] - y  # noqa: E731
    r, J = f(x), jax.jacfwd(f)(x)
    return r, NormalEquations(H=J.T @ J, e=J.T @ r)


def _exp_problem():
    rng = np.random.default_rng(4)
    t = jnp.linspace(0.0, 2.0, 60)
    y = 1.5 * jnp.exp(-0.8 * t) + 0.2 + 0.01 * rng.normal(size=60)
    return jnp.array([1.0, -0.5, 0.0]), (t, y)


def test_normal_least_squares_with_the_first_linearisation_given_takes_the_same_steps():
    x0, args = _exp_problem()
    kw = dict(rtol=1e-10, atol=1e-10, max_steps=50)
    plain = normal_least_squares(_exp_normal, x0, args, **kw)
    given = normal_least_squares(_exp_normal, x0, args, first=_exp_normal(x0, args), **kw)
    assert plain.result == optx.RESULTS.successful and int(given.num_steps) == int(plain.num_steps)
    np.testing.assert_allclose(given.x, plain.x, rtol=0, atol=1e-14)


def test_a_settled_solve_stops_within_a_hundredth_of_a_standard_deviation():
    """`settled`: one evaluation fewer here, and the answer within 0.01 sigma of the
    converged one in the covariance's metric."""
    x0, args = _exp_problem()
    kw = dict(rtol=0.0, atol=1e-12, max_steps=50)
    full = normal_least_squares(_exp_normal, x0, args, **kw)
    early = normal_least_squares(_exp_normal, x0, args, settled=1e-2, **kw)
    assert int(early.num_steps) < int(full.num_steps)
    r = full.residuals
    cov = jnp.linalg.inv(full.normal.H) * jnp.mean(r**2)
    d = early.x - full.x
    assert float(d @ jnp.linalg.solve(cov, d)) < 1e-4
