"""Inputs that escape or exhaust (issue 49, items 6 and 7): each refused by name before anything
is written, memory bounded whatever the option, nothing left behind, Ctrl-C honoured.

Input handling only: no calibration and no compile of a jaxcal program (the certificate's and
the import's pieces are called on analytic arrays); the Ctrl-C cases run `jaxcal.cli.run` in a
subprocess on a command that only writes.
"""

import argparse
import json
import math
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from jaxcal import certification
from jaxcal._selection import CV_GAIN, MIN_Z
from jaxcal.cli import build_parser, main
from jaxcal.errors import DatasetError, JaxcalError
from jaxcal.io import _logs, _schema
from jaxcal.io._files import shown
from jaxcal.io.checks import read_product, read_result_json
from jaxcal.io.csv_import import import_csv
from jaxcal.io.dataset import load_dataset
from jaxcal.io.dh_tables import read_table_file
from jaxcal.io.handeye import load_hand_eye_capture
from jaxcal.io.plan_inputs import read_camera
from jaxcal.io.result import read_result
from jaxcal.io.rosbag import read_targets
from jaxcal.records import ModelRow
from jaxcal.robots import ROBOTS_DIR, robot_file
from jaxcal.sim.simulate import SimConfig
from jaxcal.sim.tracker import TrackerSimConfig
from jaxcal.stages._two_stage import term_note

ROOT = Path(__file__).resolve().parents[1]
BAG = ROOT / "data" / "ros" / "ur5e_sweeps_mcap"
UR5_TEST = ROOT / "data" / "ur5_tracker" / "source" / "3D_UR5_uncalibrated_random_cleaned.csv"
UR5_COLUMNS = ["--joint-columns", "joint_1,joint_2,joint_3,joint_4,joint_5,joint_6", "--joint-unit", "deg",
               "--xyz", "x_t+x_dif,y_t+y_dif,z_t+z_dif", "--length-unit", "mm", "--sigma-mm", "0.02",
               "--point-mm", "0,0.09,31.0"]  # fmt: skip


def _files(root: Path) -> list[str]:
    return sorted(p.relative_to(root).as_posix() for p in root.rglob("*"))


def _refused(argv, capsys) -> str:
    """`jaxcal ARGV`'s error message, refused with exit 2 (by the command or by argparse)."""
    try:
        code = main([str(a) for a in argv])
    except SystemExit as e:
        code = e.code
    assert code == 2
    return capsys.readouterr().err


# --------------------------------------------------------------------------- names that become paths


def test_a_camera_name_that_escapes_is_refused_before_anything_is_written(tmp_path, capsys):
    """`import-bag --camera-name ../../x_escape` wrote 144 PNGs outside `--out` and left them."""
    (tmp_path / "a" / "b").mkdir(parents=True)
    err = _refused(
        ["import-bag", BAG, "--out", tmp_path / "a" / "b" / "out", "--images", "/camera/image_raw/compressed",
         "--joints", "/joint_states", "--robot", ROBOTS_DIR / "ur5e.urdf", "--target", BAG.parent / "plate0.json",
         "--config", "camera-name=../../x_escape"],
        capsys,
    )  # fmt: skip
    assert "camera-name" in err and "'../../x_escape'" in err, err
    assert _files(tmp_path) == ["a", "a/b"]


def test_every_name_that_forms_a_path_is_checked(tmp_path):
    """The device's name (`ros_<device>.txt`), a hand-eye camera's (`images/<name>/`) and a plan
    camera's (a rendered plan's `images/<name>/`): refused as the dataset's camera names are."""
    for name in ("../x", "a/b", ".hidden", "", "x" * 65, "nul\x00"):
        with pytest.raises(DatasetError, match="it names output files"):
            _schema.file_name(name, "camera")
    assert _schema.file_name("cam_0.left-1", "camera") == "cam_0.left-1"
    with pytest.raises(JaxcalError, match=r"device_name \(device-name\).*'\.\./x'"):
        import_csv(UR5_TEST, tmp_path / "out", robot=robot_file("ur5_dh"), joints=["a"] * 6, joint_unit="deg",
                   xyz=["x", "y", "z"], length_unit="mm", sigma_m=2e-5, device_name="../x")  # fmt: skip
    capture = tmp_path / "capture"
    capture.mkdir()
    (capture / "handeye.json").write_text(
        json.dumps(
            {
                "schema": "jaxcal.handeye",
                "schema_version": 1,
                "arrangement": "eye_in_hand",
                "cameras": [{"name": "..", "width": 640, "height": 480}],
            }
        )  # fmt: skip
    )
    with pytest.raises(DatasetError, match=r"cameras\[0\]: field 'name'.*'\.\.'"):
        load_hand_eye_capture(capture)
    camera = tmp_path / "camera.yaml"
    camera.write_text(
        "camera_name: ../../x\nimage_width: 640\nimage_height: 480\n"
        "camera_matrix: [[500, 0, 320], [0, 500, 240], [0, 0, 1]]\n"
        "T_base_cam: [[1, 0, 0, 1], [0, 1, 0, 0], [0, 0, 1, 1], [0, 0, 0, 1]]\n"
    )
    with pytest.raises(JaxcalError, match=r"field 'camera_name'.*'\.\./\.\./x'"):
        read_camera(camera, "flange")
    assert _files(tmp_path) == ["camera.yaml", "capture", "capture/handeye.json"]


# --------------------------------------------------------------------------- loops and depths


def test_a_symbolic_link_loop_is_refused_naming_the_path(tmp_path, capsys):
    loop = tmp_path / "loop"
    loop.symlink_to(loop)
    for argv in (
        ["import-csv", loop, "--robot", "ur5_dh", "--out", tmp_path / "out", *UR5_COLUMNS],
        ["calibrate", loop, "--out", tmp_path / "out"],
        ["inspect", loop],
        ["certify", loop],
        ["verify", loop, loop],
    ):
        err = _refused(argv, capsys)
        assert f"{loop}: a loop of symbolic links" in err and "Traceback" not in err, err
    assert _files(tmp_path) == ["loop"]


def _deep(path: Path, depth: int = 100_000) -> Path:
    if path.suffix == ".yaml":
        path.write_text("a: " + "[" * depth + "]" * depth + "\n")
    else:
        path.write_text('{"a": ' + "[" * depth + "]" * depth + "}")
    return path


def test_a_document_nested_too_deep_is_refused_by_every_reader(tmp_path):
    """A DH table nested 100,000 deep raised a RecursionError (metadata.json was refused cleanly):
    every JSON or YAML jaxcal reads goes through `_schema.loads` / `load_yaml`."""
    deep = _deep(tmp_path / "deep.json")
    words = "nested more than 100 levels deep"
    for read in (read_table_file, read_targets, read_result, read_product, read_result_json):
        with pytest.raises(DatasetError, match=words):
            read(deep)
    with pytest.raises(DatasetError, match=words):
        read_table_file(_deep(tmp_path / "deep.yaml"))
    with pytest.raises(JaxcalError, match=words):
        read_camera(_deep(tmp_path / "camera.yaml"), "flange")
    for folder, name, read in (
        ("ds", "metadata.json", load_dataset),
        ("he", "handeye.json", load_hand_eye_capture),
    ):
        (tmp_path / folder).mkdir()
        _deep(tmp_path / folder / name)
        with pytest.raises(DatasetError, match=words):
            read(tmp_path / folder)
    with pytest.raises(ValueError, match=words):  # 101 levels: the bound, not the parser's recursion
        _schema.loads("[" * 101 + "]" * 101)
    doc, depth = _schema.loads("[" * 100 + "]" * 100), 0
    while isinstance(doc, list):
        doc, depth = doc[0] if doc else None, depth + 1
    assert depth == 100


def test_the_command_line_refuses_a_deep_robot_file(tmp_path, capsys):
    deep = _deep(tmp_path / "robot_dh.json")
    err = _refused(["import-csv", UR5_TEST, "--robot", deep, "--out", tmp_path / "out", *UR5_COLUMNS], capsys)
    assert f"DH table '{deep}' cannot be read: nested more than 100 levels deep" in err, err
    assert not (tmp_path / "out").exists()


# --------------------------------------------------------------------------- numbers and sizes


def test_every_number_option_is_finite_and_every_count_bounded():
    """No command takes a bare float (`nan` reached the simulator) or an unbounded integer (a count
    that sizes memory: `certify --samples 2000000` asked for 60 GiB)."""
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    bare = [
        f"{name} {'/'.join(a.option_strings)}"
        for name, p in sub.choices.items()
        for a in p._actions
        if a.type in (float, int)
    ]
    assert bare == []


@pytest.mark.parametrize(
    "argv, words",
    [
        (
            ["certify", "res", "--config", "samples=2000000"],
            "samples=2000000: expected a positive integer of at most 100,000",
        ),
        (["montecarlo", "--trials", "5000000"], "--trials: expected a positive integer of at most 1,000,000"),
        (["simulate", "--out", "{out}", "--resolution", "100000x100000"], "each side from 1 to 65535"),
        (["simulate-tracker", "--out", "{out}", "--noise-um", "inf"], "--noise-um: expected a finite number"),
        (
            ["plan", "--config", "candidates=10000000"],
            "candidates=10000000: expected a positive integer of at most 50,000",
        ),
        (
            ["calibrate", "ds", "--out", "{out}", "--config", "cv-folds=100000"],
            "cv-folds=100000: expected a non-negative",
        ),
        (
            [
                "import-csv",
                "x.csv",
                "--robot",
                "ur5",
                "--out",
                "{out}",
                *UR5_COLUMNS[:-2],
                "--point-mm",
                "nan,0,0",
            ],
            "--point-mm: expected x,y,z (mm, finite)",
        ),
        (["certify", "res", "--region", "nan,0,0,1,1,1"], "--region 'nan,0,0,1,1,1': give finite numbers"),
    ],
)
def test_sizes_and_non_finite_numbers_are_refused_up_front(argv, words, tmp_path, capsys):
    err = _refused([a.format(out=tmp_path / "out") for a in argv], capsys)
    assert words in err, err
    assert _files(tmp_path) == []


def test_simulate_refuses_a_non_finite_option_before_writing(tmp_path, capsys):
    """`simulate --distortion nan 0 0 0 0` rendered a whole dataset, refused it on read-back and left it."""
    err = _refused(["simulate", "--out", tmp_path / "out", "--config", "distortion=nan,0,0,0,0"], capsys)
    assert "--config distortion=nan,0,0,0,0: expected a finite number, got 'nan'" in err
    assert _files(tmp_path) == []
    with pytest.raises(ValueError, match="SimConfig: distortion must be finite"):
        SimConfig(distortion=(math.nan, 0.0, 0.0, 0.0, 0.0)).check()
    with pytest.raises(ValueError, match="TrackerSimConfig: noise_um must be finite"):
        TrackerSimConfig(noise_um=math.inf).check(6)


def test_certificate_work_is_chunked_and_bounded(tmp_path, monkeypatch):
    """`norm_quantiles` and `chunked` give what one pass gives; the poses a certificate takes are bounded."""
    rng = np.random.default_rng(0)
    A = rng.standard_normal((1203, 3, 3))
    cov = A @ np.swapaxes(A, 1, 2)
    q, kept = certification.norm_quantiles(cov, keep=7)
    lam = np.clip(np.linalg.eigvalsh(cov), 0.0, None)
    d = np.sqrt(lam @ (np.random.default_rng(0).standard_normal((certification.QUANTILE_DRAWS, 3)) ** 2).T)
    np.testing.assert_array_equal(q, np.quantile(d, 0.95, axis=1))
    np.testing.assert_array_equal(kept, d[:, :7])
    seen = []

    def fn(x):
        seen.append(len(x))
        return x.sum(axis=1)

    x = rng.standard_normal((23, 4))
    np.testing.assert_array_equal(certification.chunked(fn, x, chunk=5), x.sum(axis=1))
    assert seen == [5] * 5  # the last chunk padded: one shape for every call
    with pytest.raises(ValueError, match=r"samples: from 1 to 100,000 configurations \(MAX_POSES\)"):
        certification.certify(tmp_path / "nothing", samples=certification.MAX_POSES + 1)
    monkeypatch.setattr(certification, "MAX_POSES", 10)
    poses = tmp_path / "poses.csv"
    poses.write_text("\n".join(",".join(["0.1"] * 6) for _ in range(11)) + "\n")
    with pytest.raises(DatasetError, match=f"{poses}: more than 10 configurations"):
        certification.read_poses(poses, [f"j{i}" for i in range(6)])


# --------------------------------------------------------------------------- output files


@pytest.mark.parametrize(
    "argv",
    [
        ["certify", "{res}", "--plot", "{missing}/map.png"],
        ["certify", "{res}", "--json", "{missing}/c.json"],
        ["verify", "{res}", "{res}", "--plot", "{missing}/v.png"],
        ["check", "{res}", "{res}", "--json", "{missing}/d.json"],
        ["montecarlo", "--json", "{missing}/mc.json"],
        ["plan", "--evaluate", "{res}", "--plot", "{missing}/p.png"],
    ],
    ids=lambda a: f"{a[0]} {a[-2]}",
)
def test_an_output_file_in_a_missing_folder_is_refused_up_front(argv, tmp_path, capsys):
    """A clear message before any work (the raw errno came after it), the same for every command:
    jaxcal creates an output directory's parents, not an output file's folder."""
    err = _refused([a.format(res=tmp_path / "res", missing=tmp_path / "missing") for a in argv], capsys)
    assert f"the folder {tmp_path / 'missing'} does not exist; create it first" in err, err
    assert _files(tmp_path) == []


# --------------------------------------------------------------------------- Ctrl-C

SLEEPY = r"""
import gc, signal, sys, time
import jaxcal.cli as cli
from jaxcal.io._files import atomic_directory


def sleepy(args):
    with atomic_directory(args.out, kind="result", what="--out") as tmp:
        (tmp / "part.txt").write_text("half")
        print("ready", flush=True)
        if args.mode == "python":  # an ordinary long loop
            while True:
                sum(range(1000))
        elif args.mode == "gc":  # every interrupt lands in a garbage-collection callback (JAX has one)
            gc.callbacks.append(lambda phase, info: time.sleep(0.05))
            while True:
                gc.collect()
        else:  # the main thread in C code that never sees the signal (XLA compiling)
            signal.pthread_sigmask(signal.SIG_BLOCK, [signal.SIGINT])
            time.sleep(60)
    return 0


def add(sub):
    p = sub.add_parser("sleepy")
    p.add_argument("out")
    p.add_argument("mode")
    p.set_defaults(func=sleepy)


cli.GROUPS = (*cli.GROUPS, (("sleepy",), add))
sys.argv = ["jaxcal", "sleepy", *sys.argv[1:]]
cli.run()
"""


@pytest.mark.parametrize("mode, limit_s", [("python", 2.0), ("gc", 3.0), ("blocked", 3.0)])
def test_ctrl_c_stops_a_command_at_once_and_leaves_nothing(mode, limit_s, tmp_path):
    """Once in six tries a SIGINT 25 s into `calibrate` was not honoured: it landed in JAX's
    garbage-collection callback, which drops exceptions. Whatever the main thread does, the
    command ends within `jaxcal._interrupt.STOP_S` (1.5 s; the limit here leaves a loaded
    machine its slack), exit 130, with no output, temporary directory or lock left."""
    script = tmp_path / "sleepy.py"
    script.write_text(SLEEPY)
    work = tmp_path / "work"
    work.mkdir()
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    with subprocess.Popen(
        [sys.executable, str(script), str(work / "out"), mode],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    ) as proc:  # fmt: skip
        try:
            assert proc.stdout.readline().strip() == "ready", proc.stderr.read()
            t0 = time.perf_counter()
            proc.send_signal(signal.SIGINT)
            proc.wait(timeout=30)
            elapsed = time.perf_counter() - t0
        finally:
            proc.kill()
        err = proc.stderr.read()
    assert proc.returncode == 130 and "jaxcal: interrupted" in err and "Traceback" not in err, err
    assert elapsed < limit_s, elapsed
    assert _files(work) == []


# --------------------------------------------------------------------------- streaming, warnings, wording


def test_a_table_is_read_block_by_block_naming_line_and_column(tmp_path, monkeypatch):
    monkeypatch.setattr(_logs, "BLOCK_ROWS", 3)
    rows = ["a,b,name", "1,2.5,x", "", " 3 , 1e3 , y ", ",,", '4,"5",z', "5,6,", "6,1_0,w"]
    path = tmp_path / "t.csv"
    path.write_text("\n".join(rows) + "\n")
    t = _logs.read_number_table(path, "table", lambda header: ([0, 1], [2]))
    np.testing.assert_array_equal(t.lines, [2, 4, 6, 7, 8])
    np.testing.assert_array_equal(t.values, [[1, 2.5], [3, 1000], [4, 5], [5, 6], [6, 10]])
    assert t.text[:, 0].tolist() == ["x", "y", "z", "", "w"]
    for bad, words in (("7,nan,v", "line 10 column 'b': value is nan (NaN/inf not allowed)"),
                       ("7,0x1,v", "line 10 column 'b': '0x1' is not a number"),
                       ("7,1", "line 10: expected 3 cells (the header's), got 2")):  # fmt: skip
        path.write_text("\n".join([*rows, "", bad]) + "\n")
        with pytest.raises(DatasetError, match=re.escape(f"{path} {words}")):
            _logs.read_number_table(path, "table", lambda header: ([0, 1], [2]))


def test_a_row_far_from_the_nominal_robot_is_a_warning_with_its_meaning(tmp_path, capsys):
    """One joint cell 5 deg off puts the real UR5's point 37 mm from the nominal robot: a warning
    naming the line (it was printed as plain information); the clean rows give none."""
    lines = UR5_TEST.read_text().splitlines()
    cells = lines[7].split(",")
    cells[8] = repr(float(cells[8]) + 5.0)  # joint_2 of the 7th pose (line 8)
    bad = tmp_path / "bad.csv"
    bad.write_text("\n".join([*lines[:7], ",".join(cells), *lines[8:]]) + "\n")
    assert (
        main(["import-csv", str(UR5_TEST), "--robot", "ur5_dh", "--out", str(tmp_path / "ok"), *UR5_COLUMNS])
        == 0
    )
    assert "warning" not in capsys.readouterr().out
    assert (
        main(["import-csv", str(bad), "--robot", "ur5_dh", "--out", str(tmp_path / "bad"), *UR5_COLUMNS]) == 0
    )
    out = capsys.readouterr().out
    assert f"warning: {bad}: 1 row(s) lie far from where the nominal robot puts them" in out, out
    assert "line 8 (" in out and "most likely holds a wrong cell" in out


def test_messages_name_a_shipped_robot_file_without_the_checkout(tmp_path):
    with pytest.raises(ValueError) as e:
        import_csv(UR5_TEST, tmp_path / "out", robot=robot_file("ur5_dh"), joints=["joint_1"], joint_unit="deg",
                   xyz=["x_t", "y_t", "z_t"], length_unit="mm", sigma_m=2e-5)  # fmt: skip
    assert "joints of data/robots/ur5_dh.json" in str(e.value) and str(ROOT) not in str(e.value)
    assert shown(tmp_path / "mine.json") == str(tmp_path / "mine.json")


def test_the_term_note_says_better_by_less_than_the_threshold():
    base = ModelRow(terms=(), free=25, cv_mean_mm=0.1000, kept=True)
    slightly = ModelRow(terms=("compliance",), free=31, cv_mean_mm=0.0997)
    worse = ModelRow(terms=("harmonic1",), free=37, cv_mean_mm=0.1010)
    models = (base, slightly, worse)
    assert term_note(slightly, models) == (
        "the model with compliance: cross-validation 0.0997 mm mean, better than the geometric model's "
        f"0.1000 mm by 0.30 %, less than the {100 * CV_GAIN:g} % a term must gain: not kept"
    )
    assert "not better than the geometric model's 0.1000 mm: not kept" in term_note(worse, models)
    # A term kept, then extended by the next (the real UR5: compliance, then +harmonic1): no note.
    better = ModelRow(terms=("compliance",), free=31, cv_mean_mm=0.0964)
    extended = ModelRow(terms=("compliance", "harmonic1"), free=37, cv_mean_mm=0.0916, kept=True)
    assert term_note(better, (base, better, extended)) is None
    # Better by over CV_GAIN, but not by MIN_Z standard errors of the paired distances (a few samples).
    unsure = ModelRow(terms=("compliance",), free=31, cv_mean_mm=0.0964, cv_gain_z=1.3)
    assert term_note(unsure, (base, unsure)) == (
        "the model with compliance: cross-validation 0.0964 mm mean, better than the geometric model's "
        f"0.1000 mm by 3.60 %, 1.30 standard errors of the samples' paired differences, fewer than the "
        f"{MIN_Z:g} a term's gain must stand out by: not kept"
    )
