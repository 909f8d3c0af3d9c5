"""Images -> calibrated robot: `jaxcal.calibrate`, `jaxcal calibrate`, `jaxcal demo`, and bad input.

One small rendered UR5e dataset (640x480, 12 frames per 60-degree sweep, a
40 ms clock offset left out of the metadata) is shared by every test; it has
the demo's configuration at a lower resolution, so the demo test reuses the
compiled solvers. The demo test films the arm with two cameras (the
refinement's several-camera path).
"""

import csv
import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
import threading
from pathlib import Path
from types import SimpleNamespace

import jax
import numpy as np
import optimistix as optx
import pytest
from conftest import CACHE_DIR
from helpers import ur5e_setup
from jax._src import dispatch, monitoring

import jaxcal
from jaxcal._montecarlo import trial_sweeps
from jaxcal.cli import main
from jaxcal.io._metadata import read_cameras
from jaxcal.io._schema import Loc
from jaxcal.io.dataset import DatasetError, load_dataset
from jaxcal.io.result import COVARIANCE_MODELS, covariance_model, read_result
from jaxcal.io.ros import read_easy_handeye, read_static_transform
from jaxcal.pipeline import CalibrationError, calibrate
from jaxcal.records import plain
from jaxcal.report import write_outputs
from jaxcal.sim.simulate import SimConfig, simulate
from jaxcal.stages import _programs
from jaxcal.stages.limits import Limits

CONFIG = SimConfig(
    robot="ur5e",
    seed=0,
    resolution=(640, 480),
    frames_per_joint=12,
    range_deg=60.0,
    clock_offset_ms=40.0,
    clock_known=False,
)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    return simulate(CONFIG, tmp_path_factory.mktemp("ds") / "ur5e", progress=False)


@pytest.fixture(scope="module")
def result(dataset):
    return calibrate(dataset, progress=False, workers=1)


def _digest(root: Path) -> str:
    h = hashlib.sha256()
    for p in sorted(root.rglob("*")):
        if p.is_file():
            h.update(str(p.relative_to(root)).encode())
            h.update(p.read_bytes())
    return h.hexdigest()


def _copy(dataset: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "copy"
    shutil.copytree(dataset, dst)
    return dst


def _edit_json(path: Path, edit) -> None:
    meta = json.loads(path.read_text())
    edit(meta)
    path.write_text(json.dumps(meta))


# --------------------------------------------------------------------------- recovery


@pytest.mark.slow
def test_calibration_recovers_the_rendered_arm(result):
    v = result.validation
    assert result.ok
    # 640x480 and 12 frames a 60-degree sweep (the board is ~150 px wide, PnP
    # depth noise ~1 mm): a looser bound than the 1280x960 acceptance run
    # (0.30 mm, 40 frames a 80-degree sweep), still well below the nominal model.
    assert v["ee_rms_mm_before"] > 4.0
    assert v["ee_rms_mm_after"] < 4.0
    assert v["ee_rms_mm_after"] < 0.5 * v["ee_rms_mm_before"]
    assert v["T_cam_base_error"]["trans_mm"] < 1.5 and v["T_cam_base_error"]["rot_deg"] < 0.4
    ratio = [abs(e["ratio_percent"]) for e in v["parameter_errors"].values()]
    assert max(ratio) < 0.3  # the ratios were perturbed by ~1 %
    # The clock offset was not in the metadata: estimated through the arc fits.
    assert result.clock["estimated"]
    assert abs(v["clock_offset_error_ms"]) < 1.0
    assert result.clock["std_s"] < 1e-3
    # Whitened arc residuals near 1: the PnP covariances are honest.
    assert all(0.3 < a["residual_rms"] < 2.0 for a in result.arcs)
    assert "shoulder_pan_joint.zero_offset" in result.frozen  # unobservable, held at nominal
    # The reprojection refinement runs by default, starts from the two-stage fit and improves on it.
    ref = result.refinement
    assert v["refined"] and ref["solver"]["result"] == "successful"
    assert v["ee_rms_mm_after"] <= v["ee_rms_mm_two_stage"]
    assert ref["inlier_rms_px"] < 0.5 and ref["outlier_frames"] == []
    assert ref["frozen_beyond_two_stage"] == []  # the same gauge as the axis fit
    # The zero offsets against the truth as the estimator sees it (its gauge): within their std
    # (the raw differences were 7-13 standard deviations: the origins' twists the truth perturbs).
    std = {r.name: r.std for r in result.parameters}
    for e in v.parameter_errors:
        sd = std.get(f"{e.joint}.zero_offset")
        if sd:
            assert abs(np.radians(e.zero_offset_deg)) < 5 * sd, (e, sd)


@pytest.mark.slow
def test_outputs_are_complete_and_consistent(result, tmp_path):
    import cv2
    import jax

    from jaxcal import dh_table_model, forward_kinematics, physical_table, read_dh_table
    from jaxcal._dh import table_values
    from jaxcal.io.robot_files import is_ur
    from jaxcal.io.urdf import load_urdf

    out = write_outputs(result, tmp_path / "res")
    names = sorted(p.name for p in out.iterdir())
    assert names == sorted(
        [
            ".jaxcal",
            "result.json",
            "estimate.npz",
            "calibrated.urdf",
            "camera_cam0.yaml",
            "ros_cam0.launch.yaml",
            "ros_cam0.txt",
            "easy_handeye_cam0.yaml",
            "report.md",
            "arcs.png",
            "residuals.png",
            "ee_error.png",
            "calibrated_dh.json",
            "calibrated_mdh.json",
        ]
        + (["ur_calibration.yaml"] if is_ur(result.model) else [])
    )
    r = json.loads((out / "result.json").read_text())
    for key in ("T_cam_base", "parameters", "reduction_ratios", "identifiability", "arcs", "frames", "clock",
                "timings_s", "solver", "validation", "refinement"):  # fmt: skip
        assert key in r
    assert r["validation"]["ee_rms_mm_after"] == pytest.approx(result.validation["ee_rms_mm_after"])
    assert r["covariance_model"] == "view_robust"  # the refinement's (jaxcal.io.result.COVARIANCE_MODELS)
    assert np.allclose(r["T_cam_base"]["matrix"], result.T_cam_base)
    # Every parameter has nominal, estimate, std; frozen ones did not move.
    for p in r["parameters"]:
        assert {"name", "unit", "nominal", "estimate", "std", "free"} <= set(p)
        if not p["free"]:
            assert p["estimate"] == pytest.approx(p["nominal"], abs=1e-12) and p["std"] == pytest.approx(
                0, abs=1e-12
            )
    # The calibrated URDF round-trips to the calibrated model.
    urdf = load_urdf(out / "calibrated.urdf")
    q = np.random.default_rng(0).uniform(-3, 3, (5, 6))
    for qi in q:
        a = np.asarray(jax.device_get(forward_kinematics(urdf, qi)))
        b = np.asarray(jax.device_get(forward_kinematics(result.model, qi)))
        assert np.allclose(a, b, atol=1e-9)
    assert np.allclose(urdf.reduction_ratio, result.model.reduction_ratio, rtol=1e-12)
    fs = cv2.FileStorage(str(out / "camera_cam0.yaml"), cv2.FILE_STORAGE_READ)
    assert np.allclose(fs.getNode("T_cam_base").mat(), result.T_cam_base)
    assert np.allclose(fs.getNode("T_cam_base_std").mat().ravel(), result.std_cam)
    fs.release()
    assert r["other_cameras"] == [] and result.other_cameras == ()
    # The file reads back as the result's typed records (`jaxcal.io.result.read_result`).
    back = read_result(out / "result.json")
    for name in ("clock", "frames", "intrinsics", "solver", "refinement", "validation", "arcs", "parameters"):
        assert plain(getattr(back, name)) == plain(getattr(result, name)), name
    assert plain(back.ratios) == plain(result.ratios) and back.frozen == result.frozen
    # The camera in the base link for ROS: parsed back, the calibrated pose (issue 16 item 7).
    T_base_cam = np.linalg.inv(np.asarray(result.T_cam_base))
    for f in ("ros_cam0.launch.yaml", "ros_cam0.txt"):
        T, parent, child = read_static_transform(out / f)
        np.testing.assert_allclose(T, T_base_cam, atol=1e-9)
        assert (parent, child) == (result.model.link_names[0], "cam0")
    easy = read_easy_handeye(out / "easy_handeye_cam0.yaml")
    np.testing.assert_allclose(easy["T"], T_base_cam, atol=1e-9)
    assert not easy["eye_on_hand"] and easy["tracking_marker_frame"] == result.targets[0]
    report = (out / "report.md").read_text()
    assert "EE RMS" in report and "![" in report
    # The DH / MDH tables parse back to the result's tables and to its model (issue 16 items 6, 7d).
    assert "## DH table" in report and "parallel" in report
    for convention in ("dh", "mdh"):
        table = physical_table(result, convention)
        read, doc = read_dh_table(out / f"calibrated_{convention}.json")
        np.testing.assert_allclose(table_values(read), table.estimate, atol=1e-9)
        np.testing.assert_allclose(doc["std"]["d"], table.std_table.d, atol=1e-12)
        model = dh_table_model(out / f"calibrated_{convention}.json")
        for qi in q:
            a = np.asarray(forward_kinematics(model, qi)[-1])
            np.testing.assert_allclose(a, np.asarray(forward_kinematics(result.model, qi)[-1]), atol=1e-9)
        np.testing.assert_allclose(model.reduction_ratio, result.model.reduction_ratio, rtol=1e-12)


@pytest.mark.slow
def test_covariance_model_names_the_covariance_a_result_carries():
    """`result.json`'s `covariance_model`: the refinement's view-robust covariance when it ran (the
    kernel sandwich's where its residuals' errors repeat), else a tracker point fit's model
    covariance, else the two-stage fit's."""
    refined = SimpleNamespace(refinement=SimpleNamespace(error_correlation=None), point_fit=None)
    tested = SimpleNamespace(error_correlation=SimpleNamespace(kernel_lags=None))
    kernel = SimpleNamespace(error_correlation=SimpleNamespace(kernel_lags=4))
    point_fit = SimpleNamespace(refinement=None, point_fit=object())
    two_stage = SimpleNamespace(refinement=None, point_fit=None)
    cases = (
        refined,
        SimpleNamespace(refinement=tested, point_fit=None),
        SimpleNamespace(refinement=kernel, point_fit=None),
    )
    names = [covariance_model(r) for r in (*cases, point_fit, two_stage)]
    assert names == ["view_robust", "view_robust", "kernel", "model", "two_stage"]
    assert set(names) == set(COVARIANCE_MODELS)


def test_self_calibrated_intrinsics_without_refinement_are_suspect(dataset, tmp_path):
    """`K: null` with `--no-refine` (issue 32's battery: 42x the error, status ok): the two-stage
    result inherits the self-calibration's error, and the verdict says so and what to change."""
    ds = _copy(dataset, tmp_path)
    _edit_json(ds / "metadata.json", lambda m: m["cameras"][0].update(K=None))
    r = calibrate(ds, progress=False, workers=1, refine=False)
    assert r.status == "suspect"
    assert any("self-calibrated" in s and "drop no-refine" in s for s in r.reasons), r.reasons


@pytest.mark.slow
def test_without_encoders_ratios_are_not_identifiable(dataset, tmp_path):
    ds = _copy(dataset, tmp_path)
    (ds / "encoders.csv").unlink()
    _edit_json(ds / "metadata.json", lambda m: m.update(encoders=None, clock={"offset_s": 0.04}))
    r = calibrate(ds, progress=False, workers=1)
    v = r.validation
    print({k: v[k] for k in v if k.startswith("ee_rms")})
    assert r.ok
    assert all(a["ratio"] is None and not a["ratio_identifiable"] for a in r.arcs)
    assert any("not identifiable" in w for w in r.warnings)
    # The refinement runs with every sweep frame's joint angle as an unknown.
    assert r.refinement is not None and not any(n.endswith(".rate") for n in r.refinement["std"])
    assert v["ee_rms_mm_after"] < 0.5 * v["ee_rms_mm_before"]
    assert v["ee_rms_mm_after"] < v["ee_rms_mm_two_stage"]
    # The estimated angles against the true ones (commanded coordinates): equal up
    # to one constant per joint (the zero offsets' gauge), within a few stds.
    truth = {f["row"]: f["q"] for f in json.loads((ds / "truth.json").read_text())["frames"]}
    views = r.refinement["joint_angles"]["views"]
    assert len(views) == r.refinement["views"] > 60
    z = []
    for j, name in enumerate(r.nominal.joint_names):
        mine = [a for a in views if a["joint"] == name]
        err = np.array([a["angle_deg"] - np.degrees(truth[a["frame"]][j]) for a in mine])
        z += list((err - np.median(err)) / np.array([a["std_deg"] for a in mine]))
    print(f"angle errors: {np.sqrt(np.mean(np.square(z))):.2f} stds RMS")
    assert np.sqrt(np.mean(np.square(z))) < 3.0


@pytest.mark.slow
def test_cli_calibrate_and_demo(dataset, tmp_path, capsys):
    before = _digest(dataset)
    out = tmp_path / "res"
    assert main(["calibrate", str(dataset), "--out", str(out), "--quiet", "--config", "workers=1"]) == 0
    assert _digest(dataset) == before  # input files are never modified
    assert (out / "result.json").is_file() and not list(tmp_path.glob(".res.*"))
    # How it was made: the command as given, every option after the configuration, the versions.
    run = json.loads((out / "result.json").read_text())["run"]
    assert run["command"] == f"jaxcal calibrate {dataset} --out {out} --quiet --config workers=1"
    assert run["options"]["workers"] == 1 and run["options"]["cv_folds"] == 5
    assert run["options"]["dataset"] == str(dataset) and run["jaxcal"] == jaxcal.__version__
    assert run["command"] in (out / "report.md").read_text()
    assert main(["calibrate", str(dataset), "--out", str(out), "--quiet"]) == 2  # not empty
    assert "not empty" in capsys.readouterr().err
    two = tmp_path / "two_stage"
    assert (
        main(
            [
                "calibrate",
                str(dataset),
                "--out",
                str(two),
                "--quiet",
                "--config",
                "workers=1",
                "--config",
                "no-refine=true",
            ]
        )
        == 0
    )
    r_two, r_ref = (json.loads((d / "result.json").read_text()) for d in (two, out))
    assert r_two["refinement"] is None and r_ref["refinement"] is not None
    assert (r_two["covariance_model"], r_ref["covariance_model"]) == ("two_stage", "view_robust")
    assert r_two["validation"]["ee_rms_mm_after"] == pytest.approx(r_ref["validation"]["ee_rms_mm_two_stage"])
    # The demo, filmed by two fixed cameras: the two-stage fit from the first,
    # the refinement over both (one robot, one T_cam_base each).
    demo = ["demo", "--out", str(tmp_path / "demo"), "--cameras", "2", "--config", "resolution=640x480"]
    demo += ["--config", "frames-per-joint=12", "--config", "sweep-deg=60"]
    assert main([*demo, "--quiet", "--config", "workers=1"]) == 0
    text = capsys.readouterr().out
    assert "Before / after" in text and "EE RMS mm" in text and "T_cam_base of cam1" in text
    assert "calibration ok" in text  # the verdict is said, not only its exit code
    res = tmp_path / "demo" / "result"
    said = [w.strip() for w in text.split(f"wrote {res}/: ")[1].split(" (")[0].split(",")]
    assert {"ros_cam1.launch.yaml", "ros_cam1.txt", "easy_handeye_cam1.yaml"} <= set(said)  # every camera's
    assert all((res / name).is_file() for name in said), said
    assert (res / "report.md").is_file() and "Camera cam1" in (res / "report.md").read_text()
    r = json.loads((res / "result.json").read_text())
    v, ref = r["validation"], r["refinement"]
    assert ref["views_per_camera"]["cam1"] > 40 and ref["solver"]["result"] == "successful"
    assert v["ee_rms_mm_after"] < v["ee_rms_mm_two_stage"]
    # cam1's pose relative to cam0: from its PnP start to the truth within a few of its std.
    (other,) = r["other_cameras"]
    e = v["other_cameras"]["cam1"]
    std_mm = float(np.linalg.norm(other["T_cam_base"]["std_xyz_mm"]))
    assert e["refined"]["trans_mm"] < min(0.5 * e["start"]["trans_mm"], 4 * std_mm)
    assert e["refined"]["rot_deg"] < 0.05
    import cv2

    fs = cv2.FileStorage(str(res / "camera_cam1.yaml"), cv2.FILE_STORAGE_READ)
    assert np.allclose(fs.getNode("T_cam_base").mat(), other["T_cam_base"]["matrix"])
    fs.release()


# --------------------------------------------------------------------------- bad input (one test per case)


def _fails(ds, exc, *words, **kw):
    with pytest.raises(exc) as e:
        calibrate(ds, progress=False, workers=1, **kw)
    for w in words:
        assert w in str(e.value), str(e.value)


def test_missing_metadata(dataset, tmp_path):
    ds = _copy(dataset, tmp_path)
    (ds / "metadata.json").unlink()
    _fails(ds, DatasetError, "metadata.json", "missing")


def test_unknown_schema_version(dataset, tmp_path):
    ds = _copy(dataset, tmp_path)
    _edit_json(ds / "metadata.json", lambda m: m.update(schema_version=99))
    _fails(ds, DatasetError, "schema_version", "99")


def test_missing_image(dataset, tmp_path):
    ds = _copy(dataset, tmp_path)
    victim = sorted((ds / "images" / "cam0").iterdir())[3]
    victim.unlink()
    _fails(ds, DatasetError, victim.name, "missing")  # at load, before any detection
    # As the error advises, its line of frames.csv deleted: the dataset loads, and truth.json's
    # frames follow the rows that moved up (matched by camera and capture index), the deleted one gone.
    lines = (ds / "frames.csv").read_text().splitlines(keepends=True)
    (ds / "frames.csv").write_text("".join(line for line in lines if victim.name not in line))
    loaded = load_dataset(ds)
    truth = loaded.truth["frames"]
    assert len(truth) == len(loaded.frames.file) == len(lines) - 2
    assert [(f["camera"], f["frame"]) for f in truth] == list(zip(loaded.frames.camera, loaded.frames.frame))
    assert [f["row"] for f in truth] == list(range(len(truth))) and 3 not in loaded.frames.frame


def test_unreadable_image(dataset, tmp_path):
    ds = _copy(dataset, tmp_path)
    victim = sorted((ds / "images" / "cam0").iterdir())[5]
    victim.write_bytes(b"not a png")
    _fails(ds, DatasetError, victim.name, "not an image")


def test_wrong_marker_dictionary(dataset, tmp_path):
    ds = _copy(dataset, tmp_path)
    _edit_json(ds / "metadata.json", lambda m: m["targets"][0].update(dictionary="DICT_6X6_250"))
    _fails(ds, CalibrationError, "no target was found", "DICT_6X6_250")


def test_sweep_with_too_few_frames(dataset, tmp_path):
    ds = _copy(dataset, tmp_path)
    meta = json.loads((ds / "metadata.json").read_text())
    seg = next(s for s in meta["motion"] if s["joint"] == "elbow_joint")
    span = seg["end"] - seg["start"]
    seg["end"] = seg["start"] + 0.25 * span  # only the first few frames of the sweep count
    (ds / "metadata.json").write_text(json.dumps(meta))
    _fails(ds, CalibrationError, "elbow_joint", "valid frames")
    # No sweep of it at all (a capture that ended before it): said so, before what it leads to.
    meta["motion"] = [s for s in meta["motion"] if s["joint"] != "elbow_joint"]
    (ds / "metadata.json").write_text(json.dumps(meta))
    _fails(
        ds, CalibrationError, "joint 'elbow_joint': the capture has no sweep of it", "ends before its sweep"
    )


def test_sweep_under_five_degrees(dataset, tmp_path):
    ds = _copy(dataset, tmp_path)
    path = ds / "encoders.csv"
    rows = list(csv.reader(path.read_text().splitlines()))
    col = rows[0].index("wrist_1_joint")
    for r in rows[1:]:
        r[col] = repr(0.05 * float(r[col]))  # the log says the joint barely moved (4 deg)
    with path.open("w", newline="") as f:
        csv.writer(f).writerows(rows)
    _fails(ds, CalibrationError, "wrist_1_joint", "degrees")


def _log_later(ds: Path, seconds: float, *, segments: bool) -> None:
    """The encoder log (and with `segments` the metadata's motion segments, on the same
    controller clock) stamped `seconds` later."""
    path = ds / "encoders.csv"
    rows = list(csv.reader(path.read_text().splitlines()))
    for r in rows[1:]:
        r[0] = repr(float(r[0]) + seconds)
    with path.open("w", newline="") as f:
        csv.writer(f).writerows(rows)
    if segments:
        _edit_json(
            ds / "metadata.json",
            lambda m: [s.update(start=s["start"] + seconds, end=s["end"] + seconds) for s in m["motion"]],
        )


def test_motion_segments_outside_the_encoder_log(dataset, tmp_path):
    """The log stamped 1000 s later and the motion segments not: both are on the controller
    clock, so no clock offset mends it; refused at load, naming both."""
    ds = _copy(dataset, tmp_path)
    _log_later(ds, 1000.0, segments=False)
    _fails(
        ds, DatasetError, "motion[0]", "lies outside the encoder log", "encoders.csv", "every other segment"
    )


def test_an_encoder_log_cut_short_is_named_not_the_target(dataset, tmp_path):
    """The log's last third lost: the joints swept after it have no angles, and the refusal says
    their sweep lies beyond the log (the frames showed the target all along)."""
    ds = _copy(dataset, tmp_path)
    lines = (ds / "encoders.csv").read_text().splitlines()
    (ds / "encoders.csv").write_text("\n".join(lines[: 2 * len(lines) // 3]) + "\n")
    _fails(
        ds,
        CalibrationError,
        "its sweep [",
        "(metadata.json motion) lies outside the encoder log [0, ",
        "cut short",
    )


def test_a_controller_clock_1000_s_off_is_found(dataset, tmp_path):
    """The controller's log and segments 1000 s later than the camera's stamps, nothing in the
    metadata: the motion-matching search starts the clock fit there, and the offset is the
    truth's; told to keep a given zero offset instead, the frames and the log do not overlap."""
    ds = _copy(dataset, tmp_path)
    _log_later(ds, 1000.0, segments=True)
    r = calibrate(ds, progress=False, workers=1, refine=False)
    assert r.ok and abs(r.clock["offset_s"] - (0.040 - 1000.0)) < 1e-3
    assert any("the clock fit started from -999.96" in w for w in r.warnings)
    _edit_json(ds / "metadata.json", lambda m: m.update(clock={"offset_s": 0.0}))
    _fails(ds, CalibrationError, "no overlap", "encoders.csv", clock="given", refine=False)


def test_nan_in_encoder_table(dataset, tmp_path):
    ds = _copy(dataset, tmp_path)
    path = ds / "encoders.csv"
    lines = path.read_text().splitlines()
    cells = lines[10].split(",")
    cells[2] = "nan"
    lines[10] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n")
    _fails(ds, DatasetError, "encoders.csv line 11", "NaN")


def test_unknown_joint_name(dataset, tmp_path):
    ds = _copy(dataset, tmp_path)
    _edit_json(ds / "metadata.json", lambda m: m["motion"][2].update(joint="elbow_jiont"))
    _fails(ds, DatasetError, "elbow_jiont", "unknown joint")


def test_robot_file_missing(dataset, tmp_path):
    ds = _copy(dataset, tmp_path)
    (ds / "robot.urdf").unlink()
    _fails(ds, DatasetError, "robot.urdf", "missing")


def test_robot_file_malformed(dataset, tmp_path):
    ds = _copy(dataset, tmp_path)
    (ds / "robot.urdf").write_text("<robot name='x'><link name='a'></robot")
    _fails(ds, DatasetError, "robot.urdf")


def test_output_directory_not_writable(dataset, tmp_path, capsys):
    if os.geteuid() == 0:
        # root ignores permission bits: a path under a regular file is unwritable for everyone.
        blocker = tmp_path / "file"
        blocker.write_text("x")
        out = blocker / "res"
    else:
        locked = tmp_path / "locked"
        locked.mkdir(mode=0o500)
        out = locked / "res"
    assert main(["calibrate", str(dataset), "--out", str(out), "--quiet"]) == 2
    assert "--out" in capsys.readouterr().err
    assert not out.exists()


# --------------------------------------------------------------------------- answers checked against physics


@pytest.mark.slow
def test_a_mis_sized_board_is_suspect_and_strict_writes_nothing(dataset, tmp_path, capsys):
    """The plate was printed 10 % larger than metadata.json says: every PnP
    length is 10 % short. The verdict names the target's size (and the CLI
    exits 3; with --strict it writes nothing)."""
    ds = _copy(dataset, tmp_path)
    _edit_json(
        ds / "metadata.json",
        lambda m: m["targets"][0].update(
            square_length=m["targets"][0]["square_length"] / 1.1,
            marker_length=m["targets"][0]["marker_length"] / 1.1,
        ),
    )
    out = tmp_path / "res"
    args = [
        "calibrate",
        str(ds),
        "--out",
        str(out),
        "--quiet",
        "--config",
        "workers=1",
        "--config",
        "no-refine=true",
    ]
    assert main(args) == 3
    r = json.loads((out / "result.json").read_text())
    assert r["status"] == "suspect"
    board = [c for c in r["checks"] if c["check"] == "board_scale"][0]
    assert 7.0 < board["value"] < 13.0, board  # measured: the axes 91 % as far apart as nominal
    assert any("printed size" in reason for reason in r["reasons"]), r["reasons"]
    strict = tmp_path / "strict"
    assert main([*args[:3], str(strict), *args[4:], "--strict"]) == 3
    assert not strict.exists() and "nothing written" in capsys.readouterr().out
    # Stated 1 % small (a print 1 % large): the tool point 15 mm off, which the former 2 % limit let
    # pass as ok; the spacing is measured to about 0.1 % (the capture as given: 0.094 %).
    shutil.rmtree(ds)
    ds = _copy(dataset, tmp_path)
    _edit_json(
        ds / "metadata.json",
        lambda m: m["targets"][0].update(
            square_length=0.99 * m["targets"][0]["square_length"],
            marker_length=0.99 * m["targets"][0]["marker_length"],
        ),
    )
    r = calibrate(ds, progress=False, workers=1, refine=False)
    (board,) = [c for c in r.verdict.checks if c.check == "board_scale"]
    assert r.status == "suspect" and 0.9 < board.value < 1.3, board
    reason = next(reason for reason in r.reasons if "printed size" in reason)
    fit = re.search(r"'plate0''s square of ([0-9.]+) mm would fit", reason)
    assert fit and abs(float(fit.group(1)) - 40.0) < 0.2, reason  # the printed 40 mm, the target named


@pytest.mark.slow
def test_a_wrong_focal_length_is_named_first(dataset, tmp_path):
    """metadata.json's focal length is 2 % longer than the camera's. The camera's distance and
    the link lengths absorb most of it (the tool point comes out centimetres off), so nothing
    but the refinement's score test of the held intrinsics sees it: the verdict names them
    first, with the step they point to (measured: -1.5 % on a -2 % error)."""
    ds = _copy(dataset, tmp_path)

    def longer(meta):
        K = meta["cameras"][0]["K"]
        K[0][0], K[1][1] = 1.02 * K[0][0], 1.02 * K[1][1]

    _edit_json(ds / "metadata.json", longer)
    r = calibrate(ds, progress=False, workers=1)
    t = r.refinement.intrinsics_test
    assert r.status == "suspect" and "other intrinsics than metadata.json's" in r.reasons[0], r.reasons
    assert t.sigmas > Limits().intrinsics_sigmas
    f = 1.02 * json.loads((dataset / "metadata.json").read_text())["cameras"][0]["K"][0][0]
    assert -0.03 < t.fx_px / f < -0.01 and -0.03 < t.fy_px / f < -0.01, (t.fx_px / f, t.fy_px / f)
    # The note of how far the result leans on K: linear in the focal error, 20 times its 0.1 % move
    # is the tool point's error against the truth (the noise's share is small beside it).
    said = next(
        re.search(r"0.1 % longer, the tool point would move (\d+\.\d+) mm RMS", n)
        for n in r.verdict.notes
        if "leans on" in n
    )
    assert abs(20.0 * float(said.group(1)) / r.validation["ee_rms_mm_after"] - 1.0) < 0.3, (
        said.group(0),
        r.validation,
    )
    # With K's uncertainty stated (cameras[].K_std), the step is held against it: 2 % of the focal
    # length covers the step (a note, the claim counts it); 0.1 % does not (the reason says how far).
    f0 = json.loads((dataset / "metadata.json").read_text())["cameras"][0]["K"][0][0]
    for share, named in ((0.02, False), (0.001, True)):
        _edit_json(
            ds / "metadata.json", lambda m: m["cameras"][0].update(K_std=[share * f0, share * f0, 5.0, 5.0])
        )
        r = calibrate(ds, progress=False, workers=1)
        check = next(c for c in r.verdict.checks if c.check == "cam0.intrinsics_sigmas")
        reason = [m for m in r.reasons if "other intrinsics" in m]
        if named:
            assert not check.passed and reason and "times the largest of cameras[].K_std" in reason[0], (
                r.reasons
            )
            assert float(re.search(r"sigmas\): .*, (\d+) times", reason[0]).group(1)) > 10, reason
        else:
            assert check.passed and not reason, r.reasons
            assert any("within" in n and "cameras[].K_std" in n for n in r.verdict.notes), r.verdict.notes


@pytest.mark.slow
def test_an_encoder_log_too_slow_or_stamps_that_jitter_are_named_first(dataset, result, tmp_path):
    """The joint log thinned from 500 to 10 Hz (a ROS joint_states topic throttled): between its
    samples the sweeps' accelerations are lost to linear interpolation, and the verdict names the
    log's rate first, not the sag or backlash the arcs' clock then suggests. Likewise the camera's
    stamps jittering by 5 ms."""
    ds = _copy(dataset, tmp_path)
    lines = (ds / "encoders.csv").read_text().splitlines(keepends=True)
    (ds / "encoders.csv").write_text("".join([lines[0], *lines[1::50]]))
    _edit_json(ds / "metadata.json", lambda m: m["encoders"].update(rate_hz=10.0))
    r = calibrate(ds, progress=False, workers=1, refine=False)
    check = next(c for c in r.verdict.checks if c.check == "encoder_interpolation")
    assert check.value > 2 * Limits().encoder_interpolation, check
    assert r.status == "suspect" and r.reasons[0].startswith(
        "the encoder log samples every 100 ms (10 Hz)"
    ), r.reasons
    clean = next(c for c in result.verdict.checks if c.check == "encoder_interpolation")
    assert clean.value < 0.1 * Limits().encoder_interpolation, clean
    assert not any(c.check == "stamp_jitter" for c in result.verdict.checks)  # exact stamps: no jitter
    # The log as it was, the camera's stamps jittering by 5 ms (stamped on arrival): the jitter is
    # measured from the stamps alone and named first.
    (ds / "encoders.csv").write_text("".join(lines))
    _edit_json(ds / "metadata.json", lambda m: m["encoders"].update(rate_hz=500.0))
    rows = list(csv.reader((ds / "frames.csv").read_text().splitlines()))
    rng = np.random.default_rng(1)
    for row in rows[1:]:
        row[2] = repr(float(row[2]) + 0.005 * rng.standard_normal())
    (ds / "frames.csv").write_text("\n".join(",".join(row) for row in rows) + "\n")
    r = calibrate(ds, progress=False, workers=1, refine=False)
    said = re.match(r"camera 'cam0''s stamps jitter by (\d+\.\d) ms around a steady frame rate", r.reasons[0])
    assert said and 3.5 < float(said.group(1)) < 6.5, r.reasons  # ~60 second differences: +-15 %


@pytest.mark.slow
def test_the_uncertainty_of_a_given_K_is_counted(dataset, result, tmp_path):
    """metadata.json's K 0.3 % long, as a camera's own calibration may leave it: below the
    intrinsics test's reach, the tool point is millimetres off, past what the clean capture claims.
    Stated as `K_std`, the claimed uncertainty counts it and covers the error."""
    ds = _copy(dataset, tmp_path)

    def longer(meta):
        cam = meta["cameras"][0]
        K = cam["K"]
        K[0][0], K[1][1] = 1.003 * K[0][0], 1.003 * K[1][1]
        cam["K_std"] = [0.003 * K[0][0], 0.003 * K[1][1], 1.0, 1.0]

    _edit_json(ds / "metadata.json", longer)
    r = calibrate(ds, progress=False, workers=1)
    claim = next(c.value for c in r.verdict.checks if c.check == "ee_sigma_mm")
    clean = next(c.value for c in result.verdict.checks if c.check == "ee_sigma_mm")
    error = r.validation["ee_rms_mm_after"]
    assert error > 1.5 * clean and error < 1.5 * claim, (error, clean, claim)
    # K_std is read with K, four standard deviations in px.
    meta = json.loads((ds / "metadata.json").read_text())
    for bad, says in (({"K": None}, "K_std: is given, but K is not"), ({"K_std": [1.0, 1.0]}, "K_std")):
        cam = meta["cameras"][0] | bad
        with pytest.raises(DatasetError, match=says):
            read_cameras({"cameras": [cam]}, Loc("metadata.json", "cameras"), ())


@pytest.mark.slow
def test_a_wrong_clock_offset_is_caught(dataset, tmp_path):
    """metadata.json says the clocks agree; they are 40 ms apart. The estimate
    is used and the disagreement named; trusting the metadata gives a suspect result."""
    ds = _copy(dataset, tmp_path)
    _edit_json(ds / "metadata.json", lambda m: m.update(clock={"offset_s": 0.0}))
    r = calibrate(ds, progress=False, workers=1, refine=False)
    assert abs(r.clock["offset_s"] - 0.040) < 1e-3 and r.clock["given_s"] == 0.0
    assert any("clock.offset_s is 0.000 ms but the sweeps say 40" in w for w in r.warnings), r.warnings
    assert r.status == "ok", r.reasons
    # Trusting it, in a process where MuJoCo cannot be imported: calibrating
    # needs no simulator and no OpenGL (issue 14).
    code = f"""
import json, sys
sys.modules["mujoco"] = None  # `import mujoco` now raises ImportError
import jax
jax.config.update("jax_compilation_cache_dir", {str(CACHE_DIR)!r})
jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
import jaxcal
r = jaxcal.calibrate({str(ds)!r}, progress=False, workers=1, refine=False, clock="given")
sim = sorted(m for m in sys.modules if m.startswith("jaxcal.sim") or m == "jaxcal.cli")
print(json.dumps({{"offset_s": r.clock["offset_s"], "status": r.status, "reasons": r.reasons, "sim": sim}}))
"""
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    trusted = json.loads(run.stdout.strip().splitlines()[-1])
    assert trusted["offset_s"] == 0.0 and trusted["status"] == "suspect", trusted["reasons"]
    assert trusted["sim"] == []


def test_the_two_stage_programs_compile_while_the_clock_fit_runs(monkeypatch, tmp_path):
    """`_programs.compile_two_stage_ahead` traces, lowers and compiles the arc fits'
    and the axis fit's programs on threads of their own (stored programs in a folder of the
    test's own, so nothing is loaded from an earlier run), and the stages' calls then
    neither trace, lower nor compile: the same compiled programs, reached without waiting."""
    from jaxcal import _exported

    monkeypatch.setattr(_exported, "programs_dir", lambda: tmp_path)
    setup = ur5e_setup(frames=24)
    data = jax.jit(lambda k: trial_sweeps(setup, setup.nominal, setup.T_cam_base, setup.T_flange_marker, k))(
        jax.random.key(0)
    )
    stages_ = (
        dispatch.JAXPR_TRACE_EVENT,
        dispatch.JAXPR_TO_MLIR_MODULE_EVENT,
        dispatch.BACKEND_COMPILE_EVENT,
    )
    events = []

    def listen(event, duration, **kw):
        if event in stages_ and any(n in kw.get("fun_name", "") for n in ("arc_fits", "axis_fit")):
            events.append((kw["fun_name"], event, threading.current_thread().name))

    monitoring.register_event_duration_secs_listener(listen)
    try:
        _programs.compile_two_stage_ahead("huber", setup.nominal, data, 1, True, True)
        _programs.wait_ahead()
        ahead = list(events)
        events.clear()
        arcs = _programs.arc_fits("huber", setup.nominal.joint_types)(data)
        fit = _programs.axis_fit(True)(setup.nominal, arcs, setup.T_flange_marker, None, None, True)
        jax.block_until_ready(fit)
    finally:
        monitoring.unregister_event_duration_listener(listen)
    for name in ("arc_fits", "axis_fit"):  # each on a thread of its own, in parallel
        assert (name, dispatch.JAXPR_TRACE_EVENT, "jaxcal compile ahead") in ahead
        # (a stored program's executable is named after its entry's file: `jit(arc_fits_<digest>)`)
        assert any(
            n.startswith(f"jit({name}_")
            and (e, t) == (dispatch.BACKEND_COMPILE_EVENT, "jaxcal compile ahead")
            for n, e, t in ahead
        ), ahead
    assert events == []  # nothing left to do on the calling thread
    assert bool(fit.result == optx.RESULTS.successful) and bool(
        np.all(arcs.result == optx.RESULTS.successful)
    )


@pytest.mark.parametrize(
    ("after", "before", "sigma", "says"),
    [
        (
            0.580,
            0.538,
            0.963,
            "within that claim: the two-stage being nearer the truth on this capture is within",
        ),
        (
            0.180,
            0.900,
            0.300,
            "the refinement is nearer the truth by 0.720 mm, more than the claimed 1-sigma",
        ),
        (1.790, 0.900, 0.300, "further from the truth by 0.890 mm, more than the claimed 1-sigma"),
    ],
)
def test_the_truth_line_reads_the_two_stages_against_the_claim(after, before, sigma, says):
    """On simulated data the console and report.md say whether the refined and the two-stage EE
    errors differ by more than the refined result claims (data/ur5e_sweeps: 0.580 against
    0.538 mm, a claim of 0.96 mm: noise, not a worse refinement)."""
    from types import SimpleNamespace as NS

    from jaxcal.summary import truth_line

    result = NS(
        validation=NS(refined=True, ee_rms_mm_after=after, ee_rms_mm_two_stage=before),
        verdict=NS(checks=[NS(check="ee_rms_px", value=0.1), NS(check="ee_sigma_mm", value=sigma)]),
        kind=NS(has_arcs=True),
    )
    line = truth_line(result)
    assert (
        line.startswith(f"Against the truth: refined {after:.3f} mm, two-stage {before:.3f} mm")
        and says in line
    )
    assert f"{after / sigma:.2f}x its claim" in line
    assert truth_line(NS(validation=None, verdict=result.verdict, kind=result.kind)) is None
