"""DH / MDH tables of any revolute model, their standard deviations, and the table files.

One synthetic estimate on the UR5e's datasheet table serves every covariance
test (one compiled Jacobian, one compiled batch of table evaluations).
"""

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcal
from jaxcal._correction import Estimate, ParameterLayout, apply_correction, physical_parameters
from jaxcal._dh import dh_table, parallel_pairs, table_forward_kinematics, table_to_model, table_values
from jaxcal._geometry import se3_exp
from jaxcal._kinematics import PerturbationScales, forward_kinematics, perturb_model
from jaxcal._tables import dh_values, mdh_from_dh_values, physical_table
from jaxcal.errors import DatasetError
from jaxcal.io.dh_tables import dh_table_json, dh_table_model, read_dh_table
from jaxcal.robots import ROBOTS_DIR, dh_model, load_robot

CONFIGS = 1000


def _fk_gap(table, model, qs):
    """Largest flange position (m) and rotation-matrix differences, table vs model, over `qs`."""
    T1 = np.asarray(jax.vmap(lambda q: table_forward_kinematics(table, q))(qs))
    T2 = np.asarray(jax.vmap(lambda q: forward_kinematics(model, q)[-1])(qs))
    return np.abs(T1[:, :3, 3] - T2[:, :3, 3]).max(), np.abs(T1[:, :3, :3] - T2[:, :3, :3]).max()


def _configs(n):
    return jax.random.uniform(jax.random.key(1), (CONFIGS, n), minval=-np.pi, maxval=np.pi)


# --------------------------------------------------------------------------- extraction


def test_the_shipped_tables_come_back_from_their_models():
    ur = json.loads((ROBOTS_DIR / "ur5e_dh.json").read_text())
    t = dh_table(dh_model("ur5e_dh"), "dh")
    for c in ("a", "alpha", "d", "theta"):
        np.testing.assert_allclose(getattr(t, c), ur[c], atol=1e-12, err_msg=c)
    np.testing.assert_allclose(t.beta, 0.0, atol=1e-12)
    np.testing.assert_allclose(t.T_base, np.eye(4), atol=1e-12)
    np.testing.assert_allclose(t.T_flange, np.eye(4), atol=1e-12)
    assert t.parallel == (False, True, True, False, False, False)  # shoulder-elbow-wrist 1 are parallel
    panda = json.loads((ROBOTS_DIR / "panda_mdh.json").read_text())
    t = dh_table(dh_model("panda_mdh"), "mdh")
    for c in ("a", "alpha", "theta"):
        np.testing.assert_allclose(getattr(t, c), panda[c], atol=1e-12, err_msg=c)
    # The last frame sits at the flange origin's foot on axis 7: the flange's d moves into d7.
    np.testing.assert_allclose(t.d, np.add(panda["d"], [0] * 6 + [panda["flange"]["d"]]), atol=1e-12)
    np.testing.assert_allclose(t.T_flange, np.eye(4), atol=1e-12)
    assert not any(t.parallel)


@pytest.mark.parametrize("robot", ["ur5e", "panda"])
def test_table_forward_kinematics_equals_the_model_at_random_configurations(robot):
    nominal = load_robot(robot)
    true = perturb_model(nominal, jax.random.key(7), PerturbationScales(origin_mm=2.0, origin_deg=0.5))
    qs = _configs(nominal.num_joints)
    for convention in ("dh", "mdh"):
        reference = dh_table(nominal, convention)
        true_table = dh_table(true, convention, reference=reference)
        dp, dR = _fk_gap(true_table, true, qs)
        assert dp < 1e-9 and dR < 1e-9, (convention, dp, dR)
        # The model built from the table has the same forward kinematics.
        back = table_to_model(true_table)
        T = np.asarray(jax.vmap(lambda q: forward_kinematics(back, q)[-1])(qs[:50]))
        T0 = np.asarray(jax.vmap(lambda q: forward_kinematics(true, q)[-1])(qs[:50]))
        np.testing.assert_allclose(T, T0, atol=1e-9)
        # A calibrated-like arm keeps the nominal table's form and signs: rows move by millimetres.
        assert true_table.parallel == reference.parallel
        dcol = np.abs(np.asarray(true_table.columns() - reference.columns()))
        assert dcol[[1, 2]].max() < 0.02 and dcol[[0, 3, 4]].max() < 0.1


def test_parallel_axes_use_hayati_and_plain_dh_would_blow_up():
    nominal = load_robot("ur5e")
    true = perturb_model(nominal, jax.random.key(3), PerturbationScales())
    assert parallel_pairs(nominal) == (False, True, True, False, False, False)
    ref = dh_table(nominal)
    t = dh_table(true, reference=ref)
    np.testing.assert_array_equal(np.asarray(t.d)[[1, 2]], 0.0)  # d held at 0 on the parallel rows
    beta = np.abs(np.asarray(t.beta))
    assert 1e-5 < beta[1] < 2e-2 and 1e-5 < beta[2] < 2e-2 and beta[[0, 3, 4, 5]].max() == 0.0
    # The common normal of axes a few mrad from parallel: d jumps to metres.
    plain = dh_table(true, parallel=(False,) * 6)
    assert np.abs(np.asarray(plain.d)[[1, 2]]).max() > 1.0
    with pytest.raises(ValueError, match="prismatic"):
        dh_table(
            jaxcal.make_model(np.eye(4)[None], [[0, 0, 1.0]], joint_names=["z"], joint_types=["prismatic"])
        )


# --------------------------------------------------------------------------- estimates and tables


@pytest.fixture(scope="module")
def estimate():
    """An axis-fit-sized estimate on the UR5e datasheet table: a random correction and
    covariance (0.5 mm / 0.5 mrad scale), joint 1's origin held."""
    nominal = dh_model("ur5e_dh")
    layout = ParameterLayout.of(nominal, 1)
    n = layout.axis_size
    rng = np.random.default_rng(0)
    A = rng.normal(size=(n, n)) * 5e-4
    cov = A @ A.T / n
    free = np.ones(n, bool)
    free[layout.index("origin")[:6]] = False
    cov[~free] = 0.0
    cov[:, ~free] = 0.0
    x = rng.normal(size=n) * 1e-3 * free
    mount = np.eye(4)
    mount[:3, 3] = [0.0, 0.05, 0.1]
    return Estimate(
        x=jnp.asarray(x),
        cov=jnp.asarray(cov),
        free=jnp.asarray(free),
        nominal=nominal,
        T_flange_marker0=jnp.asarray(mount)[None],
        T_cam_base0=jnp.asarray(np.eye(4)),
        reduction_ratio=jnp.full(6, 100.0),
        layout=layout,
        mount_names=("plate",),
    )


def test_parameters_to_model_is_the_corrected_model(estimate):
    out = jaxcal.parameters_to_model(estimate)
    cam, corr, rate = estimate.layout.split(estimate.x)
    assert rate is None
    model, mounts = apply_correction(estimate.nominal, estimate.T_flange_marker0, corr)
    np.testing.assert_allclose(out.model.T_parent_joint, model.T_parent_joint, atol=1e-15)
    np.testing.assert_allclose(out.model.zero_offset, model.zero_offset, atol=1e-15)
    np.testing.assert_allclose(out.T_flange_marker, mounts, atol=1e-15)
    np.testing.assert_allclose(out.model.T_flange_tool, mounts[0], atol=1e-15)
    np.testing.assert_allclose(out.model.reduction_ratio, 100.0)
    np.testing.assert_allclose(out.T_cam_base, estimate.T_cam_base0 @ se3_exp(cam), atol=1e-15)
    # A refinement's vector carries the ratios as rates, rho = rho_nom / r.
    lay = estimate.layout
    full = jnp.zeros(lay.size).at[: lay.axis_size].set(estimate.x).at[lay.index("rate")].set(0.5)
    ratio = jaxcal.parameters_to_model(estimate, full).model.reduction_ratio
    np.testing.assert_allclose(ratio, 2.0 * np.asarray(estimate.nominal.reduction_ratio))
    with pytest.raises(ValueError, match="parameter vector has shape"):
        jaxcal.parameters_to_model(estimate, jnp.zeros(5))


def test_the_urdf_table_is_the_result_parameters(estimate):
    table = physical_table(estimate, "urdf")
    cam, corr, _ = estimate.layout.split(estimate.x)
    rows = physical_parameters(
        estimate.layout, estimate.nominal, estimate.T_flange_marker0, estimate.T_cam_base0, cam, corr,
        estimate.cov, estimate.free, ["plate"],
    )  # fmt: skip
    assert [(r["name"], r["unit"], r["group"], r["free"]) for r in table.rows()] == [
        (r["name"], r["unit"], r["group"], r["free"]) for r in rows
    ]
    for key in ("nominal", "estimate", "std"):
        np.testing.assert_allclose(
            [r[key] for r in table.rows()], [r[key] for r in rows], rtol=1e-12, atol=1e-18
        )
    np.testing.assert_allclose(np.sqrt(np.diag(table.covariance)), table.std, atol=1e-15)


@pytest.fixture(scope="module")
def dh(estimate):
    return physical_table(estimate, "dh")


def test_propagated_std_matches_monte_carlo_and_the_jacobian_finite_differences(estimate, dh):
    """Sample the vector from its covariance, extract the table, take the std; and
    check the Jacobian against central differences, in one batched evaluation."""
    n = estimate.x.shape[0]
    rng = np.random.default_rng(1)
    w, V = np.linalg.eigh(np.asarray(estimate.cov))
    samples = np.asarray(estimate.x) + (rng.normal(size=(4000, n)) * np.sqrt(np.maximum(w, 0))) @ V.T
    h = 1e-6
    fd = np.asarray(estimate.x) + h * np.concatenate([np.eye(n), -np.eye(n)])
    ref = dh.nominal_table
    values = np.asarray(jax.jit(jax.vmap(lambda x: dh_values(estimate, ref, x)))(np.vstack([samples, fd])))
    mc = values[:4000].std(axis=0)
    moved = dh.std > 1e-9
    ratio = mc[moved] / dh.std[moved]
    assert 0.93 < ratio.min() and ratio.max() < 1.07, (ratio.min(), ratio.max())
    assert (
        mc[~moved].max() < 1e-10
    )  # rows no estimated parameter moves: beta of plain rows, d of parallel rows
    np.testing.assert_allclose(values[:4000].mean(axis=0), dh.estimate, atol=2e-4)
    G = (values[4000 : 4000 + n] - values[4000 + n :]).T / (2 * h)
    J = G @ np.asarray(estimate.cov) @ G.T
    np.testing.assert_allclose(np.sqrt(np.diag(J)), dh.std, rtol=1e-5, atol=1e-12)
    np.testing.assert_allclose(dh.estimate, table_values(dh.table), atol=1e-14)
    # The estimate's table reproduces the calibrated model's forward kinematics.
    dp, dR = _fk_gap(dh.table, jaxcal.parameters_to_model(estimate).model, _configs(6))
    assert dp < 1e-9 and dR < 1e-9


def test_the_mdh_table_is_the_dh_table_shifted(estimate, dh):
    mdh = physical_table(estimate, "mdh")
    direct = dh_table(jaxcal.parameters_to_model(estimate).model, "mdh", reference=mdh.nominal_table)
    np.testing.assert_allclose(mdh.estimate, table_values(direct), atol=1e-14)
    P = mdh_from_dh_values(6)
    np.testing.assert_allclose(mdh.covariance, P @ dh.covariance @ P.T, atol=1e-20)
    assert mdh.std_table.a[0] == 0 and mdh.std_table.a[3] == dh.std_table.a[2]
    assert mdh.table.parallel == (False, False, True, True, False, False)
    assert mdh.names[0] == "shoulder_pan_joint.mdh.theta" and mdh.units[1] == "m"


# --------------------------------------------------------------------------- files


def test_a_table_file_reads_back_as_the_same_table_and_model(estimate, dh, tmp_path):
    model = jaxcal.parameters_to_model(estimate).model
    doc = dh_table_json(
        dh.table, robot="ur5e", base_link="base_link", flange_link="flange", std=dh.std_table,
        nominal=dh.nominal_table, reduction_ratio=model.reduction_ratio,
    )  # fmt: skip
    path = tmp_path / "calibrated_dh.json"
    path.write_text(json.dumps(doc))
    table, back = read_dh_table(path)
    np.testing.assert_allclose(table_values(table), dh.estimate, atol=1e-12)
    np.testing.assert_allclose(back["std"]["a"], dh.std_table.a, atol=0)
    loaded = dh_table_model(path)
    assert loaded.link_names[0] == "base_link" and loaded.link_names[-1] == "flange"
    np.testing.assert_allclose(loaded.reduction_ratio, model.reduction_ratio)
    qs = _configs(6)[:200]
    T1 = np.asarray(jax.vmap(lambda q: forward_kinematics(loaded, q)[-1])(qs))
    T2 = np.asarray(jax.vmap(lambda q: forward_kinematics(model, q)[-1])(qs))
    np.testing.assert_allclose(T1, T2, atol=1e-9)
    # Bad files are named with their field.
    for edit, match in (
        (lambda d: d.pop("theta"), "no field 'theta'"),
        (lambda d: d.update(convention="xyz"), "convention"),
        (lambda d: d.update(d=[0.0] * 5), "field 'd'"),
        (lambda d: d.update(flange={"matrix": [[1.0]]}), "flange.matrix"),
    ):
        bad = json.loads(json.dumps(doc))
        edit(bad)
        path.write_text(json.dumps(bad))
        with pytest.raises(DatasetError, match=match):
            dh_table_model(path)


def test_joint_axes_at_zero_in_numpy_are_the_compiled_ones():
    """`parallel_pairs`' and the verdict's axes in NumPy equal the compiled `joint_axes` at
    q = 0, zero offsets and a prismatic joint included."""
    from jaxcal._kinematics import PRISMATIC, joint_axes, joint_axes_at_zero

    scales = PerturbationScales(zero_offset_deg=20.0, axis_tilt_deg=5.0)  # offsets that turn the axes after
    model = perturb_model(load_robot("ur5e"), jax.random.key(3), scales)
    types = (*model.joint_types[:2], PRISMATIC, *model.joint_types[3:])
    for m in (model, dataclasses.replace(model, joint_types=types)):
        for host, compiled in zip(joint_axes_at_zero(m), joint_axes(m, jnp.zeros(m.num_joints))):
            np.testing.assert_allclose(host, np.asarray(compiled), atol=1e-14)
