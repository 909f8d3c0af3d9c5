"""Denavit-Hartenberg tables of any revolute `KinematicModel`, differentiably.

A revolute chain is, at its zero commanded configuration, a list of joint axis
lines $L_i = (p_i, z_i)$ in the base frame and a flange pose. A DH table is
one way to write those lines down (Denavit and Hartenberg 1955): frame $i$
has its $z$ along axis $i+1$ and its $x$ along the common normal $N_i$ from
axis $i$ to axis $i+1$, and

* standard DH, row $i$: $A_i = R_z(\\theta_i + q_i)\\,T_z(d_i)\\,T_x(a_i)\\,R_x(\\alpha_i)$;
* modified DH (Craig 1986), row $i$: $R_x(\\alpha_{i-1})\\,T_x(a_{i-1})\\,R_z(\\theta_i + q_i)\\,T_z(d_i)$.

Both share $\\theta_i$ (the angle about axis $i$ from $N_{i-1}$ to $N_i$) and
$d_i$ (the distance along axis $i$ between their feet); $a_i$, $\\alpha_i$
(length of $N_i$ and the angle from axis $i$ to axis $i+1$ about it) sit in
row $i$ (DH) or row $i+1$ (MDH). `T_base` (base -> frame 0) and `T_flange`
(last frame -> flange) make the table's forward kinematics equal the
model's exactly: $T_{base,flange}(q) = T_{base}\\prod_i A_i(q_i)\\,T_{flange}$.

**Frame choices** (one rule each, so that the table is a function of the model):

* frame 0: $z$ along axis 1, origin the foot of the base origin on axis 1,
  $x$ the base's $x$ made orthogonal to $z$ (its $y$ when $x$ is along the axis);
* frame $i$ ($1 \\le i < n$): $x_i = \\pm (z_{i-1} \\times z_i)/\\|\\cdot\\|$, the sign
  that points along a hint (the model's link-$i$ $x$ axis, or a reference
  table's $x_i$), so that a calibrated arm keeps its datasheet's signs;
* frame $n$: $z$ along the last axis, origin the foot of the flange origin on
  it, $x$ the flange's $x$ made orthogonal to $z$; so $a_n = \\alpha_n = 0$ and
  `T_flange` holds only what the flange adds off the last axis.

**Parallel axes** (the rule this module follows). When consecutive axes $i$,
$i+1$ are (nearly) parallel the common normal slides along them: $d_i$ is
arbitrary for parallel axes and, for axes a small angle $\\gamma$ apart, jumps
to $\\sim a_i/\\tan\\gamma$ with a sensitivity $\\partial d_i/\\partial\\gamma \\sim
a_i/\\sin^2\\gamma$ (a calibrated tilt of 0.1 mrad moves it metres). Such rows
use Hayati's remedy (Hayati and Mirmirani 1985): $d_i = 0$ and an extra
rotation $\\beta_i$ about $y$, $A_i = R_z(\\theta_i+q_i)\\,T_x(a_i)\\,R_x(\\alpha_i)\\,R_y(\\beta_i)$
(MDH: $R_x(\\alpha_{i-1})\\,T_x(a_{i-1})\\,R_y(\\beta_{i-1})\\,R_z(\\theta_i+q_i)\\,T_z(d_i)$):
frame $i$'s origin is where axis $i+1$ pierces the plane through frame
$i-1$'s origin normal to axis $i$, its $x$ points there (sign by the hint),
and $\\alpha_i$, $\\beta_i$ turn axis $i$ onto axis $i+1$. A pair is treated so when
the angle between the axes is under `PARALLEL_TOL_DEG` (10 degrees); the
decision is made once on concrete numbers (the nominal model's, or a
reference table's), recorded in `DHTable.parallel`, and kept for every
model compared with it (so the calibrated table has the same form as the
nominal one and is differentiable). Every other row has $\\beta = 0$.
"""

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._device import to_device
from ._geometry import make_pose, matmul, matrix_to_rpy, pose_inverse, safe_norm
from ._kinematics import REVOLUTE, KinematicModel, forward_kinematics, joint_axes_at_zero, make_model

#: Consecutive axes closer than this (degrees) get Hayati's parallel-axis row.
PARALLEL_TOL_DEG = 10.0
#: Table conventions: standard (Denavit-Hartenberg) and modified (Craig).
CONVENTIONS = ("dh", "mdh")
#: Columns of a table, in the order `DHTable.columns` returns them.
COLUMNS = ("theta", "d", "a", "alpha", "beta")


class DHTable(eqx.Module):
    """A DH or MDH table with the base and flange transforms that make it exact.

    - `theta`, `d`, `a`, `alpha`, `beta`: per row (joint), rad and m. Row $i$
      of an MDH table holds Craig's $(\\alpha_{i-1}, a_{i-1}, \\theta_i, d_i)$
      (and $\\beta_{i-1}$), so row 1's $a$, $\\alpha$ are those of the base frame.
    - `T_base`: base -> frame 0; `T_flange`: last frame -> flange.
    - `convention`: `"dh"` or `"mdh"`; `parallel`: per row, whether it
      carries Hayati's $\\beta$ (a parallel pair $i, i+1$ is DH row $i$, MDH
      row $i+1$; its $d_i$ is 0 by the rule).
    """

    theta: Float[Array, " joints"]
    d: Float[Array, " joints"]
    a: Float[Array, " joints"]
    alpha: Float[Array, " joints"]
    beta: Float[Array, " joints"]
    T_base: Float[Array, "4 4"]
    T_flange: Float[Array, "4 4"]
    convention: str = eqx.field(static=True)
    joint_names: tuple[str, ...] = eqx.field(static=True)
    parallel: tuple[bool, ...] = eqx.field(static=True)

    def __check_init__(self):
        if self.convention not in CONVENTIONS:
            raise ValueError(f"DHTable: convention must be one of {CONVENTIONS}, got {self.convention!r}")
        if len(self.parallel) != len(self.joint_names):
            raise ValueError(
                f"DHTable: {len(self.joint_names)} joints but {len(self.parallel)} parallel flags"
            )

    def columns(self) -> Float[Array, "5 joints"]:
        """The columns stacked in `COLUMNS` order."""
        return jnp.stack([self.theta, self.d, self.a, self.alpha, self.beta])


# --------------------------------------------------------------------------- link transforms


def _rx(angle, xp=jnp) -> Float[Array, "3 3"]:
    c, s = xp.cos(angle), xp.sin(angle)
    return xp.stack([1.0, 0.0, 0.0, 0.0, c, -s, 0.0, s, c]).reshape(3, 3)


def _ry(angle, xp=jnp) -> Float[Array, "3 3"]:
    c, s = xp.cos(angle), xp.sin(angle)
    return xp.stack([c, 0.0, s, 0.0, 1.0, 0.0, -s, 0.0, c]).reshape(3, 3)


def _traced(*values) -> bool:
    return any(isinstance(v, jax.core.Tracer) for v in jax.tree.leaves(values))


def link_transform(convention: str, theta, d, a, alpha, beta) -> Float[Array, "4 4"]:
    """One row's transform: DH $R_z(\\theta)T_z(d)T_x(a)R_x(\\alpha)R_y(\\beta)$,
    MDH $R_x(\\alpha)T_x(a)R_y(\\beta)R_z(\\theta)T_z(d)$ (with the joint's $q$ in $\\theta$).
    Written out (one 3x3 and a $R_y$) to keep the compiled programs small; in NumPy when
    nothing is traced (loading a robot file compiles nothing)."""
    xp = jnp if _traced(theta, d, a, alpha, beta) else np
    ct, st, ca, sa = xp.cos(theta), xp.sin(theta), xp.cos(alpha), xp.sin(alpha)
    zero, one = xp.zeros_like(ct), xp.ones_like(ct)
    if convention == "dh":
        R = xp.stack(
            [xp.stack([ct, -st * ca, st * sa]), xp.stack([st, ct * ca, -ct * sa]), xp.stack([zero, sa, ca])]
        )
        R, t = R @ _ry(beta, xp), xp.stack([a * ct, a * st, d + zero])
    elif convention == "mdh":
        R = (
            _rx(alpha, xp)
            @ _ry(beta, xp)
            @ xp.stack([ct, -st, zero, st, ct, zero, zero, zero, one]).reshape(3, 3)
        )
        t = xp.stack([a + zero, zero, zero]) + R[:, 2] * d
    else:
        raise ValueError(f"convention must be one of {CONVENTIONS}, got {convention!r}")
    bottom = xp.stack([zero, zero, zero, one])[None]
    return xp.concatenate([xp.concatenate([R, t[:, None]], axis=1), bottom], axis=0)


def table_frames(table: DHTable, q: Float[Array, " joints"] | None = None) -> Float[Array, "frames 4 4"]:
    """Frames 0..n of the table in the base frame at commanded `q` (default zero), then the flange."""
    q = jnp.zeros_like(table.theta) if q is None else q
    T = table.T_base
    frames = [T]
    for i in range(table.theta.shape[0]):
        row = (table.theta[i] + q[i], table.d[i], table.a[i], table.alpha[i], table.beta[i])
        T = T @ link_transform(table.convention, *row)
        frames.append(T)
    frames.append(T @ table.T_flange)
    return jnp.stack(frames)


def table_forward_kinematics(table: DHTable, q: Float[Array, " joints"]) -> Float[Array, "4 4"]:
    """$T_{base,flange}(q) = T_{base}\\prod_i A_i(q_i)\\,T_{flange}$ (commanded `q`, rad)."""
    return table_frames(table, q)[-1]


def table_to_model(
    table: DHTable,
    *,
    link_names: Sequence[str] | None = None,
    reduction_ratio=None,
) -> KinematicModel:
    """The `KinematicModel` of a table: joint $i$ rotates about $z$ of its
    frame, its origin the product of the rows before it (DH: frame $i-1$
    turned by $\\theta_i$; MDH: row $i$ up to $R_z(\\theta_i)$), and the rest
    (with `T_flange`) in `T_last_flange`. Its forward kinematics equals
    `table_forward_kinematics`."""
    n = table.theta.shape[0]
    if not _traced(table):  # in NumPy: loading a robot file compiles nothing
        table = jax.tree.map(np.asarray, table)
    origins = []
    carry = table.T_base
    zero = np.zeros(())
    for i in range(n):
        if table.convention == "dh":
            origins.append(carry @ link_transform("dh", table.theta[i], zero, zero, zero, zero))
            carry = link_transform("dh", zero, table.d[i], table.a[i], table.alpha[i], table.beta[i])
        else:
            origins.append(
                carry @ link_transform("mdh", table.theta[i], zero, table.a[i], table.alpha[i], table.beta[i])
            )
            carry = link_transform("mdh", zero, table.d[i], zero, zero, zero)
    return make_model(
        to_device(np.stack(origins)) if not _traced(table) else jnp.stack(origins),
        np.tile([0.0, 0.0, 1.0], (n, 1)),
        joint_names=table.joint_names,
        link_names=link_names,
        reduction_ratio=reduction_ratio,
        T_last_flange=carry @ table.T_flange,
    )


def _columns(a, alpha, d, theta) -> list[np.ndarray]:
    arrays = [np.asarray(x, dtype=np.float64) for x in (a, alpha, d, theta)]
    n = arrays[0].shape[0] if arrays[0].ndim == 1 else -1
    for name, x in zip(("a", "alpha", "d", "theta"), arrays):
        if x.ndim != 1 or x.shape != (n,):
            raise ValueError(f"DH table column {name!r} has shape {x.shape}, expected ({max(n, 0)},)")
    return arrays


def _from_columns(convention, a, alpha, d, theta, joint_names, flange, T_base, reduction_ratio, link_names):
    a, alpha, d, theta = _columns(a, alpha, d, theta)
    n = a.shape[0]
    table = DHTable(
        theta=jnp.asarray(theta),
        d=jnp.asarray(d),
        a=jnp.asarray(a),
        alpha=jnp.asarray(alpha),
        beta=jnp.zeros(n),
        T_base=jnp.eye(4) if T_base is None else jnp.asarray(T_base, jnp.float64),
        T_flange=jnp.eye(4) if flange is None else jnp.asarray(flange, jnp.float64),
        convention=convention,
        joint_names=tuple(joint_names),
        parallel=(False,) * n,
    )
    return table_to_model(table, link_names=link_names, reduction_ratio=reduction_ratio)


def from_dh(
    a,
    alpha,
    d,
    theta,
    *,
    joint_names: Sequence[str],
    flange=None,
    T_base=None,
    reduction_ratio=None,
    link_names: Sequence[str] | None = None,
) -> KinematicModel:
    """A revolute chain from a standard DH table, $T_i = R_z(\\theta_i+q_i) T_z(d_i) T_x(a_i) R_x(\\alpha_i)$
    (`table_to_model` of that `DHTable`).

    The joint frames are the DH frames: joint 1's origin is `T_base`, joint
    $k$'s origin is $T_z(d_{k-1})T_x(a_{k-1})R_x(\\alpha_{k-1})$ (with the
    constant $\\theta_{k-1}$ folded in), and the last row goes into
    `T_last_flange` (followed by the optional `flange` 4x4).

    **Arguments:** `a` (m), `alpha` (rad), `d` (m), `theta` (rad, constant
    joint offsets of the table), each of shape `(joints,)`.
    """
    return _from_columns("dh", a, alpha, d, theta, joint_names, flange, T_base, reduction_ratio, link_names)


def from_mdh(
    a,
    alpha,
    d,
    theta,
    *,
    joint_names: Sequence[str],
    flange=None,
    T_base=None,
    reduction_ratio=None,
    link_names: Sequence[str] | None = None,
) -> KinematicModel:
    """A revolute chain from a modified (Craig) DH table, $T_i = R_x(\\alpha_{i-1}) T_x(a_{i-1}) R_z(\\theta_i+q_i) T_z(d_i)$.

    Row $i$ holds $(a_{i-1}, \\alpha_{i-1}, d_i, \\theta_i)$ as in Craig's
    table; joint $i$'s origin is $R_x(\\alpha_{i-1})T_x(a_{i-1})R_z(\\theta_i)$ and
    its $T_z(d_i)$ is carried into the next origin (or into `T_last_flange`,
    followed by `flange`).
    """
    return _from_columns("mdh", a, alpha, d, theta, joint_names, flange, T_base, reduction_ratio, link_names)


# --------------------------------------------------------------------------- extraction


def _orthogonal(h, z, fallback):
    """`h` made orthogonal to unit `z` and normalised (`fallback` when `h` is along `z`)."""
    u = h - jnp.dot(h, z) * z
    v = fallback - jnp.dot(fallback, z) * z
    n = safe_norm(u)
    use = n > 1e-6
    w = jnp.where(use, u, v)
    return w / safe_norm(w)


def _signed(n, hint):
    """Unit `n` with the sign that points along `hint` (+ when `hint` is orthogonal)."""
    n = n / safe_norm(n)
    return jnp.where(jnp.dot(hint, n) < -1e-9, -n, n)


def _angle_about(x0, x1, z):
    """The angle about `z` that turns `x0` onto `x1` (both orthogonal to `z`)."""
    return jnp.arctan2(jnp.dot(jnp.cross(x0, x1), z), jnp.dot(x0, x1))


def _common_normal_row(frame, line, hint):
    """Row of non-parallel axes: the common normal from axis i (frame's z) to the next axis."""
    x, z, o = frame
    p, w = line
    c = jnp.dot(z, w)
    r = p - o
    den = 1.0 - c * c
    s = (jnp.dot(r, z) - c * jnp.dot(r, w)) / den
    t = (c * jnp.dot(r, z) - jnp.dot(r, w)) / den
    foot_i, foot_next = o + s * z, p + t * w
    xn = _signed(jnp.cross(z, w), hint)
    row = (
        _angle_about(x, xn, z),
        s,
        jnp.dot(foot_next - foot_i, xn),
        jnp.arctan2(jnp.dot(jnp.cross(z, w), xn), c),
        jnp.zeros_like(c),
    )
    return row, (xn, w, foot_next)


def _hayati_row(frame, line, hint):
    """Row of (nearly) parallel axes: $d = 0$, origin where the next axis pierces
    the plane through the frame's origin normal to its z, and $\\alpha$, $\\beta$
    turning z onto the next axis (Hayati and Mirmirani 1985)."""
    x, z, o = frame
    p, w = line
    on = p + jnp.dot(o - p, z) / jnp.dot(w, z) * w
    v = on - o
    u = _signed(_orthogonal(v, z, _orthogonal(hint, z, x)), hint)
    y = jnp.cross(z, u)
    wx, wy, wz = jnp.dot(w, u), jnp.dot(w, y), jnp.dot(w, z)
    alpha = jnp.arctan2(-wy, wz)
    beta = jnp.arctan2(wx, jnp.sqrt(wy * wy + wz * wz))
    R = jnp.stack([u, y, z], axis=1) @ _rx(alpha) @ _ry(beta)
    row = (_angle_about(x, u, z), jnp.zeros_like(wx), jnp.dot(v, u), alpha, beta)
    return row, (R[:, 0], R[:, 2], on)


def _end_row(frame, T_flange):
    """Last row: frame n on the last axis at the flange origin's foot, x the flange's x."""
    x, z, o = frame
    pf = T_flange[:3, 3]
    xe = _orthogonal(T_flange[:3, 0], z, T_flange[:3, 1])
    d = jnp.dot(pf - o, z)
    zero = jnp.zeros_like(d)
    return (_angle_about(x, xe, z), d, zero, zero, zero), (xe, z, o + d * z)


def parallel_pairs(model: KinematicModel, tol_deg: float = PARALLEL_TOL_DEG) -> tuple[bool, ...]:
    """Per DH row $i$ ($< n$), whether axes $i$ and $i+1$ are within `tol_deg` of
    parallel (or antiparallel) at the zero configuration; the last row is False.
    Needs concrete numbers (call it outside `jit` / `jacfwd`)."""
    _, dirs = joint_axes_at_zero(model)
    sines = np.linalg.norm(np.cross(dirs[:-1], dirs[1:]), axis=1)
    return tuple(bool(s < np.sin(np.radians(tol_deg))) for s in sines) + (False,)


def _hints(frames: Float[Array, "links 4 4"], reference: DHTable | None):
    """x-axis hints of frames 0..n-1: the reference table's frames, else the model's
    links (`frames`: its forward kinematics at zero)."""
    if reference is not None:
        return table_frames(reference)[:-2, :3, 0]
    return jnp.concatenate([jnp.eye(3)[None, :, 0], frames[1:-2, :3, 0]])


def dh_table(
    model: KinematicModel,
    convention: str = "dh",
    *,
    reference: DHTable | None = None,
    parallel: Sequence[bool] | None = None,
    tol_deg: float = PARALLEL_TOL_DEG,
) -> DHTable:
    """The DH (or MDH) table of a revolute `model` (see the module docstring for the rules).

    **Arguments:**
    - `model`: a chain of revolute joints; its zero offsets go into $\\theta$
      (the table takes commanded $q$, like `forward_kinematics`).
    - `convention`: `"dh"` (standard) or `"mdh"` (Craig).
    - `reference`: a table of the same arm (e.g. the nominal's): its parallel
      rows and the signs of its $x$ axes are kept, so the two compare row by row.
    - `parallel`: per DH row, Hayati's form (default: from `reference`, else
      `parallel_pairs(model, tol_deg)`; needs a concrete model).

    **Returns:** a `DHTable` with `table_forward_kinematics(table, q) ==
    forward_kinematics(model, q)[-1]`. Pure `jnp`: differentiable in `model`.
    """
    if any(kind != REVOLUTE for kind in model.joint_types):
        bad = [j for j, k in zip(model.joint_names, model.joint_types) if k != REVOLUTE]
        raise ValueError(f"dh_table: only revolute chains have DH tables here; prismatic joints {bad}")
    if convention not in CONVENTIONS:
        raise ValueError(f"convention must be one of {CONVENTIONS}, got {convention!r}")
    n = model.num_joints
    if parallel is None:
        parallel = _dh_parallel(reference) if reference is not None else parallel_pairs(model, tol_deg)
    parallel = tuple(bool(p) for p in parallel)
    if len(parallel) != n:
        raise ValueError(f"dh_table: {n} joints but {len(parallel)} parallel flags")
    frames = forward_kinematics(model, jnp.zeros(n))
    T_joint = matmul(frames[:-2], model.T_parent_joint)  # joint frames at q = 0 (as `joint_axes`)
    points, dirs = T_joint[:, :3, 3], jnp.einsum("jab,jb->ja", T_joint[:, :3, :3], model.axis)
    T_base_flange = frames[-1]
    hints = _hints(frames, reference)
    z0 = dirs[0]
    frame = (_orthogonal(hints[0], z0, jnp.eye(3)[1]), z0, points[0] - jnp.dot(points[0], z0) * z0)
    T_base = _pose(frame)
    rows = []
    for i in range(n):
        if i == n - 1:
            row, frame = _end_row(frame, T_base_flange)
        elif parallel[i]:
            row, frame = _hayati_row(frame, (points[i + 1], dirs[i + 1]), hints[i + 1])
        else:
            row, frame = _common_normal_row(frame, (points[i + 1], dirs[i + 1]), hints[i + 1])
        rows.append(row)
    theta, d, a, alpha, beta = (jnp.stack(c) for c in zip(*rows))
    T_flange = pose_inverse(_pose(frame)) @ T_base_flange
    table = DHTable(theta, d, a, alpha, beta, T_base, T_flange, "dh", tuple(model.joint_names), parallel)
    return table if convention == "dh" else to_mdh(table)


def _pose(frame):
    x, z, o = frame
    return make_pose(jnp.stack([x, jnp.cross(z, x), z], axis=1), o)


def _dh_parallel(table: DHTable) -> tuple[bool, ...]:
    """The parallel flags in DH row order (MDH rows carry them one row later)."""
    return table.parallel if table.convention == "dh" else table.parallel[1:] + (False,)


def to_mdh(table: DHTable) -> DHTable:
    """A DH table as MDH (Craig): same $\\theta$, $d$, base and flange; $a$, $\\alpha$,
    $\\beta$ one row later (row 1's zero: frame 0 already has its z on axis 1)."""
    if table.convention == "mdh":
        return table

    def shift(c):  # one row later; host values in NumPy (no compiled program)
        return (
            jnp.concatenate([jnp.zeros(1), c[:-1]])
            if _traced(c)
            else to_device(np.r_[0.0, np.asarray(c)[:-1]])
        )

    return DHTable(
        table.theta,
        table.d,
        shift(table.a),
        shift(table.alpha),
        shift(table.beta),
        table.T_base,
        table.T_flange,
        "mdh",
        table.joint_names,
        (False,) + table.parallel[:-1],
    )


# --------------------------------------------------------------------------- flat values


def pose_xyz_rpy(T: Float[Array, "4 4"]) -> Float[Array, "6"]:
    """A pose as (x, y, z, roll, pitch, yaw) (m, rad; URDF convention)."""
    return jnp.concatenate([T[:3, 3], matrix_to_rpy(T[:3, :3])])


def table_values(table: DHTable) -> Float[Array, " values"]:
    """The table flattened: every row's `COLUMNS`, then `T_base` and `T_flange` as xyz/rpy."""
    return jnp.concatenate(
        [table.columns().T.reshape(-1), pose_xyz_rpy(table.T_base), pose_xyz_rpy(table.T_flange)]
    )


def table_value_names(table: DHTable) -> list[tuple[str, str]]:
    """`(name, unit)` of every entry of `table_values`."""
    units = {"theta": "rad", "d": "m", "a": "m", "alpha": "rad", "beta": "rad"}
    out = [(f"{j}.{table.convention}.{c}", units[c]) for j in table.joint_names for c in COLUMNS]
    pose = [("x", "m"), ("y", "m"), ("z", "m"), ("roll", "rad"), ("pitch", "rad"), ("yaw", "rad")]
    for frame in ("base", "flange"):
        out += [(f"{table.convention}.{frame}.{k}", u) for k, u in pose]
    return out


def max_fk_difference(table: DHTable, model: KinematicModel, qs: Float[Array, "configs joints"]):
    """Largest flange position (m) and rotation (Frobenius of $R_1 - R_2$) differences over `qs`."""
    T1 = jax.vmap(lambda q: table_forward_kinematics(table, q))(qs)
    T2 = jax.vmap(lambda q: forward_kinematics(model, q)[-1])(qs)
    dp = jnp.max(safe_norm(T1[:, :3, 3] - T2[:, :3, 3]))
    dR = jnp.max(jnp.sqrt(jnp.sum((T1[:, :3, :3] - T2[:, :3, :3]) ** 2, axis=(1, 2))))
    return dp, dR
