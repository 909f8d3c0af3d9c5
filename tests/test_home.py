"""Sweeps from a home configuration other than zero, rendered end to end.

Each joint sweeps with the others held at the home, which the stages read
from the encoder log (or, without one, from the metadata's `home`): the axis
fit predicts every axis and marker pose at its sweep's home, the refinement
takes every view at its own configuration.
"""

import json

import numpy as np
import pytest

from jaxcal.pipeline import calibrate
from jaxcal.sim.faults import shear_copy
from jaxcal.sim.simulate import SimConfig, simulate

pytestmark = pytest.mark.slow

HOME_DEG = (0.0, -20.0, 30.0, -15.0, 20.0, 0.0)
CONFIG = SimConfig(
    robot="ur5e", seed=5, resolution=(640, 480), frames_per_joint=12, range_deg=60.0, home_deg=HOME_DEG
)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return simulate(CONFIG, tmp_path_factory.mktemp("home") / "ur5e", progress=False)


def test_sweeps_from_a_home_configuration(dataset):
    meta = json.loads((dataset / "metadata.json").read_text())
    assert meta["motion"][1]["home"][2] == pytest.approx(np.radians(30.0))
    r = calibrate(dataset, progress=False, workers=1)
    v = r.validation
    assert r.status == "ok", r.reasons
    assert any("home configuration other than zero" in w for w in r.warnings)
    assert all(0.3 < a["residual_rms"] < 2.0 for a in r.arcs)
    assert r.axis_fit.residual_rms < 3.0  # the axes fit the model at their homes (about 2 here)
    assert v["ee_rms_mm_before"] > 4.0 and v["ee_rms_mm_after"] < 0.5 * v["ee_rms_mm_before"]
    assert v["T_cam_base_error"]["trans_mm"] < 2.0


def test_without_encoders_the_metadata_gives_the_home(dataset, tmp_path):
    """Also the robust arc fit without encoders (angles eliminated by blocks): one
    image sheared mid-sweep is rejected and named, the answer stays right."""
    ds = tmp_path / "copy"
    frames = (dataset / "frames.csv").read_text().splitlines()[1:]
    row = 2 * CONFIG.frames_per_joint + CONFIG.frames_per_joint // 2  # joint 3, mid-sweep
    (sheared,) = shear_copy(dataset, ds, rows=[row], shear=0.08)
    frame = int(frames[row].split(",")[1])
    (ds / "encoders.csv").unlink()
    meta = json.loads((ds / "metadata.json").read_text())
    meta["encoders"] = None
    (ds / "metadata.json").write_text(json.dumps(meta))
    r = calibrate(ds, progress=False, workers=1)
    v = r.validation
    assert r.axis_fit.residual_rms < 3.0
    assert v["ee_rms_mm_after"] < 0.5 * v["ee_rms_mm_before"]
    rejected = {o["frame"] for o in r.arcs[2]["outliers"]}
    assert frame in rejected, (sheared, r.arcs[2]["outliers"])
    assert sum(len(a["outliers"]) for a in r.arcs) <= 3  # the sheared frame, at most a couple of others
    assert any("rejected" in w and str(frame) in w for w in r.warnings)
