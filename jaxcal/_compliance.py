"""What a non-rigid arm does to where its joints stand: gravity compliance and backlash.

The numbers both the simulator (`jaxcal.sim.arm`, which moves the true arm
with them) and the capture planner (`jaxcal.planning`, which predicts the
bias they leave in a calibration) need, on the core's conventions: the
encoder reads the motor; the link stands `backlash_offsets` from it (the
play operator of width $b_j$ along the commanded motion) and yields
`gravity_offsets` more under the gravity torque of the links it carries,
$10^{-3} c_j \\tau_j$ with $c_j$ in rad per kN m.
"""

import jax
import jax.numpy as jnp
import numpy as np

from ._pointfit import gravity_torques


def per_joint(values, joint_types) -> np.ndarray:
    """One value per joint of `joint_types` `(joints,)` from one value or a tuple whose last
    value holds for the joints after it (None: zeros); zero for prismatic joints."""
    v = np.atleast_1d(np.asarray(0.0 if values is None else values, np.float64))
    v = np.concatenate([v, np.full(max(0, len(joint_types) - v.size), v[-1])])[: len(joint_types)]
    return np.where(np.asarray(joint_types) == "revolute", v, 0.0)


def play(x_waypoints, width) -> np.ndarray:
    """The play operator's state at each waypoint `(K, joints)` of monotone legs between
    them (`x_waypoints` `(K, joints)`, `width` `(joints,)`), started centred."""
    x = np.asarray(x_waypoints, np.float64)
    half = 0.5 * np.asarray(width, np.float64)
    y = np.empty_like(x)
    y[0] = x[0]
    for k in range(1, len(x)):
        y[k] = np.clip(y[k - 1], x[k] - half, x[k] + half)
    return y


def backlash_offsets(times, x_waypoints, x_at_t, t, width) -> np.ndarray:
    """The link minus the motor side of the dead band at controller times `t (F,)` `(F, joints)`:
    the play operator of `width (joints,)` along monotone legs between waypoints `times (K,)`,
    `x_waypoints (K, joints)`, the motor side at `t` being `x_at_t (F, joints)`."""
    width = np.asarray(width, np.float64)
    x_at_t = np.asarray(x_at_t, np.float64)
    if not np.any(width):
        return np.zeros_like(x_at_t)
    times = np.asarray(times, np.float64)
    state = play(x_waypoints, width)
    t = np.clip(np.asarray(t, np.float64), times[0], times[-1])
    i = np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(times) - 2)
    half = 0.5 * width
    return np.clip(state[i], x_at_t - half, x_at_t + half) - x_at_t


def gravity_offsets(model, q, masses, coms, compliance) -> np.ndarray:
    """$10^{-3} c_j \\tau_j(q)$ (rad) at joint values `q (..., joints)` of `model` (angles minus
    zero offsets): each joint's yield under the gravity torque (N m, gravity along the base's
    $-z$) of the links it carries (`masses (joints,)`, `coms (joints, 3)` in the link frames),
    with `compliance (joints,)` in rad per kN m."""
    q = np.asarray(q, np.float64)
    m, c = jnp.asarray(masses, jnp.float64), jnp.asarray(coms, jnp.float64)
    flat = jnp.asarray(q.reshape(-1, q.shape[-1]))
    tau = np.asarray(jax.vmap(lambda qq: gravity_torques(model, qq, m, c))(flat))
    return (1e-3 * tau * np.asarray(compliance, np.float64)).reshape(q.shape)
