"""The serial-chain kinematic model, forward kinematics and model conversions.

Conventions (defined once, used everywhere):

* Frames: `T_a_b` maps points from frame b into frame a. The model's reference
  frame is its *base* (the root link of the chain).
* Joint $i$ has a fixed origin `T_parent_joint[i]` (parent link frame -> joint
  frame, as a URDF `<origin>`), a unit `axis` expressed in the joint frame, and
  moves its child link by $\\exp(\\text{axis}\\,\\theta_i)$ (revolute) or
  $\\text{axis}\\,\\theta_i$ (prismatic).
* Encoders and angles: a motor encoder reads the motor angle $m_i$; the
  *commanded* joint position is $q_i = m_i / \\rho_i$ with $\\rho_i$ the
  reduction ratio (`reduction_ratio`, motor turns per joint turn); the angle
  the joint really stands at is $\\theta_i = q_i + \\delta_i$ with $\\delta_i$
  the zero offset (`zero_offset`). Forward kinematics takes $q$.
* After the last joint a fixed `T_last_flange` reaches the flange, and
  `T_flange_tool` the tool (or marker) frame.
"""

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, PRNGKeyArray

from ._device import to_device
from ._geometry import make_pose, matmul, matrix_to_rpy, normalize, rpy_to_matrix, se3_exp, so3_exp
from ._npgeom import rotvec_to_matrix

REVOLUTE = "revolute"
PRISMATIC = "prismatic"


class KinematicModel(eqx.Module):
    """A serial chain of revolute/prismatic joints, as a pytree.

    Numbers are leaves (so a batch of models is the same Module with a leading
    axis on every array, and `jax.vmap` maps over models); joint types and
    names are static structure.
    """

    T_parent_joint: Float[Array, "joints 4 4"]
    axis: Float[Array, "joints 3"]
    zero_offset: Float[Array, " joints"]
    reduction_ratio: Float[Array, " joints"]
    T_last_flange: Float[Array, "4 4"]
    T_flange_tool: Float[Array, "4 4"]
    joint_types: tuple[str, ...] = eqx.field(static=True)
    joint_names: tuple[str, ...] = eqx.field(static=True)
    link_names: tuple[str, ...] = eqx.field(static=True)

    def __check_init__(self):
        n = len(self.joint_types)
        if len(self.joint_names) != n:
            raise ValueError(f"KinematicModel: {n} joint types but {len(self.joint_names)} joint names")
        if len(self.link_names) != n + 2:
            raise ValueError(
                f"KinematicModel: link_names must list base, {n} joint child links and the flange "
                f"({n + 2} names), got {len(self.link_names)}"
            )
        for name, kind in zip(self.joint_names, self.joint_types):
            if kind not in (REVOLUTE, PRISMATIC):
                raise ValueError(f"KinematicModel: joint {name!r} has unsupported type {kind!r}")

    @property
    def num_joints(self) -> int:
        return len(self.joint_types)


def make_model(
    T_parent_joint,
    axis,
    *,
    joint_names: Sequence[str],
    joint_types: Sequence[str] | None = None,
    link_names: Sequence[str] | None = None,
    zero_offset=None,
    reduction_ratio=None,
    T_last_flange=None,
    T_flange_tool=None,
) -> KinematicModel:
    """Build a `KinematicModel` from arrays, filling defaults (float64)."""
    T_parent_joint = jnp.asarray(T_parent_joint, dtype=jnp.float64)
    n = T_parent_joint.shape[0]
    if T_parent_joint.shape != (n, 4, 4):
        raise ValueError(f"T_parent_joint must have shape (joints, 4, 4), got {T_parent_joint.shape}")
    axis = np.asarray(axis, dtype=np.float64)
    if axis.shape != (n, 3):
        raise ValueError(f"axis must have shape ({n}, 3), got {axis.shape}")
    norms = np.linalg.norm(axis, axis=1)
    if np.any(~np.isfinite(norms) | (norms < 1e-12)):
        j = int(np.flatnonzero(~np.isfinite(norms) | (norms < 1e-12))[0])
        raise ValueError(f"joint {tuple(joint_names)[j]!r}: axis {axis[j].tolist()} is zero or not finite")
    axis = to_device(axis / norms[:, None])
    for name, value in (("zero_offset", zero_offset), ("reduction_ratio", reduction_ratio)):
        if value is not None and np.shape(value) != (n,):
            raise ValueError(f"{name} must have shape ({n},), got {np.shape(value)}")
    for name, value in (("T_last_flange", T_last_flange), ("T_flange_tool", T_flange_tool)):
        if value is not None and np.shape(value) != (4, 4):
            raise ValueError(f"{name} must have shape (4, 4), got {np.shape(value)}")
    joint_types = tuple(joint_types) if joint_types is not None else (REVOLUTE,) * n
    link_names = (
        tuple(link_names)
        if link_names is not None
        else ("base",) + tuple(f"link{i + 1}" for i in range(n)) + ("flange",)
    )
    # Defaults made in NumPy and moved over: no compiled program per default in a fresh process.
    eye = to_device(np.eye(4))
    return KinematicModel(
        T_parent_joint=T_parent_joint,
        axis=axis,
        zero_offset=jnp.asarray(np.zeros(n) if zero_offset is None else zero_offset, jnp.float64),
        reduction_ratio=jnp.asarray(np.ones(n) if reduction_ratio is None else reduction_ratio, jnp.float64),
        T_last_flange=eye if T_last_flange is None else jnp.asarray(T_last_flange, jnp.float64),
        T_flange_tool=eye if T_flange_tool is None else jnp.asarray(T_flange_tool, jnp.float64),
        joint_types=joint_types,
        joint_names=tuple(joint_names),
        link_names=link_names,
    )


def joint_motion(kind: str, axis: Float[Array, "3"], theta: Float[Array, ""]) -> Float[Array, "4 4"]:
    if kind == REVOLUTE:
        return make_pose(so3_exp(axis * theta), jnp.zeros(3, dtype=axis.dtype))
    return make_pose(jnp.eye(3, dtype=axis.dtype), axis * theta)


def joint_angles(model: KinematicModel, q: Float[Array, " joints"]) -> Float[Array, " joints"]:
    """The angles the joints really stand at, $\\theta = q + \\delta$."""
    return q + model.zero_offset


def commanded_from_motor(
    model: KinematicModel, motor: Float[Array, "... joints"]
) -> Float[Array, "... joints"]:
    """Commanded joint positions from motor encoder angles, $q = m / \\rho$."""
    return motor / model.reduction_ratio


@jax.jit
def forward_kinematics(model: KinematicModel, q: Float[Array, " joints"]) -> Float[Array, "links 4 4"]:
    """Poses of every link in the base frame at commanded joint positions `q`.

    **Arguments:**
    - `model`: the chain.
    - `q`: commanded joint positions (rad or m), shape `(joints,)`.

    **Returns:** `T_base_link` for `model.link_names` (base, each joint's child
    link, flange), shape `(joints + 2, 4, 4)`. Vmap over `q` for many
    configurations and over `model` for many models.
    """
    theta = joint_angles(model, q)
    T = jnp.eye(4, dtype=model.T_parent_joint.dtype)
    frames = [T]
    # Products as broadcast-and-sum (`matmul`): under vmap over configurations a
    # batched 4x4 dot_general is several times slower on CPU.
    for i, kind in enumerate(model.joint_types):
        T = matmul(matmul(T, model.T_parent_joint[i]), joint_motion(kind, model.axis[i], theta[i]))
        frames.append(T)
    frames.append(matmul(T, model.T_last_flange))
    return jnp.stack(frames)


def tool_pose(model: KinematicModel, q: Float[Array, " joints"]) -> Float[Array, "4 4"]:
    """`T_base_tool` at commanded joint positions `q`."""
    return forward_kinematics(model, q)[-1] @ model.T_flange_tool


def joint_axes(
    model: KinematicModel, q: Float[Array, " joints"]
) -> tuple[Float[Array, "joints 3"], Float[Array, "joints 3"]]:
    """Every joint's axis line in the base frame at `q`: (points, unit directions).

    The point is the origin of the joint frame, which lies on the axis.
    """
    frames = forward_kinematics(model, q)
    T_joint = jnp.einsum("jab,jbc->jac", frames[:-2], model.T_parent_joint)
    dirs = jnp.einsum("jab,jb->ja", T_joint[:, :3, :3], model.axis)
    return T_joint[:, :3, 3], dirs


def joint_axes_at_zero(model: KinematicModel) -> tuple[np.ndarray, np.ndarray]:
    """`joint_axes(model, 0)` in NumPy, `(joints, 3)` points and unit directions: a host
    caller's few small products need no compiled program."""
    Tp, axis, theta = (
        np.asarray(a, np.float64) for a in (model.T_parent_joint, model.axis, model.zero_offset)
    )
    T, points, dirs = np.eye(4), [], []
    for i, kind in enumerate(model.joint_types):
        T = T @ Tp[i]
        points.append(T[:3, 3])
        dirs.append(T[:3, :3] @ axis[i])
        motion = np.eye(4)
        if kind == REVOLUTE:
            motion[:3, :3] = rotvec_to_matrix(axis[i] * theta[i])
        else:
            motion[:3, 3] = axis[i] * theta[i]
        T = T @ motion
    return np.stack(points), np.stack(dirs)


def origins_xyz_rpy(model: KinematicModel) -> tuple[np.ndarray, np.ndarray]:
    """Joint origins as URDF `xyz` (m) and `rpy` (rad), shape `(joints, 3)` each."""
    T = np.asarray(model.T_parent_joint)
    return T[:, :3, 3].copy(), rotations_to_rpy(T[:, :3, :3])


def rotations_to_rpy(R) -> np.ndarray:
    """URDF roll-pitch-yaw (`jaxcal._geometry.matrix_to_rpy`) of `(n, 3, 3)` rotations, `(n, 3)`
    (of one `(3, 3)`, `(3,)`), in NumPy: for host code that writes files."""
    return matrix_to_rpy(np.asarray(R, np.float64), np)


def origin_from_xyz_rpy(xyz, rpy) -> Float[Array, "4 4"]:
    """4x4 transform of a URDF `<origin xyz rpy>`."""
    return make_pose(rpy_to_matrix(jnp.asarray(rpy, jnp.float64)), jnp.asarray(xyz, jnp.float64))


# --------------------------------------------------------------------------- product of exponentials


class POEModel(eqx.Module):
    """Product-of-exponentials form: $T(q) = e^{[S_1] q_1} \\cdots e^{[S_n] q_n} M$.

    `screws[i] = (v_i, w_i)` is joint $i$'s screw axis in the base frame at
    the zero *commanded* configuration ($q = 0$, so zero offsets already
    applied): exactly what a joint-by-joint arc fit measures. `M` is the
    flange pose at that configuration.
    """

    screws: Float[Array, "joints 6"]
    M: Float[Array, "4 4"]


def to_poe(model: KinematicModel) -> POEModel:
    """Space-frame screw axes of `model` at $q = 0$."""
    points, dirs = joint_axes(model, jnp.zeros(model.num_joints))
    screws = []
    for i, kind in enumerate(model.joint_types):
        if kind == REVOLUTE:
            screws.append(jnp.concatenate([-jnp.cross(dirs[i], points[i]), dirs[i]]))
        else:
            screws.append(jnp.concatenate([dirs[i], jnp.zeros(3)]))
    return POEModel(screws=jnp.stack(screws), M=forward_kinematics(model, jnp.zeros(model.num_joints))[-1])


def poe_forward_kinematics(poe: POEModel, q: Float[Array, " joints"]) -> Float[Array, "4 4"]:
    """Flange pose from the product-of-exponentials form."""
    T = jnp.eye(4, dtype=poe.M.dtype)
    for i in range(poe.screws.shape[0]):
        T = T @ se3_exp(poe.screws[i] * q[i])
    return T @ poe.M


# --------------------------------------------------------------------------- perturbation


class PerturbationScales(eqx.Module):
    """Standard deviations of the deviations of a real arm from its datasheet.

    Units as named: millimetres, degrees and percent (zero offsets of
    prismatic joints use `zero_offset_mm`).
    """

    origin_mm: float = 1.0
    origin_deg: float = 0.2
    axis_tilt_deg: float = 0.2
    zero_offset_deg: float = 0.5
    zero_offset_mm: float = 0.5
    ratio_percent: float = 1.0
    tool_mm: float = 0.0
    tool_deg: float = 0.0

    @classmethod
    def of(cls, config, **overrides) -> "PerturbationScales":
        """The scales a simulator's config names in fields of the same names (`overrides` win)."""
        names = ("origin_mm", "origin_deg", "axis_tilt_deg", "zero_offset_deg", "ratio_percent")
        return cls(**({k: getattr(config, k) for k in names if hasattr(config, k)} | overrides))


def _tilt(axis: Float[Array, "3"], key: PRNGKeyArray, sigma_rad) -> Float[Array, "3"]:
    w = sigma_rad * jax.random.normal(key, (3,), dtype=axis.dtype)
    w = w - jnp.dot(w, axis) * axis  # a tilt, not a spin about the axis
    return normalize(so3_exp(w) @ axis)


def perturb_model(model: KinematicModel, key: PRNGKeyArray, scales: PerturbationScales) -> KinematicModel:
    """Draw a "true" arm from `model`: Gaussian deviations with the given scales.

    Joint origins move by `origin_mm` per axis and rotate by `origin_deg`
    about each axis, axes tilt by `axis_tilt_deg`, zero offsets by
    `zero_offset_deg` (`zero_offset_mm` for prismatic joints), reduction ratios by `ratio_percent` %, the tool by
    `tool_mm` / `tool_deg`. Pure and vmappable over `key`.
    """
    n = model.num_joints
    k_t, k_r, k_a, k_z, k_ratio, k_tool_t, k_tool_r = jax.random.split(key, 7)
    mm, deg = 1e-3, jnp.pi / 180.0
    dt = scales.origin_mm * mm * jax.random.normal(k_t, (n, 3))
    dr = scales.origin_deg * deg * jax.random.normal(k_r, (n, 3))
    dT = jax.vmap(make_pose)(jax.vmap(so3_exp)(dr), dt)
    # Translate in the parent frame, rotate in the joint frame.
    T_parent_joint = model.T_parent_joint.at[:, :3, 3].add(dt)
    T_parent_joint = T_parent_joint.at[:, :3, :3].set(
        jnp.einsum("jab,jbc->jac", model.T_parent_joint[:, :3, :3], dT[:, :3, :3])
    )
    axis_keys = jax.random.split(k_a, n)
    axis = jax.vmap(_tilt, in_axes=(0, 0, None))(model.axis, axis_keys, scales.axis_tilt_deg * deg)
    offset_scale = jnp.array(
        [
            scales.zero_offset_deg * deg if kind == REVOLUTE else scales.zero_offset_mm * mm
            for kind in model.joint_types
        ]
    )
    zero_offset = model.zero_offset + offset_scale * jax.random.normal(k_z, (n,))
    ratio = model.reduction_ratio * (1.0 + 0.01 * scales.ratio_percent * jax.random.normal(k_ratio, (n,)))
    tool_t = scales.tool_mm * mm * jax.random.normal(k_tool_t, (3,))
    tool_r = scales.tool_deg * deg * jax.random.normal(k_tool_r, (3,))
    T_flange_tool = model.T_flange_tool @ make_pose(so3_exp(tool_r), tool_t)
    return eqx.tree_at(
        lambda m: (m.T_parent_joint, m.axis, m.zero_offset, m.reduction_ratio, m.T_flange_tool),
        model,
        (T_parent_joint, axis, zero_offset, ratio, T_flange_tool),
    )


def with_tool(model: KinematicModel, T_flange_tool) -> KinematicModel:
    """`model` with its tool (or marker) transform replaced."""
    return eqx.tree_at(lambda m: m.T_flange_tool, model, jnp.asarray(T_flange_tool, jnp.float64))


def anchor_base(true: KinematicModel, nominal: KinematicModel) -> KinematicModel:
    """`true` with joint 1's origin, axis and zero offset reset to nominal (the gauge)."""
    return eqx.tree_at(
        lambda m: (m.T_parent_joint, m.axis, m.zero_offset),
        true,
        (
            true.T_parent_joint.at[0].set(nominal.T_parent_joint[0]),
            true.axis.at[0].set(nominal.axis[0]),
            true.zero_offset.at[0].set(nominal.zero_offset[0]),
        ),
    )
