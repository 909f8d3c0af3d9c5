"""Robust weights for k-vector residual samples (`jaxcal._robust`), against SciPy's chi distributions."""

import jax.numpy as jnp
import numpy as np
import pytest
from scipy import special, stats

from jaxcal._robust import (
    chi_median,
    deletion_residuals,
    loss_weights,
    rayleigh_equivalent,
    robust_scale,
    sample_weights,
)


def test_chi_median_equals_scipy():
    nu = np.array([1.0, 1.3, 2.0, 2.5, 3.0, 4.7, 6.0])
    np.testing.assert_allclose(chi_median(jnp.asarray(nu)), stats.chi.median(nu), rtol=1e-12)
    assert float(chi_median(jnp.asarray(2.0))) == pytest.approx(np.sqrt(2 * np.log(2)), rel=1e-13)


@pytest.mark.parametrize("nu", [1.5, 2.0, 3.0, 6.0])
def test_rayleigh_equivalent_has_the_same_tail_probability(nu):
    z = np.array([0.0, 0.3, 1.0, 2.5, 4.0, 8.0, 20.0, 34.0, 36.0, 60.0])
    eq = np.asarray(rayleigh_equivalent(jnp.asarray(z), jnp.asarray(nu)))
    # Rayleigh's survival function is exp(-r^2 / 2); chi_nu's is chi2.sf(z^2, nu), or
    # where SciPy underflows, its asymptotic series Q(a, x) ~ x^(a-1) e^-x / Gamma(a) sum_n (a-1)...(a-n)/x^n.
    a, x = nu / 2, np.maximum(z**2 / 2, 600.0)
    series = sum(np.prod([a - 1 - i for i in range(n)]) / x**n for n in range(6))
    asymptotic = (a - 1) * np.log(x) - x - special.gammaln(a) + np.log(series)
    log_sf = np.where(z < 36.5, stats.chi2.logsf(z**2, nu), asymptotic)
    np.testing.assert_allclose(-0.5 * eq**2, log_sf, rtol=2e-3, atol=1e-12)
    if nu == 2.0:
        np.testing.assert_allclose(eq, z, rtol=1e-6)
    assert np.all(np.diff(eq) > 0)  # monotone, across the switch to the asymptotic form (x = 600)


@pytest.mark.parametrize("nu", [3.0, 2.0, 5.6])
def test_scale_and_false_rejections_on_clean_samples(nu):
    """Norms of clean samples with nu degrees of freedom, noise 0.7: the
    scale is 0.7 and reject = 3.7 drops exp(-3.7^2/2) = 0.11 % of them."""
    rng = np.random.default_rng(int(10 * nu))
    e = 0.7 * np.sqrt(rng.chisquare(nu, size=200_000))
    mask = np.ones(e.shape, bool)
    s = robust_scale(jnp.asarray(e), jnp.full(e.shape, nu), jnp.asarray(mask))
    assert float(s) == pytest.approx(0.7, rel=0.01)
    w, z, s2 = sample_weights(
        jnp.asarray(e),
        jnp.full(e.shape, nu),
        jnp.asarray(mask),
        loss="cauchy",
        c=3.0,
        reject=3.7,
        hard=True,
    )
    assert set(np.unique(np.asarray(w))) == {0.0, 1.0}
    expected = np.exp(-(3.7**2) / 2) * e.size
    assert abs(np.sum(np.asarray(w) == 0) - expected) < 4 * np.sqrt(expected)
    # Soft: the Cauchy weights of the Rayleigh-equivalent radii; unobserved samples weigh 0.
    mask[:10] = False
    w, z, _ = sample_weights(
        jnp.asarray(e),
        jnp.full(e.shape, nu),
        jnp.asarray(mask),
        loss="cauchy",
        c=3.0,
        reject=3.7,
        hard=False,
    )
    np.testing.assert_allclose(np.asarray(w)[10:], 1.0 / (1.0 + (np.asarray(z)[10:] / 3.0) ** 2))
    assert np.all(np.asarray(w)[:10] == 0.0)


def test_loss_weights():
    z = jnp.array([0.0, 1.0, 3.0, 6.0])
    np.testing.assert_allclose(loss_weights(z, "cauchy", 3.0), [1.0, 0.9, 0.5, 0.2])
    np.testing.assert_allclose(loss_weights(z, "huber", 3.0), [1.0, 1.0, 1.0, 0.5])
    np.testing.assert_allclose(loss_weights(z, None, 3.0), 1.0)
    with pytest.raises(ValueError, match="loss must be one of"):
        loss_weights(z, "tukey", 3.0)


def _refit_without(J, y, w, i, own=None):
    """Brute-force deletion: weighted least squares without sample `i` (and its own
    parameter column `own`), its residual at `i` and that residual's covariance."""
    N, k, n = J.shape
    keep = np.arange(N) != i
    cols = np.ones(n, bool) if own is None else np.arange(n) != own
    A = J[keep][:, :, cols].reshape(-1, cols.sum())
    wr = np.repeat(w[keep], k)
    C = np.linalg.inv(A.T @ (wr[:, None] * A))
    r = y[i] - J[i][:, cols] @ (C @ A.T @ (wr * y[keep].reshape(-1)))
    return r, np.eye(k) + J[i][:, cols] @ C @ J[i][:, cols].T


def test_deletion_residuals_equal_refits_without_the_sample():
    """The deletion residual from the fit's own blocks equals a refit without the
    sample (weights 1, soft and 0; with and without a parameter of its own, which
    takes one degree of freedom), and is what a high-leverage outlier cannot hide."""
    rng = np.random.default_rng(3)
    N, k, n = 25, 6, 7
    for own in (False, True):
        J = np.zeros((N, k, n + N * own))
        J[:, :, :n] = rng.normal(size=(N, k, n))
        J[1:, :, 0] *= 0.1  # parameter 0 is seen mostly by sample 0: leverage 0.85 along it
        if own:
            J[np.arange(N), :, n + np.arange(N)] = rng.normal(size=(N, k))
        y = rng.normal(size=(N, k))
        y[0] += 20.0 * J[0, :, 0] / np.linalg.norm(J[0, :, 0])  # an outlier along that leverage
        w = rng.uniform(0.3, 1.0, N)
        w[[0, 2]] = 1.0
        w[3] = 0.2 if own else 0.0  # an excluded sample's own parameter would be undetermined
        Jf, wr = J.reshape(N * k, -1), np.repeat(w, k)
        C = np.linalg.inv(Jf.T @ (wr[:, None] * Jf))
        r = (y.reshape(-1) - Jf @ (C @ Jf.T @ (wr * y.reshape(-1)))).reshape(N, k)
        G = np.einsum("iap,pq,ibq->iab", J, C, J)
        mask = np.ones(N, bool)
        mask[5] = False
        d, nu = deletion_residuals(jnp.asarray(r), jnp.asarray(G), jnp.asarray(w), jnp.asarray(mask))
        d, nu = np.asarray(d), np.asarray(nu)
        for i in (0, 1, 2, 3):
            ri, V = _refit_without(J, y, w, i, own=n + i if own else None)
            P = np.linalg.inv(V)
            if own:  # the sample's own parameter absorbs its component along its column
                a = J[i, :, n + i]
                P = P - np.outer(P @ a, P @ a) / (a @ P @ a)
            assert d[i] == pytest.approx(np.sqrt(ri @ P @ ri), rel=1e-9), (own, i)
        np.testing.assert_allclose(nu[mask], k - own, atol=1e-9)
        assert d[5] == 0.0 and nu[5] == k
        if not own:  # masking: the outlier's fitted residual is ordinary, its deletion residual is not
            e = np.linalg.norm(r, axis=-1)
            assert e[0] < 1.5 * np.median(e) and e[0] < 1.05 * e[1:].max()
            assert d[0] > 2.5 * np.median(d[mask])
