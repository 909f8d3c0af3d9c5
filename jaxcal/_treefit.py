"""Calibrating a kinematic tree from points measured on several tips at once.

A tracker (or motion capture) sees a reflector on each hand of a body at stop-and-shoot poses;
one sample may carry several tips. The model of tip $t$ at pose $i$ is

$$ y_{it} = T_{dev,root} \\exp(\\xi_{dev})\\, T_{root,tip_t}(q_i;\\ \\text{tree}, \\text{elastic})\\, (p_t + \\delta p_t), $$

with every joint origin corrected by a twist, every joint's zero offset, each coupled joint's
multipliers, and four families of non-geometric terms (`FAMILIES`):

* `joint`: joint compliance, $\\delta\\theta_j = k_j\\, \\tau_j \\cdot a_j$, the gravity torque
  $\\tau_j$ of every link below joint $j$ (both arms load the torso: `jaxcal._tree.gravity_torques`);
* `lateral`: the joint's bending about the two axes normal to it by $k^{\\perp}$ times the
  torque's components about them;
* `harmonic`: a once-per-turn angle error $c_j \\cos\\theta_j + s_j \\sin\\theta_j$ (an eccentric
  encoder);
* `mass`: corrections to the robot file's masses where the sag sees them: each link's mass and
  first moment of mass (its centre of mass times its mass), and gravity's tilt against the root. They
  act only through the compliances, so they are tried only once a compliance is kept.

Parameters are scaled by a typical size each (`TreeLayout.scales`) and the residuals whitened by
the noise, so a parameter's conditional standard deviation is in units of its typical size.
`identifiable` keeps a parameter (in a fixed priority order: the device, the tips' points, the
joints root first, couplings, then the terms) only where the data determine it to within
`DETERMINED` typical sizes, given those kept before it: exact redundancies (a gauge, a branch no
tip measures) and directions the data hardly see stay at their nominal values, named. (Holding
what the data see only poorly costs more: on the simulated upper body, holding every parameter
not determined to half its size biased the compliances far outside their uncertainty.) `cross_validate_terms` keeps a family of
terms only where it lowers the K-fold held-out error; every fold is one vmapped solve.
"""

from dataclasses import dataclass, field

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from . import _lsq
from ._geometry import pose_inverse, se3_exp, se3_log, skew, so3_exp, so3_right_jacobian
from ._tree import (
    GRAVITY,
    KinematicTree,
    descendants,
    frames_at,
    gravity_torques,
    joint_positions,
    normal_axes,
    tips_from_frames,
)
from ._treelayout import FAMILIES, TreeLayout

#: The families that make the tree sag under gravity (the `mass` corrections act through them).
COMPLIANT = ("joint", "lateral")
#: A parameter is freed where the data determine it to within this many typical sizes: a
#: parameter held at nominal takes its real deviation (about one typical size) into the others,
#: so only what the data barely see (or not at all: a gauge, a branch no tip measures) is held.
DETERMINED = 10.0
#: The `mass` corrections, seen only through the sag, are freed where the data determine them to
#: within one typical size: more loosely held, they trade off against each other and the
#: compliances, and the solve wanders along those directions.
MASS_DETERMINED = 1.0
LM = _lsq.LMOptions(rtol=1e-6, atol=1e-2, max_steps=100, normal_cholesky=True)
#: ... and the fit resumed with what only the sag shows, whose directions the data see weakly: the
#: trust region walks them in many short steps (about 350 at 10 um of tracker noise), so it is
#: resumed up to this many times `LM`'s steps (`_solve_long`: `LM`'s compiled program again).
SAG_RESUMES = 5
#: ... resumed at most this many times, each without the new parameters the last left looser
#: than a typical size (a parameter held is off by about one: freed, it must do better).
SAG_ROUNDS = 4
#: Gauss-Newton steps after it (and from the fit to all samples, for a cross-validation fold):
#: with the exact Jacobian, two take both to where a third moves nothing that shows.
POLISH = 2


class Elastic(eqx.Module):
    """Compliances (rad per N m): `joint` about each joint's axis, `lateral` about the two
    axes normal to it (`jaxcal._tree.normal_axes`); the loads' corrections: `moments`, the
    links' first moments of mass (kg m, link frames, `jaxcal._tree.gravity_torques`), and
    `tilt`, gravity's tilt about the root's x and y (rad), and `masses`, the links' masses (kg,
    added at their centres of mass); None: the robot file's."""

    joint: Float[Array, " joints"]
    lateral: Float[Array, "joints 2"]
    moments: Float[Array, "links 3"] | None = None
    tilt: Float[Array, "2"] | None = None
    masses: Float[Array, " links"] | None = None


def _loads(tree, rigid, elastic: Elastic):
    """The gravity torque about each joint's axis `(joints,)` and about its two normals
    `(joints, 2)`, for the links' rigid poses `rigid`."""
    g = jnp.asarray(GRAVITY, rigid.dtype)
    if elastic.tilt is not None:
        g = so3_exp(jnp.concatenate([elastic.tilt, jnp.zeros(1, rigid.dtype)])) @ g
    tau = gravity_torques(tree, rigid, g, elastic.moments, elastic.masses)
    R = rigid[1:, :3, :3]
    about = jnp.einsum("jab,jb,ja->j", R, tree.axis, tau)
    return about, jnp.einsum("jka,jba,jb->jk", normal_axes(tree.axis), R, tau)


@dataclass(frozen=True)
class TreeSamples:
    """Stop-and-shoot samples: commanded actuated positions `q` `(n, actuated)`, the measured
    points `(n, tips, 3)` (m, device frame), which were `measured` `(n, tips)`, from a
    simulator the noise-free `truth`, and each point's noise `covariance` `(n, tips, 3, 3)`
    (m^2, device frame: a camera's PnP sees across better than in depth; None: isotropic)."""

    q: np.ndarray
    points: np.ndarray
    measured: np.ndarray
    truth: np.ndarray | None = None
    covariance: np.ndarray | None = None

    def subset(self, rows) -> "TreeSamples":
        part = lambda a: None if a is None else a[rows]  # noqa: E731
        return TreeSamples(
            self.q[rows], self.points[rows], self.measured[rows], part(self.truth), part(self.covariance)
        )


def _seen(tips, p, T_dev, device_tip: int):
    """Points `p` (root frame) in the device's frame: a fixed device's `T_dev` maps the root into it;
    a device on tip `device_tip` (a head camera) sits at `T_dev` in that tip's frame."""
    if device_tip < 0:
        return p @ T_dev[:3, :3].T + T_dev[:3, 3]
    D = tips[device_tip] @ T_dev
    return (p - D[:3, 3]) @ D[:3, :3]


def deflected_frames(tree, q, elastic=None, harmonic=None) -> Float[Array, "links 4 4"]:
    """The links' poses (root frame) at commanded actuated positions `q`, the body bent by
    gravity (`elastic`, None: rigid) and the joints' harmonics (`(joints, 2)`, None: none)."""
    theta = joint_positions(tree, q)
    if harmonic is not None:
        theta = theta + harmonic[:, 0] * jnp.cos(theta) + harmonic[:, 1] * jnp.sin(theta)
    frames = frames_at(tree, theta)
    if elastic is not None:
        about, torque = _loads(tree, frames, elastic)
        bend = jnp.einsum("jk,jkc->jc", elastic.lateral * torque, normal_axes(tree.axis))
        frames = frames_at(tree, theta + elastic.joint * about, bend)
    return frames


def _tip_points(tree, q, points, T_dev, elastic, harmonic, device_tip: int = -1):
    tips = tips_from_frames(tree, deflected_frames(tree, q, elastic, harmonic))
    p = jnp.einsum("tab,tb->ta", tips[:, :3, :3], points) + tips[:, :3, 3]
    return _seen(tips, p, T_dev, device_tip)


@eqx.filter_jit
def deflected_tips(
    tree, elastic, q, points, T_device, harmonic=None, device_tip: int = -1
) -> Float[Array, "n tips 3"]:
    """The tips' points `(tips, 3)` (tip frames) seen from the device at configurations `q`
    `(n, actuated)`, the body bent by gravity (`elastic`, None: rigid). `T_device`: the fixed
    device's `T_device_root`, or with `device_tip` (an index of `tree.tip_names`: a camera on the
    head) the device's pose in that tip's frame."""
    points, T = jnp.asarray(points, jnp.float64), jnp.asarray(T_device, jnp.float64)
    tip = lambda q: _tip_points(tree, q, points, T, elastic, harmonic, device_tip)  # noqa: E731
    return jax.vmap(tip)(q)


class TreeProblem(eqx.Module):
    """A tree calibration's data and start: `u` (scaled corrections) maps to a body."""

    tree: KinematicTree
    T_device_root: Float[Array, "4 4"]
    points0: Float[Array, "tips 3"]
    q: Float[Array, "n actuated"]
    y: Float[Array, "n tips 3"]
    weight: Float[Array, "n tips"]
    scales: Float[Array, " p"]
    sigma: float
    couplings: tuple = eqx.field(static=True)
    slices: tuple = eqx.field(static=True)  # (group, start, stop)
    device_tip: int = eqx.field(static=True, default=-1)  # -1: a fixed device
    #: `sigma` times the inverse Cholesky factor of each point's covariance; None: isotropic.
    whiten: Float[Array, "n tips 3 3"] | None = None


def _whitened(problem: TreeProblem, e):
    """Residuals (or Jacobian rows) `e` `(n, tips, 3, ...)` in units of the stated `sigma`."""
    if problem.whiten is None:
        return e
    return jnp.einsum("ntab,ntb...->nta...", problem.whiten, e)


def problem_of(
    tree,
    layout: TreeLayout,
    samples: TreeSamples,
    T_device_root,
    points,
    noise_mm: float,
    device_tip: int = -1,
) -> TreeProblem:
    """The problem of `samples` about a start `tree`, device pose and tip points (`device_tip`:
    the device rides on that tip, `T_device_root` is then its pose in the tip's frame)."""
    whiten = None
    if samples.covariance is not None:
        cov = np.where(samples.measured[..., None, None], samples.covariance, np.eye(3))
        whiten = 1e-3 * noise_mm * np.linalg.inv(np.linalg.cholesky(cov))
    return TreeProblem(
        tree=tree,
        T_device_root=jnp.asarray(T_device_root, jnp.float64),
        points0=jnp.asarray(points, jnp.float64),
        q=jnp.asarray(samples.q, jnp.float64),
        y=jnp.asarray(np.where(samples.measured[..., None], samples.points, 0.0), jnp.float64),
        weight=jnp.asarray(samples.measured, jnp.float64),
        scales=jnp.asarray(layout.scales),
        sigma=1e-3 * noise_mm,
        couplings=layout.couplings,
        slices=tuple((g, s.start, s.stop) for g, s in layout.slices.items()),
        device_tip=device_tip,
        whiten=None if whiten is None else jnp.asarray(whiten),
    )


def body_of(u: Float[Array, " p"], problem: TreeProblem):
    """`(tree, T_device_root, points, elastic, harmonic)` at scaled corrections `u`."""
    x = u * problem.scales
    part = {g: x[a:b] for g, a, b in problem.slices}
    tree = problem.tree
    n = tree.num_joints
    T = jax.vmap(lambda T0, xi: T0 @ se3_exp(xi))(tree.T_parent_joint, part["origin"].reshape(n, 6))
    C = tree.coupling
    for k, (j, a) in enumerate(problem.couplings):
        C = C.at[j, a].add(part["coupling"][k] * jnp.abs(tree.coupling[j, a]))
    tree = eqx.tree_at(
        lambda t: (t.T_parent_joint, t.zero_offset, t.coupling), tree, (T, tree.zero_offset + part["zero"], C)
    )
    mass = part["mass"]
    moments, masses = mass[2 : 2 + 3 * (n + 1)].reshape(n + 1, 3), mass[2 + 3 * (n + 1) :]
    elastic = Elastic(part["joint"], part["lateral"].reshape(n, 2), moments, mass[:2], masses)
    points = problem.points0 + part["point"].reshape(-1, 3)
    return (
        tree,
        problem.T_device_root @ se3_exp(part["device"]),
        points,
        elastic,
        part["harmonic"].reshape(n, 2),
    )


def predict(u, problem: TreeProblem, q=None) -> Float[Array, "n tips 3"]:
    """The tips' points in the device frame at `q` (default: the problem's poses)."""
    tree, T, points, elastic, harmonic = body_of(u, problem)
    return deflected_tips(
        tree, elastic, problem.q if q is None else q, points, T, harmonic, problem.device_tip
    )


def _residuals_autodiff(u, args) -> Float[Array, " m"]:
    free, weight, problem = args
    r = _whitened(problem, predict(u * free, problem) - problem.y) / problem.sigma
    return (r * (weight * problem.weight)[..., None]).ravel()


def _right_jacobian(xi: Float[Array, "6"]) -> Float[Array, "6 6"]:
    """$d\\,\\log(e^{-\\xi} e^{\\xi + \\delta}) / d\\delta$ at 0: a twist's change as a local one."""
    local = lambda d: se3_log(pose_inverse(se3_exp(xi)) @ se3_exp(xi + d))  # noqa: E731
    return jax.jacfwd(local)(jnp.zeros(6, xi.dtype))


def local_twists(layout: TreeLayout, x) -> np.ndarray:
    """`(p, p)`: how the fit's twists `x` (each parameter in its own unit) about the nominal
    body move with local twists about the body they reach (the device's pose and each joint's
    origin: `_right_jacobian`); the identity elsewhere. A derivative by the local twists (of the
    calibrated body read back), times it, is one by the fit's parameters, whose covariance the
    fit states."""
    M, x = np.eye(layout.size), np.asarray(x, np.float64)
    for group in ("device", "origin"):
        part = layout.slices[group]
        blocks = np.asarray(jax.vmap(_right_jacobian)(jnp.asarray(x[part].reshape(-1, 6))))
        for k, start in enumerate(range(part.start, part.stop, 6)):
            M[start : start + 6, start : start + 6] = blocks[k]
    return M


def _load_columns(tree, elastic, rigid, theta0, dh, C0, couplings, q):
    """The loads' derivatives (`_loads`: `(joints, p)` and `(joints, 2, p)`) with respect to the
    parameters they depend on, in `TreeLayout` order: local origin twists, zero offsets, coupling
    multipliers, the harmonics, then the `mass` corrections; at the links' rigid poses `rigid`.
    A parameter the rigid tips cannot see (a shift along a joint's axis) still moves a link's
    centre of mass, so it moves the sag.

    With $M_l$ a link's first moment of mass (root frame), $A_j = \\sum_{l \\succeq j} (M_l - m_l
    o_j)$ and $\\tau_j = A_j \\times g$: a motion $(\\omega, v)$ about $p$ of the links below joint
    $i$ turns $A_j$ by $\\omega$ for a joint $j$ that moves with it, and moves the sum of those
    links' moments for a joint $j$ above it."""
    n, dtype = tree.num_joints, rigid.dtype
    below = jnp.asarray(descendants(tree), dtype)  # below[j, l]: link l moves with joint j
    sub = below[:, 1:]  # sub[i, j]: joint j moves with joint i (or is it)
    above = sub.T - jnp.eye(n, dtype=dtype)  # above[i, j]: joint j lies above joint i
    R, pos = rigid[:, :3, :3], rigid[:, :3, 3]
    tilt = jnp.concatenate([elastic.tilt, jnp.zeros(1, dtype)])
    g0 = jnp.asarray(GRAVITY, dtype)
    g = so3_exp(tilt) @ g0
    centres = jnp.einsum("lab,lb->la", R, tree.centres) + pos
    m = tree.masses + elastic.masses
    M = m[:, None] * centres + jnp.einsum("lab,lb->la", R, elastic.moments)
    mass_below, B = below @ m, below @ M
    A = B - mass_below[:, None] * pos[1:]
    tau = jnp.cross(A, g)
    F = jnp.einsum("jab,jbc->jac", rigid[jnp.asarray(tree.parent) + 1], tree.T_parent_joint)
    RF, P = F[:, :3, :3], F[:, :3, 3]
    # About the joint's axis, then its two normals (root frame, moving with the child link).
    units = jnp.einsum(
        "jab,jkb->jka", R[1:], jnp.concatenate([tree.axis[:, None], normal_axes(tree.axis)], axis=1)
    )
    axis = units[:, 0]
    revolute = jnp.asarray([k == "revolute" for k in tree.joint_types])[:, None]
    none = jnp.zeros((n, 3, 3), dtype)
    # Each joint's seven motions: its origin's local twist (v, then w), then its angle.
    omega = jnp.concatenate([none, RF.transpose(0, 2, 1), jnp.where(revolute, axis, 0.0)[:, None]], axis=1)
    v = jnp.concatenate([RF.transpose(0, 2, 1), none, jnp.where(revolute, 0.0, axis)[:, None]], axis=1)
    moving = jnp.cross(jnp.cross(omega[:, :, None], A[None, None]), g)  # (i, k, j, 3)
    carried = jnp.cross(
        jnp.cross(omega, (B - mass_below[:, None] * P)[:, None]) + mass_below[:, None, None] * v, g
    )
    dtau = sub[:, None, :, None] * moving + above[:, None, :, None] * carried[:, :, None]
    d = sub[:, None, :, None] * jnp.einsum("ikc,juc->ikju", omega, jnp.cross(units, tau[:, None]))
    d = d + jnp.einsum("juc,ikjc->ikju", units, dtau)  # (i, k, j, u)
    angle = d[:, 6].transpose(1, 2, 0)  # (j, u, i)
    coupled = [angle[..., j] * dh[j] * q[a] * jnp.abs(C0[j, a]) for j, a in couplings]
    dG = so3_exp(tilt) @ jnp.cross(so3_right_jacobian(tilt)[:, :2].T, g0).T  # (3, 2)
    moments = jnp.einsum("juv,jl,lcv->julc", units, below, jnp.cross(R.transpose(0, 2, 1), g))
    cols = jnp.concatenate(
        [
            d[:, :6].transpose(2, 3, 0, 1).reshape(n, 3, 6 * n),
            angle * dh,
            jnp.stack(coupled, axis=-1) if coupled else jnp.zeros((n, 3, 0), dtype),
            jnp.stack([angle * jnp.cos(theta0), angle * jnp.sin(theta0)], axis=-1).reshape(n, 3, 2 * n),
            jnp.einsum("juc,jck->juk", units, jnp.cross(A[:, :, None], dG[None], axis=1)),
            moments.reshape(n, 3, 3 * (n + 1)),
            jnp.einsum("juv,jl,jlv->jul", units, below, jnp.cross(centres[None] - pos[1:, None], g)),
        ],
        axis=-1,
    )
    return cols[:, 0], cols[:, 1:]


def _sample_columns(tree, T_dev, points, elastic, harmonic, C0, couplings, q, device_tip: int = -1):
    """One pose's tip points `(tips, 3)` (device frame) and their derivatives `(tips, 3, p)`
    with respect to the parameters in `TreeLayout` order, in their own units, local twists on
    the device and the joint origins (the caller applies the right Jacobians); exact, the
    gravity torques' change with the geometry included (`_load_columns`)."""
    n, tips = tree.num_joints, len(tree.tip_names)
    theta0 = joint_positions(tree, q)
    dh = 1.0 - harmonic[:, 0] * jnp.sin(theta0) + harmonic[:, 1] * jnp.cos(theta0)
    theta = theta0 + harmonic[:, 0] * jnp.cos(theta0) + harmonic[:, 1] * jnp.sin(theta0)
    rigid = frames_at(tree, theta)
    about, torque = _loads(tree, rigid, elastic)
    normals = normal_axes(tree.axis)
    bend = jnp.einsum("jk,jkc->jc", elastic.lateral * torque, normals)
    frames = frames_at(tree, theta + elastic.joint * about, bend)
    F = jnp.einsum("jab,jbc->jac", frames[jnp.asarray(tree.parent) + 1], tree.T_parent_joint)
    tip = tips_from_frames(tree, frames)
    p = jnp.einsum("tab,tb->ta", tip[:, :3, :3], points) + tip[:, :3, 3]
    # A perturbation at joint j moves the tips below it; seen from a device on a tip, it counts
    # with the opposite sign where it moves the device, and not at all where it moves both.
    below = np.array([[j in tree.path(t) for j in range(n)] for t in range(tips)], float)
    moves_device = below[device_tip] if device_tip >= 0 else np.zeros(n)
    on = jnp.asarray(below - moves_device[None, :], p.dtype)[..., None]
    d = p[:, None, :] - F[None, :, :3, 3]  # (tips, joints, 3): from each joint's origin
    a = jnp.einsum("jab,jb->ja", F[:, :3, :3], tree.axis)
    revolute = jnp.asarray([k == "revolute" for k in tree.joint_types])[:, None]
    dtheta = on * jnp.where(revolute, jnp.cross(a[None], d), a[None])  # (tips, joints, 3)
    R = jnp.broadcast_to(F[None, :, :3, :3], (tips, n, 3, 3))
    origin = on[..., None] * jnp.concatenate([R, -jnp.einsum("tjab,tjbc->tjac", skew(d), R)], axis=-1)
    # The bending axes in the root frame (a change of the bend `b` turns the link about J_r(b) db).
    bent = jnp.einsum("jab,jbc,jkc->jka", frames[1:, :3, :3], jax.vmap(so3_right_jacobian)(bend), normals)
    dc = p[:, None, :] - frames[None, 1:, :3, 3]  # from each child link's origin
    bends = on[..., None] * jnp.cross(bent[None], dc[:, :, None, :])  # (tips, joints, 2, 3)
    # The sag moves with the loads: through them, with the geometry (exactly, not held fixed).
    d_about, d_torque = _load_columns(tree, elastic, rigid, theta0, dh, C0, couplings, q)
    through_loads = jnp.einsum("tjc,j,jg->tcg", dtheta, elastic.joint, d_about) + jnp.einsum(
        "tjkc,jk,jkg->tcg", bends, elastic.lateral, d_torque
    )
    tip_rows = [jnp.eye(tips)[:, t, None, None] * tip[:, :3, :3] for t in range(tips)]
    geometry = jnp.concatenate(
        [
            origin.transpose(0, 2, 1, 3).reshape(tips, 3, 6 * n),
            (dtheta * dh[None, :, None]).transpose(0, 2, 1),
            jnp.stack([dtheta[:, j] * dh[j] * q[k] * jnp.abs(C0[j, k]) for j, k in couplings], axis=-1)
            if couplings
            else jnp.zeros((tips, 3, 0)),
        ],
        axis=-1,
    )
    harmonics = (
        jnp.stack([dtheta * jnp.cos(theta0)[None, :, None], dtheta * jnp.sin(theta0)[None, :, None]], axis=-1)
        .transpose(0, 2, 1, 3)
        .reshape(tips, 3, 2 * n)
    )
    g = geometry.shape[-1]
    parts = [
        geometry + through_loads[..., :g],
        (dtheta * about[None, :, None]).transpose(0, 2, 1),
        (bends * torque[None, :, :, None]).transpose(0, 3, 1, 2).reshape(tips, 3, 2 * n),
        harmonics + through_loads[..., g : g + 2 * n],
        through_loads[..., g + 2 * n :],
    ]
    y = _seen(tip, p, T_dev, device_tip)
    if device_tip < 0:
        device = jnp.concatenate([jnp.broadcast_to(jnp.eye(3), (tips, 3, 3)), -skew(p)], axis=-1)
        return y, jnp.einsum(
            "ab,tbp->tap", T_dev[:3, :3], jnp.concatenate([device, *tip_rows, *parts], axis=-1)
        )
    # y = D^-1 p with D = T_root_tip T_dev exp(eta): dy = -eta_v - eta_w x y, in the device's frame.
    device = jnp.concatenate([-jnp.broadcast_to(jnp.eye(3), (tips, 3, 3)), skew(y)], axis=-1)
    R_D = (tip[device_tip] @ T_dev)[:3, :3]
    return y, jnp.concatenate(
        [device, jnp.einsum("ba,tbp->tap", R_D, jnp.concatenate([*tip_rows, *parts], axis=-1))], axis=-1
    )


def _residuals_terms(u, args) -> tuple[Float[Array, " m"], Float[Array, "m p"]]:
    free, weight, problem = args
    x = u * free
    tree, T_dev, points, elastic, harmonic = body_of(x, problem)
    pred, J = jax.vmap(
        lambda q: _sample_columns(
            tree,
            T_dev,
            points,
            elastic,
            harmonic,
            problem.tree.coupling,
            problem.couplings,
            q,
            problem.device_tip,
        )
    )(problem.q)
    part = dict((g, (a, b)) for g, a, b in problem.slices)
    (d0, d1), (o0, o1) = part["device"], part["origin"]
    scaled = x * problem.scales
    J = J.at[..., d0:d1].set(J[..., d0:d1] @ _right_jacobian(scaled[d0:d1]))
    M = jax.vmap(_right_jacobian)(scaled[o0:o1].reshape(-1, 6))
    origin = jnp.einsum("ntajk,jkl->ntajl", J[..., o0:o1].reshape(*J.shape[:3], -1, 6), M)
    J = J.at[..., o0:o1].set(origin.reshape(*J.shape[:3], o1 - o0))
    w = (weight * problem.weight)[..., None] / problem.sigma
    r = _whitened(problem, pred - problem.y) * w
    J = _whitened(problem, J) * (w[..., None] * problem.scales * free)
    return r.ravel(), J.reshape(r.size, -1)


def _residuals_primal(u, args) -> Float[Array, " m"]:
    return _residuals_autodiff(u, args)


#: Whitened residuals of the measured tips, `args = (free, weight, problem)`, with a Jacobian
#: written out (`_sample_columns`): autodiff's of the whole body made a program XLA's CPU
#: compiler could not build, and costs a pass per parameter.
residuals = _lsq.closed_form_jvp(_residuals_primal, _residuals_terms, _residuals_autodiff)


def _gauss_newton(u, free, weight, problem, steps: int):
    """`steps` Gauss-Newton steps over the free parameters (a held one: an identity row)."""

    def step(_, u):
        r, J = _residuals_terms(u, (free, weight, problem))
        H = J.T @ J + jnp.diag(1.0 - free)
        return u - jnp.linalg.solve(H, J.T @ r) * free

    return jax.lax.fori_loop(0, steps, step, u * free)


@eqx.filter_jit
def _solve(free, weight, problem, u0, options=LM):
    """optimistix's Levenberg-Marquardt from `u0` to a hundredth of each parameter's typical
    size, then `POLISH` Gauss-Newton steps for the rest (cheaper than the trust region's own
    steps, whose ratio test near the optimum weighs decreases at round-off)."""
    sol = _lsq.solve(residuals, u0 * free, (free, weight, problem), options)
    return _gauss_newton(sol.value, free, weight, problem, POLISH), sol.stats["num_steps"]


def _solve_long(free, problem, u, resumes: int = SAG_RESUMES):
    """`_solve` from `u`, resumed where it stopped at its step cap, at most `resumes` times:
    `(u, steps, converged)`. One compiled program for every solve of a tree."""
    total = 0
    for _ in range(resumes):
        u, k = _solve(free, 1.0, problem, u)
        total += int(k)
        if int(k) < LM.max_steps:
            return u, total, True
    return u, total, False


@eqx.filter_jit
def linearised(u, free, problem):
    """The whitened residuals and their Jacobian at `u`."""
    return _residuals_terms(u, (free, 1.0, problem))


def identifiable(
    problem: TreeProblem,
    layout: TreeLayout,
    candidates: np.ndarray,
    at=None,
    determined=DETERMINED,
    sag_only=None,
) -> np.ndarray:
    """Which candidate parameters the data determine (see the module docstring), greedily in
    the layout's order, from the whitened Jacobian at `at` (default: the start); a `mass`
    correction, and a parameter in `sag_only` (one the rigid body did not show), to within
    `MASS_DETERMINED` typical sizes."""
    loose = layout.family("mass") if sag_only is None else layout.family("mass") | sag_only
    within = np.where(loose, MASS_DETERMINED, determined)
    at = jnp.zeros(layout.size) if at is None else jnp.asarray(at)
    J = np.asarray(linearised(at, jnp.ones(layout.size), problem)[1])
    basis, free = np.zeros((J.shape[0], 0)), np.zeros(layout.size, bool)
    for c in (c for c in layout.order if candidates[c]):
        col = J[:, c]
        for _ in range(2):
            col = col - basis @ (basis.T @ col)
        norm = np.linalg.norm(col)
        if norm * within[c] > 1.0:  # conditional std below that many typical sizes
            free[c] = True
            basis = np.column_stack([basis, col / norm])
    return free


@dataclass(frozen=True)
class TreeFit:
    """A tree calibration: the scaled corrections `u`, which were `free`, their standard
    deviations in each parameter's unit (`std`, 0 where held), the residuals' estimated noise
    (mm per axis), the term families kept, the cross-validation's scores (mm) and the
    covariance of `u` (`cov`, zero where held)."""

    u: np.ndarray
    free: np.ndarray
    std: np.ndarray
    noise_mm: float
    steps: int
    families: tuple[str, ...] = ()
    cv_mm: dict = field(default_factory=dict)
    cov: np.ndarray | None = None

    def values(self, layout: TreeLayout) -> dict[str, float]:
        return dict(zip(layout.names, (self.u * layout.scales).tolist()))


def _fit_free(
    problem: TreeProblem, layout: TreeLayout, families, start=None, sag_geometry: bool = True
) -> tuple[np.ndarray, jax.Array, int]:
    """The identifiable parameters of the geometry and `families` (`free`), the least-squares fit
    over them from `start` (default: the nominal body) and its steps. What only the sag shows is
    nil at the start, where the compliances are: with a compliance, the parameters are chosen again
    at the fit and the fit resumed where that frees more. The `mass` corrections, or (with
    `sag_geometry`, without `mass`; the cross-validation's scores go without) geometry the rigid
    body does not show: gravity's direction against the root, joints a branch's weight bears on, an
    unmeasured head's mass; those to within a typical size, as the corrections."""
    candidates = ~layout.family(*FAMILIES) | layout.family(*families)
    free = identifiable(problem, layout, candidates)
    u0 = jnp.zeros(layout.size) if start is None else jnp.asarray(start)
    u, steps = _solve(jnp.asarray(free, jnp.float64), 1.0, problem, u0)
    # With the mass corrections the sag's lever arms and gravity's direction are theirs: geometry
    # freed beside them trades off against them (on a simulated body, 0.036 -> 0.055 mm held out).
    sag = sag_geometry and "mass" not in families
    if not set(COMPLIANT) & set(families) or not (sag or "mass" in families):
        return free, u, int(steps)
    pool = candidates if sag else free | layout.family(*families)
    again = identifiable(
        problem, layout, pool, at=u, sag_only=~layout.family(*FAMILIES) & ~free if sag else None
    )
    if not (again != free).any():
        return free, u, int(steps)
    if not sag:
        resumed, more = _solve(jnp.asarray(again, jnp.float64), 1.0, problem, u)
        if _cost(resumed, again, problem) < _cost(u, free, problem):  # never a worse fit
            free, u = again, resumed
        return free, u, int(steps + more)
    for _ in range(SAG_ROUNDS):  # the sag's geometry: again without what the fit left loose
        resumed, more, done = _solve_long(jnp.asarray(again, jnp.float64), problem, u)
        steps += more
        loose = again & ~free & (_std(resumed, again, problem) > MASS_DETERMINED)
        # Never a worse fit, one the solve left unfinished, nor one whose new parameters wander: the
        # greedy search's conditional spread can hide a marginal one of several typical sizes.
        if done and _cost(resumed, again, problem) < _cost(u, free, problem):
            if not loose.any():
                return again, resumed, int(steps)
        again = again & ~loose
        if not loose.any() or not (again != free).any():
            break
    return free, u, int(steps)


def _covariance(u, free, problem) -> tuple[np.ndarray, float]:
    """The covariance of the fit `u` (typical sizes; zero where held) and the residuals' variance
    over the noise's."""
    r, J = linearised(u, jnp.asarray(free, jnp.float64), problem)
    s2 = float(r @ r) / max(int(np.asarray(problem.weight).sum()) * 3 - int(free.sum()), 1)
    return np.asarray(_lsq.covariance(J, jnp.asarray(free), s2)[0]), s2


def _std(u, free, problem) -> np.ndarray:
    """Each parameter's standard deviation (typical sizes; 0 where held) at the fit `u`."""
    return np.sqrt(np.maximum(np.diag(_covariance(u, free, problem)[0]), 0.0))


def _cost(u, free, problem) -> float:
    r = linearised(u, jnp.asarray(free, jnp.float64), problem)[0]
    return float(r @ r)


def _tree_fit(problem, layout, free, u, steps, families, scores=None) -> TreeFit:
    cov, s2 = _covariance(u, free, problem)
    std = np.sqrt(np.maximum(np.diag(cov), 0.0)) * layout.scales
    noise_mm = 1e3 * problem.sigma * np.sqrt(s2)
    return TreeFit(
        np.asarray(u), free, std, noise_mm, steps, tuple(families), dict(scores or {}), np.asarray(cov)
    )


def prediction_jacobian(u, problem: TreeProblem, q) -> np.ndarray:
    """`(n, tips, 3, p)`: the derivatives by `u` of the points predicted at `q` (m per unit of `u`)."""
    n, tips = len(q), problem.y.shape[1]
    leaves = (jnp.asarray(q, jnp.float64), jnp.zeros((n, tips, 3)), jnp.ones((n, tips)), None)
    at = eqx.tree_at(lambda p: (p.q, p.y, p.weight, p.whiten), problem, leaves, is_leaf=lambda x: x is None)
    J = np.asarray(linearised(jnp.asarray(u), jnp.ones(len(u)), at)[1]).reshape(n, tips, 3, -1)
    return J * problem.sigma  # the rows were whitened by it


def predicted_covariance(u, cov, problem: TreeProblem, q) -> np.ndarray:
    """`(n, tips, 3, 3)` (m^2, device frame): the points predicted at `q` from `u` of covariance `cov`."""
    J = prediction_jacobian(u, problem, q)
    return np.einsum("ntap,pq,ntbq->ntab", J, cov, J)


def fit_tree(problem: TreeProblem, layout: TreeLayout, families=()) -> TreeFit:
    """Least squares over the identifiable parameters of the geometry and `families`."""
    return _tree_fit(problem, layout, *_fit_free(problem, layout, families), families)


@eqx.filter_jit
def _folds(free, weights, problem, u0):
    """Each fold's fit (a row of `weights`) and its prediction of every sample."""
    fit = lambda w: predict(_gauss_newton(u0, free, w[:, None], problem, POLISH), problem)  # noqa: E731
    return jax.vmap(fit)(weights)


def cv_error_mm(problem: TreeProblem, free: np.ndarray, whole, folds: int = 5, seed: int = 0) -> float:
    """K-fold held-out error: the mean distance (mm) between each held-out tip's measured and
    predicted point, every fold's fit one vmapped solve started from `whole`, the fit to all
    samples over the `free` parameters. Points with their own covariance count their distance
    whitened (in units of the stated noise): a camera's depth noise would drown the rest."""
    n = problem.q.shape[0]
    fold = np.random.default_rng(seed).permutation(n) % folds
    weights = np.stack([fold != k for k in range(folds)]).astype(np.float64)
    free = jnp.asarray(free, jnp.float64)
    e = np.asarray(_folds(free, jnp.asarray(weights), problem, whole)) - np.asarray(problem.y)
    if problem.whiten is not None:
        e = np.einsum("ntab,kntb->knta", np.asarray(problem.whiten), e)
    errors = []
    for k in range(folds):
        rows = fold == k
        d = np.linalg.norm(e[k][rows], axis=-1)
        errors.append(d[np.asarray(problem.weight)[rows] > 0])
    return 1e3 * float(np.concatenate(errors).mean())


def cross_validate_terms(
    problem: TreeProblem, layout: TreeLayout, families=FAMILIES, gain: float = 0.01
) -> TreeFit:
    """Forward selection of term families by K-fold held-out error: the family that lowers it
    most is kept while it lowers it by more than `gain` (relative); then the final fit."""
    fits: dict[tuple[str, ...], tuple] = {}

    def score(kept: tuple[str, ...]) -> float:
        # From the fit without the family tried last: its geometry is most of the answer.
        fits[kept] = _fit_free(problem, layout, kept, fits[kept[:-1]][1] if kept else None, False)
        return cv_error_mm(problem, *fits[kept][:2])

    kept: list[str] = []
    scores = {"geometric": score(())}
    best = scores["geometric"]
    while True:
        trial = {}
        # The mass corrections act through a compliance: tried once one is kept.
        tried = [f for f in families if f not in kept and (f != "mass" or set(COMPLIANT) & set(kept))]
        for fam in tried:
            trial[fam] = score((*kept, fam))
            scores["+".join([*kept, fam])] = trial[fam]
        if not trial:
            break
        fam = min(trial, key=trial.get)
        if trial[fam] > best * (1.0 - gain):
            break
        kept.append(fam)
        best = trial[fam]
    final = fits[tuple(kept)]
    if set(COMPLIANT) & set(kept) and "mass" not in kept:  # with the geometry only the sag shows
        final = _fit_free(problem, layout, tuple(kept), final[1])
    return _tree_fit(problem, layout, *final, kept, scores)
