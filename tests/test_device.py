"""`jaxcal._device`: host arrays and solver codes read without a compiled program."""

import jax
import numpy as np
import optimistix as optx

from jaxcal._device import flat_on_device, result_is, to_device


def test_result_is_equals_the_enumerations_comparison_batched_or_not():
    names = ["successful", "nonlinear_max_steps_reached", "nonlinear_divergence", "singular", "breakdown"]
    items = [getattr(optx.RESULTS, n) for n in names]
    for item in items:
        for name in ("successful", "nonlinear_max_steps_reached"):
            assert bool(result_is(item, name)) == bool(item == getattr(optx.RESULTS, name))
            assert bool(result_is(jax.device_get(item), name)) == bool(item == getattr(optx.RESULTS, name))
    # A vmapped solve's codes: one per element.
    batched = jax.vmap(
        lambda ok: optx.RESULTS.where(ok, optx.RESULTS.successful, optx.RESULTS.nonlinear_divergence)
    )(np.array([True, False, True]))
    np.testing.assert_array_equal(result_is(batched), [True, False, True])
    np.testing.assert_array_equal(result_is(batched, "nonlinear_divergence"), [False, True, False])


def test_to_device_keeps_values_dtype_and_shape():
    x = np.arange(6.0).reshape(2, 3)
    y = to_device(x)
    assert isinstance(y, jax.Array) and y.dtype == np.float64 and y.shape == (2, 3)
    np.testing.assert_array_equal(np.asarray(y), x)
    assert to_device(y) is y
    assert to_device([True, False], bool).dtype == np.bool_


def test_numpy_se3_exp_is_the_compiled_one():
    """`jaxcal._npgeom.se3_exp` (the drift check's host poses) equals `jaxcal._geometry.se3_exp`,
    small rotations included."""
    from jaxcal import _geometry, _npgeom

    rng = np.random.default_rng(0)
    for scale in (1.0, 1e-5, 1e-10, 0.0):
        xi = np.concatenate([rng.normal(size=3), scale * rng.normal(size=3)])
        np.testing.assert_allclose(_npgeom.se3_exp(xi), np.asarray(_geometry.se3_exp(xi)), atol=1e-14)


def test_flat_on_device_is_ravel_pytree():
    from jax.flatten_util import ravel_pytree

    tree = {"b": np.arange(6.0).reshape(2, 3), "a": (np.float64(2.5), np.ones((1, 2, 2))), "c": None}
    np.testing.assert_array_equal(np.asarray(flat_on_device(tree)), np.asarray(ravel_pytree(tree)[0]))
    assert flat_on_device({}).shape == (0,)
