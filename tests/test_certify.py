"""`jaxcal certify` (jaxcal.certification) and `jaxcal check` (jaxcal.drift).

The statistics on analytic data (a drift reference drawn at random, no
calibration): the false-alarm rate at zero drift and the power against a
drift of known non-centrality against the non-central chi-square, and the
95 % quantile of a Gaussian norm. One end-to-end run on a simulated
stop-and-shoot capture: certify (its bound against the true errors), check
a later capture with and without a moved device (exit 0 / 3 on the command
line) and refuse captures of another robot, device or kind.
"""

import json
import shutil

import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

import jaxcal
from jaxcal._geometry import se3_exp
from jaxcal._kinematics import forward_kinematics
from jaxcal.certification import certify, norm_quantiles
from jaxcal.cli import main
from jaxcal.drift import DriftReference, check, check_samples, detectable, power
from jaxcal.errors import DatasetError
from jaxcal.io._files import check_output_dir
from jaxcal.io.checks import drift_check_from_json, drift_check_json, product_json, read_product
from jaxcal.io.model_json import model_from_json
from jaxcal.report import write_outputs
from jaxcal.sim.tracker import TrackerSimConfig, simulate_tracker
from jaxcal.verification import verify


def _reference(rng, samples=10, joints=6, sigma=1e-5) -> DriftReference:
    y = rng.normal(0.0, 0.5, (samples, 3)) + np.array([2.0, 0.0, 0.5])
    Z = rng.normal(0.0, 0.5, (samples, 3, joints))
    B = rng.normal(0.0, 4e-6, (3 * samples, 40))  # the calibration's error, correlated over samples
    R = np.diag(np.full(3 * samples, sigma**2)) + B @ B.T
    return DriftReference(y, Z, R, tuple(f"j{k}" for k in range(joints)), np.eye(4))


def _draw(ref, rng, eps=(0.0,) * 6):
    e = (np.linalg.cholesky(ref.R) @ rng.standard_normal(len(ref.R))).reshape(-1, 3)
    T = np.linalg.inv(np.asarray(se3_exp(jnp.asarray(eps))))
    return (ref.y_hat + e) @ T[:3, :3].T + T[:3, 3]


def test_false_alarms_and_power_match_the_chi_square_laws():
    rng = np.random.default_rng(0)
    ref = _reference(rng)
    trials = 400
    alarms = np.mean([check_samples(ref, _draw(ref, rng)).detected for _ in range(trials)])
    assert 0.025 <= alarms <= 0.08  # 5 % +- 2.7 binomial sigma
    C = check_samples(ref, _draw(ref, rng)).cov
    # A translation along the worst direction at the size of 50 % power, and the closed form.
    P = np.linalg.inv(C)
    mu, U = np.linalg.eigh(P[:3, :3])
    lam = 8.0
    eps = np.r_[np.sqrt(lam / mu[0]) * U[:, 0], 0.0, 0.0, 0.0]
    expected = float(power(lam, 6))
    hits = np.mean([check_samples(ref, _draw(ref, rng, eps)).detected for _ in range(trials)])
    assert abs(hits - expected) < 0.08, (hits, expected)
    # The detectable change is the one of 95 % power.
    d = detectable(C)
    assert power(d["noncentrality"], 6) == pytest.approx(0.95, abs=1e-6)
    assert d["translation_mm_worst"] == pytest.approx(1e3 * np.sqrt(d["noncentrality"] / mu[0]))


def test_the_estimated_drift_is_within_its_sigma_and_offsets_are_optional():
    rng = np.random.default_rng(1)
    ref = _reference(rng, samples=8)
    eps = np.r_[3e-4, -2e-4, 1e-4, 0.0, np.radians(0.02), 0.0]
    c = check_samples(ref, _draw(ref, rng, eps))
    assert c.detected and c.exit_code == 3 and "moved by" in c.message
    z = np.linalg.solve(np.linalg.cholesky(c.cov), c.theta - eps)
    assert np.sum(z**2) < stats.chi2.ppf(0.999, 6)
    c = check_samples(ref, _draw(ref, rng), joint_offsets=True)
    assert c.dof == 12 and len(c.joint_offsets_deg) == 6
    # Its JSON (the offsets as {joint: [deg, std]}) reads back as the record and writes again unchanged.
    text = json.dumps(drift_check_json(c), indent=1)
    back = drift_check_from_json(json.loads(text))
    assert json.dumps(drift_check_json(back), indent=1) == text
    assert back.joint_offsets_deg[2].joint == "j2" and np.allclose(
        back.theta, c.theta, rtol=1e-12, atol=1e-18
    )
    with pytest.raises(ValueError, match="samples"):
        check_samples(ref, _draw(ref, rng)[:2])


def test_norm_quantile_of_an_isotropic_gaussian():
    q, _ = norm_quantiles(np.eye(3)[None] * 4.0)
    assert q[0] == pytest.approx(2.0 * np.sqrt(stats.chi2.ppf(0.95, 3)), rel=0.03)
    q, _ = norm_quantiles(np.diag([1.0, 0.0, 0.0])[None])
    assert q[0] == pytest.approx(stats.norm.ppf(0.975), rel=0.03)


@pytest.fixture(scope="module")
def tracker(tmp_path_factory):
    root = tmp_path_factory.mktemp("certify")
    kw = dict(robot="ur5e", seed=5, noise_um=10.0, bad_fraction=0.0, home_deg=None, pose_range_deg=120.0)
    ds = simulate_tracker(TrackerSimConfig(poses=48, **kw), root / "ds")
    res = write_outputs(jaxcal.calibrate(ds, cv_folds=0, progress=False), root / "res")
    later = simulate_tracker(TrackerSimConfig(poses=10, **(kw | {"pose_range_deg": 100.0})), root / "later")
    return root, ds, res, later


def _moved(later, dest, eps):
    """A copy of `later` whose device moved by the twist `eps` (device frame)."""
    shutil.copytree(later, dest)
    lines = (dest / "samples.csv").read_text().splitlines()
    head = lines[0].split(",")
    ix = [head.index(a) for a in "xyz"]
    T = np.linalg.inv(np.asarray(se3_exp(jnp.asarray(eps))))
    out = [lines[0]]
    for line in lines[1:]:
        cells = line.split(",")
        p = T[:3, :3] @ np.array([float(cells[i]) for i in ix]) + T[:3, 3]
        for i, v in zip(ix, p):
            cells[i] = repr(float(v))
        out.append(",".join(cells))
    (dest / "samples.csv").write_text("\n".join(out) + "\n")
    return dest


def test_end_to_end_certify_and_check_a_tracker_calibration(tracker, tmp_path):
    root, ds, res, later = tracker
    truth = json.loads((ds / "truth.json").read_text())
    c = certify(res, samples=300)
    assert c.extrapolation is not None and c.summary["poses"] == 300
    assert c.covariance_model == "model"  # the point fit's, as result.json names it
    # The certified bound against the true errors at the same configurations.
    true = model_from_json(truth["model"])
    T_db = np.asarray(truth["cameras"]["tracker"]["T_cam_base"])
    p = np.asarray(truth["targets"]["smr"]["T_link_target"])
    y_true = np.array(
        [(T_db @ np.asarray(forward_kinematics(true, jnp.asarray(q)))[-1] @ p)[:3, 3] for q in c.q]
    )
    T_cal = np.asarray(json.loads((res / "result.json").read_text())["T_device_base"]["matrix"])
    y_cal = c.points @ T_cal[:3, :3].T + T_cal[:3, 3]
    err = 1e3 * np.linalg.norm(y_true - y_cal, axis=1)
    assert np.mean(err <= c.bound95_mm) >= 0.7
    assert (
        main(
            ["certify", str(res), "--region", "0.2,-0.3,0.1,0.6,0.3,0.5", "--json", str(tmp_path / "c.json")]
        )
        == 0
    )
    cj = json.loads((tmp_path / "c.json").read_text())
    assert (cj["schema"], cj["covariance_model"]) == ("jaxcal.certificate", "model")
    # A later capture of the same set-up passes; the device moved by 0.3 mm is found.
    assert main(["check", str(res), str(later), "--json", str(tmp_path / "d.json")]) == 0
    moved = _moved(later, tmp_path / "moved", np.r_[3e-4, 0.0, 0.0, 0.0, 0.0, 0.0])
    d = check(res, moved)
    assert d.detected and abs(d.translation_mm[0] - 0.3) < 3 * d.translation_mm[1] + 0.02
    assert main(["check", str(res), str(moved)]) == 3
    assert main(["verify", str(res), str(later), "--cv", "2", "--json", str(tmp_path / "v.json")]) == 0
    # Each file reads back as its typed record (`jaxcal.io.checks`) and writes again byte for byte.
    for name, schema in (("c.json", "certificate"), ("d.json", "drift_check"), ("v.json", "verification")):
        text = (tmp_path / name).read_text()
        assert json.loads(text)["schema"] == f"jaxcal.{schema}"
        assert json.dumps(product_json(read_product(tmp_path / name)), indent=1) == text
    v = read_product(tmp_path / "v.json")
    assert v.cv.folds == 2 and v.summary.samples == len(v.samples) == 10


def test_check_refuses_a_capture_of_another_robot_device_or_kind(tracker, tmp_path):
    root, ds, res, later = tracker
    other = tmp_path / "other_device"
    shutil.copytree(later, other)
    meta = json.loads((other / "metadata.json").read_text())
    meta["device"]["name"] = "another_tracker"
    (other / "metadata.json").write_text(json.dumps(meta))
    (other / "truth.json").unlink()
    with pytest.raises(DatasetError, match="metadata.json: device 'another_tracker'"):
        check(res, other)
    panda = simulate_tracker(TrackerSimConfig(robot="panda", poses=10, home_deg=None), tmp_path / "panda")
    with pytest.raises(DatasetError, match="another robot"):
        check(res, panda)
    with pytest.raises(DatasetError, match="a camera capture"):
        check(res, "data/ur5e_sweeps")
    with pytest.raises(DatasetError, match="estimate.npz: missing"):
        check(_camera_result(tmp_path), later)


def _camera_result(tmp_path):
    p = tmp_path / "cam"
    p.mkdir()
    (p / "result.json").write_text(json.dumps({"schema": "jaxcal.result", "capture": "eye-to-hand, sweeps"}))
    return p


def test_calibrate_with_a_joint_box_certifies_it(tracker, tmp_path):
    _, ds, _, _ = tracker
    out = tmp_path / "res"
    box = ",".join(["-30:30"] * 6)
    code = main(
        ["calibrate", str(ds), "--out", str(out), "--config", "cv-folds=0", "--quiet", "--joint-box", box]
    )
    assert code in (0, 1, 2)  # the status is not the point here
    report = (out / "report.md").read_text()
    assert "## Accuracy certificate" in report and report.index("## Accuracy certificate") < report.index(
        "## Plots"
    )
    text = (out / "certificate.json").read_text()
    doc = json.loads(text)
    assert doc["region"]["kind"] == "joint_box" and doc["summary"]["p95_mm"] > 0
    c = read_product(out / "certificate.json")
    assert np.allclose(c.region.ranges, np.radians([[-30.0, 30.0]] * 6), rtol=1e-15)
    assert c.summary.p95_mm == doc["summary"]["p95_mm"] and c.q.shape == (c.summary.poses, 6)
    assert json.dumps(product_json(c), indent=1) == text
    # certificate.json joins the result's files: --overwrite may replace them all.
    assert "certificate.json" in json.loads((out / ".jaxcal").read_text())["files"]
    assert check_output_dir(out, overwrite=True, kind="result").replaces is not None


@pytest.mark.parametrize("move_mm", [0.0, 5.0])
def test_a_capture_no_rigid_move_explains_leads_with_the_mismatch(move_mm):
    """Residuals far above their degrees of freedom after the rigid fit (a clock off, another
    mount): with or without a significant "move", the headline says the capture does not fit a
    rigid move, the advice points at the timestamps and the mount, and the exit code is the
    drift's; residuals at their degrees of freedom leave the usual verdict."""
    from jaxcal.drift import verdict
    from jaxcal.records_check import EXIT_DRIFT

    theta = np.r_[1e-3 * move_mm, 0.0, 0.0, 0.0, 0.0, 0.0]
    C = np.diag([1e-8] * 3 + [1e-8] * 3)  # 0.1 mm, 0.1 mrad
    T = float(theta @ np.linalg.solve(C, theta))
    kw = dict(samples=20, joint_names=("a", "b"), T_now=np.eye(4), what="camera", frame="T_cam_base")
    bad = verdict(theta, C, T, rss=400.0, dof_r=54, **kw)
    assert bad.message.startswith("the capture does not fit the calibration with the camera moved rigidly")
    assert "timestamps against the encoder log" in bad.advice and "target mount" in bad.advice
    assert not bad.residual.fits_rigidly and bad.exit_code == EXIT_DRIFT
    good = verdict(theta, C, T, rss=50.0, dof_r=54, **kw)
    assert good.residual.fits_rigidly and good.exit_code == (EXIT_DRIFT if move_mm else 0)
    assert good.message.startswith("the camera moved by" if move_mm else "no drift detected")


def test_a_failed_calibration_is_not_certified_and_a_suspect_one_is_said(tracker, tmp_path):
    """A result whose solver failed has no covariance worth a bound: refused, naming the file and its
    reason; a suspect one is certified with the suspicion stated first; `verify` measures either, saying so."""
    _, _, res, later = tracker
    doc = json.loads((res / "result.json").read_text())
    for status in ("failed", "suspect"):
        shutil.copytree(res, tmp_path / status)
        (tmp_path / status / "result.json").write_text(
            json.dumps(doc | {"status": status, "reasons": [f"the solver {status} here"]})
        )
    with pytest.raises(
        DatasetError, match=r"failed/result.json: the calibration failed \(status 'failed': the solver"
    ):
        certify(tmp_path / "failed", samples=50)
    c = certify(tmp_path / "suspect", samples=50)
    assert (
        c.notes[0] == "the calibration is suspect (the solver suspect here): these figures take it as right"
    )
    assert "is suspect" not in " ".join(certify(res, samples=50).notes)
    # `verify` measures either all the same, and says what the result is first.
    for status in ("failed", "suspect"):
        v = verify(tmp_path / status, later)
        assert v.notes[0] == f"the calibration is {status} (the solver {status} here)", v.notes
    assert not any(n.startswith("the calibration is") for n in verify(res, later).notes)
