"""Reading `metadata.json`: the robot, cameras, targets, encoders, clock and motion fields (`docs/dataset.md`)."""

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import DatasetError
from ..markers import KINDS as TARGET_KINDS
from ..markers import TargetSpec
from . import _encoders as enc
from . import _schema as sc
from ._files import atomic_directory as atomic_directory
from ._images import MAX_PIXELS, MAX_SIDE
from ._schema import Loc

#: |clock.drift_ppm| bound (0.1 %: ten times a poor crystal).
MAX_DRIFT_PPM = 1000.0
#: `cameras[].stamp` values: what a frame's timestamp marks in its (first row's) exposure.
STAMPS = ("start", "middle", "end")
#: Longest `cameras[].exposure_s` and readout (`line_delay_s` times the height), s.
MAX_EXPOSURE_S = 10.0
#: `encoders.quantity` values: what the log holds.
QUANTITIES = ("motor_angle",)


@dataclass(frozen=True, eq=False)
class CameraInfo:
    """A camera of the dataset. `K` is `None` when the intrinsics are unknown
    (the front end then self-calibrates). `mount`: `"world"` or a link name.
    `exposure_s`, `line_delay_s` (rolling shutter: seconds from one row to the
    next) and `stamp` (what a frame's timestamp marks: `"start"`, `"middle"` or
    `"end"` of the first row's exposure): `None` when not given.
    `estimate_line_delay`: `line_delay_s` is `"estimate"` in the metadata (the
    refinement estimates it; `line_delay_s` is then `None`). `K_std`: the standard
    deviations (px) of `K`'s $f_x, f_y, c_x, c_y$ (its own calibration's), which the
    calibration's covariance then counts; `None` takes `K` as exact."""

    name: str
    width: int
    height: int
    K: np.ndarray | None
    dist: np.ndarray
    mount: str = "world"
    exposure_s: float | None = None
    line_delay_s: float | None = None
    stamp: str | None = None
    estimate_line_delay: bool = False
    K_std: tuple[float, float, float, float] | None = None

    def to_dict(self) -> dict:
        delay = "estimate" if self.estimate_line_delay else self.line_delay_s
        K_std = None if self.K_std is None else list(self.K_std)
        optional = {"exposure_s": self.exposure_s, "line_delay_s": delay, "stamp": self.stamp, "K_std": K_std}
        return {
            "name": self.name,
            "width": self.width,
            "height": self.height,
            "K": None if self.K is None else np.asarray(self.K).tolist(),
            "distortion": np.asarray(self.dist).tolist(),
            "mount": self.mount,
        } | {k: v for k, v in optional.items() if v is not None}


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


# --------------------------------------------------------------------------- reading: metadata.json


def read_robot(meta: dict, loc: Loc, root: Path):
    """`robot`: the robot file (a URDF, or a DH/MDH table), base and flange links, the joints, and their limits."""
    robot = sc.obj(
        meta["robot"],
        loc,
        required=("joints",),
        optional=("urdf", "table", "base_link", "flange_link", "payload"),
    )
    given = [k for k in ("urdf", "table") if k in robot]
    if len(given) != 1:
        raise loc.fail(
            "give exactly one of 'urdf' (a URDF file) and 'table' (a DH/MDH table file, .json or .yaml), "
            f"got {'both' if given else 'neither'}"
        )
    if given == ["table"]:
        return _read_table_robot(robot, loc, root)
    rel = sc.relative_path(sc.string(robot["urdf"], loc.key("urdf")), loc.key("urdf"))
    urdf = root / rel
    if not urdf.is_file():
        raise DatasetError(f"{urdf}: robot file missing (named by {loc.key('urdf')})")
    joints = sc.names(robot["joints"], loc.key("joints"))
    from .urdf import urdf_outline  # with the robot model's JAX: not for the parsers that import this module

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


@dataclass(frozen=True, eq=False)
class Payload:
    """What the flange carries beyond the robot file's links (the plate, a tool): its mass (kg),
    centre of mass in the flange frame (m) and, when given, its inertia tensor about that centre
    in the flange's axes (kg m^2; None: a point mass), `robot.payload` in the metadata."""

    mass_kg: float
    com_m: np.ndarray
    inertia_kgm2: np.ndarray | None = None


#: Heaviest payload `robot.payload.mass_kg` accepts (kg): more than any arm this tool calibrates lifts.
MAX_PAYLOAD_KG = 1000.0


#: Largest principal inertia `robot.payload.inertia_kgm2` accepts (kg m^2): a 1000 kg load 1 m across.
MAX_PAYLOAD_INERTIA = 1000.0


def read_payload(meta: dict, loc: Loc) -> Payload | None:
    """`robot.payload` (`{"mass_kg": m, "com_m": [x, y, z]}`, the centre in the flange frame, and
    optionally `"inertia_kgm2"`: `[Ixx, Iyy, Izz]` or a 3x3 tensor about the centre in the flange's
    axes), or None."""
    p = meta["robot"].get("payload") if isinstance(meta.get("robot"), dict) else None
    if p is None:
        return None
    p = sc.obj(p, loc, required=("mass_kg", "com_m"), optional=("inertia_kgm2",))
    mass = sc.number(p["mass_kg"], loc.key("mass_kg"), 0.0, MAX_PAYLOAD_KG)
    com = sc.array(p["com_m"], loc.key("com_m"), (3,))
    if np.max(np.abs(com)) > 5.0:
        raise loc.key("com_m").fail(
            f"{com.tolist()} is over 5 m from the flange: millimetres given as metres?"
        )
    inertia = (
        None
        if p.get("inertia_kgm2") is None
        else _payload_inertia(p["inertia_kgm2"], loc.key("inertia_kgm2"))
    )
    return Payload(mass, com, inertia)


def _payload_inertia(x, loc: Loc) -> np.ndarray:
    """An inertia tensor (kg m^2) from its principal values `[Ixx, Iyy, Izz]` or a symmetric 3x3
    matrix, refused where no rigid body has it (negative, asymmetric, or one principal value
    above the sum of the other two)."""
    flat = isinstance(x, list) and len(x) == 3 and all(not isinstance(v, list) for v in x)
    I = np.diag(sc.array(x, loc, (3,))) if flat else sc.array(x, loc, (3, 3))
    if not np.allclose(I, I.T, rtol=0.0, atol=1e-9 * max(1.0, float(np.abs(I).max()))):
        raise loc.fail(f"{I.tolist()} is not symmetric: an inertia tensor is")
    principal = np.linalg.eigvalsh(0.5 * (I + I.T))
    scale = max(float(principal.max()), 1e-12)
    if principal.min() < -1e-9 * scale or principal.max() > principal.sum() - principal.max() + 1e-9 * scale:
        raise loc.fail(
            f"principal values {np.round(principal, 9).tolist()} kg m^2 are no rigid body's (each must be >= 0 "
            "and at most the sum of the other two)"
        )
    if principal.max() > MAX_PAYLOAD_INERTIA:
        raise loc.fail(
            f"principal values up to {principal.max():g} kg m^2: grams or millimetres given as SI?"
        )
    return 0.5 * (I + I.T)


def _read_table_robot(robot: dict, loc: Loc, root: Path):
    """`read_robot` for `robot.table`: the joints are the table's, in its order; `base_link` and
    `flange_link`, if given, its own; the limits are the table's `lower` / `upper` / `velocity`."""
    from .dh_tables import TABLE_SUFFIXES, read_table_file  # JAX: only for a robot given by its table

    where = loc.key("table")
    rel = sc.relative_path(sc.string(robot["table"], where), where)
    path = root / rel
    if path.suffix.lower() not in TABLE_SUFFIXES:
        raise where.fail(f"{rel!r} is not a table file (it must end in {', '.join(TABLE_SUFFIXES)})")
    if not path.is_file():
        raise DatasetError(f"{path}: robot file missing (named by {where})")
    t = read_table_file(path)
    joints = sc.names(robot["joints"], loc.key("joints"))
    if tuple(joints) != t.table.joint_names:
        raise loc.key("joints").fail(
            f"{joints} differ from the joints of {path.name}, base to flange: {list(t.table.joint_names)}"
        )
    n = len(joints)
    children = t.link_names or tuple(f"{path.stem}_link{i + 1}" for i in range(n))
    links = frozenset((t.base_link, *children, t.flange_link))
    for key, own in (("base_link", t.base_link), ("flange_link", t.flange_link)):
        v = robot.get(key)
        if v is not None and sc.string(v, loc.key(key)) != own:
            raise loc.key(key).fail(f"{v!r} is not the {key} of {path.name} ({own!r})")
    return path, t.base_link, t.flange_link, tuple(joints), t.joint_limits(), links


def read_cameras(meta: dict, loc: Loc, links) -> tuple[CameraInfo, ...]:
    cams = meta["cameras"]
    if not isinstance(cams, list) or not cams:
        raise loc.expected("a non-empty list of cameras", cams)
    out = []
    for i, c in enumerate(cams):
        w = loc.index(i)
        sc.obj(
            c,
            w,
            required=("name", "width", "height"),
            optional=("K", "K_std", "distortion", "mount", "exposure_s", "line_delay_s", "stamp"),
        )
        name = sc.file_name(c["name"], w.key("name"))
        width = sc.integer(c["width"], w.key("width"), 1, MAX_SIDE)
        height = sc.integer(c["height"], w.key("height"), 1, MAX_SIDE)
        if width * height > MAX_PIXELS:
            raise w.fail(
                f"{width}x{height} pixels is more than the {MAX_PIXELS / 1e6:.0f} megapixels jaxcal reads"
            )
        K = c.get("K")
        K = None if K is None else sc.camera_matrix(K, w.key("K"), width, height)
        dist = sc.distortion(c.get("distortion", [0.0] * 5), w.key("distortion"))
        mount = sc.string(c.get("mount", "world"), w.key("mount"))
        if mount != "world" and mount not in links:
            raise w.key("mount").fail(f"{mount!r} is neither 'world' nor a link of the robot")
        K_std = _K_std(c.get("K_std"), K, w.key("K_std"))
        out.append(CameraInfo(name, width, height, K, dist, mount, **_exposure(c, w, height), K_std=K_std))
    names = [c.name for c in out]
    if len(set(names)) != len(names):
        raise loc.fail(f"camera names are not unique: {names}")
    return tuple(out)


def _K_std(value, K, loc) -> tuple[float, float, float, float] | None:
    """`cameras[].K_std`: four standard deviations (px) of `K`'s fx, fy, cx, cy, each under a tenth of
    the focal length; only beside a `K`."""
    if value is None:
        return None
    if K is None:
        raise loc.fail("is given, but K is not: the uncertainty of which intrinsics?")
    std = sc.array(value, loc, (4,))
    for i, x in enumerate(std):
        sc.number(float(x), loc.index(i), 0.0, 0.1 * float(K[0, 0]))
    return tuple(float(x) for x in std)


def _exposure(c: dict, loc: Loc, height: int) -> dict:
    """A camera's optional `exposure_s`, `line_delay_s` and `stamp` (each `None` when absent or null;
    `line_delay_s` `"estimate"`: `estimate_line_delay`)."""
    out = {"exposure_s": None, "line_delay_s": None, "stamp": None}
    if c.get("exposure_s") is not None:
        out["exposure_s"] = sc.number(c["exposure_s"], loc.key("exposure_s"), 0.0, MAX_EXPOSURE_S)
    if c.get("line_delay_s") == "estimate":
        out["estimate_line_delay"] = True
    elif c.get("line_delay_s") is not None:
        delay = sc.number(c["line_delay_s"], loc.key("line_delay_s"), 0.0, MAX_EXPOSURE_S)
        if delay * height > MAX_EXPOSURE_S:
            raise loc.key("line_delay_s").fail(
                f"{delay:g} s per row reads the {height} rows out in {delay * height:g} s, "
                f"more than {MAX_EXPOSURE_S:g} s (it is seconds per row, not per frame)"
            )
        out["line_delay_s"] = delay
    if c.get("stamp") is not None:
        out["stamp"] = sc.string(c["stamp"], loc.key("stamp"), choices=STAMPS)
    return out


def read_targets(meta: dict, loc: Loc, links) -> tuple[TargetInfo, ...]:
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
            "marker_length": sc.number(
                t["marker_length"], w.key("marker_length"), hi=10.0, above=0.0, metres=True
            ),
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
            spec["square_length"] = sc.number(
                t["square_length"], w.key("square_length"), hi=10.0, above=0.0, metres=True
            )
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
    _distinct_ids(out, loc)
    return tuple(out)


def _distinct_ids(targets: list[TargetInfo], loc: Loc) -> None:
    """Two targets of one dictionary whose marker ids overlap are refused, naming both: a detector
    cannot tell which of them it sees (a plate's `first_id` copied from another's)."""
    for j, b in enumerate(targets):
        for a in targets[:j]:
            if a.spec.dictionary != b.spec.dictionary or not a.spec.num_markers or not b.spec.num_markers:
                continue
            if np.intersect1d(a.spec.marker_ids, b.spec.marker_ids).size:
                ids = lambda s: f"{s.marker_ids[0]}..{s.marker_ids[-1]}"  # noqa: E731
                raise (
                    loc.index(j)
                    .key("first_id")
                    .fail(
                        f"target {b.spec.name!r}'s marker ids {ids(b.spec)} overlap target {a.spec.name!r}'s "
                        f"({ids(a.spec)}) in {b.spec.dictionary}: a detector cannot tell which plate it sees; give "
                        "each plate its own ids (first_id: the id of its first marker)"
                    )
                )


def read_encoder_meta(meta: dict, loc: Loc) -> dict | None:
    e = meta.get("encoders")
    if e is None:
        return None
    sc.obj(e, loc, optional=("file", "quantity", "unit", "rate_hz", "counts_per_rev"))
    out = {
        "file": sc.relative_path(sc.string(e.get("file", "encoders.csv"), loc.key("file")), loc.key("file")),
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


def read_clock(meta: dict, loc: Loc) -> tuple[float | None, float]:
    clock = meta.get("clock")
    if clock is None:
        return None, 0.0
    sc.obj(clock, loc, optional=("offset_s", "drift_ppm"))
    offset = clock.get("offset_s")
    offset = None if offset is None else sc.number(offset, loc.key("offset_s"))
    drift = clock.get("drift_ppm")
    drift = 0.0 if drift is None else sc.number(drift, loc.key("drift_ppm"), -MAX_DRIFT_PPM, MAX_DRIFT_PPM)
    return offset, drift


def read_motion(meta: dict, loc: Loc, joints: tuple[str, ...]) -> tuple:
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
