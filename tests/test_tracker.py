"""Tracker sweeps (issue 16 item 2): a measuring device's samples calibrated
by the arc and axis fits, with the device pose estimated or the device frame
taken as the base frame (`device_is_base`).

One simulated UR3-class capture per mode (300 samples per joint, 10 um noise,
home [0, 0, -90, 0, 90, 0] deg, 2 % bad samples at the sweep ends) is shared by
the module; both modes and the CLI run the same compiled programs.
"""

import json
import shutil

import jax.numpy as jnp
import numpy as np
import pytest

import jaxcal
from jaxcal._kinematics import joint_axes
from jaxcal.cli import main
from jaxcal.errors import CalibrationError, DatasetError
from jaxcal.fleet import FleetPrior
from jaxcal.io.dataset import load_dataset
from jaxcal.io.model_json import model_from_json
from jaxcal.io.urdf import urdf_outline
from jaxcal.robots import robot_file
from jaxcal.sim.tracker import TrackerSimConfig, bad_samples, simulate_tracker
from jaxcal.stages import CaptureKind

#: The acceptance tolerance on the DH lengths (m).
DH_TOL = 20e-6
#: Consecutive axes closer to parallel than this take the DH convention for parallel axes.
PARALLEL = np.sin(np.radians(1.0))


def dh_lengths(model) -> tuple[np.ndarray, np.ndarray]:
    """The DH lengths of `model`'s joint axes at q = 0 (base frame): `a[i]`, the
    common normal of axes i and i+1, and `d[i]`, the distance along axis i from
    the previous common normal's foot to the next one's (`d[0]` from the base
    origin's projection). Parallel pairs (within 1 deg) take the normal through
    the previous foot, as DH does (their `d` is then 0 by construction)."""
    p, d = (np.asarray(x) for x in joint_axes(model, jnp.zeros(model.num_joints)))
    prev = p[0] - np.dot(p[0], d[0]) * d[0]
    a, lengths, feet_in = [], [], prev
    for i in range(len(p) - 1):
        if np.linalg.norm(np.cross(d[i], d[i + 1])) < PARALLEL:
            fi = feet_in
            fj = p[i + 1] + np.dot(fi - p[i + 1], d[i + 1]) * d[i + 1]
        else:  # the closest points of two skew lines
            w, b = p[i] - p[i + 1], np.dot(d[i], d[i + 1])
            s = (b * np.dot(d[i + 1], w) - np.dot(d[i], w)) / (1 - b * b)
            t = (np.dot(d[i + 1], w) - b * np.dot(d[i], w)) / (1 - b * b)
            fi, fj = p[i] + s * d[i], p[i + 1] + t * d[i + 1]
        a.append(np.linalg.norm(fj - fi))
        lengths.append(np.dot(fi - feet_in, d[i]))
        feet_in = fj
    return np.array(a), np.array(lengths)


def test_dh_lengths_of_the_ur3_table():
    """The helper reads the UR3's published DH lengths off its URDF (|a|, and d with the parallel-axis convention)."""
    a, d = dh_lengths(jaxcal.robots.load_robot("ur3"))
    np.testing.assert_allclose(a, [0.0, 0.24365, 0.21325, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(d, [0.1519, 0.0, 0.0, 0.11235, 0.08535], atol=1e-12)


@pytest.fixture(scope="module")
def captures(tmp_path_factory):
    """`{device_is_base: (dataset path, result)}`: one simulated capture per mode, calibrated."""
    out = {}
    for base in (False, True):
        root = simulate_tracker(
            TrackerSimConfig(device_is_base=base, seed=3), tmp_path_factory.mktemp("tracker") / "ds"
        )
        out[base] = (root, jaxcal.calibrate(root, progress=False, validate=False, device_is_base=base))
    return out


def _dh_errors(root, result):
    true = model_from_json(load_dataset(root).truth["model"])
    (a_t, d_t), (a_e, d_e), (a_n, d_n) = (dh_lengths(m) for m in (true, result.model, result.nominal))
    return a_e - a_t, d_e - d_t, a_n - a_t, d_n - d_t


@pytest.mark.parametrize("base", [False, True], ids=["device-pose", "device-is-base"])
def test_acceptance_dh_lengths(captures, base):
    """DH lengths within 0.02 mm of the truth (the nominal UR3 is off by up to 1.5 mm); d1 too with
    `device_is_base`. Without it d1 is held: the device pose absorbs the base height."""
    root, result = captures[base]
    assert result.status == "ok", result.reasons
    ea, ed, na, nd = _dh_errors(root, result)
    checked = slice(0, None) if base else slice(1, None)
    assert np.abs(ea).max() < DH_TOL, ea
    assert np.abs(ed[checked]).max() < DH_TOL, ed
    assert np.abs(np.r_[na, nd[checked]]).max() > 50 * DH_TOL  # the calibration had work to do
    frozen = set(result.frozen)
    if base:
        np.testing.assert_array_equal(result.T_cam_base, np.eye(4))
        assert {f"T_device_base.{p}" for p in ("tx", "ty", "tz", "rx", "ry", "rz")} <= frozen
        assert "shoulder_pan_joint.origin.tz" not in frozen  # the base height is seen
    else:
        assert not any(n.startswith("T_device_base") for n in frozen)
        assert "shoulder_pan_joint.origin.tz" in frozen
        assert abs(ed[0]) > 10 * DH_TOL  # ... and not seen without device_is_base


@pytest.mark.parametrize("base", [False, True], ids=["device-pose", "device-is-base"])
def test_bad_samples_are_flagged_by_sample_and_time(captures, base):
    root, result = captures[base]
    ds = load_dataset(root)
    payload = json.loads(json.dumps(result.to_json()))  # what result.json holds
    flagged = [o for a in payload["arcs"] for o in a["outliers"]]
    bad = ds.truth["bad_samples"]
    assert len(bad) == 36  # 2 % of 300 samples in each of 6 sweeps
    assert sorted(o["sample"] for o in flagged) == bad
    for o in flagged:
        k = int(np.flatnonzero(ds.samples.sample == o["sample"])[0])
        assert o["timestamp_s"] == pytest.approx(ds.samples.timestamp[k])
        assert o["line"] == f"samples.csv line {k + 2}"
    assert payload["setup"] == "device" and payload["device"] == "tracker"
    assert payload["device_is_base"] is base
    assert "T_device_base" in payload and "T_cam_base" not in payload
    assert np.asarray(payload["T_flange_point"]).shape == (4, 4)
    assert payload["refinement"] is None and payload["frames"]["samples"] == 1800


def test_the_bad_samples_sit_at_the_sweep_ends():
    idx = bad_samples(TrackerSimConfig(), 6)
    assert idx.tolist()[:6] == [0, 1, 2, 297, 298, 299] and len(idx) == 36


def test_capture_kind():
    kind = CaptureKind.of(
        camera_on_flange=False,
        segments=(),
        encoders=True,
        link_targets=False,
        device=True,
        device_is_base=True,
    )
    assert kind.fixed_frame == "T_device_base" and not kind.fixed_frame_free
    assert kind.has_arcs and kind.axis_fit_uses_poses and not kind.refines_corners and not kind.images
    assert kind.label == "device"
    camera = CaptureKind.of(camera_on_flange=False, segments=(), encoders=True, link_targets=False)
    assert camera.fixed_frame_free and camera.refines_corners and camera.fixed_frame == "T_cam_base"


def test_device_is_base_on_a_camera_dataset_is_refused():
    with pytest.raises(CalibrationError, match="device_is_base applies to tracker data"):
        jaxcal.calibrate("data/ur5e_sweeps", device_is_base=True, progress=False)
    with pytest.raises(
        CalibrationError, match=r"ur5e_sweeps: a fleet's prior \(--prior\) applies to measured"
    ):
        jaxcal.calibrate("data/ur5e_sweeps", prior=FleetPrior(5, (), "", (), np.zeros(0), np.zeros((0, 0))))
    with pytest.raises(TypeError, match="prior: a fleet.json path or a jaxcal.fleet.FleetPrior, got dict"):
        jaxcal.calibrate("data/ur5e_sweeps", prior={})


def test_simulate_tracker_draws_stop_and_shoot_poses_from_the_command_line(tmp_path, capsys):
    ds = tmp_path / "ds"
    assert main(["simulate-tracker", "--out", str(ds), "--robot", "ur5e", "--config", "random-poses=30"]) == 0
    assert "30 tracker samples of 30 stop-and-shoot poses" in capsys.readouterr().out
    q = load_dataset(ds).samples.q
    assert q.shape == (30, 6) and np.all(np.ptp(q, axis=0) > np.radians(20))  # every joint moves


def test_cli_end_to_end(captures, tmp_path):
    """`jaxcal simulate-tracker` and `jaxcal calibrate --device-is-base` (no truth.json: no validation)."""
    ds = tmp_path / "ds"
    assert main(["simulate-tracker", "--out", str(ds), "--seed", "5", "--device-is-base"]) == 0
    data = tmp_path / "data"
    shutil.copytree(ds, data)
    (data / "truth.json").unlink()
    out = tmp_path / "out"
    assert main(["calibrate", str(data), "--out", str(out), "--device-is-base", "--quiet"]) == 0
    r = json.loads((out / "result.json").read_text())
    assert r["status"] == "ok" and r["device_is_base"] is True and r["validation"] is None
    assert r["T_device_base"]["matrix"] == np.eye(4).tolist()
    assert {o["sample"] for a in r["arcs"] for o in a["outliers"]} == set(
        bad_samples(TrackerSimConfig(), 6).tolist()
    )
    assert {"calibrated.urdf", "ur_calibration.yaml", "report.md"} <= {p.name for p in out.iterdir()}
    assert not list(out.glob("camera_*.yaml")) and not list(out.glob("ros_*"))  # no device pose to publish
    assert "Device pose" in (out / "report.md").read_text()


# --------------------------------------------------------------------------- load errors


@pytest.fixture
def small(captures, tmp_path):
    """A copy of the shared capture with a 4-sample table (edited by each test)."""
    root = tmp_path / "ds"
    shutil.copytree(captures[False][0], root)
    (root / "truth.json").unlink()
    lines = (root / "samples.csv").read_text().splitlines()
    (root / "samples.csv").write_text("\n".join(lines[:5]) + "\n")
    return root


def _edit(root, line: int, column: str, value: str) -> None:
    path = root / "samples.csv"
    rows = [r.split(",") for r in path.read_text().splitlines()]
    rows[line - 1][rows[0].index(column)] = value
    path.write_text("\n".join(",".join(r) for r in rows) + "\n")


def _meta(root, edit) -> None:
    meta = json.loads((root / "metadata.json").read_text())
    edit(meta)
    (root / "metadata.json").write_text(json.dumps(meta))


@pytest.mark.parametrize(
    "change, words",
    [
        (
            lambda r: _edit(r, 1, "x", "X"),
            ["samples.csv line 1", "header must start with sample,timestamp,joint,x,y,z"],
        ),
        (lambda r: _edit(r, 1, "elbow_joint", "elbo"), ["samples.csv line 1", "unknown column", "elbo"]),
        (  # a spreadsheet's export with semicolons
            lambda r: (r / "samples.csv").write_text((r / "samples.csv").read_text().replace(",", ";")),
            ["samples.csv line 1", "the file is separated by ';': write it comma-separated"],
        ),
        (
            lambda r: _edit(r, 3, "joint", "wrist_9"),
            ["samples.csv line 3 column 'joint'", "unknown joint 'wrist_9'"],
        ),
        (lambda r: _edit(r, 4, "y", "nan"), ["samples.csv line 4 column 'y'", "NaN"]),
        (lambda r: _edit(r, 4, "z", "1.5e3"), ["samples.csv line 4", "more than 100 m", "metres"]),
        (
            lambda r: _edit(r, 3, "sample", "0"),
            ["samples.csv line 3", "sample indices must increase strictly"],
        ),
        (
            lambda r: _edit(r, 5, "timestamp", "0"),
            [
                "samples.csv line 5",
                "timestamp 0.0 is not after line 4's",
                "timestamps must increase strictly",
            ],
        ),
        (lambda r: _edit(r, 2, "sample", "-1"), ["samples.csv line 2 column 'sample'", "'-1'"]),
        (
            lambda r: _edit(r, 2, "elbow_joint", "60"),
            [  # one cell in degrees among radians: named by line, not as the column's unit
                "samples.csv column 'elbow_joint'",
                "joint positions",
                "line 2: 60 (a commanded joint position of 60 rad) lies outside the robot file's limits",
                "1 row(s) (line 2) hold a wrong value; read as degrees it lies within them: that row in degrees",
            ],
        ),
        (
            lambda r: _meta(r, lambda m: m["device"].pop("sigma_m")),
            ["samples.csv: no noise given", "'sigma_m' column", "metadata.json: device.sigma_m"],
        ),
        (
            lambda r: _meta(r, lambda m: m["device"].update(link="tool0")),
            ["metadata.json: device.link", "'tool0'"],
        ),
        (lambda r: _meta(r, lambda m: m.update(cameras=[])), ["metadata.json", "unknown field 'cameras'"]),
        (lambda r: _meta(r, lambda m: m["device"].update(sigma_m=-1)), ["device.sigma_m", "greater than 0"]),
        (  # the point's mount in millimetres
            lambda r: _meta(
                r,
                lambda m: m["device"].update(
                    T_link_point_nominal=[[1, 0, 0, 80], [0, 1, 0, 0], [0, 0, 1, 60], [0, 0, 0, 1]]
                ),
            ),
            ["device.T_link_point_nominal", "the point lies 100 m from link 'flange'", "millimetres written"],
        ),
        (lambda r: (r / "samples.csv").unlink(), ["samples.csv: samples table", "missing"]),
    ],
)
def test_load_errors_name_the_file_line_and_column(small, change, words):
    load_dataset(small)  # the unedited copy loads
    change(small)
    with pytest.raises(DatasetError) as e:
        load_dataset(small)
    for w in words:
        assert w in str(e.value), str(e.value)


def test_orientation_columns(small):
    """A 6-DoF probe's quaternions are read (normalised) and a non-unit one is named."""
    path = small / "samples.csv"
    rows = [r.split(",") for r in path.read_text().splitlines()]
    rows = [
        r[:6] + q + r[6:] for r, q in zip(rows, [["qx", "qy", "qz", "qw"]] + [["0", "0", "0.6", "0.8"]] * 4)
    ]
    path.write_text("\n".join(",".join(r) for r in rows) + "\n")
    _meta(small, lambda m: m["device"].update(sigma_rad=1e-4))
    s = load_dataset(small).samples
    c, si = 0.8**2 - 0.6**2, 2 * 0.6 * 0.8
    np.testing.assert_allclose(s.orientation[0], [[c, -si, 0], [si, c, 0], [0, 0, 1]], atol=1e-12)
    assert s.covariances().shape == (4, 6, 6) and s.covariances()[0, 4, 4] == pytest.approx(1e-8)
    _edit(small, 3, "qw", "0.9")
    with pytest.raises(DatasetError, match="samples.csv line 3: quaternion .* norm"):
        load_dataset(small)


def test_inspect_describes_a_tracker_dataset(captures, capsys):
    """`jaxcal inspect` on tracker data: the device, and per joint its samples and the range swept."""
    root = captures[False][0]
    assert main(["inspect", str(root)]) == 0
    text = capsys.readouterr().out
    assert "samples in samples.csv" in text and "external measuring device" in text
    assert main(["inspect", str(root), "--json", "-"]) == 0
    s = json.loads(capsys.readouterr().out)
    counts = [g["samples"] for g in s["joints"]]
    assert counts == [300] * 6 and s["device"]["samples"] == 1800 and s["unassigned_samples"] == 0
    for g in s["joints"]:
        lo, hi = g["range_deg"]
        assert 110.0 < hi - lo < 130.0  # the simulator's +-60 deg sweeps


def test_the_default_home_suits_an_arm_of_another_number_of_joints(tmp_path):
    """The default home is a UR's six angles; a 7-joint Panda sweeps about the middle of its joints'
    limits (its joint 4 has no zero within them), every sample within them."""
    ds = load_dataset(simulate_tracker(TrackerSimConfig(robot="panda", samples_per_joint=10), tmp_path / "p"))
    names = list(ds.joint_names)
    lim = urdf_outline(robot_file("panda"), names).limits
    mid = np.array([(lim[n].lower + lim[n].upper) / 2 for n in names])
    q = ds.samples.q
    assert q.shape == (70, 7)
    held = np.ones_like(q, bool)
    held[np.arange(70), np.repeat(np.arange(7), 10)] = False  # each sweep's own joint moves
    np.testing.assert_allclose(q[held], np.broadcast_to(mid, q.shape)[held], atol=1e-9)
    assert all(lim[n].lower <= q[:, j].min() and q[:, j].max() <= lim[n].upper for j, n in enumerate(names))
