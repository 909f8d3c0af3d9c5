"""The robots shipped in `data/robots/`: URDF models and DH/MDH tables.

See `data/robots/README.md` for the sources and conventions of each file.
"""

from pathlib import Path

from ._kinematics import KinematicModel
from .io.dh_tables import dh_table_model
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
    Reduction ratios are 1 (the tables do not give them). The file format is
    `jaxcal.io.dh_tables`'s (calibrated tables are read by `dh_table_model`).
    """
    known = shipped("*_dh.json", ".json") + shipped("*_mdh.json", ".json")
    if not isinstance(name, str) or name not in known:
        raise ValueError(f"unknown DH table {name!r}; known tables are {sorted(known)}")
    return dh_table_model(ROBOTS_DIR / f"{name}.json", name)
