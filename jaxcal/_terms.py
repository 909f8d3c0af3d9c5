"""Non-geometric joint terms: the one joint-angle correction every observation of the arm goes through.

A real arm's joint does not stand where its encoder and a rigid model put it.
Whatever observes the arm (a tracker's point, a camera's corners, a PnP pose),
joint $j$ stands at

$$ \\theta_j = \\rho_j q_j + \\delta_j + \\Delta_j, \\qquad
   \\Delta_j = \\sum_k e_{j,k}\\, b_{j,k}(q, a), $$

with $q$ the commanded joint positions, $\\rho$ the rate, $\\delta$ the zero offset
and $\\Delta$ linear in a few coefficients $e$ per joint over a basis $b$ of the
pose and of how it was approached. The families (`TERMS`, names as
`{joint}.{family}.{coefficient}`, `names`):

- `compliance` (`rad_per_kNm`): $b = \\tau_j / (1\\,\\mathrm{kN\\,m})$, the torque joint $j$'s
  transmission carries: gravity's about its axis (`gravity_torques`) from the links'
  masses and centres of mass in the robot file plus the payload the capture states
  (`with_payload`: the plate's or tool's mass and centre on the flange), and, where
  the motion observed can tell it (a camera capture filming a joint at two speeds,
  `jaxcal.stages._terms.two_speeds`), minus the torque that accelerates the links
  beyond the joint (`transmission_torques`: `inertial_torques`
  of the log's velocity and acceleration, `log_motion`, with the links' inertia
  tensors and the payload's, `with_payload_tensors`). The joint yields $c_j \\tau_j$:
  it sags where gravity pulls, lags its motor while the arm speeds up and leads it
  while it slows down; $e = c_j$, a physical compliance, is $\\ge 0$.
- `backlash` (`approach_rad`, `load_rad`): lost motion in the transmission. The
  link follows the motor through a dead band: where nothing preloads the joint,
  the link lags the motor's last motion, against the flank the motor pushed
  it with (`approach`, $a_j \\in [-1, 1]$: $+1$ after a move to larger angles, $-1$
  after one to smaller, 0 before the joint first moves); a joint that a torque
  preloads rests against the flank the torque pushes it to, whichever way it came
  (`preload`, $\\tanh(\\tau_j / \\tau_p)$, $\\tau_p$ = `PRELOAD_NM`, for still samples;
  along a logged motion the flank of the last torque beyond $\\tau_p$, `relay`: a
  moving arm's inertial torques press a joint gravity leaves free). The first
  coefficient is minus half the lost motion of the approach rule ($\\le 0$: the link
  lags), the second half that of the load rule ($\\ge 0$); a joint follows one rule
  or the other, and the fit finds which from the data.
- `harmonic1`, `harmonic2` (`sin1`, `cos1`, `sin2`, `cos2`): $\\sin(k q_j), \\cos(k q_j)$, a
  transmission's once- and twice-per-turn error.

The basis is evaluated on the nominal model at the commanded positions (the
corrections are milliradians: first order), so $\\Delta$ is linear in $e$ and
its Jacobian is the joint angle's column times the basis. `term_basis` is pure
and jittable; `approach` is NumPy (a play operator along the commanded motion:
a tracker's sample sequence, a camera capture's encoder log).

`jaxcal._pointfit` (stop-and-shoot samples) and `jaxcal._reprojection` (every
corner) add `correction` to their joint angles; `jaxcal._correction.ParameterLayout`
lays the coefficients out (`terms` group); `jaxcal.stages._terms` selects them by
cross-validation; `jaxcal.compensation` applies them on the robot side.
"""

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._kinematics import KinematicModel, forward_kinematics

#: Non-geometric term families and their number of coefficients per joint (the vocabulary
#: `--terms` takes for every kind of capture).
TERMS = {"compliance": 1, "backlash": 2, "harmonic1": 2, "harmonic2": 2}
#: Each family's coefficient names (`{joint}.{family}.{name}`), in basis order.
SUFFIXES = {
    "compliance": ("rad_per_kNm",),
    "backlash": ("approach_rad", "load_rad"),
    "harmonic1": ("sin1", "cos1"),
    "harmonic2": ("sin2", "cos2"),
}
#: The sign a physical coefficient has (`+1`: >= 0, `-1`: <= 0, 0: either), per family, in basis order:
#: a joint yields along the gravity torque; lost motion lags the motor; a preloaded joint rests
#: against gravity's flank.
SIGNS = {"compliance": (1,), "backlash": (-1, 1), "harmonic1": (0, 0), "harmonic2": (0, 0)}
#: Standard gravity (m/s^2), along the base frame's -z.
GRAVITY = 9.80665
#: The gravity torque (N m) above which a joint counts as preloaded against one flank (the basis
#: `tanh(tau / PRELOAD_NM)`): about a gear's friction torque, a few percent of a wrist's load.
PRELOAD_NM = 1.0
#: A coefficient whose basis has an RMS over a capture's poses under this is not a candidate of a
#: fit: the joint carries no gravity load there (compliance, in kN m; e.g. a vertical axis).
BASIS_FLOOR = 1e-6
#: The play of the approach rule (rad): a joint's motor must move this far before its link turns
#: to the other flank. Far above an encoder's noise (micro-radians), below any lost motion worth
#: modelling (an arc minute is 2.9e-4 rad); only a reversal's first hundred micro-radians see it.
APPROACH_WIDTH_RAD = 1e-4
#: The span of the encoder log (s) each velocity and acceleration is fitted over (`log_motion`):
#: a quadratic through ten 500 Hz rows, short against a sweep's speed-up (a tenth of a second
#: and more), long enough to average an encoder's quantisation.
MOTION_WINDOW_S = 0.02


#: A non-geometric coefficient stays free only when the data pin its effect on the joint
#: angle (its std times the RMS of its basis over the samples) to this (rad): a
#: transmission's error or a joint's sag is a fraction of a milliradian, so a term known
#: only to more than that is not identified (e.g. wrist 3's, when the point sits on its axis).
#: The calibrations hold the others at zero (`jaxcal.stages._terms`, `_points`), and a plan's
#: prediction counts them so (`jaxcal.planning`).
TERM_STD_RAD = 1e-3


def check_terms(terms) -> tuple[str, ...]:
    """`terms` as a tuple of known family names (a `ValueError` naming the unknown ones)."""
    terms = tuple(terms)
    unknown = [t for t in terms if t not in TERMS]
    if unknown:
        raise ValueError(f"unknown non-geometric terms {unknown}; known terms are {list(TERMS)}")
    if len(set(terms)) != len(terms):
        raise ValueError(f"non-geometric terms named twice: {list(terms)}")
    return terms


def per_joint(terms: tuple[str, ...]) -> int:
    """Coefficients per joint of the families `terms`."""
    return sum(TERMS[t] for t in terms)


def names(terms: tuple[str, ...], joints) -> list[str]:
    """The coefficients' names in flattened order: family-major, joint-major within a family."""
    return [f"{j}.{t}.{s}" for t in terms for j in joints for s in SUFFIXES[t]]


def signs(terms: tuple[str, ...], num_joints: int) -> np.ndarray:
    """Each coefficient's physical sign (`SIGNS`) in flattened order."""
    return np.concatenate([np.tile(SIGNS[t], num_joints) for t in terms] or [np.zeros(0)]).astype(int)


def family_of(terms: tuple[str, ...], num_joints: int) -> np.ndarray:
    """Each coefficient's family (index into `terms`) in flattened order."""
    return np.concatenate([np.full(num_joints * TERMS[t], i) for i, t in enumerate(terms)] or [np.zeros(0)])


def column_map(terms: tuple[str, ...], n: int) -> tuple[np.ndarray, np.ndarray]:
    """Per flattened coefficient (`names` order) its joint and its column in the per-joint basis."""
    joint, col, start = [], [], 0
    for t in terms:
        m = TERMS[t]
        joint += [j for j in range(n) for _ in range(m)]
        col += [start + k for _ in range(n) for k in range(m)]
        start += m
    return np.array(joint, int), np.array(col, int)


def coefficients(terms: tuple[str, ...], x: Float[Array, " k"], num_joints: int) -> Float[Array, "joints m"]:
    """The flattened coefficients `x` (`names` order) as `(joints, per_joint(terms))`, the
    families side by side in basis order."""
    blocks, start = [], 0
    for t in terms:
        m = TERMS[t]
        blocks.append(x[start : start + num_joints * m].reshape(num_joints, m))
        start += num_joints * m
    return jnp.concatenate(blocks, axis=1) if blocks else jnp.zeros((num_joints, 0), x.dtype)


def flatten(terms: tuple[str, ...], e: np.ndarray) -> np.ndarray:
    """`coefficients`' inverse (NumPy): `(joints, m)` -> the flattened vector."""
    e = np.asarray(e)
    out, start = [], 0
    for t in terms:
        m = TERMS[t]
        out.append(e[:, start : start + m].reshape(-1))
        start += m
    return np.concatenate(out) if out else np.zeros(0)


def correction(
    terms: tuple[str, ...], x: Float[Array, " k"], basis: Float[Array, "... joints m"]
) -> Float[Array, "... joints"]:
    """$\\Delta_j = \\sum_k e_{j,k} b_{j,k}$ (rad): the joint-angle corrections of the
    coefficients `x` (flattened) over `basis` (`term_basis`)."""
    e = coefficients(terms, x, basis.shape[-2])
    return jnp.sum(e * basis, axis=-1)


def gravity_torques(model: KinematicModel, q, masses, coms) -> Float[Array, " joints"]:
    """$\\tau_j = z_j \\cdot \\sum_{k \\ge j} (c_k - o_j) \\times m_k g$ (N m): the torque
    gravity (along the base's $-z$) exerts about each joint's axis at `q`."""
    T = forward_kinematics(model, q)
    links = T[1:-1]  # each joint's child link
    c = jnp.einsum("kab,kb->ka", links[:, :3, :3], coms) + links[:, :3, 3]
    z = jnp.einsum("jab,jb->ja", links[:, :3, :3], model.axis)
    o = links[:, :3, 3]
    f = masses[:, None] * jnp.array([0.0, 0.0, -GRAVITY])
    n = model.num_joints
    down = jnp.arange(n)[None, :] >= jnp.arange(n)[:, None]  # (j, k): link k rides on joint j
    moment = jnp.cross(c[None, :, :] - o[:, None, :], f[None, :, :])  # (j, k, 3)
    return jnp.einsum("ja,jka,jk->j", z, moment, down.astype(q.dtype))


def inertial_torques(model: KinematicModel, q, qd, qdd, masses, coms, tensors) -> Float[Array, " joints"]:
    """$\\tau^{in} = \\frac{d}{dt}\\frac{\\partial T}{\\partial \\dot q} - \\frac{\\partial T}{\\partial q}
    = M(q)\\ddot q + C(q, \\dot q)\\dot q$ (N m, or N on a prismatic joint): the torques
    the joints carry to move the links at `q` with velocity `qd` and acceleration `qdd`,
    gravity left out (`gravity_torques`), from the kinetic energy $T$ of the links'
    `masses`, centres of mass `coms` and inertia tensors about them `tensors (joints, 3,
    3)`, each in its link's frame (Lagrange's equations, by automatic differentiation)."""

    def kinetic(q, qd):
        def frames(q):
            links = forward_kinematics(model, q)[1:-1]
            R = links[:, :3, :3]
            return R, jnp.einsum("kab,kb->ka", R, coms) + links[:, :3, 3]

        (R, _), (R_dot, v) = jax.jvp(frames, (q,), (qd,))
        W = jnp.einsum("kab,kcb->kac", R_dot, R)  # the links' angular velocities, skew
        w = jnp.stack([W[:, 2, 1], W[:, 0, 2], W[:, 1, 0]], axis=-1)
        w_link = jnp.einsum("kba,kb->ka", R, w)
        spin = jnp.einsum("ka,kab,kb->k", w_link, tensors, w_link)
        return 0.5 * jnp.sum(masses * jnp.sum(v * v, axis=-1) + spin)

    momentum = jax.grad(kinetic, argnums=1)
    _, rate = jax.jvp(momentum, (q, qd), (qd, qdd))
    return rate - jax.grad(kinetic, argnums=0)(q, qd)


def transmission_torques(model: KinematicModel, q, qd, qdd, masses, coms, tensors) -> Float[Array, " joints"]:
    """The torques the joints' transmissions carry at `q` moving with `qd`, `qdd` (N m):
    gravity's (`gravity_torques`) less the inertial torques (`inertial_torques`), so that a
    joint yields $c_j \\tau_j$ along them (the links' `tensors` about their centres of mass)."""
    return gravity_torques(model, q, masses, coms) - inertial_torques(
        model, q, qd, qdd, masses, coms, tensors
    )


def relay(torque, threshold: float = PRELOAD_NM) -> np.ndarray:
    """The load rule's flank along a motion's rows of transmission torques `torque (T, joints)`
    (NumPy): the sign of the last torque beyond `threshold` in size (a torque that presses a
    joint across its dead band; smaller ones leave it where it was), 0 before the first."""
    tau = np.asarray(torque, np.float64)
    out = np.zeros_like(tau)
    state = np.zeros(tau.shape[1:])
    for k in range(len(tau)):
        state = np.where(np.abs(tau[k]) > threshold, np.sign(tau[k]), state)
        out[k] = state
    return out


def with_payload(model: KinematicModel, masses, coms, mass_kg: float, com_flange_m) -> tuple:
    """The links' masses and centres of mass with a payload on the flange (the plate's or
    tool's `mass_kg` at `com_flange_m`, flange frame) lumped into the last link (NumPy)."""
    masses, coms = np.array(masses, np.float64), np.array(coms, np.float64)
    if not mass_kg:
        return masses, coms
    T = np.asarray(model.T_last_flange, np.float64)
    c = T[:3, :3] @ np.asarray(com_flange_m, np.float64) + T[:3, 3]
    total = masses[-1] + mass_kg
    coms[-1] = (masses[-1] * coms[-1] + mass_kg * c) / total
    masses[-1] = total
    return masses, coms


def with_payload_tensors(
    model: KinematicModel, masses, coms, tensors, mass_kg: float, com_flange_m, inertia_flange=None
) -> np.ndarray:
    """The links' inertia tensors about their centres of mass with the payload of `with_payload`
    lumped into the last link (the parallel-axis rule; NumPy): its own inertia about its centre
    `inertia_flange` (3x3, the flange's axes), or a point mass where None."""
    tensors = np.array(tensors, np.float64)
    if not mass_kg:
        return tensors
    T = np.asarray(model.T_last_flange, np.float64)
    if inertia_flange is not None:
        tensors[-1] = tensors[-1] + T[:3, :3] @ np.asarray(inertia_flange, np.float64) @ T[:3, :3].T
    p = T[:3, :3] @ np.asarray(com_flange_m, np.float64) + T[:3, 3]
    m0, c0 = float(masses[-1]), np.asarray(coms[-1], np.float64)
    c = (m0 * c0 + mass_kg * p) / (m0 + mass_kg)

    def shifted(m, d):
        return m * (d @ d * np.eye(3) - np.outer(d, d))

    tensors[-1] = tensors[-1] + shifted(m0, c0 - c) + shifted(mass_kg, p - c)
    return tensors


def log_motion(t_log, q_log, t, window_s: float = MOTION_WINDOW_S) -> tuple[np.ndarray, np.ndarray]:
    """The velocity and acceleration of the motion logged as `q_log (T, joints)` at times
    `t_log (T,)`, at times `t (N,)` (NumPy, `(N, joints)` each): at every log row a quadratic
    fitted to the rows within `window_s` around it (at least one on each side), its slope
    and twice its curvature, interpolated linearly between the rows (times outside the
    log: its ends)."""
    t_log, q_log = np.asarray(t_log, np.float64), np.asarray(q_log, np.float64)
    t = np.asarray(t, np.float64)
    n = len(t_log)
    if n < 3:
        return np.zeros((len(t), q_log.shape[1])), np.zeros((len(t), q_log.shape[1]))
    h = max(1, int(round(0.5 * window_s / float(np.median(np.diff(t_log))))))
    idx = np.clip(np.arange(n)[:, None] + np.arange(-h, h + 1)[None, :], 0, n - 1)  # (T, 2h+1)
    tau = t_log[idx] - t_log[:, None]
    V = np.stack([np.ones_like(tau), tau, tau * tau], axis=-1)  # (T, 2h+1, 3)
    coef = np.linalg.solve(np.einsum("tka,tkb->tab", V, V), np.einsum("tka,tkj->taj", V, q_log[idx]))
    qd, qdd = coef[:, 1], 2.0 * coef[:, 2]

    def at(x):
        return np.stack([np.interp(t, t_log, x[:, j]) for j in range(x.shape[1])], axis=-1)

    return at(qd), at(qdd)


def preload(tau: Float[Array, "... joints"]) -> Float[Array, "... joints"]:
    """The flank gravity pushes each joint to: $\\tanh(\\tau / \\tau_p)$ (`PRELOAD_NM`)."""
    return jnp.tanh(tau / PRELOAD_NM)


def term_basis(
    terms: tuple[str, ...], model: KinematicModel, q, masses, coms, approach=None, torque=None, load=None
) -> Float[Array, "samples joints k"]:
    """The terms' basis at every sample's commanded pose `q` `(samples, joints)`, on the
    nominal `model` (`masses`, `coms`: the links', the payload lumped in, `with_payload`).
    `approach` `(samples, joints)`: the approach rule's flank (`approach`; zero if None);
    `torque`: the transmissions' torques of a logged motion (`transmission_torques`; None:
    the arm stands still, gravity's at `q`); `load`: the load rule's flank along that motion
    (`relay`; None: `preload` of the torque)."""
    need_tau = any(t in ("compliance", "backlash") for t in terms)
    if need_tau and torque is None:
        torque = jax.vmap(gravity_torques, in_axes=(None, 0, None, None))(model, q, masses, coms)
    cols = []
    for t in terms:
        if t == "compliance":
            cols.append(jnp.asarray(torque, q.dtype)[..., None] / 1000.0)
        elif t == "backlash":
            a = jnp.zeros_like(q) if approach is None else jnp.asarray(approach, q.dtype)
            flank = preload(jnp.asarray(torque, q.dtype)) if load is None else jnp.asarray(load, q.dtype)
            cols += [a[..., None], flank[..., None]]
        else:
            k = 1.0 if t == "harmonic1" else 2.0
            cols += [jnp.sin(k * q)[..., None], jnp.cos(k * q)[..., None]]
    return jnp.concatenate(cols, axis=-1) if cols else jnp.zeros((*q.shape, 0), q.dtype)


def play_states(q_path, width: float = APPROACH_WIDTH_RAD) -> np.ndarray:
    """The play operator's state along a sequence of commanded positions `q_path (K, joints)`
    (NumPy): $y_k = \\mathrm{clip}(y_{k-1}, q_k - w/2, q_k + w/2)$, started at $y_0 = q_0$."""
    q = np.asarray(q_path, np.float64)
    half = 0.5 * width
    y = np.empty_like(q)
    if len(q) == 0:
        return y
    y[0] = q[0]
    for k in range(1, len(q)):
        y[k] = np.clip(y[k - 1], q[k] - half, q[k] + half)
    return y


def approach(q_path, width: float = APPROACH_WIDTH_RAD) -> np.ndarray:
    """The approach rule's flank at every position of a motion `q_path (K, joints)` (NumPy):
    $a = (q - y) / (w/2) \\in [-1, 1]$ with $y$ the play operator's state (`play_states`): $+1$
    once the joint has moved `width` towards larger angles since its last reversal, $-1$
    towards smaller, 0 before it first moves."""
    q = np.asarray(q_path, np.float64)
    return (q - play_states(q, width)) / (0.5 * width)


def approach_at(t_log, q_log, t, width: float = APPROACH_WIDTH_RAD) -> np.ndarray:
    """`approach` of the motion logged as `q_log (T, joints)` at times `t_log (T,)`, at times
    `t (...)`: the log interpolated linearly there and the play state carried from the last
    log row before, `t.shape + (joints,)` (times outside the log: its ends)."""
    t_log, q_log = np.asarray(t_log, np.float64), np.asarray(q_log, np.float64)
    t = np.clip(np.asarray(t, np.float64), t_log[0], t_log[-1])
    y = play_states(q_log, width)
    q = np.stack([np.interp(t, t_log, q_log[:, j]) for j in range(q_log.shape[1])], axis=-1)
    i = np.clip(np.searchsorted(t_log, t, side="right") - 1, 0, len(t_log) - 1)
    half = 0.5 * width
    return (q - np.clip(y[i], q - half, q + half)) / half


def _corrections_of(terms_x, model, q, a, masses, coms, terms: tuple[str, ...]):
    return correction(terms, terms_x, term_basis(terms, model, q, masses, coms, a))


_corrections = jax.jit(_corrections_of, static_argnames="terms")


def compensate(
    terms: tuple[str, ...], x, model: KinematicModel, masses, coms, q_target, flank=None, rate=None
) -> np.ndarray:
    """The commanded joints that put each joint where the rigid model's `q_target` does.

    The arm stands at $\\rho q + \\delta + \\Delta(q, a)$ where the rigid model puts it at
    $\\rho q + \\delta$ (`correction`), so the command $q_c$ for a target $q_t$ solves
    $q_c = q_t - \\Delta(q_c, a) / \\rho$: a fixed point, found by iteration (the terms are
    milliradians and smooth in $q$: each step shrinks the error by their slope, 1e-3).

    **Arguments:** the kept families `terms` and coefficients `x` (`names` order); the
    nominal `model` and the links' `masses`, `coms` (payload included) the basis is
    evaluated on; `q_target` `(..., joints)`; `flank` `(..., joints)`: the flank each
    joint comes from (+1 from smaller angles, -1 from larger, 0 unknown; default: along
    the rows of a path `(N, joints)` by `approach`, 0 for one pose); `rate` `(joints,)`:
    joint turn per commanded turn (default one).

    **Returns:** the commanded joints, shaped as `q_target` (NumPy).
    """
    q_t = np.asarray(q_target, np.float64)
    flat = q_t.reshape(-1, q_t.shape[-1])
    if flank is None:
        a = approach(flat) if q_t.ndim > 1 else np.zeros_like(flat)
    else:
        a = np.broadcast_to(np.asarray(flank, np.float64), q_t.shape).reshape(flat.shape)
    r = np.ones(flat.shape[1]) if rate is None else np.asarray(rate, np.float64)
    x = jnp.asarray(x, jnp.float64)
    m, c = jnp.asarray(masses, jnp.float64), jnp.asarray(coms, jnp.float64)
    q_c = flat.copy()
    for _ in range(COMPENSATION_STEPS):
        delta = np.asarray(_corrections(x, model, jnp.asarray(q_c), jnp.asarray(a), m, c, terms=tuple(terms)))
        q_c = flat - delta / r
    return q_c.reshape(q_t.shape)


#: Fixed-point steps of `compensate` (each shrinks the error by the terms' slope in q, ~1e-3).
COMPENSATION_STEPS = 4
