"""The dataset format (captured and synthetic alike); see `docs/dataset.md`.

```
DATASET/
  metadata.json     schema + version, robot file, cameras, targets, encoders, clock, motion segments
  robot.urdf        the nominal robot (the file metadata["robot"]["urdf"] names; or a
                    DH/MDH table, robot_dh.json, that metadata["robot"]["table"] names)
  frames.csv        camera,frame,timestamp,file        (camera clock, s)
  encoders.csv      timestamp,<joint 1>,...,<joint n>  (controller clock, s; motor angles, encoders.unit)
  images/<camera>/<frame>.png
  truth.json        synthetic datasets only: true model, camera and target poses, clock
```

A tracker dataset (an external measuring device: laser tracker, motion
capture, the controller's logged tool point) has a `device` field instead of
`cameras` and `targets`, and a samples table (`samples.csv`: per sample a
3-D point, optionally an orientation, its noise and the joint positions)
instead of `frames.csv` and images (`jaxcal.io._tracker`).

`load_dataset` checks every field of every file before any work (types,
ranges, image sizes from the file headers, timestamps, encoder units against
the URDF joint limits, encoder glitches) and raises `DatasetError` (a
`ValueError`) naming the file, field path or line, and the value. Nothing in
a dataset is modified. Writing is atomic: a dataset is assembled in a
temporary directory beside its destination and renamed into place
(`atomic_directory`, see `jaxcal.io._files`).
"""

import csv
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import DatasetError
from . import _schema as sc
from ._files import atomic_directory as atomic_directory
from ._files import resolved
from ._logs import EncoderGlitch as EncoderGlitch
from ._logs import FrameTable as FrameTable
from ._logs import read_encoders, read_frames
from ._metadata import CameraInfo as CameraInfo
from ._metadata import Payload as Payload
from ._metadata import TargetInfo as TargetInfo
from ._metadata import (
    read_cameras,
    read_clock,
    read_encoder_meta,
    read_motion,
    read_payload,
    read_robot,
    read_targets,
)
from ._schema import Loc
from ._tracker import DeviceInfo as DeviceInfo
from ._tracker import PointTarget as PointTarget
from ._tracker import TrackerSamples as TrackerSamples
from ._tracker import read_device, read_samples, sample_frames
from ._truth import SimulationRecord as SimulationRecord
from ._truth import TruePoses as TruePoses
from ._truth import read_truth
from ._truth import simulation_record as simulation_record
from ._truth import true_poses as true_poses
from .dh_tables import dh_table_model, is_table_file
from .urdf import load_urdf

SCHEMA = "jaxcal.dataset"
SCHEMA_VERSION = 1
#: Top-level metadata fields that are read, and the ones allowed but not read
#: (`simulation`: the configuration `jaxcal simulate` records). Keys starting
#: with `x_` are free for the user's own notes at every level.
META_REQUIRED = ("schema", "schema_version", "robot", "cameras", "targets")
META_OPTIONAL = ("description", "encoders", "clock", "motion")
META_IGNORED = ("simulation",)
#: ... and those of a tracker dataset (`device` in place of `cameras` and `targets`).
TRACKER_REQUIRED = ("schema", "schema_version", "robot", "device")


@dataclass(frozen=True, eq=False)
class Dataset:
    """A dataset read from disk and checked (see the module docstring for the layout).

    - `frames`: the `FrameTable`, arrays `camera` (str), `frame` (int), `timestamp`
      (camera clock, s), `file` (path relative to `root`), one entry per image.
    - `encoder_t` (T,) controller clock, s; `encoder_motor` (T, joints) motor
      angles in radians, whatever `encoders.unit` the file used; the rows of
      `encoder_glitches` are removed.
    - `clock_offset_s`: $t_{cam} - t_{controller}$ if known, else `None`.
    - `segments`: `(joint name or None, start, end)` on the controller clock;
      `segment_homes`: per segment the commanded configuration the other joints
      held (rad; the sweeping joint's entry zero), or None when not given.
    - `truth`: the parsed `truth.json` of a synthetic dataset, else `None`.
    - `robot_urdf`: the robot file: the URDF `metadata.robot.urdf` names, or the
      DH/MDH table `metadata.robot.table` names (then `robot_is_table`).
    - `joint_limits`: joint name -> `jaxcal.io.urdf.JointLimits` (URDF type,
      position and velocity limits, nominal reduction ratio; a table's
      `lower` / `upper` / `velocity`, `None` where it has none).
    - `encoder_unit`: the unit the encoder file was written in (`None`
      without a log).
    - `encoder_glitches`: the `EncoderGlitch`es found and removed at load.
    - `notes`: human-readable remarks from loading (glitches removed, fields
      not used) for the calibration to report.
    - `payload`: what the flange carries beyond the robot file's links (`robot.payload`:
      the plate's or tool's mass and centre; the non-geometric terms' gravity torques add it).
    - `device`, `samples`: a tracker dataset's measuring device (`DeviceInfo`)
      and its samples (`TrackerSamples`); `cameras` and `targets` are then
      empty and `frames` has one row per sample (the device's name in the
      `camera` column, the sample index in `frame`, `file` naming the line).
    """

    root: Path
    metadata: dict
    robot_urdf: Path
    base_link: str | None
    flange_link: str | None
    cameras: tuple[CameraInfo, ...]
    targets: tuple[TargetInfo, ...]
    joint_names: tuple[str, ...]
    frames: FrameTable
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
    device: DeviceInfo | None = None
    samples: TrackerSamples | None = None
    payload: Payload | None = None

    @property
    def point(self) -> PointTarget | None:
        """A tracker dataset's measured point, in a target's role."""
        d = self.device
        return None if d is None else PointTarget(d.point, d.link, d.T_link_point)

    def camera(self, name: str) -> CameraInfo:
        for c in self.cameras:
            if c.name == name:
                return c
        raise KeyError(name)

    def image_path(self, i: int) -> Path:
        return self.root / self.frames.file[i]

    def in_encoder_glitch(self, t_controller) -> np.ndarray:
        """Which controller-clock times fall inside an encoder glitch's interval
        (`[t_start, t_end]` of any of `encoder_glitches`): bool array, shape of the input."""
        t = np.asarray(t_controller, np.float64)
        hit = np.zeros(t.shape, bool)
        for g in self.encoder_glitches:
            hit |= (t >= g.t_start) & (t <= g.t_end)
        return hit

    @property
    def robot_is_table(self) -> bool:
        """Whether the robot file (`robot_urdf`) is a DH/MDH table (`metadata.robot.table`), not a URDF."""
        return is_table_file(self.robot_urdf) and "table" in self.metadata.get("robot", {})

    def load_model(self):
        """The nominal `KinematicModel` from the dataset's robot file (its URDF, or its DH/MDH table)."""
        try:
            if self.robot_is_table:
                return dh_table_model(self.robot_urdf)
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


def finite_json(x):
    """`x` (plain JSON, NumPy arrays and scalars allowed) with every infinite or NaN number as
    null: JSON has none (`Infinity` and `NaN` are Python's extension, which strict readers, a
    robot's among them, refuse). `jaxcal._records_base.from_plain` reads null back as NaN where
    a number is due."""
    if isinstance(x, dict):
        return {k: finite_json(v) for k, v in x.items()}
    if isinstance(x, (list, tuple, np.ndarray)):
        return [finite_json(v) for v in x]
    if isinstance(x, (float, np.floating)):
        return float(x) if np.isfinite(x) else None
    return x.item() if isinstance(x, np.generic) else x


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


# --------------------------------------------------------------------------- load_dataset


def _segments_in_log(segments, enc_t: np.ndarray, loc, log: Path) -> list[str]:
    """The motion segments and the encoder log are both on the controller clock. Every segment
    outside the log's span says one of them is stamped on another clock (or in other units),
    which no clock offset can mend: refused. Some outside (a log cut short): a note each, since
    their frames will have no joint angles."""
    t0, t1 = float(enc_t[0]), float(enc_t[-1])
    outside = [
        (k, name, start, end) for k, (name, start, end) in enumerate(segments) if end < t0 or start > t1
    ]
    words = [
        f"{loc.index(k)}: segment [{start:g}, {end:g}] s ({name or 'poses'}) lies outside the encoder log "
        f"[{t0:g}, {t1:g}] s ({log})"
        for k, name, start, end in outside
    ]
    if outside and len(outside) == len(segments):
        raise DatasetError(
            f"{words[0]}, and so does every other segment; both are on the controller clock: is one of them "
            "stamped on another?"
        )
    return [f"{w}: its frames have no joint angles" for w in words]


#: A sweep's segment must move its own joint by at least this share of the joint's travel over
#: the log while another joint moves by more than `SWAPPED_OTHER` of its own; else refused.
SWAPPED_OWN, SWAPPED_OTHER = 0.1, 0.5


def _segments_move_their_joints(segments, enc_t, enc_m, joints, loc, log: Path) -> None:
    """Each sweep's segment against the encoder log (both on the controller clock): a segment
    during which its own joint stands still while another sweeps says the log's columns, or the
    segments' joints, are swapped. Refused naming both, before any clock fit fails on it."""
    travel = np.ptp(enc_m, axis=0)
    for k, (name, start, end) in enumerate(segments):
        inside = (enc_t >= start) & (enc_t <= end)
        if name not in joints or inside.sum() < 2:
            continue
        share = np.ptp(enc_m[inside], axis=0) / np.where(travel > 0, travel, np.inf)
        j, m = joints.index(name), int(np.argmax(share))
        if m != j and share[j] < SWAPPED_OWN and share[m] > SWAPPED_OTHER:
            raise DatasetError(
                f"{loc.index(k)}: during segment [{start:g}, {end:g}] s ({name}) the encoder log ({log}) moves "
                f"column {joints[m]!r} by {100 * share[m]:.0f} % of its travel and {name!r} by {100 * share[j]:.0f} "
                "%: are the log's columns, or the segments' joints, swapped?"
            )


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
        resolved(root)  # a loop of symbolic links is named as one
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
    tracker = isinstance(meta, dict) and "device" in meta
    sc.obj(
        meta,
        loc,
        required=TRACKER_REQUIRED if tracker else META_REQUIRED,
        optional=META_OPTIONAL,
        ignored=META_IGNORED,
    )
    if "description" in meta:
        sc.string(meta["description"], loc.key("description"), allow_empty=True)
    urdf, base_link, flange_link, joints, limits, links = read_robot(meta, loc.key("robot"), root)
    payload = read_payload(meta, loc.key("robot").key("payload"))
    device = samples = None
    if tracker:
        device = read_device(meta, loc.key("device"), links)
        cameras, targets = (), ()
    else:
        cameras = read_cameras(meta, loc.key("cameras"), links)
        targets = read_targets(meta, loc.key("targets"), links)
    emeta = read_encoder_meta(meta, loc.key("encoders"))
    offset, drift = read_clock(meta, loc.key("clock"))
    segments, homes = read_motion(meta, loc.key("motion"), joints)
    notes = []
    truth_path = root / "truth.json"
    if tracker:
        samples = read_samples(root, device, joints, limits, loc)
        frames = sample_frames(device, samples)
    else:
        frames = read_frames(root, cameras, loc)
    truth = None
    if truth_path.exists():
        named = (
            ((device,), (PointTarget(device.point, device.link, None),)) if tracker else (cameras, targets)
        )
        truth = read_truth(truth_path, joints, *named, (frames.camera, frames.frame))
    enc_t = enc_m = None
    glitches = ()
    if emeta is not None:
        enc_t, enc_m, glitches, more = read_encoders(root, emeta, loc.key("encoders"), joints, limits)
        notes += more
    elif (root / "encoders.csv").exists():
        notes.append(f"{root / 'encoders.csv'} is not used: {loc.key('encoders')} is null")
    if enc_t is not None:
        notes += _segments_in_log(segments, enc_t, loc.key("motion"), root / emeta["file"])
        _segments_move_their_joints(segments, enc_t, enc_m, joints, loc.key("motion"), root / emeta["file"])
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
        device=device,
        samples=samples,
        payload=payload,
    )
