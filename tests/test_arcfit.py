"""The first error function: arc fit per joint."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest
from helpers import arc_data, arc_problem, corrupt_frames, tree_allclose
from jax.flatten_util import ravel_pytree

from jaxcal import _lsq
from jaxcal._arcdata import make_arc_data, stack_sweeps
from jaxcal._arcfit import arc_outliers, fit_arc, validate_arc_data
from jaxcal._arcmodel import (
    _arc_residuals_autodiff,
    arc_residuals,
    free_mask,
    initialise_arc,
    line_from_params,
    line_to_params,
)
from jaxcal._geometry import normalize, so3_exp, so3_log
from jaxcal._linalg import concurrent_decompositions
from jaxcal._lsq import LMOptions
from jaxcal._options import RobustOptions

fit = jax.jit(fit_arc)


def _line_error(res, truth):
    """(direction error rad, distance of the true point Q from the fitted line m)."""
    V, Q = np.asarray(truth["V"]), np.asarray(truth["Q"])
    d = np.asarray(res.direction)
    ang = np.arctan2(np.linalg.norm(np.cross(d, V)), abs(np.dot(d, V)))
    dq = Q - np.asarray(res.point)
    return ang, np.linalg.norm(dq - np.dot(dq, d) * d)


@pytest.mark.parametrize("encoder", [True, False])
@pytest.mark.parametrize("orientations", [True, False])
def test_exact_recovery(encoder, orientations):
    truth, data = arc_data(jax.random.key(1), encoder=encoder, orientations=orientations)
    res = fit(data)
    assert res.result == optx.RESULTS.successful
    ang, dist = _line_error(res, truth)
    assert ang < 1e-9 and dist < 1e-9
    if encoder:
        assert abs(float(res.rate) - truth["rate"]) < 1e-9
        assert np.sign(np.dot(res.direction, truth["V"])) > 0  # the sign follows the encoder
        np.testing.assert_allclose(res.T_cam_marker0[0, :3, 3], truth["p0"][0], atol=1e-9)
        if orientations:
            np.testing.assert_allclose(res.T_cam_marker0[0, :3, :3], truth["O0"][0], atol=1e-9)
    else:
        assert np.isnan(float(res.rate))  # not identifiable without encoders
        assert not res.has_encoder


def test_several_markers_share_one_axis():
    truth, data = arc_data(jax.random.key(2), markers=3)
    res = fit(data)
    ang, dist = _line_error(res, truth)
    assert ang < 1e-9 and dist < 1e-9
    np.testing.assert_allclose(res.T_cam_marker0[:, :3, 3], truth["p0"], atol=1e-9)


def test_padding_and_mask_are_ignored():
    truth, P, O, alpha = arc_problem(jax.random.key(3), frames=30)
    mask = np.ones(30, bool)
    mask[[0, 7, 8, 20]] = False
    P = np.asarray(P).copy()
    P[0, ~mask] = np.nan  # garbage in the padding must not leak
    data = make_arc_data(P, O, alpha, mask[None])
    res = fit(data)
    ang, dist = _line_error(res, truth)
    assert ang < 1e-9 and dist < 1e-9
    assert int(res.num_frames) == 26


def test_noisy_recovery_matches_reported_covariance():
    """Seeded Monte Carlo: normalised errors have unit RMS (the covariance is honest)."""
    keys = jax.random.split(jax.random.key(4), 300)
    truths, datas = jax.vmap(lambda k: arc_data(k, noisy=True))(keys)
    res = jax.jit(jax.vmap(fit_arc))(datas)
    assert np.all(np.asarray(res.result == optx.RESULTS.successful))
    # Rate: scalar normalised error.
    z_rate = (np.asarray(res.rate) - 1.01) / np.sqrt(np.asarray(res.rate_var))
    assert 0.8 < np.sqrt(np.mean(z_rate**2)) < 1.25
    # Direction: error projected on the fitted tangent plane, Mahalanobis with cov[:3, :3] (rank 2).
    dV = np.asarray(truths["V"] - res.direction)
    covV = np.asarray(res.cov[:, :3, :3])
    m2 = np.einsum("na,nab,nb->n", dV, np.linalg.pinv(covV, hermitian=True, rcond=1e-9), dV)
    assert 0.8 < np.sqrt(np.mean(m2) / 2.0) < 1.25
    # The whitened residual RMS is about one when the noise model is right.
    assert 0.9 < float(np.median(res.residual_rms)) < 1.1


def test_jit_equals_vmap_equals_loop():
    keys = jax.random.split(jax.random.key(5), 4)
    _, datas = jax.vmap(lambda k: arc_data(k, noisy=True))(keys)
    batched = jax.jit(jax.vmap(fit_arc))(datas)
    for i in range(4):
        one = jax.tree.map(lambda x: x[i], datas)
        r = fit(one)  # a Python loop of single jitted solves
        assert tree_allclose(r.direction, batched.direction[i], atol=1e-10)
        assert tree_allclose(r.point, batched.point[i], atol=1e-10)
        assert tree_allclose(r.rate, batched.rate[i], atol=1e-10)


@pytest.mark.parametrize("encoder", [True, False])
def test_autodiff_matches_finite_differences(encoder):
    _, data = arc_data(jax.random.key(6), noisy=True, encoder=encoder, frames=8)
    params, ref = jax.jit(initialise_arc)(data)  # one program (op by op: ~150 small ones)
    params = jax.tree.map(lambda x: x + 1e-3, params)  # away from the solution
    flat, unravel = jax.flatten_util.ravel_pytree(params)

    @jax.jit
    def f(x):
        return arc_residuals(unravel(x), (ref, data)).reshape(-1)

    Jf = jax.jit(jax.jacfwd(f))(flat)
    Jr = jax.jit(jax.jacrev(f))(flat)
    np.testing.assert_allclose(Jf, Jr, rtol=1e-10, atol=1e-8)
    h = 1e-6
    steps = h * np.eye(flat.size)
    fd = ((jax.vmap(f)(flat + steps) - jax.vmap(f)(flat - steps)) / (2 * h)).T
    np.testing.assert_allclose(Jf, fd, rtol=1e-5, atol=1e-3 * np.abs(Jf).max() * 1e-3)


@pytest.mark.parametrize(("encoder", "orientations"), [(True, False), (False, True)])
def test_closed_form_jacobian_matches_autodiff(encoder, orientations):
    """The custom JVP of `arc_residuals` equals JAX's own derivative (forward and
    reverse, two markers, a masked frame with NaN padding), and derivatives
    with respect to the encoder angles (a clock offset) still flow."""
    _, P, O, alpha = arc_problem(jax.random.key(12), frames=8, markers=2, sigma_p=1e-4, sigma_r=1e-3)
    mask = np.ones((2, 8), bool)
    mask[0, 3] = mask[1, 6] = False
    P = np.where(mask[..., None], np.asarray(P), np.nan)
    data = make_arc_data(P, O if orientations else None, alpha if encoder else None, mask)
    params, ref = jax.jit(initialise_arc)(data)
    params = jax.tree.map(lambda x: x + 1e-2, params)
    flat, unravel = jax.flatten_util.ravel_pytree(params)

    def f(fn):
        return lambda x: fn(unravel(x), (ref, data)).reshape(-1)

    J_auto = jax.jit(jax.jacfwd(f(_arc_residuals_autodiff)))(flat)
    assert np.all(np.isfinite(J_auto))
    np.testing.assert_allclose(jax.jit(jax.jacfwd(f(arc_residuals)))(flat), J_auto, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(jax.jit(jax.jacrev(f(arc_residuals)))(flat), J_auto, rtol=1e-12, atol=1e-9)
    if encoder:

        def g(fn):
            return lambda e: fn(params, (ref, eqx.tree_at(lambda d: d.encoder, data, e))).reshape(-1)

        J_enc = jax.jit(jax.jacfwd(g(_arc_residuals_autodiff)))(data.encoder)
        assert np.abs(J_enc).max() > 0
        np.testing.assert_allclose(
            jax.jit(jax.jacfwd(g(arc_residuals)))(data.encoder), J_enc, rtol=1e-12, atol=1e-9
        )
        np.testing.assert_allclose(
            jax.jit(jax.jacrev(g(arc_residuals)))(data.encoder), J_enc, rtol=1e-12, atol=1e-9
        )


def test_line_coordinates_round_trip():
    R = jnp.linalg.qr(jax.random.normal(jax.random.key(7), (3, 3)))[0]
    c = jnp.array([0.1, -0.2, 0.9])
    line = jnp.array([0.01, -0.02, 0.003, 0.004])
    Q, V = line_from_params(line, R, c)
    np.testing.assert_allclose(line_to_params(Q + 0.37 * V, V, R, c), line, atol=1e-14)
    np.testing.assert_allclose(line_to_params(Q, -V, R, c, sign_free=True), line, atol=1e-14)


def test_max_steps_reports_optimistix_code():
    _, data = arc_data(jax.random.key(8), noisy=True)
    res = jax.jit(lambda d: fit_arc(d, options=LMOptions(max_steps=1)))(data)
    assert res.result == optx.RESULTS.nonlinear_max_steps_reached


# --------------------------------------------------------------------------- bad input


def _good():
    return arc_data(jax.random.key(9))[1]


def test_too_few_frames():
    data = _good()
    mask = np.zeros_like(np.asarray(data.mask))
    mask[:, :4] = True
    with pytest.raises(ValueError, match="joint 'elbow'.*only 4 valid frames"):
        validate_arc_data(eqx.tree_at(lambda d: d.mask, data, jnp.asarray(mask)), "elbow")


def test_sweep_too_small():
    _, P, O, alpha = arc_problem(jax.random.key(10), span=np.radians(3.0))
    with pytest.raises(ValueError, match="joint 'j2'.*covers 3.0.*at least 5"):
        validate_arc_data(make_arc_data(P, O, alpha), "j2")
    with pytest.raises(ValueError, match="joint 'j2'.*covers 3.0"):
        validate_arc_data(make_arc_data(P, O, None), "j2")  # from the motion itself


def test_non_finite_values():
    data = _good()
    P = np.asarray(data.positions).copy()
    P[0, 5, 1] = np.nan
    with pytest.raises(ValueError, match="joint 'j1'.*non-finite position at marker 0, frame 5"):
        validate_arc_data(eqx.tree_at(lambda d: d.positions, data, jnp.asarray(P)), "j1")
    enc = np.asarray(data.encoder).copy()
    enc[3] = np.inf
    with pytest.raises(ValueError, match="joint 'j1'.*non-finite encoder angle at frame 3"):
        validate_arc_data(eqx.tree_at(lambda d: d.encoder, data, jnp.asarray(enc)), "j1")


def test_mismatched_lengths():
    data = _good()
    with pytest.raises(ValueError, match="joint 'j3'.*39 encoder angles for 40 frames"):
        validate_arc_data(eqx.tree_at(lambda d: d.encoder, data, data.encoder[:-1]), "j3")
    with pytest.raises(ValueError, match="joint 'j3'.*orientations have shape"):
        validate_arc_data(eqx.tree_at(lambda d: d.orientations, data, data.orientations[:, :-1]), "j3")


def test_good_data_passes_validation():
    validate_arc_data(_good(), "j1")


# --------------------------------------------------------------------------- the plain fit, by blocks


def _plain_fit(data, *, rtol=1e-8, atol=3e-2, max_steps=50):
    """The fit as it was before robust losses and blocks: one optimistix
    Levenberg-Marquardt on the flat `ArcParams` (per-frame angles included),
    covariance $\\hat\\sigma^2 (J^TJ)^{+}$ of the dense autodiff Jacobian."""
    params0, ref = initialise_arc(data)
    free = free_mask(params0, data, ref)

    def fn(p, args):
        return arc_residuals(jax.tree.map(lambda x, f: x * f, p, free), args)

    sol = optx.least_squares(
        fn, _lsq.LMOptions(rtol, atol).solver(), params0, (ref, data), max_steps=max_steps
    )
    params = jax.tree.map(lambda x, f: x * f, sol.value, free)
    flat, unravel = ravel_pytree(params)
    ff = ravel_pytree(free)[0]
    J = jax.jacfwd(lambda x: arc_residuals(unravel(x), (ref, data)).reshape(-1))(flat) * ff
    r = arc_residuals(params, (ref, data))
    sigma2 = jnp.sum(r**2) / (jnp.sum(data.mask) * r.shape[-1] - jnp.sum(ff))
    cov = jnp.linalg.pinv(J.T @ J + jnp.diag(1.0 - ff), hermitian=True) * ff[:, None] * ff[None, :] * sigma2
    idx = jax.tree.map(lambda x: x.astype(int), unravel(jnp.arange(flat.size, dtype=float)))
    has_rot = data.orientations is not None
    meas_i = jnp.concatenate([idx.line, jnp.ravel(idx.p0)] + ([jnp.ravel(idx.r0)] if has_rot else []))
    meas = jnp.concatenate([params.line, params.p0.ravel()] + ([params.r0.ravel()] if has_rot else []))
    return dict(
        meas=meas,
        meas_cov=cov[jnp.ix_(meas_i, meas_i)],
        rate=params.rate,
        rate_var=cov[idx.rate, idx.rate],
        angles=params.rate * data.encoder if data.encoder is not None else params.angles * ref.gauge,
        num_steps=sol.stats["num_steps"],
    )


@pytest.mark.parametrize("encoder", [True, False])
@pytest.mark.parametrize("orientations", [True, False])
def test_plain_fit_reproduces_the_dense_solve(encoder, orientations):
    """`loss=None` (the default) is the least-squares fit of before: with
    encoders the same optimistix solve, without it the same iteration by
    blocks (`jaxcal._schur`, the angles eliminated). Same steps, same
    solution, the same covariance (here from the dense Jacobian's inverse);
    two markers and a masked frame."""
    _, P, O, alpha = arc_problem(jax.random.key(21), frames=30, markers=2, sigma_p=1e-4, sigma_r=1e-3)
    mask = np.ones((2, 30), bool)
    mask[0, 4] = mask[1, 17] = False
    data = make_arc_data(P, O if orientations else None, alpha if encoder else None, mask)
    res = fit(data)
    ref = jax.jit(_plain_fit)(data)
    assert res.result == optx.RESULTS.successful
    assert int(res.num_steps) == int(ref["num_steps"])
    np.testing.assert_allclose(res.meas, ref["meas"], rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(res.angles, ref["angles"], rtol=1e-10, atol=1e-12)
    scale = np.abs(ref["meas_cov"]).max()
    np.testing.assert_allclose(res.meas_cov, ref["meas_cov"], atol=1e-9 * scale)
    if encoder:
        np.testing.assert_allclose(res.rate, ref["rate"], rtol=1e-12)
        np.testing.assert_allclose(res.rate_var, ref["rate_var"], rtol=1e-9)
    np.testing.assert_array_equal(res.weights, mask)
    np.testing.assert_array_equal(res.inlier, mask)
    assert res.round_steps.shape == (1,) and int(res.round_steps[0]) == int(res.num_steps)
    np.testing.assert_allclose(
        res.sample_residuals, np.linalg.norm(arc_residuals_at(res, data), axis=-1), atol=1e-9
    )


def arc_residuals_at(res, data):
    """The whitened residuals of a fit, recomputed from its reported poses (an oracle for `sample_residuals`)."""
    Q, V = np.asarray(res.point), np.asarray(res.direction)
    T0 = np.asarray(res.T_cam_marker0)
    phi = np.asarray(res.angles)
    R = np.asarray(jax.vmap(lambda a: so3_exp(jnp.asarray(V) * a))(jnp.asarray(phi)))  # (F, 3, 3)
    P_hat = Q + np.einsum("fab,mb->mfa", R, T0[:, :3, 3] - Q)
    e = P_hat - np.asarray(data.positions)
    if data.orientations is not None:
        O_hat = np.einsum("fab,mbc->mfac", R, T0[:, :3, :3])
        theta = np.asarray(
            jax.vmap(jax.vmap(so3_log))(
                jnp.asarray(np.asarray(data.orientations) @ np.swapaxes(O_hat, -1, -2))
            )
        )
        e = np.concatenate([e, theta], axis=-1)
    r = np.einsum("mfab,mfb->mfa", np.asarray(data.sqrt_info), e)
    return np.where(np.asarray(data.mask)[..., None], r, 0.0)


def test_long_sweep_without_encoders_by_blocks_matches_the_dense_solve():
    """300 frames, positions only, no encoder: the case that needed gigabytes
    through the dense Jacobian; tight tolerances, both converge to the optimum."""
    _, data = arc_data(jax.random.key(22), noisy=True, encoder=False, orientations=False, frames=300)
    res = jax.jit(lambda d: fit_arc(d, options=LMOptions(rtol=1e-10, atol=1e-6, max_steps=50)))(data)
    ref = jax.jit(lambda d: _plain_fit(d, rtol=1e-10, atol=1e-6))(data)
    np.testing.assert_allclose(res.meas, ref["meas"], rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(res.angles, ref["angles"], rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(
        res.meas_cov, ref["meas_cov"], rtol=1e-8, atol=1e-8 * np.abs(ref["meas_cov"]).max()
    )


# --------------------------------------------------------------------------- robust loss


def _line_errors(res, truth, encoder):
    """Per trial: (direction error rad, distance of the true point from the line m, rate error,
    Mahalanobis distance^2 of the true line coordinates under `meas_cov[:4, :4]`)."""
    V, Q = np.asarray(truth["V"]), np.asarray(truth["Q"])
    d = np.asarray(res.direction)
    ang = np.arctan2(np.linalg.norm(np.cross(d, V), axis=-1), np.abs(np.sum(d * V, -1)))
    dq = Q - np.asarray(res.point)
    dist = np.linalg.norm(dq - np.sum(dq * d, -1, keepdims=True) * d, axis=-1)
    rate = np.abs(np.asarray(res.rate) - 1.01) if encoder else np.zeros_like(ang)
    true_line = jax.vmap(lambda q, v, R, c: line_to_params(q, v, R, c, sign_free=not encoder))(
        truth["Q"], truth["V"], res.R_ref, res.c
    )
    dl = np.asarray(true_line - res.meas[:, :4])
    m2 = np.einsum("na,nab,nb->n", dl, np.linalg.inv(np.asarray(res.meas_cov[:, :4, :4])), dl)
    return ang, dist, rate, m2


def _corrupted_trials(seed, n, *, encoder, orientations, frames):
    """`n` seeded sweeps: clean data, the same with 10 % of frames corrupted (20 sigma in
    position, 10 sigma in orientation), the corrupted samples and their displacements."""
    keys = jax.random.split(jax.random.key(seed), n)
    truths, clean, dirty, bad, dP = [], [], [], [], []
    for k in keys:
        truth, P, O, alpha = arc_problem(k, frames=frames, sigma_p=1e-4, sigma_r=1e-3)
        P2, O2, b, d = corrupt_frames(jax.random.fold_in(k, 1), P, O)
        make = lambda P, O: make_arc_data(P, O if orientations else None, alpha if encoder else None)  # noqa: E731
        truths.append(truth)
        clean.append(make(P, O))
        dirty.append(make(P2, O2))
        bad.append(b)
        dP.append(d)
    stack = lambda xs: jax.tree.map(lambda *a: jnp.stack(a), *xs)  # noqa: E731
    return stack(truths), stack(clean), stack(dirty), np.stack(bad), np.stack(dP)


@pytest.mark.parametrize(
    ("encoder", "orientations", "frames"),
    [(True, True, 40), (True, False, 40), (False, True, 40), (False, False, 40), (False, False, 300)],
)
def test_robust_fit_rejects_corrupted_frames(encoder, orientations, frames):
    """10 % of frames corrupted: the Cauchy fit flags them (every one the model
    can see: without encoders a displacement along the arc only moves that
    frame's angle), flags at most one clean sample per sweep on average, its
    errors stay within 1.5x those of least squares on the clean data (which
    it beats by far on the corrupted data), and its reported covariance is
    honest: normalised errors with RMS in 0.7-1.4. Seeded trials."""
    n = 48 if frames == 40 else 12
    truth, clean, dirty, bad, dP = _corrupted_trials(
        30 + frames, n, encoder=encoder, orientations=orientations, frames=frames
    )
    plain = jax.jit(jax.vmap(fit_arc))
    robust = jax.jit(jax.vmap(lambda d: fit_arc(d, robust=RobustOptions("cauchy"))))(dirty)
    assert np.all(np.asarray(robust.result == optx.RESULTS.successful))
    e_clean = _line_errors(plain(clean), truth, encoder)
    e_robust = _line_errors(robust, truth, encoder)
    e_plain = _line_errors(plain(dirty), truth, encoder)
    rms = lambda x: np.sqrt(np.mean(x**2))  # noqa: E731
    for i in range(2 + encoder):
        assert rms(e_robust[i]) < 1.5 * rms(e_clean[i]), i
        assert rms(e_plain[i]) > rms(e_robust[i]), i
    assert rms(e_plain[0]) > 2.0 * rms(e_clean[0])  # the corruption matters
    # Flags.
    inlier = np.asarray(robust.inlier)
    assert np.sum(~inlier & ~bad) / n <= 1.0
    if encoder:
        assert np.all(~inlier[bad])
    else:
        # What the model can see of a displacement: its part across the arc's tangent.
        V = np.asarray(truth["V"])[:, None, None, :]
        tangent = np.cross(V, np.asarray(clean.positions) - np.asarray(truth["Q"])[:, None, None, :])
        tangent /= np.linalg.norm(tangent, axis=-1, keepdims=True)
        across = np.linalg.norm(dP - np.sum(dP * tangent, -1, keepdims=True) * tangent, axis=-1)
        assert np.all(~inlier[bad & (across > 6e-4)])
        assert np.mean(~inlier[bad]) > 0.9
    np.testing.assert_array_equal(np.asarray(robust.weights), inlier.astype(float))
    # Honest standard deviations: the line's Mahalanobis distance (4 dof), the rate's z.
    assert 0.7 < np.sqrt(np.mean(e_robust[3] / 4.0)) < 1.4
    if encoder:
        z = e_robust[2] / np.sqrt(np.asarray(robust.rate_var))
        assert 0.7 < np.sqrt(np.mean(z**2)) < 1.4
    # The residuals of the rejected samples are large, the noise scale about one.
    assert np.all(np.asarray(robust.sample_residuals)[bad & ~inlier] > 3.0)
    assert 0.8 < float(np.median(robust.robust_scale)) < 1.25


def _far_end_sweeps(seed, n, *, extra, frames=40):
    """`n` seeded one-marker sweeps with encoders: `frames - 1` frames over 0.2 rad
    and the last at 1.2 rad (the frames between lost), which decides the rate
    almost alone; that frame is turned `extra` rad further about the axis than its
    encoder says (positions and orientations alike, a consistent wrong angle)."""

    def one(key):
        k = jax.random.split(key, 6)
        V = normalize(jax.random.normal(k[0], (3,)))
        Q = 0.3 * jax.random.normal(k[1], (3,)) + jnp.array([0.0, 0.0, 1.0])
        p0 = Q + 0.2 * jax.random.normal(k[2], (1, 3))
        O0 = jax.vmap(so3_exp)(jax.random.normal(k[3], (1, 3)))
        alpha = jnp.concatenate([jnp.linspace(-0.2, 0.0, frames - 1), jnp.array([1.2])])
        R = jax.vmap(lambda a: so3_exp(V * a))(1.01 * alpha + jnp.zeros(frames).at[-1].set(extra))
        P = Q + jnp.einsum("fab,mb->mfa", R, p0 - Q) + 1e-4 * jax.random.normal(k[4], (1, frames, 3))
        dR = jax.vmap(jax.vmap(so3_exp))(1e-3 * jax.random.normal(k[5], (1, frames, 3)))
        return make_arc_data(P, jnp.einsum("mfab,fbc,mcd->mfad", dR, R, O0), alpha)

    return jax.jit(jax.vmap(one))(jax.random.split(jax.random.key(seed), n))


def test_robust_fit_unmasks_a_high_leverage_outlier():
    """An outlier at the end of a sweep that decides the rate pulls the fit onto
    itself: its least-squares residual is no larger than the clean frames' (masked),
    but its deletion residual (`jaxcal._robust`) is, so the robust fit names it in
    every trial and recovers the rate with honest standard deviations. Seeded
    trials, the shapes of `test_robust_fit_rejects_corrupted_frames` (its compiled fits)."""
    data = _far_end_sweeps(7, 48, extra=0.02)
    plain = jax.jit(jax.vmap(fit_arc))(data)
    robust = jax.jit(jax.vmap(lambda d: fit_arc(d, robust=RobustOptions("cauchy"))))(data)
    e = np.asarray(plain.sample_residuals[:, 0])
    assert np.mean(e[:, -1] < e[:, :-1].max(axis=1)) > 0.75  # masked
    inlier = np.asarray(robust.inlier[:, 0])
    assert not inlier[:, -1].any()  # named in every trial
    assert np.sum(~inlier[:, :-1]) <= 5  # of 48 x 39 clean frames
    np.testing.assert_array_equal(
        arc_outliers(jax.tree.map(lambda x: x[0], robust), data.mask[0])[-1], [0, 39]
    )
    z = lambda r: (np.asarray(r.rate) - 1.01) / np.sqrt(np.asarray(r.rate_var))  # noqa: E731
    assert 0.7 < np.sqrt(np.mean(z(robust) ** 2)) < 1.4
    assert np.sqrt(np.mean(z(plain) ** 2)) > 5.0  # least squares follows the outlier


def test_robust_fit_reports_every_round():
    """Rounds: three IRLS solves and the inlier solve, each with its status and
    steps; which samples are rejected does not depend on `max_steps` once
    every round converges; a round that runs out of steps is reported."""
    _, _, dirty, bad, _ = _corrupted_trials(40, 1, encoder=False, orientations=True, frames=40)
    data = jax.tree.map(lambda x: x[0], dirty)
    res = jax.jit(lambda d: fit_arc(d, robust=RobustOptions("huber")))(data)
    ok = np.asarray(res.round_results == optx.RESULTS.successful)
    assert ok.shape == (4,) and np.all(ok) and res.round_steps.shape == (4,)
    assert int(res.num_steps) == int(np.sum(res.round_steps))
    np.testing.assert_array_equal(~np.asarray(res.inlier), bad[0])
    np.testing.assert_array_equal(arc_outliers(res, data.mask), np.argwhere(bad[0]))
    more = jax.jit(lambda d: fit_arc(d, robust=RobustOptions("huber"), options=LMOptions(max_steps=500)))(
        data
    )
    np.testing.assert_array_equal(more.inlier, res.inlier)
    np.testing.assert_allclose(more.meas, res.meas, rtol=1e-12)
    short = jax.jit(lambda d: fit_arc(d, robust=RobustOptions("huber"), options=LMOptions(max_steps=1)))(data)
    assert short.result == optx.RESULTS.nonlinear_max_steps_reached
    assert np.all(np.asarray(short.round_results == optx.RESULTS.nonlinear_max_steps_reached))
    assert np.all(np.asarray(short.round_steps) == 1)
    # Without the inlier solve: the soft rounds only.
    soft = jax.jit(lambda d: fit_arc(d, robust=RobustOptions("cauchy", reject=None, rounds=2)))(data)
    assert soft.round_steps.shape == (2,)
    assert np.all(np.asarray(soft.weights)[bad[0]] < 0.1) and np.all(np.asarray(soft.weights)[~bad[0]] > 0.3)


def test_robust_options_are_checked():
    data = _good()
    with pytest.raises(ValueError, match="loss must be one of"):
        fit_arc(data, robust=RobustOptions("l1"))
    with pytest.raises(ValueError, match="rounds must be at least 1"):
        fit_arc(data, robust=RobustOptions("cauchy", rounds=0))


@pytest.mark.parametrize("encoder", [True, False])
def test_batched_fits_have_no_unordered_decompositions(encoder):
    """The vmapped robust fit (leverages, solves, covariance) keeps its LAPACK calls ordered (`_linalg`)."""
    keys = jax.random.split(jax.random.key(23), 3)
    _, datas = jax.vmap(lambda k: arc_data(k, noisy=True, encoder=encoder, frames=12))(keys)
    assert (
        concurrent_decompositions(jax.vmap(lambda d: fit_arc(d, robust=RobustOptions("cauchy"))), datas) == []
    )
    assert concurrent_decompositions(jax.vmap(fit_arc), datas) == []


# --------------------------------------------------------------------------- several sweeps


@pytest.mark.parametrize("encoder", [True, False])
def test_stack_sweeps_pads_to_a_bucket_and_changes_nothing(encoder):
    """Sweeps of 30 and 45 frames (one with two markers) stacked to 64 frames: the batched fit equals each fit alone."""
    _, d1 = arc_data(jax.random.key(24), noisy=True, encoder=encoder, frames=30, markers=2)
    _, d2 = arc_data(jax.random.key(25), noisy=True, encoder=encoder, frames=45)
    stacked = stack_sweeps([d1, d2])
    assert stacked.positions.shape == (2, 2, 64, 3) and stacked.mask.shape == (2, 2, 64)
    assert not np.any(np.asarray(stacked.mask[1, 1])) and not np.any(np.asarray(stacked.mask[0, :, 30:]))
    batched = jax.jit(jax.vmap(fit_arc))(stacked)
    for i, (d, F) in enumerate([(d1, 30), (d2, 45)]):
        one = fit(d)
        np.testing.assert_allclose(batched.direction[i], one.direction, atol=1e-10)
        np.testing.assert_allclose(batched.point[i], one.point, atol=1e-10)
        np.testing.assert_allclose(batched.angles[i, :F], one.angles, atol=1e-10)
        np.testing.assert_allclose(batched.meas_cov[i, :4, :4], one.meas_cov[:4, :4], rtol=1e-8)
        if encoder:
            np.testing.assert_allclose(batched.rate[i], one.rate, atol=1e-10)
    # From arrays, and the buckets.
    P = [np.asarray(d1.positions), np.asarray(d2.positions[0])]
    O = [np.asarray(d1.orientations), np.asarray(d2.orientations[0])]
    E = [np.asarray(d1.encoder), np.asarray(d2.encoder)] if encoder else None
    from_arrays = stack_sweeps(P, O, E, bucket=16)
    assert from_arrays.mask.shape == (2, 2, 48)
    assert stack_sweeps(P, O, E, bucket="pow2").mask.shape == (2, 2, 64)
    np.testing.assert_allclose(from_arrays.sqrt_info[0, 0, 0], np.diag([1e4] * 3 + [1e3] * 3))


def test_stack_sweeps_checks_its_input():
    _, d1 = arc_data(jax.random.key(26), frames=10)
    _, d2 = arc_data(jax.random.key(27), frames=12, encoder=False)
    with pytest.raises(ValueError, match="same inputs"):
        stack_sweeps([d1, d2])
    with pytest.raises(ValueError, match="2 position arrays but 1 encoder"):
        stack_sweeps([np.zeros((10, 3)), np.zeros((12, 3))], encoders=[np.zeros(10)])
    with pytest.raises(ValueError, match="bucket"):
        stack_sweeps([d1], bucket=0)
