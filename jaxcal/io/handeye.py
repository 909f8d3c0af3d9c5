"""The hand-eye capture format: images per camera, one robot pose per frame (see `docs/handeye.md`).

```
CAPTURE/
  handeye.json              arrangement, pose format and units, cameras, target
  poses.csv                 frame,<pose columns>: the flange pose in the base frame per frame
  images/<camera>/<frame>.png   (or .jpg, .jpeg, .bmp, .tif, .tiff)
  truth.json                synthetic captures only (`jaxcal simulate-handeye`)
```

Pose columns, by `poses.format` (the header names the columns, in any order):

- `matrix`: `m00,m01,...,m33`, the 4x4 `T_base_ee` row-major;
- `xyz_quat`: `x,y,z,qx,qy,qz,qw` (unit quaternion; its order is the header's);
- `xyz_rpy`: `x,y,z,roll,pitch,yaw`, ROS/URDF fixed-axis angles,
  $R = R_z(yaw) R_y(pitch) R_x(roll)$;
- `xyz_rotvec`: `x,y,z,rx,ry,rz`, a rotation vector (axis times angle, as
  Universal Robots report poses).

`poses.translation_unit` (`m` or `mm`) is required, and `poses.rotation_unit`
(`rad` or `deg`) for `xyz_rpy` and `xyz_rotvec`. `load_hand_eye_capture`
checks every field and raises `DatasetError` naming the file, line, field and
value at fault; it modifies nothing.
"""

import csv
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .._npgeom import matrix_to_quaternion, quaternion_to_matrix, rotvec_to_matrix
from ..errors import DatasetError
from ..markers import TargetSpec
from . import _schema as sc
from ._files import resolved
from ._images import image_size

SCHEMA = "jaxcal.handeye"
SCHEMA_VERSION = 1
ARRANGEMENTS = ("eye_in_hand", "eye_to_hand")
POSE_COLUMNS = {
    "matrix": tuple(f"m{i}{j}" for i in range(4) for j in range(4)),
    "xyz_quat": ("x", "y", "z", "qx", "qy", "qz", "qw"),
    "xyz_rpy": ("x", "y", "z", "roll", "pitch", "yaw"),
    "xyz_rotvec": ("x", "y", "z", "rx", "ry", "rz"),
}
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
#: `handeye.json`'s fields, its `poses`' and a camera's.
FIELDS = ("schema", "schema_version", "description", "arrangement", "frames", "poses", "cameras", "target")
POSES_FIELDS = ("file", "format", "translation_unit", "rotation_unit")
CAMERA_FIELDS = ("name", "width", "height", "K", "distortion", "frame_id")
#: A translation above this many metres is taken for a unit mistake.
MAX_TRANSLATION_M = 20.0
#: Every frame's flange nearer the base than this (m): no arm's poses, a unit misread (metres
#: declared millimetres) or a pose of the wrong frame.
MIN_REACH_M = 0.02


@dataclass(frozen=True, eq=False)
class HandEyeCamera:
    """A camera of a capture: `K` (3, 3) px or `None` (self-calibrated from the
    capture), OpenCV distortion `dist`, and its frame name for ROS outputs."""

    name: str
    width: int
    height: int
    K: np.ndarray | None
    dist: np.ndarray
    frame_id: str

    def to_dict(self) -> dict:
        return {
            "name": self.name,
            "width": self.width,
            "height": self.height,
            "K": None if self.K is None else np.asarray(self.K).tolist(),
            "distortion": np.asarray(self.dist).tolist(),
            "frame_id": self.frame_id,
        }


@dataclass(frozen=True, eq=False)
class HandEyeCapture:
    """A hand-eye capture read from disk.

    - `eye_in_hand`: the cameras ride on the flange (else they are fixed and the
      target rides on the flange).
    - `frames`: the frame names (`poses.csv`'s `frame` column), in file order.
    - `T_base_ee`: `(frames, 4, 4)` flange poses in the base frame, metres.
    - `images`: per camera, per frame, the image path.
    - `base_frame`, `ee_frame`, `target_frame`: frame names for the ROS outputs.
    - `truth`: the parsed `truth.json` of a synthetic capture, else `None`.
    - `pose_format`: the pose table's `poses.format` (`POSE_COLUMNS`).
    - `notes`: remarks from reading it (poses repeated exactly, images no pose row names).
    - `rotations`: `(frames, 3)` the rotation columns as written, in radians, for `xyz_rpy` and
      `xyz_rotvec` (read otherwise when the poses and images disagree); else None.
    """

    root: Path
    eye_in_hand: bool
    cameras: tuple[HandEyeCamera, ...]
    target: TargetSpec
    frames: tuple[str, ...]
    T_base_ee: np.ndarray
    images: tuple[tuple[Path, ...], ...]
    base_frame: str = "base_link"
    ee_frame: str = "tool0"
    target_frame: str = "calibration_target"
    description: str = ""
    truth: dict | None = field(default=None)
    pose_format: str = "matrix"
    notes: tuple[str, ...] = ()
    rotations: np.ndarray | None = field(default=None, repr=False)

    @property
    def arrangement(self) -> str:
        return "eye_in_hand" if self.eye_in_hand else "eye_to_hand"


# --------------------------------------------------------------------------- rotations (NumPy)


def rpy_to_matrix(rpy: np.ndarray) -> np.ndarray:
    """$R_z(yaw) R_y(pitch) R_x(roll)$ (ROS/URDF fixed axes), `(..., 3)` rad -> `(..., 3, 3)`."""
    r, p, y = np.moveaxis(np.asarray(rpy, np.float64), -1, 0)
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    return np.stack(
        [
            np.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], -1),
            np.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], -1),
            np.stack([-sp, cp * sr, cp * cr], -1),
        ],
        -2,
    )


def matrix_to_rpy(R: np.ndarray) -> np.ndarray:
    """Inverse of `rpy_to_matrix` (pitch in [-pi/2, pi/2])."""
    R = np.asarray(R, np.float64)
    pitch = np.arcsin(np.clip(-R[..., 2, 0], -1.0, 1.0))
    roll = np.arctan2(R[..., 2, 1], R[..., 2, 2])
    yaw = np.arctan2(R[..., 1, 0], R[..., 0, 0])
    return np.stack([roll, pitch, yaw], -1)


def matrix_to_rotvec(R: np.ndarray) -> np.ndarray:
    """Rotation vector (rad) of a rotation matrix (3, 3), through its quaternion."""
    q = matrix_to_quaternion(R)
    s = np.linalg.norm(q[:3])
    if s < 1e-12:
        return 2.0 * q[:3] / q[3]
    return 2.0 * math.atan2(s, q[3]) * q[:3] / s


# --------------------------------------------------------------------------- reading


def _require(d, key: str, where: str):
    if not isinstance(d, dict) or key not in d:
        raise DatasetError(f"{where}: missing field {key!r}")
    return d[key]


def _choice(d: dict, key: str, allowed, where: str) -> str:
    value = _require(d, key, where)
    if value not in allowed:
        raise DatasetError(f"{where}: field {key!r} must be one of {list(allowed)}, got {value!r}")
    return value


def _positive_int(d: dict, key: str, where: str) -> int:
    value = _require(d, key, where)
    if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
        raise DatasetError(f"{where}: field {key!r} must be a positive integer, got {value!r}")
    return value


def _cameras(meta: dict, where: str) -> tuple[HandEyeCamera, ...]:
    cams = _require(meta, "cameras", where)
    if not isinstance(cams, list) or not cams:
        raise DatasetError(f"{where}: field 'cameras' must be a non-empty list")
    out = []
    for i, c in enumerate(cams):
        w = f"{where}: cameras[{i}]"
        name = sc.file_name(
            _require(c, "name", w), f"{w}: field 'name'"
        )  # images/<name>/, camera_<name>.yaml
        w = f"{where}: camera {name!r}"
        width, height = _positive_int(c, "width", w), _positive_int(c, "height", w)
        # The camera block's checks are the dataset's (`jaxcal.io._schema`), named as this file names them.
        K = c.get("K")
        K = (
            None
            if K is None
            else sc.camera_matrix(K, sc.Loc(where, f"camera {name!r} field 'K'"), width, height)
        )
        dist = sc.distortion(
            c.get("distortion", [0.0] * 5), sc.Loc(where, f"camera {name!r} field 'distortion'")
        )
        frame_id = c.get("frame_id", f"{name}_optical_frame")
        if not isinstance(frame_id, str) or not frame_id:
            raise DatasetError(f"{w} field 'frame_id': must be a non-empty string, got {frame_id!r}")
        out.append(HandEyeCamera(name, width, height, K, dist, frame_id))
    names = [c.name for c in out]
    if len(set(names)) != len(names):
        raise DatasetError(f"{where}: camera names are not unique: {names}")
    return tuple(out)


def _rotation_error(R: np.ndarray) -> np.ndarray:
    return np.max(np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)), axis=(-1, -2))


def _check_rotation_unit(path, where: str, V: np.ndarray, fmt: str, unit_r: str) -> None:
    """Refuses `poses.rotation_unit` where the rotations `V` (Euler angles or rotation vectors, as
    written) say otherwise: degrees that never pass 2 pi turn the flange too little; Euler angles
    within +-pi and a rotation vector's length within pi are radians, and beyond a turn they are
    degrees declared radians."""
    turn = float(np.max(np.abs(V))) if fmt == "xyz_rpy" else float(np.max(np.linalg.norm(V, axis=1)))
    if unit_r == "deg" and turn <= 2.0 * math.pi:
        raise DatasetError(
            f"{path}: no rotation value exceeds {turn:.3g}: as degrees the flange barely turns, as radians "
            f"(at most 2 pi) they are an arm's; is {where} field 'rotation_unit' ('deg') right (radians declared "
            "degrees?)"
        )
    if unit_r == "rad" and turn > 2.0 * math.pi:
        raise DatasetError(
            f"{path}: a rotation value reaches {turn:.4g}, beyond a turn (2 pi) as radians; as degrees it "
            f"is an arm's: is {where} field 'rotation_unit' ('rad') right (degrees declared radians?)"
        )


def _read_poses(path: Path, spec: dict, where: str) -> tuple[tuple[str, ...], np.ndarray, np.ndarray | None]:
    """`(frames, T_base_ee (frames, 4, 4) in metres, the rotation columns as written in radians
    (Euler angles or rotation vectors; None for matrices and quaternions))` from the pose table."""
    fmt = _choice(spec, "format", POSE_COLUMNS, where)
    unit_t = _choice(spec, "translation_unit", ("m", "mm"), where)
    unit_r = (
        _choice(spec, "rotation_unit", ("rad", "deg"), where) if fmt in ("xyz_rpy", "xyz_rotvec") else "rad"
    )
    frames, V = _pose_table(path, POSE_COLUMNS[fmt], fmt, where)
    scale_r = math.pi / 180.0 if unit_r == "deg" else 1.0
    T = _poses(path, frames, V, fmt, 1e-3 if unit_t == "mm" else 1.0, scale_r)
    if fmt in ("xyz_rpy", "xyz_rotvec"):
        _check_rotation_unit(path, where, V[:, 3:], fmt, unit_r)
    err = _rotation_error(T[:, :3, :3])
    bad = np.flatnonzero((err > 1e-5) | (np.linalg.det(T[:, :3, :3]) < 0))
    if bad.size:
        i = bad[0]
        raise DatasetError(
            f"{path} line {i + 2} (frame {frames[i]}): the rotation is not a rotation matrix "
            f"(max |R^T R - I| = {err[i]:.3g}, det = {np.linalg.det(T[i, :3, :3]):.6g})"
        )
    far = np.flatnonzero(np.linalg.norm(T[:, :3, 3], axis=1) > MAX_TRANSLATION_M)
    if far.size:
        i = far[0]
        raise DatasetError(
            f"{path} line {i + 2} (frame {frames[i]}): translation {np.linalg.norm(T[i, :3, 3]):.1f} m from the "
            f"base; is {where} field 'translation_unit' ({unit_t!r}) right?"
        )
    reach = float(np.max(np.linalg.norm(T[:, :3, 3], axis=1)))
    if reach < MIN_REACH_M:
        raise DatasetError(
            f"{path}: every frame's flange lies within {1e3 * reach:.3g} mm of the base, no arm's reach; is {where} "
            f"field 'translation_unit' ({unit_t!r}) right (metres declared millimetres?)"
        )
    return tuple(frames), T, (V[:, 3:] * scale_r if fmt in ("xyz_rpy", "xyz_rotvec") else None)


def _pose_table(path: Path, want: tuple, fmt: str, where: str) -> tuple[list[str], np.ndarray]:
    """The pose file's frame names and its `want` columns as numbers `(frames, len(want))`, every
    line checked (its fields, numbers and finite; each frame named once)."""
    if not path.is_file():
        raise DatasetError(f"{path}: pose file missing (named by {where} field 'file')")
    try:  # a byte-order mark is no part of the header (spreadsheets write one)
        with open(path, newline="", encoding="utf-8-sig") as f:
            rows = [r for r in csv.reader(f) if r and any(c.strip() for c in r)]
    except UnicodeDecodeError as e:
        raise DatasetError(f"{path}: not UTF-8 text ({e.reason} at byte {e.start})") from None
    if not rows:
        raise DatasetError(f"{path}: empty; expected a header 'frame,{','.join(want)}'")
    header = [h.strip() for h in rows[0]]
    if header[:1] != ["frame"] or sorted(header[1:]) != sorted(want):
        raise DatasetError(
            f"{path} line 1: header {','.join(header)!r} does not match format {fmt!r}: expected 'frame' "
            f"then the columns {','.join(want)} (in any order)"
        )
    col = [header.index(c) for c in want]
    frames, values = [], []
    for n, row in enumerate(rows[1:], start=2):
        if len(row) != len(header):
            raise DatasetError(f"{path} line {n}: {len(row)} fields, the header has {len(header)}")
        name = row[0].strip()
        if not name or "/" in name:
            raise DatasetError(f"{path} line {n}: field 'frame' must be a file stem, got {row[0]!r}")
        v = []
        for c in col:
            try:
                x = float(row[c])
            except ValueError:
                raise DatasetError(
                    f"{path} line {n} (frame {name}): field {header[c]!r} = {row[c]!r} is not a number"
                ) from None
            if not math.isfinite(x):
                raise DatasetError(
                    f"{path} line {n} (frame {name}): field {header[c]!r} is {row[c]} (NaN/inf not allowed)"
                )
            v.append(x)
        frames.append(name)
        values.append(v)
    if not frames:
        raise DatasetError(f"{path}: no poses after the header")
    dup = sorted({f for f in frames if frames.count(f) > 1})
    if dup:
        raise DatasetError(f"{path}: frame names repeat: {dup[:10]}")
    return frames, np.asarray(values)


def _poses(
    path: Path, frames: list[str], V: np.ndarray, fmt: str, scale_t: float, scale_r: float
) -> np.ndarray:
    """`(frames, 4, 4)` poses from the pose table's columns `V` in format `fmt`, translations times
    `scale_t`, angles times `scale_r`; a matrix's bottom row and a quaternion's norm checked."""
    T = np.broadcast_to(np.eye(4), (len(V), 4, 4)).copy()
    if fmt == "matrix":
        M = V.reshape(-1, 4, 4)
        bottom = np.max(np.abs(M[:, 3] - [0.0, 0.0, 0.0, 1.0]), axis=-1)
        bad = np.flatnonzero(bottom > 1e-6)
        if bad.size:
            i = bad[0]
            # Written by columns: the translation in the bottom row, the last column 0, 0, 0, 1.
            by_columns = np.allclose(M[:, :3, 3], 0.0, atol=1e-6) and np.allclose(M[:, 3, 3], 1.0, atol=1e-6)
            raise DatasetError(
                f"{path} line {i + 2} (frame {frames[i]}): bottom row {M[i, 3].tolist()}, not [0, 0, 0, 1]"
                + (
                    "; every matrix holds its translation in the bottom row and 0, 0, 0, 1 in the last column: "
                    "written by columns (column-major); write each row by row, m00 m01 m02 m03 m10 ... m33"
                    if by_columns
                    else ""
                )
            )
        T[:, :3, :3], T[:, :3, 3] = M[:, :3, :3], M[:, :3, 3] * scale_t
    else:
        T[:, :3, 3] = V[:, :3] * scale_t
        if fmt == "xyz_quat":
            norm = np.linalg.norm(V[:, 3:], axis=1)
            bad = np.flatnonzero(np.abs(norm - 1.0) > 1e-3)
            if bad.size:
                i = bad[0]
                raise DatasetError(
                    f"{path} line {i + 2} (frame {frames[i]}): quaternion norm {norm[i]:.6g}, not 1 "
                    "(columns qx, qy, qz, qw)"
                )
            T[:, :3, :3] = quaternion_to_matrix(V[:, 3:] / norm[:, None])
        elif fmt == "xyz_rpy":
            T[:, :3, :3] = rpy_to_matrix(V[:, 3:] * scale_r)
        else:
            T[:, :3, :3] = rotvec_to_matrix(V[:, 3:] * scale_r)
    return T


def repeated_poses(T: np.ndarray) -> dict[int, int]:
    """`{frame: earlier frame}` for each frame whose pose equals an earlier frame's exactly: a robot
    that came back to a commanded pose, or a logger that wrote the previous pose again."""
    first, out = {}, {}
    for i, row in enumerate(np.ascontiguousarray(T).reshape(len(T), -1)):
        if (key := row.tobytes()) in first:
            out[i] = first[key]
        else:
            first[key] = i
    return out


def _repeat_note(path: Path, frames, T: np.ndarray) -> tuple[str, ...]:
    if not (same := repeated_poses(T)):
        return ()
    pairs = ", ".join(f"{frames[i]} = {frames[j]}" for i, j in list(same.items())[:5])
    more = f" and {len(same) - 5} more" if len(same) > 5 else ""
    return (
        f"{path}: {len(same)} frame(s) repeat an earlier frame's pose exactly: {pairs}{more} (a robot that came "
        "back to a commanded pose, or a logger that wrote the previous pose again: the views will tell)",
    )


def _images(root: Path, cameras, frames) -> tuple[tuple[tuple[Path, ...], ...], tuple[str, ...]]:
    """Per camera, per frame of `poses.csv`, its image; and a note per camera whose folder holds
    images of frames `poses.csv` does not name (not used: a pose row lost, or a stray file)."""
    out, notes, named = [], [], set(frames)
    for cam in cameras:
        folder = root / "images" / cam.name
        if not folder.is_dir():
            raise DatasetError(f"{folder}: image folder of camera {cam.name!r} missing")
        found = {}
        for p in folder.iterdir():
            if p.suffix.lower() in IMAGE_SUFFIXES:
                if p.stem in found:
                    raise DatasetError(
                        f"{folder}: two images for frame {p.stem!r}: {found[p.stem].name}, {p.name}"
                    )
                found[p.stem] = p
        missing = [f for f in frames if f not in found]
        if missing:
            there = [found[k].name for k in sorted(found)[:5]]
            holds = ", ".join(there) + (" ..." if len(found) > 5 else "") if there else "no image"
            raise DatasetError(
                f"{folder}: no image for frame(s) {missing[:10]} of poses.csv "
                f"(expected {folder}/<frame>{{{','.join(IMAGE_SUFFIXES)}}}; the folder holds {holds})"
            )
        out.append(tuple(found[f] for f in frames))
        _sizes(cam, out[-1])
        if extra := sorted(found[k].name for k in found if k not in named):
            shown_extra = ", ".join(extra[:5]) + (f" and {len(extra) - 5} more" if len(extra) > 5 else "")
            notes.append(
                f"{folder}: {len(extra)} image(s) not used, no row of poses.csv names their frame: {shown_extra} "
                "(a pose row missing, or files that do not belong to this capture?)"
            )
    return tuple(out), tuple(notes)


def _sizes(cam, paths) -> None:
    """Every image of `cam` of the size `handeye.json` gives it (its K is for that size)."""
    sizes = [image_size(path) for path in paths]
    wrong = [(path, size) for path, size in zip(paths, sizes) if size != (cam.width, cam.height)]
    if wrong:
        (path, (w, h)), n = wrong[0], len(wrong)
        every = (
            "; every image: a K calibrated at another resolution? give the images' size and K for it"
            if n == len(paths)
            else ""
        )
        raise DatasetError(
            f"{path}: image is {w}x{h} pixels, handeye.json gives camera {cam.name!r} {cam.width}x{cam.height} "
            f"(fields 'width', 'height'); {n} of {len(paths)} images differ{every}"
        )


def _name(d: dict, key: str, default: str, where: str) -> str:
    value = d.get(key, default)
    if not isinstance(value, str) or not value:
        raise DatasetError(f"{where}: field {key!r} must be a non-empty string, got {value!r}")
    return value


def load_hand_eye_capture(path) -> HandEyeCapture:
    """Read and check the hand-eye capture in directory `path` (nothing is modified).

    **Raises:** `DatasetError` naming the file, line, field and value at fault.
    """
    root = Path(path)
    if not root.is_dir():
        resolved(root)  # a loop of symbolic links is named as one
        raise DatasetError(f"{root}: capture directory not found")
    meta_path = root / "handeye.json"
    if not meta_path.is_file():
        raise DatasetError(f"{meta_path}: capture description missing (see docs/handeye.md)")
    try:
        meta = sc.loads(meta_path.read_text(encoding="utf-8"))
    except (ValueError, UnicodeDecodeError) as e:
        raise DatasetError(f"{meta_path}: not valid JSON ({e})") from None
    where = str(meta_path)
    if not isinstance(meta, dict) or meta.get("schema") != SCHEMA:
        got = meta.get("schema") if isinstance(meta, dict) else meta
        raise DatasetError(f"{where}: field 'schema' must be {SCHEMA!r}, got {got!r}")
    if meta.get("schema_version") != SCHEMA_VERSION:
        raise DatasetError(
            f"{where}: unknown schema_version {meta.get('schema_version')!r}; this jaxcal reads {SCHEMA_VERSION}"
        )
    # A misspelt or foreign key is refused, not ignored (notes go under keys starting with 'x_').
    sc.obj(meta, sc.Loc(meta_path), optional=FIELDS)
    if isinstance(meta.get("poses"), dict):
        sc.obj(meta["poses"], sc.Loc(meta_path, "field 'poses'"), optional=POSES_FIELDS)
    for i, c in enumerate(meta.get("cameras") or ()):
        if isinstance(c, dict):
            sc.obj(c, sc.Loc(meta_path, f"cameras[{i}]"), optional=CAMERA_FIELDS)
    arrangement = _choice(meta, "arrangement", ARRANGEMENTS, where)
    cameras = _cameras(meta, where)
    target = _require(meta, "target", where)
    if not isinstance(target, dict):
        raise DatasetError(f"{where}: field 'target' must be an object, got {target!r}")
    try:
        spec = TargetSpec.from_dict(target, where=f"target {target.get('name', 'target')!r}")
    except ValueError as e:
        raise DatasetError(f"{where}: field 'target': {e}") from None
    poses = _require(meta, "poses", where)
    pw = f"{where}: poses"
    file = sc.relative_path(str(_require(poses, "file", pw)), sc.Loc(meta_path, "field 'poses.file'"))
    frames, T, rotations = _read_poses(root / file, poses, pw)
    images, notes = _images(root, cameras, frames)
    notes = _repeat_note(root / file, frames, T) + notes
    names = meta.get("frames", {})
    if not isinstance(names, dict):
        raise DatasetError(f"{where}: field 'frames' must be an object, got {names!r}")
    truth = None
    if (root / "truth.json").is_file():
        try:
            truth = sc.loads((root / "truth.json").read_text(encoding="utf-8"))
        except (ValueError, UnicodeDecodeError) as e:
            raise DatasetError(f"{root / 'truth.json'}: not valid JSON ({e})") from None
    return HandEyeCapture(
        root=root,
        eye_in_hand=arrangement == "eye_in_hand",
        cameras=cameras,
        target=spec,
        frames=frames,
        T_base_ee=T,
        images=images,
        base_frame=_name(names, "base", "base_link", f"{where}: frames"),
        ee_frame=_name(names, "ee", "tool0", f"{where}: frames"),
        target_frame=_name(names, "target", "calibration_target", f"{where}: frames"),
        description=str(meta.get("description", "")),
        truth=truth,
        pose_format=str(poses["format"]),
        notes=notes,
        rotations=rotations,
    )


def true_T_robot_cam(capture: HandEyeCapture) -> dict[str, np.ndarray] | None:
    """A synthetic capture's true `T_robot_cam` per camera (its `truth.json`), else None."""
    if not capture.truth or "T_robot_cam" not in capture.truth:
        return None
    return {name: np.asarray(T) for name, T in capture.truth["T_robot_cam"].items()}


# --------------------------------------------------------------------------- writing


def pose_rows(
    T_base_ee: np.ndarray, fmt: str, translation_unit: str = "m", rotation_unit: str = "rad"
) -> list:
    """The pose table's value columns (in `POSE_COLUMNS[fmt]` order) for `(frames, 4, 4)` poses."""
    T = np.asarray(T_base_ee, np.float64)
    st = 1e3 if translation_unit == "mm" else 1.0
    sr = 180.0 / math.pi if rotation_unit == "deg" else 1.0
    rows = []
    for M in T:
        t = (M[:3, 3] * st).tolist()
        if fmt == "matrix":
            N = M.copy()
            N[:3, 3] *= st
            rows.append(N.ravel().tolist())
        elif fmt == "xyz_quat":
            rows.append(t + matrix_to_quaternion(M[:3, :3]).tolist())
        elif fmt == "xyz_rpy":
            rows.append(t + (matrix_to_rpy(M[:3, :3]) * sr).tolist())
        else:
            rows.append(t + (matrix_to_rotvec(M[:3, :3]) * sr).tolist())
    return rows


def write_hand_eye_description(
    root,
    *,
    eye_in_hand: bool,
    cameras: list[HandEyeCamera],
    target: TargetSpec,
    frames: list[str],
    T_base_ee: np.ndarray,
    pose_format: str = "xyz_quat",
    translation_unit: str = "m",
    rotation_unit: str = "rad",
    description: str = "",
) -> None:
    """Write `handeye.json` and `poses.csv` into `root` (the images are the caller's)."""
    root = Path(root)
    poses = {"file": "poses.csv", "format": pose_format, "translation_unit": translation_unit}
    if pose_format in ("xyz_rpy", "xyz_rotvec"):
        poses["rotation_unit"] = rotation_unit
    meta = {
        "schema": SCHEMA,
        "schema_version": SCHEMA_VERSION,
        "description": description,
        "arrangement": "eye_in_hand" if eye_in_hand else "eye_to_hand",
        "frames": {"base": "base_link", "ee": "tool0", "target": "calibration_target"},
        "poses": poses,
        "cameras": [c.to_dict() for c in cameras],
        "target": target.to_dict(),
    }
    (root / "handeye.json").write_text(json.dumps(meta, indent=1) + "\n")
    with open(root / "poses.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["frame", *POSE_COLUMNS[pose_format]])
        for name, row in zip(frames, pose_rows(T_base_ee, pose_format, translation_unit, rotation_unit)):
            w.writerow([name, *(repr(float(v)) for v in row)])


# --------------------------------------------------------------------------- a known answer

#: The names a reference file may give a camera's pose on the robot, per arrangement.
REFERENCE_KEYS = {
    "eye_in_hand": ("T_robot_cam", "T_ee_cam", "T_flange_cam"),
    "eye_to_hand": ("T_robot_cam", "T_base_cam"),
}


def _reference_pose(value, where: str) -> np.ndarray:
    """A pose given as a 4x4 matrix (nested lists, or `{"matrix": ...}`) or as a 6-vector
    `[tx, ty, tz, rx, ry, rz]` (m, and a rotation vector in rad: ViSP's `vpPoseVector`)."""
    if isinstance(value, dict):
        if "matrix" not in value:
            raise DatasetError(f"{where}: a pose object needs a field 'matrix' (4x4)")
        value, where = value["matrix"], f"{where}.matrix"
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise DatasetError(
            f"{where}: a pose must be a 4x4 matrix or [tx, ty, tz, rx, ry, rz], got {value!r}"
        ) from None
    if a.shape == (6,) and np.all(np.isfinite(a)):
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = rotvec_to_matrix(a[3:]), a[:3]
        return T
    if a.shape != (4, 4) or not np.all(np.isfinite(a)):
        raise DatasetError(
            f"{where}: a pose must be a finite 4x4 matrix or [tx, ty, tz, rx, ry, rz], got shape {a.shape}"
        )
    R = a[:3, :3]
    if not np.allclose(a[3], [0.0, 0.0, 0.0, 1.0]) or not np.allclose(R @ R.T, np.eye(3), atol=1e-6):
        raise DatasetError(
            f"{where}: not a rigid transform (its rotation is not orthonormal, or its last row is not 0 0 0 1)"
        )
    if np.linalg.norm(a[:3, 3]) > MAX_TRANSLATION_M:
        raise DatasetError(f"{where}: translation {np.linalg.norm(a[:3, 3]):.4g} m: give metres")
    return a


def read_reference(path, capture: HandEyeCapture) -> dict[str, np.ndarray]:
    """A known answer to compare a hand-eye result with (`jaxcal handeye --reference`): per camera
    of `capture`, its pose on the robot (`T_ee_cam` eye-in-hand, `T_base_cam` eye-to-hand), m.

    The file is JSON: a jaxcal hand-eye `result.json` (`cameras.<name>.T_robot_cam`), or an object
    giving the pose under one of `REFERENCE_KEYS` of the capture's arrangement, directly or inside a
    block named after the arrangement (`eye_in_hand` / `eye_to_hand`: one file for both captures),
    and, with several cameras, per camera inside `cameras.<name>` (or the pose's field keyed by
    camera name, as `jaxcal simulate-handeye`'s truth.json has it); with one camera, the pose alone
    (a 4x4 matrix or a 6-vector). Raises `DatasetError` naming the file and field."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except OSError as e:
        raise DatasetError(f"{path}: cannot read the reference ({e.strerror or e})") from None
    except ValueError as e:
        raise DatasetError(f"{path}: not valid JSON ({e})") from None
    names = [c.name for c in capture.cameras]
    if isinstance(doc, list) and len(names) == 1:  # the pose alone: a 4x4 matrix or a 6-vector
        return {names[0]: _reference_pose(doc, str(path))}
    if not isinstance(doc, dict):
        raise DatasetError(
            f"{path}: a reference must be a JSON object, or (one camera) its pose alone as a 4x4 matrix or "
            "[tx, ty, tz, rx, ry, rz]"
        )
    where = str(path)
    if capture.arrangement in doc:
        doc, where = doc[capture.arrangement], f"{where} field {capture.arrangement!r}"
        if not isinstance(doc, dict):
            raise DatasetError(f"{where}: must be an object")
    cameras = doc.get("cameras")
    if cameras is None and len(names) > 1:
        raise DatasetError(f"{where}: {len(names)} cameras ({names}): give each pose in 'cameras.<name>'")
    if cameras is not None and not isinstance(cameras, dict):
        raise DatasetError(f"{where}: field 'cameras' must be an object keyed by camera name")
    out = {}
    for name in names:
        block, at = (
            (doc, where) if cameras is None else (cameras.get(name), f"{where} field 'cameras.{name}'")
        )
        if not isinstance(block, dict):
            raise DatasetError(f"{at}: no pose for camera {name!r}")
        keys = [k for k in REFERENCE_KEYS[capture.arrangement] if k in block]
        if not keys:
            other = [k for ks in REFERENCE_KEYS.values() for k in ks if k in block]
            raise DatasetError(
                f"{at}: no {' / '.join(REFERENCE_KEYS[capture.arrangement])} (the {capture.arrangement} "
                "camera's pose)" + (f"; it gives {other[0]}, another arrangement's pose" if other else "")
            )
        value, at = block[keys[0]], f"{at} field {keys[0]!r}"
        if isinstance(value, dict) and "matrix" not in value and name in value:  # per camera (a truth.json)
            value, at = value[name], f"{at}.{name}"
        out[name] = _reference_pose(value, at)
    return out
