"""CSV in: a table of joint positions and measured points -> a tracker dataset (`docs/dataset.md`).

`import_csv` turns one row per stop-and-shoot pose (the commanded joint
positions and the point a laser tracker, motion capture or the controller
measured there, optionally an orientation: a full pose) into the tracker
format: every `joint` cell empty (all joints move between poses), one
`joint: null` motion segment, joint positions in rad, points in m,
orientations as unit quaternions. A position may be the sum of columns
(`x_t+x_dif`: nominal plus deviation), so published tables need no
preprocessing.

Every unit and convention is stated by the caller (`joint_unit` rad or deg,
`length_unit` m or mm; with an orientation its `orientation_format`, one of
`ORIENTATION_FORMATS`, and `pose_direction`, one of `POSE_DIRECTIONS`): nothing
is guessed. A pose given as the device's in the point's frame (PnP's board in
the camera) is inverted into the point's in the device frame. The point's mount
on the link is a translation (`point_m`) and, for a frame turned on its link (a
camera turned about its axis), a rotation (`point_rotvec_rad`). Before anything is written the table is checked
against the robot, and every refusal (`CsvImportError`) names the CSV file,
the column and the line:

- every named column exists (a sum names the part that does not), every cell
  is a finite number, timestamps (`time`) increase strictly;
- joint positions lie within the robot's limits widened as at load
  (`_encoders.margin`; a DH table gives none: one turn each way): degrees
  declared as radians are 57 times too large;
- the points spread like the nominal robot's for the same joints (RMS about
  their centroid, within a factor `SPREAD_FACTOR`): millimetres declared as
  metres spread 1000 times too wide, metres declared as millimetres 1000
  times too narrow;
- no point lies further from the points' median than the arm spans
  ($2 (1.1 R + 0.1)$ m, $R$ = `reach_m`): the device frame is unknown, so
  the check does not depend on it;
- after the best rigid alignment of the points onto the nominal ones
  (Kabsch, trimmed), each lies within `ALIGN_TOL_M` + 5 % of the reach of
  its nominal (another `UNKNOWN_POINT_M` when the point's mount is not
  given): a wrong cell, rows out of order, joint columns swapped;
- every orientation is a rotation (`_csv_poses.orientations`): a quaternion of unit
  norm (within `QUATERNION_TOL`), a rotation vector within one turn (else
  degrees declared as radians), a matrix orthonormal within `MATRIX_TOL` with
  determinant +1, the row, column and matrix row named;
- the orientations fit the nominal robot's (`_csv_poses.check_orientations`): after the
  best rotations of the device frame and of the mount (alternating Procrustes
  from the points' alignment), each lies within `ANGLE_TOL_DEG`, the device
  frame they imply is the points' own, and the mount's rotation is the stated
  one (or the identity) within `MOUNT_TOL_DEG` when the mount is given; a
  refusal names the format, order or direction under which the rows do fit.

The output is written atomically (`atomic_directory`, kind `dataset`, never
over an input) and checked with `load_dataset` before it is renamed into place.
"""

import hashlib
import math
import shutil
from collections.abc import Sequence
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from .._kinematics import KinematicModel, forward_kinematics
from .._npgeom import (
    matrix_to_quaternion,
    pose,
)
from ..errors import CsvImportError, DatasetError
from . import _encoders as enc
from ._csv_points import FAR_FACTOR, FAR_MIN_M, far_rows, reread_hint, rigid_alignment
from ._csv_poses import ANGLE_UNITS as ANGLE_UNITS
from ._csv_poses import LENGTH_UNITS as LENGTH_UNITS
from ._csv_poses import ORIENTATION_FORMATS as ORIENTATION_FORMATS
from ._csv_poses import POSE_DIRECTIONS as POSE_DIRECTIONS
from ._csv_poses import (
    check_orientation_arguments,
    check_orientations,
    directed,
    orientations,
    other_readings,
)
from ._files import atomic_directory, check_output_dir, shown
from ._logs import read_number_table
from ._schema import file_name
from ._tracker import DEVICE_KINDS, MAX_COORDINATE_M
from .dataset import SCHEMA, SCHEMA_VERSION, load_dataset, write_json
from .dh_tables import dh_table_model, is_table_file, read_table_file
from .urdf import load_urdf, urdf_outline

#: The measured points' RMS spread may differ from the nominal robot's by this factor
#: (a unit mistake is a factor 1000); compared only where the nominal spread exceeds
#: `MIN_SPREAD_M`.
SPREAD_FACTOR = 5.0
MIN_SPREAD_M = 0.01
#: Largest distance of a point from its nominal after the rigid alignment: this + 5 % of the reach (m).
ALIGN_TOL_M = 0.05
#: ... plus this when the point's mount on the link is not given (the link's origin stands in).
UNKNOWN_POINT_M = 0.5
#: Points closer to the nominal robot than this many times their stated noise are noted: a real
#: arm's points are millimetres off its datasheet, a table's commanded points are not.
NOMINAL_LIKE = 2.0
#: The joint range assumed for a DH/MDH table without `lower` / `upper` (rad, each way): one turn,
#: the range of UR's joints and wider than most arms'.
TABLE_RANGE = 2.0 * math.pi
#: Largest point mount offset (m): further is millimetres given as metres.
MAX_POINT_M = 2.0
#: Rows the forward kinematics and the writer take at a time: the memory an import takes is
#: bounded by it, the table's own numbers aside (`_logs.read_number_table` streams the reading).
ROWS_AT_ONCE = 65536


@dataclass(frozen=True)
class CsvImport:
    """What `import_csv` wrote: the dataset, its sample count, the robot's reach bound (m)
    and the points' RMS distance from the nominal robot's after the rigid alignment (m); `notes`:
    what looks odd but is not refused; `warnings`: what is most likely wrong but not refused (rows
    far from the nominal robot, `FAR_FACTOR`)."""

    path: Path
    samples: int
    reach_m: float
    rms_from_nominal_m: float
    notes: tuple[str, ...] = ()
    warnings: tuple[str, ...] = ()


@dataclass(frozen=True)
class _Table:
    """The CSV's values in SI units: `q` (N, joints), `P` (N, 3) and `R` (N, 3, 3) or None, the
    point's position and orientation in the device frame, `t` (N,), `lines`; `raw`: the
    orientation columns as read (N, k), for naming the format a refused table would fit."""

    q: np.ndarray
    P: np.ndarray
    R: np.ndarray | None
    t: np.ndarray
    lines: np.ndarray
    raw: np.ndarray | None = None


# --------------------------------------------------------------------------- the robot


def robot_model(robot) -> tuple[KinematicModel, dict, str, dict]:
    """The nominal model of a URDF or DH/MDH table file, its joint limits, and the metadata's `robot` object.

    **Returns:** `(model, limits, file name in the dataset, robot object)`: `limits`
    maps joint names to `JointLimits`: the URDF's, or the table's `lower` /
    `upper` (a table without them: one turn each way, `TABLE_RANGE`).
    """
    robot = Path(robot)
    try:
        if is_table_file(robot):
            t = read_table_file(robot)
            name, key = f"robot_{t.table.convention}{robot.suffix.lower()}", "table"
            model = dh_table_model(robot, Path(name).stem)
            limits = t.joint_limits()
            if t.lower is None:
                limits = {j: replace(v, lower=-TABLE_RANGE, upper=TABLE_RANGE) for j, v in limits.items()}
        else:
            name, key = "robot.urdf", "urdf"
            model = load_urdf(robot)
            limits = urdf_outline(robot, tuple(model.joint_names)).limits
    except (OSError, ValueError) as e:
        raise DatasetError(f"{shown(robot)}: cannot load the robot model: {e}") from e
    obj = {
        key: name,
        "base_link": model.link_names[0],
        "flange_link": model.link_names[-1],
        "joints": list(model.joint_names),
    }
    return model, limits, name, obj


def reach_m(model: KinematicModel, limits: dict, point_m) -> float:
    """An upper bound of the point's distance from joint 1's origin: the chain's link lengths,
    the prismatic joints' travel and the point's offset summed (triangle inequality), m."""
    T = np.asarray(model.T_parent_joint)
    r = np.linalg.norm(T[1:, :3, 3], axis=1).sum() + np.linalg.norm(np.asarray(model.T_last_flange)[:3, 3])
    for name, kind in zip(model.joint_names, model.joint_types):
        lim = limits[name]
        if kind == "prismatic":
            r += max(abs(lim.lower or 0.0), abs(lim.upper or 0.0), 1.0 if lim.lower is None else 0.0)
    return float(r + np.linalg.norm(point_m if point_m is not None else np.zeros(3)))


# --------------------------------------------------------------------------- reading


def _column(spec: str, index: dict, path: Path, option: str) -> list[int]:
    """The CSV columns a spec names (`name` or `a+b`), by index."""
    parts = [s.strip() for s in spec.split("+")]
    if not spec.strip() or any(not p for p in parts):
        raise CsvImportError(f"{path}: {option} {spec!r}: an empty column name")
    for p in parts:
        if p not in index:
            raise CsvImportError(
                f"{path} line 1: no column {p!r} (named by {option} {spec!r}); the header has {list(index)}"
            )
    return [index[p] for p in parts]


def _read(path: Path, specs: dict) -> tuple[dict, np.ndarray]:
    """Per spec (label -> (option, spec)) the summed values (N,), and the line numbers. The
    table is streamed (`_logs.read_number_table`: blocks of rows, NumPy's parser), only the
    columns the specs name converted, so that a table of a million rows takes seconds."""
    cols: dict = {}

    def columns(header: list[str]) -> tuple[list[int], list[int]]:
        header = [h.strip() for h in header]
        index = {h: i for i, h in enumerate(header)}
        if len(index) != len(header):
            raise CsvImportError(f"{path} line 1: a column name is repeated: {header}")
        cols.update({label: _column(spec, index, path, option) for label, (option, spec) in specs.items()})
        used = [c for idx in cols.values() for c in idx]
        twice = sorted({header[c] for c in used if used.count(c) > 1})
        if twice:
            raise CsvImportError(
                f"{path}: column(s) {twice} named twice (in --joint-columns, --xyz, --orientation-columns, time)"
            )
        return sorted(set(used)), []

    try:
        table = read_number_table(path, "CSV table", columns)
    except DatasetError as e:
        raise CsvImportError(str(e)) from None
    if len(table.lines) < 2:
        raise CsvImportError(f"{path}: {len(table.lines)} data row(s); a dataset needs at least 2")
    at = {c: k for k, c in enumerate(sorted({c for idx in cols.values() for c in idx}))}
    out = {label: sum(table.values[:, at[c]] for c in idx) for label, idx in cols.items()}
    return out, table.lines


def _check_limits(path: Path, q: np.ndarray, unit: str, specs, model: KinematicModel, limits: dict, lines):
    """Joint positions (rad or m) within the limits widened as at load; a unit that would fit is named."""
    for j, (name, kind) in enumerate(zip(model.joint_names, model.joint_types)):
        lim, col = limits[name], q[:, j]
        lin = "m" if kind == "prismatic" else "rad"
        if lim.lower is None or lim.upper is None:
            lo, hi, what = -enc.ABSURD[kind], enc.ABSURD[kind], f"beyond {enc.ABSURD[kind]:g} {lin}, absurd"
        else:
            m = enc.margin(kind, lim.lower, lim.upper)
            lo, hi = lim.lower - m, lim.upper + m
            what = f"outside the joint's limits [{lim.lower:.4g}, {lim.upper:.4g}] {lin} widened by {m:.3g} {lin}"
        bad = np.flatnonzero((col < lo) | (col > hi))
        if not bad.size:
            continue
        k = bad[0]
        hint = "check the column and the robot file"
        if kind != "prismatic":
            other = "deg" if unit == "rad" else "rad"
            alt = col / ANGLE_UNITS[unit] * ANGLE_UNITS[other]
            if np.all((alt >= lo) & (alt <= hi)):
                hint = f"the values look like {'degrees' if other == 'deg' else 'radians'}: --joint-unit {other}?"
        raise CsvImportError(
            f"{path} line {lines[k]} column {specs[j]!r} ({name}, --joint-unit {unit}): {col[k]:.6g} {lin} is "
            f"{what} ({bad.size} of {len(col)} rows); {hint}"
        )


def _read_table(
    path: Path, *, joints, joint_unit, xyz, length_unit, orientation, time, model, limits, pose_format=None
) -> _Table:
    """The CSV's columns in SI units, each checked for numbers, time order, joint limits and
    rotations; `pose_format`: `(orientation_format, pose_direction)` with an orientation."""
    specs = {f"q{j}": ("--joint-columns", s) for j, s in enumerate(joints)}
    specs |= {f"p{i}": ("--xyz", s) for i, s in enumerate(xyz)}
    specs |= {f"o{i}": ("--orientation-columns", s) for i, s in enumerate(orientation or ())}
    if time is not None:
        specs["t"] = ("time", time)
    v, lines = _read(path, specs)
    lin = np.array(
        [
            LENGTH_UNITS[length_unit] if k == "prismatic" else ANGLE_UNITS[joint_unit]
            for k in model.joint_types
        ]
    )
    q = np.stack([v[f"q{j}"] for j in range(len(joints))], axis=1) * lin
    _check_limits(path, q, joint_unit, list(joints), model, limits, lines)
    t = np.arange(len(lines), dtype=np.float64) if time is None else v["t"]
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        k = bad[0] + 1
        raise CsvImportError(
            f"{path} line {lines[k]} column {time!r} (time): {float(t[k])!r} s is not after line {lines[k - 1]}'s "
            f"{float(t[k - 1])!r}; timestamps must increase strictly"
        )
    P = np.stack([v[f"p{i}"] for i in range(3)], axis=1) / LENGTH_UNITS[length_unit]
    if not orientation:
        return _Table(q=q, P=P, R=None, t=t, lines=lines)
    raw = np.stack([v[f"o{i}"] for i in range(len(orientation))], axis=1)
    R = orientations(path, raw, pose_format[0], list(orientation), lines)
    P, R = directed(P, R, pose_format[1])
    return _Table(q=q, P=P, R=R, t=t, lines=lines, raw=raw)


# --------------------------------------------------------------------------- plausibility


def _check_points(path: Path, table: _Table, nominal: np.ndarray, xyz, unit: str, robot: tuple):
    """The points against the nominal robot's: spread (units), coordinates, reach, rigid alignment.

    `robot`: `(origin of joint 1 in the base frame (3,), reach bound (m), alignment tolerance (m),
    reread)`; `reread(k)`: row `k`'s nominal point with its angles read in the other unit, that
    unit's name and the stated one's (None: no revolute joint; `reread` None: not tried).
    **Returns:** `(r, hint)`: each point's distance from the aligned nominal one (m), and `hint(k)`,
    why row `k` lies far from it where a unit explains it (`reread_hint`, else "").
    """
    P, lines, cols = table.P, table.lines, f"columns {list(xyz)} (--xyz, --length-unit {unit})"
    origin, reach, tol, reread = robot
    s_m = np.sqrt(((P - P.mean(0)) ** 2).sum(1).mean())
    s_n = np.sqrt(((nominal - nominal.mean(0)) ** 2).sum(1).mean())
    if s_n > MIN_SPREAD_M and not 1 / SPREAD_FACTOR <= s_m / s_n <= SPREAD_FACTOR:
        far = int(np.argmax(np.linalg.norm(P - P.mean(0), axis=1)))
        other = "mm" if unit == "m" else "m"
        if 1 / SPREAD_FACTOR <= s_m / s_n * LENGTH_UNITS[unit] / LENGTH_UNITS[other] <= SPREAD_FACTOR:
            hint = (
                f"are the lengths in {'millimetres' if other == 'mm' else 'metres'} (--length-unit {other})?"
            )
        else:
            hint = "no length unit fits: check the joint columns (their unit, --joint-unit, and order)"
        raise CsvImportError(
            f"{path} {cols}, lines {lines[0]}-{lines[-1]}: the points spread {s_m:.4g} m (RMS about their "
            f"centroid; line {lines[far]} lies furthest out), the robot's nominal points for the same joints "
            f"{s_n:.4g} m, and it reaches {reach:.3g} m: a factor {s_m / s_n:.3g}; {hint}"
        )
    bad = np.flatnonzero(np.abs(P).max(axis=1) > MAX_COORDINATE_M)
    if bad.size:
        raise CsvImportError(
            f"{path} line {lines[bad[0]]} {cols}: a coordinate of {P[bad[0]].tolist()} m lies beyond "
            f"{MAX_COORDINATE_M:g} m of the device"
        )
    moved, r, R = rigid_alignment(P, nominal, tol)
    base = nominal + (P - moved) @ R  # the measured points in the base frame (the alignment undone)
    d = np.linalg.norm(base - origin, axis=1)
    limit = 1.1 * reach + 0.1
    far = max(FAR_MIN_M, FAR_FACTOR * float(np.median(r)))
    hint = partial(reread_hint, P=P, aligned=(nominal, moved, R), reread=reread, limit=far)
    for bad, why in (
        (np.flatnonzero(d > limit), "beyond the robot's reach"),
        (np.flatnonzero(r > tol), "too far from where the nominal robot puts it"),
    ):
        if bad.size:
            k = bad[np.argmax(r[bad])]
            off = ", ".join(f"{a} {v:+.4g}" for a, v in zip(xyz, P[k] - moved[k]))
            raise CsvImportError(
                f"{path} line {lines[k]} ({cols}): the point lies {why}: {r[k]:.4g} m from its nominal after the "
                f"best rigid alignment of all points (tolerance {tol:.3g} m; off by {off} m), {d[k]:.4g} m from "
                f"joint 1's origin (reach {reach:.3g} m, limit 1.1 x reach + 0.1 m = {limit:.3g} m); "
                f"{bad.size} of {len(P)} rows"
                + (
                    hint(k)
                    or "; check that row's cells (its joints and point), the joint columns' order and the "
                    "point's offset"
                )
            )
    return r, hint


def _check_pose(path: Path, table: _Table, frames: np.ndarray, point, mount, args) -> tuple:
    """The points (`_check_points`) and, with them, the orientations (`_check_orientations`) of
    `table` against the nominal link frames `frames` `(N, 4, 4)`; `point`: the mount's offset
    (None: unknown), `mount`: its rotation (None: unknown). `args`: `(xyz, length_unit,
    (origin, reach, tol, reread), orientation spec)`. **Returns:** `_check_points`' `(r, hint)`."""
    xyz, unit, robot, spec = args
    nominal = frames[:, :3, 3] + frames[:, :3, :3] @ (point if point is not None else np.zeros(3))
    r, hint = _check_points(path, table, nominal, xyz, unit, robot)
    if table.R is not None:
        A0 = rigid_alignment(table.P, nominal, robot[2])[2]
        check_orientations(path, table.R, table.lines, frames[:, :3, :3], A0, mount, spec)
    return r, hint


def _check_readings(path: Path, table: _Table, frames: np.ndarray, point, mount, args) -> tuple:
    """`_check_pose`; where it refuses a table with orientations, the error also names another
    reading of the columns (format, direction) under which the rows would pass."""
    try:
        return _check_pose(path, table, frames, point, mount, args)
    except CsvImportError as e:
        if table.R is None:
            raise
        for P, R, spec, text in other_readings(table.raw, table.P, table.R, args[3]):
            try:
                _check_pose(path, replace(table, P=P, R=R), frames, point, mount, args[:3] + (spec,))
            except CsvImportError:
                continue
            raise CsvImportError(f"{e}; the rows fit as {text}") from None
        raise


# --------------------------------------------------------------------------- writing


def _write_samples(path: Path, table: _Table, joint_names) -> None:
    """`samples.csv`, `ROWS_AT_ONCE` rows at a time, every number as Python's `repr` writes it
    (the shortest text that reads back to the same float)."""
    quat = np.zeros((len(table.t), 0)) if table.R is None else matrix_to_quaternion(table.R)
    head = ["sample", "timestamp", "joint", "x", "y", "z"] + (
        ["qx", "qy", "qz", "qw"] if quat.shape[1] else []
    )
    with open(path, "w", encoding="utf-8") as f:
        f.write(",".join(head + list(joint_names)) + "\n")
        for s in range(0, len(table.t), ROWS_AT_ONCE):
            e = min(s + ROWS_AT_ONCE, len(table.t))
            nums = np.column_stack([table.t[s:e], table.P[s:e], quat[s:e], table.q[s:e]])
            cols = [map(str, range(s, e)), map(repr, nums[:, 0].tolist()), [""] * (e - s)]
            cols += [map(repr, nums[:, k].tolist()) for k in range(1, nums.shape[1])]
            f.write("\n".join(map(",".join, zip(*cols))) + "\n")


def _link_frames(model: KinematicModel, q: np.ndarray, link: int) -> np.ndarray:
    """`(N, 4, 4)` the nominal frame of link `link` at each row's joints, `ROWS_AT_ONCE` rows at a
    time (the last batch padded to the same size): bounded memory whatever the table's size."""
    fk = jax.vmap(forward_kinematics, in_axes=(None, 0))
    if len(q) <= ROWS_AT_ONCE:
        return np.asarray(fk(model, jnp.asarray(q)))[:, link]
    batch = jax.jit(lambda m, x: fk(m, x)[:, link])  # one program for every batch
    out = np.empty((len(q), 4, 4))
    for s in range(0, len(q), ROWS_AT_ONCE):
        part = q[s : s + ROWS_AT_ONCE]
        n = len(part)
        padded = np.concatenate([part, np.repeat(part[-1:], ROWS_AT_ONCE - n, axis=0)])
        out[s : s + n] = np.asarray(batch(model, jnp.asarray(padded)))[:n]
    return out


def _reread_row(k: int, *, model: KinematicModel, q: np.ndarray, link: str, point, unit: str):
    """Row `k`'s nominal point (the base frame, m) with its revolute joints' numbers read in the
    angle unit other than `unit`, that unit's name and `unit`'s; None for a robot without revolute
    joints (`_check_points`' `reread`)."""
    revolute = np.array([kind != "prismatic" for kind in model.joint_types])
    if not revolute.any():
        return None
    other = "deg" if unit == "rad" else "rad"
    qk = q[k].copy()
    qk[revolute] *= ANGLE_UNITS[other] / ANGLE_UNITS[unit]
    T = _link_frames(model, qk[None], list(model.link_names).index(link))[0]
    names = {"deg": "degrees", "rad": "radians"}
    return T[:3, 3] + T[:3, :3] @ (point if point is not None else np.zeros(3)), names[other], names[unit]


def _sha256(path: Path) -> str:
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def _check_arguments(*, joint_unit, length_unit, device_kind, device_name, sigma_m, xyz, point_m):
    """`import_csv`'s units, device, noise, column counts and point offset: the offset as an array (3,)
    or None."""
    for name, value, units in (
        ("joint_unit", joint_unit, ANGLE_UNITS),
        ("length_unit", length_unit, LENGTH_UNITS),
    ):
        if value not in units:
            raise ValueError(
                f"{name} must be one of {sorted(units)} (no default: state the unit), got {value!r}"
            )
    if device_kind not in DEVICE_KINDS:
        raise ValueError(f"device_kind must be one of {DEVICE_KINDS}, got {device_kind!r}")
    file_name(device_name, "device_name (device-name)")  # it names output files (ros_<device>.txt)
    if not (isinstance(sigma_m, (int, float)) and 0.0 < sigma_m <= 1.0):
        raise ValueError(f"sigma_m (the position noise, m) must be in (0, 1], got {sigma_m!r}")
    if len(xyz) != 3:
        raise ValueError(f"xyz names 3 columns, got {list(xyz)}")
    point = None if point_m is None else np.asarray(point_m, np.float64)
    if point is not None and (point.shape != (3,) or not np.all(np.isfinite(point))):
        raise ValueError(f"point_m must be 3 finite numbers (m), got {point_m!r}")
    if point is not None and np.linalg.norm(point) > MAX_POINT_M:
        raise ValueError(
            f"point_m {point.tolist()} lies more than {MAX_POINT_M:g} m from the link: millimetres?"
        )
    return point


def import_csv(
    csv,
    out,
    *,
    robot,
    joints: Sequence[str],
    joint_unit: str,
    xyz: Sequence[str],
    length_unit: str,
    sigma_m: float,
    point_m=None,
    point_rotvec_rad=None,
    orientation: Sequence[str] | None = None,
    orientation_format: str | None = None,
    pose_direction: str | None = None,
    sigma_rad: float | None = None,
    time: str | None = None,
    device_name: str = "tracker",
    device_kind: str = "laser_tracker",
    point_name: str = "point",
    link: str | None = None,
    description: str | None = None,
    overwrite: bool = False,
) -> CsvImport:
    """Convert the CSV table `csv` into the tracker dataset `out` (see the module docstring).

    **Arguments:**
    - `robot`: a URDF file (copied as `robot.urdf`) or a DH/MDH table
      (`jaxcal.io.dh_tables`, copied as `robot_dh.json` / `robot_mdh.json`).
    - `joints`: one column spec per robot joint, in the robot's joint order;
      `joint_unit`: `"rad"` or `"deg"` (a prismatic joint's in `length_unit`).
    - `xyz`: three column specs, the point in the device frame; `length_unit`: `"m"` or `"mm"`.
      A spec is a column name or a sum of them (`"x_t+x_dif"`).
    - `sigma_m`: the position noise, 1-sigma per axis (m).
    - `point_m`: the point's offset on `link` (m, 3), or None when unknown;
      `point_rotvec_rad`: its frame's rotation on `link` (a rotation vector, rad;
      with `point_m`; None: not turned), e.g. `(0, 0, pi/2)` for a camera turned
      a quarter turn about its axis.
    - `orientation`: the orientation's column specs, as many as `orientation_format`
      has (`ORIENTATION_FORMATS`: `quat-xyzw`, `quat-wxyz`, `rotvec-rad`,
      `rotvec-deg`, or `matrix`, row by row), or None; `pose_direction`
      (`POSE_DIRECTIONS`): each row is the point's pose in the device frame, or the
      device's in the point's (inverted here); `sigma_rad`: the orientation noise,
      1-sigma per axis (rad). All three are required with an orientation.
    - `time`: a column of timestamps (s, strictly increasing), else the row index.
    - `device_name`, `device_kind`, `point_name`: the metadata's `device` fields.
    - `link`: the link the point rides on (default the robot's flange).
    - `overwrite`: replace a dataset jaxcal wrote at `out`.

    **Returns:** a `CsvImport`. Raises `CsvImportError` naming the CSV file,
    the column and the line; `DatasetError` for the robot; `OutputError` for `out`.
    """
    csv, robot_file = Path(csv), Path(robot)
    checked = check_output_dir(
        out, inputs=[csv, robot_file], overwrite=overwrite, kind="dataset", what="--out"
    )
    point = _check_arguments(
        joint_unit=joint_unit,
        length_unit=length_unit,
        device_kind=device_kind,
        device_name=device_name,
        sigma_m=sigma_m,
        xyz=xyz,
        point_m=point_m,
    )
    mount = check_orientation_arguments(
        orientation, orientation_format, pose_direction, sigma_rad, point, point_rotvec_rad
    )
    model, limits, robot_name, robot_obj = robot_model(robot_file)
    link = _chain_link(model, robot_file, joints, link)
    columns = dict(
        joints=joints,
        joint_unit=joint_unit,
        xyz=xyz,
        length_unit=length_unit,
        orientation=orientation,
        time=time,
    )
    pose_format = (orientation_format, pose_direction)
    table = _read_table(csv, **columns, model=model, limits=limits, pose_format=pose_format)
    T_link = _link_frames(model, table.q, list(model.link_names).index(link))
    reach = reach_m(model, limits, point)
    tol = ALIGN_TOL_M + 0.05 * reach + (UNKNOWN_POINT_M if point is None else 0.0)
    origin = np.asarray(model.T_parent_joint)[0, :3, 3]
    reread = partial(_reread_row, model=model, q=table.q, link=link, point=point, unit=joint_unit)
    args = (xyz, length_unit, (origin, reach, tol, reread), (orientation, orientation_format, pose_direction))
    r, hint = _check_readings(csv, table, T_link, point, mount, args)
    rms, warnings = float(np.sqrt(np.mean(r**2))), far_rows(csv, table.lines, r, hint)
    del T_link  # a large table's read-back (`load_dataset`) needs the memory
    meta = _metadata(
        csv,
        table,
        model,
        robot_obj,
        **columns,
        link=link,
        point=None if point is None else pose(mount, point),
        device=(device_name, device_kind, point_name),
        sigma=(sigma_m, sigma_rad),
        description=description,
        pose_format=pose_format,
    )
    with atomic_directory(
        out, overwrite=overwrite, inputs=[csv, robot_file], kind="dataset", what="--out", checked=checked
    ) as tmp:
        shutil.copyfile(robot_file, tmp / robot_name)
        _write_samples(tmp / "samples.csv", table, model.joint_names)
        samples, table = len(table.t), None  # a large table's read-back (`load_dataset`) needs the memory
        write_json(tmp / "metadata.json", meta)
        load_dataset(tmp)  # the format's every check, before the rename
    notes = _nominal_like(rms, sigma_m, xyz)
    return CsvImport(Path(out), samples, reach, rms, notes, tuple(warnings))


def _nominal_like(rms: float, sigma_m: float, xyz) -> tuple[str, ...]:
    """A note when the points lie as near the nominal robot's as their noise: commanded points?"""
    if rms >= NOMINAL_LIKE * sigma_m:
        return ()
    return (
        f"the points lie only {rms * 1e3:.3g} mm RMS from the nominal robot's, within {NOMINAL_LIKE:g}x their "
        f"stated noise ({sigma_m * 1e3:.3g} mm): are {xyz} the commanded (nominal) points rather than "
        "measured ones? A real arm is typically 0.5-5 mm off its datasheet, and a calibration on these "
        "points learns nothing",
    )


def _chain_link(model, robot_file: Path, joints: Sequence[str], link: str | None) -> str:
    """The link the point rides on (default the flange), once the joint columns match the chain."""
    if len(joints) != len(model.joint_names):
        raise ValueError(
            f"{len(joints)} joint column(s) {list(joints)} for the {len(model.joint_names)} joints of {shown(robot_file)}: "
            f"name one column per joint, in the robot's order {list(model.joint_names)}"
        )
    link = link or model.link_names[-1]
    if link not in model.link_names:
        raise ValueError(
            f"link {link!r} is not a link of the chain of {shown(robot_file)}: {list(model.link_names)}"
        )
    return link


def _metadata(
    csv: Path,
    table,
    model,
    robot_obj,
    *,
    joints,
    joint_unit,
    xyz,
    length_unit,
    orientation,
    time,
    link,
    point,
    device,
    sigma,
    description,
    pose_format,
) -> dict:
    """The imported dataset's `metadata.json`: the device (`device`: its name, kind and point
    name; `sigma`: the position and orientation noise) and the CSV's provenance (`x_csv`)."""
    device_name, device_kind, point_name = device
    sigma_m, sigma_rad = sigma
    device = {
        "name": device_name,
        "kind": device_kind,
        "file": "samples.csv",
        "link": link,
        "point": point_name,
        "T_link_point_nominal": point,
        "sigma_m": float(sigma_m),
        "sigma_rad": None if orientation is None else float(sigma_rad),
    }
    return {
        "schema": SCHEMA,
        "schema_version": SCHEMA_VERSION,
        "description": description or f"imported from the CSV table {csv.name} by jaxcal import-csv",
        "robot": robot_obj,
        "device": device,
        "motion": [{"joint": None, "start": float(table.t[0]), "end": float(table.t[-1])}],
        "x_csv": {
            "file": csv.name,
            "sha256": _sha256(csv),
            "joints": dict(zip(model.joint_names, joints)),
            "joint_unit": joint_unit,
            "xyz": list(xyz),
            "length_unit": length_unit,
            "orientation": None if orientation is None else list(orientation),
            "orientation_format": pose_format[0],
            "pose_direction": pose_format[1],
            "time": time,
            "rows": len(table.t),
        },
    }
