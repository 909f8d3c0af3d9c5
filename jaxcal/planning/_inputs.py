"""What `jaxcal plan` reads from the user: a camera file, a target file, a region, a pose.

- Camera: an OpenCV YAML file like the `camera_<name>.yaml` `jaxcal calibrate`
  writes: `camera_matrix` (3x3), `distortion_coefficients` (5, optional),
  `image_width` / `image_height` (or the `--resolution` given), and where the
  camera is: `T_base_cam` or `T_cam_base` for a fixed camera, `T_flange_cam`
  for a camera on the flange; `camera_name` optional.
- Target: a JSON file `{"spec": {TargetSpec fields}, "link": "flange" or
  "world", "T_link_target": 4x4}` (the `target` object of a plan file).
- Region: `x0,y0,z0,x1,y1,z1` (m, base frame).

Every error is a `PlanFileError` naming the file and the field.
"""

from pathlib import Path

import cv2
import numpy as np

from ..errors import DatasetError, PlanFileError
from ..io._schema import Loc, read_json
from ._plan import PlanCamera, PlanTarget, target_from_dict


def _matrix(fs, name: str, path: Path, shape) -> np.ndarray | None:
    node = fs.getNode(name)
    if node.empty():
        return None
    m = node.mat()
    if m is None or m.size != int(np.prod(shape)) or not np.all(np.isfinite(m)):
        raise PlanFileError(
            f"{path}: {name}: expected a {'x'.join(map(str, shape))} matrix of finite numbers"
        )
    return np.asarray(m, np.float64).reshape(shape)


def read_camera(path, flange: str, resolution: tuple[int, int] | None = None) -> PlanCamera:
    """A `PlanCamera` from an OpenCV YAML file (see the module docstring)."""
    path = Path(path)
    if not path.is_file():
        raise PlanFileError(f"{path}: camera file missing")
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except cv2.error as e:
        raise PlanFileError(f"{path}: not an OpenCV YAML/JSON file ({e.msg.strip()})") from None
    try:
        K = _matrix(fs, "camera_matrix", path, (3, 3))
        if K is None:
            raise PlanFileError(f"{path}: missing field 'camera_matrix'")
        dist = _matrix(fs, "distortion_coefficients", path, (5,))
        size = [fs.getNode(k) for k in ("image_width", "image_height")]
        if all(not n.empty() for n in size):
            w, h = (int(n.real()) for n in size)
        elif resolution is not None:
            w, h = resolution
        else:
            raise PlanFileError(
                f"{path}: missing fields 'image_width' and 'image_height' (or pass --resolution)"
            )
        poses = {k: _matrix(fs, k, path, (4, 4)) for k in ("T_base_cam", "T_cam_base", "T_flange_cam")}
        name = fs.getNode("camera_name")
        name = name.string() if not name.empty() and name.isString() else "cam0"
    finally:
        fs.release()
    if poses["T_flange_cam"] is not None:
        mount, T = flange, poses["T_flange_cam"]
    elif poses["T_base_cam"] is not None:
        mount, T = "world", poses["T_base_cam"]
    elif poses["T_cam_base"] is not None:
        mount, T = "world", np.linalg.inv(poses["T_cam_base"])
    else:
        raise PlanFileError(
            f"{path}: no camera pose: give T_base_cam or T_cam_base (fixed), or T_flange_cam (on the arm)"
        )
    R = T[:3, :3]
    if not (
        np.allclose(R.T @ R, np.eye(3), atol=1e-6)
        and np.linalg.det(R) > 0
        and np.allclose(T[3], (0, 0, 0, 1))
    ):
        raise PlanFileError(f"{path}: the camera pose is not a rigid transform")
    if not (K[0, 0] > 0 and K[1, 1] > 0 and w > 0 and h > 0):
        raise PlanFileError(f"{path}: camera_matrix needs fx, fy > 0 and the image size must be positive")
    return PlanCamera(name, int(w), int(h), K, np.zeros(5) if dist is None else dist, mount, T)


def read_target(path) -> PlanTarget:
    """A `PlanTarget` from a JSON file (see the module docstring)."""
    path = Path(path)
    try:
        return target_from_dict(read_json(path, "target file"), Loc(path))
    except DatasetError as e:
        raise PlanFileError(str(e)) from None


def parse_region(text: str) -> tuple[np.ndarray, np.ndarray]:
    """`x0,y0,z0,x1,y1,z1` (m) as the box's `(lo, hi)` corners."""
    try:
        v = np.array([float(x) for x in text.split(",")])
    except ValueError:
        raise PlanFileError(f"--region: expected x0,y0,z0,x1,y1,z1 in metres, got {text!r}") from None
    if v.shape != (6,) or not np.all(np.isfinite(v)):
        raise PlanFileError(f"--region: expected six numbers x0,y0,z0,x1,y1,z1, got {text!r}")
    return np.minimum(v[:3], v[3:]), np.maximum(v[:3], v[3:])


def parse_pose(text: str, joints: int) -> np.ndarray:
    """`q1,q2,...` (rad), one per joint."""
    try:
        q = np.array([float(x) for x in text.split(",")])
    except ValueError:
        raise PlanFileError(
            f"--taught: expected {joints} comma-separated joint values (rad), got {text!r}"
        ) from None
    if q.shape != (joints,) or not np.all(np.isfinite(q)):
        raise PlanFileError(f"--taught: expected {joints} joint values (rad), got {q.size}")
    return q
