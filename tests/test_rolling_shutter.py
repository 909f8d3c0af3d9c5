"""Rolling shutter in the refinement, on analytic corners (no rendering).

The sweeps and UR5e of `tests/test_refine.py`; each corner is seen at its
view's time plus its row times the line delay, $t_{cam,v} + y_{vk}\\,\\ell$,
so the corners of one view come from different joint angles. The truth's
corners are generated self-consistently (a corner's row is where it is seen
at its own row's time: a fixed point, reached by iteration).
"""

import dataclasses
import json
from types import SimpleNamespace

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest
from jax.flatten_util import ravel_pytree
from scipy import stats

from jaxcal._correction import Estimate, ParameterLayout
from jaxcal._diagnostics import intrinsics_test, lens_test, line_delay_test, view_information
from jaxcal._montecarlo import default_setup
from jaxcal._refine import (
    RefineProblem,
    grid_points,
    identifiable_mask,
    projected_corners,
    refine,
    sweep_corner_data,
    zero_params,
)
from jaxcal._reprojection import corner_times, joint_positions, rolling
from jaxcal.errors import DatasetError
from jaxcal.io._metadata import CameraInfo, read_cameras
from jaxcal.io._schema import Loc
from jaxcal.io.result import read_estimate, write_estimate
from jaxcal.robots import load_robot
from jaxcal.stages._blur import SUSPECT_SHARE, blur_notes, blur_rows, lost_to_blur
from jaxcal.stages._observe import pose_times
from jaxcal.stages._refine import rolling_shutter
from jaxcal.stages._setup import _line_delay_estimated
from jaxcal.stages.limits import Limits

NOMINAL = load_robot("ur5e")
SETUP = default_setup(NOMINAL)
N = NOMINAL.num_joints
#: 20 ms top-to-bottom over 960 rows.
DELAY_S = 0.02 / 960


def _problem(row: bool, delay0_s: float = 0.0, dt: float = 0.05) -> RefineProblem:
    data = sweep_corner_data(grid_points(), N, 8, 60.0, dt=dt)
    problem = RefineProblem(
        nominal=NOMINAL,
        T_flange_marker0=SETUP.T_flange_marker,
        T_cam_base0=SETUP.T_cam_base,
        K0=jnp.array([[1000.0, 0, 640], [0, 1000, 480], [0, 0, 1]]),
        dist0=jnp.array([-0.05, 0.02, 0.0005, -0.0003, 0.0]),
        offset0_s=jnp.zeros(()),
        data=data,
    )
    if not row:
        return problem
    problem = eqx.tree_at(
        lambda p: (p.data.row, p.line_delay0_s),
        problem,
        (jnp.zeros(data.mask.shape), jnp.array([delay0_s])),
        is_leaf=lambda x: x is None,
    )
    return problem


def _params(row: bool, line_delay_us: float = 0.0):
    p = zero_params(N, 1)
    if row:
        p = eqx.tree_at(lambda q: q.line_delay_us, p, jnp.array([line_delay_us]), is_leaf=lambda x: x is None)
    return p


def _seen(params, problem, iterations: int = 8) -> RefineProblem:
    """`problem` with the corners where a rolling shutter sees them at `params`: each
    corner's row is the row of its own prediction (fixed-point iteration) and the
    pixels are that prediction."""
    for _ in range(iterations):
        u = projected_corners(params, problem)
        problem = eqx.tree_at(lambda p: (p.data.row, p.data.pixels), problem, (u[..., 1], u))
    return problem


def test_corner_time_is_the_frame_time_plus_row_times_delay():
    problem = _problem(True, DELAY_S)
    rows = jnp.asarray(np.random.default_rng(0).uniform(0, 960, problem.data.mask.shape))
    problem = eqx.tree_at(lambda p: p.data.row, problem, rows)
    t = corner_times(_params(True, 1.5), problem)
    expected = problem.data.t_cam[:, None] + rows * (DELAY_S + 1.5e-6)
    np.testing.assert_array_equal(np.asarray(t), np.asarray(expected))
    # Each corner's joint angles are the encoder log at its own time: on these
    # constant-speed ramps, the view's angles plus the speed times the row's delay.
    q_view = np.asarray(joint_positions(_params(True), problem))
    q_corner = np.asarray(joint_positions(_params(True), problem, per_corner=True))
    speed = np.radians(60.0) / 7 / 0.05  # rad/s of the sweeping joint
    # Away from the sweeps' ends: the log's samples are 50 ms apart, read by cubic segments
    # (`interpolate_encoders`) with three-point slopes, which are the ramp's speed except at a
    # sweep's first and last samples (their neighbours jump to the next sweep): views 1 to 5.
    inner = (np.arange(len(q_view)) % 8 > 0) & (np.arange(len(q_view)) % 8 < 6)
    lag = (q_corner - q_view[:, None, :])[inner]
    moving = np.abs(np.diff(q_view, axis=0)).max(axis=0) > 0
    ramp = np.abs(lag).max(axis=-1)
    np.testing.assert_allclose(ramp, speed * np.asarray(rows)[inner] * DELAY_S, rtol=1e-9)
    assert moving.all()


def test_zero_line_delay_predicts_the_global_shutter():
    """A rolling-shutter model with a zero line delay is the global shutter's (the
    pipeline never builds it: a camera with `line_delay_s` 0 or absent has no rows)."""
    glob, roll = _problem(False), _problem(True, 0.0)
    roll = eqx.tree_at(lambda p: p.data.row, roll, jnp.full(roll.data.mask.shape, 300.0))
    assert not rolling(glob) and rolling(roll)
    u_g = projected_corners(_params(False), glob)
    u_r = projected_corners(_params(True), roll)
    np.testing.assert_allclose(np.asarray(u_r), np.asarray(u_g), atol=1e-9)


@pytest.mark.parametrize("given", [True, False])
def test_refinement_recovers_the_line_delay(given):
    """Noise-free corners of a rolling-shutter capture: with the delay given the
    refinement recovers every parameter exactly; estimated (from zero) it recovers
    the delay too. Ignoring it (a global-shutter model) leaves pixels of error."""
    delay0 = DELAY_S if given else 0.0
    problem = _problem(True, delay0)
    p0 = _params(True)
    flat0, unravel = ravel_pytree(p0)
    layout = ParameterLayout.of(NOMINAL, 1, line_delays=("cam0",))
    cand = layout.candidates(rates=True, line_delay=not given)
    rng = np.random.default_rng(1)
    g = layout.indices()
    scale = np.zeros(flat0.size)
    scale[g["cam"]] = 5e-3
    scale[g["origin"]] = np.tile([1e-3] * 3 + [2e-3] * 3, N)
    scale[g["zero"]] = 3e-3
    scale[g["tool"]] = np.tile([1e-3] * 3 + [5e-3] * 3, 1)
    scale[g["rate"]] = 0.01
    free, _ = jax.jit(identifiable_mask)(_seen(p0, problem, 1), p0, cand)  # rows where the corners are
    free = np.asarray(free)
    assert free[g["line_delay"]].all() != given
    x_true = np.asarray(flat0) + scale * rng.standard_normal(flat0.size) * free
    x_true[g["line_delay"]] = 1e6 * (DELAY_S - delay0)
    truth = unravel(jnp.asarray(x_true))
    seen = _seen(truth, problem)
    # The fixed point: every corner's row is where its own time puts it.
    np.testing.assert_allclose(
        np.asarray(seen.data.row), np.asarray(projected_corners(truth, seen))[..., 1], atol=1e-9
    )
    start = unravel(jnp.asarray(np.asarray(flat0) + 0.5 * (x_true - np.asarray(flat0)) * free))
    res = jax.jit(lambda pb, s: refine(pb, s, free, robust=None))(seen, start)
    assert res.result == optx.RESULTS.successful
    err = np.abs(np.asarray(ravel_pytree(res.params)[0]) - x_true)
    names = layout.names()
    # Corners whose times straddle an encoder sample see a kink of the interpolated
    # log, so Levenberg-Marquardt stops within a micro-pixel of the exact fit rather
    # than at round-off: 1e-6 (m, rad) is a thousandth of the tests' corrections.
    assert float(res.residual_rms_px) < 1e-5
    err[g["line_delay"]] = 0.0  # us, checked relatively below
    assert err.max() < 1e-6, names[int(np.argmax(err))]
    assert abs(float(res.line_delay_s[0]) - DELAY_S) < 1e-4 * DELAY_S
    # The same corners predicted without the line delay are pixels off.
    x_none = x_true.copy()
    x_none[g["line_delay"]] = -1e6 * delay0
    off = np.asarray(projected_corners(unravel(jnp.asarray(x_none)), seen) - seen.data.pixels)
    assert np.sqrt(np.mean(off[np.asarray(seen.data.mask)] ** 2)) > 1.0


def test_global_shutter_refinement_flags_the_rows_the_lens_and_the_intrinsics():
    """The score tests of a global-shutter refinement (`line_delay_test`, `lens_test`,
    `intrinsics_test`): on a rolling shutter's corners the first finds the line delay (the other
    parameters absorb none of the within-view skew) far beyond its noise; on corners through a
    stronger lens than the one given the second finds the difference; on corners of a camera whose
    focal length is 6 % longer than the one given, or whose principal point is 25 px to the right,
    the third finds them; on a global shutter's through the given camera all stay within a few
    sigmas."""
    rolling_problem = _problem(True, DELAY_S)
    truth = _params(True)
    seen = _seen(truth, rolling_problem)
    rng = np.random.default_rng(2)
    noise = 0.1 * rng.standard_normal(seen.data.pixels.shape)
    p0 = zero_params(N, 1)
    free = np.asarray(ParameterLayout.of(NOMINAL, 1).candidates(rates=True, clock=True))
    free, _ = jax.jit(identifiable_mask)(_problem(False), p0, free)
    free = np.asarray(free)
    # A lens whose k1 is 0.1 stronger than the one the refinement is given (held): the plate stays
    # within 200-300 px of the centre, where that shifts its corners by up to about 2 px.
    lens = eqx.tree_at(
        lambda p: p.dist0, _problem(False), _problem(False).dist0 + jnp.array([-0.1, 0, 0, 0, 0])
    )
    K0 = _problem(False).K0
    focal = eqx.tree_at(lambda p: p.K0, _problem(False), K0.at[0, 0].mul(1.06).at[1, 1].mul(1.06))
    principal = eqx.tree_at(lambda p: p.K0, _problem(False), K0.at[0, 2].add(25.0))
    cases = (
        ("rolling", seen.data.pixels),
        ("global", projected_corners(p0, _problem(False))),
        ("lens", projected_corners(p0, lens)),
        ("focal", projected_corners(p0, focal)),
        ("principal", projected_corners(p0, principal)),
    )
    out, radial, pinhole = {}, {}, {}
    tests = jax.jit(lambda pb, r: (line_delay_test(pb, r), lens_test(pb, r), intrinsics_test(pb, r)))
    solve = jax.jit(lambda pb, s: refine(pb, s, free, robust=None))
    for name, pixels in cases:
        glob = eqx.tree_at(lambda p: p.data.pixels, _problem(False), pixels + noise)
        res = solve(glob, p0)
        out[name], radial[name], pinhole[name] = tests(glob, res)
        if name == "global":  # the views' information adds up to the normal matrix the covariance inverts
            info = np.asarray(jax.jit(lambda pb, r: view_information(pb, r, free))(glob, res)).sum(axis=0)
            f = np.flatnonzero(free)
            bread = np.asarray(res.cov_model)[np.ix_(f, f)] / float(res.sigma_px) ** 2
            np.testing.assert_allclose(info @ bread, np.eye(f.size), atol=1e-6)
    # A first-order step from a biased fit: within a tenth of the truth.
    assert abs(float(out["rolling"].line_delay_s[0]) / DELAY_S - 1.0) < 0.1
    assert float(out["rolling"].sigmas[0]) > 2 * Limits().shutter_sigmas
    assert float(out["global"].sigmas[0]) < 4.0
    # The lens's score test: k1 found within 15 % (the robot absorbs some of it; k2, which the
    # plate's small radii barely see, is not checked), past its limit; none on the right lens.
    assert abs(float(radial["lens"].distortion[0]) / -0.1 - 1.0) < 0.15
    assert float(radial["lens"].sigmas) > 1.5 * Limits().lens_sigmas
    assert float(radial["global"].sigmas) < 4.0
    # The intrinsics' score test (chi^2 on 4 dof): its step points along the error (the camera's
    # distance absorbs most of a focal length's, so only its sign and size within a factor of 3
    # are checked; a principal point's within 25 %), past the limit; none on the right camera.
    limit = Limits().intrinsics_sigmas
    chi2_limit = float(stats.chi2.isf(stats.norm.sf(limit), 4))
    f_step = np.asarray(pinhole["focal"].step[:2]) / np.diag(np.asarray(K0))[:2]
    assert np.all((f_step > 0.06 / 3) & (f_step < 0.06 * 3)), f_step
    assert float(pinhole["focal"].chi2) > chi2_limit
    step = np.asarray(pinhole["principal"].step)
    assert abs(step[2] / 25.0 - 1.0) < 0.25 and float(pinhole["principal"].chi2) > chi2_limit, step
    assert float(pinhole["global"].chi2) < float(stats.chi2.isf(0.001, 4))


def test_pose_times_and_the_metadata():
    t = np.array([1.0, 2.0, 3.0])
    det = [{"a": _Det(np.array([[0.0, 10.0], [0.0, 30.0]]))}, {}, {"a": _Det(np.array([[5.0, 100.0]]))}]
    assert pose_times(t, det, None) is t and pose_times(t, det, 0.0) is t  # a global shutter: untouched
    np.testing.assert_allclose(pose_times(t, det, 1e-4), [1.0 + 20 * 1e-4, 2.0, 3.0 + 100 * 1e-4], rtol=1e-15)
    info = CameraInfo("cam0", 64, 48, None, np.zeros(5), estimate_line_delay=True)
    d = json.loads(json.dumps(info.to_dict()))
    assert d["line_delay_s"] == "estimate"
    (back,) = read_cameras({"cameras": [d]}, Loc("metadata.json", "cameras"), ())
    assert back.estimate_line_delay and back.line_delay_s is None
    assert rolling_shutter(back) and not rolling_shutter(dataclasses.replace(back, estimate_line_delay=False))
    assert not rolling_shutter(dataclasses.replace(back, estimate_line_delay=False, line_delay_s=0.0))
    with pytest.raises(DatasetError, match="line_delay_s"):
        read_cameras({"cameras": [d | {"line_delay_s": "auto"}]}, Loc("m", "cameras"), ())


class _Det:
    def __init__(self, pixels):
        self.pixels = pixels


def _sweep(found_when):
    """One joint sweeping 80 deg in 2 s on a raised cosine (fastest mid-sweep), 24 frames,
    the target's corners moving 1000 px per radian; found where `found_when(speed)`."""
    enc_t = np.linspace(0.0, 2.0, 1001)
    q = np.radians(80.0) * 0.5 * (1.0 - np.cos(np.pi * enc_t / 2.0))
    t = np.linspace(0.02, 1.98, 24)
    qf = np.interp(t, enc_t, q)
    speed = np.interp(t, enc_t, np.gradient(q, enc_t))
    dets = [
        {"plate": _Det(np.array([[1000.0 * a, 50.0]]))} if found_when(s) else {} for a, s in zip(qf, speed)
    ]
    sync = SimpleNamespace(joint=np.zeros(24, int), log_q=(enc_t, q[:, None]), t_ctrl=t, q=qf[:, None])
    obs = SimpleNamespace(detections=dets, camera=SimpleNamespace(exposure_s=0.01))
    return obs, sync, speed


def test_a_sweep_that_lost_its_fast_frames_names_motion_blur():
    obs, sync, speed = _sweep(lambda s: s < 0.5)
    text = lost_to_blur(None, obs, sync, 0)
    assert text.startswith("motion blur:") and "shorten the exposure" in text
    lost = speed >= 0.5
    assert f"lost in {lost.sum()} of the sweep's 24 frames" in text
    # The smear: exposure x the fastest lost frame's speed x 1000 px/rad (the found frames' own rate).
    assert f"by up to {0.01 * speed[lost].max() * 1000.0:.0f} px" in text
    # Frames lost where the joint is slow, or a smear under two pixels, or none lost: not blur.
    assert lost_to_blur(None, *_sweep(lambda s: s > 0.3)[:2], 0) == ""
    obs, sync, _ = _sweep(lambda s: s < 0.5)
    obs.camera.exposure_s = 1e-3
    assert lost_to_blur(None, obs, sync, 0) == ""
    assert lost_to_blur(None, *_sweep(lambda s: True)[:2], 0) == ""
    # An exposure stated as 0 s is an instant (a simulator's), not an unknown one: no blur, and
    # no "the metadata gives no exposure_s" (trial 14 found it blamed for a shifted clock).
    obs.camera.exposure_s = 0.0
    assert lost_to_blur(None, obs, sync, 0) == ""
    obs.camera.exposure_s = None
    assert "gives no exposure_s" in lost_to_blur(None, obs, sync, 0)


def test_a_sweep_fast_throughout_names_motion_blur():
    """Twice the speed: the target found only in a few fast frames mid-acceleration (where it
    happened to show well), lost in slow and fast ones alike; with the 10 ms exposure most lost
    frames smeared it beyond two pixels, so the blur is named; with a 1 ms one (at most 1.1 px)
    it is not."""
    obs, sync, speed = _sweep(lambda s: 0.6 < s < 0.75)
    lost = ~((speed > 0.6) & (speed < 0.75))
    smeared = lost & (0.01 * speed * 1000.0 > 2.0)
    assert np.median(speed[lost]) < 1.5 * np.median(speed[~lost])  # not "the fast ones"
    text = lost_to_blur(None, obs, sync, 0)
    assert text.startswith(f"motion blur: the target was lost in {lost.sum()} of the sweep's 24 frames, ")
    assert f"{smeared.sum()} of them while the joint turned at" in text
    assert f"smears by up to {0.01 * speed[lost].max() * 1000.0:.0f} px" in text
    obs.camera.exposure_s = 1e-3
    assert lost_to_blur(None, obs, sync, 0) == ""


def test_the_option_estimates_only_unknown_line_delays():
    unknown = CameraInfo("cam0", 64, 48, None, np.zeros(5))
    given = dataclasses.replace(unknown, line_delay_s=1e-5)
    glob = dataclasses.replace(unknown, line_delay_s=0.0)
    assert _line_delay_estimated(unknown).estimate_line_delay
    assert not _line_delay_estimated(given).estimate_line_delay
    assert not _line_delay_estimated(glob).estimate_line_delay  # 0: a global shutter, said so


def test_estimate_file_keeps_the_line_delays(tmp_path):
    """`estimate.npz` holds the layout's line delays (a refinement's vector ends with them)."""
    layout = ParameterLayout.of(NOMINAL, 1, line_delays=("cam0",))
    n = layout.size
    est = Estimate(
        x=jnp.arange(n, dtype=jnp.float64),
        cov=jnp.eye(n),
        free=jnp.ones(n, bool),
        nominal=NOMINAL,
        T_flange_marker0=SETUP.T_flange_marker,
        T_cam_base0=SETUP.T_cam_base,
        reduction_ratio=NOMINAL.reduction_ratio,
        layout=layout,
        mount_names=("plate0",),
    )
    write_estimate(tmp_path / "estimate.npz", est)
    back = read_estimate(tmp_path / "estimate.npz")
    assert back.layout == layout and back.layout.names()[-1] == "cam0.line_delay_us"
    np.testing.assert_array_equal(np.asarray(back.x), np.asarray(est.x))


def test_blur_notes_name_the_joint():
    setup = SimpleNamespace(dataset=SimpleNamespace(joint_names=("j0",)))
    (note,) = blur_notes(setup, *_sweep(lambda s: s < 0.5)[:2])
    assert note.startswith("joint 'j0': motion blur:")
    assert blur_notes(setup, *_sweep(lambda s: True)[:2]) == ()


def test_a_sweep_that_lost_most_of_its_frames_to_blur_is_suspect():
    """The verdict's row: the share of the sweep's frames blur lost, against `SUSPECT_SHARE`
    (half: an arc's precision goes as the square root of its frames). Found below 0.5 rad/s,
    the raised cosine of `_sweep` (peak 1.1 rad/s) keeps its 8 slow end frames; found below 0.9,
    it keeps 14 of 24."""
    setup = SimpleNamespace(dataset=SimpleNamespace(joint_names=("j0",)))
    ((name, share, limit, reason),) = blur_rows(setup, *_sweep(lambda s: s < 0.5)[:2])
    speed = _sweep(lambda s: True)[2]
    kept = int(np.sum(speed < 0.5))
    assert name == "j0.blur_lost_share" and limit == SUSPECT_SHARE
    assert share == pytest.approx(1.0 - kept / 24, abs=1e-15) and share > limit
    assert reason.startswith("joint 'j0': motion blur:")
    assert f"its arc rests on the {kept} slow frames left" in reason and reason.endswith("(stop-and-shoot)")
    ((_, share, _, _),) = blur_rows(setup, *_sweep(lambda s: s < 0.9)[:2])
    assert share == pytest.approx(1.0 - np.sum(speed < 0.9) / 24, abs=1e-15) and share <= SUSPECT_SHARE
    assert blur_rows(setup, *_sweep(lambda s: True)[:2]) == ()
