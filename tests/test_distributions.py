"""`jaxcal._distributions` gives what `scipy.stats` gives for the tests' distributions (it
computes them from `scipy.special` so that a command need not import `scipy.stats`)."""

import numpy as np
import pytest
import scipy.stats as st

from jaxcal import _distributions as d


def _cases(n=400, seed=0):
    rng = np.random.default_rng(seed)
    for _ in range(n):
        dof, dfd, trials = (int(v) for v in rng.integers(1, [3000, 500, 2000]))
        yield dof, dfd, trials, float(rng.uniform(0, 2 * dof)), float(rng.uniform(5e-4, 1 - 5e-4)), rng


def test_chi2_and_f_as_scipy_stats():
    for dof, dfd, _, x, q, _ in _cases():
        assert d.chi2_sf(x, dof) == pytest.approx(st.chi2.sf(x, dof), rel=1e-12, abs=1e-300)
        assert d.chi2_ppf(q, dof) == pytest.approx(st.chi2.ppf(q, dof), rel=1e-12)
        assert d.f_sf(x / dof, dof, dfd) == pytest.approx(st.f.sf(x / dof, dof, dfd), rel=1e-12, abs=1e-300)
        assert d.f_ppf(q, dof, dfd) == pytest.approx(st.f.ppf(q, dof, dfd), rel=1e-12)


def test_binomial_as_scipy_stats():
    """The cdf to 1e-9 wherever it is above 1e-250 (SciPy's own two implementations part in the
    underflow below), the quantile exactly."""
    for _, _, n, _, q, rng in _cases():
        k = int(rng.integers(0, n + 1))
        ref = st.binom.cdf(k, n, 0.95)
        if ref > 1e-250:
            assert d.binom_cdf(k, n, 0.95) == pytest.approx(ref, rel=1e-9)
        assert d.binom_ppf(q, n, 0.95) == st.binom.ppf(q, n, 0.95)
    assert d.binom_ppf(1e-3, 20, 0.95) == 15 and d.binom_cdf(20, 20, 0.95) == 1.0
