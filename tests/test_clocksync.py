"""Clock offset from the joint sweeps (`jaxcal._clocksync`), plain and robust."""

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest
from helpers import corrupt_frames
from jax.flatten_util import ravel_pytree

from jaxcal import _lsq
from jaxcal._arcdata import make_arc_data
from jaxcal._arcmodel import arc_residuals, free_mask, initialise_arc
from jaxcal._clocksync import (
    LINEAR_UP_TO_S,
    _with_encoder,
    controller_time,
    fit_clock_offset,
    interpolate_encoders,
)
from jaxcal._geometry import normalize, so3_exp
from jaxcal._options import RobustOptions
from jaxcal.stages._synchronise import interpolate

OFFSET_S = 0.037
SIGMA_P, SIGMA_R = 1e-4, 1e-3


def _sweeps(seed, *, joints=2, frames=40, corrupt=False):
    """Joint-by-joint sweeps that accelerate and decelerate (so a time shift is
    not an angle shift), an encoder log at 250 Hz (controller clock) and camera
    stamps `OFFSET_S` later; positions and orientations with noise, optionally
    10 % of frames corrupted (20 sigma, 10 sigma)."""
    rng = np.random.default_rng(seed)
    T, A = 3.0, 1.2
    enc_t = np.arange(0.0, joints * (T + 1.0) + 1.0, 0.004)
    enc_q = np.zeros((enc_t.size, joints))
    P, O, t_cam, bad = [], [], [], []
    for j in range(joints):
        t0 = 0.5 + j * (T + 1.0)
        s = np.clip((enc_t - t0) / T, 0.0, 1.0)
        enc_q[:, j] = A * (0.5 - 0.5 * np.cos(np.pi * s)) - A / 2
        t_ctrl = t0 + np.linspace(0.05, T - 0.05, frames)
        q = np.interp(t_ctrl, enc_t, enc_q[:, j])
        V = np.asarray(normalize(jnp.asarray(rng.normal(size=3))))
        Q = 0.3 * rng.normal(size=3) + np.array([0.0, 0.0, 1.0])
        p0 = Q + 0.2 * rng.normal(size=3)
        O0 = np.asarray(so3_exp(jnp.asarray(rng.normal(size=3))))
        R = np.asarray(jax.vmap(lambda a, V=V: so3_exp(jnp.asarray(V) * a))(jnp.asarray(1.01 * q)))
        Pj = (Q + np.einsum("fab,b->fa", R, p0 - Q) + SIGMA_P * rng.normal(size=(frames, 3)))[None]
        noise = np.asarray(jax.vmap(so3_exp)(jnp.asarray(SIGMA_R * rng.normal(size=(frames, 3)))))
        Oj = (noise @ R @ O0)[None]
        b = np.zeros((1, frames), bool)
        if corrupt:
            Pj, Oj, b, _ = corrupt_frames(jax.random.key(seed * 100 + j), Pj, Oj)
        P.append(Pj)
        O.append(Oj)
        bad.append(b)
        t_cam.append(t_ctrl + OFFSET_S)
    data = jax.vmap(
        lambda P, O: make_arc_data(P, O, jnp.zeros(frames), sigma_position=SIGMA_P, sigma_rotation=SIGMA_R)
    )(jnp.asarray(np.stack(P)), jnp.asarray(np.stack(O)))
    return data, jnp.asarray(np.stack(t_cam)), jnp.asarray(enc_t), jnp.asarray(enc_q), np.stack(bad)


def _plain_clock_fit(data, t_cam, enc_t, enc_q):
    """The clock fit as it was (one optimistix solve, covariance from the dense Jacobian)."""

    def encoders(offset_s):
        t = controller_time(t_cam, offset_s)
        return jax.vmap(interpolate_encoders, in_axes=(0, None, 1))(t, enc_t, enc_q)

    data0 = jax.vmap(_with_encoder)(data, encoders(0.0))
    params0, refs = jax.vmap(initialise_arc)(data0)
    free = jax.vmap(free_mask)(params0, data0, refs)

    def residuals(y, args):
        p, ms = y
        p = jax.tree.map(lambda x, f: x * f, p, free)
        d = jax.vmap(_with_encoder)(data, encoders(1e-3 * ms))
        return jax.vmap(lambda p, r, dj: arc_residuals(p, (r, dj)))(p, refs, d)

    sol = optx.least_squares(
        residuals,
        _lsq.LMOptions(1e-8, 1e-2).solver(),
        (params0, jnp.zeros(())),
        None,
        max_steps=100,
    )
    flat, unravel = ravel_pytree(sol.value)
    ff = ravel_pytree((free, jnp.ones(())))[0]
    J = jax.jacfwd(lambda x: residuals(unravel(x), None).reshape(-1))(flat) * ff
    r = residuals(sol.value, None)
    sigma2 = jnp.sum(r**2) / (jnp.sum(data.mask) * r.shape[-1] - jnp.sum(ff))
    normal = J.T @ J + jnp.diag(1.0 - ff)
    cov = jnp.linalg.pinv(normal, hermitian=True)
    std = 1e-3 * jnp.sqrt(cov[-1, -1] * sigma2)
    return 1e-3 * sol.value[1], std, sol.stats["num_steps"], jnp.linalg.cond(normal)


def test_plain_fit_recovers_the_offset_as_before():
    data, t_cam, enc_t, enc_q, _ = _sweeps(1)
    res = jax.jit(fit_clock_offset)(data, t_cam, enc_t, enc_q)
    offset, std, steps, cond = jax.jit(_plain_clock_fit)(data, t_cam, enc_t, enc_q)
    assert res.result == optx.RESULTS.successful and int(res.num_steps) == int(steps)
    np.testing.assert_allclose(res.offset_s, offset, rtol=1e-10)
    # Two covariance routes (closed-form vs autodiff Jacobian, different summation orders) invert
    # normal matrices that differ by rounding, a few eps relative. To first order
    # |d(A^-1)_ii| / (A^-1)_ii <= cond(A) * |dA| / |A|, so the variances (and the std, half of it)
    # agree to about cond * eps: here cond ~ 3.5e8, cond * eps ~ 8e-8, and 8.4e-8 / 1.17e-7 were
    # measured on two machines of one kind. 10x for the bound's constants and the summation order.
    rtol = 10 * float(cond) * np.finfo(np.float64).eps
    assert rtol < 1e-5  # still a sharp check: a wrong covariance is off by O(1)
    np.testing.assert_allclose(res.std_s, std, rtol=rtol)
    assert abs(float(res.offset_s) - OFFSET_S) < 4 * float(res.std_s) and float(res.std_s) < 2e-3
    np.testing.assert_array_equal(res.inlier, data.mask)


def test_robust_fit_recovers_the_offset_from_corrupted_frames():
    """Seeded sweeps with 10 % of frames corrupted: the robust clock fit flags
    them, its offset is within its honest standard deviation of the truth
    (normalised error RMS under 1.6), and it beats least squares on the same data."""
    runs = [_sweeps(10 + i, corrupt=True) for i in range(6)]
    stack = lambda xs: jax.tree.map(lambda *a: jnp.stack(a), *xs)  # noqa: E731
    data, t_cam = stack([r[0] for r in runs]), stack([r[1] for r in runs])
    enc_t, enc_q = runs[0][2], runs[0][3]
    bad = np.stack([r[4] for r in runs])
    fit = lambda loss: jax.jit(  # noqa: E731
        jax.vmap(
            lambda d, t: fit_clock_offset(
                d, t, enc_t, enc_q, robust=None if loss is None else RobustOptions(loss)
            )
        )
    )(data, t_cam)
    robust, plain = fit("cauchy"), fit(None)
    assert np.all(np.asarray(robust.result == optx.RESULTS.successful))
    ok = np.asarray(robust.round_results == optx.RESULTS.successful)
    assert ok.shape == (6, 4) and np.all(ok)
    inlier = np.asarray(robust.inlier)
    assert np.all(~inlier[bad]) and np.sum(~inlier & ~bad) <= len(runs)
    err_robust = np.asarray(robust.offset_s) - OFFSET_S
    err_plain = np.asarray(plain.offset_s) - OFFSET_S
    z = err_robust / np.asarray(robust.std_s)
    assert np.sqrt(np.mean(z**2)) < 1.6
    assert np.sqrt(np.mean(err_robust**2)) < 0.7 * np.sqrt(np.mean(err_plain**2))  # 0.43 here


def test_robust_options_are_checked():
    data, t_cam, enc_t, enc_q, _ = _sweeps(2, frames=10)
    with pytest.raises(ValueError, match="loss must be one of"):
        fit_clock_offset(data, t_cam, enc_t, enc_q, robust=RobustOptions("tukey"))


def test_encoder_interpolation_error_follows_from_the_sampling():
    """A 50 Hz log of a cosine sweep (80 deg in 0.8 s, the rendered captures' sweep) read
    at 2001 instants: the cubic Hermite interpolation stays within its bound
    $h^3 \\max|\\dddot q|/24 + h^4 \\max|q^{(4)}|/384$ (`interpolate_encoders`), 2.7e-4 deg
    here, where the linear one errs by up to $h^2 \\max|\\ddot q|/8 = 0.031$ deg; it passes
    through every sample, its derivative in t is the sweep's rate to the next order, and a
    500 Hz log (segments up to `LINEAR_UP_TO_S`) is read linearly, as `jnp.interp` reads it."""
    A, T = np.radians(80.0), 0.8  # rad, s
    w = np.pi / T
    q = lambda t: A * (0.5 - 0.5 * np.cos(w * np.clip(t, 0.0, T)))  # noqa: E731
    # |q''| <= A w^2 / 2, |q'''| <= A w^3 / 2, |q''''| <= A w^4 / 2 inside the sweep.
    t = np.linspace(0.0, T, 2001)
    h = 0.02
    enc_t = np.arange(-0.1, T + 0.1 + h / 2, h)
    enc_q = q(enc_t)
    cubic = np.asarray(interpolate_encoders(jnp.asarray(t), jnp.asarray(enc_t), jnp.asarray(enc_q)))
    bound = h**3 * A * w**3 / 2 / 24 + h**4 * A * w**4 / 2 / 384
    # The sweep starts and stops with a jump in acceleration (rest -> cosine): within one
    # sample of it the slope's parabola straddles the jump, and the error is the
    # acceleration's, h^2 |q''| / 8 at most; the bound holds one sample away from the ends.
    inner = (t > h) & (t < T - h)
    assert np.max(np.abs(cubic - q(t))[inner]) <= bound
    assert np.max(np.abs(cubic - q(t))) <= h**2 * A * w**2 / 2 / 8
    linear = np.interp(t, enc_t, enc_q)
    assert np.max(np.abs(linear - q(t))[inner]) > 10 * bound  # what the cubic removes
    np.testing.assert_allclose(
        interpolate_encoders(jnp.asarray(enc_t), jnp.asarray(enc_t), jnp.asarray(enc_q)), enc_q, atol=1e-15
    )
    # The stage's NumPy reading is the same, joint by joint.
    np.testing.assert_allclose(
        interpolate(t, enc_t, np.stack([enc_q, -enc_q], 1)), np.stack([cubic, -cubic], 1)
    )
    fast_t = np.arange(-0.1, T + 0.1, 0.002)
    assert 0.002 <= LINEAR_UP_TO_S
    np.testing.assert_array_equal(
        interpolate_encoders(jnp.asarray(t), jnp.asarray(fast_t), jnp.asarray(q(fast_t))),
        jnp.interp(jnp.asarray(t), jnp.asarray(fast_t), jnp.asarray(q(fast_t))),
    )
    # The rate: the derivative in t of the 50 Hz interpolation, against the sweep's.
    rate = jax.vmap(jax.grad(lambda s: interpolate_encoders(s, jnp.asarray(enc_t), jnp.asarray(q(enc_t)))))
    # Differentiating the cubic costs one order of h: the rate errs by O(h^2 |q'''|).
    err = np.abs(np.asarray(rate(jnp.asarray(t))) - A * w / 2 * np.sin(w * t))[inner]
    assert np.max(err) <= h**2 * A * w**3 / 2 / 4


def _sweeps_capture(offset_s: float, fps: float = 10.0):
    """Three joints sweeping one after the other (the same 4 s speed profile each, 1 s pauses),
    logged at 100 Hz from t = 0, and a camera at `fps` stamping each frame `offset_s` later
    (camera minus controller) from 2 s into the log: `(obs, log_q)` for `coarse_offset`, the
    camera seeing a plate turn with whichever joint moves."""
    from types import SimpleNamespace

    from jaxcal._npgeom import axis_rotation
    from jaxcal.records_stages import ByTarget

    enc_t = np.arange(0.0, 17.0, 0.01)
    q = np.zeros((len(enc_t), 3))
    for j in range(3):
        s = np.clip((enc_t - 1.0 - 5.0 * j) / 4.0, 0.0, 1.0)
        q[:, j] = np.radians(80.0) * (s - np.sin(2 * np.pi * s) / (2 * np.pi))  # smooth start and stop
    t_ctrl = np.arange(2.0, 16.0, 1.0 / fps)
    q_f = np.stack([np.interp(t_ctrl, enc_t, q[:, j]) for j in range(3)], axis=-1)
    axes = np.eye(3)
    poses = []
    for qq in q_f:
        R = np.eye(3)
        for j in range(3):
            R = R @ axis_rotation(axes[j], np.array([qq[j]]))[0]
        T = np.eye(4)
        T[:3, :3] = R
        poses.append(ByTarget.of({"plate": SimpleNamespace(T_cam_target=T)}))
    obs = SimpleNamespace(
        has_orientation=True, t_cam=t_ctrl + offset_s, poses=poses, found=np.ones(len(poses), bool)
    )
    return obs, (enc_t, q)


@pytest.mark.parametrize("offset_s", [0.04, 10.04, -7.5])
def test_the_coarse_search_finds_a_clock_seconds_off(offset_s):
    """The clock fit converges only near its start; the motion-matching search finds an offset
    of seconds (another epoch, a camera's own time base) to within a frame, and not one sweep
    early or late although every sweep has the same speed profile."""
    from jaxcal.stages._synchronise import coarse_offset

    obs, log_q = _sweeps_capture(offset_s)
    found, r = coarse_offset(obs, log_q)
    assert abs(found - offset_s) < 0.1 and r > 0.9
    # Positions only (a tracker without orientations): nothing to match, no guess.
    obs.has_orientation = False
    assert coarse_offset(obs, log_q) is None
