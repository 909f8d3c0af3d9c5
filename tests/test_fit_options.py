"""The fits take their settings as objects (`LMOptions`, `RobustOptions`); the keywords
they replaced still work for one release, with a `DeprecationWarning`, and give the
same result bit for bit (the same values reach the same compiled solver)."""

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
from jaxcal._options import fit_options
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


def test_old_keywords_warn_and_give_the_same_arc_fit():
    data = _noisy_sweep()
    new = jaxcal.fit_arc(
        data, robust=RobustOptions("huber", c=2.5, reject=4.0, rounds=2), options=LMOptions(1e-9, 1e-2, 40)
    )
    with pytest.warns(
        DeprecationWarning, match=r"fit_arc\(loss=, c=, reject=, rounds=, rtol=, atol=, max_steps=\)"
    ):
        old = jaxcal.fit_arc(
            data, loss="huber", c=2.5, reject=4.0, rounds=2, rtol=1e-9, atol=1e-2, max_steps=40
        )  # fmt: skip
    _same(new, old)
    assert int(new.num_steps) > 0 and not np.all(np.asarray(new.inlier)[np.asarray(data.mask)])


def test_the_defaults_and_plain_least_squares_are_kept():
    """`loss=None` (and `c`, `reject`, `rounds` without a loss, which never applied) is
    `robust=None`; `max_steps` alone keeps the fit's other defaults."""
    data = _noisy_sweep()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the new spelling does not warn
        plain = jaxcal.fit_arc(data)
        capped = jaxcal.fit_arc(data, options=LMOptions(1e-8, 3e-2, 7))
    with pytest.warns(DeprecationWarning, match="robust=RobustOptions"):
        _same(jaxcal.fit_arc(data, loss=None, c=2.0), plain)
    with pytest.warns(DeprecationWarning, match=r"options=LMOptions\(max_steps=\.\.\.\)"):
        _same(jaxcal.fit_arc(data, max_steps=7), capped)


def test_the_mapping_fills_the_objects():
    base = LMOptions(1e-8, 3e-2, 50)
    with pytest.warns(DeprecationWarning):
        options, robust = fit_options("f", base, None, {"atol": 1e-3, "loss": "cauchy", "reject": None})
    assert (options.rtol, options.atol, options.max_steps) == (1e-8, 1e-3, 50)
    assert robust == RobustOptions("cauchy", 3.0, None, 3)
    with pytest.warns(DeprecationWarning):  # a fit whose default is robust keeps its loss
        _, robust = fit_options("f", base, RobustOptions("huber"), {"c": 1.5})
    assert robust == RobustOptions("huber", 1.5)
    assert fit_options("f", base, None, {}) == (base, None)


def test_unknown_keywords_and_robust_keywords_of_plain_fits_are_type_errors():
    with pytest.raises(TypeError, match="fit_arc\\(\\) got an unexpected keyword argument 'tol'"):
        jaxcal.fit_arc(_noisy_sweep(), tol=1e-3)
    with pytest.raises(TypeError, match="fit_circle\\(\\) got an unexpected keyword argument 'loss'"):
        fit_circle(jnp.zeros((8, 2)), loss="cauchy")


def test_old_keywords_of_the_plain_fits_warn_and_agree():
    t = np.linspace(0.0, 2.0, 12)
    points = jnp.asarray(np.c_[0.3 + 0.1 * np.cos(t), -0.2 + 0.1 * np.sin(t)])
    new = fit_circle(points, options=LMOptions(1e-10, 1e-10, 20))
    with pytest.warns(DeprecationWarning, match="fit_circle"):
        old = fit_circle(points, max_steps=20)
    _same(new, old)
    np.testing.assert_allclose(np.asarray(new.centre), [0.3, -0.2], atol=1e-9)  # exact points


def test_the_sweeps_and_the_refinement_keep_their_defaults():
    """`fit_sweeps`' one `options` is what both of its fits had (the arc and axis fits'
    tolerances, 100 steps each); `refine`'s objects hold the keywords' old defaults."""
    assert SWEEP_OPTIONS == replace(ARC_OPTIONS, max_steps=100) == replace(AXIS_OPTIONS, max_steps=100)
    assert REFINE_OPTIONS == LMOptions(rtol=1e-7, atol=1e-7, max_steps=50)
    assert REFINE_ROBUST == RobustOptions("cauchy", c=3.0, reject=3.7, rounds=3)
