"""The dataset format (captured and synthetic alike); see `docs/dataset.md`.

```
DATASET/
  metadata.json     schema + version, robot file, cameras, targets, encoders, clock, motion segments
  robot.urdf        the nominal robot (the file metadata["robot"]["urdf"] names)
  frames.csv        camera,frame,timestamp,file        (camera clock, s)
  encoders.csv      timestamp,<joint 1>,...,<joint n>  (controller clock, s; motor angles, encoders.unit)
  images/<camera>/<frame>.png
  truth.json        synthetic datasets only: true model, camera and target poses, clock
```

`load_dataset` checks every field of every file before any work (types,
ranges, image sizes from the file headers, timestamps, encoder units against
the URDF joint limits, encoder glitches) and raises `DatasetError` (a
`ValueError`) naming the file, field path or line, and the value. Nothing in
a dataset is modified. Writing is atomic: a dataset is assembled in a
temporary directory beside its destination and renamed into place
(`atomic_directory`, see `jaxcal.io._files`).
"""

import csv
import io
import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath, PureWindowsPath

import numpy as np

from ..errors import DatasetError
from ..markers import KINDS as TARGET_KINDS
from ..markers import TargetSpec
from . import _encoders as enc
from . import _schema as sc
from ._files import atomic_directory as atomic_directory
from ._images import MAX_PIXELS, image_size
from ._schema import Loc
from .urdf import load_urdf, urdf_outline

SCHEMA = "jaxcal.dataset"
SCHEMA_VERSION = 1
#: Top-level metadata fields that are read, and the ones allowed but not read
#: (`simulation`: the configuration `jaxcal simulate` records). Keys starting
#: with `x_` are free for the user's own notes at every level.
META_REQUIRED = ("schema", "schema_version", "robot", "cameras", "targets")
META_OPTIONAL = ("description", "encoders", "clock", "motion")
META_IGNORED = ("simulation",)
#: Camera names become file names (`camera_<name>.yaml`).
CAMERA_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")
#: Largest image side (pixels).
MAX_SIDE = 65535
#: Frame indices: below 2**31, and per camera spanning at most
#: `FRAME_SPAN_FACTOR` x its rows + `FRAME_SPAN_SLACK` (a 99 % drop rate fits;
#: nothing downstream can allocate per missing index beyond that).
MAX_FRAME_INDEX = 2**31 - 1
FRAME_SPAN_FACTOR = 100
FRAME_SPAN_SLACK = 1000
#: |clock.drift_ppm| bound (0.1 %: ten times a poor crystal).
MAX_DRIFT_PPM = 1000.0
#: `encoders.quantity` values: what the log holds.
QUANTITIES = ("motor_angle",)


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


@dataclass(frozen=True)
class EncoderGlitch:
    """An isolated glitch of one joint's encoder log, removed at load.

    - `joint`: the joint whose log jumped.
    - `rows`: `(first, last)` data rows of the encoder file (0 = the first row
      after the header), inclusive; `lines`: the same as file line numbers.
    - `t_start`, `t_end`: controller-clock interval (s) in which the log is
      affected: from the last good sample before the glitch to the first good
      one after. Encoder values interpolated inside it bridge the removed rows;
      frames whose controller time falls in `[t_start, t_end]` should be dropped.
    - `size`: the jump away from the local trend (rad or m of joint motion).
    """

    joint: str
    rows: tuple[int, int]
    lines: tuple[int, int]
    t_start: float
    t_end: float
    size: float


@dataclass(frozen=True, eq=False)
class Dataset:
    """A dataset read from disk and checked (see the module docstring for the layout).

    - `frames`: dict of arrays `camera` (str), `frame` (int), `timestamp`
      (camera clock, s), `file` (path relative to `root`), one entry per image.
    - `encoder_t` (T,) controller clock, s; `encoder_motor` (T, joints) motor
      angles in radians, whatever `encoders.unit` the file used; the rows of
      `encoder_glitches` are removed.
    - `clock_offset_s`: $t_{cam} - t_{controller}$ if known, else `None`.
    - `segments`: `(joint name or None, start, end)` on the controller clock;
      `segment_homes`: per segment the commanded configuration the other joints
      held (rad; the sweeping joint's entry zero), or None when not given.
    - `truth`: the parsed `truth.json` of a synthetic dataset, else `None`.
    - `joint_limits`: joint name -> `jaxcal.io.urdf.JointLimits` (URDF type,
      position and velocity limits, nominal reduction ratio).
    - `encoder_unit`: the unit the encoder file was written in (`None`
      without a log).
    - `encoder_glitches`: the `EncoderGlitch`es found and removed at load.
    - `notes`: human-readable remarks from loading (glitches removed, fields
      not used) for the calibration to report.
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
    segment_homes: tuple = ()
    joint_limits: dict = field(default_factory=dict)
    encoder_unit: str | None = None
    encoder_glitches: tuple[EncoderGlitch, ...] = ()
    notes: tuple[str, ...] = ()

    def camera(self, name: str) -> CameraInfo:
        for c in self.cameras:
            if c.name == name:
                return c
        raise KeyError(name)

    def image_path(self, i: int) -> Path:
        return self.root / self.frames["file"][i]

    def in_encoder_glitch(self, t_controller) -> np.ndarray:
        """Which controller-clock times fall inside an encoder glitch's interval
        (`[t_start, t_end]` of any of `encoder_glitches`): bool array, shape of the input."""
        t = np.asarray(t_controller, np.float64)
        hit = np.zeros(t.shape, bool)
        for g in self.encoder_glitches:
            hit |= (t >= g.t_start) & (t <= g.t_end)
        return hit

    def load_model(self):
        """The nominal `KinematicModel` from the dataset's robot file."""
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


# --------------------------------------------------------------------------- reading: files


def _inside(text: str, loc: Loc) -> str:
    """A path relative to the dataset directory that stays inside it."""
    if "\\" in text or "\x00" in text:
        raise loc.expected("a relative path with '/' separators", text)
    p = PurePosixPath(text)
    if p.is_absolute() or PureWindowsPath(text).drive or ".." in p.parts or not p.parts:
        raise loc.expected("a path relative to the dataset directory that stays inside it", text)
    return text


def _read_csv(path: Path, what: str) -> tuple[list[str], list[tuple[int, list[str]]]]:
    """Header and `(line number, cells)` rows of a CSV file; blank lines are skipped."""
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise DatasetError(f"{path}: {what} missing") from None
    except OSError as e:
        raise DatasetError(f"{path}: cannot read the {what} ({e.strerror})") from None
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise DatasetError(f"{path}: not UTF-8 text ({e.reason} at byte {e.start})") from None
    reader = csv.reader(io.StringIO(text, newline=""))
    rows = []
    try:
        for cells in reader:
            if cells and any(c.strip() for c in cells):
                rows.append((reader.line_num, cells))
    except csv.Error as e:
        raise DatasetError(f"{path} line {reader.line_num}: not CSV ({e})") from None
    if not rows:
        raise DatasetError(f"{path}: empty (expected a header line)")
    return rows[0][1], rows[1:]


def _float(text: str, where: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise DatasetError(f"{where}: {text!r} is not a number") from None
    if not math.isfinite(v):
        raise DatasetError(f"{where}: value is {text} (NaN/inf not allowed)")
    return v


# --------------------------------------------------------------------------- reading: metadata.json


def _robot(meta: dict, loc: Loc, root: Path):
    """`robot`: the URDF path, base and flange links, the joints, and their limits."""
    robot = sc.obj(meta["robot"], loc, required=("urdf", "joints"), optional=("base_link", "flange_link"))
    rel = _inside(sc.string(robot["urdf"], loc.key("urdf")), loc.key("urdf"))
    urdf = root / rel
    if not urdf.is_file():
        raise DatasetError(f"{urdf}: robot file missing (named by {loc.key('urdf')})")
    joints = sc.names(robot["joints"], loc.key("joints"))
    try:
        outline = urdf_outline(urdf)
    except (OSError, ValueError) as e:
        raise DatasetError(f"{urdf}: cannot read the robot model: {e}") from None
    movable = {j: kind for j, kind, _ in outline.parent_joint.values()}
    for i, name in enumerate(joints):
        if name not in movable:
            raise (
                loc.key("joints")
                .index(i)
                .fail(
                    f"{name!r} is not a joint of {urdf.name} (its movable joints: "
                    f"{sorted(j for j, k in movable.items() if k != 'fixed')})"
                )
            )
        if movable[name] not in ("revolute", "continuous", "prismatic"):
            raise (
                loc.key("joints")
                .index(i)
                .fail(
                    f"joint {name!r} is {movable[name]} in {urdf.name}; expected revolute, continuous or prismatic"
                )
            )
    links = {}
    for key in ("base_link", "flange_link"):
        v = robot.get(key)
        if v is not None and sc.string(v, loc.key(key)) not in outline.links:
            raise loc.key(key).fail(f"{v!r} is not a link of {urdf.name} (links: {sorted(outline.links)})")
        links[key] = v
    if links["flange_link"] is not None:
        chain, link, seen = [], links["flange_link"], set()
        while link != links["base_link"] and link in outline.parent_joint and link not in seen:
            seen.add(link)
            name, kind, link = outline.parent_joint[link]
            if kind != "fixed":
                chain.append(name)
        if links["base_link"] is not None and link != links["base_link"]:
            raise loc.key("flange_link").fail(
                f"{links['flange_link']!r} is not below base_link {links['base_link']!r} in {urdf.name}"
            )
        if chain[::-1] != joints:
            raise loc.key("joints").fail(
                f"{joints} differ from the movable joints from base to flange in {urdf.name}: {chain[::-1]}"
            )
    try:
        limits = urdf_outline(urdf, joints).limits
    except ValueError as e:
        raise DatasetError(f"{urdf}: cannot read the robot model: {e}") from None
    return urdf, links["base_link"], links["flange_link"], tuple(joints), limits, outline.links


def _intrinsics(x, loc: Loc, width: int, height: int) -> np.ndarray:
    K = sc.array(x, loc, (3, 3))
    fx, fy = K[0, 0], K[1, 1]
    if not (fx > 0 and fy > 0):
        raise loc.fail(f"focal lengths K[0][0], K[1][1] must be positive, got fx = {fx:g}, fy = {fy:g}")
    if K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0:
        raise loc.fail(
            f"the entries below the diagonal must be 0, got {[float(K[1, 0]), float(K[2, 0]), float(K[2, 1])]}"
        )
    if K[2, 2] != 1:
        raise loc.fail(f"bottom row must be [0, 0, 1], got {K[2].tolist()}")
    cx, cy = K[0, 2], K[1, 2]
    if not (-0.5 <= cx <= width - 0.5 and -0.5 <= cy <= height - 0.5):
        raise loc.fail(
            f"principal point ({cx:g}, {cy:g}) lies outside the {width}x{height} image "
            "(pixel centres run from 0 to width - 1)"
        )
    return K


def _cameras(meta: dict, loc: Loc, links) -> tuple[CameraInfo, ...]:
    cams = meta["cameras"]
    if not isinstance(cams, list) or not cams:
        raise loc.expected("a non-empty list of cameras", cams)
    out = []
    for i, c in enumerate(cams):
        w = loc.index(i)
        sc.obj(c, w, required=("name", "width", "height"), optional=("K", "distortion", "mount"))
        name = sc.string(c["name"], w.key("name"))
        if not CAMERA_NAME.fullmatch(name):
            raise w.key("name").expected("letters, digits, '_', '.' or '-' (it names output files)", name)
        width = sc.integer(c["width"], w.key("width"), 1, MAX_SIDE)
        height = sc.integer(c["height"], w.key("height"), 1, MAX_SIDE)
        if width * height > MAX_PIXELS:
            raise w.fail(
                f"{width}x{height} pixels is more than the {MAX_PIXELS / 1e6:.0f} megapixels jaxcal reads"
            )
        K = c.get("K")
        K = None if K is None else _intrinsics(K, w.key("K"), width, height)
        dist = c.get("distortion", [0.0] * 5)
        if not isinstance(dist, list) or len(dist) not in (4, 5, 8, 12, 14):
            raise w.key("distortion").expected("a list of 4, 5, 8, 12 or 14 OpenCV coefficients", dist)
        dist = sc.array(dist, w.key("distortion"), (None,))
        mount = sc.string(c.get("mount", "world"), w.key("mount"))
        if mount != "world" and mount not in links:
            raise w.key("mount").fail(f"{mount!r} is neither 'world' nor a link of the robot")
        out.append(CameraInfo(name, width, height, K, dist, mount))
    names = [c.name for c in out]
    if len(set(names)) != len(names):
        raise loc.fail(f"camera names are not unique: {names}")
    return tuple(out)


def _targets(meta: dict, loc: Loc, links) -> tuple[TargetInfo, ...]:
    targets = meta["targets"]
    if not isinstance(targets, list) or not targets:
        raise loc.expected("a non-empty list of targets", targets)
    out = []
    for i, t in enumerate(targets):
        w = loc.index(i)
        if not isinstance(t, dict):
            raise w.expected("a JSON object", t)
        kind = sc.string(t.get("kind", "charuco"), w.key("kind"), choices=TARGET_KINDS)
        shape = ("squares", "square_length") if kind == "charuco" else ()
        sc.obj(
            t,
            w,
            required=("name", "dictionary", "marker_length", "link", *shape),
            optional=("kind", "first_id", "margin", "T_link_target_nominal")
            + (() if kind == "charuco" else ("squares", "square_length")),
        )
        spec = {
            "name": sc.string(t["name"], w.key("name")),
            "kind": kind,
            "dictionary": sc.string(t["dictionary"], w.key("dictionary")),
            "marker_length": sc.number(t["marker_length"], w.key("marker_length"), hi=10.0, above=0.0),
            "first_id": sc.integer(t.get("first_id", 0), w.key("first_id"), 0, 100000),
            "margin": sc.number(t.get("margin", 0.01), w.key("margin"), 0.0, 10.0),
        }
        if kind == "charuco":
            sq = t["squares"]
            if not isinstance(sq, list) or len(sq) != 2:
                raise w.key("squares").expected("[columns, rows]", sq)
            spec["squares"] = tuple(
                sc.integer(v, w.key("squares").index(k), 2, 100) for k, v in enumerate(sq)
            )
            spec["square_length"] = sc.number(t["square_length"], w.key("square_length"), hi=10.0, above=0.0)
        link = sc.string(t["link"], w.key("link"))
        if link != "world" and link not in links:
            raise w.key("link").fail(f"{link!r} is neither 'world' nor a link of the robot")
        T = t.get("T_link_target_nominal")
        T = None if T is None else sc.pose(T, w.key("T_link_target_nominal"))
        try:
            target = TargetSpec(**spec)
        except ValueError as e:
            raise w.fail(str(e)) from None
        out.append(TargetInfo(target, link, T))
    names = [t.name for t in out]
    if len(set(names)) != len(names):
        raise loc.fail(f"target names are not unique: {names}")
    return tuple(out)


def _encoder_meta(meta: dict, loc: Loc) -> dict | None:
    e = meta.get("encoders")
    if e is None:
        return None
    sc.obj(e, loc, optional=("file", "quantity", "unit", "rate_hz", "counts_per_rev"))
    out = {
        "file": _inside(sc.string(e.get("file", "encoders.csv"), loc.key("file")), loc.key("file")),
        "quantity": sc.string(e.get("quantity", "motor_angle"), loc.key("quantity"), choices=QUANTITIES),
        "unit": sc.string(e.get("unit", "rad"), loc.key("unit"), choices=enc.UNITS),
        "rate_hz": None,
        "counts_per_rev": None,
    }
    if e.get("rate_hz") is not None:
        out["rate_hz"] = sc.number(e["rate_hz"], loc.key("rate_hz"), hi=1e6, above=0.0)
    if e.get("counts_per_rev") is not None:
        out["counts_per_rev"] = sc.integer(e["counts_per_rev"], loc.key("counts_per_rev"), 1, 2**48)
    if out["unit"] == "counts" and out["counts_per_rev"] is None:
        raise loc.fail("unit 'counts' needs counts_per_rev (encoder counts per motor revolution)")
    return out


def _clock(meta: dict, loc: Loc) -> tuple[float | None, float]:
    clock = meta.get("clock")
    if clock is None:
        return None, 0.0
    sc.obj(clock, loc, optional=("offset_s", "drift_ppm"))
    offset = clock.get("offset_s")
    offset = None if offset is None else sc.number(offset, loc.key("offset_s"))
    drift = clock.get("drift_ppm")
    drift = 0.0 if drift is None else sc.number(drift, loc.key("drift_ppm"), -MAX_DRIFT_PPM, MAX_DRIFT_PPM)
    return offset, drift


def _motion(meta: dict, loc: Loc, joints: tuple[str, ...]) -> tuple:
    motion = meta.get("motion")
    if motion is None:
        return (), ()
    if not isinstance(motion, list):
        raise loc.expected("a list of segments {joint, start, end}", motion)
    out, homes = [], []
    for i, s in enumerate(motion):
        w = loc.index(i)
        sc.obj(s, w, required=("joint", "start", "end"), optional=("home",))
        joint = s["joint"]
        if joint is not None:
            sc.string(joint, w.key("joint"))
            if joint not in joints:
                raise w.key("joint").fail(f"unknown joint {joint!r}; the robot's joints are {list(joints)}")
        start = sc.number(s["start"], w.key("start"))
        end = sc.number(s["end"], w.key("end"))
        if not end > start:
            raise w.fail(f"end ({end:g}) must be after start ({start:g})")
        home = None
        if s.get("home") is not None:
            home = sc.array(s["home"], w.key("home"), (len(joints),))
            if joint is not None:
                home[joints.index(joint)] = 0.0  # the sweeping joint's own entry is its encoder zero
        out.append((joint, start, end))
        homes.append(home)
    return tuple(out), tuple(homes)


# --------------------------------------------------------------------------- reading: frames.csv


def _frames(root: Path, cameras: tuple[CameraInfo, ...], meta_loc: Loc) -> dict:
    path = root / "frames.csv"
    header, rows = _read_csv(path, "frames table")
    if header != ["camera", "frame", "timestamp", "file"]:
        raise DatasetError(
            f"{path} line 1: header must be camera,frame,timestamp,file, got {','.join(header)}"
        )
    if not rows:
        raise DatasetError(f"{path}: no frames")
    cams = {c.name: c for c in cameras}
    cam, idx, ts, files, lines = [], [], [], [], []
    seen_row, seen_frame, seen_file = {}, {}, {}
    for line, row in rows:
        w = f"{path} line {line}"
        if len(row) != 4:
            raise DatasetError(f"{w}: expected 4 columns (camera,frame,timestamp,file), got {len(row)}")
        key = tuple(row)
        if key in seen_row:
            raise DatasetError(f"{w}: repeats line {seen_row[key]}")
        seen_row[key] = line
        name, frame_text, t_text, file = row
        if name not in cams:
            raise DatasetError(f"{w}: unknown camera {name!r}; metadata cameras are {sorted(cams)}")
        if not frame_text.isascii() or not frame_text.isdigit():
            raise DatasetError(f"{w}: frame {frame_text!r} is not a non-negative integer")
        frame = int(frame_text) if len(frame_text) <= 12 else MAX_FRAME_INDEX + 1
        if frame > MAX_FRAME_INDEX:
            raise DatasetError(
                f"{w}: frame {sc.show(frame_text)} is above the largest capture index {MAX_FRAME_INDEX}"
            )
        if (name, frame) in seen_frame:
            raise DatasetError(
                f"{w}: camera {name!r} frame {frame} is already on line {seen_frame[name, frame]}"
            )
        seen_frame[name, frame] = line
        t = _float(t_text, f"{w} column 'timestamp'")
        _inside(file, Loc(path, f"line {line} column 'file'"))
        if file in seen_file:
            raise DatasetError(f"{w}: file {file!r} is already named on line {seen_file[file]}")
        seen_file[file] = line
        cam.append(name)
        idx.append(frame)
        ts.append(t)
        files.append(file)
        lines.append(line)
    frames = {
        "camera": np.array(cam),
        "frame": np.array(idx, dtype=np.int64),
        "timestamp": np.array(ts, dtype=np.float64),
        "file": np.array(files),
    }
    lines = np.array(lines)
    for name in cams:
        rows_c = np.flatnonzero(frames["camera"] == name)
        if rows_c.size == 0:
            continue
        f_c = frames["frame"][rows_c]
        span = int(f_c.max() - f_c.min())
        bound = FRAME_SPAN_FACTOR * rows_c.size + FRAME_SPAN_SLACK
        if span > bound:
            worst = rows_c[np.argmax(np.abs(f_c - np.median(f_c)))]
            raise DatasetError(
                f"{path} line {lines[worst]}: camera {name!r} frame {frames['frame'][worst]}: its frame indices "
                f"span {span}, more than {FRAME_SPAN_FACTOR} x its {rows_c.size} rows + {FRAME_SPAN_SLACK} "
                "(a capture index far off the others)"
            )
        order = rows_c[np.argsort(f_c, kind="stable")]
        t_c = frames["timestamp"][order]
        bad = np.flatnonzero(np.diff(t_c) <= 0)
        if bad.size:
            a, b = order[bad[0]], order[bad[0] + 1]
            raise DatasetError(
                f"{path} lines {lines[a]} and {lines[b]}: camera {name!r} frame {frames['frame'][a]} has timestamp "
                f"{float(frames['timestamp'][a])!r} and the later frame {frames['frame'][b]} has "
                f"{float(frames['timestamp'][b])!r}; timestamps must increase strictly with the frame index"
            )
    _check_images(root, path, frames, lines, cameras, meta_loc)
    return frames


def _check_images(root: Path, path: Path, frames: dict, lines, cameras, meta_loc: Loc) -> None:
    """Every image exists, is an image, and has its camera's size (from the file header)."""
    index = {c.name: i for i, c in enumerate(cameras)}
    wrong: dict[str, list] = {}
    for k, (name, file) in enumerate(zip(frames["camera"].tolist(), frames["file"].tolist())):
        size = image_size(root / file, f"{path} line {lines[k]}: {file}")
        cam = cameras[index[name]]
        if size != (cam.width, cam.height):
            wrong.setdefault(name, []).append((k, size))
    for name, bad in wrong.items():
        k, (w, h) = bad[0]
        cam = cameras[index[name]]
        total = int(np.sum(frames["camera"] == name))
        more = f"; so are {len(bad) - 1} more of its {total} images" if len(bad) > 1 else ""
        raise DatasetError(
            f"{path} line {lines[k]}: {frames['file'][k]} is {w}x{h} pixels, but {meta_loc.key('cameras')}"
            f"[{index[name]}] ({name!r}) says {cam.width}x{cam.height}{more}"
        )


# --------------------------------------------------------------------------- reading: the encoder log


def _encoder_table(
    path: Path, what: str, joints: tuple[str, ...]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The encoder file's timestamps (T,), logged values (T, joints) and line numbers (T,)."""
    header, rows = _read_csv(path, what)
    if not header or header[0] != "timestamp":
        raise DatasetError(f"{path} line 1: the header must start with 'timestamp', got {','.join(header)!r}")
    if tuple(header[1:]) != joints:
        unknown = [h for h in header[1:] if h not in joints]
        detail = f"unknown joint names {unknown}" if unknown else f"columns {header[1:]}"
        raise DatasetError(f"{path}: {detail}; expected the robot's joints {list(joints)}")
    if len(rows) < 2:
        raise DatasetError(f"{path}: fewer than 2 encoder readings")
    for line, row in rows:
        if len(row) != len(header):
            raise DatasetError(f"{path} line {line}: expected {len(header)} columns, got {len(row)}")
    try:
        values = np.array([row for _, row in rows], dtype=np.float64)
    except ValueError:
        values = None
    if values is None or not np.all(np.isfinite(values)):  # find the cell, name it
        for line, row in rows:
            for c, text in enumerate(row):
                _float(text, f"{path} line {line} column {header[c]!r}")
    lines = np.array([line for line, _ in rows])
    t = values[:, 0]
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        k = bad[0]
        raise DatasetError(
            f"{path} line {lines[k + 1]}: timestamp {float(t[k + 1])!r} is not after line {lines[k]}'s "
            f"{float(t[k])!r}; timestamps must increase strictly"
        )
    return t, values[:, 1:], lines


def _speed_limit(limits) -> float:
    return limits.velocity or enc.DEFAULT_VELOCITY[limits.joint_type]


def _glitches(t, q, lines, joints, limits) -> tuple[list[EncoderGlitch], list, np.ndarray]:
    """Every joint's isolated glitches, its jumps that stay, and the rows to drop."""
    glitches, jumps, drop = [], [], np.zeros(len(t), bool)
    for j, name in enumerate(joints):
        vmax = _speed_limit(limits[name])
        runs, leaps = enc.find_glitches(t, q[:, j], vmax)
        jumps += [(name, leap, vmax) for leap in leaps]
        for a, b in runs:
            before, after = max(a - 1, 0), min(b + 1, len(t) - 1)
            line = np.interp(t[a : b + 1], t[[before, after]], q[[before, after], j])
            size = float(np.max(np.abs(q[a : b + 1, j] - line)))
            glitches.append(
                EncoderGlitch(
                    name, (a, b), (int(lines[a]), int(lines[b])), float(t[before]), float(t[after]), size
                )
            )
            drop[a : b + 1] = True
    return glitches, jumps, drop


def _glitch_note(path: Path, glitches: list[EncoderGlitch], rows: int) -> str:
    where = "; ".join(
        f"line {g.lines[0]}"
        + (f"-{g.lines[1]}" if g.lines[1] != g.lines[0] else "")
        + f" ({g.joint}, {g.size:.3g} off, t = {g.t_start:.4f}..{g.t_end:.4f} s)"
        for g in glitches[:10]
    )
    return (
        f"{path}: {len(glitches)} isolated encoder glitch{'es' if len(glitches) > 1 else ''} removed ({rows} "
        f"rows): {where}{'; ...' if len(glitches) > 10 else ''}; frames taken in those controller-clock "
        "intervals are unreliable"
    )


def _encoders(root: Path, emeta: dict, loc: Loc, joints: tuple[str, ...], limits: dict):
    """The encoder log in radians, checked and cleaned: `(t, motor, glitches, notes)`.

    Glitches are found first (one wild sample must not read as a unit mistake);
    the units are then checked on the clean rows (on all of them when the log is
    too glitchy to clean), and the speeds last.
    """
    path = root / emeta["file"]
    t, raw, lines = _encoder_table(path, f"encoder log (named by {loc.key('file')})", joints)
    factor = enc.to_radians(emeta["unit"], emeta["counts_per_rev"])
    q = raw * factor / np.array([limits[j].reduction_ratio for j in joints])
    glitches, jumps, drop = _glitches(t, q, lines, joints, limits)
    reliable = not jumps and len(glitches) <= enc.GLITCH_MAX_COUNT and drop.mean() <= enc.GLITCH_MAX_FRACTION
    keep = ~drop if reliable else np.ones(len(t), bool)
    for j, name in enumerate(joints):
        problem = enc.unit_problem(raw[keep, j], factor, emeta["unit"], emeta["counts_per_rev"], limits[name])
        if problem is not None:
            raise DatasetError(f"{path} column {name!r}: {problem}")
    if jumps:
        name, leap, vmax = jumps[0]
        k = leap.index
        raise DatasetError(
            f"{path} line {lines[k]}: joint {name!r} jumps by {leap.size:.4g} (rad or m, joint side) in "
            f"{t[k] - t[k - 1]:.4g} s, beyond its speed limit of {vmax:.4g}/s, and does not come back within "
            f"{enc.GLITCH_MAX_RUN} samples: not an isolated glitch (an encoder reset, or a change of unit?)"
        )
    if not reliable:
        raise DatasetError(
            f"{path}: {len(glitches)} glitches over {int(drop.sum())} of {len(t)} rows (more than "
            f"{enc.GLITCH_MAX_COUNT} glitches or {100 * enc.GLITCH_MAX_FRACTION:g} % of the rows): the log is "
            f"unreliable (first at line {glitches[0].lines[0]}, joint {glitches[0].joint!r})"
        )
    t, q, raw, lines = t[keep], q[keep], raw[keep], lines[keep]
    if len(t) < 2:
        raise DatasetError(f"{path}: fewer than 2 encoder readings once the glitches are removed")
    for j, name in enumerate(joints):
        vmax = _speed_limit(limits[name])
        speed = np.abs(enc.local_rate(t, q[:, j]))
        k = int(np.argmax(speed))
        if speed[k] > enc.SPEED_FACTOR * vmax:
            unit = emeta["unit"]
            hint = " (degrees logged as radians move 57 times too fast)" if unit == "rad" else ""
            raise DatasetError(
                f"{path} line {lines[k]}: joint {name!r} moves at {speed[k]:.4g}/s (joint side), "
                f"{speed[k] / vmax:.0f} times its URDF velocity limit {vmax:.4g}/s; is encoders.unit "
                f"({unit!r}) right?{hint}"
            )
    notes = [_glitch_note(path, glitches, int(drop.sum()))] if glitches else []
    if emeta["rate_hz"] is not None:
        rate = 1.0 / float(np.median(np.diff(t)))
        if abs(rate / emeta["rate_hz"] - 1.0) > 0.1:
            notes.append(
                f"{loc.key('rate_hz')} is {emeta['rate_hz']:g} Hz but {path.name} is sampled at {rate:.4g} Hz "
                "(median interval); the timestamps are used"
            )
    return t, raw * factor, tuple(glitches), notes


# --------------------------------------------------------------------------- reading: truth.json


def _truth(path: Path, joints, cameras, targets, n_rows: int) -> dict:
    truth = sc.read_json(path, "truth file")
    loc = Loc(path)
    sc.obj(truth, loc, required=("model", "cameras", "targets", "clock"),
           optional=("T_world_base", "dropped_frames", "frames"))  # fmt: skip
    n = len(joints)
    m = loc.key("model")
    model = sc.obj(
        truth["model"],
        m,
        required=("joint_names", "joint_types", "link_names", "T_parent_joint", "axis", "zero_offset",
                  "reduction_ratio", "T_last_flange"),
    )  # fmt: skip
    if sc.names(model["joint_names"], m.key("joint_names")) != list(joints):
        raise m.key("joint_names").fail(f"{model['joint_names']} differ from robot.joints {list(joints)}")
    types = model["joint_types"]
    if not isinstance(types, list) or len(types) != n:
        raise m.key("joint_types").expected(f"a list of {n} joint types", types)
    for i, v in enumerate(types):
        sc.string(v, m.key("joint_types").index(i), choices=("revolute", "prismatic"))
    link_names = sc.names(model["link_names"], m.key("link_names"), unique=False)
    if len(link_names) != n + 2:
        raise m.key("link_names").expected(f"{n + 2} names (base, {n} joint child links, flange)", link_names)
    T = sc.array(model["T_parent_joint"], m.key("T_parent_joint"), (n, 4, 4))
    for i in range(n):
        sc.pose(T[i].tolist(), m.key("T_parent_joint").index(i))
    axis = sc.array(model["axis"], m.key("axis"), (n, 3))
    if not np.allclose(np.linalg.norm(axis, axis=1), 1.0, rtol=0.0, atol=1e-6):
        raise m.key("axis").fail("every axis must be a unit vector")
    sc.array(model["zero_offset"], m.key("zero_offset"), (n,))
    ratio = sc.array(model["reduction_ratio"], m.key("reduction_ratio"), (n,))
    if np.any(ratio == 0):
        raise m.key("reduction_ratio").fail(f"reduction ratios must be non-zero, got {ratio.tolist()}")
    sc.pose(model["T_last_flange"], m.key("T_last_flange"))
    if "T_world_base" in truth:
        sc.pose(truth["T_world_base"], loc.key("T_world_base"))
    cam_names, target_names = [c.name for c in cameras], [t.name for t in targets]
    cams = truth["cameras"]
    if not isinstance(cams, dict):
        raise loc.key("cameras").expected("an object keyed by camera name", cams)
    for name, c in cams.items():
        w = loc.key("cameras").key(name)
        if name not in cam_names:
            raise w.fail(f"{name!r} is not a camera of the metadata {cam_names}")
        sc.obj(c, w, required=("mount", "T_mount_cam"), optional=("T_cam_base",))
        sc.string(c["mount"], w.key("mount"))
        sc.pose(c["T_mount_cam"], w.key("T_mount_cam"))
        if "T_cam_base" in c:
            sc.pose(c["T_cam_base"], w.key("T_cam_base"))
    tgts = truth["targets"]
    if not isinstance(tgts, dict):
        raise loc.key("targets").expected("an object keyed by target name", tgts)
    for name, t in tgts.items():
        w = loc.key("targets").key(name)
        if name not in target_names:
            raise w.fail(f"{name!r} is not a target of the metadata {target_names}")
        sc.obj(t, w, required=("link", "T_link_target"))
        sc.string(t["link"], w.key("link"))
        sc.pose(t["T_link_target"], w.key("T_link_target"))
    w = loc.key("clock")
    clock = sc.obj(truth["clock"], w, required=("offset_s",), optional=("drift_ppm", "jitter_ms"))
    sc.number(clock["offset_s"], w.key("offset_s"))
    sc.number(clock.get("drift_ppm", 0.0), w.key("drift_ppm"), -MAX_DRIFT_PPM, MAX_DRIFT_PPM)
    sc.number(clock.get("jitter_ms", 0.0), w.key("jitter_ms"), 0.0)
    dropped = truth.get("dropped_frames", [])
    if not isinstance(dropped, list):
        raise loc.key("dropped_frames").expected("a list of capture indices", dropped)
    for i, v in enumerate(dropped):
        sc.integer(v, loc.key("dropped_frames").index(i), 0, MAX_FRAME_INDEX)
    frames = truth.get("frames", [])
    if not isinstance(frames, list):
        raise loc.key("frames").expected("a list with one entry per row of frames.csv", frames)
    for i, f in enumerate(frames):
        w = loc.key("frames").index(i)
        sc.obj(f, w, required=("row", "camera", "frame", "t", "theta", "q", "T_cam_target", "visible"))
        sc.integer(f["row"], w.key("row"), 0, n_rows - 1)
        sc.string(f["camera"], w.key("camera"), choices=cam_names)
        sc.integer(f["frame"], w.key("frame"), 0, MAX_FRAME_INDEX)
        sc.number(f["t"], w.key("t"))
        sc.array(f["theta"], w.key("theta"), (n,))
        sc.array(f["q"], w.key("q"), (n,))
        for key, check in (("T_cam_target", sc.pose), ("visible", None)):
            d = f[key]
            if not isinstance(d, dict):
                raise w.key(key).expected("an object keyed by target name", d)
            for name, v in d.items():
                if name not in target_names:
                    raise w.key(key).key(name).fail(f"{name!r} is not a target of the metadata")
                if check is None:
                    if not isinstance(v, bool):
                        raise w.key(key).key(name).expected("true or false", v)
                else:
                    check(v, w.key(key).key(name))
    return truth


# --------------------------------------------------------------------------- load_dataset


def load_dataset(path) -> Dataset:
    """Read and check the dataset in directory `path` (nothing is modified).

    Every field of `metadata.json`, `frames.csv`, the encoder log and
    `truth.json` is type- and range-checked, every image's size is read from
    its header, and the encoder log is converted to radians, checked against
    the URDF joint limits and cleaned of isolated glitches (`docs/dataset.md`
    lists every check).

    **Returns:** a `Dataset`. Raises `DatasetError` naming the file, the field
    path or line, and the value at fault.
    """
    root = Path(path)
    if not root.is_dir():
        raise DatasetError(f"{root}: dataset directory not found")
    meta_path = root / "metadata.json"
    meta = sc.read_json(meta_path, "metadata file")
    loc = Loc(meta_path)
    if not isinstance(meta, dict):
        raise loc.expected("a JSON object (the metadata of docs/dataset.md)", meta)
    if meta.get("schema") != SCHEMA:
        raise DatasetError(
            f"{meta_path}: field 'schema' must be {SCHEMA!r}, got {sc.show(meta.get('schema'))}"
        )
    version = meta.get("schema_version")
    if version != SCHEMA_VERSION or isinstance(version, bool):
        raise DatasetError(
            f"{meta_path}: unknown schema_version {sc.show(version)}; this jaxcal reads version {SCHEMA_VERSION}"
        )
    sc.obj(meta, loc, required=META_REQUIRED, optional=META_OPTIONAL, ignored=META_IGNORED)
    if "description" in meta:
        sc.string(meta["description"], loc.key("description"), allow_empty=True)
    urdf, base_link, flange_link, joints, limits, links = _robot(meta, loc.key("robot"), root)
    cameras = _cameras(meta, loc.key("cameras"), links)
    targets = _targets(meta, loc.key("targets"), links)
    emeta = _encoder_meta(meta, loc.key("encoders"))
    offset, drift = _clock(meta, loc.key("clock"))
    segments, homes = _motion(meta, loc.key("motion"), joints)
    notes = []
    truth_path = root / "truth.json"
    frames = _frames(root, cameras, loc)
    truth = None
    if truth_path.exists():
        truth = _truth(truth_path, joints, cameras, targets, len(frames["file"]))
    enc_t = enc_m = None
    glitches = ()
    if emeta is not None:
        enc_t, enc_m, glitches, more = _encoders(root, emeta, loc.key("encoders"), joints, limits)
        notes += more
    elif (root / "encoders.csv").exists():
        notes.append(f"{root / 'encoders.csv'} is not used: {loc.key('encoders')} is null")
    return Dataset(
        root=root,
        metadata=meta,
        robot_urdf=urdf,
        base_link=base_link,
        flange_link=flange_link,
        cameras=cameras,
        targets=targets,
        joint_names=joints,
        frames=frames,
        encoder_t=enc_t,
        encoder_motor=enc_m,
        clock_offset_s=offset,
        clock_drift_ppm=drift,
        segments=segments,
        segment_homes=homes,
        truth=truth,
        joint_limits=limits,
        encoder_unit=None if emeta is None else emeta["unit"],
        encoder_glitches=glitches,
        notes=tuple(notes),
    )
