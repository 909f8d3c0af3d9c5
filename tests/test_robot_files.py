"""Files robots read (`jaxcal.io.robot_files`): each export parsed back and compared with the model (1e-9)."""

import io
import shlex
from types import SimpleNamespace

import jax
import numpy as np
import pytest
from ruamel.yaml import YAML

from jaxcal._kinematics import PerturbationScales, forward_kinematics, perturb_model
from jaxcal._npgeom import quaternion_to_matrix
from jaxcal.io.robot_files import is_ur, origin_of, ur_fk, ur_kinematics_text, write_ros_camera_files
from jaxcal.robots import load_robot

#: ur_description's config/ur5e/default_kinematics.yaml (Universal_Robots_ROS2_Description 2.4.5), hash left out.
UR5E_DEFAULT = {
    "shoulder": dict(x=0, y=0, z=0.1625, roll=0, pitch=0, yaw=0),
    "upper_arm": dict(x=0, y=0, z=0, roll=1.570796327, pitch=0, yaw=0),
    "forearm": dict(x=-0.425, y=0, z=0, roll=0, pitch=0, yaw=0),
    "wrist_1": dict(x=-0.3922, y=0, z=0.1333, roll=0, pitch=0, yaw=0),
    "wrist_2": dict(x=0, y=-0.0997, z=-2.044881182297852e-11, roll=1.570796327, pitch=0, yaw=0),
    "wrist_3": dict(
        x=0, y=0.09959999999999999, z=-2.042830148012698e-11, roll=1.570796326589793, pitch=np.pi, yaw=np.pi
    ),
}
SEGMENTS = tuple(UR5E_DEFAULT)


def _parse(text: str) -> dict:
    return YAML(typ="safe").load(io.StringIO(text))


def test_nominal_ur5e_gives_ur_descriptions_default_kinematics():
    m = load_robot("ur5e")
    assert is_ur(m) and not is_ur(load_robot("panda"))
    text, C = ur_kinematics_text(m, m)
    kin = _parse(text)["kinematics"]
    assert kin["hash"].startswith("jaxcal_")
    for seg in SEGMENTS:  # the default file rounds pi/2 to 1e-9 and carries 2e-11 m round-off
        np.testing.assert_allclose(origin_of(kin[seg]), origin_of(UR5E_DEFAULT[seg]), atol=1e-9, err_msg=seg)
    np.testing.assert_allclose(C, np.eye(4), atol=1e-15)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_ur_file_reproduces_the_calibrated_fk(seed):
    """The URDF built from the written file (origins x y z roll pitch yaw, axes z, no offsets) times the
    constant T_tool0_flange equals the calibrated model's FK (tilted axes, zero offsets) to 1e-9."""
    nominal = load_robot("ur5e")
    model = perturb_model(nominal, jax.random.key(seed), PerturbationScales())
    assert np.abs(np.asarray(model.axis) - np.asarray(nominal.axis)).max() > 1e-4  # axes do tilt
    text, C = ur_kinematics_text(model, nominal)
    kin = _parse(text)["kinematics"]
    E = np.stack([origin_of(kin[s]) for s in SEGMENTS])
    written_C = np.array(eval(text.split("# T_tool0_flange: ")[1].splitlines()[0]))  # the comment line
    np.testing.assert_allclose(written_C, C, atol=1e-15)
    # The constant tool0 -> flange: the last axis's tilt (a rotation, and the flange's offset off that axis).
    assert np.degrees(np.arccos((np.trace(C[:3, :3]) - 1) / 2)) < 1.0 and np.abs(C[:3, 3]).max() < 1e-3
    for q in np.random.default_rng(seed).uniform(-np.pi, np.pi, (20, 6)):
        want = np.asarray(forward_kinematics(model, q)[-1])
        np.testing.assert_allclose(ur_fk(E, q, C), want, atol=1e-9)
    # Close to the nominal file: millimetres and tenths of a degree, not a different layout.
    nom = _parse(ur_kinematics_text(nominal, nominal)[0])["kinematics"]
    for s in SEGMENTS:
        assert np.abs(origin_of(kin[s])[:3, 3] - origin_of(nom[s])[:3, 3]).max() < 0.01, s


def _transform(x, y, z, qx, qy, qz, qw) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = quaternion_to_matrix(np.array([qx, qy, qz, qw], np.float64))
    T[:3, 3] = x, y, z
    return T


def _fake_result(eye_in_hand: bool):
    rng = np.random.default_rng(3)
    A = np.eye(4)
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    A[:3, :3] = R * np.sign(np.linalg.det(R))
    A[:3, 3] = rng.normal(size=3)
    return SimpleNamespace(
        model=SimpleNamespace(link_names=["base_link", "l1", "flange"]),
        eye_in_hand=eye_in_hand,
        T_cam_base=A,
        T_flange_target=A[None],
        camera="cam0",
        kind=SimpleNamespace(describe=lambda: "test"),
        status="ok",
        board="board0",
        targets=["plate0"],
    )


@pytest.mark.parametrize("eye_in_hand", [False, True])
def test_camera_pose_for_ros(tmp_path, eye_in_hand):
    r = _fake_result(eye_in_hand)
    want = r.T_cam_base if eye_in_hand else np.linalg.inv(r.T_cam_base)
    parent = "flange" if eye_in_hand else "base_link"
    files = write_ros_camera_files(tmp_path, r)
    assert files == ["ros_cam0.launch.yaml", "ros_cam0.txt", "easy_handeye_cam0.yaml"]
    launch = _parse((tmp_path / "ros_cam0.launch.yaml").read_text())["launch"][0]["node"]
    assert (launch["pkg"], launch["exec"]) == ("tf2_ros", "static_transform_publisher")
    a = shlex.split(launch["args"])
    named = dict(zip(a[::2], a[1::2]))
    assert (named["--frame-id"], named["--child-frame-id"]) == (parent, "cam0")
    T = _transform(*(float(named[f"--{k}"]) for k in ("x", "y", "z", "qx", "qy", "qz", "qw")))
    np.testing.assert_allclose(T, want, atol=1e-9)
    ros2, ros1 = (tmp_path / "ros_cam0.txt").read_text().splitlines()
    assert ros2.startswith("ros2 run tf2_ros static_transform_publisher --x ")
    v = ros1.split()[3:]
    assert v[7:] == [parent, "cam0"]
    np.testing.assert_allclose(_transform(*map(float, v[:7])), want, atol=1e-9)
    e = _parse((tmp_path / "easy_handeye_cam0.yaml").read_text())
    assert e["eye_on_hand"] is eye_in_hand
    assert (e["robot_base_frame"], e["robot_effector_frame"], e["tracking_base_frame"]) == (
        "base_link",
        "flange",
        "cam0",
    )
    assert e["tracking_marker_frame"] == ("board0" if eye_in_hand else "plate0")
    t = e["transformation"]
    np.testing.assert_allclose(
        _transform(*(t[k] for k in ("x", "y", "z", "qx", "qy", "qz", "qw"))), want, atol=1e-9
    )
