"""The independent SciPy reference of the UR5 laser-tracker calibration (benchmarks/_scipy_tracker.py).

Checks it reproduces the published reference on the shipped data: 25
identifiable parameters, test mean error 0.1005 mm (RMS 0.104, max 0.158),
uncalibrated test mean 2.566 mm.
"""

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import _scipy_tracker as ref  # noqa: E402


@pytest.fixture(scope="module")
def calibrated():
    q, y = ref.load_samples(ref.GRID)
    return ref.fit(q, y)


def test_loads_shipped_data():
    q, y = ref.load_samples(ref.GRID)
    qt, yt = ref.load_samples(ref.TEST)
    assert q.shape == (1000, 6) and y.shape == (1000, 3)
    assert qt.shape == (20, 6) and yt.shape == (20, 3)


def test_uncalibrated_error():
    qt, yt = ref.load_samples(ref.TEST)
    assert abs(ref.nominal_errors_mm(qt, yt).mean() - 2.566) < 0.001


def test_identifiable_count(calibrated):
    assert calibrated["n_params"] == 35
    assert calibrated["n_free"] == 25
    names = [n for n, f in zip(ref.param_names(), calibrated["free"]) if not f]
    # the eight exact redundancies and the two wrist-2 parameters the near-axial tool point hides
    assert set(names) == {
        "dd2", "dd4", "dalpha6", "dtheta6", "base_tz", "base_wz", "tool_x", "tool_z", "dtheta5", "dalpha5",
    }  # fmt: skip


def test_calibrated_test_errors(calibrated):
    qt, yt = ref.load_samples(ref.TEST)
    e = ref.test_errors_mm(calibrated, qt, yt)
    assert e.shape == (20,)
    assert abs(e.mean() - 0.1005) < 0.0005
    assert abs(np.sqrt((e**2).mean()) - 0.104) < 0.001
    assert abs(e.max() - 0.158) < 0.001


def test_complex_step_agrees(calibrated):
    q, y = ref.load_samples(ref.GRID)
    qt, yt = ref.load_samples(ref.TEST)
    r = ref.fit(q, y, jac="complex")
    assert r["n_free"] == calibrated["n_free"]
    np.testing.assert_allclose(r["predict"](qt), calibrated["predict"](qt), atol=1e-8)
