"""The first error function: arc fit per joint."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest
from helpers import arc_data, arc_problem, tree_allclose

from jaxcal._arcfit import (
    _arc_residuals_autodiff,
    arc_residuals,
    fit_arc,
    initialise_arc,
    line_from_params,
    line_to_params,
    make_arc_data,
    validate_arc_data,
)

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
    params, ref = initialise_arc(data)
    params = jax.tree.map(lambda x: x + 1e-3, params)  # away from the solution
    flat, unravel = jax.flatten_util.ravel_pytree(params)

    def f(x):
        return arc_residuals(unravel(x), (ref, data)).reshape(-1)

    Jf = jax.jacfwd(f)(flat)
    Jr = jax.jacrev(f)(flat)
    np.testing.assert_allclose(Jf, Jr, rtol=1e-10, atol=1e-8)
    h = 1e-6
    fd = np.stack([(f(flat.at[i].add(h)) - f(flat.at[i].add(-h))) / (2 * h) for i in range(flat.size)], 1)
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
    params, ref = initialise_arc(data)
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
    res = jax.jit(lambda d: fit_arc(d, max_steps=1))(data)
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
