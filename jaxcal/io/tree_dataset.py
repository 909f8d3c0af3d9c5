"""Tree datasets: a folder with `tree.json`, the robot file and a samples CSV (`jaxcal.trees`).

    tree.json     {"robot": "robot.urdf", "tips": ["left_hand", "right_hand"], "noise_mm": 0.1}
    samples.csv   torso_yaw,...,left_hand.x,left_hand.y,left_hand.z,right_hand.x,...

Each row is a stop-and-shoot pose: the actuated joints (rad or m) and each measured tip's point
(m, device frame). A device whose points carry their own covariance (a camera's PnP sees across
the image far better than in depth) adds `TIP.cov_xx`, `TIP.cov_xy`, `TIP.cov_xz`, `TIP.cov_yy`,
`TIP.cov_yz`, `TIP.cov_zz` per tip (m^2, device frame) and states no `noise_mm`.
"""

import csv
import json
from dataclasses import dataclass
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from .._npgeom import kabsch
from .._rowshift import describe, misfit_share, shifted_points
from .._tree import KinematicTree, tip_poses
from .._treefit import FAMILIES, TreeSamples
from ._csv_poses import ANGLE_UNITS, LENGTH_UNITS
from ._files import atomic_directory, shown
from .urdf_tree import actuated_limits, load_urdf_tree

#: A point's covariance columns (`TIP.cov_xx` ...: m^2), and where each sits in the 3x3 matrix.
COVARIANCE = {
    "cov_xx": (0, 0),
    "cov_xy": (0, 1),
    "cov_xz": (0, 2),
    "cov_yy": (1, 1),
    "cov_yz": (1, 2),
    "cov_zz": (2, 2),
}


def read_tree_samples(path, tree: KinematicTree) -> TreeSamples:
    """Stop-and-shoot samples from a CSV file: a column per actuated joint (its name; rad or m)
    and, per measured tip, columns `TIP.x`, `TIP.y`, `TIP.z` (m, device frame). An empty cell
    in a tip's columns marks the tip unmeasured in that row; `TIP.cov_xx` ... `TIP.cov_zz` (m^2,
    every tip or none) give each point's covariance. Raises `ValueError` naming the file, the row
    and the column of what cannot be read."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"tree samples {shown(path)!r} do not exist")
    with path.open(newline="", encoding="utf-8-sig") as f:  # a spreadsheet's byte-order mark
        header = next(csv.reader(f), [])
        f.seek(0)
        rows = list(csv.DictReader(f))
    if not rows:
        raise ValueError(f"tree samples {shown(path)!r}: no rows")
    twice = sorted({h for h in header if header.count(h) > 1})
    if twice:
        raise ValueError(f"tree samples {shown(path)!r}: column(s) {twice} appear more than once")
    missing = [n for n in tree.actuated_names if n not in header]
    if missing:
        raise ValueError(f"tree samples {shown(path)!r}: no column for joint(s) {missing}")
    suffixes = ("x", "y", "z", *COVARIANCE)
    groups = {h.rsplit(".", 1)[0] for h in header if h.rsplit(".", 1)[-1] in suffixes and "." in h}
    unknown = sorted(groups - set(tree.tip_names))
    if unknown:
        raise ValueError(
            f"tree samples {shown(path)!r}: columns for {unknown}, which are not tips of the tree {tree.tip_names}"
        )
    partial = sorted(t for t in groups if not all(f"{t}.{a}" in header for a in "xyz"))
    if partial:
        raise ValueError(
            f"tree samples {shown(path)!r}: tip(s) {partial} lack one of their .x, .y, .z columns"
        )
    with_cov = sorted(t for t in groups if any(f"{t}.{c}" in header for c in COVARIANCE))
    partial = [t for t in with_cov if not all(f"{t}.{c}" in header for c in COVARIANCE)]
    if partial or (with_cov and set(with_cov) != groups):
        raise ValueError(
            f"tree samples {shown(path)!r}: every tip needs all six of {[f'TIP.{c}' for c in COVARIANCE]} "
            f"or none; {sorted(set(partial) | (groups - set(with_cov)))} lack some"
        )
    tips = [t for t in tree.tip_names if t in groups]
    if not tips:
        raise ValueError(
            f"tree samples {shown(path)!r}: no tip's columns; expected TIP.x, TIP.y, TIP.z for a tip of {tree.tip_names}"
        )

    def number(row: int, column: str, text: str) -> float:
        try:
            value = float(text)
        except (TypeError, ValueError):
            value = float("nan")
        if not np.isfinite(value):
            raise ValueError(
                f"tree samples {shown(path)!r}: line {row + 2}, column {column!r}: {text!r} is not a finite number"
            )
        return value

    q = np.array([[number(i, n, r[n]) for n in tree.actuated_names] for i, r in enumerate(rows)])
    _coupled_columns(path, tree, header, rows, q)
    points = np.full((len(rows), len(tree.tip_names), 3), np.nan)
    measured = np.zeros((len(rows), len(tree.tip_names)), bool)
    cov = np.tile(np.eye(3), (len(rows), len(tree.tip_names), 1, 1))
    for i, r in enumerate(rows):
        for t in tips:
            cells = [r[f"{t}.{a}"] for a in "xyz"]
            if all(c in ("", None) for c in cells):
                continue
            k = tree.tip_names.index(t)
            points[i, k] = [number(i, f"{t}.{a}", c) for a, c in zip("xyz", cells)]
            measured[i, k] = True
            for c, (a, b) in COVARIANCE.items() if with_cov else ():
                cov[i, k, a, b] = cov[i, k, b, a] = number(i, f"{t}.{c}", r[f"{t}.{c}"])
    return TreeSamples(q, points, measured, covariance=cov if with_cov else None)


#: A tree dataset is a folder with this file (besides its robot file and samples CSV).
TREE_FILE = "tree.json"


@dataclass(frozen=True)
class TreeDataset:
    """A tree dataset read by `load_tree_dataset`: the robot file, its tree (with the tips the
    samples measure), the samples, the device's noise (mm per axis: the covariances' RMS
    where the samples carry them), the points' nominal
    positions on the tips (m), the term families (None: cross-validation chooses), the
    actuated joints' limits, and the truth a simulator wrote (`truth.json`, or None)."""

    folder: Path
    urdf: Path
    tree: KinematicTree
    samples: TreeSamples
    noise_mm: float
    points: np.ndarray
    families: tuple[str, ...] | None
    limits: np.ndarray
    truth: dict | None
    device_on: str | None = None


def is_tree_dataset(path) -> bool:
    return (Path(path) / TREE_FILE).is_file()


def _field(doc: dict, name: str, path: Path, kind, required: bool = True, default=None):
    if name not in doc:
        if required:
            raise ValueError(f"{shown(path)!r}: no field {name!r}")
        return default
    value = doc[name]
    if not isinstance(value, kind) or isinstance(value, bool):
        raise ValueError(f"{shown(path)!r}: field {name!r} is {value!r}, not a {kind.__name__}")
    return value


def read_json_object(path: Path, what: str) -> dict:
    """The JSON object in `path` (`what` it is, for the errors), or a `ValueError` naming it."""
    try:
        doc = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ValueError(f"{what} {shown(path)!r} cannot be read: {e}") from None
    if not isinstance(doc, dict):
        raise ValueError(f"{what} {shown(path)!r}: not a JSON object")
    return doc


def covariance_noise_mm(samples: TreeSamples) -> float:
    """The measured points' covariances as one noise, mm per axis: their RMS (`calibrate_tree`'s
    stated noise where the samples carry covariances)."""
    seen = np.asarray(samples.covariance)[np.asarray(samples.measured)]
    return 1e3 * float(np.sqrt(np.trace(seen, axis1=-2, axis2=-1).mean() / 3.0))


#: A logged coupled joint off its robot file's law by more than this (rad or m) contradicts it.
COUPLED_TOL = 1e-3


def _coupled_columns(path: Path, tree: KinematicTree, header, rows, q: np.ndarray) -> None:
    """Refuse a column that logs a coupled joint (a `<mimic>`) whose values break the robot file's
    law (`COUPLED_TOL`): the law is wrong, or the joint is driven on its own."""
    coupled = [j for j, n in enumerate(tree.joint_names) if n in header and n not in tree.actuated_names]
    if not coupled:
        return
    law = q @ np.asarray(tree.coupling).T + np.asarray(tree.coupling_offset)
    for j in coupled:
        name = tree.joint_names[j]
        cells = [(i, r[name]) for i, r in enumerate(rows) if r[name] not in ("", None)]
        try:
            logged = np.array([float(c) for _, c in cells])
        except ValueError:
            continue  # not numbers: the column is not used, as any other unknown one
        gap = np.abs(logged - law[[i for i, _ in cells], j]) if cells else np.zeros(0)
        if gap.size and np.nanmax(gap) > COUPLED_TOL:
            k = int(np.nanargmax(gap))
            raise ValueError(
                f"tree samples {shown(path)!r}: column {name!r} logs a joint the robot file couples to others "
                f"(<mimic>), and it breaks that law by up to {gap[k]:.4g} (line {cells[k][0] + 2}): the robot "
                "file's multiplier or offset is wrong, or the joint is driven on its own (then it must not be a "
                "<mimic>); drop the column to use the law as it is"
            )


#: A measured point farther than this (m) from the device is no robot's: millimetres as metres.
MAX_POINT_M = 100.0


def _plausible(path: Path, tree: KinematicTree, samples: TreeSamples, limits: np.ndarray) -> None:
    """Refuse, by file, line and column, points no robot reaches (`MAX_POINT_M`: millimetres) and
    joint positions outside the robot file's limits (in degrees where every such one reads as a
    position within them in degrees)."""
    far = np.argwhere(np.asarray(samples.measured) & (np.abs(samples.points).max(axis=-1) > MAX_POINT_M))
    if far.size:
        i, t = far[0]
        raise ValueError(
            f"tree samples {shown(path)!r}: line {i + 2}, tip {tree.tip_names[t]!r}: the point "
            f"{samples.points[i, t].tolist()} lies more than {MAX_POINT_M:g} m from the device: give metres "
            "(millimetres written?)"
        )
    q = np.asarray(samples.q)
    out = (q < limits[:, 0] - 1e-9) | (q > limits[:, 1] + 1e-9)
    if out.any():
        i, j = np.argwhere(out)[0]
        rad = np.radians(q[out[:, j], j])
        degrees = bool(np.all((rad >= limits[j, 0] - 1e-9) & (rad <= limits[j, 1] + 1e-9)))
        raise ValueError(
            f"tree samples {shown(path)!r}: line {i + 2}, column {tree.actuated_names[j]!r}: {q[i, j]:.6g} lies "
            f"outside the robot file's limits [{limits[j, 0]:.6g}, {limits[j, 1]:.6g}] (rad or m); {int(out[:, j].sum())} "
            f"row(s) of that column do"
            + ("; read as degrees they lie within them: the column in degrees?" if degrees else "")
        )


#: A tip's points are another tip's when at least this share of them lie 20 mm or more from its
#: own nominal tip (`jaxcal._rowshift.misfit_share`) and at most this share from the other's (a
#: body is centimetres off its robot file where its joints sag: looser than a chain's).
SWAP_AS_READ, SWAP_FITS = 0.75, 0.25


def _paired(path: Path, tree: KinematicTree, samples: TreeSamples) -> None:
    """Refuse, naming the fix, points that fit the robot file's tips (a fixed device's frame and
    each tip's point fitted, `jaxcal._rowshift`) only shifted against the joint positions, or
    only under another tip's columns (two tips' columns swapped)."""
    frames = np.asarray(jax.vmap(lambda q: tip_poses(tree, q))(jnp.asarray(samples.q)))
    measured = np.asarray(samples.measured)
    for t, name in enumerate(tree.tip_names):
        rows = np.flatnonzero(measured[:, t])
        if rows.size < 8:
            continue
        found = shifted_points(frames[rows, t], samples.points[rows, t])
        if found is not None:
            where = describe(found, lambda k: str(rows[k] + 2), "line", "robot pose")
            raise ValueError(
                f"tree samples {shown(path)!r}: tip {name!r}'s points fit the robot file only with the rows "
                f"shifted against the joint positions: {where}. Pair each point with the joints it was measured at"
            )
        if misfit_share(frames[rows, t], samples.points[rows, t]) < SWAP_AS_READ:
            continue
        for u, other in enumerate(tree.tip_names):
            if u != t and misfit_share(frames[rows, u], samples.points[rows, t]) <= SWAP_FITS:
                raise ValueError(
                    f"tree samples {shown(path)!r}: tip {name!r}'s columns fit the robot file as {other!r}'s: "
                    f"the columns {name}.x, .y, .z and {other}'s are swapped (label them as measured)"
                )


def load_tree_dataset(folder) -> TreeDataset:
    """Read a tree dataset folder: `tree.json` names the robot file (`robot`), the measured
    `tips`, the `samples` CSV (default `samples.csv`, `read_tree_samples`' format), the device's
    `noise_mm` (1-sigma per axis; none where the samples carry covariances), optionally `points_m` (each tip's point, m, tip frame),
    `terms` (`"auto"`, or a list of `jaxcal._treefit.FAMILIES`), `base_link` and `device_on` (the
    tip the device rides on: a head camera; it is then one of `tips`, and never measured). Raises
    `ValueError` naming the file and field of what is missing or malformed."""
    folder = Path(folder)
    path = folder / TREE_FILE
    doc = read_json_object(path, "tree dataset")
    urdf = folder / _field(doc, "robot", path, str)
    tips = _field(doc, "tips", path, list)
    if not tips or not all(isinstance(t, str) for t in tips):
        raise ValueError(
            f"tree dataset {shown(path)!r}: field 'tips' must list the measured tips' link names"
        )
    noise = doc.get("noise_mm")
    if noise is not None and (
        not isinstance(noise, (int, float)) or isinstance(noise, bool) or not noise > 0
    ):
        raise ValueError(
            f"tree dataset {shown(path)!r}: field 'noise_mm' must be the device's positive noise (mm per axis), got {noise!r}"
        )
    tree = load_urdf_tree(urdf, base_link=_field(doc, "base_link", path, str, required=False), tips=tips)
    device_on = _field(doc, "device_on", path, str, required=False)
    _no_device_columns(
        folder / _field(doc, "samples", path, str, required=False, default="samples.csv"), device_on
    )
    table = folder / _field(doc, "samples", path, str, required=False, default="samples.csv")
    samples = read_tree_samples(table, tree)
    _plausible(table, tree, samples, actuated_limits(urdf, tree))
    if device_on is None:  # a fixed device: the points against the robot file's tips
        _paired(table, tree, samples)
    if samples.covariance is not None and noise is not None:
        raise ValueError(
            f"tree dataset {shown(path)!r}: field 'noise_mm' is given, but the samples carry their own "
            "covariances (TIP.cov_xx ...): state one or the other"
        )
    if samples.covariance is None and noise is None:
        raise ValueError(
            f"tree dataset {shown(path)!r}: no field 'noise_mm' (the device's noise, mm per axis) and no "
            "covariance columns (TIP.cov_xx ...) in the samples"
        )
    points = np.zeros((len(tips), 3))
    for t, xyz in _field(doc, "points_m", path, dict, required=False, default={}).items():
        if t not in tips or np.shape(xyz) != (3,) or not np.all(np.isfinite(np.asarray(xyz, float))):
            raise ValueError(
                f"tree dataset {shown(path)!r}: points_m[{t!r}] must be a tip's [x, y, z] (m), got {xyz!r}"
            )
        points[tips.index(t)] = xyz
    terms = doc.get("terms", "auto")
    if terms != "auto" and (not isinstance(terms, list) or set(terms) - set(FAMILIES)):
        raise ValueError(
            f"tree dataset {shown(path)!r}: field 'terms' must be \"auto\" or a list of {list(FAMILIES)}, got {terms!r}"
        )
    truth_path = folder / "truth.json"
    return TreeDataset(
        folder=folder,
        urdf=urdf,
        tree=tree,
        samples=samples,
        noise_mm=float(noise) if noise is not None else covariance_noise_mm(samples),
        points=points,
        families=None if terms == "auto" else tuple(terms),
        limits=actuated_limits(urdf, tree),
        truth=json.loads(truth_path.read_text()) if truth_path.is_file() else None,
        device_on=device_on,
    )


def _no_device_columns(path: Path, device_on: str | None) -> None:
    """Refuse a samples CSV with columns for the tip the device rides on (it measures the others)."""
    if device_on is None or not path.is_file():
        return
    with path.open(newline="", encoding="utf-8-sig") as f:
        header = next(csv.reader(f), [])
    own = [h for h in header if h.startswith(f"{device_on}.")]
    if own:
        raise ValueError(
            f"tree samples {shown(path)!r}: columns {own[:3]}{' ...' if len(own) > 3 else ''} are for tip "
            f"{device_on!r}, which the device rides on (tree.json's device_on): drop them"
        )


def write_tree_dataset(
    folder,
    *,
    urdf_text: str,
    tips,
    samples: TreeSamples,
    tree: KinematicTree,
    noise_mm: float | None,
    points,
    truth: dict | None = None,
    device_on: str | None = None,
    overwrite: bool = False,
) -> Path:
    """Write a tree dataset (`load_tree_dataset`'s format) atomically: `robot.urdf`, `tree.json`,
    `samples.csv` (unmeasured tips' cells empty; each point's covariance where the samples carry
    one, and then no `noise_mm`) and, from a simulator, `truth.json`. `device_on`: the tip the
    device rides on (a head camera), which has no columns."""
    folder = Path(folder)
    cov = samples.covariance
    if (cov is None) == (noise_mm is None):
        raise ValueError("give noise_mm, or samples that carry their covariances, not both")
    columns = [k for k, t in enumerate(tips) if t != device_on]
    names = ("x", "y", "z", *(COVARIANCE if cov is not None else ()))
    header = list(tree.actuated_names) + [f"{tips[k]}.{a}" for k in columns for a in names]
    rows = []
    for i, (q, p, seen) in enumerate(zip(samples.q, samples.points, samples.measured)):
        cells = [repr(float(v)) for v in q]
        for k in columns:
            values = [*p[k], *(cov[i, k][ab] for ab in COVARIANCE.values())] if cov is not None else p[k]
            cells += [repr(float(v)) for v in values] if seen[k] else [""] * len(names)
        rows.append(",".join(cells))
    doc = {
        "robot": "robot.urdf",
        "tips": list(tips),
        "samples": "samples.csv",
        **({"noise_mm": noise_mm} if cov is None else {}),
        **({"device_on": device_on} if device_on else {}),
        "points_m": {t: np.asarray(x, float).tolist() for t, x in zip(tips, points)},
        "terms": "auto",
    }
    with atomic_directory(folder, overwrite=overwrite, kind="dataset") as tmp:
        (tmp / "robot.urdf").write_text(urdf_text)
        (tmp / TREE_FILE).write_text(json.dumps(doc, indent=2) + "\n")
        (tmp / "samples.csv").write_text(",".join(header) + "\n" + "\n".join(rows) + "\n")
        if truth is not None:
            (tmp / "truth.json").write_text(json.dumps(truth, indent=2) + "\n")
    return folder


#: Points further than this from the robot file's (after the best rigid alignment, RMS) are
#: named when a CSV is imported: wrong columns or units, not a robot's errors.
IMPORT_FAR_M = 0.05


def import_tree_csv(
    path,
    out,
    *,
    robot,
    links,
    joints,
    joint_unit: str,
    xyz,
    length_unit: str,
    sigma_m: float,
    overwrite=False,
) -> tuple[Path, int, float]:
    """`jaxcal import-csv` for a robot that is a tree: a table of joint positions and a point per
    link in `links` (`xyz`: three column specs per link, `a` or a sum `a+b`; a link's three cells
    empty where it was not measured) into a tree dataset. Joints in `joint_unit` (revolute) or
    `length_unit` (prismatic), points in `length_unit`, `sigma_m` the device's noise per axis.
    Returns the folder, the rows and the points' RMS distance (m) from the robot file's after the
    best rigid alignment. Raises `ValueError` naming the file, line and column of what is wrong."""
    path, robot = Path(path), Path(robot)
    tree = load_urdf_tree(robot, tips=list(links))
    if len(joints) != tree.num_actuated:
        raise ValueError(
            f"--joint-columns: {len(joints)} columns for the tree's {tree.num_actuated} actuated joints "
            f"{list(tree.actuated_names)} (in that order)"
        )
    if len(xyz) != 3 * len(links):
        raise ValueError(
            f"--xyz: {len(xyz)} columns for {len(links)} links {list(links)}: give x,y,z of each"
        )
    kinds = dict(zip(tree.joint_names, tree.joint_types))
    scale = np.array(
        [
            1 / LENGTH_UNITS[length_unit] if kinds[n] == "prismatic" else ANGLE_UNITS[joint_unit]
            for n in tree.actuated_names
        ]
    )
    q, points = _read_table(path, joints, xyz, scale, len(links))
    points = points / LENGTH_UNITS[length_unit]
    _within_limits(path, q, actuated_limits(robot, tree), tree, joints, joint_unit)
    measured = np.isfinite(points).all(axis=-1)
    if not measured.any():
        raise ValueError(f"{shown(path)!r}: no row measures any link's point")
    tips = np.stack([np.asarray(tip_poses(tree, jnp.asarray(qi))) for qi in q])
    nominal = tips[..., :3, 3]  # each link's origin: the points' offsets on them are unknown yet
    T = kabsch(nominal[measured], points[measured])
    rms = float(
        np.sqrt(np.mean(np.sum((nominal[measured] @ T[:3, :3].T + T[:3, 3] - points[measured]) ** 2, -1)))
    )
    samples = TreeSamples(q, np.where(measured[..., None], points, 0.0), measured)
    folder = write_tree_dataset(
        out,
        urdf_text=robot.read_text(),
        tips=list(links),
        samples=samples,
        tree=tree,
        noise_mm=1e3 * sigma_m,
        points=np.zeros((len(links), 3)),
        overwrite=overwrite,
    )
    return folder, len(q), rms


def _read_table(path: Path, joints, xyz, scale: np.ndarray, links: int) -> tuple[np.ndarray, np.ndarray]:
    """`import_tree_csv`'s table: the joints times `scale` `(rows, actuated)`, and each link's
    point `(rows, links, 3)` in the table's unit (NaN where its three cells are empty)."""
    try:
        with path.open(newline="", encoding="utf-8-sig") as f:
            rows = list(csv.reader(f))
    except (OSError, UnicodeDecodeError) as e:
        raise ValueError(f"{shown(path)!r}: cannot read the CSV table ({e})") from None
    header = [h.strip() for h in (rows[0] if rows else [])]
    rows = [r for r in rows[1:] if any(c.strip() for c in r)]
    if len(rows) < 2:
        raise ValueError(f"{shown(path)!r}: {len(rows)} data row(s); a dataset needs at least 2")

    def columns(spec: str, option: str) -> list[int]:
        missing = [p.strip() for p in spec.split("+") if p.strip() not in header]
        if missing or not spec.strip():
            raise ValueError(
                f"{shown(path)!r} line 1: no column {missing or spec!r} (named by {option}); the header has {header}"
            )
        return [header.index(p.strip()) for p in spec.split("+")]

    def value(row: list[str], line: int, spec: str, cols: list[int]) -> float | None:
        cells = [row[c].strip() if c < len(row) else "" for c in cols]
        if all(not c for c in cells):
            return None
        try:
            v = sum(float(c) for c in cells)
        except ValueError:
            v = float("nan")
        if not np.isfinite(v):
            raise ValueError(
                f"{shown(path)!r} line {line} column {spec!r}: {'+'.join(cells)!r} is not a finite number"
            )
        return v

    jcols = [columns(s, "--joint-columns") for s in joints]
    pcols = [columns(s, "--xyz") for s in xyz]
    q = np.zeros((len(rows), len(joints)))
    points = np.full((len(rows), links, 3), np.nan)
    for i, row in enumerate(rows):
        line = i + 2
        for j, (spec, cols) in enumerate(zip(joints, jcols)):
            v = value(row, line, spec, cols)
            if v is None:
                raise ValueError(
                    f"{shown(path)!r} line {line} column {spec!r}: empty (every joint is needed)"
                )
            q[i, j] = v * scale[j]
        for k in range(links):
            cells = [value(row, line, xyz[3 * k + a], pcols[3 * k + a]) for a in range(3)]
            if any(c is None for c in cells) and not all(c is None for c in cells):
                raise ValueError(
                    f"{shown(path)!r} line {line}: link {links[k]!r} has some of its x, y, z and not all"
                )
            if cells[0] is not None:
                points[i, k] = cells
    return q, points


def _within_limits(
    path: Path, q: np.ndarray, limits: np.ndarray, tree: KinematicTree, joints, unit: str
) -> None:
    """Refuse joint positions outside the robot file's limits, naming the line and column (and
    degrees where the values would fit as degrees)."""
    bad = (q < limits[:, 0] - 1e-9) | (q > limits[:, 1] + 1e-9)
    if not bad.any():
        return
    i, j = np.argwhere(bad)[0]
    hint = ""
    if unit == "rad" and np.all(np.abs(np.radians(q[:, j])) <= np.maximum(np.abs(limits[j]).max(), np.pi)):
        hint = "; the values look like degrees: --joint-unit deg?"
    raise ValueError(
        f"{shown(path)!r} line {i + 2} column {joints[j]!r} ({tree.actuated_names[j]}): {q[i, j]:.6g} is outside "
        f"the limits [{limits[j, 0]:.6g}, {limits[j, 1]:.6g}] ({bad.sum()} cells){hint}"
    )
