"""The dataset format (captured and synthetic alike); see `docs/dataset.md`.

```
DATASET/
  metadata.json     schema + version, robot file, cameras, targets, encoders, clock, motion segments
  robot.urdf        the nominal robot (the file metadata["robot"]["urdf"] names)
  frames.csv        camera,frame,timestamp,file        (camera clock, s)
  encoders.csv      timestamp,<joint 1>,...,<joint n>  (controller clock, s; motor angles, rad)
  images/<camera>/<frame>.png
  truth.json        synthetic datasets only: true model, camera and target poses, clock
```

`load_dataset` checks everything it reads and raises `DatasetError` (a
`ValueError`) naming the file, field, row or frame at fault. Writing is
atomic: a dataset is assembled in a temporary directory beside its
destination and renamed into place.
"""

import csv
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import DatasetError
from ..markers import TargetSpec
from ._files import atomic_directory as atomic_directory

SCHEMA = "jaxcal.dataset"
SCHEMA_VERSION = 1


@dataclass(frozen=True, eq=False)
class CameraInfo:
    """A camera of the dataset. `K` is `None` when the intrinsics are unknown
    (the front end then self-calibrates). `mount`: `"world"` or a link name."""

    name: str
    width: int
    height: int
    K: np.ndarray | None
    dist: np.ndarray
    mount: str = "world"

    def to_dict(self) -> dict:
        return {
            "name": self.name,
            "width": self.width,
            "height": self.height,
            "K": None if self.K is None else np.asarray(self.K).tolist(),
            "distortion": np.asarray(self.dist).tolist(),
            "mount": self.mount,
        }


@dataclass(frozen=True, eq=False)
class TargetInfo:
    """A marker plate: what is printed (`spec`), the link it rides on (`"world"`
    when fixed in the scene) and, when known from design, its nominal mount."""

    spec: TargetSpec
    link: str
    T_link_target: np.ndarray | None = None

    @property
    def name(self) -> str:
        return self.spec.name

    def to_dict(self) -> dict:
        d = self.spec.to_dict()
        d["link"] = self.link
        d["T_link_target_nominal"] = (
            None if self.T_link_target is None else np.asarray(self.T_link_target).tolist()
        )
        return d


@dataclass(frozen=True, eq=False)
class Dataset:
    """A dataset read from disk (see the module docstring for the layout).

    - `frames`: dict of arrays `camera` (str), `frame` (int), `timestamp`
      (camera clock, s), `file` (path relative to `root`), one entry per image.
    - `encoder_t` (T,) controller clock, s; `encoder_motor` (T, joints), rad.
    - `clock_offset_s`: $t_{cam} - t_{controller}$ if known, else `None`.
    - `segments`: `(joint name or None, start, end)` on the controller clock.
    - `truth`: the parsed `truth.json` of a synthetic dataset, else `None`.
    """

    root: Path
    metadata: dict
    robot_urdf: Path
    base_link: str | None
    flange_link: str | None
    cameras: tuple[CameraInfo, ...]
    targets: tuple[TargetInfo, ...]
    joint_names: tuple[str, ...]
    frames: dict
    encoder_t: np.ndarray | None
    encoder_motor: np.ndarray | None
    clock_offset_s: float | None
    clock_drift_ppm: float
    segments: tuple
    truth: dict | None = field(default=None)

    def camera(self, name: str) -> CameraInfo:
        for c in self.cameras:
            if c.name == name:
                return c
        raise KeyError(name)

    def image_path(self, i: int) -> Path:
        return self.root / self.frames["file"][i]

    def load_model(self):
        """The nominal `KinematicModel` from the dataset's robot file."""
        from .urdf import load_urdf

        try:
            return load_urdf(self.robot_urdf, self.base_link, self.flange_link)
        except (OSError, ValueError) as e:
            raise DatasetError(f"{self.robot_urdf}: cannot load the robot model: {e}") from e


# --------------------------------------------------------------------------- writing


def _json_default(x):
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.generic):
        return x.item()
    raise TypeError(f"not JSON serialisable: {type(x).__name__}")


def write_json(path: Path, payload: dict) -> None:
    Path(path).write_text(json.dumps(payload, indent=1, default=_json_default) + "\n")


def write_frames(path: Path, camera, frame, timestamp, file) -> None:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["camera", "frame", "timestamp", "file"])
        for row in zip(camera, frame, timestamp, file):
            w.writerow([row[0], int(row[1]), repr(float(row[2])), row[3]])


def write_encoders(path: Path, t, motor, joint_names) -> None:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["timestamp", *joint_names])
        for ti, mi in zip(t, motor):
            w.writerow([repr(float(ti)), *(repr(float(v)) for v in mi)])


# --------------------------------------------------------------------------- reading


def _require(d: dict, key: str, where: str):
    if not isinstance(d, dict) or key not in d:
        raise DatasetError(f"{where}: missing field {key!r}")
    return d[key]


def _matrix(x, shape, where: str) -> np.ndarray:
    try:
        a = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError):
        raise DatasetError(f"{where}: not a numeric array") from None
    if a.shape != shape:
        raise DatasetError(f"{where}: expected shape {shape}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise DatasetError(f"{where}: contains NaN or inf")
    return a


def _read_csv(path: Path, header_first: str) -> tuple[list[str], list[list[str]]]:
    if not path.is_file():
        raise DatasetError(f"{path}: file missing")
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    if not rows or not rows[0] or rows[0][0] != header_first:
        raise DatasetError(f"{path}: the first line must be a header starting with {header_first!r}")
    return rows[0], rows[1:]


def _float(text: str, where: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise DatasetError(f"{where}: {text!r} is not a number") from None
    if not math.isfinite(v):
        raise DatasetError(f"{where}: value is {text} (NaN/inf not allowed)")
    return v


def _cameras(meta: dict, where: str) -> tuple[CameraInfo, ...]:
    cams = _require(meta, "cameras", where)
    if not isinstance(cams, list) or not cams:
        raise DatasetError(f"{where}: 'cameras' must be a non-empty list")
    out = []
    for i, c in enumerate(cams):
        w = f"{where}: cameras[{i}]"
        name = str(_require(c, "name", w))
        w = f"{where}: camera {name!r}"
        width, height = int(_require(c, "width", w)), int(_require(c, "height", w))
        K = c.get("K")
        K = None if K is None else _matrix(K, (3, 3), f"{w} field 'K'")
        dist = np.asarray(c.get("distortion", [0.0] * 5), np.float64).ravel()
        if dist.size not in (4, 5, 8, 12, 14) or not np.all(np.isfinite(dist)):
            raise DatasetError(
                f"{w} field 'distortion': expected 4, 5, 8, 12 or 14 finite OpenCV coefficients"
            )
        out.append(CameraInfo(name, width, height, K, dist, str(c.get("mount", "world"))))
    names = [c.name for c in out]
    if len(set(names)) != len(names):
        raise DatasetError(f"{where}: camera names are not unique: {names}")
    return tuple(out)


def _targets(meta: dict, where: str) -> tuple[TargetInfo, ...]:
    targets = _require(meta, "targets", where)
    if not isinstance(targets, list) or not targets:
        raise DatasetError(f"{where}: 'targets' must be a non-empty list")
    out = []
    for i, t in enumerate(targets):
        w = f"{where}: targets[{i}]"
        t = dict(t)
        link = str(_require(t, "link", w))
        T = t.pop("T_link_target_nominal", None)
        t.pop("link")
        try:
            spec = TargetSpec.from_dict(t, where=w)
        except ValueError as e:
            raise DatasetError(str(e)) from None
        T = None if T is None else _matrix(T, (4, 4), f"{w} field 'T_link_target_nominal'")
        out.append(TargetInfo(spec, link, T))
    return tuple(out)


def load_dataset(path) -> Dataset:
    """Read and check the dataset in directory `path` (nothing is modified)."""
    root = Path(path)
    if not root.is_dir():
        raise DatasetError(f"{root}: dataset directory not found")
    meta_path = root / "metadata.json"
    if not meta_path.is_file():
        raise DatasetError(f"{meta_path}: metadata file missing")
    try:
        meta = json.loads(meta_path.read_text())
    except json.JSONDecodeError as e:
        raise DatasetError(f"{meta_path}: not valid JSON ({e})") from None
    where = str(meta_path)
    if meta.get("schema") != SCHEMA:
        raise DatasetError(f"{where}: field 'schema' must be {SCHEMA!r}, got {meta.get('schema')!r}")
    version = meta.get("schema_version")
    if version != SCHEMA_VERSION:
        raise DatasetError(
            f"{where}: unknown schema_version {version!r}; this jaxcal reads version {SCHEMA_VERSION}"
        )
    robot = _require(meta, "robot", where)
    urdf = root / str(_require(robot, "urdf", f"{where}: robot"))
    if not urdf.is_file():
        raise DatasetError(f"{urdf}: robot file missing (named by {where} field robot.urdf)")
    cameras = _cameras(meta, where)
    targets = _targets(meta, where)

    # Frames table.
    frames_path = root / "frames.csv"
    header, rows = _read_csv(frames_path, "camera")
    if header != ["camera", "frame", "timestamp", "file"]:
        raise DatasetError(
            f"{frames_path}: header must be camera,frame,timestamp,file, got {','.join(header)}"
        )
    cam_names = {c.name for c in cameras}
    cam, idx, ts, files = [], [], [], []
    for k, row in enumerate(rows, start=2):
        w = f"{frames_path} line {k}"
        if len(row) != 4:
            raise DatasetError(f"{w}: expected 4 columns, got {len(row)}")
        if row[0] not in cam_names:
            raise DatasetError(f"{w}: unknown camera {row[0]!r}; metadata cameras are {sorted(cam_names)}")
        cam.append(row[0])
        try:
            idx.append(int(row[1]))
        except ValueError:
            raise DatasetError(f"{w}: frame {row[1]!r} is not an integer") from None
        ts.append(_float(row[2], w))
        files.append(row[3])
    if not rows:
        raise DatasetError(f"{frames_path}: no frames")
    frames = {
        "camera": np.array(cam),
        "frame": np.array(idx, dtype=np.int64),
        "timestamp": np.array(ts),
        "file": np.array(files),
    }

    # Encoder table (optional: datasets without encoders calibrate without ratios).
    enc_meta = meta.get("encoders")
    joint_names = tuple(str(j) for j in _require(robot, "joints", f"{where}: robot"))
    enc_t = enc_m = None
    enc_path = root / "encoders.csv"
    if enc_meta is not None:
        header, rows = _read_csv(enc_path, "timestamp")
        if tuple(header[1:]) != joint_names:
            unknown = [h for h in header[1:] if h not in joint_names]
            detail = f"unknown joint names {unknown}" if unknown else f"columns {header[1:]}"
            raise DatasetError(f"{enc_path}: {detail}; expected the robot's joints {list(joint_names)}")
        values = np.empty((len(rows), len(header)))
        for k, row in enumerate(rows, start=2):
            if len(row) != len(header):
                raise DatasetError(f"{enc_path} line {k}: expected {len(header)} columns, got {len(row)}")
            for c, text in enumerate(row):
                values[k - 2, c] = _float(text, f"{enc_path} line {k} column {header[c]!r}")
        if len(values) < 2:
            raise DatasetError(f"{enc_path}: fewer than 2 encoder readings")
        if np.any(np.diff(values[:, 0]) <= 0):
            k = int(np.flatnonzero(np.diff(values[:, 0]) <= 0)[0]) + 3
            raise DatasetError(f"{enc_path} line {k}: timestamps must increase")
        enc_t, enc_m = values[:, 0], values[:, 1:]

    clock = meta.get("clock", {}) or {}
    offset = clock.get("offset_s")
    segments = []
    for i, s in enumerate(meta.get("motion", []) or []):
        w = f"{where}: motion[{i}]"
        joint = s.get("joint")
        if joint is not None and joint not in joint_names:
            raise DatasetError(f"{w}: unknown joint {joint!r}; the robot's joints are {list(joint_names)}")
        segments.append((joint, float(_require(s, "start", w)), float(_require(s, "end", w))))

    truth = None
    truth_path = root / "truth.json"
    if truth_path.is_file():
        try:
            truth = json.loads(truth_path.read_text())
        except json.JSONDecodeError as e:
            raise DatasetError(f"{truth_path}: not valid JSON ({e})") from None

    return Dataset(
        root=root,
        metadata=meta,
        robot_urdf=urdf,
        base_link=robot.get("base_link"),
        flange_link=robot.get("flange_link"),
        cameras=cameras,
        targets=targets,
        joint_names=joint_names,
        frames=frames,
        encoder_t=enc_t,
        encoder_motor=enc_m,
        clock_offset_s=None if offset is None else float(offset),
        clock_drift_ppm=float(clock.get("drift_ppm", 0.0) or 0.0),
        segments=tuple(segments),
        truth=truth,
    )
