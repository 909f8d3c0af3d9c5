"""The few distributions jaxcal's statistical tests use, from `scipy.special`'s functions: what
`scipy.stats` computes for them, without importing `scipy.stats` (most of a second of a command's
start-up for a handful of numbers). Each is the same special function `scipy.stats` calls, so the
values are its own."""

import numpy as np
from scipy import special


def chi2_sf(x, dof):
    """$P(\\chi^2_{dof} > x)$."""
    return special.chdtrc(dof, x)


def chi2_ppf(q, dof):
    """The `q` quantile of $\\chi^2_{dof}$."""
    return special.chdtri(dof, 1.0 - np.asarray(q))


def normal_isf(p):
    """The standard normal's upper `p` quantile (a p-value as a size in sigmas), finite for `p`
    down to the smallest double."""
    return -special.ndtri(np.maximum(np.asarray(p, np.float64), np.finfo(np.float64).tiny))


def f_sf(x, dfn, dfd):
    """$P(F_{dfn, dfd} > x)$."""
    return special.fdtrc(dfn, dfd, x)


def f_ppf(q, dfn, dfd):
    """The `q` quantile of $F_{dfn, dfd}$."""
    return special.fdtri(dfn, dfd, q)


def binom_cdf(k, n, p):
    """$P(B(n, p) \\le k)$."""
    return special.bdtr(np.floor(k), n, p)


def binom_ppf(q, n, p):
    """The smallest $k$ with $P(B(n, p) \\le k) \\ge q$."""
    k = np.ceil(special.bdtrik(q, n, p))
    below = np.maximum(k - 1, 0)
    return np.where(special.bdtr(below, n, p) >= q, below, k)
