"""Host data onto the device, and device results read on the host, without a compiled program.

`jnp.asarray` of a NumPy array runs a small compiled program per shape and dtype
(JAX 0.10 stages the copy through `lax`), as do `ravel_pytree`, an optimistix result
code's `==` and any `jnp` operation on host values: in a fresh process each costs a
trace, a lowering and a compile or a cache read, and the first of them loads JAX's
lowering machinery. A warm command's host code therefore uses these instead, and
runs nothing compiled but its stored programs (`jaxcal._exported`; a test keeps a
warm calibration so). `jax.device_put` transfers an array with no program: the same
values, dtype and shape (not weakly typed; `to_device` is for arrays, not Python
scalars, whose weak type `jnp.asarray` keeps).
"""

import jax
import numpy as np


def to_device(x, dtype=None) -> jax.Array:
    """`x` (a NumPy array, a nested list, or a device array) as a device array of `dtype`
    (default: its own), moved without a compiled program (a traced `x` is cast in its program)."""
    if isinstance(x, jax.Array) and (dtype is None or x.dtype == np.dtype(dtype)):
        return x
    if isinstance(x, jax.core.Tracer):
        return x.astype(dtype)
    return jax.device_put(np.asarray(x, dtype))


def flat_on_device(tree) -> jax.Array:
    """`jax.flatten_util.ravel_pytree(tree)[0]` (the leaves in `jax.tree.leaves` order, each
    flattened) for a host caller, joined in NumPy and moved: `ravel_pytree` runs a compiled
    program per leaf shape."""
    leaves = [np.ravel(np.asarray(leaf)) for leaf in jax.tree.leaves(tree)]
    return to_device(np.concatenate(leaves) if leaves else np.zeros(0))


def result_is(result, name: str = "successful") -> np.ndarray:
    """Per element, whether optimistix result codes (an `optx.RESULTS` item, batched or not, on
    the host or the device) are `name` (`RESULTS.successful` by default), as NumPy booleans.
    `result == RESULTS.successful` makes a JAX array, a compiled program (module docstring).
    Not for traced codes (use `==` inside programs)."""
    return np.asarray(result._value) == np.asarray(getattr(result._enumeration, name)._value)
