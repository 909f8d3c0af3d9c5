"""Reading tracker data: the `device` field of `metadata.json` and the samples table (`docs/dataset.md`).

An external measuring device (a laser tracker with a retro-reflector on the
flange, a motion-capture system, or the controller's own logged tool point)
gives, per sample, a 3-D point and optionally an orientation in the device
frame, with its noise. No images, no PnP: the samples go to the arc fits as
marker positions (and orientations when present).
"""

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .._npgeom import quaternion_to_matrix
from ..errors import DatasetError
from . import _encoders as enc
from . import _schema as sc
from ._files import atomic_directory as atomic_directory
from ._logs import MAX_FRAME_INDEX, FrameTable, read_number_table
from ._schema import Loc

#: `device.kind` values (informative: every kind is calibrated the same way).
DEVICE_KINDS = ("laser_tracker", "motion_capture", "controller", "other")
#: The samples table's leading columns, in this order.
LEADING = ("sample", "timestamp", "joint", "x", "y", "z")
#: An orientation's columns (a unit quaternion, scalar last), all four or none.
QUATERNION = ("qx", "qy", "qz", "qw")
#: Largest coordinate (m): a point further out is a unit mistake (mm written as m).
MAX_COORDINATE_M = 100.0
#: A quaternion's norm may differ from 1 by this much (it is then normalised).
QUATERNION_TOL = 1e-3


@dataclass(frozen=True, eq=False)
class DeviceInfo:
    """The measuring device of a tracker dataset.

    - `name`: names the device frame (`T_device_base`) and output files.
    - `kind`: `laser_tracker`, `motion_capture`, `controller` or `other`.
    - `file`: the samples table, relative to the dataset.
    - `link`, `point`: the robot link the measured point rides on (the
      flange) and the point's name (a retro-reflector, a probe).
    - `T_link_point`: its nominal mount (4x4) when known from design, else None.
    - `sigma_m`, `sigma_rad`: per-sample noise (1-sigma per axis, m; per
      rotation axis, rad) for samples whose row does not give its own.
    """

    name: str
    kind: str
    file: str
    link: str
    point: str
    T_link_point: np.ndarray | None
    sigma_m: float | None
    sigma_rad: float | None


@dataclass(frozen=True, eq=False)
class PointTarget:
    """The measured point in a marker target's role (`link`, `T_link_target`); nothing printed (`spec` None)."""

    name: str
    link: str
    T_link_target: np.ndarray | None
    spec: None = None


@dataclass(frozen=True, eq=False)
class TrackerSamples:
    """The samples table, checked (`N` rows, file order).

    - `sample` (N,) integers, strictly increasing; `timestamp` (N,) device clock, s.
    - `joint` (N,): index of the joint sweeping alone in the sample, -1 where
      the cell is empty; `has_joint`: some row names one.
    - `position` (N, 3) m and `orientation` (N, 3, 3) or None, device frame.
    - `sigma_m` (N,), `sigma_rad` (N,) or None: per-sample noise.
    - `q` (N, joints): the controller's joint positions (rad or m), or None.
    - `lines`: each row's line number in the file.
    """

    sample: np.ndarray
    timestamp: np.ndarray
    joint: np.ndarray
    has_joint: bool
    position: np.ndarray
    orientation: np.ndarray | None
    sigma_m: np.ndarray
    sigma_rad: np.ndarray | None
    q: np.ndarray | None
    lines: np.ndarray

    def covariances(self) -> np.ndarray:
        """Per sample the isotropic covariance of `(position[, rotation vector])`: `(N, k, k)`."""
        k = 3 if self.orientation is None else 6
        var = np.repeat(self.sigma_m[:, None] ** 2, k, axis=1)
        if self.orientation is not None:
            var[:, 3:] = self.sigma_rad[:, None] ** 2
        return var[:, :, None] * np.eye(k)


#: A measured point this far (m) from its link's frame is no tool's: a length in millimetres.
MAX_POINT_OFFSET_M = 2.0


def read_device(meta: dict, loc: Loc, links) -> DeviceInfo:
    """`device`: the measuring device, its samples file, the measured point and the default noise."""
    d = sc.obj(
        meta["device"],
        loc,
        required=("name",),
        optional=("kind", "file", "link", "point", "T_link_point_nominal", "sigma_m", "sigma_rad"),
    )
    name = sc.file_name(d["name"], loc.key("name"))
    link = sc.string(d.get("link", "flange"), loc.key("link"))
    if link not in links:
        raise loc.key("link").fail(f"{link!r} is not a link of the robot (links: {sorted(links)})")
    T = d.get("T_link_point_nominal")
    if T is not None:
        T = sc.pose(T, loc.key("T_link_point_nominal"))
        if np.linalg.norm(T[:3, 3]) > MAX_POINT_OFFSET_M:
            raise loc.key("T_link_point_nominal").fail(
                f"the point lies {np.linalg.norm(T[:3, 3]):.4g} m from link {link!r}'s frame, beyond any tool's "
                f"{MAX_POINT_OFFSET_M:g} m: give its translation in metres (millimetres written?)"
            )
    sig = {}
    for key, hi in (("sigma_m", 1.0), ("sigma_rad", 1.0)):
        v = d.get(key)
        sig[key] = None if v is None else sc.number(v, loc.key(key), hi=hi, above=0.0)
    return DeviceInfo(
        name=name,
        kind=sc.string(d.get("kind", "laser_tracker"), loc.key("kind"), choices=DEVICE_KINDS),
        file=sc.relative_path(sc.string(d.get("file", "samples.csv"), loc.key("file")), loc.key("file")),
        link=link,
        point=sc.string(d.get("point", "point"), loc.key("point")),
        T_link_point=T,
        sigma_m=sig["sigma_m"],
        sigma_rad=sig["sigma_rad"],
    )


def _columns(header: list[str], path: Path, joints: tuple[str, ...]) -> dict:
    """Which optional columns the header has: `{"quaternion", "sigma_m", "sigma_rad", "joints"}` -> indices."""
    if tuple(header[: len(LEADING)]) != LEADING:
        delimiter = next((d for d in (";", "\t") if d in ",".join(header)), None)
        raise DatasetError(
            f"{path} line 1: the header must start with {','.join(LEADING)}, got {','.join(header)}"
            + (
                f" (the file is separated by {delimiter!r}: write it comma-separated, with '.' decimals)"
                if delimiter
                else ""
            )
        )
    rest = header[len(LEADING) :]
    index = {h: len(LEADING) + i for i, h in enumerate(rest)}
    known = set(QUATERNION) | {"sigma_m", "sigma_rad"} | set(joints)
    unknown = [h for h in rest if h not in known]
    if unknown:
        raise DatasetError(
            f"{path} line 1: unknown column(s) {unknown}; after {','.join(LEADING)} come optional "
            f"{','.join(QUATERNION)}, sigma_m, sigma_rad and the robot's joints {list(joints)}"
        )
    if len(set(rest)) != len(rest):
        raise DatasetError(f"{path} line 1: a column is repeated: {rest}")
    quat = [h in index for h in QUATERNION]
    if any(quat) and not all(quat):
        raise DatasetError(f"{path} line 1: an orientation needs all of {','.join(QUATERNION)}, got {rest}")
    given = [j in index for j in joints]
    if any(given) and not all(given):
        missing = [j for j, g in zip(joints, given) if not g]
        raise DatasetError(f"{path} line 1: joint position columns must name every joint; missing {missing}")
    if "sigma_rad" in index and not all(quat):
        raise DatasetError(f"{path} line 1: column sigma_rad without an orientation ({','.join(QUATERNION)})")
    return {
        "quaternion": [index[h] for h in QUATERNION] if all(quat) else None,
        "sigma_m": index.get("sigma_m"),
        "sigma_rad": index.get("sigma_rad"),
        "joints": [index[j] for j in joints] if all(given) else None,
    }


def _quaternions(rows: np.ndarray, lines, path: Path) -> np.ndarray:
    """Unit quaternions `(x, y, z, w)` per row -> rotation matrices, a norm off 1 named by its line."""
    norm = np.linalg.norm(rows, axis=1)
    bad = np.flatnonzero(np.abs(norm - 1.0) > QUATERNION_TOL)
    if bad.size:
        k = bad[0]
        raise DatasetError(
            f"{path} line {lines[k]}: quaternion (qx, qy, qz, qw) has norm {norm[k]:.6g}; expected a unit "
            f"quaternion (within {QUATERNION_TOL:g})"
        )
    return quaternion_to_matrix(rows / norm[:, None])


def _sigmas(values, cols, device: DeviceInfo, path: Path, lines, meta_loc: Loc):
    """Per-sample noise from the table's columns, else the metadata's."""
    out = []
    for key, col, default in (
        ("sigma_m", cols["sigma_m"], device.sigma_m),
        ("sigma_rad", cols["sigma_rad"], device.sigma_rad),
    ):
        if key == "sigma_rad" and cols["quaternion"] is None:
            out.append(None)
            continue
        if col is not None:
            s = values[:, col]
            bad = np.flatnonzero(~((s > 0) & (s <= 1.0)))
            if bad.size:
                raise DatasetError(
                    f"{path} line {lines[bad[0]]} column {key!r}: expected a number in (0, 1], got {s[bad[0]]!r}"
                )
            out.append(s)
        elif default is not None:
            out.append(np.full(len(values), default))
        else:
            raise DatasetError(
                f"{path}: no noise given: add a {key!r} column or {meta_loc.key('device').key(key)} "
                "(1-sigma per axis)"
            )
    return out


def read_samples(root: Path, device: DeviceInfo, joints: tuple[str, ...], limits: dict, meta_loc: Loc):
    """The samples table of `device`, checked: a `TrackerSamples`.

    Errors name the file, line and column: the header, numbers (finite),
    sample indices (non-negative integers, strictly increasing), timestamps
    (strictly increasing), joint names, coordinates (within 100 m), unit
    quaternions, noise (0, 1], and joint positions within their URDF limits.
    """
    path = root / device.file
    found = {}

    def columns(header: list[str]) -> tuple[list[int], list[int]]:
        found.update(_columns(header, path, joints))
        return [c for c in range(len(header)) if c != 2], [0, 2]

    t = read_number_table(path, f"samples table (named by {meta_loc.key('device').key('file')})", columns)
    header, lines, values = t.header, t.lines, t.values
    if not len(lines):
        raise DatasetError(f"{path}: no samples")
    # `values` skips column 2 (the joint's name, text): the header's column c > 2 is its c - 1.
    cols = {
        k: None if c is None else [i - 1 for i in c] if isinstance(c, list) else c - 1
        for k, c in found.items()
    }
    sample, names = t.text[:, 0], t.text[:, 1]
    digits = np.char.isdigit(sample) & (np.char.str_len(sample) <= 12)
    bad = np.flatnonzero(~digits | (values[:, 0] > MAX_FRAME_INDEX))
    try:
        sample.astype(np.bytes_)  # ASCII only (`isdigit` takes other scripts' digits too)
    except UnicodeEncodeError:
        bad = np.union1d(bad, [r for r, x in enumerate(sample.tolist()) if not x.isascii()]).astype(int)
    if len(bad):
        raise DatasetError(
            f"{path} line {lines[bad[0]]} column 'sample': {str(sample[bad[0]])!r} is not an integer from 0 to "
            f"{MAX_FRAME_INDEX}"
        )
    index = {j: k for k, j in enumerate(joints)}
    joint = np.full(len(lines), -1)
    for name in set(names.tolist()) - {""}:
        rows = np.flatnonzero(names == name)
        if name not in index:
            raise DatasetError(
                f"{path} line {lines[rows[0]]} column 'joint': unknown joint {name!r}; the robot's joints are "
                f"{list(joints)}"
            )
        joint[rows] = index[name]
    for c, what in ((0, "sample indices"), (1, "timestamps")):
        bad = np.flatnonzero(np.diff(values[:, c]) <= 0)
        if bad.size:
            k = bad[0]
            show = (lambda v: f"{int(v)}") if c == 0 else (lambda v: f"{float(v)!r}")
            order = (
                "; the rows run backwards: sort them ascending" if np.all(np.diff(values[:, c]) < 0) else ""
            )
            raise DatasetError(
                f"{path} line {lines[k + 1]}: {header[c]} {show(values[k + 1, c])} is not after line {lines[k]}'s "
                f"{show(values[k, c])}; {what} must increase strictly{order}"
            )
    P = values[:, 2:5]
    far = np.flatnonzero(np.abs(P).max(axis=1) > MAX_COORDINATE_M)
    if far.size:
        raise DatasetError(
            f"{path} line {lines[far[0]]}: point {P[far[0]].tolist()} is more than {MAX_COORDINATE_M:g} m from the "
            "device: coordinates are in metres"
        )
    O = None if cols["quaternion"] is None else _quaternions(values[:, cols["quaternion"]], lines, path)
    sigma_m, sigma_rad = _sigmas(values, cols, device, path, lines, meta_loc)
    q = None
    if cols["joints"] is not None:
        q = values[:, cols["joints"]]
        for j, name in enumerate(joints):
            problem = enc.unit_problem(
                q[:, j],
                limits[name].reduction_ratio,
                "rad",
                None,
                limits[name],
                lines,
                f"{path.name}'s joint columns are SI (rad, m)",
            )
            if problem is not None:
                raise DatasetError(f"{path} column {name!r} (joint positions, rad or m): {problem}")
    return TrackerSamples(
        sample=values[:, 0].astype(np.int64),
        timestamp=values[:, 1],
        joint=joint,
        has_joint=bool((joint >= 0).any()),
        position=P,
        orientation=O,
        sigma_m=sigma_m,
        sigma_rad=sigma_rad,
        q=q,
        lines=lines,
    )


def sample_frames(device: DeviceInfo, samples: TrackerSamples) -> FrameTable:
    """The frame table of a tracker dataset: one row per sample, the device in the camera's column."""
    n = len(samples.sample)
    return FrameTable(
        camera=np.full(n, device.name),
        frame=samples.sample.copy(),
        timestamp=samples.timestamp.copy(),
        file=np.char.add(f"{device.file} line ", samples.lines.astype(str)),
    )
