"""Stop-and-shoot tracker data (issue 31): the point fit's residual model
(`jaxcal._pointfit`), its stage (`stages._points`), `jaxcal verify`, and the real
UR5 measured by a laser tracker (`data/ur5_tracker`, public data).

Simulated captures: 200 random poses inside the joint limits, 10 um noise, a
perturbed UR5 (DH table) and a Panda (URDF). "Every identifiable parameter
within 3 sigma" is checked in the fit's own gauge: the same free parameters fitted
to the noise-free points give the truth of that gauge (residual ~0 when the
model spans the perturbation), and each free parameter of the noisy fit must lie
within 3 of its standard deviations of it.
"""

import json
import shutil

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcal
from jaxcal._kinematics import forward_kinematics
from jaxcal._linalg import concurrent_decompositions
from jaxcal._pointfit import cross_validate, fit_points, fold_masks, point_jacobian, predict
from jaxcal.cli import main
from jaxcal.errors import DatasetError
from jaxcal.inspection import inspect_dataset
from jaxcal.io.model_json import model_from_json
from jaxcal.sim.tracker import TrackerSimConfig, simulate_tracker
from jaxcal.stages._points import _refit
from jaxcal.verification import verify

#: The UR5's true compliances in the simulation (rad per kN m): shoulder and elbow sag.
COMPLIANCE = (0.0, 0.05, 0.1, 0.0, 0.0, 0.0)


def _simulate(tmp_path_factory, robot, **kw):
    out = tmp_path_factory.mktemp(f"poses_{robot}") / "ds"
    config = TrackerSimConfig(
        robot=robot, seed=3, poses=200, noise_um=10.0, bad_fraction=0.0, home_deg=None, **kw
    )
    return simulate_tracker(config, out)


@pytest.fixture(scope="module")
def ur5(tmp_path_factory):
    path = _simulate(tmp_path_factory, "ur5")
    return path, jaxcal.calibrate(path, cv_folds=0)


@pytest.fixture(scope="module")
def panda(tmp_path_factory):
    path = _simulate(tmp_path_factory, "panda")
    return path, jaxcal.calibrate(path, cv_folds=0)


def _true_points(path, q):
    truth = json.loads((path / "truth.json").read_text())
    model = model_from_json(truth["model"])
    T_db = np.asarray(truth["cameras"]["tracker"]["T_cam_base"])
    T_fp = np.asarray(truth["targets"]["smr"]["T_link_target"])
    F = np.asarray(jax.vmap(lambda qq: forward_kinematics(model, qq)[-1])(jnp.asarray(q)))
    return np.einsum("ab,sbc,c->sa", T_db, F, T_fp[:, 3])[:, :3]


def _z_scores(path, result):
    """Per free parameter, the noisy fit's distance from the noise-free fit (same gauge) in its std."""
    pf = result.point_fit
    problem = pf.problem
    y = _true_points(path, np.asarray(problem.data.q))
    exact = eqx.tree_at(lambda p: p.data.y, problem, jnp.asarray(y))
    ref = _refit(exact, jnp.asarray(pf.candidates), jnp.asarray(pf.fit.free))
    free = np.asarray(pf.fit.free)
    z = (np.asarray(pf.fit.x) - np.asarray(ref.x))[free] / np.asarray(pf.fit.std)[free]
    return z, float(ref.rms_m)


@pytest.mark.parametrize("which", ["ur5", "panda"])
def test_simulated_poses_recover_every_identifiable_parameter(which, request):
    path, r = request.getfixturevalue(which)
    assert r.kind.fits_points and r.status == "ok", r.reasons
    z, exact_rms = _z_scores(path, r)
    assert exact_rms < 1e-9  # the free parameters span the perturbation: the exact data fit exactly
    assert np.all(np.abs(z) < 3.0), np.round(z, 2)
    assert 0.6 < np.sqrt(np.mean(z**2)) < 1.5  # the std are honest, not merely wide
    # The frozen ones are named, and the fit sees the tool point to micrometres.
    assert r.frozen and all(isinstance(n, str) for n in r.frozen)
    assert r.validation["ee_rms_mm_after"] < 0.01 < 1.0 < r.validation["ee_rms_mm_before"]


def test_simulated_compliance_is_recovered_and_kept_by_cross_validation(tmp_path_factory):
    path = _simulate(tmp_path_factory, "ur5", compliance=COMPLIANCE)
    r = jaxcal.calibrate(path, terms=("compliance",))
    assert r.status == "ok", r.reasons
    models = r.point_fit.models
    assert [m["terms"] for m in models] == [[], ["compliance"]]
    assert models[1]["kept"] and models[1]["cv_mean_mm"] < 0.2 * models[0]["cv_mean_mm"]
    rows = {row["name"].split(".")[0]: row for row in r.point_fit.term_rows}
    assert not rows["shoulder_pan_joint"]["free"]  # a vertical axis carries no gravity torque
    for joint, c in zip(r.nominal.joint_names, COMPLIANCE):
        row = rows[joint]
        if row["free"] and c > 0:
            assert abs(row["estimate"] - c) < 3 * row["std"], (joint, row)
    assert rows["shoulder_lift_joint"]["free"] and rows["elbow_joint"]["free"]


def test_point_jacobian_matches_autodiff(ur5):
    _, r = ur5
    problem = r.point_fit.problem
    x = 1e-2 * jax.random.normal(jax.random.key(0), (r.point_fit.layout.size,))
    closed = jax.jit(point_jacobian)(x, problem)  # each one program (op by op: ~150 small ones)
    auto = jax.jit(jax.jacfwd(predict))(x, problem)
    np.testing.assert_allclose(closed, auto, atol=1e-12 * float(jnp.max(jnp.abs(auto))))


def test_cross_validation_keeps_lapack_calls_ordered(ur5):
    _, r = ur5
    pf = r.point_fit
    train = jnp.asarray(fold_masks(len(pf.used), 3))
    assert concurrent_decompositions(cross_validate, pf.problem, pf.candidates, pf.fit.free, train) == []
    # A fold's fit equals the same fit run alone.
    dist, test, _ = cross_validate(pf.problem, pf.candidates, pf.fit.free, train)
    fold = eqx.tree_at(lambda p: p.data.mask, pf.problem, pf.problem.data.mask & train[1])
    alone = fit_points(fold, jnp.asarray(pf.candidates), tol=0.0, free=jnp.asarray(pf.fit.free))
    d1 = np.linalg.norm(np.asarray(predict(alone.x, pf.problem)) - np.asarray(pf.problem.data.y), axis=1)
    np.testing.assert_allclose(np.asarray(dist)[1][np.asarray(test)[1]], d1[np.asarray(test)[1]], rtol=1e-6)


def _table_without_joints(src, dst):
    shutil.copytree(src, dst)
    lines = (dst / "samples.csv").read_text().splitlines()
    header = lines[0].split(",")
    keep = [i for i, h in enumerate(header) if h in ("sample", "timestamp", "joint", "x", "y", "z")]
    (dst / "samples.csv").write_text(
        "\n".join(",".join(line.split(",")[i] for i in keep) for line in lines) + "\n"
    )
    (dst / "truth.json").unlink()


def test_stop_and_shoot_is_recognised_and_needs_joint_positions(ur5, tmp_path):
    path, _ = ur5
    summary = inspect_dataset(path, sample=1)
    assert "stop-and-shoot poses" in summary["kind"]
    assert all(j["samples"] == 200 for j in summary["joints"]) and summary["unassigned_samples"] == 0
    # A `joint: null` motion segment says the same.
    seg = tmp_path / "segment"
    shutil.copytree(path, seg)
    meta = json.loads((seg / "metadata.json").read_text())
    meta["motion"] = [{"joint": None, "start": 0.0, "end": 10.0}]
    (seg / "metadata.json").write_text(json.dumps(meta))
    assert "stop-and-shoot poses" in inspect_dataset(seg, sample=1)["kind"]
    # Without joint positions the samples cannot be placed: the error names the file and what to add.
    bare = tmp_path / "bare"
    _table_without_joints(path, bare)
    meta = json.loads((bare / "metadata.json").read_text())
    meta["motion"] = [{"joint": None, "start": 0.0, "end": 10.0}]
    (bare / "metadata.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match=r"samples.csv: stop-and-shoot samples .* joint positions"):
        jaxcal.calibrate(bare)


# --------------------------------------------------------------------------- the real UR5


@pytest.fixture(scope="module")
def ur5_real(tmp_path_factory):
    out = tmp_path_factory.mktemp("ur5_real") / "result"
    assert main(["calibrate", "data/ur5_tracker/grid", "--device-is-base", "--out", str(out), "--quiet"]) == 0
    return out


def test_real_ur5_calibration_meets_the_independent_reference(ur5_real, tmp_path):
    """The issue's acceptance on public laser-tracker data of a real UR5: an independent
    SciPy fit of the same model gives 0.1005 mm mean on the 20 held-out poses."""
    doc = json.loads((ur5_real / "result.json").read_text())
    assert doc["status"] == "ok" and doc["capture"].endswith("stop-and-shoot poses, joint positions")
    pf = doc["point_fit"]
    assert sum(pf["free"]) == 25 and len(pf["held"]) == 20
    assert pf["models"][0]["cv_mean_mm"] < 0.105
    v = verify(ur5_real, "data/ur5_tracker/test")
    s = v.summary
    assert 2.5 < s["nominal_mm"]["mean"] < 2.6
    assert s["calibrated_mm"]["mean"] <= 0.1010 and s["calibrated_mm"]["rms"] <= 0.105
    assert s["calibrated_mm"]["max"] <= 0.16
    assert 0.7 <= 1 / s["measured_over_predicted"] <= 1.4
    # The CLI writes its table, JSON and plot, and refuses to overwrite an input.
    out = tmp_path / "v.json"
    assert (
        main(
            [
                "verify",
                str(ur5_real),
                "data/ur5_tracker/test",
                "--json",
                str(out),
                "--plot",
                str(tmp_path / "v.png"),
            ]
        )
        == 0
    )
    assert len(json.loads(out.read_text())["samples"]) == 20 and (tmp_path / "v.png").stat().st_size > 10_000
    assert (
        main(["verify", str(ur5_real), "data/ur5_tracker/test", "--json", str(ur5_real / "result.json")]) == 2
    )


def test_a_check_freeing_the_joint_offsets_reaches_the_least_squares_optimum(ur5_real):
    """The real UR5's held-out poses checked with the joints' zero offsets free: the device's
    rotation about the base's vertical and the first joint's offset are nearly one direction, and
    undamped Gauss-Newton (the drift fit before) overshot on its first full step and stopped where
    its eight steps ended (T 35.0 or 31.4 with the arithmetic of the program). The fit reaches the
    optimum: zero gradient, and the sum of squares and statistic of SciPy's solve from zero."""
    from scipy.optimize import least_squares

    from jaxcal import drift
    from jaxcal.io.dataset import load_dataset

    s = load_dataset("data/ur5_tracker/test").samples
    ref = drift.reference(drift.read_calibration(ur5_real), s.q, s.sigma_m)
    y = np.asarray(s.position, np.float64)
    c = drift.check_samples(ref, y, joint_offsets=True)
    W = drift.whitening(ref.R)

    def res(theta):
        return jnp.asarray(W) @ (jnp.asarray(y) - drift._model(theta, ref.y_hat, ref.Z)).reshape(-1)

    A = np.asarray(jax.jacfwd(res)(jnp.asarray(c.theta)))
    assert np.linalg.cond(A) > 1e4  # the near-degenerate pair
    r = np.asarray(res(jnp.asarray(c.theta)))
    scale = np.linalg.norm(A, axis=0) * np.linalg.norm(r)
    assert np.max(np.abs(A.T @ r) / scale) < 1e-6  # stationary
    sol = least_squares(
        lambda t: np.asarray(res(jnp.asarray(t))),
        np.zeros(12),
        jac=lambda t: np.asarray(jax.jacfwd(res)(jnp.asarray(t))),
        method="lm",
        xtol=1e-15,
        ftol=1e-15,
        gtol=1e-15,
    )
    assert r @ r == pytest.approx(sol.fun @ sol.fun, rel=1e-9)
    J = sol.jac
    assert c.statistic == pytest.approx(sol.x @ (J.T @ J) @ sol.x, rel=1e-4)


def test_verify_refuses_data_of_another_robot_or_kind(ur5_real, panda, tmp_path):
    panda_path, _ = panda
    with pytest.raises(DatasetError, match="another robot"):
        verify(ur5_real, panda_path)
    camera = tmp_path / "camera_result"
    camera.mkdir()
    (camera / "result.json").write_text(json.dumps({"schema": "jaxcal.result", "capture": "eye-to-hand"}))
    with pytest.raises(DatasetError, match="no 'point_fit' block"):
        verify(camera, "data/ur5_tracker/test")
    with pytest.raises(DatasetError, match="not a tracker dataset"):
        verify(ur5_real, "data/ur5e_sweeps")


def test_sweeps_and_poses_mixed_in_one_table_fit_every_sample(ur5, tmp_path):
    """A table whose `joint` cells name sweeping joints for some samples and leave the
    others empty, joint positions given for all: the point fit takes every sample."""
    path, alone = ur5
    mixed = tmp_path / "mixed"
    shutil.copytree(path, mixed)
    lines = (mixed / "samples.csv").read_text().splitlines()
    header, rows = lines[0], lines[1:]
    joints = header.split(",")[6:]
    sweep = []
    for line in rows[:40]:  # the first 40 poses re-labelled as wrist 1 "sweep" samples
        cells = line.split(",")
        cells[2] = joints[3]
        sweep.append(",".join(cells))
    (mixed / "samples.csv").write_text("\n".join([header, *sweep, *rows[40:]]) + "\n")
    assert "stop-and-shoot poses" in inspect_dataset(mixed, sample=1)["kind"]
    r = jaxcal.calibrate(mixed, cv_folds=0)
    assert r.point_fit is not None and int(r.point_fit.used.sum()) == 200
    np.testing.assert_allclose(r.point_fit.fit.x, alone.point_fit.fit.x, atol=1e-12)
