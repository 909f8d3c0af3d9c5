"""Prismatic joints: the line fit (`fit_line`), the axis fit on a SCARA
(R-R-P-R, `data/robots/scara.urdf`), URDF in and out, the input checks, and
one rendered calibration through `jaxcal.calibrate`.

The revolute path is unchanged: `fit_joint_sweeps` without a prismatic joint is
`jax.vmap(fit_arc)` itself, and `tests/test_arcfit.py`, `tests/test_axisfit.py`
and `tests/test_stages.py` hold its figures.
"""

import json
import shutil

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest
from jax.flatten_util import ravel_pytree

import jaxcal
from jaxcal._arcdata import make_arc_data
from jaxcal._arcfit import fit_joint_sweeps, fit_line, validate_arc_data
from jaxcal._axisfit import fit_axes, parameter_names
from jaxcal._geometry import make_pose, matmul, so3_exp
from jaxcal._kinematics import PerturbationScales, anchor_base, forward_kinematics, joint_axes, perturb_model
from jaxcal._linemodel import initialise_line, line_residuals, line_terms
from jaxcal._montecarlo import default_setup
from jaxcal._uncertainty import joint_travel, on_travel, random_configurations
from jaxcal.errors import DatasetError
from jaxcal.inspection import format_inspection, inspect_dataset
from jaxcal.io.urdf import load_urdf, save_urdf, urdf_outline
from jaxcal.report import write_outputs
from jaxcal.sim.simulate import SimConfig, simulate

NOMINAL = jaxcal.robots.load_robot("scara")
J3 = 2  # the prismatic joint (the quill)
#: Sweeps: 60 degrees for joints 1 and 2, the quill's 200 mm, 90 degrees for the wrist.
RANGES = np.array([np.radians(60.0), np.radians(60.0), 0.2, np.radians(90.0)])
FRAMES = 120
#: PnP-like noise of the synthetic poses: 20 um and 0.02 deg per marker and frame.
SIGMA_P, SIGMA_R = 2e-5, np.radians(0.02)


def _angle_deg(a, b) -> float:
    a, b = np.asarray(a), np.asarray(b)
    return float(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1.0, 1.0))))


def _scene():
    """A camera 1.5 m off the arm's side looking down 20 degrees, two markers on the flange."""
    eye, target = np.array([0.5, -1.2, 0.8]), np.array([0.4, 0.0, 0.25])
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    T_base_cam = np.eye(4)
    T_base_cam[:3, :3] = np.stack([x, np.cross(z, x), z], 1)
    T_base_cam[:3, 3] = eye
    mounts = jnp.stack(
        [
            make_pose(so3_exp(jnp.array([0.0, 1.2, 0.0])), jnp.array([0.0, 0.06, 0.02])),
            make_pose(so3_exp(jnp.array([0.3, 1.0, 0.2])), jnp.array([0.05, -0.04, 0.03])),
        ]
    )
    return jnp.asarray(np.linalg.inv(T_base_cam)), mounts


def _sweeps(true, T_cam_base, mounts, key):
    """Every joint's sweep from the zero configuration: noisy marker poses and the encoder."""
    n, M = NOMINAL.num_joints, mounts.shape[0]
    q_cmd = jnp.eye(n)[:, None, :] * (jnp.linspace(-0.5, 0.5, FRAMES)[None, :, None] * RANGES[:, None, None])
    q_true = q_cmd * NOMINAL.reduction_ratio / true.reduction_ratio  # the motor turns as commanded
    T_bf = jax.vmap(jax.vmap(lambda q: forward_kinematics(true, q)[-1]))(q_true)
    T = jnp.einsum("ab,jfbc,mcd->jmfad", T_cam_base, T_bf, mounts)
    k_p, k_r = jax.random.split(key)
    P = T[..., :3, 3] + SIGMA_P * jax.random.normal(k_p, (n, M, FRAMES, 3))
    dR = jax.vmap(so3_exp)(SIGMA_R * jax.random.normal(k_r, (n * M * FRAMES, 3)))
    O = matmul(dR.reshape(n, M, FRAMES, 3, 3), T[..., :3, :3])
    enc = jnp.einsum("jfj->jf", q_cmd)
    return jax.vmap(lambda P, O, a: make_arc_data(P, O, a, sigma_position=SIGMA_P, sigma_rotation=SIGMA_R))(
        P, O, enc
    )


@jax.jit
def _calibrate(data):
    arcs = fit_joint_sweeps(data, NOMINAL.joint_types)
    return arcs, fit_axes(NOMINAL, arcs)


@pytest.fixture(scope="module")
def scara():
    true = anchor_base(perturb_model(NOMINAL, jax.random.key(1), PerturbationScales()), NOMINAL)
    T_cam_base, mounts = _scene()
    data = _sweeps(true, T_cam_base, mounts, jax.random.key(2))
    arcs, fit = _calibrate(data)
    return true, T_cam_base, mounts, data, arcs, fit


def test_line_fit_recovers_the_prismatic_direction_and_scale(scara):
    true, T_cam_base, _, _, arcs, _ = scara
    assert bool(jnp.all(arcs.result == optx.RESULTS.successful))
    _, d_true = joint_axes(true, jnp.zeros(4))
    d_cam = np.asarray(d_true @ T_cam_base[:3, :3].T)
    s_true = float(NOMINAL.reduction_ratio[J3] / true.reduction_ratio[J3])
    err_deg = _angle_deg(arcs.direction[J3], d_cam[J3])
    sigma_deg = float(np.degrees(np.sqrt(np.trace(arcs.cov[J3, :3, :3]))))
    scale_err = abs(float(arcs.rate[J3]) / s_true - 1.0)
    sigma_scale = float(np.sqrt(arcs.rate_var[J3])) / s_true
    # Measured (seeds 1, 2): 0.0017 deg (sigma 0.0018), scale 0.0013 % (sigma 0.0022 %).
    assert err_deg < 0.01 and err_deg < 4.0 * sigma_deg
    assert scale_err < 1e-4 and scale_err < 4.0 * sigma_scale
    assert 1e-4 < sigma_deg < 0.005 and 1e-6 < sigma_scale < 5e-5  # honest, not vacuous
    assert abs(s_true - 1.0) > 1e-3  # the truth's scale really differs from nominal
    # A translation has no axis position; the whitened residuals are at the noise.
    assert np.all(np.isnan(arcs.point[J3])) and np.all(np.isfinite(arcs.point[np.array([0, 1, 3])]))
    assert 0.8 < float(arcs.residual_rms[J3]) < 1.2
    # The marker at encoder zero: the truth's flange pose at zero.
    p0 = (T_cam_base @ forward_kinematics(true, jnp.zeros(4))[-1] @ scara[2][0])[:3, 3]
    assert float(jnp.linalg.norm(arcs.T_cam_marker0[J3, 0, :3, 3] - p0)) < 2e-5


def test_axis_fit_recovers_the_scara(scara):
    true, T_cam_base, mounts, _, _, fit = scara
    assert fit.result == optx.RESULTS.successful
    _, d_true = joint_axes(true, jnp.zeros(4))
    _, d_fit = joint_axes(fit.model, jnp.zeros(4))
    _, d_nom = joint_axes(NOMINAL, jnp.zeros(4))
    # The quill's direction in the base frame (the gauge: joint 1's frame), and its scale.
    assert _angle_deg(d_fit[J3], d_true[J3]) < 0.01 < _angle_deg(d_nom[J3], d_true[J3])
    ratio_err = np.abs(np.asarray(fit.model.reduction_ratio) / np.asarray(true.reduction_ratio) - 1.0)
    assert ratio_err[J3] < 1e-4 and ratio_err.max() < 1e-4
    # The marker over random configurations: 3.1 mm nominal, 0.016 mm calibrated (measured).
    q = jax.random.uniform(jax.random.key(5), (200, 4), minval=-1.0, maxval=1.0) * jnp.array(
        [1.5, 2.0, 0.1, 3.0]
    )

    def marker(model, T_cb, mount):
        return jax.vmap(lambda qq: (T_cb @ forward_kinematics(model, qq)[-1] @ mount)[:3, 3])(q)

    truth = marker(true, T_cam_base, mounts[0])
    rms = lambda m: float(1e3 * jnp.sqrt(jnp.mean(jnp.sum((m - truth) ** 2, -1))))  # noqa: E731
    after = rms(marker(fit.model, fit.T_cam_base, fit.T_flange_marker[0]))
    before = rms(marker(NOMINAL, fit.T_cam_base, fit.T_flange_marker[0]))
    assert after < 0.05 and before > 1.0


def test_identifiability_of_the_scara(scara):
    """The rank-revealing search freezes what a prismatic joint cannot show: the
    quill's origin along (and across one side of) its axis and its zero offset,
    all vertical translations the camera's height absorbs."""
    _, _, _, _, arcs, fit = scara
    names = parameter_names(NOMINAL, 2)
    free = np.asarray(fit.free)
    frozen = {n for n, f in zip(names, free) if not f}
    assert {"joint3.origin.tz", "joint3.zero_offset", "joint1.zero_offset"} <= frozen
    assert "joint3.origin.rx" not in frozen and "joint3.origin.ry" not in frozen
    # The search's own record: a frozen column lies in the span of the kept ones
    # (relative distance below its tolerance, 1e-7), a kept one does not, and the
    # kept columns are well conditioned at the solution.
    indep = np.asarray(fit.independence)
    assert np.all(indep[~free] < 1e-7) and np.all(indep[free] > 1e-7)
    sv = np.asarray(fit.singular_values)[: int(free.sum())]
    assert sv.min() > 1e-6 * sv.max()
    # The quill gives its direction but no line position: those residuals are zero.
    assert np.all(np.asarray(arcs.meas[J3, 2:4]) == 0.0)


def test_line_jacobian_matches_autodiff(scara):
    data = jax.tree.map(lambda x: x[J3], scara[3])

    @jax.jit  # one program: op by op, the two Jacobians compile ~300 small ones
    def jacobians(data):
        params, ref = initialise_line(data)
        x, unravel = ravel_pytree(jax.tree.map(lambda x: x + 0.01, params))

        def plain(x):
            return line_terms(unravel(x), ref, data, jacobian=False)[0]

        return jax.jacfwd(lambda x: line_residuals(unravel(x), (ref, data)))(x), jax.jacfwd(plain)(x)

    J, J_plain = jacobians(data)
    np.testing.assert_allclose(J, J_plain, atol=1e-9 * float(jnp.abs(J).max()))


def test_prismatic_sweep_errors(scara):
    data = jax.tree.map(lambda x: x[J3], scara[3])
    validate_arc_data(data, "COBRA.j3", "prismatic")  # the good sweep passes
    no_encoder = make_arc_data(data.positions, data.orientations, None)
    with pytest.raises(ValueError, match="'COBRA.j3'.*encoder positions"):
        validate_arc_data(no_encoder, "COBRA.j3", "prismatic")
    with pytest.raises(ValueError, match="encoder positions"):
        fit_line(no_encoder)
    short = make_arc_data(data.positions, data.orientations, data.encoder * 0.01)  # 2 mm of travel
    with pytest.raises(ValueError, match="'COBRA.j3': the prismatic sweep travels 2.00 mm, at least 5"):
        validate_arc_data(short, "COBRA.j3", "prismatic")
    # As a revolute joint the same sweep is refused as an arc (the message users met before).
    with pytest.raises(ValueError, match="'COBRA.j3': the sweep covers .* degrees"):
        validate_arc_data(short, "COBRA.j3")
    with pytest.raises(ValueError, match="4 joint types for 3 sweeps"):
        fit_joint_sweeps(jax.tree.map(lambda x: x[:3], scara[3]), NOMINAL.joint_types)


def test_prismatic_joints_where_unsupported_and_in_random_configurations():
    with pytest.raises(ValueError, match=r"monte_carlo: .*prismatic joints \['joint3'\]"):
        jaxcal.monte_carlo(default_setup(NOMINAL), jax.random.key(0), 1)
    with pytest.raises(ValueError, match=r"prismatic joints \['joint3'\]"):
        jaxcal.dh_table(NOMINAL)
    # The validation's sample: revolute columns over [-pi, pi] as they were, the quill
    # within its URDF stroke (or +-0.1 m without limits), uniformly.
    limits = urdf_outline(jaxcal.robots.robot_path("scara"), NOMINAL.joint_names).limits
    q = random_configurations(jax.random.key(0), 2000, 4)
    for lim, (lo, hi) in ((limits, (-0.105, 0.105)), (None, (-0.1, 0.1))):
        travel = joint_travel(NOMINAL, lim)
        np.testing.assert_array_equal(travel[[0, 1, 3]], [[-np.pi, np.pi]] * 3)
        qt = np.asarray(on_travel(NOMINAL, q, travel))
        np.testing.assert_array_equal(qt[:, [0, 1, 3]], np.asarray(q)[:, [0, 1, 3]])
        assert lo <= qt[:, J3].min() < lo + 0.01 and hi - 0.01 < qt[:, J3].max() <= hi


def test_scara_urdf_in_and_out(tmp_path):
    assert NOMINAL.joint_types == ("revolute", "revolute", "prismatic", "revolute")
    assert np.isclose(float(NOMINAL.reduction_ratio[J3]), 2 * np.pi / 0.02)  # a 20 mm lead screw
    # Arm stretched along x, the quill at mid-stroke, the flange facing down.
    T = np.asarray(forward_kinematics(NOMINAL, jnp.zeros(4))[-1])
    np.testing.assert_allclose(T[:3, 3], [0.6, 0.0, 0.177], atol=1e-12)
    assert T[2, 2] < -0.999
    T_up = np.asarray(forward_kinematics(NOMINAL, jnp.array([0.0, 0.0, 0.05, 0.0]))[-1])
    np.testing.assert_allclose(T_up[:3, 3] - T[:3, 3], [0.0, 0.0, 0.05], atol=1e-12)
    for source in (None, jaxcal.robots.robot_path("scara")):
        path = tmp_path / f"out_{source is None}.urdf"
        save_urdf(NOMINAL, path, source=source)
        back = load_urdf(path)
        assert back.joint_types == NOMINAL.joint_types
        np.testing.assert_allclose(back.T_parent_joint, NOMINAL.T_parent_joint, atol=1e-12)
        text = path.read_text()
        limit = (
            '<limit lower="-0.105" upper="0.105"' if source is not None else '<limit lower="-1.0" upper="1.0"'
        )
        assert '<joint name="joint3" type="prismatic">' in text and limit in text


@pytest.mark.slow
def test_rendered_scara_calibration(tmp_path):
    """`jaxcal.calibrate` end to end on a rendered SCARA (640x480, 10 frames a
    sweep of 30 degrees or 150 mm): tolerances looser than the synthetic test's,
    since the PnP noise of a board seen 50 degrees off its normal is ~10x larger
    and there are 12x fewer frames."""
    config = SimConfig(
        robot="scara", seed=0, resolution=(640, 480), camera_distance=0.65, square_length=0.05,
        marker_length=0.0375, frames_per_joint=10, range_deg=30.0, range_mm=150.0,
        clock_offset_ms=20.0, clock_known=False,
    )  # fmt: skip
    ds = simulate(config, tmp_path / "scara", progress=False)
    # `jaxcal inspect` gives the quill's travel in mm (the log holds metres), the arms' sweeps in degrees.
    text = format_inspection(inspect_dataset(ds, sample=2))
    assert "joint3: " in text and "travels -75.0 .. 75.0 mm" in text and "sweeps -15.0 .. 15.0 deg" in text
    r = jaxcal.calibrate(ds, progress=False, workers=1)
    v = r.validation
    # Measured over 1000 configurations, the quill within its URDF stroke: 4.13 mm nominal,
    # 2.48 mm two-stage, 1.39 mm refined, against a propagated 1-sigma of 1.78 mm.
    sigma = next(c["value"] for c in r.verdict.checks if c["check"] == "ee_sigma_mm")
    assert v["ee_rms_mm_before"] > 3.0 and v["ee_rms_mm_after"] < 2.0
    assert v["ee_rms_mm_after"] < 0.5 * v["ee_rms_mm_before"]
    assert v["ee_rms_mm_after"] <= v["ee_rms_mm_two_stage"] < 0.8 * v["ee_rms_mm_before"]
    assert 0.3 * sigma < v["ee_rms_mm_after"] < 2.0 * sigma < 5.0  # the reported uncertainty is honest
    assert r.status == "ok" and r.refinement["solver"]["result"] == "successful"
    # Ten frames a 30-degree sweep: the board moves 3 deg between frames and its detector errors repeat
    # a little (the residual test finds it); the kernel sandwich grows the 1-sigma by far less than the
    # 1.2x that would make the result suspect (`Limits.correlation_growth`), so it is a note.
    notes = [n for n in r.verdict.notes if "repeat from frame to frame" in n]
    assert len(notes) == 1 and "within the 1.2x" in notes[0]
    errors = v["parameter_errors"]
    # Measured: every axis direction within 0.06 deg, ratios within 0.15 %.
    assert all(e["axis_direction_deg"] < 0.1 and abs(e["ratio_percent"]) < 0.25 for e in errors.values())
    quill = errors["joint3"]
    # Measured: 0.021 deg and -0.036 %.
    assert quill["axis_direction_deg"] < 0.05 and abs(quill["ratio_percent"]) < 0.1
    assert "axis_position_mm" not in quill and "zero_offset_mm" in quill
    row = next(a for a in r.arcs if a["joint"] == "joint3")
    assert row["type"] == "prismatic" and row["point_cam_m"] is None and row["ratio_unit"] == "rad/m"
    # The line fit's scale against the truth's (nominal over true ratio), within its own sigma.
    s_true = float(NOMINAL.reduction_ratio[J3]) / v["true_ratios"][J3]
    assert abs(row["scale"] - s_true) < 3.0 * row["scale_std"] and 0.0 < row["scale_std"] < 0.005
    assert abs(r.clock["offset_s"] - 0.020) < 2e-4  # fitted on the revolute joints' arcs (measured 2 us off)
    out = tmp_path / "out"
    out.mkdir()
    write_outputs(r, out)
    assert '<joint name="joint3" type="prismatic">' in (out / "calibrated.urdf").read_text()
    saved = json.loads((out / "result.json").read_text())
    assert saved["reduction_ratios"]["joint3"]["ratio_unit"] == "rad/m"
    assert "joint3 is prismatic" in (out / "report.md").read_text()
    # The same dataset with its encoder log declared in degrees: an angle unit on a
    # column that holds metres is refused, naming the field and the joint.
    bad = tmp_path / "deg"
    shutil.copytree(ds, bad)
    meta = json.loads((bad / "metadata.json").read_text())
    meta["encoders"]["unit"] = "deg"
    (bad / "metadata.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match=r"encoders\.unit.*'deg'.*\['joint3'\] are prismatic"):
        jaxcal.calibrate(bad, progress=False, workers=1)
