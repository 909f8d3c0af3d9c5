"""The cluster-robust (sandwich) covariances of `jaxcal._lsq` (`cluster_covariance`, the views'
kernel sandwich `hac_covariance`) on analytic data, and the refinement's test of errors that
repeat along the capture or between a pose's views (`jaxcal.stages._refine.error_correlation`).

A linear least-squares problem whose observations come in views: every view's
regressors share a view-level part (as a camera view's corners share the view's
pose) and its errors a view-coherent part (the detector's shift of a whole view).
The 95 % ellipsoid of a covariance covers the true parameters in 95 % of trials when
the covariance is honest; the plain $s^2 (X^TX)^{-1}$ assumes independent errors.
"""

import types

import jax
import jax.numpy as jnp
import numpy as np
from scipy import stats

from jaxcal._lsq import cluster_covariance, covariance, hac_covariance, larger_covariance, newey_west_lags
from jaxcal.stages import Limits
from jaxcal.stages._refine import _Corners
from jaxcal.stages._residual_tests import corner_pairs, error_correlation

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


# --------------------------------------------------------------------------- hac_covariance


def _ar1_problem(views: int, per_view: int, phi: float, tau: float, seed: int):
    """A fixed design `X` `(views, per_view, K)` (a common part, so that the views' errors add
    up in the estimate, plus view-level and per-observation parts) and the errors' covariance
    `Omega`: unit noise per observation plus a per-view shift, AR(1) along the views' order
    (coefficient `phi`, stationary variance `tau^2`)."""
    rng = np.random.default_rng(seed)
    X = np.array([1.0, 0.5, -0.5]) + _regressors(rng, views, per_view)
    lag = np.abs(np.arange(views)[:, None] - np.arange(views)[None, :])
    Omega = np.eye(views * per_view) + tau**2 * np.kron(phi**lag, np.ones((per_view, per_view)))
    return X, Omega


def _expected_hac(X, Omega, lags):
    """The exact expectation of `hac_covariance` under errors of covariance `Omega`, written out
    independently of it: $W T X^T(\\mathcal K \\circ M\\Omega M)X\\, T W^T$ (see its docstring)."""
    views, per_view, _ = X.shape
    A = X.reshape(-1, K)
    B = np.linalg.inv(A.T @ A)
    M = np.eye(len(A)) - A @ B @ A.T
    lag = np.abs(np.arange(views)[:, None] - np.arange(views)[None, :])
    Kv = np.clip(1.0 - lag / (lags + 1.0), 0.0, None)
    Kc = np.kron(Kv, np.ones((per_view, per_view)))
    S = A.T @ (Kc * (M @ Omega @ M)) @ A
    W = np.linalg.cholesky(B)
    mu, Q = np.linalg.eigh(W.T @ A.T @ (Kc * M) @ A @ W)  # E[S] with independent unit errors, whitened
    T = (Q / np.sqrt(mu)) @ Q.T
    return W @ T @ W.T @ S @ W @ T @ W.T, B


def _hac_trials(X, Omega, lags, trials, seed):
    """Per trial the estimate's error and `hac_covariance`: `(trials, K)`, `(trials, K, K)`."""
    views, per_view, _ = X.shape
    A = X.reshape(-1, K)
    B = np.linalg.inv(A.T @ A)
    e = np.random.default_rng(seed).standard_normal((trials, len(A))) @ np.linalg.cholesky(Omega).T
    d = e @ A @ B  # the estimate's error per trial
    r = (e - d @ A.T).reshape(trials, views, per_view)
    scores = np.einsum("vik,tvi->tvk", X, r)
    info = np.einsum("vik,vil->vkl", X, X)
    hac = jax.jit(jax.vmap(lambda s: hac_covariance(jnp.asarray(B), s, jnp.asarray(info), lags)[0]))
    covs = np.concatenate([np.asarray(hac(jnp.asarray(c))) for c in np.array_split(scores, 4)])
    return d, covs


def _relative_eigenvalues(C, R):
    """The generalised eigenvalues of `C` against `R` (1 everywhere: equal)."""
    Li = np.linalg.inv(np.linalg.cholesky(R))
    return np.linalg.eigvalsh(Li @ C @ Li.T)


def _whitened_diagonals(covs, R):
    """`(..., K)`: the variances of `covs` along the axes in which `R` is the identity."""
    Li = np.linalg.inv(np.linalg.cholesky(R))
    return np.einsum("ai,...ij,aj->...a", Li, covs, Li)


def _mean_and_tolerance(covs, R):
    """The trials' mean of `covs` along `R`'s whitened axes and 4 of its standard errors (from
    the trials' own scatter)."""
    x = _whitened_diagonals(covs, R)
    return x.mean(axis=0), 4.0 * x.std(axis=0, ddof=1) / np.sqrt(len(x))


def test_hac_covariance_is_unbiased_with_independent_errors():
    """With independent errors of variance 1 the adjusted sandwich's expectation is $(X^TX)^{-1}$
    exactly (the adjustment is built so; to round-off) for every bandwidth, though the plain kernel
    sandwich is biased low by what the solution absorbs (more with more lags); and over trials its
    mean agrees with that to its sampling spread."""
    X, _ = _ar1_problem(200, 3, 0.0, 0.0, seed=10)
    Omega = np.eye(600)
    for lags in (0, 4, 20):
        expected, B = _expected_hac(X, Omega, lags)
        np.testing.assert_allclose(expected, B, rtol=1e-9, atol=1e-12 * np.abs(B).max())
    d, covs = _hac_trials(X, Omega, 20, 1000, seed=11)
    # Along each fixed axis the sandwich scatters per trial by about sqrt(2 / G_eff) (G_eff = 14
    # effective views at 20 lags of 200: 0.38, more after the adjustment): the tolerance is 4
    # standard errors of the mean from the trials' own scatter (about 0.05).
    mean, tol = _mean_and_tolerance(covs, B)
    assert np.all(np.abs(mean - 1.0) < tol), (mean, tol)
    assert newey_west_lags(240) == 4 and newey_west_lags(100) == 4 and newey_west_lags(1000) == 6


def test_hac_covariance_matches_the_monte_carlo_covariance_under_ar1_view_errors():
    """Views whose common errors follow an AR(1) along the capture order (coefficient 0.5, as
    large as the corner noise): the estimate's covariance over 2000 trials, the mean of the
    adjusted Bartlett sandwich (20 lags) and its exact expectation agree along every direction,
    while the per-observation model $\\hat\\sigma^2 (X^TX)^{-1}$ is several times too small.

    Tolerances: the Monte Carlo covariance's variances scatter by $\\sqrt{2/2000}$ = 0.032
    relative (4 sigma: 0.13); the sandwich's mean by its trials' scatter over sqrt(2000) (4 of
    its standard errors, from the trials, about 0.04);
    its expectation differs from the truth by the kernel's truncation, $2\\sum_j \\frac{j}{21}0.5^j$
    of the shifts' long-run variance (about 6 % low at most), and by the adjustment, exact for
    independent errors only, of what the solution absorbs of the correlated part (200 views, 3
    parameters: about 1 %): 8 % in all (measured: 0.95-1.003)."""
    X, Omega = _ar1_problem(200, 3, 0.5, 1.0, seed=12)
    A = X.reshape(-1, K)
    B = np.linalg.inv(A.T @ A)
    truth = B @ A.T @ Omega @ A @ B
    expected, _ = _expected_hac(X, Omega, 20)
    lam = _relative_eigenvalues(expected, truth)
    assert np.all(np.abs(lam - 1.0) < 0.08), lam
    d, covs = _hac_trials(X, Omega, 20, 2000, seed=13)
    mean, tol = _mean_and_tolerance(covs, expected)
    assert np.all(np.abs(mean - 1.0) < tol), (mean, tol)
    mean, tol = _mean_and_tolerance(covs, truth)
    mc = _whitened_diagonals(d.T @ d / len(d), truth)
    assert np.all(np.abs(mean - mc) < 4.0 * np.sqrt(2.0 / len(d)) + tol + 0.08), (mean, mc)
    model = np.trace(Omega) / len(A) * B  # the per-observation model's covariance (its expectation, about)
    assert _relative_eigenvalues(model, truth).min() < 0.3


# --------------------------------------------------------------------------- errors that repeat


def _corner_capture(views: int, corners: int, phi: float, shared: float, seed: int, targets: int = 1):
    """A linear capture of `views` views (`targets` per pose, poses 0.1 s apart) of `corners`
    corners with two coordinates each: regressors like `_regressors`' (the pose-level part
    shared by the pose's views), every corner's error an
    AR(1) along the poses (coefficient `phi`, unit variance), plus a per-pose error of standard
    deviation `shared` that every view of the pose shares. Returns the refinement's stand-in
    (`jaxcal.stages._refine.error_correlation` reads it), the views' bookkeeping, the estimate's
    error and its exact covariance."""
    rng = np.random.default_rng(seed)
    poses = views // targets
    pose_part = np.repeat(
        rng.standard_normal((poses, 1, 1, K)), targets, axis=0
    )  # the views of a pose share it
    X = np.array([1.0, 0.5, -0.5]) + pose_part + 0.3 * rng.standard_normal((views, corners, 2, K))
    e = np.zeros((poses, targets, corners, 2))
    e[0] = rng.standard_normal((targets, corners, 2))
    for p in range(1, poses):
        e[p] = phi * e[p - 1] + np.sqrt(1.0 - phi**2) * rng.standard_normal((targets, corners, 2))
    e = (e + shared * rng.standard_normal((poses, 1, 1, 2))).reshape(views, corners, 2)
    A = X.reshape(-1, K)
    B = np.linalg.inv(A.T @ A)
    d = B @ A.T @ e.reshape(-1)
    r = e - X @ d
    s2 = float(np.sum(r**2) / (A.shape[0] - K))
    res = types.SimpleNamespace(
        residuals=r,
        weights=np.ones((views, corners)),
        inlier=np.ones((views, corners), bool),
        free=np.ones(K, bool),
        sigma_px=np.sqrt(s2),
        cov_model=s2 * B,
        cov=s2 * B,
        view_scores=np.einsum("vcdk,vcd->vk", X, r),
        view_information=np.einsum("vcdk,vcdl->vkl", X, X),
    )
    pose = np.repeat(np.arange(poses), targets)
    capture = _Corners(
        target=list(np.tile(np.arange(targets), poses)),
        pose=list(pose),
        t_cam=list(0.1 * pose),
        ids=[np.arange(corners)] * views,
        camera=[0] * views,
    )
    return res, capture, d, B


def test_errors_that_repeat_along_the_capture_are_found_and_covered():
    """Each corner's error an AR(1) along 300 poses (coefficient 0.5): the residuals' lag-k
    correlation is about 0.5^k, the one-sided test far past its limit, and the covariance
    becomes the kernel sandwich's (twice the longest correlated lag, at least Newey-West's),
    whose variance of the mean-like direction is the AR(1)'s long-run factor (1 + phi) / (1 - phi)
    = 3 times the model's, less the kernel's truncation; with independent errors the test
    reads a standard normal and the covariance stays. Tolerances: the lag correlations' sampling
    spread (1/sqrt(2 * 4 * 300) = 0.02, 4 sigmas) and the sandwich's (G_eff about 60: 35 %)."""
    limits = Limits()
    res, capture, _, B = _corner_capture(300, 4, 0.5, 0.0, seed=20)
    record, cov, before = error_correlation(capture, res, limits, lambda: res.view_information)
    np.testing.assert_allclose(record.autocorrelation[:3], [0.5, 0.25, 0.125], atol=0.08)
    assert record.pairs == tuple(4 * (300 - k) for k in range(1, 9)) and record.dof == 8
    assert record.sigmas > 8 and record.p_value < 1e-12 and record.pose_sigmas is None
    assert record.kernel_lags >= 2 * 3 and record.kernel_lags >= newey_west_lags(300)
    np.testing.assert_array_equal(before, res.cov)
    growth = _relative_eigenvalues(cov, res.cov)
    assert np.all(growth >= 1.0 - 1e-9) and 1.6 < growth.max() < 4.0, growth
    res, capture, _, _ = _corner_capture(300, 4, 0.0, 0.0, seed=21)
    record, cov, before = error_correlation(capture, res, limits, lambda: res.view_information)
    assert abs(record.sigmas) < 3.0 and cov is None and before is None and record.kernel_lags is None


def test_errors_a_poses_views_share_are_found():
    """Two targets per pose whose corners share a per-pose error as large as their own noise (as
    a robot pose error moves both): the score test between a pose's views passes its limit;
    without it, it reads a standard normal."""
    res, capture, _, _ = _corner_capture(400, 4, 0.0, 1.0, seed=22, targets=2)
    record, cov, _ = error_correlation(capture, res, Limits(), lambda: res.view_information)
    assert record.pose_sigmas > Limits().correlation_sigmas and cov is not None
    res, capture, _, _ = _corner_capture(400, 4, 0.0, 0.0, seed=23, targets=2)
    record, cov, _ = error_correlation(capture, res, Limits(), lambda: res.view_information)
    assert abs(record.pose_sigmas) < 3.0 and cov is None


def test_corner_pairs_stay_within_a_run_of_the_capture():
    """Pairs join the same corner id of one camera and target `k` capture indices apart, not
    across a gap in time (the next sweep) nor between targets; ids matched, not slots."""
    capture = _Corners(
        target=[0, 0, 0, 1, 0],
        pose=[0, 1, 2, 2, 3],
        t_cam=[0.0, 0.1, 0.2, 0.2, 5.0],
        ids=[np.array([0, 1, 2]), np.array([1, 2, 5]), np.array([2, 5]), np.array([0, 1]), np.array([2])],
        camera=[0, 0, 0, 0, 0],
    )
    lag1, lag2 = corner_pairs(capture, lags=2)
    np.testing.assert_array_equal(lag1, [[0, 1, 1, 0], [0, 2, 1, 1], [1, 1, 2, 0], [1, 2, 2, 1]])
    np.testing.assert_array_equal(lag2, [[0, 2, 2, 0]])
