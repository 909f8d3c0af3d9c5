"""A URDF's links (with their inertials) and joints read with the standard library, as
yourdfpy reads them (`jaxcal.io.urdf.load_urdf`'s chain, `urdf_inertials`' masses; yourdfpy
imports trimesh, a second of start-up)."""

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np


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
