"""The ROS exports of a camera pose (`jaxcal.io.ros`) parse back to the pose."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jaxcal.io.ros import read_easy_handeye, read_static_transform, write_easy_handeye, write_static_transform


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_static_transform_and_easy_handeye_round_trip(tmp_path, seed):
    rng = np.random.default_rng(seed)
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=seed).as_matrix()
    T[:3, 3] = rng.uniform(-2, 2, 3)
    write_static_transform(tmp_path, "cam0", T, "base_link", "cam0_optical", "a test")
    for f in ("ros_cam0.launch.yaml", "ros_cam0.txt"):
        T_back, parent, child = read_static_transform(tmp_path / f)
        np.testing.assert_allclose(T_back, T, atol=1e-11)
        assert (parent, child) == ("base_link", "cam0_optical")
    ros1 = (tmp_path / "ros_cam0.txt").read_text().splitlines()[1].split()
    assert ros1[:2] == ["rosrun", "tf2_ros"] and ros1[-2:] == ["base_link", "cam0_optical"]
    np.testing.assert_allclose([float(x) for x in ros1[3:6]], T[:3, 3], atol=1e-11)
    write_easy_handeye(
        tmp_path / "e.yaml", T, eye_on_hand=True, base_frame="base", effector_frame="tool0",
        camera_frame="cam0_optical", marker_frame="board",
    )  # fmt: skip
    e = read_easy_handeye(tmp_path / "e.yaml")
    np.testing.assert_allclose(e["T"], T, atol=1e-11)
    assert e["eye_on_hand"] and e["robot_effector_frame"] == "tool0" and e["tracking_marker_frame"] == "board"
