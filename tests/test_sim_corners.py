"""Analytic corners of a simulated capture (`jaxcal.sim.corners`) and the observe stage on given
detections: the truth's corners where the renderer put them, a rolling shutter's rows at their own
times, and the stages run on corners instead of images."""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from jaxcal import stages
from jaxcal.errors import CalibrationError
from jaxcal.io.dataset import load_dataset
from jaxcal.sim.arm import ArmModel
from jaxcal.sim.corners import analytic_detections, capture_truth
from jaxcal.vision import detect_frames

DESIGN = Path(__file__).resolve().parents[1] / "data" / "ur5e_sweeps"
#: 20 ms top-to-bottom over the design's 600 rows.
DELAY_S = 0.02 / 600


@pytest.fixture(scope="module")
def design():
    ds = load_dataset(DESIGN)
    return ds, capture_truth(ds)


def test_the_corners_are_the_truths_projection(design):
    """At the frames' times the corners are the truth's target poses (`truth.json`) projected:
    the motion, arm and mounts rebuilt exactly."""
    ds, truth = design
    rows, t = truth.frames["cam0"]
    T = truth.target_poses("cam0", "plate0", t)
    recorded = np.array(
        [f["T_cam_target"]["plate0"] for f in sorted(ds.truth["frames"], key=lambda f: f["row"])]
    )
    np.testing.assert_allclose(T, recorded, atol=1e-12)
    dets = analytic_detections(truth, "cam0")
    seen = [
        i for i, f in enumerate(sorted(ds.truth["frames"], key=lambda f: f["row"])) if f["visible"]["plate0"]
    ]
    assert [i for i, d in enumerate(dets) if d] == seen
    d = dets[seen[0]]["plate0"]
    points = ds.targets[0].spec.points()[d.ids]
    P = points @ T[seen[0], :3, :3].T + T[seen[0], :3, 3]
    u = (ds.cameras[0].K @ (P / P[:, 2:]).T).T[:, :2]
    np.testing.assert_allclose(d.pixels, u, atol=1e-9)


def test_rolling_shutter_rows_are_their_own_times(design):
    """Each corner is where the truth puts it at its own row's time: the fixed point
    $y = v(t + y\\,\\ell)$, reached to well under a nanopixel; it moves by the image's speed times
    its row's delay."""
    _, truth = design
    rows, t = truth.frames["cam0"]
    frame = np.repeat(np.arange(len(rows)), 12)
    ids = np.tile(np.arange(12), len(rows))
    u = truth.corners("cam0", "plate0", t[frame], ids, DELAY_S)
    again = truth.project("cam0", "plate0", t[frame] + u[:, 1] * DELAY_S, ids)
    np.testing.assert_allclose(again, u, atol=1e-8)
    g = truth.corners("cam0", "plate0", t[frame], ids)
    # The shift is the image's speed (at the middle of the row's delay) times the delay: to
    # 0.02 px but where the sweeps' acceleration jumps (their waypoints) within a row's delay.
    dt, mid = 1e-5, t[frame] + 0.5 * u[:, 1] * DELAY_S
    speed = (
        truth.project("cam0", "plate0", mid + dt, ids) - truth.project("cam0", "plate0", mid - dt, ids)
    ) / (2 * dt)
    err = np.abs(u - g - speed * (u[:, 1:] * DELAY_S))
    assert np.percentile(err, 95) < 0.02 and err.max() < 0.3, (np.percentile(err, 95), err.max())
    assert np.max(np.abs(u - g)) > 5.0  # pixels: the skew the estimator has to model


def test_the_detector_finds_the_analytic_corners(design):
    """On the design's own images the detector's corners lie within its noise of the analytic
    ones (RMS about 0.054 px per axis, no shift): the renderer and the truth agree."""
    ds, truth = design
    rows, _ = truth.frames["cam0"]
    like = detect_frames(
        [ds.image_path(int(r)) for r in rows], [ds.targets[0].spec], K=ds.cameras[0].K, progress=False
    )
    dets = analytic_detections(truth, "cam0", like=like)
    e = np.concatenate([a["plate0"].pixels - d["plate0"].pixels for a, d in zip(like, dets) if "plate0" in a])
    assert len(e) > 1000
    rms = np.sqrt(np.mean(e**2, axis=0))
    assert np.all(rms < 0.07) and np.all(np.abs(e.mean(axis=0)) < 0.01), (rms, e.mean(axis=0))
    noisy = analytic_detections(truth, "cam0", like=like, noise_px=0.05, rng=np.random.default_rng(0))
    n = np.concatenate(
        [a["plate0"].pixels - d["plate0"].pixels for a, d in zip(noisy, dets) if "plate0" in a]
    )
    np.testing.assert_allclose(np.std(n, axis=0), 0.05, rtol=0.05)


def test_observe_takes_given_detections(design):
    """`stages.observe(..., detections=)` on the images' own detections gives the poses and
    times observing the images does; corners of an unknown target, or of too few frames, are refused."""
    ds, truth = design
    opt = stages.Options(progress=False)
    setup = stages.setup(DESIGN, opt)
    images = stages.observe(setup, opt)
    given = stages.observe(setup, opt, {"cam0": images.primary.detections})
    for a, b in zip(images.primary.poses, given.primary.poses):
        assert a.keys() == b.keys()
        for k in a:
            np.testing.assert_array_equal(a[k].T_cam_target, b[k].T_cam_target)
    np.testing.assert_array_equal(images.primary.t_cam, given.primary.t_cam)
    with pytest.raises(CalibrationError, match="frames"):
        stages.observe(setup, opt, {"cam0": images.primary.detections[:-1]})
    with pytest.raises(CalibrationError, match="unknown targets"):
        stages.observe(setup, opt, {"cam0": [{"board9": d} for d in images.primary.detections]})


def test_a_compliant_arm_on_a_rigid_design(design):
    """`capture_truth(..., arm=)`: the joints stand where that arm puts them (the shoulder sags by
    its compliance times a gravity torque of tens of N m)."""
    ds, rigid = design
    bent = capture_truth(ds, arm=ArmModel(name="sag", compliance=0.05))
    _, t = rigid.frames["cam0"]
    d = bent.angles_at(t) - rigid.angles_at(t)
    assert 0.05 * 0.01 < np.max(np.abs(d[:, 1])) < 0.05 * 0.2  # rad: 0.05 rad/kN m x 10..200 N m


def test_only_the_sweeps_are_rebuilt(tmp_path):
    """A capture whose recorded motion the simulation's record does not rebuild is refused."""
    out = tmp_path / "ds"
    shutil.copytree(DESIGN, out)
    meta = json.loads((out / "metadata.json").read_text())
    meta["simulation"]["range_deg"] = 60.0
    (out / "metadata.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="do not reproduce"):
        capture_truth(out)
