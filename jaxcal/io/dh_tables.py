"""DH / MDH table files (JSON): the shipped datasheet tables and the calibrated ones.

The schema of `data/robots/*_dh.json` (`convention`, `joint_names`, columns
`a`, `alpha`, `d`, `theta`, an optional `base` 4x4, `flange`, `base_link`,
`flange_link`), extended for calibrated tables by:

- `beta`, `parallel`: Hayati's extra rotation about $y$ per row and the rows
  that carry it (consecutive axes within 10 degrees of parallel; their $d$ is
  0 by the rule of `jaxcal._dh`); absent means zero / none.
- `flange`: either Craig/DH parameters `{a, alpha, d, theta}` (the datasheets)
  or `{"matrix": 4x4}` (a calibrated flange is a general transform).
- `reduction_ratio` (optional), `std` (1-sigma of every column and of the
  base and flange as `xyz_rpy`), `nominal` (the nominal model's columns).

`read_dh_table` reads either kind; `dh_table_model` turns a file into a
`KinematicModel` (`robots.dh_model` uses it), `dh_table_json` writes one.
"""

import json
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from .._dh import COLUMNS, DHTable, link_transform, table_to_model
from .._kinematics import KinematicModel
from ..errors import DatasetError

#: What `parallel` means, written into every calibrated table.
PARALLEL_RULE = (
    "rows marked parallel join axes within 10 degrees of parallel: DH is ill-conditioned there "
    "(d slides along the axes), so they use Hayati's form, d = 0 and an extra rotation beta about y "
    "(DH: Rz(theta) Tx(a) Rx(alpha) Ry(beta); MDH: Rx(alpha) Tx(a) Ry(beta) Rz(theta) Tz(d))"
)


def read_dh_table(path) -> tuple[DHTable, dict]:
    """The `DHTable` of a table file and the file's JSON (for its other fields).

    Raises `DatasetError` naming the file and the field at fault.
    """
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise DatasetError(f"DH table {str(path)!r} cannot be read: {e}") from None
    convention = doc.get("convention")
    if convention not in ("dh", "mdh"):
        raise DatasetError(f"DH table {str(path)!r}: convention must be 'dh' or 'mdh', got {convention!r}")
    try:
        names = [str(j) for j in doc["joint_names"]]
        n = len(names)
        cols = {
            c: np.asarray(doc[c] if c != "beta" else doc.get("beta", [0.0] * n), dtype=np.float64)
            for c in COLUMNS
        }
        flange = doc["flange"]
        parallel = tuple(bool(p) for p in doc.get("parallel", [False] * n))
    except KeyError as e:
        raise DatasetError(f"DH table {str(path)!r} has no field {e.args[0]!r}") from None
    except (TypeError, ValueError) as e:
        raise DatasetError(f"DH table {str(path)!r}: a column is not a list of numbers ({e})") from None
    for c, v in cols.items():
        if v.shape != (n,) or not np.all(np.isfinite(v)):
            raise DatasetError(
                f"DH table {str(path)!r}: field {c!r} must hold {n} finite numbers, got {v.tolist()}"
            )
    if len(parallel) != n:
        raise DatasetError(f"DH table {str(path)!r}: field 'parallel' must hold {n} flags")
    T_base = _matrix(path, "base", doc.get("base"))
    if isinstance(flange, dict) and "matrix" in flange:
        T_flange = _matrix(path, "flange.matrix", flange["matrix"])
    else:
        try:
            f = [float(flange[k]) for k in ("theta", "d", "a", "alpha")]
        except (KeyError, TypeError, ValueError):
            raise DatasetError(
                f"DH table {str(path)!r}: field 'flange' must be {{a, alpha, d, theta}} or {{matrix}}"
            ) from None
        T_flange = link_transform(convention, *f, 0.0)
    table = DHTable(
        *(jnp.asarray(cols[c]) for c in COLUMNS), T_base, T_flange, convention, tuple(names), parallel
    )
    return table, doc


def _matrix(path: Path, field: str, value) -> jnp.ndarray:
    if value is None:
        return jnp.eye(4)
    T = np.asarray(value, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise DatasetError(f"DH table {str(path)!r}: field {field!r} must be a finite 4x4 matrix")
    return jnp.asarray(T)


def dh_table_model(path, name: str | None = None) -> KinematicModel:
    """The `KinematicModel` of a table file: the table's frames named
    `"{name}_link{i}"` between its `base_link` and `flange_link`, and its
    `reduction_ratio` (1 when the file has none)."""
    table, doc = read_dh_table(path)
    name = Path(path).stem if name is None else name
    n = len(table.joint_names)
    try:
        links = [doc["base_link"], *(f"{name}_link{i + 1}" for i in range(n)), doc["flange_link"]]
    except KeyError as e:
        raise DatasetError(f"DH table {str(path)!r} has no field {e.args[0]!r}") from None
    ratio = doc.get("reduction_ratio")
    return table_to_model(
        table, link_names=links, reduction_ratio=None if ratio is None else np.asarray(ratio)
    )


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
