"""The simulator's arm model (`jaxcal.sim.arm`) against analytic expectations: the
gravity deflection is the compliance times the torque of the masses carried, backlash
lags the encoder by half the lost motion against the direction of motion, encoder
readings sit within half a count of the motor (stamped `latency_s` late), and
`simulate` films the arm where the model puts it."""

import json
from dataclasses import replace

import jax
import numpy as np
import pytest

from jaxcal._kinematics import forward_kinematics
from jaxcal.cli import ARMS
from jaxcal.io.dataset import load_dataset
from jaxcal.robots import link_inertials, load_robot
from jaxcal.sim.arm import ARM_PRESETS, ArmModel, ArmMotion, arm_model, gravity_deflection
from jaxcal.sim.motion import EncoderModel, Trajectory, encoder_stream, free_motion
from jaxcal.sim.simulate import SimConfig, simulate

G = 9.80665


def _still(q, seconds: float = 1.0) -> Trajectory:
    """The arm held at `q` (rad)."""
    q = np.asarray(q, np.float64)
    return free_motion([0.0, seconds], np.stack([q, q]))


def test_presets_match_the_command_line():
    assert tuple(ARM_PRESETS) == ARMS
    for name in ARM_PRESETS:
        assert arm_model(name).name == name
    assert arm_model("ideal").rigid and not arm_model("realistic").rigid
    with pytest.raises(ValueError, match="unknown arm"):
        arm_model("floppy")
    with pytest.raises(ValueError, match="compliance"):
        arm_model(ArmModel(compliance=-1.0))
    with pytest.raises(ValueError, match="counts_per_rev"):
        arm_model(ArmModel(counts_per_rev=2.5))
    with pytest.raises(ValueError, match="backlash_deg"):
        ArmMotion(ArmModel(backlash_deg=(0.1,) * 7), _still(np.zeros(6)), np.ones(6), load_robot("ur5e"))


def test_gravity_deflection_is_compliance_times_the_carried_torque():
    """UR5e at zero: the arm stretched out horizontally. The base's vertical axis carries
    no gravity torque; the shoulder's is $g \\sum_k m_k\\, d_k$ with $d_k$ the horizontal
    lever arm of link $k$'s centre of mass across the axis, and the arm yields downwards."""
    model = load_robot("ur5e")
    masses, coms = link_inertials("ur5e")
    c = np.array([0.02, 0.03, 0.04, 0.2, 0.2, 0.2])
    q0 = np.zeros(6)
    motion = ArmMotion(
        ArmModel(compliance=tuple(c)), _still(q0), model.reduction_ratio, model, (masses, coms)
    )
    deflection = motion.angles(0.5) - motion.rigid_angles(0.5)

    T = np.asarray(jax.device_get(forward_kinematics(model, q0)))
    links = T[1:-1]
    centres = np.einsum("kab,kb->ka", links[:, :3, :3], coms) + links[:, :3, 3]
    z1, o1 = links[1][:3, :3] @ np.asarray(model.axis[1]), links[1][:3, 3]
    assert abs(z1[2]) < 1e-12  # the shoulder's axis is horizontal
    lever = np.cross(z1, [0.0, 0.0, 1.0])  # horizontal, across the axis: tau = g m (c - o) . (z x up)
    tau_shoulder = G * sum(m * ((ck - o1) @ lever) for m, ck in zip(masses[1:], centres[1:]))
    assert abs(deflection[0]) < 1e-15  # vertical axis: no torque
    assert deflection[1] == pytest.approx(1e-3 * c[1] * tau_shoulder, rel=1e-9)
    # The sag: the flange lower than the rigid arm's, by about the deflections times the reach.
    rigid = np.asarray(forward_kinematics(model, q0))[-1][:3, 3]
    sagged = np.asarray(forward_kinematics(model, q0 + deflection))[-1][:3, 3]
    assert sagged[2] < rigid[2] - 0.5 * abs(deflection[1]) * np.linalg.norm(rigid[:2])


def test_backlash_lags_against_the_direction_of_motion():
    """Out to +20 deg and back: the link trails the motor by b/2 each way, and stands
    still while the motor crosses the dead band after the reversal."""
    model = load_robot("ur5e")
    b = np.radians(0.5)
    q = np.zeros((3, 6))
    q[1, 1] = np.radians(20.0)
    motion = ArmMotion(
        ArmModel(backlash_deg=0.5), Trajectory([0.0, 1.0, 2.0], q, []), model.reduction_ratio, model
    )
    t = np.array([0.5, 0.9, 1.5, 1.9])
    lag = motion.angles(t) - motion.rigid_angles(t)
    assert np.allclose(lag[:, 1], [-b / 2, -b / 2, b / 2, b / 2], atol=1e-15)
    assert np.allclose(lag[:, [0, 2, 3, 4, 5]], 0.0)  # the joints that never move stay centred
    # Just after the reversal the link has not moved yet: it stands where the outward leg left it.
    t_turn = 1.0 + np.arccos(1.0 - 2.0 * 0.5 * b / np.radians(20.0)) / np.pi  # the motor back by b/2
    before = motion.angles(np.linspace(1.0, t_turn, 5))[:, 1]
    assert np.allclose(before, np.radians(20.0) - b / 2, atol=1e-12)


def test_encoder_readings_within_half_a_count_and_late_by_the_latency():
    model = load_robot("ur5e")
    traj = Trajectory([0.0, 1.0], np.stack([np.zeros(6), np.full(6, 0.3)]), [])
    enc = EncoderModel(rate_hz=200.0, counts_per_rev=1024, noise_counts=0.0, latency_s=0.004)
    ratio = np.asarray(model.reduction_ratio)
    t, motor = encoder_stream(traj, ratio, enc, np.random.default_rng(0))
    step = 2 * np.pi / 1024
    assert np.allclose(motor / step, np.round(motor / step), atol=1e-9)  # whole counts
    assert np.max(np.abs(motor - traj(t - 0.004) * ratio)) <= 0.5 * step + 1e-12
    # Half a count off is what a latency-free model of the same readings would miss, at least.
    assert np.max(np.abs(motor - traj(t) * ratio)) > 0.5 * step


@pytest.mark.slow
def test_simulate_films_the_arm_where_the_model_puts_it(tmp_path):
    arm = ArmModel(name="test", compliance=0.05, backlash_deg=0.2, counts_per_rev=4096, latency_s=0.003)
    config = SimConfig(resolution=(64, 48), frames_per_joint=3, arm=arm, grayscale=True)
    out = simulate(config, tmp_path / "ds", progress=False)
    truth = json.loads((out / "truth.json").read_text())
    meta = json.loads((out / "metadata.json").read_text())
    assert truth["arm"]["latency_s"] == 0.003 and meta["encoders"]["counts_per_rev"] == 4096
    assert meta["simulation"]["arm"]["name"] == "test" and load_dataset(out).cameras
    rigid = simulate(
        SimConfig(resolution=(64, 48), frames_per_joint=3, grayscale=True), tmp_path / "r", progress=False
    )
    rigid_truth = json.loads((rigid / "truth.json").read_text())
    dtheta = np.array([f["theta"] for f in truth["frames"]]) - np.array(
        [f["theta"] for f in rigid_truth["frames"]]
    )
    # Within the lost motion's half width plus the largest gravity deflection (0.05 rad/kNm x < 150 N m).
    assert np.all(np.abs(dtheta) <= np.radians(0.1) + 0.05 * 0.15 + 1e-12)
    assert np.max(np.abs(dtheta[:, 1])) > np.radians(0.1)  # the shoulder sags beyond the play


# --------------------------------------------------------------------------- the verdict's arm check


@pytest.mark.slow
def test_verdict_flags_an_arm_that_sags(tmp_path):
    """The same rendered sweeps of a rigid arm and of one whose joints yield 0.1 rad per kN m
    (three times a UR5's shoulder), calibrated as a rigid arm: the rigid one passes both arm rows (F of order 1, the F law's
    mean; the arcs' clock within its sigmas of the refinement's), the sagging one's arcs put the
    clock many sigmas off the refinement's (its joints yield along their own sweeps), flagged with
    gravity sag and backlash named (the analytic corners' version, over seeds:
    `tests/test_armcheck.py`)."""
    from jaxcal import calibrate

    config = SimConfig(resolution=(640, 480), frames_per_joint=12, range_deg=80.0, grayscale=True)
    rigid = calibrate(simulate(config, tmp_path / "rigid", progress=False), progress=False)
    sag = ArmModel(name="sag", compliance=(0.1, 0.1, 0.1, 0.2))
    # Without the non-geometric terms (a rigid model: `tests/test_terms.py` fits them).
    bent = calibrate(
        simulate(replace(config, arm=sag), tmp_path / "sag", progress=False), progress=False, terms=()
    )
    rows_rigid, rows_bent = ({c.check: c for c in r.verdict.checks} for r in (rigid, bent))
    assert rows_rigid["arm_gravity_F"].passed and rows_rigid["arm_gravity_F"].value < 5.0, rows_rigid[
        "arm_gravity_F"
    ]
    assert rows_rigid["arm_clock_z"].passed, rows_rigid["arm_clock_z"]
    assert not rows_bent["arm_clock_z"].passed and bent.status == "suspect", rows_bent["arm_clock_z"]
    reason = next(r for r in bent.reasons if "clock" in r and "gravity sag" in r)
    assert "backlash" in reason and "stop-and-shoot" in reason


# --------------------------------------------------------------------------- the physics arm


#: The base's leg of `physics`' motion: held 1 s, then 30 deg in 0.6 s (a raised cosine), held 1 s.
LEG = (1.0, 0.6, np.radians(30.0))
#: A pose that loads the shoulder and the elbow (the arm reaching out and down).
LOADED = np.radians([0.0, -30.0, 40.0, 0.0, 0.0, 0.0])


@pytest.fixture(scope="module")
def physics():
    """MuJoCo's arm (the `physics` preset) at `LOADED`, its base swept by `LEG`."""
    from jaxcal.robots import link_inertias
    from jaxcal.sim.physics import PhysicsMotion

    model = load_robot("ur5e")
    start, span, angle = LEG
    q = np.stack([LOADED, LOADED, LOADED + [angle, 0, 0, 0, 0, 0], LOADED + [angle, 0, 0, 0, 0, 0]])
    traj = Trajectory([0.0, start, start + span, start + span + 1.0], q, [])
    arm = ARM_PRESETS["physics"]
    return model, arm, traj, PhysicsMotion(arm, traj, model.reduction_ratio, model, link_inertias("ur5e"))


def _twist(model, motion, t):
    """The transmissions' twist at `t`: the links' angles less the motors' (in joint angles)."""
    return motion.angles(t) - (
        motion.motor(t) / np.asarray(model.reduction_ratio) + np.asarray(model.zero_offset)
    )


def test_the_physics_arm_sags_by_its_compliance_against_one_flank(physics):
    """Held still, each joint's transmission carries the gravity torque of what it lifts (MuJoCo's
    dynamics on the URDF's full inertias, against `jaxcal._pointfit.gravity_torques` on its masses and
    centres): every joint gravity loads sits $10^{-3} c_j \\tau_j$ from its motor plus half the lost
    motion, against the flank gravity presses it to; the others within the dead band. Tolerance: the bearing's friction may hold the link anywhere within
    $F / k$ of that (0.5 N m at 32 kN m/rad: 1.6e-5 rad) and the torque is the formula's at the
    deflected angles to first order (0.5 %)."""
    model, arm, _, motion = physics
    t = LEG[0] - 0.05  # settled before the base moves
    twist = _twist(model, motion, t)
    c = arm.per_joint("compliance", model.joint_types)
    sag = gravity_deflection(model, motion.angles(t), model.zero_offset, c, link_inertials("ur5e"))
    half = 0.5 * np.radians(arm.per_joint("backlash_deg", model.joint_types))
    loaded = np.abs(sag) > 1e-6  # every joint but the vertical base and the last wrist
    assert np.all(loaded[1:5]) and abs(sag[1]) > 1e-3
    expected = sag + np.sign(sag) * half
    bearing = 1e-3 * c * arm.dynamics.per_joint("bearing_friction_nm", model.joint_types)
    assert np.all(np.abs(twist - expected)[loaded] <= bearing[loaded] + 0.005 * np.abs(expected[loaded]))
    assert np.all(np.abs(twist[~loaded]) <= half[~loaded] + bearing[~loaded] + 1e-5)


def test_the_physics_arm_lags_while_it_accelerates(physics):
    """The base (a vertical axis: no gravity torque) swept: while it accelerates its link trails its
    motor beyond the dead band, by about the inertial torque over the stiffness (the link's inertia
    about the axis times the raised cosine's mean acceleration over the leg's first half), leads it
    while it decelerates, and comes to rest inside its dead band where it stops (no torque presses
    it to a flank; the ringing of a transmission damped to 0.15 of critical averages out over the
    halves: within a factor 2). The encoders read the motors, which the servo keeps within a degree of the
    command."""
    import mujoco

    model, arm, traj, motion = physics
    start, span, angle = LEG
    c = arm.per_joint("compliance", model.joint_types)[0]
    half = 0.5 * np.radians(arm.per_joint("backlash_deg", model.joint_types)[0])
    data = mujoco.MjData(motion.model)
    for j, name in enumerate(model.joint_names):
        data.qpos[motion.model.jnt_qposadr[motion.model.joint(name).id]] = LOADED[j]
    mujoco.mj_forward(motion.model, data)
    M = np.zeros((motion.model.nv, motion.model.nv))
    mujoco.mj_fullM(motion.model, data, M)
    dof = motion.model.jnt_dofadr[motion.model.joint(model.joint_names[0]).id]
    inertia = M[dof, dof]  # the base link's (and all it carries) about its axis, kg m^2
    accelerating = start + np.linspace(0.05, 0.45, 41) * span
    decelerating = start + np.linspace(0.55, 0.95, 41) * span
    mean_acc = np.mean(0.5 * angle * (np.pi / span) ** 2 * np.cos(np.pi * (accelerating - start) / span))
    lag = 1e-3 * c * inertia * mean_acc  # rad, the mean inertial twist over the first half
    trail = -np.mean(_twist(model, motion, accelerating)[:, 0])
    lead = np.mean(_twist(model, motion, decelerating)[:, 0])
    assert trail > half and lead > half
    assert 0.5 * lag < trail - half < 2.0 * lag and 0.5 * lag < lead - half < 2.0 * lag
    bearing = 1e-3 * c * arm.dynamics.per_joint("bearing_friction_nm", model.joint_types)[0]
    assert abs(_twist(model, motion, start + span + 0.9)[0]) <= half + bearing  # at rest in its dead band
    t = np.linspace(0.0, traj.duration, 200)
    ratio = np.asarray(model.reduction_ratio)
    command = traj(t) * ratio
    assert 0.0 < np.max(np.abs(motion.motor(t) - command) / ratio) < np.radians(1.0)
    enc = EncoderModel(rate_hz=500.0, counts_per_rev=2**17, noise_counts=0.0)
    te, log = encoder_stream(traj, ratio, enc, np.random.default_rng(0), motion.motor)
    assert np.max(np.abs(log - motion.motor(te))) <= np.pi / 2**17 + 1e-12  # half a count


@pytest.mark.slow
def test_simulate_films_the_physics_arm(tmp_path):
    """`jaxcal simulate --arm physics` at 64x48: the truth's joint angles are MuJoCo's (the capture's
    truth rebuilt from its record, the target plate as the payload, reproduces them to 1e-9), the
    encoders log the motors and the shoulder sags under the plate's weight."""
    from jaxcal.sim.corners import capture_truth

    config = SimConfig(resolution=(64, 48), frames_per_joint=3, arm="physics", grayscale=True)
    out = simulate(config, tmp_path / "ds", progress=False)
    truth = json.loads((out / "truth.json").read_text())
    recorded = ArmModel.from_metadata(truth["arm"])
    assert (
        recorded.name == "physics"
        and recorded.dynamics.payload_kg == ARM_PRESETS["physics"].dynamics.payload_kg
    )
    capture_truth(out)  # raises unless the rebuilt physics reproduces the truth's angles
    ds = load_dataset(out)
    theta = np.array([f["theta"] for f in truth["frames"]])
    t = np.array([f["t"] for f in truth["frames"]])
    # The motor at a frame's time: the reading stamped the encoders' latency later.
    late = t + ARM_PRESETS["physics"].latency_s
    motor = np.stack([np.interp(late, ds.encoder_t, m) for m in ds.encoder_motor.T], axis=1)
    twist = theta - (motor / np.asarray(load_robot("ur5e").reduction_ratio) + truth["model"]["zero_offset"])
    assert 1e-3 < np.median(np.abs(twist[:, 1])) < 5e-3  # the shoulder's sag under the arm and plate
