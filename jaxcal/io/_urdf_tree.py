"""A URDF's links (with their inertials) and joints read with the standard library, as
yourdfpy reads them (`jaxcal.io.urdf.load_urdf`'s chain, `urdf_inertials`' masses; yourdfpy
imports trimesh, a second of start-up)."""

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ._files import write_text_atomic


@dataclass(frozen=True)
class Joint:
    """What the chain needs of a `<joint>`, read as yourdfpy reads it."""

    name: str
    type: str | None
    parent: str
    child: str
    origin: np.ndarray | None  # (4, 4), None without <origin>
    axis: np.ndarray
    mimic: ET.Element | None
    rising: float | None  # <calibration rising>


@dataclass(frozen=True)
class Inertial:
    """A `<link>`'s `<inertial>`: its mass (kg), the pose of its centre of mass (`<origin>`)
    and its inertia tensor about the centre of mass in that pose's axes (kg m^2; `None`
    without an `<inertia>`)."""

    mass: float
    origin: np.ndarray | None  # (4, 4), None without <origin>
    inertia: np.ndarray | None = None  # (3, 3)


@dataclass(frozen=True)
class Link:
    name: str
    inertial: Inertial | None = None


@dataclass(frozen=True)
class Tree:
    links: list
    joints: list


def origin_matrix(xyz: list[float], rpy: list[float]) -> np.ndarray:
    """`[R t; 0 1]` with R = Rz(yaw) Ry(pitch) Rx(roll), entry for entry as yourdfpy's
    `compose_matrix(translate=xyz, angles=rpy)` (trimesh's static-axes `sxyz` Euler matrix)."""
    # A non-finite angle gives NaNs (as NumPy's sin would), for the joint checks to name the joint.
    si, sj, sk = (math.sin(a) if math.isfinite(a) else math.nan for a in rpy)
    ci, cj, ck = (math.cos(a) if math.isfinite(a) else math.nan for a in rpy)
    cc, cs, sc, ss = ci * ck, ci * sk, si * ck, si * sk
    return np.array(
        [
            [cj * ck, sj * sc - cs, sj * cc + ss, xyz[0]],
            [cj * sk, sj * ss + cc, sj * cs - sc, xyz[1]],
            [-sj, cj * si, cj * ci, xyz[2]],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )


def _origin(el: ET.Element | None) -> np.ndarray | None:
    """An `<origin xyz rpy>` element's matrix (None without one)."""
    if el is None:
        return None
    xyz = [float(v) for v in el.get("xyz", "0 0 0").split()]
    rpy = [float(v) for v in el.get("rpy", "0 0 0").split()]
    return origin_matrix(xyz, rpy)


def _inertial(link: ET.Element) -> Inertial | None:
    el = link.find("inertial")
    if el is None:
        return None
    mass, tensor = el.find("mass"), el.find("inertia")
    inertia = None
    if tensor is not None:
        xx, yy, zz, xy, xz, yz = (
            float(tensor.get(k, "0")) for k in ("ixx", "iyy", "izz", "ixy", "ixz", "iyz")
        )
        inertia = np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])
    return Inertial(
        0.0 if mass is None else float(mass.get("value", "0")), _origin(el.find("origin")), inertia
    )


def read_tree(root: ET.Element, path: Path) -> Tree:
    """The links and joints of a URDF (after `check_joint_links`), without yourdfpy: a joint's
    origin and axis as yourdfpy parses them (defaults: identity, `1 0 0`)."""
    try:
        joints = []
        for el in root.findall("joint"):
            origin = _origin(el.find("origin"))
            axis, calibration = el.find("axis"), el.find("calibration")
            xyz_axis = "1 0 0" if axis is None else axis.get("xyz", "1 0 0")
            joints.append(
                Joint(
                    el.attrib["name"],
                    el.get("type"),
                    el.find("parent").get("link"),
                    el.find("child").get("link"),
                    origin,
                    np.array([float(v) for v in xyz_axis.split()]),
                    el.find("mimic"),
                    None
                    if calibration is None or calibration.get("rising") is None
                    else float(calibration.get("rising")),
                )
            )
        links = [Link(el.attrib["name"], _inertial(el)) for el in root.findall("link")]
        return Tree(links, joints)
    except (KeyError, AttributeError, TypeError, ValueError, IndexError) as e:
        raise ValueError(f"URDF file {str(path)!r} could not be read: {e!r}") from None


# --------------------------------------------------------------------------- writing


def fmt(values) -> str:
    """Floats as Python `repr` (the shortest string that round-trips exactly)."""
    return " ".join(repr(float(v)) for v in np.ravel(values))


def rpy_error(R: np.ndarray, rpy: np.ndarray) -> float:
    return float(np.abs(origin_matrix((0.0, 0.0, 0.0), rpy)[:3, :3] - R).max())


def rpy_exact(R: np.ndarray, rpy: np.ndarray) -> np.ndarray:
    """`rpy`, or gimbal-lock-safe angles where those reproduce `R` better.

    At pitch $= \\pm\\pi/2$ only roll $\\mp$ yaw is determined, and
    `matrix_to_rpy` takes roll and yaw separately from entries that are pure
    round-off. Here roll comes from those small entries and yaw from the
    $O(1)$ entries $R_{01}, R_{11}$, which fixes the difference to full
    precision (error $O(\\cos^2 \\text{pitch})$).
    """
    err = rpy_error(R, rpy)
    if err <= 1e-15 or abs(R[2, 0]) < 1.0 - 1e-10:
        return rpy
    pitch = math.atan2(-R[2, 0], math.hypot(R[0, 0], R[1, 0]))
    roll = math.atan2(R[2, 1], R[2, 2]) if (R[2, 1] != 0.0 or R[2, 2] != 0.0) else 0.0
    if R[2, 0] < 0.0:  # pitch near +pi/2: R01 = sin(roll - yaw), R11 = cos(roll - yaw)
        yaw = roll - math.atan2(R[0, 1], R[1, 1])
    else:  # pitch near -pi/2: R01 = -sin(roll + yaw), R11 = cos(roll + yaw)
        yaw = math.atan2(-R[0, 1], R[1, 1]) - roll
    safe = np.array([roll, pitch, math.atan2(math.sin(yaw), math.cos(yaw))])
    return safe if rpy_error(R, safe) < err else rpy


def checked_rpy(T: np.ndarray, xyz: np.ndarray, rpy: np.ndarray, what: str) -> np.ndarray:
    """`rpy` repaired at gimbal lock and checked to reproduce `T` to 1e-12."""
    rpy = rpy_exact(T[:3, :3], np.asarray(rpy, dtype=np.float64))
    back = origin_matrix(xyz, rpy)
    if not np.abs(back - T).max() <= 1e-12:
        raise ValueError(f"{what} is not a rigid transform and cannot be written as xyz/rpy:\n{T}")
    return rpy


def set_origin(joint_el: ET.Element, xyz: np.ndarray, rpy: np.ndarray) -> None:
    origin = joint_el.find("origin")
    if origin is None:
        origin = ET.Element("origin")
        joint_el.insert(0, origin)
    origin.set("xyz", fmt(xyz))
    origin.set("rpy", fmt(rpy))


def write_atomic(tree: ET.ElementTree, path: Path) -> None:
    ET.indent(tree, space="  ")
    write_text_atomic(
        path, '<?xml version="1.0"?>\n' + ET.tostring(tree.getroot(), encoding="unicode") + "\n"
    )
