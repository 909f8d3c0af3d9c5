"""MuJoCo's physics as the simulator's arm: an arm not written from the estimator's formulas.

`ArmModel.dynamics` (the `physics` preset) moves the true arm with MuJoCo
instead of `jaxcal.sim.arm`'s compliance and play formulas (which the
estimator's non-geometric terms share, `jaxcal._compliance`). The model, in
the true kinematics (every link body in its joint frame, as `jaxcal.sim.scene`
builds it):

- **links**: each link's mass, centre of mass and inertia tensor from the robot
  file (`jaxcal.robots.link_inertias`: the URDF's `<inertial>`s, fixed links lumped
  in), each target plate on a link `Dynamics.payload_kg` at its centre (a thin
  plate's inertia), gravity $-9.81$ m/s$^2$ along the base's $z$.
- **transmissions**: joint $j$ is two degrees of freedom, the motor-side rotor (a
  hinge on the parent link with the rotor's inertia reflected through the gear,
  `armature_kgm2`, and the gear's Coulomb friction) and the link (its bearing's
  friction). A fixed tendon of length $\\theta_j - \\theta_{m,j}$ couples them: a
  spring of stiffness $10^3 / c_j$ N m/rad (`ArmModel.compliance`, rad per kN m)
  with a dead band of the lost motion $b_j$ (`ArmModel.backlash_deg`: no force
  while $|\\theta_j - \\theta_{m,j}| \\le b_j/2$), damped to `transmission_damping` of
  critical against the link's inertia. A joint with neither is rigid (a joint
  equality constraint).
- **controller**: a position servo per rotor (MuJoCo's position actuator,
  $\\tau = k_p(u - \\theta_m) - k_v \\dot\\theta_m$, finite gains: `servo_hz` natural
  frequency and `servo_damping` against the joint's inertia at the zero configuration),
  its set point $u = \\theta_0 + (k_v \\dot\\theta_0 + \\tau_{ff}) / k_p$: the command
  $\\theta_0 = q\\,\\rho_{nom}/\\rho_{true} + \\delta$ with its velocity, and the
  feed-forward $\\tau_{ff}$ of the links' gravity and Coriolis torques at the joint
  (MuJoCo's bias force at the link, one step old), as an industrial controller's
  model-based feed-forward.

The arm is held at the motion's first pose for `settle_s`, then stepped
(`timestep_s`, the implicit-fast integrator) through the commanded motion. The
links lag while they accelerate (the transmissions carry the inertial torques),
ring and sag where they stop, and stay against one flank of the dead band where
gravity preloads them; a gear's friction holds its motor where the servo cannot
quite reach. The renderer poses the links (`angles`); the **encoders read the
motor side** (`motor`): a real arm's joint encoders sit on the motor shaft,
behind the gear, so they log $m = (\\theta_m - \\delta)\\,\\rho_{true}$, the rotor's
actual angle in motor turns (not the command: the servo's tracking error is in the
log, as it is in a real controller's), and never see the transmission's twist.
"""

import numpy as np

from ._gl import select_backend

select_backend()
import mujoco  # noqa: E402

from .arm import ArmModel  # noqa: E402
from .motion import Trajectory  # noqa: E402
from .scene import add_arm, mujoco_quat, placement  # noqa: E402

#: Gravity along the base's -z (m/s^2), as `jaxcal._pointfit.gravity_torques` takes it.
GRAVITY = 9.81
#: A rigid coupling's constraint time constant, in simulation steps (MuJoCo's solref).
RIGID_STEPS = 4


class PhysicsMotion:
    """Where the true arm's joints stand, and its motors turn, along `trajectory` under MuJoCo's physics.

    **Arguments:** `arm` (an `ArmModel` with `dynamics`); `trajectory` (the commanded
    positions); `nominal_ratio`, `true` (the true `KinematicModel`: its kinematics,
    ratios and zero offsets); `inertias` (masses, centres of mass, inertia tensors:
    `jaxcal.robots.link_inertias`); `plates`: the target plates (`PlateSpec`s; those on
    links weigh `Dynamics.payload_kg`).

    `angles(t)` `(..., joints)`: the links' joint angles $\\theta$ (rad), as the renderer
    poses them; `motor(t)`: the motor angles the encoders read, $(\\theta_m - \\delta)\\rho_{true}$;
    `rigid_angles(t)`: the command's joint angles $\\theta_0$. Times outside the motion hold its ends.
    """

    def __init__(self, arm: ArmModel, trajectory: Trajectory, nominal_ratio, true, inertias, plates=()):
        if arm.dynamics is None:
            raise ValueError(f"arm {arm.name!r} has no dynamics: use jaxcal.sim.arm.ArmMotion")
        joints = trajectory.q.shape[1]
        arm.check(joints)
        self.arm, self.trajectory, self.true = arm, trajectory, true
        self.scale = np.asarray(nominal_ratio, np.float64) / np.asarray(true.reduction_ratio, np.float64)
        self.zero = np.asarray(true.zero_offset, np.float64)
        self.ratio = np.asarray(true.reduction_ratio, np.float64)
        model, link_dof, rotor_dof, link_q, rotor_q = _build(arm, true, inertias, plates)
        self.model = model
        self.dt = float(model.opt.timestep)
        self.t, self.link, self.rotor = _run(
            model, arm, trajectory, self.scale, self.zero, link_dof, rotor_dof, link_q, rotor_q
        )

    def rigid_angles(self, t) -> np.ndarray:
        """$\\theta_0 = q\\,\\rho_{nom}/\\rho_{true} + \\delta$ at `t`: the command's joint angles."""
        return self.trajectory(t) * self.scale + self.zero

    def _at(self, samples: np.ndarray, t) -> np.ndarray:
        t = np.asarray(t, np.float64)
        pos = np.clip((t - self.t[0]) / self.dt, 0.0, len(self.t) - 1.0)
        i = np.minimum(np.floor(pos).astype(int), len(self.t) - 2)
        frac = (pos - i)[..., None]
        return samples[i] * (1.0 - frac) + samples[i + 1] * frac

    def angles(self, t) -> np.ndarray:
        """The links' joint angles at controller times `t` (linear between the steps)."""
        return self._at(self.link, t)

    def motor(self, t) -> np.ndarray:
        """The motor angles (rad of motor turn) at `t`: what the encoders read."""
        return (self._at(self.rotor, t) - self.zero) * self.ratio


def _plate_inertia(plate, mass: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A plate's centre (in its link frame), orientation and diagonal inertia (a thin
    plate spanning its target's points, in the target's axes)."""
    points = np.asarray(plate.target.points(), np.float64)
    lo, hi = points.min(axis=0), points.max(axis=0)
    a, b = np.maximum(hi - lo, 1e-3)[:2] * 1.25  # the board's margin beyond its outer corners
    T = np.asarray(plate.T_link_target, np.float64)
    centre = T[:3, :3] @ (0.5 * (lo + hi)) + T[:3, 3]
    inertia = mass / 12.0 * np.array([b * b, a * a, a * a + b * b])
    return centre, T[:3, :3], inertia


def flange_payload(plates, mass_kg: float, flange: str) -> dict | None:
    """The metadata's `robot.payload` of the plates a physics arm carries on its `flange` link,
    each `mass_kg` at its centre (`_plate_inertia`): their mass, centre in the flange frame and
    inertia tensor about it (JSON-ready), or None where none rides on the flange."""
    parts = [_plate_inertia(p, mass_kg) for p in plates if p.link == flange]
    if not parts or mass_kg <= 0.0:
        return None
    total = mass_kg * len(parts)
    com = sum(c for c, _, _ in parts) / len(parts)
    inertia = np.zeros((3, 3))
    for c, R, d in parts:  # each plate's own inertia, moved to the common centre
        r = c - com
        inertia += R @ np.diag(d) @ R.T + mass_kg * (r @ r * np.eye(3) - np.outer(r, r))
    return {"mass_kg": total, "com_m": com.tolist(), "inertia_kgm2": inertia.tolist()}


def _build(arm: ArmModel, true, inertias, plates):
    """The compiled MuJoCo model and the indices `(link_dof, rotor_dof, link_qpos, rotor_qpos)`."""
    dyn = arm.dynamics
    types = true.joint_types
    names = tuple(true.joint_names)
    masses, coms, tensors = (np.asarray(a, np.float64) for a in inertias)
    if masses.shape != (len(names),):
        raise ValueError(f"arm {arm.name!r}: {masses.size} link masses for {len(names)} joints")
    compliance = arm.per_joint("compliance", types)
    play = np.radians(arm.per_joint("backlash_deg", types))
    if np.any((play > 0) & (compliance <= 0)):
        raise ValueError(
            f"arm {arm.name!r}: the physics arm needs a compliance wherever it has lost motion "
            "(the dead band sits in the transmission's spring)"
        )
    spec = mujoco.MjSpec()
    spec.modelname = "jaxcal_physics"
    spec.option.timestep = dyn.timestep_s
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    spec.option.gravity = [0.0, 0.0, -GRAVITY]
    bodies = add_arm(spec.worldbody, true, None, 0.035)
    links = tuple(true.link_names)
    flange = bodies[links[-1]]
    flange.mass, flange.inertia = 1e-6, [1e-9, 1e-9, 1e-9]  # its own inertial is lumped into the last link's
    T_parent_joint = np.asarray(true.T_parent_joint, np.float64)
    armature = dyn.per_joint("armature_kgm2", types)
    gear, bearing = dyn.per_joint("gear_friction_nm", types), dyn.per_joint("bearing_friction_nm", types)
    for i, joint in enumerate(names):
        body = bodies[links[i + 1]]
        if masses[i] > 0:
            principal, axes = np.linalg.eigh(0.5 * (tensors[i] + tensors[i].T))
            if np.linalg.det(axes) < 0:
                axes[:, 0] *= -1.0
            body.mass, body.ipos = float(masses[i]), coms[i].tolist()
            body.inertia, body.iquat = np.maximum(principal, 1e-9).tolist(), mujoco_quat(axes)
        link_joint = spec.joint(joint)
        link_joint.frictionloss = float(bearing[i])
        rotor = bodies[links[i]].add_body(name=f"rotor:{joint}", **placement(T_parent_joint[i]))
        rotor.explicitinertial = True
        rotor.mass, rotor.inertia = 1e-3, [1e-6, 1e-6, 1e-6]
        rotor.add_joint(
            name=f"rotor:{joint}",
            type=link_joint.type,
            axis=list(link_joint.axis),
            armature=float(armature[i]),
            frictionloss=float(gear[i]),
        )
        if compliance[i] > 0:
            tendon = spec.add_tendon(name=f"transmission:{joint}")
            tendon.stiffness = [1e3 / compliance[i], 0.0, 0.0]
            tendon.springlength = [-0.5 * play[i], 0.5 * play[i]]
            tendon.wrap_joint(joint, 1.0)
            tendon.wrap_joint(f"rotor:{joint}", -1.0)
        else:
            spec.add_equality(
                type=mujoco.mjtEq.mjEQ_JOINT,
                name1=joint,
                name2=f"rotor:{joint}",
                solref=[RIGID_STEPS * dyn.timestep_s, 1.0],
            )
        actuator = spec.add_actuator(name=f"servo:{joint}", target=f"rotor:{joint}")
        actuator.trntype = mujoco.mjtTrn.mjTRN_JOINT
        actuator.set_to_position(kp=1.0, kv=0.0)  # gains set below, from the compiled inertias
    for k, plate in enumerate(p for p in plates if p.link != "world"):
        centre, R, inertia = _plate_inertia(plate, dyn.payload_kg)
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, centre
        payload = bodies[plate.link].add_body(name=f"payload{k}:{plate.target.name}", **placement(T))
        payload.explicitinertial = True
        payload.mass, payload.inertia = float(dyn.payload_kg), inertia.tolist()
    model = spec.compile()
    ids = [model.joint(n).id for n in names]
    rotor_ids = [model.joint(f"rotor:{n}").id for n in names]
    link_dof, rotor_dof = model.jnt_dofadr[ids], model.jnt_dofadr[rotor_ids]
    link_q, rotor_q = model.jnt_qposadr[ids], model.jnt_qposadr[rotor_ids]
    _tune(model, arm, true, link_dof, rotor_dof, link_q, rotor_q, compliance)
    return model, link_dof, rotor_dof, link_q, rotor_q


def _tune(model, arm: ArmModel, true, link_dof, rotor_dof, link_q, rotor_q, compliance) -> None:
    """The servos' gains and the transmissions' damping from the joints' inertias at the
    zero offsets' pose (`Dynamics`: servo frequency and damping ratio, transmission damping)."""
    dyn = arm.dynamics
    data = mujoco.MjData(model)
    data.qpos[link_q] = data.qpos[rotor_q] = np.asarray(true.zero_offset, np.float64)
    mujoco.mj_forward(model, data)
    M = np.zeros((model.nv, model.nv))
    mujoco.mj_fullM(model, data, M)
    link_inertia = M[link_dof, link_dof]
    inertia = link_inertia + M[rotor_dof, rotor_dof]
    omega = 2.0 * np.pi * dyn.servo_hz
    kp = inertia * omega**2
    kv = 2.0 * dyn.servo_damping * np.sqrt(kp * inertia)
    model.actuator_gainprm[:, 0] = kp
    model.actuator_biasprm[:, 1], model.actuator_biasprm[:, 2] = -kp, -kv
    names = tuple(true.joint_names)
    for j, c in enumerate(compliance):
        if c > 0:
            t = model.tendon(f"transmission:{names[j]}").id
            model.tendon_damping[t] = 2.0 * dyn.transmission_damping * np.sqrt(1e3 / c * link_inertia[j])


def _run(model, arm: ArmModel, trajectory: Trajectory, scale, zero, link_dof, rotor_dof, link_q, rotor_q):
    """Settle at the first pose, then step through the motion: `(t, link angles, rotor angles)`
    at every step from 0 to the motion's end."""
    dyn = arm.dynamics
    dt = float(model.opt.timestep)
    start = float(trajectory.times[0])
    steps = int(np.ceil((trajectory.duration - start) / dt)) + 1
    t = start + dt * np.arange(steps + 1)
    target = trajectory(t) * scale + zero
    velocity = trajectory.velocity(t) * scale
    kp, kv = model.actuator_gainprm[:, 0].copy(), -model.actuator_biasprm[:, 2].copy()
    lead = kv / kp * velocity
    data = mujoco.MjData(model)
    data.qpos[link_q] = data.qpos[rotor_q] = target[0]
    mujoco.mj_forward(model, data)
    for _ in range(int(round(dyn.settle_s / dt))):
        data.ctrl[:] = target[0] + data.qfrc_bias[link_dof] / kp
        mujoco.mj_step(model, data)
    link, rotor = np.empty_like(target), np.empty_like(target)
    for k in range(steps + 1):
        link[k], rotor[k] = data.qpos[link_q], data.qpos[rotor_q]
        data.ctrl[:] = target[k] + lead[k] + data.qfrc_bias[link_dof] / kp
        mujoco.mj_step(model, data)
    if not (np.all(np.isfinite(link)) and np.all(np.isfinite(rotor))):
        raise RuntimeError(f"arm {arm.name!r}: MuJoCo's simulation diverged (a shorter timestep_s?)")
    return t, link, rotor
