"""Read a serial chain from a URDF file, and write a calibrated chain back.

Impure edge: files and XML (read with the standard library, as yourdfpy reads them:
`jaxcal.io._urdf_tree`). Never jitted; returns `KinematicModel`s.

How a URDF maps onto a `KinematicModel`:

* The chain is the path of joints from `base_link` to `tip_link`.
* `revolute` and `continuous` joints become `"revolute"`, `prismatic` joints
  `"prismatic"`; `floating` and `planar` joints are rejected.
* Fixed joints before a movable joint are composed into that joint's origin
  (`T_parent_joint`); fixed joints after the last movable joint make up
  `T_last_flange`.
* `link_names` are the base link, each movable joint's child link, and the tip
  link (the flange).
* The zero offset of a joint is read from (and written to)
  `<calibration rising="..."/>`, the reduction ratio from the
  `<mechanicalReduction>` of the ROS transmission that names the joint
  (1.0 where there is none). Tools other than jaxcal ignore `<calibration>`:
  in yourdfpy, MuJoCo or ROS the joint angle is the commanded one.
"""

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .._kinematics import (
    PRISMATIC,
    REVOLUTE,
    KinematicModel,
    make_model,
    origins_xyz_rpy,
    rotations_to_rpy,
)
from ._files import shown
from ._urdf_checks import check_joint_element, check_joint_links, limit_range, limit_value
from ._urdf_tree import checked_rpy, fmt, read_tree, set_origin, write_atomic

MOVABLE = {"revolute": REVOLUTE, "continuous": REVOLUTE, "prismatic": PRISMATIC}
_UNSUPPORTED = ("floating", "planar")
# Fixed transforms folded into a joint origin count as identity below this (max abs entry).
_IDENTITY_ATOL = 1e-12


# --------------------------------------------------------------------------- reading


def parse_urdf(path: Path) -> ET.ElementTree:
    """Parse `path` as XML with comments kept; ValueError on a missing file or bad XML."""
    if not path.is_file():
        raise ValueError(f"URDF file {shown(path)!r} does not exist")
    parser = ET.XMLParser(target=ET.TreeBuilder(insert_comments=True))
    try:
        tree = ET.parse(path, parser=parser)
    except ET.ParseError as e:
        raise ValueError(f"URDF file {shown(path)!r} is not well-formed XML: {e}") from None
    if tree.getroot().tag != "robot":
        raise ValueError(
            f"URDF file {shown(path)!r}: root element is <{tree.getroot().tag}>, expected <robot>"
        )
    return tree


def _reduction_elements(transmission: ET.Element) -> list[ET.Element]:
    """`<mechanicalReduction>` elements of a ROS transmission (in the actuator, or legacy direct)."""
    return transmission.findall("actuator/mechanicalReduction") + transmission.findall("mechanicalReduction")


def _transmissions_by_joint(root: ET.Element) -> dict[str, list[ET.Element]]:
    """Every top-level `<transmission>` indexed by the names of the joints it drives."""
    out: dict[str, list[ET.Element]] = {}
    for tr in root.findall("transmission"):
        for j in tr.findall("joint"):
            name = j.get("name")
            if name is not None:
                out.setdefault(name, []).append(tr)
    return out


def _reduction_ratio(joint: str, transmissions: dict[str, list[ET.Element]], path: Path) -> float:
    """The mechanical reduction of `joint` (1.0 without a transmission)."""
    found = transmissions.get(joint, [])
    if len(found) > 1:
        names = [tr.get("name") for tr in found]
        raise ValueError(
            f"URDF file {shown(path)!r}: joint {joint!r} is driven by several transmissions {names}"
        )
    if not found:
        return 1.0
    tr = found[0]
    if len(tr.findall("joint")) != 1:
        raise ValueError(
            f"URDF file {shown(path)!r}: transmission {tr.get('name')!r} couples several joints; "
            f"the reduction ratio of joint {joint!r} is ambiguous"
        )
    values = set()
    for el in _reduction_elements(tr):
        try:
            values.add(float((el.text or "").strip()))
        except ValueError:
            raise ValueError(
                f"URDF file {shown(path)!r}: transmission {tr.get('name')!r} has a non-numeric "
                f"mechanicalReduction {el.text!r}"
            ) from None
    if not values:
        return 1.0
    if len(values) > 1:
        raise ValueError(
            f"URDF file {shown(path)!r}: transmission {tr.get('name')!r} gives joint {joint!r} "
            f"several reductions {sorted(values)}"
        )
    ratio = values.pop()
    if not math.isfinite(ratio) or ratio == 0.0:
        raise ValueError(
            f"URDF file {shown(path)!r}: transmission {tr.get('name')!r} has invalid reduction {ratio!r}"
        )
    return ratio


@dataclass(frozen=True)
class JointLimits:
    """What the URDF says of one movable joint, read without building the model.

    `joint_type`: `revolute`, `continuous` or `prismatic`; `lower` < `upper`
    (rad or m) from `<limit>` (required, see `urdf_outline`), `None` for a continuous joint;
    `velocity` (rad/s or m/s), `None` when absent or zero; `reduction_ratio`
    from the joint's transmission (1.0 without one).
    """

    joint_type: str
    lower: float | None
    upper: float | None
    velocity: float | None
    reduction_ratio: float


@dataclass(frozen=True)
class UrdfOutline:
    """A URDF's link names, its joints by child link (`child -> (joint, type,
    parent)`), and the `JointLimits` of the joints asked for."""

    links: frozenset
    parent_joint: dict
    limits: dict


def urdf_outline(path, joint_names=()) -> UrdfOutline:
    """Links, joints and the limits of `joint_names` of a URDF file, from its XML alone
    (fast: no model, no yourdfpy). Raises `ValueError` naming the file for a missing
    or malformed file, a joint naming a link that does not exist, a name in
    `joint_names` that is not a movable joint, or one of those joints that fails
    `check_joint_element` (no `<limit>`, lower >= upper, a non-finite value)."""
    path = Path(path)
    root = parse_urdf(path).getroot()
    check_joint_links(root, path)
    links = frozenset(el.get("name") for el in root.findall("link") if el.get("name"))
    parent_joint, elements = {}, {}
    for el in root.findall("joint"):
        name, kind = el.get("name"), el.get("type")
        parent, child = el.find("parent"), el.find("child")
        parent_joint[child.get("link")] = (name, kind, parent.get("link"))
        elements[name] = el
    transmissions = _transmissions_by_joint(root)
    limits = {}
    for name in joint_names:
        el = elements.get(name)
        if el is None:
            raise ValueError(f"URDF file {shown(path)!r} has no joint {name!r}")
        kind = el.get("type")
        if kind not in MOVABLE:
            raise ValueError(f"URDF file {shown(path)!r}: joint {name!r} is {kind}, not a movable joint")
        check_joint_element(el, path)
        lower, upper = (None, None) if kind == "continuous" else limit_range(el, path)
        if lower == upper == 0.0:
            lower = upper = None  # no range stated (see `check_joint_element`)
        velocity = limit_value(el, "velocity", path)
        limits[name] = JointLimits(
            kind,
            lower,
            upper,
            velocity if velocity is not None and velocity > 0 else None,
            _reduction_ratio(name, transmissions, path),
        )
    return UrdfOutline(links, parent_joint, limits)


def urdf_link_names(path) -> set[str]:
    """The names of a URDF file's links."""
    return {el.get("name") for el in parse_urdf(Path(path)).getroot().iter("link")}


def _leaves_with_motion(children: dict[str, list], base: str) -> list[str]:
    """Leaf links below `base` whose path from `base` crosses a non-fixed joint."""
    leaves, stack, seen = [], [(base, False)], set()
    while stack:
        link, moved = stack.pop()
        if link in seen:  # a malformed URDF with a cycle
            continue
        seen.add(link)
        kids = children.get(link, [])
        if not kids and moved:
            leaves.append(link)
        for j in kids:
            stack.append((j.child, moved or j.type != "fixed"))
    return sorted(leaves)


def base_link_of(robot, path: Path, base_link: str | None) -> str:
    """`base_link`, checked to be a link of `robot` (a `jaxcal.io._urdf_tree.Tree`), or its one
    root link; `ValueError` naming the file otherwise."""
    links = {link.name for link in robot.links}
    if base_link is None:
        roots = sorted(links - {j.child for j in robot.joints})
        if len(roots) != 1:
            raise ValueError(f"URDF file {shown(path)!r}: expected one root link, found {roots}")
        return roots[0]
    if base_link not in links:
        raise ValueError(
            f"URDF file {shown(path)!r}: unknown base link {base_link!r}; links are {sorted(links)}"
        )
    return base_link


def _chain(robot, path: Path, base_link: str | None, tip_link: str | None) -> tuple[list, str, str]:
    """The joints from `base_link` to `tip_link` (base first), and the two link names, of
    `robot` (a `jaxcal.io._urdf_tree.Tree`)."""
    links = {link.name for link in robot.links}
    parent_joint = {j.child: j for j in robot.joints}
    children: dict[str, list] = {}
    for j in robot.joints:
        children.setdefault(j.parent, []).append(j)
    base_link = base_link_of(robot, path, base_link)
    if tip_link is None:
        leaves = _leaves_with_motion(children, base_link)
        if not leaves:
            raise ValueError(f"URDF file {shown(path)!r}: no movable joint below base link {base_link!r}")
        if len(leaves) > 1:
            raise ValueError(
                f"URDF file {shown(path)!r}: the tree branches below {base_link!r}; name the flange link, "
                f"one of the leaves {leaves} or a link above one (metadata.json's robot.flange_link, the CLI's "
                "--config flange-link=NAME, the API's tip_link)"
            )
        tip_link = leaves[0]
    elif tip_link not in links:
        raise ValueError(
            f"URDF file {shown(path)!r}: unknown tip link {tip_link!r}; links are {sorted(links)}"
        )
    joints, link = [], tip_link
    while link != base_link:
        if link not in parent_joint or len(joints) > len(parent_joint):
            raise ValueError(
                f"URDF file {shown(path)!r}: no chain of joints from base link {base_link!r} "
                f"to tip link {tip_link!r}"
            )
        joints.append(parent_joint[link])
        link = parent_joint[link].parent
    return joints[::-1], base_link, tip_link


def _origin(joint) -> np.ndarray:
    return np.eye(4) if joint.origin is None else np.asarray(joint.origin, dtype=np.float64)


def check_joint_type(joint, path: Path, *, mimic: bool = False) -> None:
    """Refuse a joint a chain (`mimic`: a tree, which may couple joints) cannot hold, naming it."""
    if joint.type in _UNSUPPORTED:
        raise ValueError(
            f"URDF file {shown(path)!r}: joint {joint.name!r} is {joint.type}; only revolute, "
            "continuous, prismatic and fixed joints are supported"
        )
    if joint.type != "fixed" and joint.type not in MOVABLE:
        raise ValueError(f"URDF file {shown(path)!r}: joint {joint.name!r} has unknown type {joint.type!r}")
    if joint.mimic is not None and not mimic:
        raise ValueError(
            f"URDF file {shown(path)!r}: joint {joint.name!r} mimics another joint, which a serial chain "
            "cannot hold: read the robot as a tree (jaxcal.io.urdf_tree.load_urdf_tree)"
        )


def load_urdf(path, base_link: str | None = None, tip_link: str | None = None) -> KinematicModel:
    """Read the serial chain from `base_link` to `tip_link` of a URDF file.

    **Arguments:**
    - `path`: the URDF file.
    - `base_link`: the model's base frame; defaults to the root link.
    - `tip_link`: the flange; defaults to the one leaf link below `base_link`
      reached through a movable joint (a ValueError lists the leaves if the
      tree branches).

    **Returns:** a `KinematicModel` with `T_parent_joint` (m), unit axes,
    zero offsets from `<calibration rising>` (rad or m, default 0) and
    reduction ratios from the transmissions (default 1).

    Raises `ValueError` naming the file for a missing file, malformed XML,
    unknown links, a joint naming a link that is not in the file, no path
    between the links, no movable joint, or a chain joint that is unsupported
    (floating, planar, mimic) or malformed (a non-finite origin, a zero or
    non-finite axis; a revolute or prismatic joint without `<limit>` or with
    lower >= upper: see `check_joint_element`).
    """
    path = Path(path)
    root = parse_urdf(path).getroot()
    check_joint_links(root, path)
    joints, base_link, tip_link = _chain(read_tree(root, path), path, base_link, tip_link)
    transmissions = _transmissions_by_joint(root)
    elements = {el.get("name"): el for el in root.findall("joint")}

    origins, axes, types, names, child_links, offsets, ratios = [], [], [], [], [], [], []
    pending = np.eye(4)
    for joint in joints:
        check_joint_type(joint, path)
        check_joint_element(elements[joint.name], path)
        if joint.type == "fixed":
            pending = pending @ _origin(joint)
            continue
        axis = np.asarray(joint.axis, dtype=np.float64)
        norm = float(np.linalg.norm(axis))
        if not norm > 0.0 or not math.isfinite(norm):
            raise ValueError(
                f"URDF file {shown(path)!r}: joint {joint.name!r} has a zero or invalid axis {axis}"
            )
        origins.append(pending @ _origin(joint))
        pending = np.eye(4)
        axes.append(axis / norm)
        types.append(MOVABLE[joint.type])
        names.append(joint.name)
        child_links.append(joint.child)
        offsets.append(0.0 if joint.rising is None else joint.rising)
        ratios.append(_reduction_ratio(joint.name, transmissions, path))
    if not names:
        raise ValueError(
            f"URDF file {shown(path)!r}: no movable joint between base link {base_link!r} "
            f"and tip link {tip_link!r}"
        )
    return make_model(
        np.stack(origins),
        np.stack(axes),
        joint_names=names,
        joint_types=types,
        link_names=[base_link, *child_links, tip_link],
        zero_offset=np.asarray(offsets),
        reduction_ratio=np.asarray(ratios),
        T_last_flange=pending,
    )


def urdf_inertials(
    path, base_link: str | None = None, tip_link: str | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The masses (kg, (joints,)) and centres of mass (m, (joints, 3)) of the links
    that move with each movable joint of `load_urdf(path, base_link, tip_link)`'s chain,
    each centre in that joint's child link frame (the model's link frame).

    A link's `<inertial>` (its `<origin>` is the centre of mass) is lumped with
    those of the links hanging from it by fixed joints (a flange, a tool
    frame): $m = \\sum_k m_k$, $c = \\sum_k m_k\\,T_{link,k}\\,c_k / m$. A link
    without one weighs 0 (its centre is then the link origin). Raises
    `ValueError` naming the file when no link of the chain has a mass.
    """
    masses, coms, _ = urdf_inertias(path, base_link, tip_link)
    return masses, coms


def urdf_inertias(
    path, base_link: str | None = None, tip_link: str | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`urdf_inertials`' masses and centres of mass, and each lumped link's inertia tensor
    about its centre of mass in the link frame (kg m^2, (joints, 3, 3)).

    Each `<inertia>` is turned into the link frame ($R I R^T$, $R$ its `<origin>`'s
    rotation) and moved to the lumped centre of mass by the parallel-axis theorem,
    $I + m(|d|^2 E - d d^T)$; a link without an `<inertia>` is a point mass.
    """
    path = Path(path)
    root = parse_urdf(path).getroot()
    check_joint_links(root, path)
    tree = read_tree(root, path)
    joints, _, _ = _chain(tree, path, base_link, tip_link)
    links = {link.name: link for link in tree.links}
    fixed_children: dict[str, list] = {}
    for j in tree.joints:
        if j.type == "fixed":
            fixed_children.setdefault(j.parent, []).append(j)
    masses, coms, tensors = [], [], []
    for joint in (j for j in joints if j.type != "fixed"):
        parts, stack, seen = [], [(joint.child, np.eye(4))], set()  # (mass, centre, tensor at it)
        while stack:
            name, T = stack.pop()
            if name in seen:
                continue
            seen.add(name)
            inertial = links[name].inertial
            if inertial is not None and inertial.mass:
                pose = T @ (np.eye(4) if inertial.origin is None else np.asarray(inertial.origin, np.float64))
                tensor = np.zeros((3, 3)) if inertial.inertia is None else inertial.inertia
                parts.append((float(inertial.mass), pose[:3, 3], pose[:3, :3] @ tensor @ pose[:3, :3].T))
            stack += [(f.child, T @ _origin(f)) for f in fixed_children.get(name, [])]
        m_sum = sum(m for m, _, _ in parts)
        com = sum(m * c for m, c, _ in parts) / m_sum if m_sum > 0 else np.zeros(3)
        tensor = np.zeros((3, 3))
        for m, c, inertia in parts:
            d = c - com
            tensor += inertia + m * (d @ d * np.eye(3) - np.outer(d, d))
        masses.append(m_sum)
        coms.append(com)
        tensors.append(tensor)
    masses = np.asarray(masses)
    if not masses.any() or not np.all(np.isfinite(masses)):
        raise ValueError(
            f"URDF file {shown(path)!r} gives no link masses (no <inertial> on the chain's links)"
        )
    return masses, np.stack(coms), np.stack(tensors)


# --------------------------------------------------------------------------- writing


def _joint_origins(model: KinematicModel, arrays: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """xyz/rpy of every joint origin of `model`, exact to 1e-12."""
    xyz, rpy = origins_xyz_rpy(model)
    rpy = np.stack(
        [
            checked_rpy(T, x, r, f"save_urdf: origin of joint {name!r}")
            for T, x, r, name in zip(arrays["T_parent_joint"], xyz, rpy, model.joint_names)
        ]
    )
    return xyz, rpy


def _flange_origin(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    xyz = T[:3, 3].copy()
    rpy = rotations_to_rpy(T[:3, :3])
    return xyz, checked_rpy(T, xyz, rpy, "save_urdf: T_last_flange")


def _set_child(parent: ET.Element, tag: str, **attrib: str) -> ET.Element:
    el = parent.find(tag)
    if el is None:
        el = ET.SubElement(parent, tag)
    for k, v in attrib.items():
        el.set(k, v)
    return el


def _new_transmission(joint: str, ratio: float) -> ET.Element:
    tr = ET.Element("transmission", name=f"{joint}_trans")
    ET.SubElement(tr, "type").text = "transmission_interface/SimpleTransmission"
    j = ET.SubElement(tr, "joint", name=joint)
    ET.SubElement(j, "hardwareInterface").text = "hardware_interface/EffortJointInterface"
    act = ET.SubElement(tr, "actuator", name=f"{joint}_motor")
    ET.SubElement(act, "hardwareInterface").text = "hardware_interface/EffortJointInterface"
    ET.SubElement(act, "mechanicalReduction").text = repr(float(ratio))
    return tr


def _set_ratio(
    root: ET.Element, transmissions: dict[str, list[ET.Element]], joint: str, ratio: float
) -> None:
    found = transmissions.get(joint, [])
    if not found:
        if ratio != 1.0:
            root.append(_new_transmission(joint, ratio))
        return
    for tr in found:  # the reader has rejected ambiguous cases, so this is one transmission
        reductions = _reduction_elements(tr)
        if not reductions:
            holder = tr.find("actuator")
            reductions = [ET.SubElement(tr if holder is None else holder, "mechanicalReduction")]
        for el in reductions:
            el.text = repr(float(ratio))


def _model_arrays(model: KinematicModel) -> dict[str, np.ndarray]:
    arrays = {
        "T_parent_joint": np.asarray(model.T_parent_joint, dtype=np.float64),
        "axis": np.asarray(model.axis, dtype=np.float64),
        "zero_offset": np.asarray(model.zero_offset, dtype=np.float64),
        "reduction_ratio": np.asarray(model.reduction_ratio, dtype=np.float64),
        "T_last_flange": np.asarray(model.T_last_flange, dtype=np.float64),
    }
    n = model.num_joints
    expected = {"T_parent_joint": (n, 4, 4), "axis": (n, 3), "zero_offset": (n,), "reduction_ratio": (n,)}
    expected["T_last_flange"] = (4, 4)
    for name, shape in expected.items():
        if arrays[name].shape != shape:
            raise ValueError(
                f"save_urdf: model.{name} has shape {arrays[name].shape}, expected {shape} "
                "(save one model, not a batch)"
            )
        if not np.all(np.isfinite(arrays[name])):
            raise ValueError(f"save_urdf: model.{name} is not finite")
    return arrays


def _fill_from_source(model: KinematicModel, arrays: dict[str, np.ndarray], source: Path) -> ET.ElementTree:
    tree = parse_urdf(source)
    root = tree.getroot()
    check_joint_links(root, source)
    joints, _, _ = _chain(read_tree(root, source), source, model.link_names[0], model.link_names[-1])
    movable = [j for j in joints if j.type != "fixed"]
    for j in joints:
        check_joint_type(j, source)
    if tuple(j.name for j in movable) != model.joint_names:
        raise ValueError(
            f"save_urdf: the chain {model.link_names[0]!r} -> {model.link_names[-1]!r} of source "
            f"{str(source)!r} has joints {[j.name for j in movable]}, the model has {list(model.joint_names)}"
        )
    for j, kind in zip(movable, model.joint_types):
        if MOVABLE[j.type] != kind:
            raise ValueError(
                f"save_urdf: joint {j.name!r} is {j.type} in {str(source)!r} but {kind} in the model"
            )

    elements = {el.get("name"): el for el in root.findall("joint")}
    transmissions = _transmissions_by_joint(root)
    xyz, rpy = _joint_origins(model, arrays)
    i, folded = 0, []
    for j in joints:
        if j.type == "fixed":
            folded.append(j)
            continue
        for f in folded:
            if not np.abs(_origin(f) - np.eye(4)).max() <= _IDENTITY_ATOL:
                raise ValueError(
                    f"save_urdf: fixed joint {f.name!r} of {str(source)!r} is folded into the origin of "
                    f"joint {j.name!r}; its transform is not the identity, so the calibrated origin "
                    "cannot be written back to the URDF one joint at a time"
                )
        folded = []
        el = elements[j.name]
        set_origin(el, xyz[i], rpy[i])
        _set_child(el, "axis", xyz=fmt(arrays["axis"][i]))
        _set_child(el, "calibration", rising=repr(float(arrays["zero_offset"][i])))
        ratio = float(arrays["reduction_ratio"][i])
        _reduction_ratio(j.name, transmissions, source)  # rejects ambiguous transmissions
        _set_ratio(root, transmissions, j.name, ratio)
        i += 1

    # The fixed joints after the last movable one carry T_last_flange.
    nominal = np.eye(4)
    for f in folded:
        nominal = nominal @ _origin(f)
    if not np.array_equal(nominal, arrays["T_last_flange"]):
        if not folded:
            raise ValueError(
                f"save_urdf: model.T_last_flange is not the identity but {str(source)!r} has no fixed "
                f"joint after the last movable joint to hold it (flange link {model.link_names[-1]!r})"
            )
        rest = np.eye(4)
        for f in folded[1:]:
            rest = rest @ _origin(f)
        set_origin(elements[folded[0].name], *_flange_origin(arrays["T_last_flange"] @ np.linalg.inv(rest)))
    return tree


def _minimal_tree(model: KinematicModel, arrays: dict[str, np.ndarray], robot_name: str) -> ET.ElementTree:
    links = model.link_names
    flange_is_link = links[-1] == links[-2]
    if flange_is_link and not np.abs(arrays["T_last_flange"] - np.eye(4)).max() <= _IDENTITY_ATOL:
        raise ValueError(
            f"save_urdf: the flange link {links[-1]!r} is the last joint's child link, so the "
            "non-identity model.T_last_flange has no fixed joint to go into; give the flange its own name"
        )
    if len(set(links[: -1 if flange_is_link else None])) != len(links) - flange_is_link:
        raise ValueError(f"save_urdf: model.link_names has duplicates: {list(links)}")
    xyz, rpy = _joint_origins(model, arrays)
    root = ET.Element("robot", name=robot_name)
    root.append(ET.Comment(" Kinematic chain written by jaxcal.io.save_urdf: no geometry, no inertia. "))
    for name in dict.fromkeys(links):
        ET.SubElement(root, "link", name=name)
    for i, (name, kind) in enumerate(zip(model.joint_names, model.joint_types)):
        el = ET.SubElement(root, "joint", name=name, type=kind)
        ET.SubElement(el, "parent", link=links[i])
        ET.SubElement(el, "child", link=links[i + 1])
        set_origin(el, xyz[i], rpy[i])
        ET.SubElement(el, "axis", xyz=fmt(arrays["axis"][i]))
        lim = math.pi if kind == REVOLUTE else 1.0  # rad, or m for a prismatic joint
        ET.SubElement(el, "limit", lower=repr(-lim), upper=repr(lim), effort="0.0", velocity="0.0")
        ET.SubElement(el, "calibration", rising=repr(float(arrays["zero_offset"][i])))
    if not flange_is_link:
        fixed_name = f"{links[-1]}_joint"
        while fixed_name in model.joint_names:
            fixed_name += "_fixed"
        el = ET.SubElement(root, "joint", name=fixed_name, type="fixed")
        ET.SubElement(el, "parent", link=links[-2])
        ET.SubElement(el, "child", link=links[-1])
        set_origin(el, *_flange_origin(arrays["T_last_flange"]))
    for name, ratio in zip(model.joint_names, arrays["reduction_ratio"]):
        root.append(_new_transmission(name, ratio))
    return ET.ElementTree(root)


def save_urdf(model: KinematicModel, path, *, source=None) -> None:
    """Write `model` as a URDF file (atomically: a temporary file, then a rename).

    With `source` (the URDF the model was loaded from), the file is a copy of
    `source` in which each chain joint gets the model's `<origin>` (xyz/rpy)
    and `<axis>`, `<calibration rising="zero_offset"/>`, and its
    transmission's `mechanicalReduction` set to the reduction ratio;
    `T_last_flange` goes into the fixed joint(s) after the last movable joint.
    Fixed joints that `load_urdf` folded into a movable joint's origin must be
    identity transforms (to 1e-12), otherwise a `ValueError` explains that the
    origin cannot be written back one joint at a time.

    Without `source`, a minimal URDF: links without geometry, the joints with
    origins, axes, limits of $\\pm\\pi$ (a prismatic joint: $\\pm 1$ m), calibration, a fixed joint to the
    flange, and one transmission per joint.

    `load_urdf` of the written file gives back the model to 1e-12 (floats are
    written as `repr`). `model.T_flange_tool` is not written.
    """
    path = Path(path)
    if not path.parent.is_dir():
        raise ValueError(f"save_urdf: directory {str(path.parent)!r} of {shown(path)!r} does not exist")
    arrays = _model_arrays(model)
    if source is not None:
        tree = _fill_from_source(model, arrays, Path(source))
    else:
        tree = _minimal_tree(model, arrays, robot_name=path.stem)
    write_atomic(tree, path)
