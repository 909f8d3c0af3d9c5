"""Capture plans as data: what the robot does and when the camera shoots, before any image exists.

A `CapturePlan` names the robot, the camera (intrinsics and where it is: fixed in
the world, or on the flange), the target (a ChArUco plate on the flange, or a
board in the world for a camera on the flange), the taught pose the robot starts
from, and a list of segments:

- `Sweep`: one joint turns alone from `start` to `end` (commanded, rad) with the
  other joints at `home`, filmed in `frames` frames evenly spaced in time; the
  design of the seed method (`jaxcal simulate`'s sweeps are `home = 0`).
- `PoseSet`: stop-and-shoot: the robot moves to each configuration of `poses`,
  stands still for `hold_s` and the camera takes one frame in the middle.
- `FreeMotion`: every joint at once through timed waypoints, filmed throughout
  (the capture for markers on every link).

`CapturePlan.motion()` turns the plan into a timed path (waypoints joined by
smooth steps, zero velocity at each waypoint), the recorded stretches and the
frame times, which `jaxcal simulate-plan` renders and `jaxcal.evaluate_plan`
pre-evaluates. `plan_to_dict` / `plan_from_dict` are the JSON file's object
(`docs/plan.md`; `jaxcal.planning.save_plan` / `load_plan` write and read the file):
every field is checked and every error is a `PlanFileError` naming the file and the field.
"""

from dataclasses import dataclass, field, replace

import numpy as np

from ..errors import DatasetError, PlanFileError
from ..markers import TargetSpec
from ._schema import Loc, array, file_name, integer, names, number, obj, pose, string

SCHEMA = "jaxcal.plan"
SCHEMA_VERSION = 1
#: Shortest move between two waypoints (s), whatever the speed.
MIN_MOVE_S = 0.2


@dataclass(frozen=True, eq=False)
class PlanCamera:
    """A pinhole camera: `K` (px, OpenCV's pixel-centre convention), OpenCV's
    `distortion` (k1, k2, p1, p2, k3), the image size, and its pose `T_mount_cam`
    (OpenCV axes) in `mount`'s frame: `"world"` (the robot base frame) for a
    fixed camera, or the flange link for a camera on the arm (eye-in-hand)."""

    name: str
    width: int
    height: int
    K: np.ndarray
    distortion: np.ndarray
    mount: str
    T_mount_cam: np.ndarray


@dataclass(frozen=True, eq=False)
class PlanTarget:
    """The target: its `TargetSpec`, the link it rides on (the flange, or `"world"`
    for the board an eye-in-hand camera films) and its pose `T_link_target` there."""

    spec: TargetSpec
    link: str
    T_link_target: np.ndarray


@dataclass(frozen=True, eq=False)
class Sweep:
    """Joint `joint` turns alone from `start` to `end` (commanded, rad or m) at mean
    speed `speed` (rad/s), the other joints at `home` (the sweeping joint's entry
    is ignored); `frames` frames evenly spaced in time."""

    joint: str
    home: np.ndarray
    start: float
    end: float
    frames: int
    speed: float = 0.5
    kind: str = field(default="sweep", init=False)


@dataclass(frozen=True, eq=False)
class PoseSet:
    """Stop-and-shoot: the robot moves to each row of `poses` (commanded, `(N, joints)`)
    with its fastest joint at mean speed `speed` (rad/s), stands still `hold_s` seconds
    and the camera takes one frame in the middle."""

    poses: np.ndarray
    speed: float = 1.0
    hold_s: float = 0.2
    kind: str = field(default="poses", init=False)


@dataclass(frozen=True, eq=False)
class FreeMotion:
    """Every joint at once through `waypoints` `(K, joints)` at `times` `(K,)` (s, from
    the segment's start, the first 0), filmed in `frames` frames evenly spaced in time."""

    times: np.ndarray
    waypoints: np.ndarray
    frames: int
    kind: str = field(default="free", init=False)


@dataclass(frozen=True)
class Correction:
    """What the feasibility check did to one frame of the plan: `action` `"moved"`
    (toward the taught pose, `fraction` of the way from the taught pose it kept)
    or `"dropped"`, and the `reason` (a check's name) that made it fail first."""

    segment: int
    index: int
    action: str
    reason: str
    fraction: float = 0.0


@dataclass(frozen=True, eq=False)
class CapturePlan:
    """A capture plan (see the module docstring).

    - `robot`: a shipped robot's name (`"ur5e"`, `"panda"`) or a URDF path;
      `joints`: its movable joints, base to tip.
    - `camera`, `target`: `PlanCamera`, `PlanTarget`.
    - `taught`: the taught pose the robot starts and ends at (commanded).
    - `segments`: `Sweep`, `PoseSet` or `FreeMotion`, in capture order.
    - `floor_z`: height of the floor in the base frame (m), `None` for none.
    - `checks`: the feasibility limits used (`FeasibilityLimits` fields).
    - `corrections`: per frame the feasibility check moved or dropped.
    - `prediction`: the pre-evaluation's summary when the plan was made.
    - `description`: free text.
    """

    robot: str
    joints: tuple[str, ...]
    camera: PlanCamera
    target: PlanTarget
    taught: np.ndarray
    segments: tuple
    floor_z: float | None = None
    checks: dict = field(default_factory=dict)
    corrections: tuple[Correction, ...] = ()
    prediction: dict | None = None
    description: str = ""

    @property
    def eye_in_hand(self) -> bool:
        return self.camera.mount != "world"

    @property
    def frames(self) -> int:
        """Frames the plan takes (one per pose of a pose set)."""
        return sum(len(s.poses) if isinstance(s, PoseSet) else s.frames for s in self.segments)

    def motion(self) -> "PlanMotion":
        """The timed path, its recorded stretches and the frame times (see `PlanMotion`)."""
        return plan_motion(self)

    def views(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every frame's commanded configuration `(F, joints)`, controller time `(F,)`
        and segment index `(F,)`, in capture order."""
        m = self.motion()
        return m.at(m.frame_times), m.frame_times, m.frame_segment

    def with_segments(self, segments, corrections=(), prediction=None) -> "CapturePlan":
        return replace(self, segments=tuple(segments), corrections=tuple(corrections), prediction=prediction)


@dataclass(frozen=True, eq=False)
class PlanMotion:
    """A plan as time: waypoints `times (K,)`, `q (K, joints)` joined by smooth steps
    $q_i + (q_{i+1} - q_i)(1 - \\cos \\pi s)/2$ (as `jaxcal.sim.motion.Trajectory`),
    the recorded `segments` `(joint name or None, start, end)` on the controller
    clock, and the frame times `frame_times (F,)` with each frame's segment."""

    times: np.ndarray
    q: np.ndarray
    segments: tuple
    frame_times: np.ndarray
    frame_segment: np.ndarray

    def at(self, t) -> np.ndarray:
        """Commanded joint positions at controller times `t`."""
        t = np.clip(np.asarray(t, np.float64), self.times[0], self.times[-1])
        i = np.clip(np.searchsorted(self.times, t, side="right") - 1, 0, len(self.times) - 2)
        s = (t - self.times[i]) / (self.times[i + 1] - self.times[i])
        w = 0.5 * (1.0 - np.cos(np.pi * s))
        return self.q[i] + (self.q[i + 1] - self.q[i]) * w[..., None]


def _move_time(a, b, speed: float) -> float:
    return max(MIN_MOVE_S, float(np.max(np.abs(np.asarray(b) - np.asarray(a)))) / speed)


def plan_motion(plan: CapturePlan) -> PlanMotion:
    """The timed path of `plan`: from the taught pose through every segment and back."""
    n = len(plan.joints)
    q_prev = np.asarray(plan.taught, np.float64)
    times, qs, segments, frames, frame_seg = [0.0], [q_prev], [], [], []

    def go(q, speed):
        nonlocal q_prev
        times.append(times[-1] + _move_time(q_prev, q, speed))
        qs.append(np.asarray(q, np.float64))
        q_prev = qs[-1]

    def stay(seconds):
        times.append(times[-1] + seconds)
        qs.append(q_prev)

    for k, seg in enumerate(plan.segments):
        if isinstance(seg, Sweep):
            j = plan.joints.index(seg.joint)
            a, b = np.array(seg.home, np.float64), np.array(seg.home, np.float64)
            a[j], b[j] = seg.start, seg.end
            go(a, max(seg.speed, 1.0))
            t0 = times[-1]
            go(b, seg.speed)
            segments.append((seg.joint, t0, times[-1]))
            dt = (times[-1] - t0) / seg.frames
            frames.append(t0 + dt * (np.arange(seg.frames) + 0.5))
            frame_seg.append(np.full(seg.frames, k))
        elif isinstance(seg, PoseSet):
            for p in np.asarray(seg.poses, np.float64).reshape(-1, n):
                go(p, seg.speed)
                t0 = times[-1]
                stay(seg.hold_s)
                segments.append((None, t0, times[-1]))
                frames.append(np.array([0.5 * (t0 + times[-1])]))
                frame_seg.append(np.array([k]))
        else:
            wp = np.asarray(seg.waypoints, np.float64)
            go(wp[0], 1.0)
            t0 = times[-1]
            for t, q in zip(np.asarray(seg.times)[1:], wp[1:]):
                times.append(t0 + float(t))
                qs.append(q)
                q_prev = q
            segments.append((None, t0, times[-1]))
            dt = (times[-1] - t0) / seg.frames
            frames.append(t0 + dt * (np.arange(seg.frames) + 0.5))
            frame_seg.append(np.full(seg.frames, k))
    go(np.asarray(plan.taught, np.float64), 1.0)
    return PlanMotion(
        times=np.asarray(times),
        q=np.stack(qs),
        segments=tuple(segments),
        frame_times=np.concatenate(frames) if frames else np.zeros(0),
        frame_segment=np.concatenate(frame_seg).astype(int) if frame_seg else np.zeros(0, int),
    )


# --------------------------------------------------------------------------- JSON


def _list(a) -> list:
    return np.asarray(a, np.float64).tolist()


def segment_to_dict(seg) -> dict:
    if isinstance(seg, Sweep):
        return {
            "kind": "sweep",
            "joint": seg.joint,
            "home": _list(seg.home),
            "start": float(seg.start),
            "end": float(seg.end),
            "frames": int(seg.frames),
            "speed": float(seg.speed),
        }
    if isinstance(seg, PoseSet):
        return {
            "kind": "poses",
            "poses": _list(seg.poses),
            "speed": float(seg.speed),
            "hold_s": float(seg.hold_s),
        }
    return {
        "kind": "free",
        "times": _list(seg.times),
        "waypoints": _list(seg.waypoints),
        "frames": int(seg.frames),
    }


def plan_to_dict(plan: CapturePlan) -> dict:
    """The JSON object of `plan` (`docs/plan.md`)."""
    cam, tgt = plan.camera, plan.target
    return {
        "schema": SCHEMA,
        "schema_version": SCHEMA_VERSION,
        "description": plan.description,
        "robot": plan.robot,
        "joints": list(plan.joints),
        "camera": {
            "name": cam.name,
            "width": int(cam.width),
            "height": int(cam.height),
            "K": _list(cam.K),
            "distortion": _list(cam.distortion),
            "mount": cam.mount,
            "T_mount_cam": _list(cam.T_mount_cam),
        },
        "target": {"spec": tgt.spec.to_dict(), "link": tgt.link, "T_link_target": _list(tgt.T_link_target)},
        "taught": _list(plan.taught),
        "floor_z": None if plan.floor_z is None else float(plan.floor_z),
        "checks": dict(plan.checks),
        "segments": [segment_to_dict(s) for s in plan.segments],
        "corrections": [
            {
                "segment": c.segment,
                "index": c.index,
                "action": c.action,
                "reason": c.reason,
                "fraction": c.fraction,
            }
            for c in plan.corrections
        ],
        "prediction": plan.prediction,
    }


#: The checks' names and limits a plan may record (`jaxcal.planning.FeasibilityLimits`).
CHECK_FIELDS = (
    "view_angle_deg",
    "margin_px",
    "min_corner_px",
    "min_distance",
    "max_distance",
    "clearance",
    "joint_margin",
)


def _segment(x, loc: Loc, joints: tuple[str, ...]):
    n = len(joints)
    if not isinstance(x, dict):
        raise loc.expected("a JSON object", x)
    if "kind" not in x:
        raise loc.fail("missing field 'kind' (one of 'sweep', 'poses', 'free')")
    kind = string(x["kind"], loc.key("kind"), choices=("sweep", "poses", "free"))
    if kind == "sweep":
        obj(x, loc, required=("kind", "joint", "home", "start", "end", "frames"), optional=("speed",))
        seg = Sweep(
            joint=string(x["joint"], loc.key("joint"), choices=joints),
            home=array(x["home"], loc.key("home"), (n,)),
            start=number(x["start"], loc.key("start")),
            end=number(x["end"], loc.key("end")),
            frames=integer(x["frames"], loc.key("frames"), 2, 100000),
            speed=number(x.get("speed", 0.5), loc.key("speed"), above=0.0),
        )
        if seg.start == seg.end:
            raise loc.fail("a sweep needs start != end")
        return seg
    if kind == "poses":
        obj(x, loc, required=("kind", "poses"), optional=("speed", "hold_s"))
        poses = array(x["poses"], loc.key("poses"), (None, n))
        if len(poses) == 0:
            raise loc.key("poses").fail("a pose set needs at least one pose")
        return PoseSet(
            poses=poses,
            speed=number(x.get("speed", 1.0), loc.key("speed"), above=0.0),
            hold_s=number(x.get("hold_s", 0.2), loc.key("hold_s"), above=0.0),
        )
    obj(x, loc, required=("kind", "times", "waypoints", "frames"))
    times = array(x["times"], loc.key("times"), (None,))
    wp = array(x["waypoints"], loc.key("waypoints"), (len(times), n))
    if len(times) < 2 or times[0] != 0.0 or np.any(np.diff(times) <= 0):
        raise loc.key("times").fail("expected at least 2 strictly increasing times starting at 0")
    return FreeMotion(times=times, waypoints=wp, frames=integer(x["frames"], loc.key("frames"), 2, 100000))


#: Farthest a camera or a target may be placed (m): more is millimetres read as metres.
MAX_PLACEMENT_M = 20.0


def check_placement(T: np.ndarray, loc) -> np.ndarray:
    """`T` (4x4, m) unless its translation is beyond `MAX_PLACEMENT_M`: millimetres given as metres."""
    d = float(np.linalg.norm(T[:3, 3]))
    if d > MAX_PLACEMENT_M:
        raise PlanFileError(
            f"{loc}: translation {np.round(T[:3, 3], 3).tolist()} is {d:.0f} m away; lengths are in metres "
            "(millimetres given as metres?)"
        )
    return T


def _camera(x, loc: Loc) -> PlanCamera:
    obj(x, loc, required=("width", "height", "K", "mount", "T_mount_cam"), optional=("name", "distortion"))
    w = integer(x["width"], loc.key("width"), 1, 65535)
    h = integer(x["height"], loc.key("height"), 1, 65535)
    K = array(x["K"], loc.key("K"), (3, 3))
    if not (K[0, 0] > 0 and K[1, 1] > 0 and np.allclose(K[2], (0, 0, 1)) and K[1, 0] == K[2, 0] == 0):
        raise loc.key("K").fail(
            f"expected a camera matrix (fx, fy > 0, bottom row [0, 0, 1]), got {K.tolist()}"
        )
    dist = array(x.get("distortion", [0.0] * 5), loc.key("distortion"), (5,))
    return PlanCamera(
        name=file_name(x.get("name", "cam0"), loc.key("name")),
        width=w,
        height=h,
        K=K,
        distortion=dist,
        mount=string(x["mount"], loc.key("mount")),
        T_mount_cam=check_placement(pose(x["T_mount_cam"], loc.key("T_mount_cam")), loc.key("T_mount_cam")),
    )


def target_from_dict(x, loc: Loc) -> PlanTarget:
    obj(x, loc, required=("spec", "link", "T_link_target"))
    try:
        spec = TargetSpec.from_dict(
            obj(x["spec"], loc.key("spec"), optional=TargetSpec.__dataclass_fields__),
            where=str(loc.key("spec")),
        )
    except (TypeError, ValueError) as e:
        raise PlanFileError(str(e) if str(loc.file) in str(e) else f"{loc.key('spec')}: {e}") from None
    T = check_placement(pose(x["T_link_target"], loc.key("T_link_target")), loc.key("T_link_target"))
    return PlanTarget(spec, string(x["link"], loc.key("link")), T)


def plan_from_dict(x, path="plan") -> CapturePlan:
    """A `CapturePlan` from its JSON object, every field checked (a `PlanFileError`
    naming the file and the field)."""
    try:
        return _plan_from_dict(x, Loc(path))
    except DatasetError as e:
        raise PlanFileError(str(e)) from None


def _plan_from_dict(x, loc: Loc) -> CapturePlan:
    required = ("schema", "schema_version", "robot", "joints", "camera", "target", "taught", "segments")
    optional = ("description", "floor_z", "checks", "corrections", "prediction")
    obj(x, loc, required=required, optional=optional)
    string(x["schema"], loc.key("schema"), choices=(SCHEMA,))
    integer(x["schema_version"], loc.key("schema_version"), SCHEMA_VERSION, SCHEMA_VERSION)
    joints = tuple(names(x["joints"], loc.key("joints")))
    n = len(joints)
    camera = _camera(x["camera"], loc.key("camera"))
    target = target_from_dict(x["target"], loc.key("target"))
    if camera.mount == "world" and target.link == "world":
        raise loc.fail(
            "the camera and the target cannot both be fixed in the world (one rides on the flange)"
        )
    if camera.mount != "world" and target.link != "world":
        raise loc.fail(
            f"camera.mount {camera.mount!r} puts the camera on the arm, so the target must be fixed in the "
            f"world (target.link 'world'), got target.link {target.link!r}"
        )
    segs = x["segments"]
    if not isinstance(segs, list) or not segs:
        raise loc.key("segments").expected("a non-empty list of segments", segs)
    segments = tuple(_segment(s, loc.key("segments").index(i), joints) for i, s in enumerate(segs))
    floor = x.get("floor_z")
    checks = obj(x.get("checks", {}) or {}, loc.key("checks"), optional=CHECK_FIELDS)
    checks = {k: number(v, loc.key("checks").key(k)) for k, v in checks.items()}
    corrections = []
    cs = x.get("corrections", []) or []
    if not isinstance(cs, list):
        raise loc.key("corrections").expected("a list", cs)
    for i, c in enumerate(cs):
        cl = loc.key("corrections").index(i)
        obj(c, cl, required=("segment", "index", "action", "reason"), optional=("fraction",))
        corrections.append(
            Correction(
                segment=integer(c["segment"], cl.key("segment"), 0),
                index=integer(c["index"], cl.key("index"), 0),
                action=string(c["action"], cl.key("action"), choices=("moved", "dropped")),
                reason=string(c["reason"], cl.key("reason")),
                fraction=number(c.get("fraction", 0.0), cl.key("fraction"), 0.0, 1.0),
            )
        )
    prediction = x.get("prediction")
    if prediction is not None and not isinstance(prediction, dict):
        raise loc.key("prediction").expected("an object or null", prediction)
    return CapturePlan(
        robot=string(x["robot"], loc.key("robot")),
        joints=joints,
        camera=camera,
        target=target,
        taught=array(x["taught"], loc.key("taught"), (n,)),
        segments=segments,
        floor_z=None if floor is None else number(floor, loc.key("floor_z")),
        checks=checks,
        corrections=tuple(corrections),
        prediction=prediction,
        description=string(x.get("description", ""), loc.key("description"), allow_empty=True),
    )
