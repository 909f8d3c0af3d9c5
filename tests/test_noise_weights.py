"""The smear and timing pieces of `benchmarks/noise_weights.py` on an analytic moving point.

The benchmark measures the detector's per-view corner errors against the smear
(exposure times image speed) on the realism renders; these tests check what it
rests on without rendering: the simulator's exposure smears a point moving at a
constant image velocity over exactly speed times exposure, centred on the
exposure's middle (`jaxcal.sim.camera.CameraModel.schedule`); `fit_timing`
recovers the lag and line delay that move the truth at the stamp onto such a
point; `sharpness` reads an edge's width.
"""

import sys
from pathlib import Path

import numpy as np
import pytest

from jaxcal.sim.camera import CameraModel

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import noise_weights  # noqa: E402

#: A corner's image velocity during a fast sweep (px/s) and where it is at t = 0 (px).
VELOCITY = np.array([250.0, -140.0])
START = np.array([400.0, 300.0])


@pytest.mark.parametrize("stamp", ["start", "middle", "end"])
def test_a_moving_point_smears_over_speed_times_exposure_around_the_exposure_middle(stamp):
    camera = CameraModel(name="e", exposure_s=0.005, subframes=4, stamp=stamp)
    times, weights = camera.schedule(t_stamp=1.0, height=600)
    # Each instant stands for an equal slice of the exposure: the slices cover [min - E/2n, max + E/2n].
    slice_s = camera.exposure_s / camera.subframes
    extent_s = times.max() - times.min() + slice_s
    speed = np.linalg.norm(VELOCITY)
    np.testing.assert_allclose(speed * extent_s, speed * camera.exposure_s, rtol=1e-12)
    # The blurred point's centroid: the mean position over the exposure, at its middle.
    centroid = weights[0] @ (START + VELOCITY * times[:, None])
    middle = 1.0 + camera.exposure_start() + 0.5 * camera.exposure_s
    np.testing.assert_allclose(centroid, START + VELOCITY * middle, rtol=0, atol=1e-9)


def test_fit_timing_recovers_the_lag_and_line_delay_of_analytic_corners():
    # A rolling shutter stamped at the first row's exposure start: corner at row y is seen, on
    # average, E/2 + y * line_delay after the stamp. Rows are interpolated linearly between
    # renders, exact for a point moving at a constant velocity, so the errors are exactly the
    # velocity times that lag (to rounding: ~1e-13 px on ~10 px errors).
    camera = CameraModel(name="r", exposure_s=0.004, subframes=4, stamp="start", readout_s=0.02, step_s=1e-3)
    height, t_stamp = 600, 2.0
    times, weights = camera.schedule(t_stamp, height)
    rng = np.random.default_rng(0)
    rows = rng.integers(0, height, 40)
    velocities = rng.normal(0.0, 200.0, (40, 2))
    seen = np.stack([weights[r] @ (START + v * times[:, None]) for r, v in zip(rows, velocities)])
    truth = START + velocities * t_stamp
    pixels = np.c_[seen[:, 0], rows.astype(float)]
    lag, delay = noise_weights.fit_timing(seen - truth, velocities, pixels)
    np.testing.assert_allclose(lag, 0.5 * camera.exposure_s, rtol=1e-9)
    np.testing.assert_allclose(delay, camera.line_delay(height), rtol=1e-9)


def test_sharpness_is_one_over_an_edges_width():
    # Sobel over 8 is the central difference: a step gives half its contrast per px at the two
    # pixels beside it (0.5), a linear ramp over L px its contrast over L (1/L).
    step = np.zeros((40, 40))
    step[:, 20:] = 200.0
    ramp = np.clip((np.arange(40.0) - 18.0) / 4.0, 0.0, 1.0)[None, :] * np.ones((40, 1)) * 200.0
    corners = np.array([[20.0, 20.0], [19.0, 10.0]])
    np.testing.assert_allclose(noise_weights.sharpness(step, corners), 0.5, rtol=1e-12)
    np.testing.assert_allclose(noise_weights.sharpness(ramp, corners), 0.25, rtol=1e-12)


def test_std_gain_of_per_view_weights():
    # Two views of one corner each, variances 1 and 4 px^2 per axis: the mean's variance is
    # (1 + 4) / 4 = 1.25 unweighted and 1 / (1 + 1/4) = 0.8 with inverse-variance weights.
    rows = [{"corners": 1, "rms_px": np.sqrt(2.0)}, {"corners": 1, "rms_px": np.sqrt(8.0)}]
    assert noise_weights.std_gain(rows, np.array([1.0, 2.0])) == pytest.approx(np.sqrt(1.25 / 0.8), rel=1e-12)
    assert noise_weights.std_gain(rows, np.ones(2)) == 1.0  # one sigma for all: the unweighted mean


def test_the_smear_model_is_fitted_over_the_blurred_cases():
    """s_v^2 = s_0^2 + (b smear_v)^2 per axis: `b` shared, `s_0` per case with a smear; the sharp
    case and the renderer's artefact (`ARTEFACTS`) left out, and no fit without a smear (the
    suite's run of the benchmark has the ideal case alone)."""
    b, s0 = 0.03, {"exposure_10ms": 0.05, "camera_mix": 0.08}

    def rows(s, smears):
        return [{"smear_px": m, "rms_px": float(np.sqrt(2.0 * (s**2 + (b * m) ** 2)))} for m in smears]

    cases = {name: rows(s, np.linspace(0.5, 4.0, 8)) for name, s in s0.items()}
    cases["ideal"] = rows(0.04, np.zeros(8))
    cases["rolling_shutter"] = rows(0.5, np.linspace(0.5, 4.0, 8))
    out = noise_weights.fit(cases)
    assert out["b"] == pytest.approx(b, rel=1e-9) and out["b2"] == pytest.approx(b**2, rel=1e-9)
    assert out["s0_px"] == pytest.approx(s0, rel=1e-9)
    assert noise_weights.fit({"ideal": cases["ideal"]}) == {}
