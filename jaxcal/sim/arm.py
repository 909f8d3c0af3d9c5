"""Arm models for the simulator: gravity compliance, backlash, encoder quantisation and latency.

An `ArmModel` turns the controller's commanded motion into where the joints
really stand (what the cameras film) and what the encoders log. With the
core's conventions (`jaxcal.sim.motion`): the motor follows the command,
$m = q\\,\\rho_{nom}$, and the encoder reads $m$; the rigid joint would stand at
$\\theta_0 = q\\,\\rho_{nom}/\\rho_{true} + \\delta$. Between motor and link:

- **backlash** (lost motion, `backlash_deg` $b_j$ per joint): the link follows
  the motor through a dead band of width $b_j$, the play (hysteresis) operator
  $\\theta_b(t) = \\mathrm{clip}(\\theta_b(t^-),\\ \\theta_0(t) - b/2,\\ \\theta_0(t) + b/2)$,
  centred at the start. While a joint turns one way its link lags the encoder
  by $b/2$; after a reversal it stands still until the motor has crossed the
  band. The commanded legs of a `Trajectory` are monotone (smooth steps between
  waypoints), so the operator is exact from its state at the waypoints:
  $\\theta_b(t) = \\mathrm{clip}(\\theta_b(t_i),\\ \\theta_0(t) - b/2,\\ \\theta_0(t) + b/2)$ on
  the leg from waypoint $t_i$. A gear that gravity preloads stays against
  one flank whichever way it turns; that is not modelled here, so the lost
  motion of loaded joints (a shoulder, an elbow) is a pessimistic case.
- **gravity compliance** (`compliance`, rad per kN m per joint, $c_j$): the
  joint yields by $c_j\\,\\tau_j$, with $\\tau_j$ the gravity torque about its
  axis from the robot file's link masses and centres of mass
  (`jaxcal._pointfit.gravity_torques`, gravity along the base's $-z$),
  evaluated at the unloaded angles (first order: deflections are milliradians):
  $\\theta = \\theta_b + 10^{-3} c_j\\,\\tau_j(\\theta_b)$.

With `dynamics` (a `Dynamics`, the `physics` preset), none of these formulas: MuJoCo's
physics moves the arm (`jaxcal.sim.physics`): servoed motors behind compliant
transmissions with a dead band, the links' inertias from the robot file and the
plate's mass under gravity, stepped through the commanded motion, so that the
links lag while they accelerate, ring and sag where they stop, and the encoders
read the motors. `compliance` and `backlash_deg` are then the transmissions'
stiffness ($1/c_j$) and dead band.

The encoders log the motor angle `counts_per_rev` counts per motor turn
(quantised, with the simulation's noise in counts), and stamp each reading
`latency_s` late: the reading stamped $t$ is the motor's angle at
$t - $`latency_s` (the first one held at the start).

The presets (`ARM_PRESETS`, `arm_model(name)`), typical values rather than one
product's measurements:

- `ideal`: a rigid arm with fine, prompt encoders (2^17 counts per motor turn,
  no latency): the simulator's historical arm, for the tests' exact truths.
- `realistic`: a six-axis arm of the UR5e's class with strain-wave gears:
  compliance 1/32 rad per kN m at the base, shoulder and elbow (the shoulder's
  32 kN m/rad measured on real laser-tracker data of a UR5, see the real-robot
  issue), 1/5 at the wrists (smaller gears); lost motion of 1 arcmin per joint
  (the strain-wave gear makers' catalogue bound); 2^17 counts per motor turn;
  the joint states stamped 2 ms late (a controller's sample published over the
  network, stamped on arrival).
- `physics`: the `realistic` arm's compliance, lost motion, encoder and latency,
  simulated by MuJoCo (`Dynamics()`'s servo, rotors, friction and plate) instead of
  by the formulas above: an arm the estimator's terms were not written from.
"""

import math
from dataclasses import dataclass, fields, replace

import jax
import jax.numpy as jnp
import numpy as np

from .._compliance import play as play
from .._pointfit import gravity_torques
from ..records_capture import ArmFigures
from .motion import EncoderModel, Trajectory


def _per_joint(value, joint_types) -> np.ndarray:
    """`value` (one number, or a tuple whose last entry holds for the joints after it) per joint
    of `joint_types`, `(joints,)`, zeros for prismatic joints (and for None)."""
    v = np.atleast_1d(np.asarray(0.0 if value is None else value, np.float64))
    v = np.concatenate([v, np.full(max(0, len(joint_types) - v.size), v[-1])])[: len(joint_types)]
    return np.where(np.asarray(joint_types) == "revolute", v, 0.0)


def _check_values(owner: str, key: str, value, joints: int | None) -> None:
    """One value, or up to one per joint, finite and >= 0 (a `ValueError` naming `owner`'s `key`)."""
    v = np.atleast_1d(np.asarray(value, np.float64))
    if v.ndim != 1 or v.size == 0 or (joints is not None and v.size > joints):
        raise ValueError(f"{owner}: {key} needs one value or up to one per joint ({joints}), got {value}")
    if not (np.all(np.isfinite(v)) and np.all(v >= 0.0)):
        raise ValueError(f"{owner}: {key} must be finite and >= 0, got {value}")


@dataclass(frozen=True)
class Dynamics:
    """How `jaxcal.sim.physics` drives the arm (MuJoCo); typical values of a six-axis cobot of
    the UR5e's class, not one product's measurements.

    Each joint is a motor-side rotor (a hinge with the reflected rotor inertia `armature_kgm2`,
    kg m^2 at the joint, and the gear's Coulomb friction `gear_friction_nm`, N m) coupled to its
    link by the transmission: a spring of the arm's stiffness $1/c_j$ with a dead band of the
    arm's lost motion, damped to `transmission_damping` of its critical damping against the
    link's inertia; the link's bearing has its own friction `bearing_friction_nm`. A position
    servo (MuJoCo's position actuator: $\\tau = k_p(u - \\theta_m) - k_v\\dot\\theta_m$) drives
    each rotor at `servo_hz` natural frequency and `servo_damping` damping ratio against the
    joint's inertia at the zero configuration, with the controller's velocity and gravity feed-forward (the
    command's velocity, the links' gravity and Coriolis torque at the joint). Each target plate
    on a link weighs `payload_kg` at its centre. `timestep_s`: MuJoCo's step (implicit-fast);
    `settle_s`: the arm held at the motion's first pose before it starts. Per-joint values take
    one number or a tuple whose last value holds for the joints after it.
    """

    servo_hz: float = 10.0
    servo_damping: float = 0.8
    armature_kgm2: float | tuple[float, ...] = (1.0, 1.0, 0.5, 0.1)
    gear_friction_nm: float | tuple[float, ...] = (8.0, 8.0, 5.0, 1.5)
    bearing_friction_nm: float | tuple[float, ...] = (0.5, 0.5, 0.3, 0.1)
    transmission_damping: float = 0.15
    payload_kg: float = 0.35
    timestep_s: float = 2e-4
    settle_s: float = 1.0

    def check(self, joints: int | None = None) -> None:
        for key in ("armature_kgm2", "gear_friction_nm", "bearing_friction_nm"):
            _check_values("arm dynamics", key, getattr(self, key), joints)
        for key in ("servo_hz", "servo_damping", "transmission_damping", "payload_kg", "settle_s"):
            value = getattr(self, key)
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"arm dynamics: {key} must be finite and >= 0, got {value}")
        if not (self.servo_hz > 0.0 and 0.0 < self.timestep_s <= 1e-3):
            raise ValueError(
                f"arm dynamics: servo_hz > 0 and a timestep in (0, 1 ms] are needed, got {self.servo_hz}, "
                f"{self.timestep_s}"
            )
        if not np.all(np.atleast_1d(self.armature_kgm2) > 0.0):
            raise ValueError(f"arm dynamics: armature_kgm2 must be > 0, got {self.armature_kgm2}")

    def per_joint(self, key: str, joint_types) -> np.ndarray:
        """`key`'s values for joints of `joint_types` (the last value repeated; a prismatic
        joint's armature in kg and its frictions in N)."""
        v = np.atleast_1d(np.asarray(getattr(self, key), np.float64))
        return np.concatenate([v, np.full(max(0, len(joint_types) - v.size), v[-1])])[: len(joint_types)]


@dataclass(frozen=True)
class ArmModel:
    """How the simulated arm deviates from a rigid one with perfect encoders (see the module docstring).

    `compliance`: rad per kN m of gravity torque (None: rigid).
    `backlash_deg`: lost motion per joint (deg). Both take one value for
    every joint or a tuple, whose last value holds for the joints after it (a
    preset's wrists). Prismatic joints neither yield nor lose motion.
    `counts_per_rev`: motor encoder counts per motor turn. `latency_s`: how
    late the encoder readings are stamped (s). `dynamics`: MuJoCo's physics
    moves the arm (`jaxcal.sim.physics`), `compliance` and `backlash_deg` its
    transmissions' (None: the formulas of the module docstring).
    """

    name: str = "ideal"
    compliance: float | tuple[float, ...] | None = None
    backlash_deg: float | tuple[float, ...] = 0.0
    counts_per_rev: int = 2**17
    latency_s: float = 0.0
    dynamics: Dynamics | None = None

    def check(self, joints: int | None = None) -> None:
        for key in ("compliance", "backlash_deg"):
            value = getattr(self, key)
            if value is not None:
                _check_values(f"arm {self.name!r}", key, value, joints)
        if self.dynamics is not None:
            self.dynamics.check(joints)
        if int(self.counts_per_rev) != self.counts_per_rev or self.counts_per_rev < 4:
            raise ValueError(
                f"arm {self.name!r}: counts_per_rev must be an integer >= 4, got {self.counts_per_rev}"
            )
        if not (math.isfinite(self.latency_s) and 0.0 <= self.latency_s <= 1.0):
            raise ValueError(f"arm {self.name!r}: latency_s must be in [0, 1] s, got {self.latency_s}")

    @property
    def rigid(self) -> bool:
        """No compliance, no backlash and no dynamics: the joints stand exactly where the command puts them."""
        return (
            (self.compliance is None or not np.any(self.compliance))
            and not np.any(self.backlash_deg)
            and self.dynamics is None
        )

    def per_joint(self, key: str, joint_types) -> np.ndarray:
        """`key`'s values for joints of `joint_types`, `(joints,)`: the last value repeated,
        zeros for prismatic joints (and when None)."""
        return _per_joint(getattr(self, key), joint_types)

    def encoder(self, rate_hz: float, noise_counts: float) -> EncoderModel:
        """The arm's `EncoderModel` at the simulation's rate; `noise_counts` are counts of the
        ideal arm's encoder (2^17 per turn): a coarser one keeps that noise in radians and adds
        its own quantisation."""
        scale = self.counts_per_rev / ArmModel.counts_per_rev
        return EncoderModel(rate_hz, int(self.counts_per_rev), noise_counts * scale, self.latency_s)

    @classmethod
    def from_metadata(cls, record: dict | None) -> "ArmModel":
        """The arm `metadata` recorded (`truth.json`'s `arm`: per joint values), or the rigid
        arm for none."""
        if not record:
            return cls()
        compliance, dynamics = record.get("compliance_rad_per_kNm"), record.get("dynamics")
        return cls(
            name=record.get("name", "recorded"),
            compliance=None if compliance is None else tuple(compliance),
            backlash_deg=tuple(record.get("backlash_deg") or (0.0,)),
            counts_per_rev=int(record.get("counts_per_rev", cls.counts_per_rev)),
            latency_s=float(record.get("latency_s", 0.0)),
            dynamics=None
            if dynamics is None
            else Dynamics(**{k: tuple(v) if isinstance(v, list) else v for k, v in dynamics.items()}),
        )

    def figures(self) -> ArmFigures:
        """The figures a capture plan's prediction takes (`jaxcal.evaluate_plan(..., arm=)`)."""
        compliance = () if self.compliance is None else tuple(np.atleast_1d(self.compliance).tolist())
        return ArmFigures(
            self.name,
            compliance,
            tuple(np.atleast_1d(self.backlash_deg).tolist()),
            int(self.counts_per_rev),
            float(self.latency_s),
        )

    def metadata(self, joint_types) -> dict:
        """What `truth.json` records of the arm (`arm`), per joint of `joint_types`."""
        return {
            "name": self.name,
            "compliance_rad_per_kNm": None
            if self.compliance is None
            else self.per_joint("compliance", joint_types).tolist(),
            "backlash_deg": self.per_joint("backlash_deg", joint_types).tolist(),
            "counts_per_rev": int(self.counts_per_rev),
            "latency_s": self.latency_s,
        } | (
            {}
            if self.dynamics is None
            else {
                "dynamics": {
                    f.name: self.dynamics.per_joint(f.name, joint_types).tolist()
                    if isinstance(getattr(self.dynamics, f.name), tuple)
                    else getattr(self.dynamics, f.name)
                    for f in fields(self.dynamics)
                }
            }
        )


def gravity_deflection(true, theta, zero_offset, compliance, inertials) -> np.ndarray:
    """$10^{-3} c_j \\tau_j$ (rad) at true joint angles `theta` `(..., joints)`: each joint's
    yield under the gravity torque (N m) of the links it carries (`inertials`: masses,
    centres of mass, as `jaxcal.robots.link_inertials`)."""
    masses, coms = (jnp.asarray(a, jnp.float64) for a in inertials)
    theta = np.asarray(theta, np.float64)
    q = jnp.asarray(theta.reshape(-1, theta.shape[-1]) - np.asarray(zero_offset, np.float64))
    tau = np.asarray(jax.vmap(lambda qq: gravity_torques(true, qq, masses, coms))(q))
    return (1e-3 * tau * np.asarray(compliance, np.float64)).reshape(theta.shape)


class ArmMotion:
    """Where the joints of the true arm stand at controller times `t` along `trajectory`.

    **Arguments:** `arm` (`ArmModel`); `trajectory` (commanded positions);
    `nominal_ratio`, `true` (the true `KinematicModel`: its ratios, zero
    offsets and, for compliance, its kinematics); `inertials` (masses and
    centres of mass, needed with compliance).

    `angles(t)` `(..., joints)`: the true joint angles $\\theta$ (rad), as the
    renderer poses them; `rigid_angles(t)`: without compliance and backlash.
    """

    def __init__(self, arm: ArmModel, trajectory: Trajectory, nominal_ratio, true, inertials=None):
        arm.check(trajectory.q.shape[1])
        if arm.dynamics is not None:
            raise ValueError(
                f"arm {arm.name!r}: its joints come from MuJoCo's physics (jaxcal.sim.physics.PhysicsMotion), "
                "not from the formulas of ArmMotion"
            )
        self.arm, self.trajectory, self.true = arm, trajectory, true
        self.scale = np.asarray(nominal_ratio, np.float64) / np.asarray(true.reduction_ratio, np.float64)
        self.zero = np.asarray(true.zero_offset, np.float64)
        self.width = np.radians(arm.per_joint("backlash_deg", true.joint_types))
        self.compliance = arm.per_joint("compliance", true.joint_types)
        if np.any(self.compliance) and inertials is None:
            raise ValueError(f"arm {arm.name!r}: compliance needs the robot's link masses (inertials)")
        self.inertials = inertials
        self.state = play(trajectory.q * self.scale + self.zero, self.width)

    def rigid_angles(self, t) -> np.ndarray:
        """$\\theta_0 = q\\,\\rho_{nom}/\\rho_{true} + \\delta$ at `t`."""
        return self.trajectory(t) * self.scale + self.zero

    def backlash_angles(self, t) -> np.ndarray:
        """The link side of the dead band at `t`: $\\theta_b$ (rad)."""
        theta0 = self.rigid_angles(t)
        if not np.any(self.width):
            return theta0
        times = self.trajectory.times
        t = np.clip(np.asarray(t, np.float64), times[0], times[-1])
        i = np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(times) - 2)
        half = 0.5 * self.width
        return np.clip(self.state[i], theta0 - half, theta0 + half)

    def angles(self, t) -> np.ndarray:
        """The true joint angles at `t`: backlash, then the gravity deflection."""
        theta = self.backlash_angles(t)
        if not np.any(self.compliance):
            return theta
        return theta + gravity_deflection(self.true, theta, self.zero, self.compliance, self.inertials)


#: The named arms (see the module docstring for their sources).
ARM_PRESETS = {
    "ideal": ArmModel(),
    "realistic": ArmModel(
        name="realistic",
        compliance=(1 / 32, 1 / 32, 1 / 32, 1 / 5),
        backlash_deg=1 / 60,
        counts_per_rev=2**17,
        latency_s=2e-3,
    ),
}
ARM_PRESETS["physics"] = replace(ARM_PRESETS["realistic"], name="physics", dynamics=Dynamics())


def arm_model(arm) -> ArmModel:
    """An `ArmModel` from a preset's name (`ARM_PRESETS`) or a model itself, checked."""
    if isinstance(arm, ArmModel):
        model = arm
    elif arm in ARM_PRESETS:
        model = ARM_PRESETS[arm]
    else:
        raise ValueError(f"unknown arm {arm!r}; the presets are {sorted(ARM_PRESETS)}")
    model.check()
    return model
