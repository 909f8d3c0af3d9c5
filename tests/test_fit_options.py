"""The fits take their settings as objects (`LMOptions`, `RobustOptions`); the keywords
they replaced, deprecated for one release, are gone."""

import warnings
from dataclasses import replace

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import arc_problem, corrupt_frames

import jaxcal
from jaxcal import LMOptions, RobustOptions
from jaxcal._arcdata import make_arc_data
from jaxcal._arcfit import ARC_OPTIONS
from jaxcal._axisfit import AXIS_OPTIONS
from jaxcal._montecarlo import SWEEP_OPTIONS
from jaxcal._refine import REFINE_OPTIONS, REFINE_ROBUST
from jaxcal._tooloffset import fit_circle


def _noisy_sweep():
    """A noisy sweep with corrupted frames, so that the robust rounds have work."""
    _, P, O, alpha = arc_problem(jax.random.key(3), sigma_p=1e-4, sigma_r=1e-3, frames=24)
    P, O, _, _ = corrupt_frames(jax.random.key(4), P, O)
    return make_arc_data(P, O, alpha, sigma_position=1e-4, sigma_rotation=1e-3)


def _same(a, b):
    la, lb = jax.tree.leaves(a), jax.tree.leaves(b)
    assert len(la) == len(lb)
    for x, y in zip(la, lb):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_the_objects_are_exported_frozen_and_checked():
    assert jaxcal.LMOptions is LMOptions and jaxcal.RobustOptions is RobustOptions
    with pytest.raises(AttributeError):
        RobustOptions().c = 2.0  # frozen
    with pytest.raises(ValueError, match="loss must be one of"):
        RobustOptions("l1")
    with pytest.raises(ValueError, match="plain least squares: robust=None"):
        RobustOptions(None)
    with pytest.raises(ValueError, match="rounds must be at least 1"):
        RobustOptions(rounds=0)


def test_the_objects_reach_the_fit_and_do_not_warn():
    data = _noisy_sweep()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fit = jaxcal.fit_arc(
            data,
            robust=RobustOptions("huber", c=2.5, reject=4.0, rounds=2),
            options=LMOptions(1e-9, 1e-2, 40),
        )
        capped = jaxcal.fit_arc(data, options=LMOptions(1e-8, 3e-2, 1))
    assert int(fit.num_steps) > 0 and not np.all(np.asarray(fit.inlier)[np.asarray(data.mask)])
    # max_steps reaches every solve: 3 rounds and the inlier solve, 1 step each.
    assert int(capped.num_steps) <= 4


@pytest.mark.parametrize("old", [{"loss": "huber"}, {"c": 2.5}, {"rtol": 1e-9}, {"max_steps": 7}])
def test_the_keywords_the_objects_replaced_are_gone(old):
    """They worked for one release with a `DeprecationWarning`; now Python's own error."""
    (name,) = old
    with pytest.raises(TypeError, match=f"unexpected keyword argument '{name}'"):
        jaxcal.fit_arc(_noisy_sweep(), **old)
    with pytest.raises(TypeError, match=f"unexpected keyword argument '{name}'"):
        fit_circle(jnp.zeros((8, 2)), **old)


def test_the_sweeps_and_the_refinement_keep_their_defaults():
    """`fit_sweeps`' one `options` is what both of its fits had (the arc and axis fits'
    tolerances, 100 steps each); `refine`'s objects hold the keywords' old defaults."""
    assert SWEEP_OPTIONS == replace(ARC_OPTIONS, max_steps=100) == replace(AXIS_OPTIONS, max_steps=100)
    assert REFINE_OPTIONS == LMOptions(rtol=1e-7, atol=1e-7, max_steps=50)
    assert REFINE_ROBUST == RobustOptions("cauchy", c=3.0, reject=3.7, rounds=3)
