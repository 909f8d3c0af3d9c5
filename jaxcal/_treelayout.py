"""The parameter vector of a tree calibration (`jaxcal._treefit`): each parameter's name, typical
size, group and the joint it belongs to, and the order in which the identifiability search
frees them."""

from dataclasses import dataclass, field

import numpy as np

from ._tree import KinematicTree

#: The families of non-geometric terms, in the order the layout lists them.
FAMILIES = ("joint", "lateral", "harmonic", "mass")


@dataclass(frozen=True)
class TreeLayout:
    """The flattened vector: each parameter's name, typical size (its unit: m, rad, rad/(N m), or
    relative for a multiplier) and group (`device`, `point`, `origin`, `zero`, `coupling`, or a
    family of `FAMILIES`), grouped (each group a slice), and `order`: the identifiability
    search's priority order (the device, the tips' points, each joint root first with its zero
    offset before its origin, couplings, then the terms)."""

    names: tuple[str, ...]
    scales: np.ndarray
    groups: tuple[str, ...]
    joints: tuple[int, ...]  # the joint a parameter belongs to (-1: none)
    couplings: tuple[tuple[int, int], ...]  # (joint, actuated) of each coupling multiplier
    slices: dict = field(compare=False)
    order: np.ndarray = field(compare=False, default=None)

    @property
    def size(self) -> int:
        return len(self.names)

    def family(self, *groups: str) -> np.ndarray:
        return np.isin(np.asarray(self.groups), groups)


def tree_layout(tree: KinematicTree) -> TreeLayout:
    """The parameters of `tree`'s calibration (see the module docstring for their order)."""
    rows: list[tuple[str, float, str, int]] = []
    slices = {}

    def add(group, entries):
        start = len(rows)
        rows.extend((name, scale, group, j) for name, scale, j in entries)
        slices[group] = slice(start, len(rows))

    add("device", [(f"device.{a}", 1e-2, -1) for a in ("x", "y", "z", "rx", "ry", "rz")])
    add("point", [(f"{t}.point.{a}", 5e-3, -1) for t in tree.tip_names for a in "xyz"])
    twist = {"x": 1e-3, "y": 1e-3, "z": 1e-3, "rx": 3e-3, "ry": 3e-3, "rz": 3e-3}
    add(
        "origin",
        [(f"{n}.origin.{a}", s, j) for j, n in enumerate(tree.joint_names) for a, s in twist.items()],
    )
    add("zero", [(f"{n}.zero_offset", 5e-3, j) for j, n in enumerate(tree.joint_names)])
    C = np.asarray(tree.coupling)
    couplings = tuple((int(j), int(a)) for j in tree.coupled for a in np.flatnonzero(C[j]))
    add(
        "coupling",
        [(f"{tree.joint_names[j]}.multiplier.{tree.actuated_names[a]}", 1e-2, j) for j, a in couplings],
    )
    add("joint", [(f"{n}.compliance", 2e-4, j) for j, n in enumerate(tree.joint_names)])
    add(
        "lateral",
        [(f"{n}.lateral_compliance.{k}", 1e-4, j) for j, n in enumerate(tree.joint_names) for k in "12"],
    )
    add(
        "harmonic",
        [(f"{n}.harmonic.{k}", 1e-3, j) for j, n in enumerate(tree.joint_names) for k in ("cos", "sin")],
    )
    links = list(zip(tree.link_names, np.asarray(tree.masses).tolist()))
    add(
        "mass",
        [(f"gravity.tilt.{a}", 3e-3, -1) for a in "xy"]
        + [
            (f"{link}.moment.{a}", max(2e-2 * m, 1e-3), j - 1)
            for j, (link, m) in enumerate(links)
            for a in "xyz"
        ]
        + [(f"{link}.mass", max(0.05 * m, 0.05), j - 1) for j, (link, m) in enumerate(links)],
    )
    names, scales, groups, joints = zip(*rows)
    rank = {"device": 0, "point": 1, "zero": 2, "origin": 2, "coupling": 3}
    within = {"zero": 0, "origin": 1}
    key = [
        (rank.get(g, 4), j if g in within else 0, within.get(g, 0), i)
        for i, (g, j) in enumerate(zip(groups, joints))
    ]
    order = np.array([k[-1] for k in sorted(key)])
    return TreeLayout(names, np.asarray(scales), groups, joints, couplings, slices, order)
