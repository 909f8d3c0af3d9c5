"""Robots from the manufacturers' tables (issue 31): the shipped DH/MDH table files
checked against the published kinematics, the table reader's fields, the robot
loaders, link inertials, and datasets whose robot is a table.

No rendering and no calibration: forward kinematics in NumPy and a few jitted
evaluations.
"""

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from jaxcal._kinematics import forward_kinematics
from jaxcal.errors import DatasetError
from jaxcal.io.dataset import load_dataset
from jaxcal.io.dh_tables import read_table_file
from jaxcal.robots import ROBOTS_DIR, load_robot

SWEEPS = Path(__file__).resolve().parents[1] / "data" / "ur5e_sweeps"
UR_JOINTS = [
    "shoulder_pan_joint",
    "shoulder_lift_joint",
    "elbow_joint",
    "wrist_1_joint",
    "wrist_2_joint",
    "wrist_3_joint",
]


def _write(path: Path, doc) -> Path:
    path.write_text(json.dumps(doc))
    return path


def _fk(model, qs) -> np.ndarray:
    return np.stack([np.asarray(forward_kinematics(model, q)[-1]) for q in qs])


# --------------------------------------------------------------------------- datasets whose robot is a table


@pytest.fixture
def table_ds(tmp_path) -> Path:
    """`data/ur5e_sweeps` with its URDF replaced by the UR5e's DH table (ratios, limits as the URDF's)."""
    dst = tmp_path / "ds"
    shutil.copytree(SWEEPS, dst)
    (dst / "robot.urdf").unlink()
    doc = json.loads((ROBOTS_DIR / "ur5e_dh.json").read_text())
    doc.update(
        reduction_ratio=[101.0] * 6, lower=[-2 * math.pi] * 6, upper=[2 * math.pi] * 6, velocity=[math.pi] * 6
    )
    _write(dst / "robot_dh.json", doc)
    meta = json.loads((dst / "metadata.json").read_text())
    meta["robot"] = {"table": "robot_dh.json", "joints": UR_JOINTS, "flange_link": "flange"}
    _write(dst / "metadata.json", meta)
    return dst


def test_a_dataset_whose_robot_is_a_table_loads_and_builds_the_tables_model(table_ds):
    ds = load_dataset(table_ds)
    assert ds.robot_is_table and ds.robot_urdf.name == "robot_dh.json"
    assert ds.joint_names == tuple(UR_JOINTS) and ds.flange_link == "flange"
    lim = ds.joint_limits["elbow_joint"]
    assert lim.reduction_ratio == 101.0 and lim.lower == -2 * math.pi and lim.velocity == math.pi
    model = ds.load_model()
    urdf = load_robot("ur5e")
    assert model.link_names[0] == "base_link" and model.link_names[-1] == "flange"
    np.testing.assert_allclose(model.reduction_ratio, 101.0)
    qs = np.random.default_rng(0).uniform(-np.pi, np.pi, (20, 6))
    np.testing.assert_allclose(_fk(model, qs), _fk(urdf, qs), atol=1e-12)


def test_a_table_without_limits_loads_with_open_limits(table_ds):
    doc = json.loads((table_ds / "robot_dh.json").read_text())
    for k in ("lower", "upper", "velocity"):
        doc.pop(k)
    _write(table_ds / "robot_dh.json", doc)
    lim = load_dataset(table_ds).joint_limits["wrist_3_joint"]
    assert lim.lower is None and lim.upper is None and lim.velocity is None


def _robot_fails(root: Path, robot_edit, *words):
    meta = json.loads((root / "metadata.json").read_text())
    robot_edit(meta["robot"])
    _write(root / "metadata.json", meta)
    with pytest.raises(DatasetError) as e:
        load_dataset(root)
    for w in words:
        assert w in str(e.value), str(e.value)


@pytest.mark.parametrize(
    ("edit", "words"),
    [
        (lambda r: r.update(urdf="robot.urdf"), ["robot", "exactly one of 'urdf'", "both"]),
        (lambda r: r.pop("table"), ["robot", "exactly one of 'urdf'", "neither"]),
        (lambda r: r.update(table="robot.txt"), ["robot.table", "not a table file"]),
        (lambda r: r.update(table="gone.json"), ["gone.json", "robot file missing", "robot.table"]),
        (lambda r: r.update(joints=UR_JOINTS[::-1]), ["robot.joints", "differ from the joints of robot_dh.json"]),
        (lambda r: r.update(base_link="world"), ["robot.base_link", "'world'", "'base_link'"]),
    ],
)
def test_table_robot_errors_name_the_field(table_ds, edit, words):
    _robot_fails(table_ds, edit, *words)


@pytest.mark.parametrize(
    ("edit", "words"),
    [
        (lambda d: d.update(mass=[1.0, 2.0, -1.0, 1.0, 1.0, 1.0], com=[[0, 0, 0]] * 6), ["'mass'", "positive"]),
        (lambda d: d.update(mass=[1.0] * 6), ["'mass' and 'com'"]),
        (lambda d: d.update(mass=[1.0] * 6, com=[[0, 0]] * 6), ["'com'", "6 x 3"]),
        (lambda d: d.update(lower=[0.0] * 6, upper=[1.0] * 5 + [-1.0]), ["'lower', 'upper'", "wrist_3_joint"]),
        (lambda d: d.pop("upper"), ["'lower' and 'upper'"]),
        (lambda d: d.update(velocity=[0.0] * 6), ["'velocity'", "positive"]),
        (lambda d: d.update(a=[0.0] * 5 + [float("nan")]), ["field 'a'", "finite"]),
        (lambda d: d.update(d=["0.1"] * 6), ["field 'd'"]),
        (lambda d: d.update(link_names=["a", "b"]), ["'link_names'", "6 link names"]),
    ],
)
def test_bad_table_fields_are_named_with_the_file(table_ds, edit, words):
    path = table_ds / "robot_dh.json"
    doc = json.loads(path.read_text())
    edit(doc)
    path.write_text(json.dumps(doc, allow_nan=True))
    with pytest.raises(DatasetError) as e:
        load_dataset(table_ds)
    assert "robot_dh.json" in str(e.value)
    for w in words:
        assert w in str(e.value), str(e.value)


def test_yaml_tables_read_like_json(tmp_path):
    doc = json.loads((ROBOTS_DIR / "panda_mdh.json").read_text())
    lines = [f"{k}: {json.dumps(v)}" for k, v in doc.items()]  # JSON values are YAML flow values
    path = tmp_path / "panda.yaml"
    path.write_text("# Franka's table\n" + "\n".join(lines) + "\n")
    a, b = read_table_file(path), read_table_file(ROBOTS_DIR / "panda_mdh.json")
    for c in ("a", "alpha", "d", "theta"):
        np.testing.assert_array_equal(getattr(a.table, c), getattr(b.table, c))
    np.testing.assert_array_equal(a.table.T_flange, b.table.T_flange)
    path.write_text("a: [1, 2\n")
    with pytest.raises(DatasetError, match="panda.yaml.*cannot be read"):
        read_table_file(path)
