"""The robots shipped in `data/robots/`: URDF models and DH/MDH tables.

See `data/robots/README.md` for the sources and conventions of each file.
"""

import json
from pathlib import Path

import numpy as np

from ._kinematics import KinematicModel, dh_link, from_dh, from_mdh, mdh_link
from .io.urdf import load_urdf

ROBOTS_DIR = Path(__file__).resolve().parents[1] / "data" / "robots"


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
    Reduction ratios are 1 (the tables do not give them).
    """
    known = shipped("*_dh.json", ".json") + shipped("*_mdh.json", ".json")
    if not isinstance(name, str) or name not in known:
        raise ValueError(f"unknown DH table {name!r}; known tables are {sorted(known)}")
    path = ROBOTS_DIR / f"{name}.json"
    table = json.loads(path.read_text())
    convention = table.get("convention")
    if convention not in ("dh", "mdh"):
        raise ValueError(f"DH table {str(path)!r}: convention must be 'dh' or 'mdh', got {convention!r}")
    try:
        columns = {k: np.asarray(table[k], dtype=np.float64) for k in ("a", "alpha", "d", "theta")}
        flange = table["flange"]
        joint_names = list(table["joint_names"])
        base_link, flange_link = table["base_link"], table["flange_link"]
    except KeyError as e:
        raise ValueError(f"DH table {str(path)!r} has no field {e.args[0]!r}") from None
    f = [float(flange[k]) for k in ("a", "alpha", "d", "theta")]
    T_flange = dh_link(*f) if convention == "dh" else mdh_link(*f)
    build = from_dh if convention == "dh" else from_mdh
    n = len(joint_names)
    return build(
        **columns,
        joint_names=joint_names,
        flange=T_flange,
        T_base=None if table.get("base") is None else np.asarray(table["base"], dtype=np.float64),
        link_names=[base_link, *(f"{name}_link{i + 1}" for i in range(n)), flange_link],
    )
