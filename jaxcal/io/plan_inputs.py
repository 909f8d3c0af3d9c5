"""What `jaxcal plan` reads from the user: a camera file, a target file, a region, a pose.

- Camera: a YAML file: OpenCV's (`%YAML:1.0`, `!!opencv-matrix`, like the
  `camera_<name>.yaml` `jaxcal calibrate` writes) or plain YAML, where a
  matrix is a list of rows or ROS camera_info's `{rows, cols, data}`:
  `camera_matrix` (3x3), `distortion_coefficients` (5, optional),
  `image_width` / `image_height` (or the `--resolution` given), and where the
  camera is, one of: `T_base_cam` or `T_cam_base` for a fixed camera,
  `T_flange_cam` for a camera on the flange; `camera_name` optional.
- Target: a JSON file `{"spec": {TargetSpec fields}, "link": "flange" or
  "world", "T_link_target": 4x4}` (the `target` object of a plan file).
- Region: `x0,y0,z0,x1,y1,z1` (m, base frame).

Every error is a `PlanFileError` naming the file and the field.
"""

from pathlib import Path

import cv2
import numpy as np

from ..errors import DatasetError, PlanFileError
from ._schema import Loc, file_name, load_yaml, read_json
from .plan import MAX_PLACEMENT_M, PlanCamera, PlanTarget, check_placement, target_from_dict

#: The camera file's fields `read_camera` reads.
CAMERA_FIELDS = (
    "camera_matrix",
    "distortion_coefficients",
    "image_width",
    "image_height",
    "T_base_cam",
    "T_cam_base",
    "T_flange_cam",
    "camera_name",
)


def _node(node):
    """An OpenCV `FileNode` as plain Python: numbers, strings, lists, dicts, arrays."""
    if node.isInt() or node.isReal():
        return node.real()
    if node.isString():
        return node.string()
    if node.isSeq():
        return [_node(node.at(i)) for i in range(node.size())]
    if node.isMap():
        if {"rows", "cols", "dt", "data"} <= set(node.keys()):
            return node.mat()
        return {k: _node(node.getNode(k)) for k in node.keys()}
    return None


def _read_fields(path: Path) -> dict:
    """The camera file's top-level fields: OpenCV `FileStorage` YAML (`%YAML:1.0`,
    `!!opencv-matrix`) or JSON, else plain YAML (nested lists, or ROS camera_info's
    `{rows, cols, data}`)."""
    text = path.read_text(errors="replace")
    if text.lstrip().startswith("%YAML") or path.suffix.lower() == ".json":
        try:
            fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
            try:
                root = fs.root()
                return {k: _node(root.getNode(k)) for k in root.keys()}
            finally:
                fs.release()
        except (cv2.error, SystemError) as e:
            why = e.msg.strip() if isinstance(e, cv2.error) else "unreadable"
            raise PlanFileError(f"{path}: not a camera file OpenCV can read ({why})") from None
    from ruamel.yaml import YAMLError

    try:
        fields = load_yaml(text)
    except (YAMLError, ValueError) as e:
        raise PlanFileError(f"{path}: not valid YAML ({str(e).splitlines()[0]})") from None
    if not isinstance(fields, dict):
        raise PlanFileError(
            f"{path}: expected YAML fields ({', '.join(CAMERA_FIELDS)}), got {type(fields).__name__}"
        )
    return fields


def _matrix(fields: dict, name: str, path: Path, shape: tuple[int, ...]) -> np.ndarray | None:
    """Field `name` as a float64 array of exactly `shape` (a vector: any layout of its
    values), from nested lists, an OpenCV matrix or ROS's `{rows, cols, data}`."""
    value = fields.get(name)
    if value is None:
        return None
    want = "x".join(map(str, shape))
    try:
        if isinstance(value, dict) and {"rows", "cols", "data"} <= set(value):
            m = np.asarray(value["data"], np.float64).reshape(int(value["rows"]), int(value["cols"]))
        else:
            m = np.asarray(value, np.float64)
    except (TypeError, ValueError):
        raise PlanFileError(f"{path}: field {name!r}: expected a {want} matrix of numbers") from None
    if len(shape) == 1:
        m = m.reshape(-1)
        if name == "distortion_coefficients" and m.size == 4:
            m = np.append(m, 0.0)  # k1 k2 p1 p2, k3 = 0
        if m.size != shape[0]:
            raise PlanFileError(
                f"{path}: field {name!r}: expected {shape[0]} numbers (k1 k2 p1 p2 k3; or 4 with k3 = 0), "
                f"got {m.size}"
            )
    if m.shape != shape:
        raise PlanFileError(f"{path}: field {name!r}: expected a {want} matrix, got shape {m.shape}")
    if not np.all(np.isfinite(m)):
        raise PlanFileError(f"{path}: field {name!r}: not finite: {m.tolist()}")
    return m


def _pixels(fields: dict, name: str, path: Path) -> int | None:
    value = fields.get(name)
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not float(value).is_integer():
        raise PlanFileError(f"{path}: field {name!r}: expected a whole number of pixels, got {value!r}")
    if not 1 <= value <= 65535:
        raise PlanFileError(f"{path}: field {name!r}: expected 1 to 65535 pixels, got {value!r}")
    return int(value)


def read_camera(path, flange: str, resolution: tuple[int, int] | None = None) -> PlanCamera:
    """A `PlanCamera` from a camera file (see the module docstring); every field
    checked, a `PlanFileError` naming the file and the field."""
    path = Path(path)
    if not path.is_file():
        raise PlanFileError(f"{path}: camera file missing")
    fields = _read_fields(path)
    K = _matrix(fields, "camera_matrix", path, (3, 3))
    if K is None:
        raise PlanFileError(
            f"{path}: missing field 'camera_matrix' (fields found: {', '.join(map(str, fields))})"
        )
    if not (K[0, 0] > 0 and K[1, 1] > 0 and np.allclose(K[2], (0, 0, 1), atol=1e-9) and K[1, 0] == 0):
        raise PlanFileError(
            f"{path}: field 'camera_matrix': expected a pinhole camera matrix (fx, fy > 0, bottom row "
            f"[0, 0, 1]), got {K.tolist()}"
        )
    dist = _matrix(fields, "distortion_coefficients", path, (5,))
    w, h = _pixels(fields, "image_width", path), _pixels(fields, "image_height", path)
    if w is None or h is None:
        if resolution is None:
            raise PlanFileError(
                f"{path}: missing fields 'image_width' and 'image_height' (or set resolution: --config resolution=WxH)"
            )
        w, h = resolution
    poses = {k: _matrix(fields, k, path, (4, 4)) for k in ("T_base_cam", "T_cam_base", "T_flange_cam")}
    given = [k for k, v in poses.items() if v is not None]
    if len(given) > 1:
        raise PlanFileError(
            f"{path}: fields {' and '.join(map(repr, given))}: give one camera pose: T_base_cam or T_cam_base "
            "(a fixed camera), or T_flange_cam (a camera on the arm)"
        )
    if not given:
        raise PlanFileError(
            f"{path}: no camera pose: give T_base_cam or T_cam_base (fixed), or T_flange_cam (on the arm) "
            f"(fields found: {', '.join(map(str, fields))})"
        )
    T = poses[given[0]]
    R = T[:3, :3]
    if not (
        np.allclose(R.T @ R, np.eye(3), atol=1e-6)
        and np.linalg.det(R) > 0
        and np.allclose(T[3], (0, 0, 0, 1))
    ):
        raise PlanFileError(
            f"{path}: field {given[0]!r}: not a rigid transform (rotation and [0, 0, 0, 1] last row)"
        )
    check_placement(T, f"{path}: field {given[0]!r}")
    mount = flange if given[0] == "T_flange_cam" else "world"
    if given[0] == "T_cam_base":
        T = np.linalg.inv(T)
    try:
        name = file_name(fields.get("camera_name", "cam0"), f"{path}: field 'camera_name'")
    except DatasetError as e:
        raise PlanFileError(str(e)) from None
    return PlanCamera(name, w, h, K, np.zeros(5) if dist is None else dist, mount, T)


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
    if np.max(np.abs(v)) > MAX_PLACEMENT_M:
        raise PlanFileError(
            f"--region: {text!r} reaches {np.max(np.abs(v)):.0f} m; it is in metres (millimetres?)"
        )
    return np.minimum(v[:3], v[3:]), np.maximum(v[:3], v[3:])


def parse_pose(text: str, joints: int) -> np.ndarray:
    """`q1,q2,...` (rad), one per joint."""
    try:
        q = np.array([float(x) for x in text.split(",")])
    except ValueError:
        raise PlanFileError(
            f"taught: expected {joints} comma-separated joint values (rad), got {text!r}"
        ) from None
    if q.shape != (joints,) or not np.all(np.isfinite(q)):
        raise PlanFileError(f"taught: expected {joints} joint values (rad), got {q.size}")
    return q
