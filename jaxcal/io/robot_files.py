"""Files robots read, from a calibration: the UR calibration file and the camera pose for ROS.

**Universal Robots** (`ur_calibration.yaml`): the `kinematics:` file of
Universal_Robots_ROS_Driver / ur_calibration, read by ur_description's
`ur_macro.xacro` (`kinematics_parameters_file`): per joint (`shoulder`,
`upper_arm`, `forearm`, `wrist_1`, `wrist_2`, `wrist_3`) the joint origin
`x y z roll pitch yaw` of `<joint><origin>` in the parent link's frame, every
axis `0 0 1`, no zero offsets, and a `hash:`.

Frame convention. jaxcal's calibrated model has tilted axes and zero offsets,
which that file cannot state; it is re-expressed exactly:

1. Each joint frame is turned so that its axis is z (the smallest rotation
   `A_i` taking z to the calibrated axis) and the zero offset is folded into
   the origin: `T'_i = A_{i-1}^T T_i R(a_i, delta_i) A_i`. The product
   telescopes, so every joint's axis line and the chain's motion are kept.
2. Each frame slides along its own axis (which changes no motion) to
   ur_description's layout, the DH frames with `d_i` in joint i's origin:
   frame i is placed so that the next origin has no y offset in the next
   frame (consecutive axes not parallel, as in the nominal robot), or, for
   parallel axes, so that its own origin has no z offset (UR's `upper_arm`,
   `forearm`), the last so that the flange sits at its origin. For the
   nominal UR5e this gives ur_description's default kinematics.
3. The `shoulder` origin is relative to ur_description's `base_link_inertia`
   (its `base`, DH frame 0): the calibration's base link when the nominal
   joint-1 origin has no rotation (jaxcal's shipped UR URDFs), else that
   link turned by the nominal joint-1 rotation (ur_description's `base_link`,
   turned by pi about z).

The flange: ur_description's `tool0` coincides with `wrist_3_link` (its
`flange` and `tool0` joints compose to the identity) and the file cannot
move it, so `tool0` of the URDF built from the file differs from the
calibrated flange by a constant `T_tool0_flange` (for jaxcal's UR URDFs,
whose flange is DH frame 6: a rotation by the last axis's tilt, a fraction
of a degree, and the flange's sub-millimetre offset off that axis), written into the file as a comment and returned; the
calibrated marker mount, expressed in `tool0`, absorbs it.
Forward kinematics: `FK_file(q) @ T_tool0_flange == FK_calibrated(q)`.

`hash:` is ur_calibration's checksum of the robot's own calibration, which
jaxcal cannot know: the file carries `jaxcal_<digest of its values>`, and
the driver warns that it does not match the robot's (expected: the file
says it was not read from the robot).

**Camera pose for ROS**: the static transform of the camera (eye-to-hand: in
the base frame; eye-in-hand: in the flange frame) as a ROS 2 launch file and
`static_transform_publisher` argument lines, and easy_handeye's YAML, written
by the functions `jaxcal.io.handeye_results` uses for hand-eye results.
"""

import hashlib
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from .._geometry import rpy_to_matrix
from .._kinematics import KinematicModel, rotations_to_rpy
from .._npgeom import pose, rotvec_to_matrix
from . import ros

#: ur_description's joint names and the file's segment names, base to flange.
UR_JOINTS = (
    ("shoulder_pan_joint", "shoulder"),
    ("shoulder_lift_joint", "upper_arm"),
    ("elbow_joint", "forearm"),
    ("wrist_1_joint", "wrist_1"),
    ("wrist_2_joint", "wrist_2"),
    ("wrist_3_joint", "wrist_3"),
)
#: Consecutive axes this close to parallel (sine of the angle) count as parallel.
PARALLEL_SIN = 1e-6


def is_ur(model: KinematicModel) -> bool:
    """Whether the chain has UR's joint layout: six revolute joints named as in ur_description
    (any `tf_prefix`), base to flange."""
    names = tuple(model.joint_names)
    return (
        len(names) == 6
        and all(n.endswith(u) for n, (u, _) in zip(names, UR_JOINTS))
        and all(k == "revolute" for k in model.joint_types)
    )


def _align(a: np.ndarray) -> np.ndarray:
    """The smallest rotation taking z to the unit vector `a`."""
    z = np.array([0.0, 0.0, 1.0])
    w = np.cross(z, a)
    s, c = np.linalg.norm(w), float(z @ a)
    if s < 1e-15:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    return rotvec_to_matrix(w / s * np.arctan2(s, c))


def _tz(s: float) -> np.ndarray:
    return pose(np.eye(3), (0.0, 0.0, s))


def ur_origins(model: KinematicModel, nominal: KinematicModel) -> tuple[np.ndarray, np.ndarray]:
    """The UR file's joint origins (6, 4, 4) and the constant `T_tool0_flange` (see the module docstring)."""
    T = np.asarray(model.T_parent_joint, np.float64)
    axis = np.asarray(model.axis, np.float64)
    axis = axis / np.linalg.norm(axis, axis=1, keepdims=True)
    delta = np.asarray(model.zero_offset, np.float64)
    n = len(T)
    A = [np.eye(3)] + [_align(a) for a in axis]
    E = [pose(A[i].T) @ T[i] @ pose(rotvec_to_matrix(axis[i] * delta[i])) @ pose(A[i + 1]) for i in range(n)]
    F = pose(A[n].T) @ np.asarray(model.T_last_flange, np.float64)
    nom_axis = np.asarray(nominal.axis, np.float64)
    nom_R = np.asarray(nominal.T_parent_joint, np.float64)[:, :3, :3]
    for i in range(n):  # slide frame i along its axis: E_i <- E_i Tz(s), E_{i+1} <- Tz(-s) E_{i+1}
        if i == n - 1:
            s = F[2, 3]
        else:
            ni = nom_R[i + 1] @ nom_axis[i + 1]  # the next axis in frame i (nominal)
            if np.linalg.norm(np.cross(nom_axis[i], ni)) > PARALLEL_SIN:
                Rn, tn = E[i + 1][:3, :3], E[i + 1][:3, 3]
                s = (Rn.T @ tn)[1] / (Rn.T @ np.array([0.0, 0.0, 1.0]))[1]
            else:
                s = -(E[i][:3, :3].T @ E[i][:3, 3])[2]
        E[i] = E[i] @ _tz(s)
        if i == n - 1:
            F = _tz(-s) @ F
        else:
            E[i + 1] = _tz(-s) @ E[i + 1]
    base = nom_R[0]
    if np.abs(base - np.eye(3)).max() > 1e-9:
        E[0] = pose(base.T) @ E[0]
    return np.stack(E), F


def ur_kinematics_text(model: KinematicModel, nominal: KinematicModel) -> tuple[str, np.ndarray]:
    """The UR calibration file's text and `T_tool0_flange` (raises `ValueError` when not `is_ur`)."""
    if not is_ur(model):
        raise ValueError(f"not a UR joint layout: {list(model.joint_names)}")
    E, C = ur_origins(model, nominal)
    body = []
    for (_, seg), Ti in zip(UR_JOINTS, E):
        rpy = rotations_to_rpy(Ti[:3, :3])
        body.append(f"  {seg}:")
        body += [f"    {k}: {float(v)!r}" for k, v in zip(("x", "y", "z"), Ti[:3, 3])]
        body += [f"    {k}: {float(v)!r}" for k, v in zip(("roll", "pitch", "yaw"), rpy)]
    digest = hashlib.sha256("\n".join(body).encode()).hexdigest()[:16]
    angle = np.degrees(np.arccos(np.clip((np.trace(C[:3, :3]) - 1) / 2, -1, 1)))
    head = [
        "# Universal Robots calibration (ur_description kinematics_parameters_file), written by jaxcal",
        "# from a camera calibration: joint origins with every axis z and the zero offsets folded in.",
        "# 'shoulder' is relative to base_link_inertia (DH frame 0). The calibrated flange is tool0 of",
        f"# this file (= wrist_3_link) turned by T_tool0_flange ({angle:.4f} deg); the hash is",
        "# jaxcal's, not the robot's checksum (the driver warns that they differ).",
        f"# T_tool0_flange: {np.round(C, 15).tolist()}",
        "kinematics:",
    ]
    return "\n".join(head + body + [f"  hash: jaxcal_{digest}"]) + "\n", C


def ur_fk(origins, q, T_tool0=None) -> np.ndarray:
    """`T_base_link_inertia_tool0` of the URDF built from UR origins (6, 4, 4) at joint angles `q`."""
    T = np.eye(4)
    for Ei, qi in zip(origins, q):
        c, s = np.cos(qi), np.sin(qi)
        T = T @ Ei @ pose(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]))
    return T if T_tool0 is None else T @ T_tool0


def origin_of(entry: dict) -> np.ndarray:
    """4x4 of a UR file entry `{x, y, z, roll, pitch, yaw}` (a URDF `<origin xyz rpy>`)."""
    R = np.asarray(rpy_to_matrix(jnp.asarray([entry["roll"], entry["pitch"], entry["yaw"]], jnp.float64)))
    return pose(R, [entry["x"], entry["y"], entry["z"]])


# --------------------------------------------------------------------------- the camera for ROS


def camera_transform(result) -> tuple[np.ndarray, str, str]:
    """`(T_parent_camera, parent, camera)`: the camera's pose in the base link (eye-to-hand) or the flange
    link (eye-in-hand), with the frame names of the robot file."""
    links = result.model.link_names
    if result.eye_in_hand:
        return np.asarray(result.T_flange_target[0], np.float64), links[-1], result.camera
    return np.linalg.inv(np.asarray(result.T_cam_base, np.float64)), links[0], result.camera


def write_ros_camera_files(folder: Path, result) -> list[str]:
    """Each camera's pose for ROS (`jaxcal.io.ros`): `ros_<camera>.launch.yaml`,
    `ros_<camera>.txt` and `easy_handeye_<camera>.yaml` in `folder`; the
    further fixed cameras too (in the base link). Returns the file names."""
    T, parent, child = camera_transform(result)
    poses = [(child, parent, T)]
    poses += [
        (c.camera, parent, np.linalg.inv(np.asarray(c.T_cam_base, np.float64)))
        for c in getattr(result, "other_cameras", [])
    ]
    links = result.model.link_names
    marker = result.board if result.eye_in_hand else (result.targets[0] if result.targets else "target")
    comment = f"jaxcal calibration ({result.kind.describe()}, status {result.status})"
    files = []
    for name, frame, T_frame_cam in poses:
        ros.write_static_transform(folder, name, T_frame_cam, frame, name, comment)
        ros.write_easy_handeye(
            folder / f"easy_handeye_{name}.yaml",
            T_frame_cam,
            eye_on_hand=result.eye_in_hand,
            base_frame=links[0],
            effector_frame=links[-1],
            camera_frame=name,
            marker_frame=str(marker),
        )
        files += [f"ros_{name}.launch.yaml", f"ros_{name}.txt", f"easy_handeye_{name}.yaml"]
    return files
