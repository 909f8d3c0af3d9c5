"""The joint axes the arcs measured through the target, against the nominal robot's.

Their spacing is the result's scale: a camera measures lengths in units of the target's printed
size, so a target printed larger or smaller than metadata.json says scales the whole calibrated
arm, the tool point's error with it. `axis_spacing_ratio` measures the scale against the nominal
robot's joint-axis spacing (the verdict's `board_scale` check), `reach_rms` turns a scale error
into the tool point's. Their senses follow the encoder log: `reversed_joints` finds a joint whose
measured axis points against those the robot file makes parallel to it (its log's sign, or its
URDF axis, reversed)."""

import jax
import jax.numpy as jnp
import numpy as np

from .._kinematics import PRISMATIC, forward_kinematics, joint_axes_at_zero
from .._npgeom import line_distance
from .._uncertainty import joint_travel, on_travel
from ._setup import Setup

#: How closely a real arm's joint-axis spacing agrees with its datasheet: about a millimetre over
#: its long links (a UR5's 0.8 m: 0.125 %; docs/calibrate.md), and no closer than 0.15 % (clean
#: simulated captures read 0.05-0.15 %). A reading past it is noted, were it the target's size.
REAL_ARM_SPACING_MM, REAL_ARM_SPACING_PERCENT = 1.0, 0.15
#: A spacing this far off (mm over the pairs measured) is not the arm's own: the limit is this or
#: `Limits.board_scale_percent`, the larger (a SCARA's one 325 mm pair: 0.77 %).
SPACING_LIMIT_MM = 2.5


def spacing_limits(nominal_m: float, limit_percent: float) -> tuple[float, float]:
    """`(limit, noted)`, %: the `board_scale` check's limit and the reading past which it notes the
    tool point's move, for axes `nominal_m` apart in all (the pairs' nominal sum)."""
    return (
        max(limit_percent, 0.1 * SPACING_LIMIT_MM / nominal_m),
        max(REAL_ARM_SPACING_PERCENT, 0.1 * REAL_ARM_SPACING_MM / nominal_m),
    )


def axis_spacing_ratio(setup: Setup, arcs) -> tuple[float, list[tuple[str, float, float]]]:
    """How far apart consecutive joint axes are measured, over the nominal
    robot's spacing: the ratio of the sums over pairs at least 5 cm apart (near
    parallel pairs by the distance of one axis point from the other line,
    skew ones by the common normal; the long links weigh most, as a millimetre
    of a real arm's own deviation is least of them), and the pairs `(joints,
    measured, nominal)` (m)."""
    nominal = setup.nominal
    p_nom, d_nom = joint_axes_at_zero(nominal)
    p_meas, d_meas = np.asarray(arcs.point), np.asarray(arcs.direction)
    names = nominal.joint_names
    pairs = []
    for i in range(nominal.num_joints - 1):
        if not np.all(np.isfinite(p_meas[i : i + 2])):  # a prismatic joint's line has no position
            continue
        nom = float(line_distance(p_nom[i], d_nom[i], p_nom[i + 1], d_nom[i + 1]))
        if nom < 0.05:
            continue
        if abs(float(np.dot(d_meas[i], d_meas[i + 1]))) > np.cos(np.radians(5.0)):
            dp = p_meas[i + 1] - p_meas[i]
            meas = float(np.linalg.norm(dp - np.dot(dp, d_meas[i]) * d_meas[i]))
        else:
            meas = float(line_distance(p_meas[i], d_meas[i], p_meas[i + 1], d_meas[i + 1]))
        pairs.append((f"{names[i]}/{names[i + 1]}", meas, nom))
    if not pairs:
        return float("nan"), pairs
    return float(sum(m for _, m, _ in pairs) / sum(n for _, _, n in pairs)), pairs


def reach_rms(model, limits=None, T_cam_base=None, n: int = 256) -> float:
    """RMS distance (m) of the flange from the base, or from a fixed camera at `T_cam_base`, over
    `n` random configurations (seed 0; a prismatic joint within its URDF `limits`): how far a
    scale error of 1 moves the tool point. A mis-sized target scales the scene about the camera,
    so the tool point seen from the camera (as the claimed uncertainty measures it) moves by the
    scale error times its distance from the camera."""
    q = jax.random.uniform(jax.random.PRNGKey(0), (n, model.num_joints), minval=-jnp.pi, maxval=jnp.pi)
    q = on_travel(model, q, joint_travel(model, limits))
    p = np.asarray(jax.vmap(lambda qq: forward_kinematics(model, qq)[-1][:3, 3])(q))
    if T_cam_base is not None:
        T = np.asarray(T_cam_base, np.float64)
        p = p @ T[:3, :3].T + T[:3, 3]
    return float(np.sqrt(np.mean(np.sum(p**2, axis=1))))


def reversed_joints(setup: Setup, arcs) -> list[tuple[int, list[int]]]:
    """The joints whose measured axis (`arcs.direction`, its sense the encoder's) points against
    every other joint of its group of consecutive joints the nominal robot makes parallel (three
    or more: with two, either could be the one), where the nominal robot has them agree:
    `(joint, the group's others)` each."""
    _, d_nom = joint_axes_at_zero(setup.nominal)
    d_meas = np.asarray(arcs.direction, np.float64)
    revolute = np.asarray(setup.nominal.joint_types) != PRISMATIC  # a slide's line fit: left out
    parallel = [
        bool(revolute[i] and revolute[i + 1])
        and abs(float(np.dot(d_nom[i], d_nom[i + 1]))) > np.cos(np.radians(5.0))
        for i in range(len(d_nom) - 1)
    ]
    groups, run = [], [0]
    for i, p in enumerate(parallel):
        if p:
            run.append(i + 1)
        else:
            groups.append(run)
            run = [i + 1]
    groups.append(run)
    out = []
    for group in (g for g in groups if len(g) >= 3 and np.all(np.isfinite(d_meas[g]))):
        for j in group:
            others = [k for k in group if k != j]
            against = [
                np.sign(np.dot(d_meas[j], d_meas[k])) != np.sign(np.dot(d_nom[j], d_nom[k])) for k in others
            ]
            if all(against):
                out.append((j, others))
    return out
