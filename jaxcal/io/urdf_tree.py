"""A URDF with branches and coupled joints read as a `jaxcal._tree.KinematicTree`, and written back.

`load_urdf_tree` keeps every movable joint below the base link, in the file's order (breadth-first
from the base where the file lists a child before its parent). Fixed joints fold into the next
movable joint's origin (or into a tip's frame), and a link's mass and centre of mass fold into the
link that carries it. A `<mimic joint multiplier offset>` joint follows its leader:
$\\theta = m\\, \\theta_{leader} + o$ (a mimic of a mimic composes). Tips are the links named, or
every leaf reached through a movable joint.

`save_urdf_tree` writes a copy of the source file with the tree's joint origins (zero offsets
turned into them), axes and mimic laws; the fixed joints stay as they are (a movable joint's
origin is written relative to them), so the written file's structure is the source's.
"""

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .._kinematics import joint_motion, rotations_to_rpy
from .._tree import KinematicTree, make_tree
from ._files import shown
from ._urdf_checks import check_joint_element, check_joint_links, limit_range
from ._urdf_tree import checked_rpy, fmt, read_tree, set_origin, write_atomic
from .urdf import MOVABLE, base_link_of, check_joint_type, parse_urdf


@dataclass(frozen=True)
class _Frame:
    """Where a link sits: on the child link of movable joint `owner` (-1: the base), at `T`."""

    owner: int
    T: np.ndarray
    fixed: tuple  # the fixed joints from the owner to this link, nearest last


def _walk(robot, path: Path, base: str):
    """Movable joints below `base` (parents first, file order) and every link's `_Frame`."""
    children: dict[str, list] = {}
    for j in robot.joints:
        children.setdefault(j.parent, []).append(j)
    frames, movable, stack = {base: _Frame(-1, np.eye(4), ())}, [], [base]
    while stack:
        link = stack.pop(0)
        for j in children.get(link, []):
            check_joint_type(j, path, mimic=True)
            if j.child in frames:
                raise ValueError(f"URDF file {shown(path)!r}: link {j.child!r} is reached twice (a cycle)")
            here = frames[link]
            origin = np.eye(4) if j.origin is None else np.asarray(j.origin, np.float64)
            if j.type == "fixed":
                frames[j.child] = _Frame(here.owner, here.T @ origin, (*here.fixed, j.name))
            else:
                movable.append((j, here))
                frames[j.child] = _Frame(len(movable) - 1, np.eye(4), ())
            stack.append(j.child)
    return movable, frames


def _ordered_walk(robot, path: Path, base: str):
    """`_walk`, the movable joints then put in the file's order where every parent comes first
    there (as most files list them, and as yourdfpy orders its joints); else breadth-first."""
    movable, frames = _walk(robot, path, base)
    position = {j.name: i for i, j in enumerate(robot.joints)}
    order = sorted(range(len(movable)), key=lambda i: position[movable[i][0].name])
    new = {old: k for k, old in enumerate(order)}
    remap = lambda f: _Frame(-1 if f.owner < 0 else new[f.owner], f.T, f.fixed)  # noqa: E731
    if any(movable[old][1].owner >= 0 and new[movable[old][1].owner] >= k for k, old in enumerate(order)):
        return movable, frames
    return [(movable[old][0], remap(movable[old][1])) for old in order], {
        k: remap(f) for k, f in frames.items()
    }


def _coupling(movable, path: Path) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """The coupling matrix and offsets of the movable joints, and the actuated joints' names."""
    index = {j.name: i for i, (j, _) in enumerate(movable)}
    actuated = [j.name for j, _ in movable if j.mimic is None]
    C, d = np.zeros((len(movable), len(actuated))), np.zeros(len(movable))

    def law(i: int, depth: int = 0) -> tuple[np.ndarray, float]:
        j = movable[i][0]
        if j.mimic is None:
            return np.eye(len(actuated))[actuated.index(j.name)], 0.0
        leader = j.mimic.get("joint")
        if leader is None or leader == j.name:
            what = "names no joint (joint=)" if leader is None else "names the joint itself"
            raise ValueError(f"URDF file {shown(path)!r}: joint {j.name!r}'s <mimic> {what}")
        if leader not in index or depth > len(movable):
            raise ValueError(
                f"URDF file {shown(path)!r}: joint {j.name!r} mimics {leader!r}, which is not a movable joint "
                "below the base link (or the mimic laws form a loop)"
            )
        try:
            m, o = float(j.mimic.get("multiplier", "1")), float(j.mimic.get("offset", "0"))
        except ValueError:
            raise ValueError(
                f"URDF file {shown(path)!r}: joint {j.name!r}'s <mimic> has a non-numeric value"
            ) from None
        row, off = law(index[leader], depth + 1)
        return m * row, m * off + o

    for i in range(len(movable)):
        C[i], d[i] = law(i)
    return C, d, actuated


def _masses(robot, frames: dict, count: int) -> tuple[np.ndarray, np.ndarray]:
    """Each movable link's mass (root first) and centre of mass, the fixed links' folded in."""
    mass, moment = np.zeros(count + 1), np.zeros((count + 1, 3))
    for link in robot.links:
        if link.name not in frames or link.inertial is None:
            continue
        f = frames[link.name]
        c = np.zeros(3) if link.inertial.origin is None else link.inertial.origin[:3, 3]
        mass[f.owner + 1] += link.inertial.mass
        moment[f.owner + 1] += link.inertial.mass * (f.T[:3, :3] @ c + f.T[:3, 3])
    centres = np.divide(moment, mass[:, None], out=np.zeros_like(moment), where=mass[:, None] > 0)
    return mass, centres


def load_urdf_tree(path, base_link: str | None = None, tips=None) -> KinematicTree:
    """Read every movable joint below `base_link` (default: the root link) of a URDF file.

    **Arguments:**
    - `path`: the URDF file.
    - `base_link`: the tree's root frame.
    - `tips`: link names whose frames are the tree's tips (hands, a camera); default every leaf
      link reached through a movable joint.

    Raises `ValueError` naming the file and the joint or link for what `load_urdf` refuses
    (but `<mimic>`), a mimic of a joint that is not in the tree, and an unknown tip.
    """
    path = Path(path)
    if isinstance(tips, str):
        raise ValueError(f"tips must be a list of link names, got the string {tips!r} (write [{tips!r}])")
    root = parse_urdf(path).getroot()
    check_joint_links(root, path)
    robot = read_tree(root, path)
    base_link = base_link_of(robot, path, base_link)
    movable, frames = _ordered_walk(robot, path, base_link)
    if not movable:
        raise ValueError(f"URDF file {shown(path)!r}: no movable joint below base link {base_link!r}")
    elements = {el.get("name"): el for el in root.findall("joint")}
    for j, _ in movable:
        check_joint_element(elements[j.name], path)
    if tips is None:
        parents = {j.parent for j in robot.joints}
        tips = [n for n in frames if n not in parents and frames[n].owner >= 0]
    unknown = [t for t in tips if t not in frames]
    if unknown:
        raise ValueError(
            f"URDF file {shown(path)!r}: tip link(s) {unknown} are not below base link {base_link!r}"
        )
    C, d, actuated = _coupling(movable, path)
    masses, centres = _masses(robot, frames, len(movable))
    return make_tree(
        np.stack([f.T @ (np.eye(4) if j.origin is None else j.origin) for j, f in movable]),
        np.stack([j.axis for j, _ in movable]),
        parent=[f.owner for _, f in movable],
        joint_names=[j.name for j, _ in movable],
        joint_types=[MOVABLE[j.type] for j, _ in movable],
        link_names=[base_link, *(j.child for j, _ in movable)],
        tip_link=[frames[t].owner + 1 for t in tips],
        tip_names=list(tips),
        T_link_tip=np.stack([frames[t].T for t in tips]),
        coupling=C,
        coupling_offset=d,
        actuated_names=actuated,
        zero_offset=[0.0 if j.rising is None or j.mimic is not None else j.rising for j, _ in movable],
        masses=masses,
        centres=centres,
    )


def actuated_limits(path, tree: KinematicTree) -> np.ndarray:
    """`(actuated, 2)` lower and upper limits of the tree's actuated joints in its URDF file
    (a continuous joint has none: -inf, inf)."""
    root = parse_urdf(Path(path)).getroot()
    elements = {el.get("name"): el for el in root.findall("joint")}
    rows = []
    for name in tree.actuated_names:
        el = elements[name]
        rows.append((-np.inf, np.inf) if el.get("type") == "continuous" else limit_range(el, Path(path)))
    return np.asarray(rows, np.float64)


def _xyz_rpy(T: np.ndarray, what: str) -> tuple[np.ndarray, np.ndarray]:
    xyz = T[:3, 3].copy()
    return xyz, checked_rpy(T, xyz, rotations_to_rpy(T[:3, :3]), f"save_urdf_tree: {what}")


def _same_structure(tree: KinematicTree, source_tree: KinematicTree, source: Path) -> None:
    """Refuse a `source` whose robot is not the tree's, naming the first difference."""
    for what in ("joint_names", "parent", "joint_types", "actuated_names", "tip_link"):
        if getattr(tree, what) != getattr(source_tree, what):
            raise ValueError(
                f"save_urdf_tree: {shown(source)!r} is not this tree's robot file: its {what} are "
                f"{getattr(source_tree, what)}, the tree's {getattr(tree, what)}"
            )
    if not np.array_equal(np.asarray(tree.coupling) != 0, np.asarray(source_tree.coupling) != 0):
        raise ValueError(
            f"save_urdf_tree: {shown(source)!r} is not this tree's robot file: its mimic joints follow other joints"
        )


def save_urdf_tree(tree: KinematicTree, path, *, source) -> None:
    """Write `tree` as a copy of `source` (the URDF it was read from), atomically.

    Each movable joint gets the tree's origin (relative to the fixed joints above it, which
    stay) and axis; an actuated joint's zero offset is turned into its origin (a `<calibration
    rising>` becomes 0: robot_state_publisher, MoveIt and yourdfpy ignore that tag), a mimic
    joint's goes into its law's offset, beside the law's multiplier. A tip's frame goes into
    the last fixed joint above it. `load_urdf_tree` of the written file gives back the tree's
    forward kinematics to 1e-12, and so does any URDF reader. `source` must have the tree's
    structure (joints, parents, types, couplings, tips), else `ValueError` says what differs.
    """
    path, source = Path(path), Path(source)
    if not path.parent.is_dir():
        raise ValueError(f"save_urdf_tree: directory {str(path.parent)!r} of {shown(path)!r} does not exist")
    xml = parse_urdf(source)
    root = xml.getroot()
    robot = read_tree(root, source)
    _same_structure(
        tree, load_urdf_tree(source, base_link=tree.link_names[0], tips=list(tree.tip_names)), source
    )
    movable, frames = _ordered_walk(robot, source, tree.link_names[0])
    elements = {el.get("name"): el for el in root.findall("joint")}
    T_joint, axes = np.asarray(tree.T_parent_joint), np.asarray(tree.axis)
    zero, C, d = (np.asarray(a) for a in (tree.zero_offset, tree.coupling, tree.coupling_offset))
    for i, (j, above) in enumerate(movable):
        el = elements[j.name]
        T = T_joint[i]
        if j.mimic is None:  # the zero offset turned into the origin: what every URDF reader applies
            T = T @ np.asarray(joint_motion(tree.joint_types[i], axes[i], zero[i]))
            calibration = el.find("calibration")
            if calibration is not None and calibration.get("rising") is not None:
                calibration.set("rising", "0.0")
        set_origin(el, *_xyz_rpy(np.linalg.solve(above.T, T), f"origin of joint {j.name!r}"))
        axis = el.find("axis")
        if axis is None:
            axis = ET.SubElement(el, "axis")
        axis.set("xyz", fmt(axes[i]))
        if j.mimic is not None:
            leader = j.mimic.get("joint")
            while leader not in tree.actuated_names:
                leader = elements[leader].find("mimic").get("joint")
            j.mimic.set("joint", leader)
            j.mimic.set("multiplier", fmt(C[i, tree.actuated_names.index(leader)]))
            j.mimic.set("offset", fmt(d[i] + zero[i]))
    for t, name in enumerate(tree.tip_names):
        frame = frames[name]
        T_tip = np.asarray(tree.T_link_tip)[t]
        if not frame.fixed:
            if np.abs(T_tip - np.eye(4)).max() > 1e-12:
                raise ValueError(f"save_urdf_tree: tip {name!r} has no fixed joint to hold its frame")
            continue
        last = elements[frame.fixed[-1]]
        above = frames[last.find("parent").get("link")].T
        set_origin(last, *_xyz_rpy(np.linalg.solve(above, T_tip), f"frame of tip {name!r}"))
    write_atomic(xml, path)
