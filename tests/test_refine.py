"""Reprojection refinement on analytic corners (no rendering).

A UR5e, a camera 1.5 m away and a 4x3-corner grid on the flange; the truth is
the nominal model with random corrections on the identifiable parameters
only (so the frozen ones are truly at nominal and recovery can be exact).
Every noisy test runs through one compiled `jit(vmap(refine))` over a batch
of trials: plain least squares is the robust solver with `c = reject = inf`.
"""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest
from jax.flatten_util import ravel_pytree

from jaxcal import RobustOptions
from jaxcal._axisfit import apply_correction
from jaxcal._correction import ParameterLayout
from jaxcal._geometry import make_pose, se3_exp, so3_exp
from jaxcal._kinematics import forward_kinematics
from jaxcal._linalg import concurrent_decompositions
from jaxcal._montecarlo import default_setup
from jaxcal._refine import (
    CornerData,
    OtherCameras,
    RefineProblem,
    default_free,
    grid_points,
    identifiable_mask,
    joint_positions,
    make_corner_data,
    projected_corners,
    refine,
    refine_parameter_names,
    reprojection_residuals,
    summarize_refinement,
    sweep_corner_data,
    target_poses,
    zero_params,
)
from jaxcal.robots import load_robot

NOMINAL = load_robot("ur5e")
SETUP = default_setup(NOMINAL)
N = NOMINAL.num_joints
TRIALS = 8
SIGMA_PX = 0.3
PROBLEM = RefineProblem(
    nominal=NOMINAL,
    T_flange_marker0=SETUP.T_flange_marker,
    T_cam_base0=SETUP.T_cam_base,
    K0=jnp.array([[1000.0, 0, 640], [0, 1000, 480], [0, 0, 1]]),
    dist0=jnp.array([-0.05, 0.02, 0.0005, -0.0003, 0.0]),
    offset0_s=jnp.zeros(()),
    data=sweep_corner_data(grid_points(), N, 8, 60.0),
)
P0 = zero_params(N, 1)
FLAT0, UNRAVEL = ravel_pytree(P0)
FLAT0 = np.asarray(FLAT0)
NAMES = refine_parameter_names(NOMINAL, 1)


@pytest.fixture(scope="module")
def free():
    mask, _ = jax.jit(identifiable_mask)(PROBLEM, P0, default_free(N, 1))
    return np.asarray(mask)


def _perturbed(flat0, free, rng, markers: int = 1, angles: int = 0) -> np.ndarray:
    """A truth near `flat0`, on the `free` parameters only: 5 mm / mrad on the
    camera, 1 mm and 2 mrad on the joint origins, 3 mrad zero offsets, 1 mm and
    5 mrad on each mount, 1 % rates, 0.02 rad per-view angles."""
    g = ParameterLayout.sized(N, markers, 0, angles).indices()
    scale = np.zeros(np.size(flat0))
    scale[g["cam"]] = 5e-3
    scale[g["origin"]] = np.tile([1e-3] * 3 + [2e-3] * 3, N)
    scale[g["zero"]] = 3e-3
    scale[g["tool"]] = np.tile([1e-3] * 3 + [5e-3] * 3, markers)
    scale[g["rate"]] = 0.01
    scale[g["angles"]] = 0.02
    return np.asarray(flat0) + scale * rng.standard_normal(np.size(flat0)) * free


@pytest.fixture(scope="module")
def truth(free):
    return _perturbed(FLAT0, free, np.random.default_rng(0))


@pytest.fixture(scope="module")
def solve(free):
    """`jit(vmap)` over trials' pixels; shared start, loss constants traced."""

    def one(pixels, start, c, reject):
        problem = eqx.tree_at(lambda p: p.data.pixels, PROBLEM, pixels)
        return refine(problem, start, free, robust=RobustOptions(c=c, reject=reject))

    return jax.jit(jax.vmap(one, in_axes=(0, None, None, None)))


def _pixels(x_true, key, sigma=SIGMA_PX):
    clean = projected_corners(UNRAVEL(jnp.asarray(x_true)), PROBLEM)
    return clean + sigma * jax.random.normal(key, (TRIALS,) + clean.shape)


def _start(x_true, free):
    # Half-way from nominal to the truth: several mm and mrad off.
    return UNRAVEL(jnp.asarray(FLAT0 + 0.5 * (x_true - FLAT0) * free))


def _flat(res):
    return np.asarray(jax.vmap(lambda p: ravel_pytree(p)[0])(res.params))


def _corrupt(pixels, key, fraction=0.1):
    """Displace `fraction` of the corners by 5-50 px in random directions."""
    k1, k2, k3 = jax.random.split(key, 3)
    hit = jax.random.uniform(k1, pixels.shape[:-1]) < fraction
    size = jax.random.uniform(k2, pixels.shape[:-1], minval=5.0, maxval=50.0)
    angle = jax.random.uniform(k3, pixels.shape[:-1], maxval=2 * jnp.pi)
    shift = size[..., None] * jnp.stack([jnp.cos(angle), jnp.sin(angle)], -1)
    return pixels + jnp.where(hit[..., None], shift, 0.0)


INF = jnp.inf


def _assert_exact_recovery(problem, flat0, unravel, x_true, free, names):
    """From the truth's noise-free corners and a start half-way from `flat0`
    to the truth `x_true` (flattened), plain least squares over the `free`
    parameters gives back every parameter to 1e-8; returns the `RefineResult`."""
    x_true = jnp.asarray(x_true)
    problem = eqx.tree_at(lambda p: p.data.pixels, problem, projected_corners(unravel(x_true), problem))
    start = unravel(jnp.asarray(flat0) + 0.5 * (x_true - jnp.asarray(flat0)) * free)
    res = jax.jit(lambda pb, s: refine(pb, s, free, robust=None))(problem, start)
    assert res.result == optx.RESULTS.successful
    err = np.abs(np.asarray(ravel_pytree(res.params)[0]) - np.asarray(x_true))
    assert err.max() < 1e-8, names[int(np.argmax(err))]
    return res


def test_identifiable_parameters(free):
    frozen = [n for n, f, c in zip(NAMES, free, default_free(N, 1)) if c and not f]
    # The same gauge as the axis fit: 30 kinematic + camera + mount parameters and the 6 rates.
    assert int(free.sum()) == 36
    assert "shoulder_pan_joint.zero_offset" in frozen
    assert all(f"shoulder_pan_joint.origin.{p}" in frozen for p in ("tx", "ty", "tz", "rx", "ry", "rz"))
    assert not free[NAMES.index("clock_offset_ms")] and not free[NAMES.index("intrinsics.fx")]


def test_chain_matches_forward_kinematics():
    x = jnp.asarray(FLAT0 + 1e-2 * np.random.default_rng(3).standard_normal(FLAT0.size))
    p = UNRAVEL(x)
    model, mounts = apply_correction(NOMINAL, SETUP.T_flange_marker, p.correction)
    q = joint_positions(p, PROBLEM)
    T_cb = SETUP.T_cam_base @ se3_exp(p.cam)
    expected = jax.vmap(lambda qq: T_cb @ forward_kinematics(model, qq)[-1] @ mounts[0])(q)
    assert np.allclose(np.asarray(target_poses(p, PROBLEM)), np.asarray(expected), atol=1e-12)


def test_jacobian_matches_finite_differences():
    # A generic point: corrections, a clock offset between log samples, intrinsics moved.
    x = FLAT0 + 1e-3 * np.random.default_rng(1).standard_normal(FLAT0.size)
    x[NAMES.index("clock_offset_ms")] = 3.3
    x = jnp.asarray(x)

    @jax.jit
    def f(x):
        return reprojection_residuals(UNRAVEL(x), PROBLEM).reshape(-1)

    J = np.asarray(jax.jit(jax.jacfwd(f))(x))
    h = 1e-6
    H = h * jnp.eye(FLAT0.size)
    fd = np.asarray((jax.vmap(f)(x + H) - jax.vmap(f)(x - H)) / (2 * h)).T
    scale = np.maximum(np.abs(J).max(0), 1e-3)
    err = np.abs(J - fd).max(0) / scale
    assert err.max() < 1e-5, NAMES[int(np.argmax(err))]


def test_batched_refinement_keeps_lapack_calls_ordered(free):
    """No two LAPACK calls of a vmapped refinement can run side by side: on a
    two-core machine that deadlocks jaxlib's CPU thread pool (see jaxcal._linalg)."""

    def one(pixels):
        return refine(eqx.tree_at(lambda p: p.data.pixels, PROBLEM, pixels), P0, free)

    pixels = jnp.broadcast_to(PROBLEM.data.pixels, (2,) + PROBLEM.data.pixels.shape)
    assert concurrent_decompositions(jax.vmap(one), pixels) == []


def test_exact_recovery_on_noise_free_corners(solve, truth, free):
    pixels = _pixels(truth, jax.random.key(0), sigma=0.0)
    res = solve(pixels, _start(truth, free), 3.0, 3.7)
    assert np.all(np.asarray(res.result == optx.RESULTS.successful))
    err = np.abs(_flat(res) - truth[None])
    assert err.max() < 1e-8, NAMES[int(np.argmax(err.max(0)))]
    assert float(res.residual_rms_px.max()) < 1e-6
    assert np.all(np.asarray(res.std)[:, ~free] == 0)


@pytest.fixture(scope="module")
def clean_run(solve, truth, free):
    pixels = _pixels(truth, jax.random.key(1))
    return pixels, solve(pixels, _start(truth, free), 3.0, 3.7)


def test_standard_deviations_are_honest(clean_run, truth, free):
    _, res = clean_run
    assert np.all(np.asarray(res.result == optx.RESULTS.successful))
    z = (_flat(res) - truth[None])[:, free] / np.asarray(res.std)[:, free]
    rms = float(np.sqrt(np.mean(z**2)))
    assert 0.8 < rms < 1.25, rms
    assert np.allclose(np.asarray(res.sigma_px), SIGMA_PX, rtol=0.1)
    # Clean data: (almost) nothing rejected.
    assert float(np.mean(~np.asarray(res.inlier))) < 0.01


def test_robust_loss_resists_misdetections(solve, clean_run, truth, free):
    pixels, clean = clean_run
    std = np.asarray(clean.std)[:, free]
    bad = _corrupt(pixels, jax.random.key(2))
    # One view entirely misdetected: reported as an outlier frame.
    bad = bad.at[:, 5].add(30.0)
    start = _start(truth, free)
    robust = solve(bad, start, 3.0, 3.7)
    plain = solve(bad, start, INF, INF)

    def err(res):
        return float(np.sqrt(np.mean(((_flat(res) - truth[None])[:, free] / std) ** 2)))

    e_clean, e_robust, e_plain = err(clean), err(robust), err(plain)
    assert e_robust < 1.5 * e_clean, (e_clean, e_robust)
    assert e_plain > 5 * e_clean, (e_clean, e_plain)
    report = summarize_refinement(jax.tree.map(lambda a: a[0], robust), NAMES, PROBLEM.data)
    assert 5 in report["outlier_frames"]
    assert report["outlier_corners"] >= 0.08 * report["corners"]
    assert report["solver"]["result"] == "successful"


def test_plain_least_squares_is_one_round_whatever_else(free):
    """`robust=None` traces one plain round; the keywords of the release before the objects
    (`loss=`, `rounds=`, ...) are Python's `TypeError`."""

    def program(**kw):
        return str(jax.make_jaxpr(lambda pb, s: refine(pb, s, free, **kw))(PROBLEM, P0))

    assert program(robust=None) != program()
    with pytest.raises(TypeError, match="unexpected keyword argument 'loss'"):
        program(loss=None)


def test_bad_arguments(free):
    with pytest.raises(ValueError, match="free mask has shape"):
        refine(PROBLEM, P0, free[:-1])
    with pytest.raises(ValueError, match="loss must be one of"):
        refine(PROBLEM, P0, free, robust=RobustOptions(loss="tukey"))
    with pytest.raises(ValueError, match="no free parameter"):
        refine(PROBLEM, P0, np.zeros_like(free))


def _two_cameras():
    """`PROBLEM` seen by a second camera too, 40 deg round the arm, with other intrinsics."""
    d = PROBLEM.data
    V = d.points.shape[0]

    def twice(a):
        return jnp.concatenate([a, a])

    data = CornerData(
        points=twice(d.points),
        pixels=twice(d.pixels),
        mask=twice(d.mask),
        target=twice(d.target),
        frame=twice(d.frame),
        t_cam=twice(d.t_cam),
        enc_t=d.enc_t,
        enc_q=d.enc_q,
        drift_ppm=d.drift_ppm,
        camera=jnp.repeat(jnp.arange(2), V),
    )
    T_side = SETUP.T_cam_base @ make_pose(so3_exp(jnp.array([0.0, 0.0, 0.7])), jnp.array([0.2, 0.1, 0.0]))
    others = OtherCameras(
        T_cam_base0=T_side[None],
        K=jnp.array([[[900.0, 0, 600], [0, 900, 500], [0, 0, 1]]]),
        dist=jnp.zeros((1, 5)),
    )
    problem = RefineProblem(
        nominal=PROBLEM.nominal,
        T_flange_marker0=PROBLEM.T_flange_marker0,
        T_cam_base0=PROBLEM.T_cam_base0,
        K0=PROBLEM.K0,
        dist0=PROBLEM.dist0,
        offset0_s=PROBLEM.offset0_s,
        data=data,
        other_cameras=others,
    )
    params0 = eqx.tree_at(lambda p: p.other_cams, P0, jnp.zeros((1, 6)), is_leaf=lambda x: x is None)
    return problem, params0, T_side


def test_two_cameras_share_one_robot(truth, free):
    """A second fixed camera: its pose is one more unknown of the same
    refinement; each camera's views go through its own pose and intrinsics,
    and noise-free corners give back both cameras and the robot exactly."""
    problem, params0, T_side = _two_cameras()
    flat0, unravel = ravel_pytree(params0)
    names = refine_parameter_names(NOMINAL, 1, ["side"])
    assert len(names) == flat0.size == FLAT0.size + 6
    assert names[-6:] == [f"side.T_cam_base.{p}" for p in ("tx", "ty", "tz", "rx", "ry", "rz")]
    assert default_free(N, 1, other_cameras=1)[-6:].all()
    # The base frame's gauge is the first camera's: the second adds its own pose and
    # nothing else (exact recovery below shows these 42 parameters are all determined).
    free2 = np.concatenate([free, np.ones(6, bool)])

    side = np.array([2e-3, -1e-3, 3e-3, 2e-3, -3e-3, 1e-3])
    x_true = jnp.asarray(np.concatenate([truth, side]))
    p_true = unravel(x_true)
    # Camera 1's views are camera 0's chain re-based on its own pose.
    model, mounts = apply_correction(NOMINAL, SETUP.T_flange_marker, p_true.correction)
    q = joint_positions(p_true, PROBLEM)
    T1 = T_side @ se3_exp(jnp.asarray(side))
    expected = jax.vmap(lambda qq: T1 @ forward_kinematics(model, qq)[-1] @ mounts[0])(q)
    V = q.shape[0]
    np.testing.assert_allclose(target_poses(p_true, problem)[V:], expected, atol=1e-12)

    res = _assert_exact_recovery(problem, flat0, unravel, x_true, free2, names)
    np.testing.assert_allclose(res.T_cam_bases[1], T1, atol=1e-9)
    np.testing.assert_allclose(res.T_cam_bases[0], res.T_cam_base, atol=0)
    assert float(res.std[-1]) > 0


def test_eye_in_hand_recovers_the_board_and_the_robot():
    """Eye-in-hand: the camera rides on the flange and films a board fixed in
    the world. The chain is the eye-to-hand one with the roles swapped
    (T_board_cam = T_board_base FK(q) T_flange_cam), the corners projected
    through its inverse; noise-free corners give back the robot, the camera
    mount and the board exactly."""
    T_flange_cam = make_pose(jnp.eye(3), jnp.array([0.0, 0.0, 0.03]))
    # The board 0.5 m in front of the camera at the zero configuration, facing it.
    T_cam_board = make_pose(jnp.eye(3), jnp.array([-0.1, -0.08, 0.5]))
    T_base_board = forward_kinematics(NOMINAL, jnp.zeros(N))[-1] @ T_flange_cam @ T_cam_board
    problem = dataclasses.replace(
        PROBLEM,
        T_flange_marker0=T_flange_cam[None],
        T_cam_base0=jnp.linalg.inv(T_base_board),
        data=sweep_corner_data(grid_points(), N, 8, 30.0),
        eye_in_hand=True,
    )
    free, _ = jax.jit(identifiable_mask)(problem, P0, default_free(N, 1))
    free = np.asarray(free)
    assert free[ParameterLayout.sized(N, 1).indices()["tool"]].all(), "the camera mount must be identifiable"
    x_true = jnp.asarray(_perturbed(FLAT0, free, np.random.default_rng(3)))
    p_true = UNRAVEL(x_true)

    model, mounts = apply_correction(NOMINAL, problem.T_flange_marker0, p_true.correction)
    T_bb = problem.T_cam_base0 @ se3_exp(p_true.cam)
    q = joint_positions(p_true, problem)
    expected = jax.vmap(lambda qq: jnp.linalg.inv(T_bb @ forward_kinematics(model, qq)[-1] @ mounts[0]))(q)
    np.testing.assert_allclose(target_poses(p_true, problem), expected, atol=1e-12)
    assert float(jnp.min(target_poses(p_true, problem)[:, 2, 3])) > 0.15  # the board stays in front

    res = _assert_exact_recovery(problem, FLAT0, UNRAVEL, x_true, free, NAMES)
    np.testing.assert_allclose(res.T_flange_marker[0], mounts[0], atol=1e-9)
    with pytest.raises(ValueError, match="eye-in-hand"):
        two = eqx.tree_at(lambda p: p.T_flange_marker0, problem, jnp.stack([T_flange_cam, T_flange_cam]))
        refine(two, zero_params(N, 2), default_free(N, 2))


def test_without_encoders_the_angles_are_unknowns():
    """No encoder log: each view's sweeping-joint angle is an unknown (the
    others at zero); rates and clock drop out (zero Jacobian columns), every
    angle stays identifiable, and noise-free corners give back the robot and
    the angles exactly."""
    d = PROBLEM.data
    V = d.points.shape[0]
    joint = np.repeat(np.arange(N), V // N)
    problem = eqx.tree_at(
        lambda p: p.data.sweep_joint, PROBLEM, jnp.asarray(joint), is_leaf=lambda x: x is None
    )
    commanded = np.asarray(d.enc_q)[np.arange(V), joint]
    params0 = eqx.tree_at(lambda p: p.angles, P0, jnp.asarray(commanded), is_leaf=lambda x: x is None)
    flat0, unravel = ravel_pytree(params0)
    g = ParameterLayout.sized(N, 1, 0, V).indices()
    assert flat0.size == FLAT0.size + V and g["angles"].size == V
    names = refine_parameter_names(NOMINAL, 1, angles=[f"view{v}" for v in range(V)])
    assert len(names) == flat0.size and names[-1] == f"view{V - 1}"
    free, _ = jax.jit(identifiable_mask)(
        problem, params0, default_free(N, 1, rates=True, clock=True, angles=V)
    )
    free = np.asarray(free)
    assert free[g["angles"]].all()
    assert not free[g["rate"]].any() and not free[g["clock"]].any()
    # The zero offsets of the middle joints stay visible (they set the pose while the others sweep).
    assert free[g["zero"]][1:5].all()

    x_true = jnp.asarray(_perturbed(flat0, free, np.random.default_rng(5), angles=V))
    p_true = unravel(x_true)
    q = joint_positions(p_true, problem)
    np.testing.assert_allclose(q[np.arange(V), joint], p_true.angles)
    assert float(jnp.abs(q).sum()) == pytest.approx(float(jnp.abs(p_true.angles).sum()))

    _assert_exact_recovery(problem, flat0, unravel, x_true, free, names)
    with pytest.raises(ValueError, match="without encoders"):
        refine(PROBLEM, params0, free)


def test_targets_on_several_links_under_arbitrary_motion():
    """Markers on every link: each target's chain stops at its link (here the
    flange, the child of joint 1 and the child of joint 3), all joints move at
    once, and noise-free corners give back the robot and all three mounts."""
    rng = np.random.default_rng(7)
    F = 24
    q = rng.uniform(-0.5, 0.5, (F, N))
    t = 0.05 * np.arange(F)
    links = np.array([N + 1, 2, 4])
    F0 = forward_kinematics(NOMINAL, jnp.zeros(N))
    # Each target sits where the flange plate is at zero, rigidly on its own link.
    mounts = jnp.stack([jnp.linalg.inv(F0[k]) @ F0[-1] @ SETUP.T_flange_marker[0] for k in links])
    pts = grid_points()
    M = len(links)
    data = make_corner_data(
        [pts] * (F * M),
        [np.zeros((len(pts), 2))] * (F * M),
        np.tile(np.arange(M), F),
        np.repeat(np.arange(F), M),
        np.repeat(t, M),
        t,
        q,
    )
    problem = dataclasses.replace(PROBLEM, T_flange_marker0=mounts, data=data, target_link=jnp.asarray(links))
    params0 = zero_params(N, M)
    flat0, unravel = ravel_pytree(params0)
    p_true = unravel(flat0)
    expected = jax.vmap(lambda qq: SETUP.T_cam_base @ forward_kinematics(NOMINAL, qq)[links] @ mounts)(q)
    np.testing.assert_allclose(target_poses(p_true, problem), expected.reshape(F * M, 4, 4), atol=1e-12)

    free, _ = jax.jit(identifiable_mask)(problem, params0, default_free(N, M))
    free = np.asarray(free)
    g = ParameterLayout.sized(N, M).indices()
    assert free[g["tool"]].all(), "every mount is seen"
    x_true = jnp.asarray(_perturbed(flat0, free, rng, markers=M))
    p_true = unravel(x_true)
    _assert_exact_recovery(problem, flat0, unravel, x_true, free, refine_parameter_names(NOMINAL, M))
    with pytest.raises(ValueError, match="one link per target"):
        refine(dataclasses.replace(problem, target_link=jnp.asarray(links[:2])), params0, free)
