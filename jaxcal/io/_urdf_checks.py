"""Checks of a URDF file's joints, read from its XML before any model is built.

Every error is a `ValueError` naming the file and the joint: a non-finite
origin, axis or limit, a zero axis, a revolute or prismatic joint without
`<limit>` or with an empty range, a joint naming a link the file lacks.
"""

import math
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

#: The joint types that move (`jaxcal.io.urdf` maps them to revolute or prismatic).
MOVABLE = ("revolute", "continuous", "prismatic")


def limit_value(joint: ET.Element, attr: str, path: Path) -> float | None:
    el = joint.find("limit")
    text = None if el is None else el.get(attr)
    if text is None:
        return None
    try:
        v = float(text)
    except ValueError:
        raise ValueError(
            f"URDF file {str(path)!r}: joint {joint.get('name')!r} has a non-numeric limit {attr}={text!r}"
        ) from None
    if not math.isfinite(v):
        raise ValueError(f"URDF file {str(path)!r}: joint {joint.get('name')!r} has limit {attr}={text!r}")
    return v


def joint_floats(el: ET.Element | None, attr: str, default: str, joint: str, path: Path) -> np.ndarray:
    """The three numbers of attribute `attr` of `el` (`default` when `el` or the attribute
    is absent); ValueError naming the file and the joint unless there are three finite numbers."""
    if el is None:
        el = ET.Element("?")  # the defaults are valid: this name never shows
    text = el.get(attr, default)
    where = f"URDF file {str(path)!r}: joint {joint!r}: <{el.tag} {attr}={text!r}>"
    try:
        values = np.array([float(v) for v in text.split()], dtype=np.float64)
    except ValueError:
        raise ValueError(f"{where} is not numeric") from None
    if values.shape != (3,):
        raise ValueError(f"{where} must hold 3 numbers, it has {values.size}")
    if not np.all(np.isfinite(values)):
        raise ValueError(f"{where} is not finite")
    return values


def limit_range(joint: ET.Element, path: Path) -> tuple[float, float]:
    """`<limit lower upper>` of `joint`, each 0 where absent (the URDF specification's default)."""
    lower, upper = limit_value(joint, "lower", path), limit_value(joint, "upper", path)
    return (0.0 if lower is None else lower), (0.0 if upper is None else upper)


def check_joint_element(el: ET.Element, path: Path) -> None:
    """Refuse a `<joint>` whose numbers cannot describe a robot, naming the file and the joint.

    Every joint: a finite `<origin xyz rpy>`. A revolute, continuous or prismatic
    joint: a finite, non-zero `<axis xyz>`. A revolute or prismatic joint: a
    `<limit>` element (the URDF specification requires one) with finite `lower <
    upper`; both unset (0, the specification's default, which would lock the
    joint) is read as no range stated, as many files mean it. A continuous joint's
    `<limit>` may omit `lower` and `upper`; the values it gives must be finite.
    """
    name, kind = el.get("name"), el.get("type")
    where = f"URDF file {str(path)!r}: joint {name!r}"
    origin = el.find("origin")
    joint_floats(origin, "xyz", "0 0 0", name, path)
    joint_floats(origin, "rpy", "0 0 0", name, path)
    if kind not in MOVABLE:
        return
    axis = joint_floats(el.find("axis"), "xyz", "1 0 0", name, path)
    if not np.linalg.norm(axis) > 0.0:
        raise ValueError(
            f"{where} has a zero or invalid axis {axis.tolist()}; a movable joint needs a direction"
        )
    limit = el.find("limit")
    for attr in ("lower", "upper", "velocity"):
        limit_value(el, attr, path)  # numeric and finite where given
    if kind == "continuous":
        return
    if limit is None:
        raise ValueError(
            f"{where} is {kind} but has no <limit> element; the URDF specification requires "
            f'<limit lower=".." upper=".." effort=".." velocity=".."/> for revolute and prismatic '
            'joints (a joint that turns without limits is type="continuous")'
        )
    lower, upper = limit_range(el, path)
    if lower == upper == 0.0:
        return  # lower and upper unset (effort and velocity only): no range stated, read as unlimited
    if not lower < upper:
        given = " ".join(f"{a}={limit.get(a)!r}" for a in ("lower", "upper") if limit.get(a) is not None)
        raise ValueError(
            f"{where} has <limit {given or 'without lower and upper'}>: the {kind} joint's range "
            f"[{lower:g}, {upper:g}] is empty (lower must be below upper; each defaults to 0)"
        )


def check_joint_links(root: ET.Element, path: Path) -> None:
    """Every `<joint>` has a name, a parent and a child, and both are `<link>`s of the file."""
    links = {el.get("name") for el in root.findall("link")}
    for el in root.findall("joint"):
        name, parent, child = el.get("name"), el.find("parent"), el.find("child")
        if not name or parent is None or child is None:
            raise ValueError(f"URDF file {str(path)!r}: a <joint> lacks a name, parent or child")
        for role, ref in (("parent", parent), ("child", child)):
            if ref.get("link") not in links:
                raise ValueError(
                    f"URDF file {str(path)!r}: joint {name!r} names {role} link {ref.get('link')!r}, "
                    "which is not a <link> of the file"
                )
