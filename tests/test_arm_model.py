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
from jaxcal.sim.arm import ARM_PRESETS, ArmModel, ArmMotion, arm_model
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
