"""The transmissions' torques of a moving arm (`jaxcal._terms`): inverse dynamics against MuJoCo's,
derivatives of an encoder log, the load rule's relay, and the payload's inertia from the metadata."""

import json
import shutil
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxcal import _terms
from jaxcal.errors import DatasetError
from jaxcal.io.dataset import load_dataset
from jaxcal.robots import link_inertias, load_robot
from jaxcal.sim._gl import select_backend

select_backend()
import mujoco  # noqa: E402

from jaxcal.sim.scene import add_arm, mujoco_quat  # noqa: E402

NOMINAL = load_robot("ur5e")
N = NOMINAL.num_joints
MASSES, COMS, TENSORS = link_inertias("ur5e")
ROOT = Path(__file__).resolve().parents[1]


def _mujoco_arm(model, masses, coms, tensors):
    """The chain in MuJoCo (`jaxcal.sim.scene.add_arm`), each link with its inertial, no gravity."""
    spec = mujoco.MjSpec()
    spec.option.gravity = [0.0, 0.0, 0.0]
    bodies = add_arm(spec.worldbody, model, None, 0.035)
    links = tuple(model.link_names)
    flange = bodies[links[-1]]
    flange.mass, flange.inertia = 1e-12, [1e-15] * 3
    for i in range(model.num_joints):
        body = bodies[links[i + 1]]
        principal, axes = np.linalg.eigh(tensors[i])
        if np.linalg.det(axes) < 0:
            axes[:, 0] *= -1.0
        body.mass, body.ipos = float(masses[i]), coms[i].tolist()
        body.inertia, body.iquat = np.maximum(principal, 1e-15).tolist(), mujoco_quat(axes)
    return spec.compile()


def test_the_inertial_torques_are_mujocos_inverse_dynamics():
    """Lagrange's equations by automatic differentiation give MuJoCo's recursive Newton-Euler
    torques (an implementation no one here wrote) for random states of the UR5e, and no torque
    at rest; the transmissions' torques add gravity's."""
    m = _mujoco_arm(NOMINAL, MASSES, COMS, TENSORS)
    d = mujoco.MjData(m)
    rng = np.random.default_rng(3)
    f = jax.jit(jax.vmap(_terms.inertial_torques, in_axes=(None, 0, 0, 0, None, None, None)))
    q, qd, qdd = rng.uniform(-2.5, 2.5, (3, 8, N))
    ours = np.asarray(f(NOMINAL, q, qd, qdd, MASSES, COMS, TENSORS))
    for k in range(len(q)):
        d.qpos[:], d.qvel[:] = q[k], qd[k]
        mujoco.mj_forward(m, d)
        d.qacc[:] = qdd[k]
        theirs = np.zeros(m.nv)
        mujoco.mj_rne(m, d, 1, theirs)
        np.testing.assert_allclose(ours[k], theirs, rtol=1e-9, atol=1e-9 * np.abs(theirs).max())
    still = np.asarray(f(NOMINAL, q, 0 * qd, 0 * qdd, MASSES, COMS, TENSORS))
    np.testing.assert_allclose(still, 0.0, atol=1e-12)
    tau = _terms.transmission_torques(NOMINAL, q[0], qd[0], qdd[0], MASSES, COMS, TENSORS)
    g = _terms.gravity_torques(NOMINAL, jnp.asarray(q[0]), MASSES, COMS)
    np.testing.assert_allclose(np.asarray(tau), np.asarray(g) - ours[0], rtol=1e-12, atol=1e-9)


def test_a_logs_velocity_and_acceleration():
    """A quadratic through ten rows is exact on a quadratic motion; on a 500 Hz log of a
    one-second cosine leg (a sweep's speed-up) the acceleration errs by under 1 %; between rows
    the derivatives are interpolated, and outside the log they hold its ends."""
    t = np.arange(0.0, 1.0, 0.002)
    quad = np.stack([3.0 * t**2 - t, -0.5 * t**2], axis=-1)
    qd, qdd = _terms.log_motion(t, quad, t[5:-5])
    np.testing.assert_allclose(qd, np.stack([6 * t[5:-5] - 1, -t[5:-5]], -1), atol=1e-9)
    np.testing.assert_allclose(qdd, np.tile([6.0, -1.0], (len(t) - 10, 1)), atol=1e-8)
    cos = 0.7 * (1.0 - np.cos(np.pi * t))[:, None]
    ts = np.linspace(0.05, 0.95, 37)
    qd, qdd = _terms.log_motion(t, cos, ts)
    np.testing.assert_allclose(qd[:, 0], 0.7 * np.pi * np.sin(np.pi * ts), atol=2e-3)
    np.testing.assert_allclose(qdd[:, 0], 0.7 * np.pi**2 * np.cos(np.pi * ts), atol=0.01 * 0.7 * np.pi**2)
    end = _terms.log_motion(t, cos, np.array([5.0]))[0]
    np.testing.assert_allclose(end, _terms.log_motion(t, cos, t[-1:])[0])


def test_the_load_flank_is_the_last_torque_beyond_the_threshold():
    """A torque beyond `PRELOAD_NM` presses the joint to its flank; smaller ones leave it there."""
    tau = np.array([0.0, 0.5, 2.0, 0.3, -0.2, -1.5, 0.9, 1.2])[:, None]
    np.testing.assert_array_equal(_terms.relay(tau)[:, 0], [0, 0, 1, 1, 1, -1, -1, 1])


def test_the_basis_of_a_moving_arm_takes_the_transmissions_torque_and_flank():
    rng = np.random.default_rng(1)
    q, torque = rng.uniform(-1.0, 1.0, (2, 4, N))
    load = np.sign(rng.standard_normal((4, N)))
    b = np.asarray(
        _terms.term_basis(
            ("compliance", "backlash"), NOMINAL, jnp.asarray(q), MASSES, COMS, None, torque, load
        )
    )
    np.testing.assert_allclose(b[..., 0], torque / 1000.0, rtol=1e-12)
    np.testing.assert_allclose(b[..., 1], 0.0)
    np.testing.assert_allclose(b[..., 2], load)


def test_a_payloads_inertia_joins_the_last_link_by_the_parallel_axis_rule():
    """The lumped link's inertia about the joint centre equals the link's and the payload's, each
    shifted to that centre; a point mass adds only its shift."""
    com, inertia = np.array([0.02, -0.01, 0.08]), np.diag([2e-3, 3e-3, 4e-3])
    masses, coms = _terms.with_payload(NOMINAL, MASSES, COMS, 1.5, com)
    lumped = _terms.with_payload_tensors(NOMINAL, MASSES, COMS, TENSORS, 1.5, com, inertia)
    T = np.asarray(NOMINAL.T_last_flange)
    p = T[:3, :3] @ com + T[:3, 3]

    def about(point, m, c, I):
        d = c - point
        return I + m * (d @ d * np.eye(3) - np.outer(d, d))

    origin = np.zeros(3)  # both sides about the last link's origin
    want = about(origin, MASSES[-1], COMS[-1], TENSORS[-1]) + about(
        origin, 1.5, p, T[:3, :3] @ inertia @ T[:3, :3].T
    )
    np.testing.assert_allclose(about(origin, masses[-1], coms[-1], lumped[-1]), want, rtol=1e-12, atol=1e-15)
    point = _terms.with_payload_tensors(NOMINAL, MASSES, COMS, TENSORS, 1.5, com)
    np.testing.assert_allclose(lumped[-1] - point[-1], T[:3, :3] @ inertia @ T[:3, :3].T, atol=1e-15)
    np.testing.assert_array_equal(lumped[:-1], TENSORS[:-1])


@pytest.fixture
def dataset_copy(tmp_path):
    src = ROOT / "data" / "ur5e_sweeps"
    out = tmp_path / "ds"
    shutil.copytree(src, out, ignore=shutil.ignore_patterns("images"))
    (out / "images").symlink_to(src / "images")
    return out


def _with_payload(root: Path, payload) -> None:
    meta = json.loads((root / "metadata.json").read_text())
    meta["robot"]["payload"] = payload
    (root / "metadata.json").write_text(json.dumps(meta))


def test_the_metadata_states_a_payloads_inertia(dataset_copy):
    """`robot.payload.inertia_kgm2` as principal values or a tensor; one no rigid body has is
    refused naming the field."""
    _with_payload(dataset_copy, {"mass_kg": 0.35, "com_m": [0, 0, 0.01], "inertia_kgm2": [3e-4, 6e-4, 9e-4]})
    np.testing.assert_allclose(load_dataset(dataset_copy).payload.inertia_kgm2, np.diag([3e-4, 6e-4, 9e-4]))
    tensor = [[3e-4, 1e-5, 0], [1e-5, 6e-4, 0], [0, 0, 9e-4]]
    _with_payload(dataset_copy, {"mass_kg": 0.35, "com_m": [0, 0, 0.01], "inertia_kgm2": tensor})
    np.testing.assert_allclose(load_dataset(dataset_copy).payload.inertia_kgm2, tensor)
    assert load_dataset(ROOT / "data" / "ur5e_sweeps").payload is None
    for bad, words in (
        ([1e-3, 1e-3, 5e-3], "no rigid body's"),
        ([[3e-4, 1e-4, 0], [0, 6e-4, 0], [0, 0, 9e-4]], "not symmetric"),
        ([-1e-3, 1e-3, 1e-3], "no rigid body's"),
        ([2e3, 2e3, 2e3], "grams or millimetres"),
    ):
        _with_payload(dataset_copy, {"mass_kg": 0.35, "com_m": [0, 0, 0.01], "inertia_kgm2": bad})
        with pytest.raises(DatasetError, match=rf"robot\.payload\.inertia_kgm2.*{words}"):
            load_dataset(dataset_copy)


def test_a_capture_filmed_at_two_speeds_is_told_apart(tmp_path):
    """`SimConfig.sweep_back` films every sweep on the way back too, twice as slowly: each joint's
    segments' peak speeds differ by two, so the terms' torques take the inertial ones; the design
    capture of data/ur5e_sweeps sweeps each joint once, and they stay gravity's."""
    from jaxcal import stages
    from jaxcal.sim.simulate import SimConfig, simulate
    from jaxcal.stages._synchronise import commanded_positions
    from jaxcal.stages._terms import speeds, two_speeds

    def setup_and_log(root):
        setup = stages.setup(root, stages.Options(progress=False))
        return setup, commanded_positions(setup.dataset, setup.nominal)

    config = SimConfig(
        resolution=(64, 48), frames_per_joint=3, range_deg=40.0, sweep_back=2.0, grayscale=True
    )
    setup, log = setup_and_log(simulate(config, tmp_path / "ds", progress=False))
    peaks = speeds(setup, log)
    assert list(peaks) == list(NOMINAL.joint_names) and all(len(p) == 2 for p in peaks.values())
    for fast, slow in peaks.values():  # a raised cosine's peak: pi/2 x 40 deg / 0.1 s, then half that
        np.testing.assert_allclose(
            [fast, slow], [0.5 * np.pi * np.radians(40.0) / 0.1 * r for r in (1, 0.5)], rtol=0.05
        )
    assert two_speeds(setup, log) == NOMINAL.joint_names[0]
    assert two_speeds(*setup_and_log(ROOT / "data" / "ur5e_sweeps")) is None


def test_a_physics_arm_states_the_plates_it_carries_as_its_payload():
    """`jaxcal.sim.physics.flange_payload`: the plates on the flange (not those elsewhere) as one
    payload, their mass, centre and inertia about it as a user would state them from the design."""
    from jaxcal.markers import TargetSpec
    from jaxcal.sim.physics import _plate_inertia, flange_payload
    from jaxcal.sim.scene import PlateSpec

    spec = TargetSpec(
        kind="charuco", dictionary="DICT_4X4_50", squares=(5, 4), square_length=0.04, marker_length=0.03
    )
    T = [np.eye(4), np.eye(4)]
    T[1][:3, 3] = [0.1, 0.0, 0.02]
    T[1][:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    plates = [
        PlateSpec(spec, "flange", T[0]),
        PlateSpec(spec, "flange", T[1]),
        PlateSpec(spec, "wrist_3_link", T[0]),
    ]
    p = flange_payload(plates, 0.35, "flange")
    parts = [_plate_inertia(q, 0.35) for q in plates[:2]]
    centre = 0.5 * (parts[0][0] + parts[1][0])
    assert p["mass_kg"] == pytest.approx(0.7) and np.allclose(p["com_m"], centre)
    want = sum(
        R @ np.diag(d) @ R.T
        + 0.35 * ((c - centre) @ (c - centre) * np.eye(3) - np.outer(c - centre, c - centre))
        for c, R, d in parts
    )
    np.testing.assert_allclose(p["inertia_kgm2"], want, rtol=1e-12)
    assert (
        flange_payload(plates[2:], 0.35, "flange") is None and flange_payload(plates, 0.0, "flange") is None
    )


@pytest.mark.slow
def test_the_physics_arm_filmed_at_two_speeds_is_calibrated_with_its_inertial_torques(tmp_path):
    """MuJoCo's physics arm (an arm the terms were not written from), each 80 deg sweep filmed in
    0.8 s and back in 1.6 s: the terms take the transmissions' inertial torques (the notes say so),
    compliance is kept, and the tool point errs far less than the rigid model's
    (docs/performance.md, over three seeds at 800x600)."""
    from jaxcal import calibrate
    from jaxcal.sim.simulate import SimConfig, simulate

    config = SimConfig(
        resolution=(640, 480), frames_per_joint=12, fps=15.0, range_deg=80.0, sweep_back=2.0, grayscale=True,
        clock_offset_ms=40.0, clock_known=False, arm="physics",
    )  # fmt: skip
    ds = simulate(config, tmp_path / "ds", progress=False)
    assert load_dataset(ds).payload.inertia_kgm2 is not None
    terms = calibrate(ds, progress=False)
    rigid = calibrate(ds, progress=False, terms=())
    assert "compliance" in terms.terms.kept
    assert any("inertial" in n and "two speeds" in n for n in terms.terms.notes), terms.terms.notes
    with_terms, without = terms.validation["ee_rms_mm_after"], rigid.validation["ee_rms_mm_after"]
    assert with_terms < 0.7 * without, (with_terms, without)  # 1.48 against 2.97 mm when written
