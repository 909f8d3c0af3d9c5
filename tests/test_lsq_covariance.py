"""The kit's normal-matrix covariances (`jaxcal._lsq.normal_pinv`, `normal_inverse`): the
formulas the fits used to write themselves, on fixed cases."""

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal._lsq import normal_inverse, normal_pinv

RNG = np.random.default_rng(34)
#: A tall Jacobian with columns of very different scales (m, rad, px): condition ~1e6.
J = RNG.normal(size=(40, 5)) * np.array([1e-3, 1.0, 1e2, 1.0, 10.0])


def test_the_pseudo_inverse_over_the_free_parameters():
    free = np.array([1.0, 1.0, 0.0, 1.0, 1.0])
    Jf = J * free
    cov = normal_pinv(jnp.asarray(Jf.T @ Jf), jnp.asarray(free), 2.5)
    idx = np.flatnonzero(free)
    # The exact inverse of the free block; the rest zero. Relative error ~ cond(H) eps = 1e-12 x
    # the entries' scale (cond(H) = cond(J)^2 ~ 1e12 at most here): 1e-6 leaves room and still
    # catches a wrong scale, a missing frozen row or a lost sigma^2.
    want = np.zeros((5, 5))
    want[np.ix_(idx, idx)] = 2.5 * np.linalg.inv(J[:, idx].T @ J[:, idx])
    np.testing.assert_allclose(cov, want, rtol=1e-6, atol=1e-9 * np.abs(want).max())
    assert np.all(np.asarray(cov)[2] == 0.0) and np.all(np.asarray(cov)[:, 2] == 0.0)


def test_the_pseudo_inverse_is_the_hermitian_pinv_the_fits_wrote():
    """Bit for bit the expressions `_arcfit`, `_clocksync`, `_handeye` and `touch` had."""
    H = jnp.asarray(J.T @ J)
    free = jnp.asarray([1.0, 0.0, 1.0, 1.0, 1.0])
    before = jnp.linalg.pinv(H + jnp.diag(1.0 - free), hermitian=True) * free[:, None] * free[None, :]
    assert np.array_equal(jax.jit(normal_pinv)(H, free), jax.jit(lambda h, f: before)(H, free))
    assert np.array_equal(normal_pinv(H), jnp.linalg.pinv(H, hermitian=True))


def test_the_inverse_keeps_numpy_on_the_host_and_jax_in_a_program():
    H = J.T @ J
    out = normal_inverse(H, 4.0)
    assert isinstance(out, np.ndarray) and np.array_equal(out, 4.0 * np.linalg.inv(H))
    assert np.array_equal(normal_inverse(H), np.linalg.inv(H))
    traced = jax.jit(lambda h, s: normal_inverse(h, s**2))(jnp.asarray(H), 2.0)
    np.testing.assert_allclose(traced, out, rtol=1e-6)  # same maths, another LU: cond(H) eps
