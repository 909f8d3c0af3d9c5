"""`jaxcal inspect`: what a capture holds, in seconds, before a calibration is started.

`inspect_dataset(path)` loads a dataset (every check of `load_dataset`) and
summarises it without any fit: the cameras (image size, whether K is given,
mount), the motion segments (from the metadata, else found in the encoder
log as `import-bag` does) with the frames of each camera in each and the
range each sweep covers in the encoder log, the overlap of the camera and
controller clocks, the detection rate of every target on a small sample of
frames, and the capture kind `jaxcal calibrate` will resolve. For a tracker
dataset: the device and, per joint, its samples, time span and range.
"""

import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from .io._rosmsgs import find_segments, segment_tuples
from .io.dataset import Dataset, load_dataset
from .records import Named, Record, keyed, named, optional
from .stages._setup import device_kind
from .stages.kinds import CaptureKind
from .vision import detect


@dataclass(frozen=True, eq=False)
class RobotFile(Record):
    """The robot file (under `urdf` or `table`, and as `file`) and its joints."""

    urdf: str | None = optional()
    table: str | None = optional()
    file: str = ""
    joints: tuple[str, ...] = ()


@dataclass(frozen=True, eq=False)
class CameraSummary(Record):
    name: str
    #: Image width and height (px).
    size: tuple[int, int]
    K_given: bool
    mount: str
    frames: int


@dataclass(frozen=True, eq=False)
class TargetSummary(Record):
    name: str
    kind: str
    link: str


@dataclass(frozen=True, eq=False)
class EncoderSummary(Record):
    samples: int
    unit: str
    glitches: int


@dataclass(frozen=True, eq=False)
class SegmentSummary(Record):
    """A motion segment: its joint (None: every joint, poses), span (s), frames per camera and range."""

    joint: str | None
    start_s: float
    end_s: float
    frames: tuple[Named, ...] = named()
    #: The range the joint covers in the encoder log: mm (prismatic) or deg (revolute).
    range_mm: tuple[float, float] | None = optional()
    range_deg: tuple[float, float] | None = optional()


@dataclass(frozen=True, eq=False)
class ClockSummary(Record):
    """The metadata's offset (None: unknown) and the camera's and encoders' spans (s) and overlap."""

    offset_s: float | None
    camera_s: tuple[float, float]
    encoders_s: tuple[float, float] | None = optional()
    overlap_s: float | None = optional()
    frames_outside_log: int | None = optional()


@dataclass(frozen=True, eq=False)
class DetectionSample(Record):
    """A camera's sampled frames and, per target, in how many it was detected."""

    camera: str
    frames: int
    found: tuple[Named, ...] = named()


@dataclass(frozen=True, eq=False)
class Inspection(Record):
    """`inspect_dataset`'s summary of a camera dataset (reads as its JSON, `jaxcal inspect --json`)."""

    dataset: str
    robot: RobotFile
    cameras: tuple[CameraSummary, ...]
    targets: tuple[TargetSummary, ...]
    encoders: EncoderSummary | None
    segments_from: str
    segments: tuple[SegmentSummary, ...]
    clock: ClockSummary
    detection_sample: tuple[DetectionSample, ...] = keyed("camera")
    kind: str = ""
    camera_of_the_fit: str = ""
    notes: tuple[str, ...] = ()
    seconds: float = 0.0


@dataclass(frozen=True, eq=False)
class DeviceSummary(Record):
    name: str
    kind: str
    file: str
    point: str
    link: str
    samples: int
    orientations: bool
    joint_positions: bool


@dataclass(frozen=True, eq=False)
class TrackerJoint(Record):
    """A joint's samples, their time span (s) and the range the joint covers."""

    joint: str
    samples: int
    time_s: tuple[float, float] | None = optional()
    range_mm: tuple[float, float] | None = optional()
    range_deg: tuple[float, float] | None = optional()


@dataclass(frozen=True, eq=False)
class TrackerInspection(Record):
    """`inspect_dataset`'s summary of a tracker dataset."""

    dataset: str
    robot: RobotFile
    device: DeviceSummary
    joints: tuple[TrackerJoint, ...]
    unassigned_samples: int
    kind: str
    notes: tuple[str, ...]
    seconds: float


def _segments(ds: Dataset, q) -> tuple[list, str]:
    if ds.segments:
        return list(ds.segments), "metadata.json"
    if q is None:
        return [], "none (no 'motion' and no encoder log)"
    found, _ = find_segments(ds.encoder_t, q, ds.joint_names)
    return segment_tuples(found), "found in the encoder log (not in metadata.json)"


def _joint_range(ds: Dataset, joint: str, values) -> dict[str, tuple[float, float]]:
    """The range one joint covers, as the record's fields: `range_mm` for a
    prismatic joint (m in the log), `range_deg` for a revolute one."""
    v = np.asarray(values)
    if ds.joint_limits[joint].joint_type == "prismatic":
        return {"range_mm": (1e3 * float(v.min()), 1e3 * float(v.max()))}
    return {"range_deg": (float(np.degrees(v.min())), float(np.degrees(v.max())))}


def _format_range(g: SegmentSummary | TrackerJoint, verb: str = "sweeps") -> str:
    if g.range_mm is not None:
        return f", travels {g.range_mm[0]:.1f} .. {g.range_mm[1]:.1f} mm"
    if g.range_deg is not None:
        return f", {verb} {g.range_deg[0]:.1f} .. {g.range_deg[1]:.1f} deg"
    return ""


def _sweeps(ds: Dataset, q, segments, offset: float) -> tuple[SegmentSummary, ...]:
    out = []
    for joint, start, end in segments:
        frames = []
        for cam in ds.cameras:
            t = ds.frames.timestamp[ds.frames.camera == cam.name] - offset
            frames.append(Named(cam.name, int(np.count_nonzero((t >= start) & (t <= end)))))
        rng = {}
        if q is not None and joint is not None:
            j = ds.joint_names.index(joint)
            inside = (ds.encoder_t >= start) & (ds.encoder_t <= end)
            if inside.any():
                rng = _joint_range(ds, joint, q[inside, j])
        out.append(SegmentSummary(joint, start, end, frames=tuple(frames), **rng))
    return tuple(out)


def _detection_sample(ds: Dataset, sample: int) -> tuple[DetectionSample, ...]:
    """Per camera: the sampled rows (evenly spread) and, per target, in how many a detection came back."""
    out = []
    for cam in ds.cameras:
        rows = np.flatnonzero(ds.frames.camera == cam.name)
        pick = rows[np.unique(np.linspace(0, len(rows) - 1, min(sample, len(rows))).round().astype(int))]
        found = dict.fromkeys((t.name for t in ds.targets), 0)
        for i in pick:
            image = cv2.imread(str(ds.image_path(i)), cv2.IMREAD_UNCHANGED)
            for t in ds.targets:
                d = detect(image, t.spec, K=cam.K, dist=None if cam.K is None else cam.dist)
                found[t.name] += d is not None
        out.append(DetectionSample(cam.name, int(len(pick)), found=named_counts(found)))
    return tuple(out)


def _tracker_summary(ds: Dataset, path, t0: float) -> TrackerInspection:
    """`inspect_dataset` for a tracker dataset: the device, and per joint its
    samples, their time span and the range the joint covers (when the table
    gives joint positions)."""
    d, s = ds.device, ds.samples
    kind = device_kind(ds)
    joints = []
    for j, name in enumerate(ds.joint_names):
        # Stop-and-shoot poses: every sample moves every joint; sweeps: the joint's own samples.
        rows = np.ones(len(s.sample), bool) if kind.fits_points else s.joint == j
        extra = {}
        if rows.any():
            extra["time_s"] = (float(s.timestamp[rows].min()), float(s.timestamp[rows].max()))
            if s.q is not None:
                extra |= _joint_range(ds, name, s.q[rows, j])
        joints.append(TrackerJoint(name, int(np.count_nonzero(rows)), **extra))
    return TrackerInspection(
        dataset=str(Path(path)),
        robot=_robot(ds),
        device=DeviceSummary(
            name=d.name,
            kind=d.kind,
            file=d.file,
            point=d.point,
            link=d.link,
            samples=int(len(s.sample)),
            orientations=s.orientation is not None,
            joint_positions=s.q is not None,
        ),
        joints=tuple(joints),
        unassigned_samples=0 if kind.fits_points else int(np.count_nonzero(s.joint < 0)),
        kind=kind.describe(),
        notes=tuple(ds.notes),
        seconds=time.perf_counter() - t0,
    )


def _robot(ds: Dataset) -> RobotFile:
    """The summary's robot: its file (under `urdf` or `table`, and as `file`) and joints."""
    name = ds.robot_urdf.name
    return RobotFile(
        urdf=None if ds.robot_is_table else name,
        table=name if ds.robot_is_table else None,
        file=name,
        joints=tuple(ds.joint_names),
    )


def named_counts(d: dict) -> tuple[Named, ...]:
    """`Named` rows of a `{name: count}` mapping."""
    return tuple(Named(k, v) for k, v in d.items())


def _format_tracker(s: TrackerInspection) -> str:
    d = s.device
    lines = [
        f"{s.dataset}: {s.robot.file}, joints {', '.join(s.robot.joints)}",
        f"device {d.name} ({d.kind}): {d.samples} samples in {d.file} of point {d.point} on "
        f"{d.link}; "
        + ("orientations" if d.orientations else "positions only")
        + (", joint positions given" if d.joint_positions else ", no joint positions"),
    ]
    poses = "stop-and-shoot" in s.kind
    for g in s.joints:
        span = f", {g.time_s[0]:.3f}-{g.time_s[1]:.3f} s" if g.time_s is not None else ""
        rng = _format_range(g, "stands at" if poses else "sweeps")
        lines.append(f"  {g.joint}: {g.samples} samples{span}{rng}")
    if s.unassigned_samples:
        lines.append(f"  {s.unassigned_samples} samples name no joint")
    lines.append(f"capture kind: {s.kind}")
    lines += [f"note: {n}" for n in s.notes]
    lines.append(f"({s.seconds:.1f} s)")
    return "\n".join(lines)


def inspect_dataset(path, *, sample: int = 5) -> Inspection | TrackerInspection:
    """A summary of the dataset at `path` (see the module docstring): a typed record that
    reads as its JSON (`plain(summary)`, `summary["kind"]`)."""
    t0 = time.perf_counter()
    ds = load_dataset(path)
    if ds.device is not None:
        return _tracker_summary(ds, path, t0)
    model = ds.load_model()
    ratio = np.asarray(model.reduction_ratio, np.float64)
    q = None if ds.encoder_t is None else ds.encoder_motor / ratio
    segments, source = _segments(ds, q)
    offset = 0.0 if ds.clock_offset_s is None else ds.clock_offset_s
    cam_t = ds.frames.timestamp - offset
    clock = ClockSummary(ds.clock_offset_s, (float(cam_t.min()), float(cam_t.max())))
    if ds.encoder_t is not None:
        lo, hi = max(cam_t.min(), ds.encoder_t[0]), min(cam_t.max(), ds.encoder_t[-1])
        clock = dataclasses.replace(
            clock,
            encoders_s=(float(ds.encoder_t[0]), float(ds.encoder_t[-1])),
            overlap_s=float(max(0.0, hi - lo)),
            frames_outside_log=int(np.count_nonzero((cam_t < ds.encoder_t[0]) | (cam_t > ds.encoder_t[-1]))),
        )
    flange = model.link_names[-1]
    fixed = [c for c in ds.cameras if c.mount == "world"]
    cam = (fixed or list(ds.cameras))[0]
    kind = CaptureKind.of(
        camera_on_flange=cam.mount == flange,
        segments=tuple(segments),
        encoders=ds.encoder_t is not None,
        link_targets=any(t.link not in (flange, "world") for t in ds.targets),
    )
    return Inspection(
        dataset=str(Path(path)),
        robot=_robot(ds),
        cameras=tuple(
            CameraSummary(
                name=c.name,
                size=(c.width, c.height),
                K_given=c.K is not None,
                mount=c.mount,
                frames=int(np.count_nonzero(ds.frames.camera == c.name)),
            )
            for c in ds.cameras
        ),
        targets=tuple(TargetSummary(t.name, t.spec.kind, t.link) for t in ds.targets),
        encoders=None
        if ds.encoder_t is None
        else EncoderSummary(int(len(ds.encoder_t)), ds.encoder_unit, len(ds.encoder_glitches)),
        segments_from=source,
        segments=_sweeps(ds, q, segments, offset),
        clock=clock,
        detection_sample=_detection_sample(ds, sample),
        kind=kind.describe(),
        camera_of_the_fit=cam.name,
        notes=tuple(ds.notes),
        seconds=time.perf_counter() - t0,
    )


def format_inspection(s: Inspection | TrackerInspection) -> str:
    """`inspect_dataset`'s summary as text for the console."""
    if isinstance(s, TrackerInspection):
        return _format_tracker(s)
    lines = [f"{s.dataset}: {s.robot.file}, joints {', '.join(s.robot.joints)}"]
    for c in s.cameras:
        lines.append(
            f"camera {c.name}: {c.size[0]}x{c.size[1]}, {c.frames} frames, mount {c.mount}, "
            + ("K given" if c.K_given else "K null (self-calibrated from the images)")
        )
    lines.append("targets: " + ", ".join(f"{t.name} ({t.kind} on {t.link})" for t in s.targets))
    e = s.encoders
    lines.append(
        "encoder log: none"
        if e is None
        else f"encoder log: {e.samples} samples ({e.unit}), {e.glitches} glitches removed"
    )
    lines.append(f"motion segments ({s.segments_from}):")
    for g in s.segments:
        frames = ", ".join(f"{r.name} {r.value}" for r in g.frames)
        lines.append(
            f"  {g.joint or 'all joints (poses)'}: {g.start_s:.3f}-{g.end_s:.3f} s, frames {frames}{_format_range(g)}"
        )
    c = s.clock
    given = "unknown (estimated by calibrate)" if c.offset_s is None else f"{1e3 * c.offset_s:.3f} ms"
    line = f"clocks: offset {given}; camera {c.camera_s[0]:.3f}-{c.camera_s[1]:.3f} s"
    if c.encoders_s is not None:
        line += (
            f", encoders {c.encoders_s[0]:.3f}-{c.encoders_s[1]:.3f} s, overlap {c.overlap_s:.3f} s, "
            f"{c.frames_outside_log} frames outside the log"
        )
    lines.append(line)
    for d in s.detection_sample:
        found = ", ".join(f"{r.name} {r.value}/{d.frames}" for r in d.found)
        lines.append(f"detection on {d.frames} sample frames of {d.camera}: {found}")
    lines.append(f"capture kind: {s.kind} (camera {s.camera_of_the_fit})")
    lines += [f"note: {n}" for n in s.notes]
    lines.append(f"({s.seconds:.1f} s)")
    return "\n".join(lines)
