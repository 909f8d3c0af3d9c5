"""Decompositions that are safe to batch on CPU (`jaxcal._linalg`).

The batched entry points (Monte Carlo trial, refinement, hand-eye) are checked
for unordered LAPACK calls in their own test modules; here: the helpers and
the checker itself.
"""

import re
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxcal._geometry import so3_exp
from jaxcal._linalg import after, concurrent_decompositions, gauss_newton_covariance, nearest_rotation
from jaxcal._lsq import BATCHED_ENTRY_POINTS


@pytest.fixture
def jacobian():
    rng = np.random.default_rng(3)
    # Columns in very different units (mm next to rad next to ratio), as in the fits.
    return rng.standard_normal((40, 6)) * np.array([1e-3, 1.0, 1e3, 0.1, 10.0, 1e-2])


def test_covariance_equals_the_inverse_normal_matrix(jacobian):
    cov, sv, Vt = gauss_newton_covariance(jnp.asarray(jacobian))
    np.testing.assert_allclose(cov, np.linalg.inv(jacobian.T @ jacobian), rtol=1e-9)
    Jn = jacobian / np.linalg.norm(jacobian, axis=0)
    np.testing.assert_allclose(sv, np.linalg.svd(Jn, compute_uv=False), rtol=1e-12)
    np.testing.assert_allclose(np.abs(Vt @ np.linalg.svd(Jn)[2].T), np.eye(6), atol=1e-9)


def test_zero_columns_get_zero_variance(jacobian):
    J = jacobian.copy()
    J[:, 2] = 0.0  # a frozen parameter
    cov, sv, _ = gauss_newton_covariance(jnp.asarray(J))
    cov = np.asarray(cov)
    assert np.all(cov[2] == 0.0) and np.all(cov[:, 2] == 0.0)
    keep = [0, 1, 3, 4, 5]
    np.testing.assert_allclose(cov[np.ix_(keep, keep)], np.linalg.inv(J[:, keep].T @ J[:, keep]), rtol=1e-9)
    assert float(sv[-1]) < 1e-15 * float(sv[0])


def test_rank_deficient_jacobian_gives_a_generalised_inverse(jacobian):
    J = jacobian.copy()
    J[:, 5] = 3.0 * J[:, 1]  # two parameters the data cannot tell apart
    cov = np.asarray(gauss_newton_covariance(jnp.asarray(J))[0])
    assert np.all(np.isfinite(cov))
    # J cov J^T is the orthogonal projector onto J's range (rank 5).
    P = J @ cov @ J.T
    np.testing.assert_allclose(P @ P, P, atol=1e-9)
    np.testing.assert_allclose(P, P.T, atol=1e-9)
    assert np.trace(P) == pytest.approx(5.0, abs=1e-9)


def test_nearest_rotation_is_the_polar_factor():
    rng = np.random.default_rng(4)
    R = jax.vmap(so3_exp)(jnp.asarray(rng.standard_normal((5, 3))))
    A = rng.standard_normal((5, 3, 3))
    S = np.einsum("bij,bkj->bik", A, A) + 0.1 * np.eye(3)  # symmetric positive definite
    np.testing.assert_allclose(nearest_rotation(R @ S), R, atol=1e-10)
    # A reflection's nearest proper rotation: det +1 and orthonormal.
    M = np.diag([1.0, 2.0, -3.0])
    Q = np.asarray(nearest_rotation(jnp.asarray(M)))
    np.testing.assert_allclose(Q @ Q.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(Q) == pytest.approx(1.0)
    # ... flipping the direction of the smallest singular value (x here).
    np.testing.assert_allclose(Q, np.diag([-1.0, 1.0, -1.0]), atol=1e-12)


def _two_decompositions(a, b, ordered):
    s = jnp.linalg.svd(a, compute_uv=False)
    if ordered:
        b = after(b, s)
    w = jnp.linalg.eigh(b)[0]
    return s.sum() + w.sum()


def test_checker_finds_side_by_side_decompositions():
    a, b = jnp.ones((4, 5, 3)), jnp.eye(3)[None].repeat(4, 0)
    found = concurrent_decompositions(jax.vmap(lambda x, y: _two_decompositions(x, y, False)), a, b)
    assert len(found) == 1 and "svd" in found[0] and "eigh" in found[0]
    assert concurrent_decompositions(jax.vmap(lambda x, y: _two_decompositions(x, y, True)), a, b) == []
    # Inside a loop body too, named by its path.
    loop = lambda x, y: jax.lax.fori_loop(0, 3, lambda i, c: c + _two_decompositions(x, y, False), 0.0)  # noqa: E731
    found = concurrent_decompositions(loop, a[0], b[0])
    assert len(found) == 1 and found[0].startswith("/scan")
    # The ordered version computes the same numbers.
    np.testing.assert_allclose(_two_decompositions(a[0], b[0], True), _two_decompositions(a[0], b[0], False))


@pytest.mark.parametrize("batched", [False, True])
def test_checker_sees_inside_lineax_solves(batched):
    """lineax's `linear_solve` (every optimistix Levenberg-Marquardt step) keeps
    its factorisation out of the jaxpr; the checker counts it as one, vmapped
    (equinox's `vprim`) or not."""
    import lineax as lx

    def f(A, b, ordered):
        x = lx.linear_solve(lx.MatrixLinearOperator(A), b).value
        s = jnp.linalg.svd(after(A, x) if ordered else A, compute_uv=False)
        return x.sum() + s.sum()

    A, b = jnp.eye(3) + 0.1 * jnp.ones((3, 3)), jnp.ones(3)
    args = (A[None].repeat(4, 0), b[None].repeat(4, 0)) if batched else (A, b)
    wrap = jax.vmap if batched else (lambda g: g)
    found = concurrent_decompositions(wrap(lambda A, b: f(A, b, False)), *args)
    # (vmapped outside a loop, lineax may bind its LU directly)
    assert len(found) == 1 and ("linear_solve" in found[0] or "(lu)" in found[0]) and "svd" in found[0]
    assert concurrent_decompositions(wrap(lambda A, b: f(A, b, True)), *args) == []


def _operands(hlo: str) -> dict[str, list[str]]:
    """`{instruction: [operand names]}` of a compiled program's HLO text (all computations)."""
    graph = {}
    for line in hlo.splitlines():
        m = re.match(r"\s*(?:ROOT )?%([\w.\-]+) = .*?\b[\w\-]+\((.*?)\)(?:, |$)", line)
        if m:
            graph[m.group(1)] = re.findall(r"%([\w.\-]+)", m.group(2))
    return graph


def test_after_orders_the_compiled_program():
    """The ordering must survive XLA's optimisations: in the compiled program
    the eigh's input depends on the SVD's output (with an optimisation
    barrier instead, XLA drops the barrier and the two are independent)."""
    a = jax.random.normal(jax.random.key(0), (64, 5, 5))
    b = a @ jnp.swapaxes(a, -1, -2)

    def depends(fn) -> bool:
        hlo = jax.jit(fn).lower(a, b).compile().as_text()
        graph = _operands(hlo)
        eigh = [n for n, line in _defining_lines(hlo).items() if "dsyevd" in line]
        svd = {n for n, line in _defining_lines(hlo).items() if "dgesdd" in line}
        assert len(eigh) == 1 and len(svd) == 1
        seen, todo = set(), list(graph[eigh[0]])
        while todo:
            n = todo.pop()
            if n in svd:
                return True
            if n not in seen:
                seen.add(n)
                todo += graph.get(n, [])
        return False

    def ordered(x, y):
        return _two_decompositions(x, y, True)

    def barrier(x, y):
        s = jnp.linalg.svd(x, compute_uv=False)
        y, _ = jax.lax.optimization_barrier((y, s))
        return s.sum() + jnp.linalg.eigh(y)[0].sum()

    assert depends(ordered)
    assert not depends(barrier)
    np.testing.assert_array_equal(after(b, a), b)


def _defining_lines(hlo: str) -> dict[str, str]:
    out = {}
    for line in hlo.splitlines():
        m = re.match(r"\s*(?:ROOT )?%([\w.\-]+) = ", line)
        if m:
            out[m.group(1)] = line
    return out


# --------------------------------------------------------------------------- every batched entry point

#: Where each of `jaxcal._lsq.BATCHED_ENTRY_POINTS` is checked (file::test).
GUARDS = {
    # A Monte Carlo trial vmaps the arc fits over joints and the axis fit, and the trials over keys.
    "jaxcal._arcfit.fit_arc": "test_montecarlo.py::test_batched_trials_keep_lapack_calls_ordered",
    "jaxcal._axisfit.fit_axes": "test_montecarlo.py::test_batched_trials_keep_lapack_calls_ordered",
    "jaxcal._montecarlo.run_trial": "test_montecarlo.py::test_batched_trials_keep_lapack_calls_ordered",
    "jaxcal._refine.refine": "test_refine.py::test_batched_refinement_keeps_lapack_calls_ordered",
    "jaxcal._pointfit.cross_validate": "test_pointfit.py::test_cross_validation_keeps_lapack_calls_ordered",
    "jaxcal.calibrate_hand_eye": "test_handeye.py::test_batched_solves_keep_lapack_calls_ordered",
}


def test_every_batched_entry_point_is_guarded():
    assert set(GUARDS) == set(BATCHED_ENTRY_POINTS)
    here = Path(__file__).parent
    for where in GUARDS.values():
        file, name = where.split("::")
        assert f"def {name}(" in (here / file).read_text(), f"{where} is missing"
