"""Shared test helpers: tree comparison and a catalogue of synthetic problems."""

import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal._arcdata import make_arc_data
from jaxcal._geometry import normalize, so3_exp
from jaxcal._montecarlo import MonteCarloSetup, SweepPlan, default_setup
from jaxcal.robots import load_robot


def tree_allclose(a, b, *, atol=1e-12, rtol=0.0) -> bool:
    leaves_a, leaves_b = jax.tree.leaves(a), jax.tree.leaves(b)
    if len(leaves_a) != len(leaves_b):
        return False
    return all(
        np.allclose(np.asarray(x), np.asarray(y), atol=atol, rtol=rtol) for x, y in zip(leaves_a, leaves_b)
    )


@functools.partial(jax.jit, static_argnames=("frames", "markers"))
def arc_problem(key, *, frames=40, markers=1, span=1.2, rate=1.01, sigma_p=0.0, sigma_r=0.0):
    """A random joint sweep: truth (V, Q, rate) and noisy marker poses (one
    compiled program per shape: op by op it would compile each of its ~40 ops)."""
    k = jax.random.split(key, 7)
    V = normalize(jax.random.normal(k[0], (3,)))
    Q = 0.3 * jax.random.normal(k[1], (3,)) + jnp.array([0.0, 0.0, 1.0])
    p0 = Q + 0.2 * jax.random.normal(k[2], (markers, 3))
    O0 = jax.vmap(so3_exp)(jax.random.normal(k[3], (markers, 3)))
    alpha = jnp.linspace(-span / 2, span / 2, frames)
    R = jax.vmap(lambda a: so3_exp(V * a * rate))(alpha)
    P = Q + jnp.einsum("fab,mb->mfa", R, p0 - Q) + sigma_p * jax.random.normal(k[4], (markers, frames, 3))
    O = jnp.einsum("fab,mbc->mfac", R, O0)
    dR = jax.vmap(jax.vmap(so3_exp))(sigma_r * jax.random.normal(k[5], (markers, frames, 3)))
    O = jnp.einsum("mfab,mfbc->mfac", dR, O)
    truth = dict(V=V, Q=Q, rate=rate, p0=p0, O0=O0)
    return truth, P, O, alpha


def arc_data(key, *, encoder=True, orientations=True, sigma_p=1e-4, sigma_r=1e-3, noisy=False, **kw):
    truth, P, O, alpha = arc_problem(
        key, sigma_p=sigma_p if noisy else 0.0, sigma_r=sigma_r if noisy else 0.0, **kw
    )
    data = make_arc_data(
        P,
        O if orientations else None,
        alpha if encoder else None,
        sigma_position=sigma_p,
        sigma_rotation=sigma_r,
    )
    return truth, data


def ur5e_setup(noise=None, frames=40) -> MonteCarloSetup:
    """The UR5e filmed from 1.5 m with a marker 5 cm off the flange."""
    return default_setup(load_robot("ur5e"), noise=noise, plan=SweepPlan(frames=frames))


def corrupt_frames(
    key, P, O, *, fraction=0.1, sigma_p=1e-4, sigma_r=1e-3, position_sigmas=20.0, rotation_sigmas=10.0
):
    """Gross errors in a random `fraction` of the frames (every marker of a
    frame): positions moved by `position_sigmas` noise sigmas and orientations
    turned by `rotation_sigmas`, each in a random direction.

    **Returns:** `(P, O, bad, dP)`: the corrupted arrays, the `(markers, frames)`
    mask of corrupted samples and the position displacements (m).
    """
    P, O = np.asarray(P), np.asarray(O)
    M, F = P.shape[:2]
    k1, k2, k3 = jax.random.split(key, 3)
    frames = np.asarray(jax.random.choice(k1, F, (int(round(fraction * F)),), replace=False))
    bad = np.zeros((M, F), bool)
    bad[:, frames] = True
    d = np.array(jax.random.normal(k2, (M, F, 3)))
    dP = np.where(
        bad[..., None], position_sigmas * sigma_p * d / np.linalg.norm(d, axis=-1, keepdims=True), 0.0
    )
    a = np.array(jax.random.normal(k3, (M, F, 3)))
    a = rotation_sigmas * sigma_r * a / np.linalg.norm(a, axis=-1, keepdims=True)
    dR = np.asarray(jax.vmap(jax.vmap(so3_exp))(jnp.asarray(a)))
    O = np.where(bad[..., None, None], dR @ O, O)
    return P + dP, O, bad, dP
