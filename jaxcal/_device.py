"""Host data onto the device without a compiled program.

`jnp.asarray` of a NumPy array runs a small compiled program per shape and dtype
(JAX 0.10 stages the copy through `lax`): in a fresh process each costs a trace,
a lowering and a compile or a cache read, tens of milliseconds, and a
calibration's host code made a few dozen of them. `jax.device_put` of the same
array transfers it with no program: the same values, dtype and shape (not
weakly typed; `to_device` is for arrays, not Python scalars, whose weak type
`jnp.asarray` keeps).
"""

import jax
import numpy as np


def to_device(x, dtype=None) -> jax.Array:
    """`x` (a NumPy array, a nested list, or a device array) as a device array of `dtype`
    (default: its own), moved without a compiled program."""
    if isinstance(x, jax.Array) and (dtype is None or x.dtype == np.dtype(dtype)):
        return x
    return jax.device_put(np.asarray(x, dtype))
