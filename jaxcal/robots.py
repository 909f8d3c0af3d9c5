"""The robots shipped in `data/robots/`: URDF models and DH/MDH tables.

See `data/robots/README.md` for the sources and conventions of each file.
`load_robot_file` and `link_inertials` take a shipped name or any robot
file: a URDF, or a DH/MDH table (`.json`, `.yaml`, `.yml`).
"""

from pathlib import Path

import numpy as np

from ._kinematics import KinematicModel
from .io._files import SHIPPED_ROBOTS
from .io.dh_tables import dh_table_model, is_table_file, table_inertials
from .io.urdf import load_urdf, urdf_inertials, urdf_inertias

ROBOTS_DIR = SHIPPED_ROBOTS


def shipped(pattern: str = "*.urdf", strip: str = ".urdf") -> list[str]:
    """Names of the shipped robot files matching `pattern` (without `strip`)."""
    return sorted(p.name.removesuffix(strip) for p in ROBOTS_DIR.glob(pattern))


def robot_path(name: str) -> Path:
    """Path of the URDF of the shipped robot `name` (`"ur5e"`, `"panda"`)."""
    if not isinstance(name, str) or name not in shipped():
        raise ValueError(f"unknown robot {name!r}; known robots are {shipped()}")
    return ROBOTS_DIR / f"{name}.urdf"


def load_robot(name: str) -> KinematicModel:
    """The `KinematicModel` of the shipped robot `name`, from its URDF (base link to flange)."""
    return load_urdf(robot_path(name))


def dh_model(name: str) -> KinematicModel:
    """The `KinematicModel` of a shipped DH/MDH table (`"ur5e_dh"`, `"ur5e_mdh"`, `"panda_mdh"`).

    The table's `base_link` and `flange_link` name the first and last link, so
    the flange pose can be compared with the URDF model's; the frames in
    between are the table's (DH or MDH) frames, named `"{name}_link{i}"`.
    Reduction ratios are 1 (the tables do not give them). The file format is
    `jaxcal.io.dh_tables`'s (calibrated tables are read by `dh_table_model`).
    """
    known = shipped("*_dh.json", ".json") + shipped("*_mdh.json", ".json")
    if not isinstance(name, str) or name not in known:
        raise ValueError(f"unknown DH table {name!r}; known tables are {sorted(known)}")
    return dh_table_model(ROBOTS_DIR / f"{name}.json", name)


def shipped_names() -> list[str]:
    """Every name `robot_file` resolves: the shipped URDFs, and the tables with and
    without their `_dh` / `_mdh` suffix (`"ur5"` is `ur5_dh.json`)."""
    tables = shipped("*_dh.json", ".json") + shipped("*_mdh.json", ".json")
    bare = [t.removesuffix("_dh").removesuffix("_mdh") for t in tables]
    return sorted(set(shipped()) | set(tables) | set(bare))


def robot_file(path_or_name) -> Path:
    """The robot file a shipped name or a path names.

    A name is looked up in `data/robots/` as `{name}.urdf`, then `{name}.json`,
    `{name}_dh.json`, `{name}_mdh.json` (so `"ur5e"` is the URDF, `"ur5e_dh"`
    its DH table, `"ur10e"` and `"iiwa14"` their tables); anything else must
    be an existing file. Raises `ValueError` listing the known names.
    """
    text = str(path_or_name)
    if (
        isinstance(path_or_name, str)
        and "/" not in text
        and not text.endswith((".urdf", ".json", ".yaml", ".yml"))
    ):
        for candidate in (f"{text}.urdf", f"{text}.json", f"{text}_dh.json", f"{text}_mdh.json"):
            if (ROBOTS_DIR / candidate).is_file():
                return ROBOTS_DIR / candidate
    path = Path(path_or_name)
    if path.is_file():
        return path
    raise ValueError(
        f"robot {text!r} is neither a shipped robot nor an existing file; shipped robots are {shipped_names()}"
    )


def load_robot_file(path_or_name) -> KinematicModel:
    """The `KinematicModel` of a shipped robot name or a robot file.

    **Arguments:**
    - `path_or_name`: a shipped name (`"ur5e"`, `"ur5"`, `"ur5_dh"`,
      `"panda"`, `"iiwa14"`: see `robot_file`), a URDF file, or a DH/MDH table
      file (`.json`, `.yaml`, `.yml`; `jaxcal.io.dh_tables`).

    **Returns:** a URDF's chain from its root link to its one leaf
    (`load_urdf`), or a table's model (`dh_table_model`). Raises `ValueError`
    (a table's `DatasetError` is one) naming the file at fault.
    """
    path = robot_file(path_or_name)
    return dh_table_model(path) if is_table_file(path) else load_urdf(path)


def link_inertials(path_or_name) -> tuple[np.ndarray, np.ndarray]:
    """Masses (kg, `(joints,)`) and centres of mass (m, `(joints, 3)`) of the links
    of `load_robot_file(path_or_name)`, each centre in its link frame (`link_names[i + 1]`,
    the frame joint $i$ moves).

    From a URDF, the `<inertial>` of each joint's child link, with the links fixed
    to it lumped in (`jaxcal.io.urdf.urdf_inertials`); from a table, its `mass`
    and `com` (given in the table's frames, moved into the model's:
    `jaxcal.io.dh_tables.table_inertials`). Raises `ValueError` naming the
    file when it gives no masses.
    """
    path = robot_file(path_or_name)
    return table_inertials(path) if is_table_file(path) else urdf_inertials(path)


#: A robot table's link, which gives no inertia tensor, as a solid sphere of this radius (m) about its centre.
TABLE_LINK_RADIUS_M = 0.05


def link_inertias(path_or_name) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`link_inertials`' masses and centres of mass, and each link's inertia tensor about its
    centre of mass in its link frame (kg m^2, `(joints, 3, 3)`): from a URDF its `<inertia>`
    tensors, lumped as the masses are (`jaxcal.io.urdf.urdf_inertias`); a table gives none,
    so each of its links is a solid sphere of `TABLE_LINK_RADIUS_M` about its centre."""
    path = robot_file(path_or_name)
    if is_table_file(path):
        masses, coms = table_inertials(path)
        tensors = 0.4 * masses[:, None, None] * TABLE_LINK_RADIUS_M**2 * np.eye(3)
        return masses, coms, tensors
    return urdf_inertias(path)
