"""The compiled programs the stages run, built once per process.

Each is a `jax.jit` of a pure solver; what changes between datasets (the
numbers) are arguments, what decides shapes and control flow is static. JAX's
persistent cache (`jaxcal._cache`) keeps them across processes.
"""

import functools

import jax
import numpy as np

from .._arcfit import fit_arc
from .._axisfit import fit_axes
from .._clocksync import fit_clock_offset
from .._refine import identifiable_mask, refine


@functools.cache
def arc_fits():
    """Every joint's arc fit at once: `jax.vmap(fit_arc)` over stacked `ArcData`."""
    return jax.jit(jax.vmap(lambda d: fit_arc(d, max_steps=100)))


@functools.cache
def arc_fit():
    """One joint's arc fit (the sequential procedure fits joint after joint)."""
    return jax.jit(lambda d: fit_arc(d, max_steps=100))


@functools.cache
def axis_fit(use_poses: bool):
    """`fit_axes(nominal, arcs, T_flange_marker=mount, free=free)`."""

    def fit(nominal, arcs, mount, free=None):
        return fit_axes(nominal, arcs, T_flange_marker=mount, use_poses=use_poses, free=free)

    return jax.jit(fit)


@functools.cache
def clock_fit():
    """`fit_clock_offset(data, t_cam, enc_t, enc_q, offset0_s, drift_ppm)`."""

    def fit(data, t_cam, enc_t, enc_q, offset0_s, drift_ppm):
        return fit_clock_offset(data, t_cam, enc_t, enc_q, offset0_s=offset0_s, drift_ppm=drift_ppm)

    return jax.jit(fit)


@functools.cache
def _refinement(free: tuple):
    return jax.jit(lambda problem, params0: refine(problem, params0, np.asarray(free)))


def refinement(free: np.ndarray):
    """`refine(problem, params0, free)` for a concrete `free` mask (static)."""
    return _refinement(tuple(bool(f) for f in np.asarray(free)))


@functools.cache
def identifiable():
    """The refinement's `identifiable_mask(problem, params, candidates, tol=...)`."""
    return jax.jit(identifiable_mask)
