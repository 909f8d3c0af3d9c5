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
"""

import math
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from .._compliance import play as play
from .._pointfit import gravity_torques
from ..records_capture import ArmFigures
from .motion import EncoderModel, Trajectory


@dataclass(frozen=True)
class ArmModel:
    """How the simulated arm deviates from a rigid one with perfect encoders (see the module docstring).

    `compliance`: rad per kN m of gravity torque (None: rigid).
    `backlash_deg`: lost motion per joint (deg). Both take one value for
    every joint or a tuple, whose last value holds for the joints after it (a
    preset's wrists). Prismatic joints neither yield nor lose motion.
    `counts_per_rev`: motor encoder counts per motor turn. `latency_s`: how
    late the encoder readings are stamped (s).
    """

    name: str = "ideal"
    compliance: float | tuple[float, ...] | None = None
    backlash_deg: float | tuple[float, ...] = 0.0
    counts_per_rev: int = 2**17
    latency_s: float = 0.0

    def check(self, joints: int | None = None) -> None:
        for key in ("compliance", "backlash_deg"):
            value = getattr(self, key)
            if value is None:
                continue
            v = np.atleast_1d(np.asarray(value, np.float64))
            if v.ndim != 1 or v.size == 0 or (joints is not None and v.size > joints):
                raise ValueError(
                    f"arm {self.name!r}: {key} needs one value or up to one per joint ({joints}), got {value}"
                )
            if not (np.all(np.isfinite(v)) and np.all(v >= 0.0)):
                raise ValueError(f"arm {self.name!r}: {key} must be finite and >= 0, got {value}")
        if int(self.counts_per_rev) != self.counts_per_rev or self.counts_per_rev < 4:
            raise ValueError(
                f"arm {self.name!r}: counts_per_rev must be an integer >= 4, got {self.counts_per_rev}"
            )
        if not (math.isfinite(self.latency_s) and 0.0 <= self.latency_s <= 1.0):
            raise ValueError(f"arm {self.name!r}: latency_s must be in [0, 1] s, got {self.latency_s}")

    @property
    def rigid(self) -> bool:
        """No compliance and no backlash: the joints stand exactly where the command puts them."""
        return (self.compliance is None or not np.any(self.compliance)) and not np.any(self.backlash_deg)

    def per_joint(self, key: str, joint_types) -> np.ndarray:
        """`key`'s values for joints of `joint_types`, `(joints,)`: the last value repeated,
        zeros for prismatic joints (and when None)."""
        value = getattr(self, key)
        v = np.atleast_1d(np.asarray(0.0 if value is None else value, np.float64))
        v = np.concatenate([v, np.full(max(0, len(joint_types) - v.size), v[-1])])[: len(joint_types)]
        return np.where(np.asarray(joint_types) == "revolute", v, 0.0)

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
        compliance = record.get("compliance_rad_per_kNm")
        return cls(
            name=record.get("name", "recorded"),
            compliance=None if compliance is None else tuple(compliance),
            backlash_deg=tuple(record.get("backlash_deg") or (0.0,)),
            counts_per_rev=int(record.get("counts_per_rev", cls.counts_per_rev)),
            latency_s=float(record.get("latency_s", 0.0)),
        )

    def figures(self) -> ArmFigures:
        """The figures a capture plan's prediction takes (`jaxcal.evaluate_plan(..., arm=)`)."""
        compliance = () if self.compliance is None else tuple(np.atleast_1d(self.compliance).tolist())
        return ArmFigures(
            self.name, compliance, tuple(np.atleast_1d(self.backlash_deg).tolist()),
            int(self.counts_per_rev), float(self.latency_s),
        )  # fmt: skip

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
        }


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
