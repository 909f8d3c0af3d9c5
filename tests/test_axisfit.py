"""The second error function: measured axes -> kinematics + camera-to-base."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest
from helpers import tree_allclose, ur5e_setup

from jaxcal._arcfit import fit_arc
from jaxcal._axisfit import (
    AxisFitParams,
    AxisFitProblem,
    KinematicCorrection,
    _axis_residuals_autodiff,
    _whitening,
    apply_correction,
    axis_jacobian,
    axis_residuals,
    fit_axes,
    parameter_names,
    register_lines,
)
from jaxcal._geometry import pose_inverse, se3_exp, se3_log
from jaxcal._lsq import LMOptions
from jaxcal._montecarlo import NoiseModel, nominal_free_mask, synthesize_sweeps

SETUP = ur5e_setup(frames=24)
NOMINAL = SETUP.nominal
NAMES = parameter_names(NOMINAL, 1)


@pytest.fixture(scope="module")
def free():
    return np.asarray(jax.jit(nominal_free_mask)(SETUP))


def _param_truth(key, free):
    """A truth inside the estimator's parameter space: random corrections on
    the identifiable parameters only (so the frozen ones are truly nominal)."""
    k1, k2 = jax.random.split(key)
    n = NOMINAL.num_joints
    scale = jnp.concatenate(
        [
            jnp.array([20e-3] * 3 + [0.03] * 3),  # camera
            jnp.tile(jnp.array([1e-3] * 3 + [3e-3] * 3), n),  # origins
            jnp.full(n, 0.01),  # zero offsets
            jnp.array([2e-3] * 3 + [0.02] * 3),  # marker mount
        ]
    )
    x = scale * jax.random.normal(k1, scale.shape) * free
    _, unravel = jax.flatten_util.ravel_pytree(_zeros())
    p = unravel(x)
    model, mounts = apply_correction(NOMINAL, SETUP.T_flange_marker, p.correction)
    return model, mounts, SETUP.T_cam_base @ se3_exp(p.cam)


def _zeros():
    n = NOMINAL.num_joints
    return AxisFitParams(
        cam=jnp.zeros(6),
        correction=KinematicCorrection(
            origin=jnp.zeros((n, 6)), zero_offset=jnp.zeros(n), tool=jnp.zeros((1, 6))
        ),
    )


def _trial(key, free, noise, use_encoders=True):
    k_truth, k_noise = jax.random.split(key)
    model, mounts, T_cam_base = _param_truth(k_truth, free)
    data = synthesize_sweeps(
        model,
        T_cam_base,
        mounts,
        SETUP.plan,
        noise,
        k_noise,
        nominal_ratio=NOMINAL.reduction_ratio,
        use_encoders=use_encoders,
    )
    arcs = jax.vmap(lambda d: fit_arc(d, scale_covariance=False))(data)
    fit = fit_axes(NOMINAL, arcs, free=free)
    return fit, (model, mounts, T_cam_base)


trial = jax.jit(_trial, static_argnames="use_encoders")


def test_identifiability_report(free):
    frozen = {n for n, f in zip(NAMES, free) if not f}
    # The base frame cannot be told from the camera pose: joint 1's whole
    # origin and its zero offset are held at nominal.
    assert {f"shoulder_pan_joint.origin.{p}" for p in ("tx", "ty", "tz", "rx", "ry", "rz")} <= frozen
    assert "shoulder_pan_joint.zero_offset" in frozen
    # A joint frame's spin about its own axis is its zero offset.
    assert "elbow_joint.origin.rz" in frozen
    # Lines + the marker pose: 4 per revolute joint + 6 (the POE count), plus the camera.
    assert int(free.sum()) == 4 * 6 + 6
    assert all(n.startswith("T_cam_base") for n in NAMES[:6]) and free[:6].all()


def test_exact_recovery_with_encoders(free):
    fit, (model, mounts, T_cam_base) = trial(jax.random.key(1), free, NoiseModel(0.0, 0.0, 0.0))
    assert fit.result == optx.RESULTS.successful
    np.testing.assert_allclose(fit.model.T_parent_joint, model.T_parent_joint, atol=1e-8)
    np.testing.assert_allclose(fit.model.zero_offset, model.zero_offset, atol=1e-8)
    np.testing.assert_allclose(fit.T_cam_base, T_cam_base, atol=1e-8)
    np.testing.assert_allclose(fit.T_flange_marker, mounts, atol=1e-8)
    np.testing.assert_allclose(fit.model.reduction_ratio, NOMINAL.reduction_ratio, rtol=1e-10)


def test_exact_recovery_from_a_home_configuration(free):
    """Sweeps about a home that is not zero (each joint's arc measured with the
    others there): the fit predicts every axis and marker pose at its sweep's home."""
    model, mounts, T_cam_base = _param_truth(jax.random.key(4), free)
    data = synthesize_sweeps(
        model, T_cam_base, mounts, SETUP.plan, NoiseModel(0.0, 0.0, 0.0), jax.random.key(5),
        nominal_ratio=NOMINAL.reduction_ratio, home=HOME,
    )  # fmt: skip
    arcs = jax.jit(jax.vmap(fit_arc))(data)  # one arc program for both axis fits
    fit = jax.jit(lambda a: fit_axes(NOMINAL, a, free=free, home=HOME))(arcs)
    assert fit.result == optx.RESULTS.successful
    np.testing.assert_allclose(fit.model.T_parent_joint, model.T_parent_joint, atol=1e-8)
    np.testing.assert_allclose(fit.T_cam_base, T_cam_base, atol=1e-8)
    np.testing.assert_allclose(fit.T_flange_marker, mounts, atol=1e-8)
    # Treating the same sweeps as if they started from zero is wrong by far.
    wrong = jax.jit(lambda a: fit_axes(NOMINAL, a, free=free))(arcs)
    assert float(wrong.residual_rms) > 1e3 * max(float(fit.residual_rms), 1e-6)


def test_exact_recovery_without_encoders(free):
    """Lines only: kinematics and camera pose (the last joint's zero offset and the
    marker mount are not identifiable without knowing which frame is zero)."""
    fit, (model, mounts, T_cam_base) = trial(
        jax.random.key(2), free, NoiseModel(0.0, 0.0, 0.0), use_encoders=False
    )
    assert fit.result == optx.RESULTS.successful
    names = parameter_names(NOMINAL, 1)
    frozen = {n for n, f in zip(names, np.asarray(fit.free)) if not f}
    assert "wrist_3_joint.zero_offset" in frozen or "marker.mount.rz" in frozen
    # Every joint axis in the camera frame is exact.
    from jaxcal._kinematics import joint_axes

    def axes_cam(m, T):
        p, d = joint_axes(m, jnp.zeros(6))
        return p @ T[:3, :3].T + T[:3, 3], d @ T[:3, :3].T

    pe, de = axes_cam(fit.model, fit.T_cam_base)
    pt, dt = axes_cam(model, T_cam_base)
    np.testing.assert_allclose(de, dt, atol=1e-9)
    dp = pe - pt
    off = dp - jnp.sum(dp * dt, -1, keepdims=True) * dt
    assert float(jnp.abs(off).max()) < 1e-9
    np.testing.assert_allclose(fit.T_cam_base, T_cam_base, atol=1e-8)


#: The seeded noisy trials two tests share (one compiled batch).
NOISY = NoiseModel(position_mm=0.1, orientation_deg=0.05)


@pytest.fixture(scope="module")
def noisy_batch(free):
    keys = jax.random.split(jax.random.key(3), 60)
    fits, truths = jax.jit(jax.vmap(lambda k: _trial(k, free, NOISY)))(keys)
    return keys, fits, truths


def test_noisy_covariance_is_honest(noisy_batch):
    """Over seeded trials the identifiable parameters' errors follow the
    reported covariance: mean chi-square per parameter within 0.8 - 1.25."""
    keys, fits, truths = noisy_batch
    assert np.all(np.asarray(fits.result == optx.RESULTS.successful))
    chi2 = []
    for i in range(keys.shape[0]):
        f = jax.tree.map(lambda x: x[i], fits)
        model, mounts, T_cam_base = (jax.tree.map(lambda x: x[i], t) for t in truths)
        x_est = jax.flatten_util.ravel_pytree(f.params)[0]
        T0 = f.T_cam_base @ se3_exp(-f.params.cam)
        M0 = f.T_flange_marker[0] @ se3_exp(-f.params.correction.tool[0])
        true_params = AxisFitParams(
            cam=se3_log(pose_inverse(T0) @ T_cam_base),
            correction=KinematicCorrection(
                origin=jax.vmap(se3_log)(
                    jnp.einsum(
                        "jab,jbc->jac", jax.vmap(pose_inverse)(NOMINAL.T_parent_joint), model.T_parent_joint
                    )
                ),
                zero_offset=model.zero_offset - NOMINAL.zero_offset,
                tool=se3_log(pose_inverse(M0) @ mounts[0])[None],
            ),
        )
        x_true = jax.flatten_util.ravel_pytree(true_params)[0]
        keep = np.asarray(f.free)
        e = np.asarray(x_est - x_true)[keep]
        C = np.asarray(f.cov)[np.ix_(keep, keep)]
        chi2.append(e @ np.linalg.solve(C, e) / keep.sum())
    assert 0.8 < float(np.mean(chi2)) < 1.25


def test_jit_equals_vmap_equals_loop(free, noisy_batch):
    """The vmapped batch of the covariance test against single jitted trials."""
    keys, batched, _ = noisy_batch
    for i in range(2):
        single, _ = trial(keys[i], free, NOISY)
        assert tree_allclose(single.T_cam_base, batched.T_cam_base[i], atol=1e-10)
        assert tree_allclose(single.model.T_parent_joint, batched.model.T_parent_joint[i], atol=1e-10)


@pytest.fixture(scope="module")
def sweeps(free):
    """One noisy trial's truth, arc fits and axis fit (jitted once, shared)."""

    def make(key):
        k_truth, k_noise = jax.random.split(key)
        model, mounts, T_cam_base = _param_truth(k_truth, free)
        data = synthesize_sweeps(
            model,
            T_cam_base,
            mounts,
            SETUP.plan,
            NoiseModel(),
            k_noise,
            nominal_ratio=NOMINAL.reduction_ratio,
        )
        arcs = jax.vmap(lambda d: fit_arc(d, scale_covariance=False))(data)
        return arcs, fit_axes(NOMINAL, arcs, free=free)

    return jax.jit(make)(jax.random.key(5))


def test_autodiff_matches_finite_differences(sweeps):
    arcs, fit = sweeps
    problem = AxisFitProblem(
        nominal=NOMINAL,
        T_flange_marker0=fit.T_flange_marker,
        T_cam_base0=fit.T_cam_base,
        arcs=arcs,
        sqrt_info=jax.vmap(_whitening)(arcs.meas_cov),
        use_poses=True,
    )
    params = jax.tree.map(lambda x: x + 1e-3, _zeros())  # off the solution
    flat, unravel = jax.flatten_util.ravel_pytree(params)

    @jax.jit
    def f(x):
        return axis_residuals(unravel(x), problem).reshape(-1)

    Jf = jax.jit(jax.jacfwd(f))(flat)
    Jr = jax.jit(jax.jacrev(f))(flat)
    np.testing.assert_allclose(Jf, Jr, rtol=1e-9, atol=1e-6 * np.abs(Jf).max())
    h = 1e-7
    steps = h * np.eye(flat.size)
    fd = jax.vmap(lambda e: (f(flat + e) - f(flat - e)) / (2 * h))(steps).T
    np.testing.assert_allclose(Jf, fd, rtol=1e-4, atol=1e-5 * np.abs(Jf).max())


def test_the_stage_program_searches_or_takes_a_mask_in_one_compiled_program(sweeps, free):
    """`stages._programs.axis_fit`: without a mask it searches the identifiable
    parameters; a given mask is used as it is (the validation's gauge reuses the
    fit's); both run one compiled program (`fit_axes(search=)` is traced)."""
    from jaxcal.stages import _programs

    arcs, _ = sweeps
    axis_fit = _programs.axis_fit(True)
    compiled = axis_fit.program.cache_size()  # other files' calibrations may have added some
    mount = SETUP.T_flange_marker
    searched = axis_fit(NOMINAL, arcs, mount)
    np.testing.assert_array_equal(searched.free, free)  # the nominal geometry's mask
    assert np.isfinite(np.asarray(searched.independence)).sum() > 6
    given = axis_fit(NOMINAL, arcs, mount, searched.free)
    np.testing.assert_array_equal(given.free, searched.free)
    assert np.all(np.isnan(np.asarray(given.independence)))
    np.testing.assert_allclose(given.T_cam_base, searched.T_cam_base, rtol=0, atol=1e-12)
    np.testing.assert_allclose(given.model.T_parent_joint, searched.model.T_parent_joint, rtol=0, atol=1e-12)
    fewer = np.asarray(searched.free).copy()
    fewer[np.flatnonzero(fewer)[6]] = False  # one more parameter held: the first after the camera's
    held = axis_fit(NOMINAL, arcs, mount, fewer)
    np.testing.assert_array_equal(held.free, fewer)
    assert float(held.residual_rms) > float(searched.residual_rms)
    assert axis_fit.program.cache_size() <= compiled + 1  # three calls, one program


# (encoders without the marker poses runs the lines-only residuals of (False, False) on other arcs)
#: A home configuration for every sweep (UR5e's [0, -90, 90, -90, -90, 0] deg family), own entry zero.
HOME = jnp.asarray(np.radians([0.0, -60.0, 70.0, -40.0, 30.0, 20.0])) * (1.0 - jnp.eye(6))


#: The arc fits the Jacobian checks start from (one program for the cases with encoders).
_fit_arcs_unscaled = jax.jit(jax.vmap(lambda d: fit_arc(d, scale_covariance=False)))


@pytest.mark.parametrize(
    ("use_encoders", "use_poses", "home"), [(True, True, False), (False, False, False), (True, True, True)]
)
def test_closed_form_jacobian_matches_autodiff(use_encoders, use_poses, home):
    """The closed-form Jacobian of `axis_residuals` (its custom JVP, forward and
    reverse, and `axis_jacobian`) equals JAX's derivative of the same residuals
    written with `forward_kinematics`, to 1e-10, off the solution; derivatives
    with respect to the measurements still flow (autodiff fallback)."""
    data = synthesize_sweeps(
        NOMINAL,
        SETUP.T_cam_base,
        SETUP.T_flange_marker,
        SETUP.plan,
        NoiseModel(),
        jax.random.key(3),
        nominal_ratio=NOMINAL.reduction_ratio,
        use_encoders=use_encoders,
    )
    arcs = _fit_arcs_unscaled(data)
    k = 4 if not use_poses else arcs.meas.shape[-1]
    problem = AxisFitProblem(
        nominal=NOMINAL,
        T_flange_marker0=SETUP.T_flange_marker,
        T_cam_base0=register_lines(NOMINAL, arcs),
        arcs=arcs,
        sqrt_info=jax.vmap(_whitening)(arcs.meas_cov[:, :k, :k]),
        use_poses=use_poses,
        home=HOME if home else None,
    )
    flat0, unravel = jax.flatten_util.ravel_pytree(_zeros())
    x = flat0 + 0.02 * jax.random.normal(jax.random.key(0), flat0.shape)  # off the solution

    def f(fn):
        return lambda x: fn(unravel(x), problem).reshape(-1)

    r_auto = jax.jit(f(_axis_residuals_autodiff))(x)
    J_auto = jax.jit(jax.jacfwd(f(_axis_residuals_autodiff)))(x)
    scale = np.abs(J_auto).max()
    np.testing.assert_allclose(
        jax.jit(f(axis_residuals))(x), r_auto, rtol=0, atol=1e-10 * np.abs(r_auto).max()
    )
    for J in (
        jax.jit(jax.jacfwd(f(axis_residuals)))(x),
        jax.jit(jax.jacrev(f(axis_residuals)))(x),
        jax.jit(lambda x: axis_jacobian(unravel(x), problem)[1])(x),
    ):
        np.testing.assert_allclose(J, J_auto, rtol=0, atol=1e-10 * scale)

    def g(fn):
        return lambda meas: fn(unravel(x), eqx.tree_at(lambda p: p.arcs.meas, problem, meas)).reshape(-1)

    J_meas = jax.jit(jax.jacfwd(g(_axis_residuals_autodiff)))(arcs.meas)
    np.testing.assert_allclose(
        jax.jit(jax.jacfwd(g(axis_residuals)))(arcs.meas), J_meas, rtol=1e-12, atol=1e-9
    )


def test_max_steps_reports_optimistix_code(sweeps, free):
    arcs, _ = sweeps
    fit = jax.jit(lambda a: fit_axes(NOMINAL, a, free=free, options=LMOptions(max_steps=1)))(arcs)
    assert fit.result == optx.RESULTS.nonlinear_max_steps_reached


def test_wrong_number_of_axes(sweeps):
    arcs, _ = sweeps
    with pytest.raises(ValueError, match="5 measured axes for a model with 6 joints"):
        fit_axes(NOMINAL, jax.tree.map(lambda x: x[:5], arcs))
    with pytest.raises(ValueError, match="free mask has shape"):
        fit_axes(NOMINAL, arcs, free=np.ones(3, bool))
