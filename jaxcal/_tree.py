"""Kinematic trees: several tips on branches of one body, coupled joints, and gravity's load.

A humanoid's upper body, a dual-arm cell or a mobile manipulator is not one chain: a torso carries
two arms and a head, and a joint may follow others by a linear law (a URDF `<mimic>`, a
parallel linkage). `KinematicTree` holds every movable joint of such a body once, in an order
where each joint comes after its parent, with the conventions of `jaxcal._kinematics`:

* joint $j$ has a fixed origin `T_parent_joint[j]` from its parent link (the child link of
  joint `parent[j]`, or the root link for -1) and a unit `axis` in its own frame;
* the controller commands the *actuated* joints, $q \\in \\mathbb{R}^a$; every joint stands at
  $\\theta = C q + d + \\delta$, with `coupling` $C$ (a row of the identity for an actuated joint,
  the law's multipliers for a coupled one), `coupling_offset` $d$ and the zero offsets $\\delta$;
* tip $t$ (a hand, a camera, a marker plate) is a fixed frame `T_link_tip[t]` on link
  `tip_link[t]` (0: the root link, $j + 1$: joint $j$'s child link).

`tree_frames` is the whole tree's forward kinematics, one pure jitted function over every link
at once (vmap over configurations or over trees). `branch` is the serial chain from the root to
one tip, a `KinematicModel`, for what exists for chains (DH tables, plots).

**Gravity's load.** `gravity_torques` is the torque vector that the links' masses (centres of
mass from the robot file) put on each joint, every link below the joint counted, so a torso
joint carries both arms. Joint compliance turns a joint by $k_j\\, \\tau_j \\cdot a_j$ about its
axis; lateral compliance bends it by $k^{\\perp}_{j,1,2}$ times the torque's components about
two axes normal to it (`jaxcal._treefit`).
"""

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._device import to_device
from ._geometry import make_pose, matmul, so3_exp
from ._kinematics import PRISMATIC, REVOLUTE, KinematicModel, joint_motion, make_model

#: Standard gravity in the root frame (m/s^2), z up.
GRAVITY = (0.0, 0.0, -9.80665)


class KinematicTree(eqx.Module):
    """Every movable joint of a branching body once, parents before children, as a pytree.

    Numbers are leaves (a batch of trees vmaps); the structure (parents, tips, names, joint
    types) is static. `masses` (kg) and `centres` (m, in each link's frame) are the links'
    inertials, root first, for gravity's load (zeros where the robot file has none)."""

    T_parent_joint: Float[Array, "joints 4 4"]
    axis: Float[Array, "joints 3"]
    zero_offset: Float[Array, " joints"]
    coupling: Float[Array, "joints actuated"]
    coupling_offset: Float[Array, " joints"]
    T_link_tip: Float[Array, "tips 4 4"]
    masses: Float[Array, " links"]
    centres: Float[Array, "links 3"]
    parent: tuple[int, ...] = eqx.field(static=True)
    tip_link: tuple[int, ...] = eqx.field(static=True)
    joint_types: tuple[str, ...] = eqx.field(static=True)
    joint_names: tuple[str, ...] = eqx.field(static=True)
    actuated_names: tuple[str, ...] = eqx.field(static=True)
    link_names: tuple[str, ...] = eqx.field(static=True)
    tip_names: tuple[str, ...] = eqx.field(static=True)

    def __check_init__(self):
        n = len(self.joint_types)
        for field, size in (("joint_names", n), ("parent", n), ("link_names", n + 1)):
            if len(getattr(self, field)) != size:
                raise ValueError(
                    f"KinematicTree: {field} must have {size} entries, got {len(getattr(self, field))}"
                )
        for j, p in enumerate(self.parent):
            if not -1 <= p < j:
                raise ValueError(
                    f"KinematicTree: joint {self.joint_names[j]!r}'s parent {p} is not an earlier joint"
                )
        if len(self.tip_names) != len(self.tip_link) or not all(0 <= t <= n for t in self.tip_link):
            raise ValueError(f"KinematicTree: tips {self.tip_names} sit on links {self.tip_link} of 0..{n}")
        for name, kind in zip(self.joint_names, self.joint_types):
            if kind not in (REVOLUTE, PRISMATIC):
                raise ValueError(f"KinematicTree: joint {name!r} has unsupported type {kind!r}")

    @property
    def num_joints(self) -> int:
        return len(self.joint_types)

    @property
    def num_actuated(self) -> int:
        return len(self.actuated_names)

    @property
    def coupled(self) -> tuple[int, ...]:
        """The joints the controller does not command: each follows a law of others."""
        return tuple(j for j, name in enumerate(self.joint_names) if name not in self.actuated_names)

    def path(self, tip: int | str) -> tuple[int, ...]:
        """The joints from the root to tip `tip` (an index or a name), root first."""
        t = self.tip_names.index(tip) if isinstance(tip, str) else tip
        joints, j = [], self.tip_link[t] - 1
        while j >= 0:
            joints.append(j)
            j = self.parent[j]
        return tuple(joints[::-1])


def make_tree(
    T_parent_joint,
    axis,
    *,
    parent: Sequence[int],
    joint_names: Sequence[str],
    link_names: Sequence[str],
    tip_link: Sequence[int],
    tip_names: Sequence[str],
    T_link_tip=None,
    joint_types: Sequence[str] | None = None,
    coupling=None,
    coupling_offset=None,
    actuated_names: Sequence[str] | None = None,
    zero_offset=None,
    masses=None,
    centres=None,
) -> KinematicTree:
    """Build a `KinematicTree` from arrays, filling defaults (float64): no coupling (every joint
    actuated), identity tip frames, massless links."""
    T_parent_joint = np.asarray(T_parent_joint, np.float64)
    n = T_parent_joint.shape[0]
    axis = np.asarray(axis, np.float64)
    if T_parent_joint.shape != (n, 4, 4) or axis.shape != (n, 3):
        raise ValueError(
            f"T_parent_joint {T_parent_joint.shape} and axis {axis.shape} must be (n, 4, 4), (n, 3)"
        )
    norms = np.linalg.norm(axis, axis=1)
    if np.any(~np.isfinite(norms) | (norms < 1e-12)):
        j = int(np.flatnonzero(~np.isfinite(norms) | (norms < 1e-12))[0])
        raise ValueError(f"joint {tuple(joint_names)[j]!r}: axis {axis[j].tolist()} is zero or not finite")
    if coupling is None:
        coupling, actuated_names = np.eye(n), tuple(joint_names)
    elif actuated_names is None:
        raise ValueError("make_tree: a coupling needs the names of the actuated joints it maps from")
    coupling = np.asarray(coupling, np.float64)
    if coupling.shape != (n, len(actuated_names)):
        raise ValueError(f"coupling must have shape ({n}, {len(actuated_names)}), got {coupling.shape}")
    tips = len(tuple(tip_names))
    links = n + 1
    arrays = dict(
        T_parent_joint=T_parent_joint,
        axis=axis / norms[:, None],
        zero_offset=np.zeros(n) if zero_offset is None else zero_offset,
        coupling=coupling,
        coupling_offset=np.zeros(n) if coupling_offset is None else coupling_offset,
        T_link_tip=np.broadcast_to(np.eye(4), (tips, 4, 4)) if T_link_tip is None else T_link_tip,
        masses=np.zeros(links) if masses is None else masses,
        centres=np.zeros((links, 3)) if centres is None else centres,
    )
    return KinematicTree(
        **{k: to_device(np.array(v, np.float64)) for k, v in arrays.items()},
        parent=tuple(int(p) for p in parent),
        tip_link=tuple(int(t) for t in tip_link),
        joint_types=tuple(joint_types) if joint_types is not None else (REVOLUTE,) * n,
        joint_names=tuple(joint_names),
        actuated_names=tuple(actuated_names),
        link_names=tuple(link_names),
        tip_names=tuple(tip_names),
    )


def joint_positions(tree: KinematicTree, q: Float[Array, " actuated"]) -> Float[Array, " joints"]:
    """Where every joint stands at commanded actuated positions `q`: $C q + d + \\delta$."""
    return tree.coupling @ q + tree.coupling_offset + tree.zero_offset


def frames_at(tree: KinematicTree, theta, bend=None) -> Float[Array, "links 4 4"]:
    eye = jnp.eye(4, dtype=tree.T_parent_joint.dtype)
    frames = [eye]
    for j, kind in enumerate(tree.joint_types):
        T = matmul(
            matmul(frames[tree.parent[j] + 1], tree.T_parent_joint[j]),
            joint_motion(kind, tree.axis[j], theta[j]),
        )
        if bend is not None:  # a small rotation of the child link about its origin (lateral compliance)
            T = matmul(T, make_pose(so3_exp(bend[j]), jnp.zeros(3, dtype=T.dtype)))
        frames.append(T)
    return jnp.stack(frames)


@jax.jit
def tree_frames(tree: KinematicTree, q: Float[Array, " actuated"]) -> Float[Array, "links 4 4"]:
    """Poses of every link in the root frame at commanded actuated positions `q`, root first
    (`tree.link_names`). Vmap over `q` for many configurations, over `tree` for many trees."""
    return frames_at(tree, joint_positions(tree, q))


def tips_from_frames(tree: KinematicTree, frames: Float[Array, "links 4 4"]) -> Float[Array, "tips 4 4"]:
    """Every tip's pose in the root frame from the links' poses."""
    return matmul(frames[jnp.asarray(tree.tip_link)], tree.T_link_tip)


@jax.jit
def tip_poses(tree: KinematicTree, q: Float[Array, " actuated"]) -> Float[Array, "tips 4 4"]:
    """Every tip's pose in the root frame at commanded actuated positions `q`."""
    return tips_from_frames(tree, tree_frames(tree, q))


def gravity_torques(
    tree: KinematicTree, frames: Float[Array, "links 4 4"], gravity=GRAVITY, moments=None, masses=None
) -> Float[Array, "joints 3"]:
    """The torque vector (N m, root frame) that gravity on every link below joint $j$ puts about
    joint $j$'s origin, for the links' poses `frames`; the joint's own link included. `moments`
    `(links, 3)`: corrections to the links' first moments of mass (kg m, link frames; a centre
    of mass moved by $\\delta c$ is $m\\,\\delta c$), which add $R_l \\delta_l \\times g$ to every
    joint above link $l$; `masses` `(links,)`: corrections to the links' masses (kg, at their
    centres of mass)."""
    g = jnp.asarray(gravity, frames.dtype)
    centres = jnp.einsum("lab,lb->la", frames[:, :3, :3], tree.centres) + frames[:, :3, 3]
    forces = (tree.masses if masses is None else tree.masses + masses)[:, None] * g
    below = jnp.asarray(descendants(tree), frames.dtype)
    origins = frames[1:, :3, 3]  # joint j's frame sits at its child link's origin
    arms = centres[None, :, :] - origins[:, None, :]
    tau = jnp.einsum("jl,jla->ja", below, jnp.cross(arms, forces[None, :, :]))
    if moments is not None:
        tau = tau + below @ jnp.cross(jnp.einsum("lab,lb->la", frames[:, :3, :3], moments), g)
    return tau


def descendants(tree: KinematicTree) -> np.ndarray:
    """`below[j, l]`: link `l` (root first) moves with joint `j`."""
    n = tree.num_joints
    below = np.zeros((n, n + 1))
    for j in range(n):
        k = j
        while k >= 0:
            below[k, j + 1] = 1.0
            k = tree.parent[k]
    return below


def normal_axes(axis: Float[Array, "joints 3"]) -> Float[Array, "joints 2 3"]:
    """Two unit axes normal to each joint's axis (in its frame), the directions it bends about."""
    helper = jnp.where(jnp.abs(axis[:, :1]) < 0.9, jnp.array([[1.0, 0.0, 0.0]]), jnp.array([[0.0, 1.0, 0.0]]))
    n1 = jnp.cross(axis, helper)
    n1 = n1 / jnp.linalg.norm(n1, axis=1, keepdims=True)
    return jnp.stack([n1, jnp.cross(axis, n1)], axis=1)


def branch(tree: KinematicTree, tip: int | str) -> tuple[KinematicModel, np.ndarray]:
    """The serial chain from the root to `tip`: a `KinematicModel` over the path's joints (the
    tip as its flange) and the `(path joints, actuated)` map $C$ from actuated commands to the
    chain's joint positions (its zero offsets take $d + \\delta$). Traceable in the tree's
    geometry (a table's derivatives with respect to a fit's parameters)."""
    path = list(tree.path(tip))
    t = tree.tip_names.index(tip) if isinstance(tip, str) else tip
    if not path:
        raise ValueError(f"tip {tree.tip_names[t]!r} sits on the root link: no joint moves it")
    rows = jnp.asarray(path)
    return (
        make_model(
            tree.T_parent_joint[rows],
            np.asarray(tree.axis)[path],
            joint_names=[tree.joint_names[j] for j in path],
            joint_types=[tree.joint_types[j] for j in path],
            link_names=[tree.link_names[0], *(tree.link_names[j + 1] for j in path), tree.tip_names[t]],
            zero_offset=(tree.zero_offset + tree.coupling_offset)[rows],
            T_last_flange=tree.T_link_tip[t],
        ),
        tree.coupling[rows],
    )


def held_by_branch(tree: KinematicTree, layout, free: np.ndarray, candidates: np.ndarray) -> dict:
    """The candidate parameters (of a `jaxcal._treefit.TreeLayout`) held at nominal, by where they sit: `shared` (a joint on several
    tips' paths), a tip's name (a joint on that tip's path only; its point), `unmeasured` (a
    joint on no tip's path: a head when only the hands are tips), or `device`."""
    paths = {t: set(tree.path(t)) for t in tree.tip_names}
    held: dict[str, list[str]] = {}
    for i in np.flatnonzero(candidates & ~free):
        j, name = layout.joints[i], layout.names[i]
        if layout.groups[i] == "device":
            where = "device"
        elif layout.groups[i] == "point":
            where = name.split(".point.")[0]
        else:
            on = [t for t, p in paths.items() if j in p]
            where = "shared" if len(on) > 1 else (on[0] if on else "unmeasured")
        held.setdefault(where, []).append(name)
    return held
