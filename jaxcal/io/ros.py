"""A camera pose for ROS: a static transform (ROS 2 launch file and the
`static_transform_publisher` command lines of ROS 2 and ROS 1) and easy_handeye's
calibration YAML, with readers that parse each back (the round-trip tests).

Both the hand-eye command (`jaxcal.io.handeye_results`) and `jaxcal calibrate`
(`jaxcal.report`) write them. A pose is `T_parent_child` (4x4, m): the child
frame's pose in the parent frame, which is what a tf2 static transform from
`parent` to `child` publishes; quaternions are (x, y, z, w).
"""

import re
from pathlib import Path

import numpy as np

from .._npgeom import matrix_to_quaternion, quaternion_to_matrix


def static_transform_args(T_parent_child, parent: str, child: str) -> dict:
    """`static_transform_publisher` arguments for `T_parent_child`: `ros2` (named
    flags), `ros1` (positional `x y z qx qy qz qw parent child`), `parent`, `child`."""
    T = np.asarray(T_parent_child, np.float64)
    v = [f"{x:.12g}" for x in (*T[:3, 3], *matrix_to_quaternion(T[:3, :3]))]
    ros2 = (
        f"--x {v[0]} --y {v[1]} --z {v[2]} --qx {v[3]} --qy {v[4]} --qz {v[5]} --qw {v[6]} "
        f"--frame-id {parent} --child-frame-id {child}"
    )
    return {"ros2": ros2, "ros1": " ".join(v) + f" {parent} {child}", "parent": parent, "child": child}


def write_static_transform(
    folder: Path, name: str, T_parent_child, parent: str, child: str, comment: str
) -> None:
    """`ros_<name>.launch.yaml` (a ROS 2 launch file running one tf2_ros
    static_transform_publisher) and `ros_<name>.txt` (the ROS 2 and ROS 1 command lines)."""
    a = static_transform_args(T_parent_child, parent, child)
    launch = (
        f"# {comment}\n"
        f"# the pose of {child} in {parent}.  Run: ros2 launch ros_{name}.launch.yaml\n"
        "launch:\n"
        "- node:\n"
        "    pkg: tf2_ros\n"
        "    exec: static_transform_publisher\n"
        f"    name: jaxcal_{name}\n"
        f'    args: "{a["ros2"]}"\n'
    )
    (folder / f"ros_{name}.launch.yaml").write_text(launch)
    (folder / f"ros_{name}.txt").write_text(
        f"ros2 run tf2_ros static_transform_publisher {a['ros2']}\n"
        f"rosrun tf2_ros static_transform_publisher {a['ros1']}\n"
    )


def read_static_transform(path) -> tuple[np.ndarray, str, str]:
    """`(T_parent_child, parent, child)` from a `ros_<name>.launch.yaml` or the
    ROS 2 line of `ros_<name>.txt` (the named flags)."""
    text = Path(path).read_text()
    flags = dict(re.findall(r"--([a-z-]+) (\S+)", text))
    t = np.array([float(flags[k]) for k in ("x", "y", "z")])
    q = np.array([float(flags[k]) for k in ("qx", "qy", "qz", "qw")])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = quaternion_to_matrix(q), t
    return T, flags["frame-id"], flags["child-frame-id"].strip('"')


def write_easy_handeye(
    path: Path,
    T_parent_camera,
    *,
    eye_on_hand: bool,
    base_frame: str,
    effector_frame: str,
    camera_frame: str,
    marker_frame: str,
) -> None:
    """easy_handeye's calibration YAML: `eye_on_hand`, the four frames and
    `transformation` (x y z qx qy qz qw): the camera (`tracking_base_frame`)
    in the effector frame when `eye_on_hand`, else in the robot base frame."""
    T = np.asarray(T_parent_camera, np.float64)
    q = matrix_to_quaternion(T[:3, :3])
    lines = [
        f"eye_on_hand: {'true' if eye_on_hand else 'false'}",
        f"robot_base_frame: {base_frame}",
        f"robot_effector_frame: {effector_frame}",
        f"tracking_base_frame: {camera_frame}",
        f"tracking_marker_frame: {marker_frame}",
        "transformation:",
        *(f"  {k}: {v:.12g}" for k, v in zip(("x", "y", "z"), T[:3, 3])),
        *(f"  {k}: {v:.12g}" for k, v in zip(("qx", "qy", "qz", "qw"), q)),
    ]
    path.write_text("\n".join(lines) + "\n")


def read_easy_handeye(path) -> dict:
    """The fields of an easy_handeye calibration YAML (the flat layout
    `write_easy_handeye` writes), with `T` the 4x4 transformation."""
    out, transform = {}, {}
    for line in Path(path).read_text().splitlines():
        key, _, value = line.partition(":")
        if not value.strip():
            continue
        (transform if line.startswith("  ") else out)[key.strip()] = value.strip()
    t = np.array([float(transform[k]) for k in ("x", "y", "z")])
    q = np.array([float(transform[k]) for k in ("qx", "qy", "qz", "qw")])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = quaternion_to_matrix(q), t
    out["eye_on_hand"] = out["eye_on_hand"] == "true"
    out["T"] = T
    return out
