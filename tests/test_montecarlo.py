"""Monte Carlo entry point: one jit(vmap) call over seeded trials."""

import equinox as eqx
import jax
import numpy as np
import optimistix as optx
from helpers import ur5e_setup

from jaxcal._montecarlo import NoiseModel, monte_carlo, summarize

SETUP = ur5e_setup(frames=24)


def test_noise_free_trials_are_exact():
    quiet = ur5e_setup(noise=NoiseModel(0.0, 0.0, 0.0), frames=24)
    res = monte_carlo(quiet, jax.random.key(0), 4)
    assert np.all(np.asarray(res.success))
    assert float(np.max(res.ee_rms_mm)) < 1e-5
    assert float(np.max(res.axis_dir_deg)) < 1e-8
    assert float(np.max(res.cam_trans_mm)) < 1e-6
    assert float(np.max(np.abs(res.ratio_err_percent))) < 1e-8
    # The uncalibrated arm is millimetres off: the calibration is doing real work.
    assert float(np.min(res.ee_rms_mm_nominal)) > 1.0


def test_noisy_trials_improve_and_are_reproducible():
    res = monte_carlo(SETUP, jax.random.key(1), 16)
    assert np.asarray(res.arc_result._value).shape == (16, 6)
    assert np.all(np.asarray(res.arc_result._value) == optx.RESULTS.successful._value)
    s = summarize(res)
    assert s["success_rate"] == 1.0
    # 0.1 mm / 0.05 deg marker noise: sub-millimetre after, millimetres before.
    assert s["ee_rms_mm_median"] < 0.5
    assert s["ee_rms_mm_nominal_median"] > 5.0 * s["ee_rms_mm_median"]
    assert s["ratio_err_percent_max_median"] < 0.2
    again = monte_carlo(SETUP, jax.random.key(1), 16)
    np.testing.assert_array_equal(np.asarray(res.ee_rms_mm), np.asarray(again.ee_rms_mm))


def test_error_grows_with_noise():
    """Same compiled trial, a noise level 4x larger: errors scale accordingly."""
    loud = ur5e_setup(noise=NoiseModel(0.4, 0.2, 0.0), frames=24)
    low = summarize(monte_carlo(SETUP, jax.random.key(2), 16))
    high = summarize(monte_carlo(loud, jax.random.key(2), 16))
    ratio = high["ee_rms_mm_median"] / low["ee_rms_mm_median"]
    assert 2.5 < ratio < 6.0


def test_failed_trials_are_flagged_not_raised():
    """A step budget of 1: every solve stops early, and the batch still returns
    with each trial flagged by optimistix's own result code."""
    starved = eqx.tree_at(lambda s: s.max_steps, SETUP, 1)
    res = monte_carlo(starved, jax.random.key(3), 4)
    assert not np.any(np.asarray(res.success))
    assert np.all(np.asarray(res.axis_result._value) == optx.RESULTS.nonlinear_max_steps_reached._value)
