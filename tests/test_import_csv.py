"""`jaxcal import-csv` (jaxcal.io.csv_import): a CSV of joints and measured points -> a tracker dataset.

A round trip on a synthetic table (nominal FK of the UR5e plus a device pose and
millimetre deviations), every malformed input refused naming the column and the
line with nothing written, outputs never over an input, and the shipped UR5
laser-tracker datasets (data/ur5_tracker) loading with their sample counts.
"""

import json
import shutil
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxcal import forward_kinematics
from jaxcal.cli import main
from jaxcal.errors import CsvImportError, OutputError
from jaxcal.io.csv_import import import_csv
from jaxcal.io.dataset import load_dataset
from jaxcal.robots import ROBOTS_DIR, load_robot

ROOT = Path(__file__).resolve().parents[1]
URDF = ROBOTS_DIR / "ur5e.urdf"
TABLE = ROBOTS_DIR / "ur5e_dh.json"
POINT_M = np.array([0.0, 0.02, 0.05])
JOINTS = [f"j{i}" for i in range(1, 7)]
XYZ = ["X+dX", "Y+dY", "Z+dZ"]
ROWS = 40


def _table(seed: int = 0) -> tuple[list[str], np.ndarray]:
    """Header and rows: joints (deg), the nominal point (mm, a device frame turned and moved from the
    base) and a deviation of about a millimetre (mm), as published tracker tables give them."""
    rng = np.random.default_rng(seed)
    q = rng.uniform(-1.2, 1.2, (ROWS, 6))
    frames = np.asarray(jax.vmap(forward_kinematics, in_axes=(None, 0))(load_robot("ur5e"), jnp.asarray(q)))
    p = frames[:, -1, :3, 3] + frames[:, -1, :3, :3] @ POINT_M
    c, s = np.cos(0.4), np.sin(0.4)
    p_dev = p @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T + [1.5, -0.3, 0.2]
    dev = rng.normal(0.0, 1.0, (ROWS, 3))
    header = ["step", *JOINTS, "X", "Y", "Z", "dX", "dY", "dZ"]
    rows = np.column_stack([np.arange(ROWS), np.degrees(q), p_dev * 1e3, dev])
    return header, rows


def _write(path: Path, header, rows, edit=None) -> Path:
    cells = [[repr(float(v)) for v in r] for r in rows]
    if edit is not None:
        edit(cells)
    path.write_text(",".join(header) + "\n" + "\n".join(",".join(r) for r in cells) + "\n")
    return path


def _import(csv, out, **kw):
    args = dict(
        robot=URDF, joints=JOINTS, joint_unit="deg", xyz=XYZ, length_unit="mm", sigma_m=2e-5, point_m=POINT_M
    )
    return import_csv(csv, out, **(args | kw))


@pytest.fixture(scope="module")
def table():
    return _table()


@pytest.mark.parametrize("robot", [URDF, TABLE], ids=["urdf", "dh_table"])
def test_round_trip(tmp_path, table, robot):
    header, rows = table
    csv = _write(tmp_path / "poses.csv", header, rows)
    r = _import(csv, tmp_path / "ds", robot=robot)
    assert r.samples == ROWS and r.rms_from_nominal_m < 5e-3
    ds = load_dataset(tmp_path / "ds")
    s = ds.samples
    np.testing.assert_allclose(s.q, np.radians(rows[:, 1:7]), atol=1e-15)
    np.testing.assert_allclose(s.position, (rows[:, 7:10] + rows[:, 10:13]) / 1e3, atol=1e-15)
    assert (s.joint == -1).all() and s.orientation is None
    np.testing.assert_array_equal(s.sample, np.arange(ROWS))
    np.testing.assert_array_equal(s.timestamp, np.arange(ROWS, dtype=float))
    np.testing.assert_allclose(s.sigma_m, 2e-5)
    np.testing.assert_allclose(ds.device.T_link_point[:3, 3], POINT_M)
    assert ds.segments == ((None, 0.0, ROWS - 1.0),)
    assert ds.robot_is_table == (robot == TABLE)
    meta = json.loads((tmp_path / "ds" / "metadata.json").read_text())
    assert meta["x_csv"]["joint_unit"] == "deg" and meta["x_csv"]["xyz"] == XYZ
    assert json.loads((tmp_path / "ds" / ".jaxcal").read_text())["kind"] == "dataset"


def test_time_column_orientation_and_duplicate_rows(tmp_path, table):
    header, rows = table
    rows = np.vstack([rows, rows[-1:]])  # a pose measured twice: fine
    t = np.arange(len(rows)) * 2.5 + 100.0
    frames = np.asarray(
        jax.vmap(forward_kinematics, in_axes=(None, 0))(load_robot("ur5e"), jnp.radians(rows[:, 1:7]))
    )
    R = frames[:, -1, :3, :3]
    # The flange's orientation as a unit quaternion (x, y, z, w), in a device frame turned about z.
    c, s = np.cos(0.2), np.sin(0.2)
    Rd = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ R
    w = 0.5 * np.sqrt(np.maximum(1 + np.trace(Rd, axis1=1, axis2=2), 1e-12))
    quat = np.column_stack(
        [
            (Rd[:, 2, 1] - Rd[:, 1, 2]) / (4 * w),
            (Rd[:, 0, 2] - Rd[:, 2, 0]) / (4 * w),
            (Rd[:, 1, 0] - Rd[:, 0, 1]) / (4 * w),
            w,
        ]
    )
    csv = _write(
        tmp_path / "poses.csv", [*header, "t", "qx", "qy", "qz", "qw"], np.column_stack([rows, t, quat])
    )
    _import(csv, tmp_path / "ds", time="t", orientation=["qx", "qy", "qz", "qw"], sigma_rad=1e-4)
    ds = load_dataset(tmp_path / "ds")
    np.testing.assert_allclose(ds.samples.timestamp, t)
    np.testing.assert_allclose(ds.samples.orientation, Rd, atol=1e-9)
    shuffled = np.column_stack([rows, t, quat[::-1]])  # orientations of other rows
    csv = _write(tmp_path / "shuffled.csv", [*header, "t", "qx", "qy", "qz", "qw"], shuffled)
    with pytest.raises(CsvImportError, match=r"line 3 columns \['qx', 'qy', 'qz', 'qw'\].*turned"):
        _import(csv, tmp_path / "ds2", time="t", orientation=["qx", "qy", "qz", "qw"], sigma_rad=1e-4)


def _nan(cells):
    cells[4][3] = "nan"


def _text(cells):
    cells[2][5] = "12x"


def _far(cells):
    cells[7][7] = repr(float(cells[7][7]) + 5000.0)


def _off(cells):
    cells[9][9] = repr(float(cells[9][9]) + 300.0)


def _back_in_time(cells):
    cells[6][-1] = "0.5"


#: (what, edit of the cells, import arguments, the words the message must hold)
MALFORMED = [
    ("deg declared rad", None, dict(joint_unit="rad"), ["line 2 column 'j1'", "--joint-unit deg?"]),
    ("mm declared m", None, dict(length_unit="m"), ["'X+dX'", "lines 2-41", "--length-unit mm"]),
    ("missing joint column", None, dict(joints=[*JOINTS[:5], "j7"]), ["line 1", "no column 'j7'"]),
    ("unknown column in a sum", None, dict(xyz=["X+dX", "Y+dQ", "Z+dZ"]), ["line 1", "no column 'dQ'"]),
    ("NaN cell", _nan, {}, ["line 6 column 'j3'", "NaN"]),
    ("non-numeric cell", _text, {}, ["line 4 column 'j5'", "not a number"]),
    ("out-of-reach point", _far, {}, ["line 9 column 'X+dX'", "beyond the robot's reach"]),
    ("point off its nominal", _off, {}, ["line 11 column 'Z+dZ'", "from where the nominal robot puts it"]),
    ("time going back", _back_in_time, dict(time="t"), ["line 8 column 't'", "increase strictly"]),
]


@pytest.mark.parametrize("what, edit, kw, words", MALFORMED, ids=[m[0] for m in MALFORMED])
def test_malformed_tables_are_refused_naming_column_and_line(tmp_path, table, what, edit, kw, words):
    header, rows = table
    if "time" in kw:
        header, rows = [*header, "t"], np.column_stack([rows, np.arange(len(rows), dtype=float)])
    csv = _write(tmp_path / "poses.csv", header, rows, edit)
    with pytest.raises(CsvImportError) as e:
        _import(csv, tmp_path / "ds", **kw)
    for w in [str(csv), *words]:
        assert w in str(e.value), str(e.value)
    assert not (tmp_path / "ds").exists() and [p.name for p in tmp_path.iterdir()] == ["poses.csv"]


def test_metres_declared_as_millimetres_are_refused(tmp_path, table):
    header, rows = table
    rows = rows.copy()
    rows[:, 7:13] /= 1e3
    csv = _write(tmp_path / "poses.csv", header, rows)
    with pytest.raises(CsvImportError, match=r"'X\+dX'.*a factor 0\.001.*--length-unit m\)"):
        _import(csv, tmp_path / "ds")


def test_radians_declared_as_degrees_are_refused(tmp_path, table):
    header, rows = table
    rows = rows.copy()
    rows[:, 1:7] = np.radians(rows[:, 1:7])  # within every limit as degrees, so the points tell
    csv = _write(tmp_path / "poses.csv", header, rows)
    with pytest.raises(CsvImportError, match=r"'X\+dX'.*lines 2-41.*no length unit fits.*--joint-unit"):
        _import(csv, tmp_path / "ds")


def test_arguments_are_checked(tmp_path, table):
    csv = _write(tmp_path / "poses.csv", *table)
    with pytest.raises(ValueError, match="5 joint column"):
        _import(csv, tmp_path / "ds", joints=JOINTS[:5])
    with pytest.raises(ValueError, match="no default: state the unit"):
        _import(csv, tmp_path / "ds", joint_unit="degrees")
    with pytest.raises(ValueError, match="millimetres"):
        _import(csv, tmp_path / "ds", point_m=POINT_M * 1e3)
    with pytest.raises(ValueError, match="sigma_rad"):
        _import(csv, tmp_path / "ds", orientation=["j1", "j2", "j3", "j4"])


def test_outputs_never_overwrite_an_input(tmp_path, table):
    (tmp_path / "in").mkdir()
    csv = _write(tmp_path / "in" / "poses.csv", *table)
    robot = Path(shutil.copy(URDF, tmp_path / "robot.urdf"))
    before = csv.read_bytes(), robot.read_bytes()
    for out, words in (
        (tmp_path / "in", "contains the input"),
        (csv, "is the input"),
        (robot, "is the input"),
        (tmp_path, "contains the input"),
    ):
        with pytest.raises(OutputError, match=words):
            _import(csv, out, robot=robot, overwrite=True)
    assert (csv.read_bytes(), robot.read_bytes()) == before
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("mine")
    with pytest.raises(OutputError, match="not written by jaxcal"):
        _import(csv, tmp_path / "other", overwrite=True)
    _import(csv, tmp_path / "ds")
    with pytest.raises(OutputError, match="not empty"):
        _import(csv, tmp_path / "ds")
    _import(csv, tmp_path / "ds", overwrite=True)


def test_command_line(tmp_path, table, capsys):
    csv = _write(tmp_path / "poses.csv", *table)
    common = ["import-csv", str(csv), "--robot", "ur5e", "--joints", ",".join(JOINTS), "--xyz", ",".join(XYZ)]
    common += ["--sigma-mm", "0.02", "--point-mm", "0,20,50", "--length-unit", "mm"]
    assert main([*common, "--out", str(tmp_path / "ds"), "--joint-unit", "deg"]) == 0
    assert f"wrote {tmp_path / 'ds'}: {ROWS} samples" in capsys.readouterr().out
    assert main([*common, "--out", str(tmp_path / "ds2"), "--joint-unit", "rad"]) == 2
    assert "column 'j1'" in capsys.readouterr().err and not (tmp_path / "ds2").exists()
    with pytest.raises(SystemExit):  # no unit, no default
        main([*common, "--out", str(tmp_path / "ds3")])


@pytest.mark.parametrize("name, samples", [("grid", 1000), ("test", 20)])
def test_shipped_ur5_tracker_datasets_load(name, samples):
    ds = load_dataset(ROOT / "data" / "ur5_tracker" / name)
    assert len(ds.samples.sample) == samples and ds.robot_is_table
    assert ds.device.kind == "laser_tracker" and ds.samples.q is not None
    np.testing.assert_allclose(ds.device.T_link_point[:3, 3], [0.0, 0.09e-3, 31.0e-3])


def test_shipped_test_set_is_what_the_script_writes(tmp_path):
    """data/ur5_tracker/convert.py's import of the 20 random poses, redone: the same samples."""
    here = ROOT / "data" / "ur5_tracker"
    spec = json.loads((here / "test" / "metadata.json").read_text())["x_csv"]
    import_csv(
        here / "source" / spec["file"],
        tmp_path / "test",
        robot=ROBOTS_DIR / "ur5_dh.json",
        joints=list(spec["joints"].values()),
        joint_unit=spec["joint_unit"],
        xyz=spec["xyz"],
        length_unit=spec["length_unit"],
        sigma_m=2e-5,
        point_m=[0.0, 0.09e-3, 31.0e-3],
    )
    assert (tmp_path / "test" / "samples.csv").read_text() == (here / "test" / "samples.csv").read_text()


def test_commanded_points_are_noted_measured_ones_are_not(tmp_path):
    """The real UR5 table holds both the commanded (nominal) points x_t and the measured ones
    x_t + x_dif: importing the commanded ones as if measured is noted, the measured ones are not."""
    here = ROOT / "data" / "ur5_tracker"
    spec = json.loads((here / "test" / "metadata.json").read_text())["x_csv"]
    kw = dict(
        robot=ROBOTS_DIR / "ur5_dh.json", joints=list(spec["joints"].values()), joint_unit=spec["joint_unit"],
        length_unit=spec["length_unit"], sigma_m=2e-5, point_m=[0.0, 0.09e-3, 31.0e-3],
    )  # fmt: skip
    source = here / "source" / spec["file"]
    commanded = import_csv(source, tmp_path / "commanded", xyz=["x_t", "y_t", "z_t"], **kw)
    assert commanded.rms_from_nominal_m < 4e-5
    assert (
        len(commanded.notes) == 1 and "commanded (nominal) points rather than measured" in commanded.notes[0]
    )
    measured = import_csv(source, tmp_path / "measured", xyz=spec["xyz"], **kw)
    assert measured.rms_from_nominal_m > 3e-4 and measured.notes == ()
