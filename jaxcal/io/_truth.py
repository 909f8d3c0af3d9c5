"""Reading `truth.json`, the ground truth a synthetic dataset carries."""

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .._kinematics import KinematicModel
from . import _schema as sc
from ._files import atomic_directory as atomic_directory
from ._logs import MAX_FRAME_INDEX
from ._metadata import MAX_DRIFT_PPM
from ._schema import Loc
from .model_json import model_from_json

# --------------------------------------------------------------------------- reading: truth.json


@dataclass(frozen=True, eq=False)
class TruePoses:
    """What a `truth.json` (as `read_truth` returns it) says of the frames a calibration
    estimates, as arrays: per camera its pose in the base frame (when given) and on its mount,
    per target its pose on its link, the base in the world and the clock offset."""

    T_cam_base: dict[str, np.ndarray]
    T_mount_cam: dict[str, np.ndarray]
    T_link_target: dict[str, np.ndarray]
    T_world_base: np.ndarray
    clock_offset_s: float | None
    #: The true kinematic model.
    model: KinematicModel
    #: Per entry of the truth's `frames` (a rendered dataset's, one per row of `frames.csv`):
    #: each target's pose in the camera, and whether it is wholly in view.
    T_cam_target: tuple[dict[str, np.ndarray], ...] = ()
    visible: tuple[dict[str, bool], ...] = ()
    #: The capture indices dropped (images) and the bad tracker samples' indices.
    dropped_frames: tuple[int, ...] = ()
    bad_samples: tuple[int, ...] = ()
    #: Per entry of the truth's `frames`: its row of `frames.csv`, its camera, its controller
    #: time (s; a rendered frame's first row) and the true joint angles then (rad).
    frame_rows: tuple[int, ...] = ()
    frame_cameras: tuple[str, ...] = ()
    frame_t: np.ndarray | None = None
    frame_theta: np.ndarray | None = None
    #: Each camera's mount (`world` or a link) and each target's link.
    camera_mount: dict[str, str] | None = None
    target_link: dict[str, str] | None = None
    #: The simulated arm's record (`jaxcal.sim.arm.ArmModel.metadata`), None for the rigid arm.
    arm: dict | None = None


@dataclass(frozen=True)
class SimulationRecord:
    """What `metadata.json`'s `simulation` (the configuration `jaxcal simulate` records) says of
    a joint-sweeps capture's motion and lens: the robot, frames per sweep, frame rate, each
    sweep's range (deg, or per joint) and a prismatic joint's (mm), the home pose (deg) and the
    lens's OpenCV distortion."""

    robot: str
    frames_per_joint: int
    fps: float
    range_deg: float | tuple[float, ...]
    range_mm: float
    home_deg: tuple[float, ...] | None
    distortion: tuple[float, ...]


def simulation_record(meta: dict) -> SimulationRecord | None:
    """The `SimulationRecord` of a dataset's metadata, None when it has none (not simulated)."""
    sim = meta.get("simulation")
    if not isinstance(sim, dict) or "frames_per_joint" not in sim:
        return None
    rng, home = sim.get("range_deg", 40.0), sim.get("home_deg")
    return SimulationRecord(
        robot=str(sim.get("robot", "ur5e")),
        frames_per_joint=int(sim["frames_per_joint"]),
        fps=float(sim.get("fps", 30.0)),
        range_deg=tuple(float(x) for x in rng) if isinstance(rng, list) else float(rng),
        range_mm=float(sim.get("range_mm", 100.0)),
        home_deg=None if home is None else tuple(float(x) for x in home),
        distortion=tuple(float(x) for x in sim.get("distortion", (0.0,) * 5)),
    )


def true_poses(truth: dict) -> TruePoses:
    """The frames of a checked `truth` (`read_truth`'s) as a `TruePoses`."""
    cams, tgts = truth.get("cameras", {}), truth.get("targets", {})
    return TruePoses(
        T_cam_base={n: np.asarray(c["T_cam_base"]) for n, c in cams.items() if "T_cam_base" in c},
        T_mount_cam={n: np.asarray(c["T_mount_cam"]) for n, c in cams.items() if "T_mount_cam" in c},
        T_link_target={n: np.asarray(t["T_link_target"]) for n, t in tgts.items()},
        T_world_base=np.asarray(truth.get("T_world_base", np.eye(4))),
        clock_offset_s=truth.get("clock", {}).get("offset_s"),
        model=model_from_json(truth["model"]),
        T_cam_target=tuple(
            {n: np.asarray(T) for n, T in f["T_cam_target"].items()} for f in truth.get("frames", ())
        ),
        visible=tuple(dict(f["visible"]) for f in truth.get("frames", ())),
        dropped_frames=tuple(truth.get("dropped_frames", ())),
        bad_samples=tuple(truth.get("bad_samples", ())),
        frame_rows=tuple(int(f["row"]) for f in truth.get("frames", ())),
        frame_cameras=tuple(str(f["camera"]) for f in truth.get("frames", ())),
        frame_t=np.array([f["t"] for f in truth.get("frames", ())], np.float64),
        frame_theta=np.array([f["theta"] for f in truth.get("frames", ())], np.float64),
        camera_mount={n: str(c["mount"]) for n, c in cams.items()},
        target_link={n: str(t["link"]) for n, t in tgts.items()},
        arm=truth.get("arm"),
    )


def read_truth(path: Path, joints, cameras, targets, rows: tuple[np.ndarray, np.ndarray]) -> dict:
    """`truth.json` checked against the dataset's joints, cameras and targets. Its `frames` are
    matched to the frame table's `rows` (`(camera, capture index)` per row) by camera and capture
    index: an entry whose frame the table no longer lists (a row deleted with its image) is
    dropped, and every kept entry's `row` is its row now."""
    truth = sc.read_json(path, "truth file")
    loc = Loc(path)
    sc.obj(
        truth,
        loc,
        required=("model", "cameras", "targets", "clock"),
        optional=("T_world_base", "dropped_frames", "frames", "bad_samples", "compliance_rad_per_kNm", "arm"),
    )
    n = len(joints)
    m = loc.key("model")
    model = sc.obj(
        truth["model"],
        m,
        required=(
            "joint_names",
            "joint_types",
            "link_names",
            "T_parent_joint",
            "axis",
            "zero_offset",
            "reduction_ratio",
            "T_last_flange",
        ),
    )
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
    bad = truth.get("bad_samples", [])
    if not isinstance(bad, list):
        raise loc.key("bad_samples").expected("a list of sample indices (tracker data)", bad)
    for i, v in enumerate(bad):
        sc.integer(v, loc.key("bad_samples").index(i), 0, MAX_FRAME_INDEX)
    frames = truth.get("frames", [])
    if not isinstance(frames, list):
        raise loc.key("frames").expected("a list with one entry per row of frames.csv", frames)
    row_of = {(str(c), int(k)): r for r, (c, k) in enumerate(zip(*rows))}
    kept = []
    for i, f in enumerate(frames):
        w = loc.key("frames").index(i)
        sc.obj(f, w, required=("row", "camera", "frame", "t", "theta", "q", "T_cam_target", "visible"))
        sc.integer(f["row"], w.key("row"), 0, MAX_FRAME_INDEX)
        sc.string(f["camera"], w.key("camera"), choices=cam_names)
        sc.integer(f["frame"], w.key("frame"), 0, MAX_FRAME_INDEX)
        if (row := row_of.get((f["camera"], f["frame"]))) is not None:
            kept.append(f | {"row": row})
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
    return truth | ({"frames": kept} if "frames" in truth else {})


def small_markers(truth: TruePoses, cameras, targets) -> list[str]:
    """Warnings for targets whose markers a rendered capture shows smaller than they need to be
    found (`TargetSpec.min_marker_px`): per camera and target, the median over the frames it is
    wholly in view of a marker's shorter side (px), a marker-sized square at the plate's origin
    seen through the camera's pinhole, foreshortening included."""
    K = {c.name: np.asarray(c.K, np.float64) for c in cameras if c.K is not None}
    out = []
    for cam, Kc in K.items():
        for t in targets:
            need = t.spec.min_marker_px
            if need is None:
                continue
            square = 0.5 * t.spec.marker_length * np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0.0]])
            sides = []
            for poses, seen, name in zip(truth.T_cam_target, truth.visible, truth.frame_cameras):
                if name == cam and seen.get(t.name) and t.name in poses:
                    P = square @ poses[t.name][:3, :3].T + poses[t.name][:3, 3]
                    uv = P[:, :2] / P[:, 2:] @ Kc[:2, :2].T
                    sides.append(float(np.min(np.linalg.norm(uv - np.roll(uv, 1, axis=0), axis=1))))
            if sides and (side := float(np.median(sides))) < need:
                out.append(
                    f"camera {cam!r} sees target {t.name!r}'s markers about {side:.0f} px wide (median), under "
                    f"the {need:g} px a {t.spec.dictionary} marker needs to be found: calibrating it will find "
                    "few or none; render at a higher --resolution or with a larger target"
                )
    return out
