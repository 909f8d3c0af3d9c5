"""The cluster-robust (sandwich) covariance of `jaxcal._lsq.cluster_covariance` on analytic data.

A linear least-squares problem whose observations come in views: every view's
regressors share a view-level part (as a camera view's corners share the view's
pose) and its errors a view-coherent part (the detector's shift of a whole view).
The 95 % ellipsoid of a covariance covers the true parameters in 95 % of trials when
the covariance is honest; the plain $s^2 (X^TX)^{-1}$ assumes independent errors.
"""

import jax.numpy as jnp
import numpy as np
from scipy import stats

from jaxcal._lsq import cluster_covariance, covariance, larger_covariance

K = 3  # parameters
CHI2_95 = stats.chi2.ppf(0.95, K)


def _regressors(rng, views: int, per_view: int) -> np.ndarray:
    """`(views, per_view, K)`: a view-level part plus a small per-observation part, like the
    corners of one view that move together with its pose."""
    return rng.standard_normal((views, 1, K)) + 0.3 * rng.standard_normal((views, per_view, K))


def _coverage(trials: int, views: int, per_view: int, tau: float, seed: int):
    """Share of trials whose true parameters lie in the 95 % ellipsoid, (plain, cluster-robust):
    unit corner noise plus a view-coherent error of standard deviation `tau`."""
    rng = np.random.default_rng(seed)
    beta = np.array([1.0, -2.0, 0.5])
    hits = np.zeros((trials, 2), bool)
    for t in range(trials):
        X = _regressors(rng, views, per_view)
        y = X @ beta + tau * rng.standard_normal((views, 1)) + rng.standard_normal((views, per_view))
        A, b = X.reshape(-1, K), y.reshape(-1)
        bread = np.linalg.inv(A.T @ A)
        est = bread @ A.T @ b
        r = (b - A @ est).reshape(views, per_view)
        s2 = np.sum(r**2) / (A.shape[0] - K)
        scores = np.einsum("vik,vi->vk", X, r)
        robust = np.asarray(cluster_covariance(jnp.asarray(bread), jnp.asarray(scores), A.shape[0]))
        d = est - beta
        for k, cov in enumerate((s2 * bread, robust)):
            hits[t, k] = d @ np.linalg.solve(cov, d) <= CHI2_95
    return hits.mean(axis=0)


# Binomial tolerance of a coverage over 1000 trials: 3.5 standard deviations of 0.95's
# share, sqrt(0.95 * 0.05 / 1000) = 0.0069, so 0.024 (CR1's own small-sample bias with
# 200 clusters and 3 parameters is under 0.005).
TOL = 0.024


def test_view_coherent_errors_covered_by_the_cluster_covariance():
    """View-coherent errors as large as the corner noise (tau = 1, 8 corners a view): the
    plain covariance is too small by about 1 + 8 tau^2 in the view-level directions."""
    plain, robust = _coverage(1000, 200, 8, tau=1.0, seed=0)
    assert abs(robust - 0.95) < TOL
    assert plain < 0.95 - 0.3  # about 0.3 in fact: the plain ellipsoid is ~3x too small


def test_independent_errors_give_the_plain_covariance():
    """Without view-coherent errors the sandwich estimates what s^2 (X^T X)^-1 does: the
    traces agree on average over trials to their sampling spread (a sandwich of 200
    clusters: about sqrt(2/200) = 0.1 per trial, 0.01 over 100)."""
    rng = np.random.default_rng(2)
    ratios = []
    for _ in range(100):
        X = _regressors(rng, 200, 8)
        y = X @ np.ones(K) + rng.standard_normal((200, 8))
        A, b = X.reshape(-1, K), y.reshape(-1)
        bread = np.linalg.inv(A.T @ A)
        r = (b - A @ (bread @ A.T @ b)).reshape(200, 8)
        s2 = np.sum(r**2) / (A.shape[0] - K)
        robust = np.asarray(
            cluster_covariance(jnp.asarray(bread), jnp.asarray(np.einsum("vik,vi->vk", X, r)), A.shape[0])
        )
        ratios.append(np.trace(robust) / np.trace(s2 * bread))
    assert abs(np.mean(ratios) - 1.0) < 0.04


def test_frozen_parameters_and_empty_clusters():
    """A frozen parameter (zero row and column of the bread) gets zero variance; a cluster
    without a gradient (padding) is not counted in G / (G - 1)."""
    rng = np.random.default_rng(3)
    bread = np.diag([1.0, 2.0, 0.0])
    scores = rng.standard_normal((4, 3))
    scores[:, 2] = 0.0
    scores[3] = 0.0
    expect = 1.5 * bread @ scores.T @ scores @ bread  # G / (G - 1) with G = 3
    got = np.asarray(cluster_covariance(jnp.asarray(bread), jnp.asarray(scores)))
    np.testing.assert_allclose(got, expect, rtol=1e-12)
    assert got[2, 2] == 0.0


def test_larger_covariance_keeps_the_model_unless_the_other_exceeds_it():
    """From `covariance`'s SVD: the model's covariance back when `other` is it or smaller,
    `other` where it is larger than the model's in every direction, and with margin 0 a
    covariance at least each of the two along every direction (to round-off)."""
    rng = np.random.default_rng(5)
    J = jnp.asarray(rng.standard_normal((40, 4)) * np.array([1.0, 10.0, 0.1, 3.0]))
    bread, sv, Vt = covariance(J)
    s2 = 0.7
    model = s2 * np.asarray(bread)
    tol = dict(rtol=1e-9, atol=1e-12 * np.abs(model).max())
    np.testing.assert_allclose(larger_covariance(J, sv, Vt, s2, jnp.asarray(model)), model, **tol)
    np.testing.assert_allclose(larger_covariance(J, sv, Vt, s2, jnp.asarray(0.5 * model)), model, **tol)
    np.testing.assert_allclose(larger_covariance(J, sv, Vt, s2, jnp.asarray(3.0 * model)), 3.0 * model, **tol)
    B = rng.standard_normal((4, 4))
    other = model + B @ np.diag([1e-2, 0.0, 0.0, 0.0]) @ B.T
    C = np.asarray(larger_covariance(J, sv, Vt, s2, jnp.asarray(other)))
    for M in (model, other):
        assert np.linalg.eigvalsh(C - M).min() > -1e-9 * np.abs(C).max()
