"""Decompositions that are safe to batch on CPU (`jaxcal._linalg`).

The batched entry points (Monte Carlo trial, refinement, hand-eye) are checked
for unordered LAPACK calls in their own test modules; here: the helpers and
the checker itself.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxcal._geometry import so3_exp
from jaxcal._linalg import after, concurrent_decompositions, gauss_newton_covariance, nearest_rotation


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
