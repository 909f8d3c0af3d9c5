"""DH / MDH table files (JSON or YAML): the shipped datasheet tables and the calibrated ones.

The schema of `data/robots/*_dh.json` (`convention`, `joint_names`, columns
`a`, `alpha`, `d`, `theta`, an optional `base` 4x4, `flange`, `base_link`,
`flange_link`), with optional per-joint fields a datasheet gives:

- `lower`, `upper` (rad): the joint's position limits (both or neither,
  `lower < upper`); `velocity` (rad/s, positive): its speed limit.
- `mass` (kg, positive) and `com` (m, one `[x, y, z]` per joint): the mass
  and centre of mass of the link that moves with joint $i$, in that link's
  table frame $i$ (DH frame $i$ of a `"dh"` table, MDH frame $i$ of an
  `"mdh"` one: the frames the manufacturers publish them in).
- `link_names`: the names of the links that move with each joint (default
  `"{name}_link{i}"`, `name` the file's stem).

and, for calibrated tables:

- `beta`, `parallel`: Hayati's extra rotation about $y$ per row and the rows
  that carry it (consecutive axes within 10 degrees of parallel; their $d$ is
  0 by the rule of `jaxcal._dh`); absent means zero / none.
- `flange`: either Craig/DH parameters `{a, alpha, d, theta}` (the datasheets)
  or `{"matrix": 4x4}` (a calibrated flange is a general transform).
- `reduction_ratio` (optional), `std` (1-sigma of every column and of the
  base and flange as `xyz_rpy`), `nominal` (the nominal model's columns).

`base_link` and `flange_link` default to `"base_link"` and `"flange"`. A file
ending in `.yaml` or `.yml` is read as YAML, any other as JSON.

`read_table_file` reads and checks either kind (`read_dh_table` gives its
`DHTable` and raw document); `dh_table_model` turns a file into a
`KinematicModel` (`robots.dh_model` uses it), `table_inertials` gives its
masses and centres of mass in that model's link frames, `dh_table_json`
writes a calibrated table.
"""

import math
from dataclasses import dataclass
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from ruamel.yaml import YAMLError

from .._device import to_device
from .._dh import COLUMNS, DHTable, link_transform, table_to_model
from .._kinematics import KinematicModel
from ..errors import DatasetError
from ._files import shown
from ._schema import load_yaml, loads
from .urdf import JointLimits

#: What `parallel` means, written into every calibrated table.
PARALLEL_RULE = (
    "rows marked parallel join axes within 10 degrees of parallel: DH is ill-conditioned there "
    "(d slides along the axes), so they use Hayati's form, d = 0 and an extra rotation beta about y "
    "(DH: Rz(theta) Tx(a) Rx(alpha) Ry(beta); MDH: Rx(alpha) Tx(a) Ry(beta) Rz(theta) Tz(d))"
)
#: File endings read as table files (the rest of a robot's files are URDFs).
TABLE_SUFFIXES = (".json", ".yaml", ".yml")
#: Link names of a table without `base_link` / `flange_link`.
DEFAULT_BASE_LINK, DEFAULT_FLANGE_LINK = "base_link", "flange"


def is_table_file(path) -> bool:
    """Whether `path` names a table file (by its ending, `TABLE_SUFFIXES`), not a URDF."""
    return Path(path).suffix.lower() in TABLE_SUFFIXES


@dataclass(frozen=True, eq=False)
class TableFile:
    """A checked table file (see the module docstring for the fields).

    `table`: its `DHTable`; `doc`: the parsed document (for the other
    fields); `link_names`: the links of joints 1..n (`None`: the default
    names); `reduction_ratio`, `lower`, `upper`, `velocity`, `mass` (joints,)
    and `com` (joints, 3) are `None` where the file does not give them.
    """

    path: Path
    table: DHTable
    doc: dict
    base_link: str
    flange_link: str
    link_names: tuple[str, ...] | None
    reduction_ratio: np.ndarray | None
    lower: np.ndarray | None
    upper: np.ndarray | None
    velocity: np.ndarray | None
    mass: np.ndarray | None
    com: np.ndarray | None

    def joint_limits(self) -> dict[str, JointLimits]:
        """Joint name -> `JointLimits` (revolute; limits `None` where the file has none)."""
        n = len(self.table.joint_names)
        ratio = np.ones(n) if self.reduction_ratio is None else self.reduction_ratio
        return {
            name: JointLimits(
                "revolute",
                None if self.lower is None else float(self.lower[i]),
                None if self.upper is None else float(self.upper[i]),
                None if self.velocity is None else float(self.velocity[i]),
                float(ratio[i]),
            )
            for i, name in enumerate(self.table.joint_names)
        }


def _fail(path: Path, message: str) -> DatasetError:
    return DatasetError(f"DH table {shown(path)!r}: {message}")


def _document(path: Path) -> dict:
    """The parsed file: YAML for `.yaml` / `.yml`, else JSON; an object, or a `DatasetError`."""
    try:
        text = path.read_text(encoding="utf-8-sig")
        doc = load_yaml(text) if path.suffix.lower() in (".yaml", ".yml") else loads(text)
    except (OSError, UnicodeDecodeError, ValueError, YAMLError) as e:
        raise DatasetError(f"DH table {shown(path)!r} cannot be read: {e}") from None
    if not isinstance(doc, dict):
        raise _fail(path, f"expected an object of fields, got {type(doc).__name__}")
    return doc


def _numbers(path: Path, field: str, value, shape: tuple[int, ...]) -> np.ndarray:
    """`value` as a float array of `shape`, every entry a finite number (not a bool or a string)."""

    def ok(v, depth):
        if depth == len(shape):
            return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
        return isinstance(v, list) and len(v) == shape[depth] and all(ok(x, depth + 1) for x in v)

    if not ok(value, 0):
        what = " x ".join(map(str, shape))
        raise _fail(path, f"field {field!r} must hold {what} finite numbers, got {value!r}"[:400])
    return np.asarray(value, dtype=np.float64)


def _optional(path: Path, doc: dict, field: str, shape: tuple[int, ...]) -> np.ndarray | None:
    return None if doc.get(field) is None else _numbers(path, field, doc[field], shape)


def _link_name(path: Path, doc: dict, field: str, default: str) -> str:
    v = doc.get(field, default)
    if not isinstance(v, str) or not v:
        raise _fail(path, f"field {field!r} must be a link name (a non-empty string), got {v!r}")
    return v


def read_table_file(path) -> TableFile:
    """Read and check a DH / MDH table file (JSON, or YAML by its ending).

    Raises `DatasetError` naming the file and the field at fault: a missing
    column, a column of the wrong length or not finite, limits with
    `lower >= upper`, a mass that is not positive, a centre of mass that is
    not one finite `[x, y, z]` per joint.
    """
    path = Path(path)
    doc = _document(path)
    convention = doc.get("convention")
    if convention not in ("dh", "mdh"):
        raise _fail(path, f"convention must be 'dh' or 'mdh', got {convention!r}")
    names = doc.get("joint_names")
    if not isinstance(names, list) or not names or not all(isinstance(j, str) and j for j in names):
        if "joint_names" not in doc:
            raise DatasetError(f"DH table {shown(path)!r} has no field 'joint_names'")
        raise _fail(path, f"field 'joint_names' must be a non-empty list of names, got {names!r}")
    if len(set(names)) != len(names):
        raise _fail(path, f"field 'joint_names' has duplicates: {names}")
    n = len(names)
    for c in ("a", "alpha", "d", "theta", "flange"):
        if c not in doc:
            raise DatasetError(f"DH table {shown(path)!r} has no field {c!r}")
    cols = {
        c: _numbers(path, c, doc[c] if c != "beta" else doc.get("beta", [0.0] * n), (n,)) for c in COLUMNS
    }
    parallel = doc.get("parallel", [False] * n)
    if not isinstance(parallel, list) or len(parallel) != n or not all(isinstance(p, bool) for p in parallel):
        raise _fail(path, f"field 'parallel' must hold {n} flags (true / false)")
    T_base = _matrix(path, "base", doc.get("base"))
    flange = doc["flange"]
    if isinstance(flange, dict) and "matrix" in flange:
        T_flange = _matrix(path, "flange.matrix", flange["matrix"])
    else:
        try:
            f = [_numbers(path, f"flange.{k}", flange[k], ()) for k in ("theta", "d", "a", "alpha")]
        except (KeyError, TypeError):
            raise _fail(path, "field 'flange' must be {a, alpha, d, theta} or {matrix}") from None
        T_flange = to_device(link_transform(convention, *(float(v) for v in f), 0.0), np.float64)
    table = DHTable(
        *(to_device(cols[c], np.float64) for c in COLUMNS),
        T_base,
        T_flange,
        convention,
        tuple(names),
        tuple(parallel),
    )
    base_link = _link_name(path, doc, "base_link", DEFAULT_BASE_LINK)
    flange_link = _link_name(path, doc, "flange_link", DEFAULT_FLANGE_LINK)
    links = doc.get("link_names")
    if links is not None:
        if not isinstance(links, list) or len(links) != n or not all(isinstance(v, str) and v for v in links):
            raise _fail(path, f"field 'link_names' must hold {n} link names, got {links!r}")
        if len({base_link, *links}) != n + 1 or flange_link in links[:-1]:
            raise _fail(path, f"field 'link_names' {links} repeats a name or the base link {base_link!r}")
        links = tuple(links)
    ratio = _optional(path, doc, "reduction_ratio", (n,))
    if ratio is not None and np.any(ratio == 0.0):
        raise _fail(path, f"field 'reduction_ratio' must be non-zero, got {ratio.tolist()}")
    if (doc.get("lower") is None) != (doc.get("upper") is None):
        raise _fail(
            path, "fields 'lower' and 'upper' (joint limits, rad) come together: give both or neither"
        )
    lower, upper = _optional(path, doc, "lower", (n,)), _optional(path, doc, "upper", (n,))
    if lower is not None and not np.all(lower < upper):
        i = int(np.flatnonzero(~(lower < upper))[0])
        raise _fail(
            path, f"fields 'lower', 'upper': joint {names[i]!r} has lower {lower[i]:g} >= upper {upper[i]:g}"
        )
    velocity = _optional(path, doc, "velocity", (n,))
    if velocity is not None and not np.all(velocity > 0):
        raise _fail(path, f"field 'velocity' (rad/s) must be positive, got {velocity.tolist()}")
    mass, com = _optional(path, doc, "mass", (n,)), _optional(path, doc, "com", (n, 3))
    if mass is not None and not np.all(mass > 0):
        raise _fail(path, f"field 'mass' (kg) must be positive, got {mass.tolist()}")
    if (mass is None) != (com is None):
        raise _fail(
            path, "fields 'mass' and 'com' (the links' centres of mass) come together: give both or neither"
        )
    return TableFile(
        path, table, doc, base_link, flange_link, links, ratio, lower, upper, velocity, mass, com
    )


def read_dh_table(path) -> tuple[DHTable, dict]:
    """The `DHTable` of a table file and the file's document (for its other fields).

    Raises `DatasetError` naming the file and the field at fault (`read_table_file`).
    """
    t = read_table_file(path)
    return t.table, t.doc


def _matrix(path: Path, field: str, value) -> jnp.ndarray:
    if value is None:
        return to_device(np.eye(4))
    T = np.asarray(value, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise DatasetError(f"DH table {shown(path)!r}: field {field!r} must be a finite 4x4 matrix")
    return to_device(T)


def dh_table_model(path, name: str | None = None) -> KinematicModel:
    """The `KinematicModel` of a table file: the table's frames between its
    `base_link` and `flange_link`, named by its `link_names` or else
    `"{name}_link{i}"` (`name`: the file's stem by default), and its
    `reduction_ratio` (1 when the file has none)."""
    t = read_table_file(path)
    name = Path(path).stem if name is None else name
    n = len(t.table.joint_names)
    children = t.link_names or tuple(f"{name}_link{i + 1}" for i in range(n))
    return table_to_model(
        t.table, link_names=[t.base_link, *children, t.flange_link], reduction_ratio=t.reduction_ratio
    )


def table_inertials(path) -> tuple[np.ndarray, np.ndarray]:
    """The masses (kg, (joints,)) and centres of mass (m, (joints, 3)) of a table
    file's links, the centres in the link frames of `dh_table_model`'s model.

    The file gives the centre of link $i$ in its table frame $i$; the model's
    link frame $i$ is where joint $i$'s motion ends, so (with $q$ in both)
    $T_{link_i, DH_i} = T_z(d_i)\\,T_x(a_i)\\,R_x(\\alpha_i)\\,R_y(\\beta_i)$ for DH
    and $T_{link_i, MDH_i} = T_z(d_i)$ for MDH (see `jaxcal._dh.table_to_model`).
    Raises `ValueError` naming the file when it has no `mass` / `com`.
    """
    t = read_table_file(path)
    if t.mass is None:
        raise ValueError(f"DH table {str(t.path)!r} gives no link masses (fields 'mass' and 'com')")
    tab, zero = jax.tree.map(np.asarray, t.table), np.zeros(())
    coms = []
    for i in range(len(tab.joint_names)):
        if tab.convention == "dh":
            T = link_transform("dh", zero, tab.d[i], tab.a[i], tab.alpha[i], tab.beta[i])
        else:
            T = link_transform("mdh", zero, tab.d[i], zero, zero, zero)
        T = np.asarray(T)
        coms.append(T[:3, :3] @ t.com[i] + T[:3, 3])
    return t.mass.copy(), np.stack(coms)


def _columns(table: DHTable) -> dict:
    return {c: np.asarray(getattr(table, c)).tolist() for c in COLUMNS}


def dh_table_json(
    table: DHTable,
    *,
    robot: str,
    base_link: str,
    flange_link: str,
    std: DHTable | None = None,
    base_flange_std: dict | None = None,
    nominal: DHTable | None = None,
    reduction_ratio=None,
    source: str = "",
) -> dict:
    """A table file's JSON (see the module docstring): `table`, and for a
    calibrated table its `std` (a `DHTable` of standard deviations), the base
    and flange std (`{"base": 6, "flange": 6}` xyz m / rpy rad) and the nominal."""
    doc = {
        "robot": robot,
        "convention": table.convention,
        "joint_names": list(table.joint_names),
        **_columns(table),
        "parallel": list(table.parallel),
        "base": np.asarray(table.T_base).tolist(),
        "flange": {"matrix": np.asarray(table.T_flange).tolist()},
        "base_link": base_link,
        "flange_link": flange_link,
        "units": {"a": "m", "d": "m", "alpha": "rad", "theta": "rad", "beta": "rad"},
        "parallel_rule": PARALLEL_RULE,
    }
    if reduction_ratio is not None:
        doc["reduction_ratio"] = np.asarray(reduction_ratio).tolist()
    if std is not None:
        doc["std"] = _columns(std)
        for k, v in (base_flange_std or {}).items():
            doc["std"][f"{k}_xyz_rpy"] = np.asarray(v).tolist()
    if nominal is not None:
        doc["nominal"] = _columns(nominal)
    doc["source"] = source
    return doc
