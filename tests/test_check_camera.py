"""`jaxcal check` of camera captures (jaxcal.drift, jaxcal._drift_camera) on rendered images.

The calibration is the scene's truth written as a result (`result.json` and
`estimate.npz`: the true arm as nominal, zero correction, a small covariance),
so that the test needs no calibration run (`jaxcal.sim.drift.truth_result`); the
check captures are ten rendered stop-and-shoot images (640x480: the plate is too
small to detect at 320x240) of the same scene, the camera unmoved and moved by
1 mm and 0.2 deg; eye-to-hand and eye-in-hand (the camera on the flange moved). The
statistics on analytic corners: the rendered capture's detections replaced by the model's
prediction with a drawn calibration error and corner noise, against the F laws.
"""

import dataclasses
import json
import shutil

import numpy as np
import pytest

from jaxcal._drift_camera import view_jacobians
from jaxcal.certification import read_result
from jaxcal.cli import main
from jaxcal.drift import camera_capture, camera_check_reference, check, check_camera, power
from jaxcal.errors import DatasetError
from jaxcal.io.checks import drift_check_json, product_json, read_product
from jaxcal.io.dataset import load_dataset
from jaxcal.planning._check import plan_check
from jaxcal.robots import robot_path
from jaxcal.sim.drift import random_poses, render_check_capture, truth_result
from jaxcal.sim.simulate import SimConfig

CONFIG = SimConfig(resolution=(640, 480), seed=3)
MOVE = (1e-3 * np.array([0.6, 0.6, -0.53]), np.radians(0.2) * np.array([0.0, 0.6, 0.8]))


@pytest.fixture(scope="module")
def captures(tmp_path_factory):
    root = tmp_path_factory.mktemp("check_camera")
    q = random_poses(6, 10, 10.0, seed=1)
    still = render_check_capture(CONFIG, root / "still", q)
    moved = render_check_capture(CONFIG, root / "moved", q, move=MOVE)
    truth_result(CONFIG, still, root / "result")
    return root / "result", still, moved


@pytest.mark.slow
def test_a_moved_camera_is_detected_and_an_unmoved_one_is_not(captures, tmp_path):
    res, still, moved = captures
    c0 = check(res, still)
    assert not c0.detected and c0.exit_code == 0 and "no drift detected" in c0.message
    assert c0.what == "camera" and c0.samples == 10 and "not tested" not in c0.message
    # A capture of more cameras than the one the result calibrated: the others are said untested.
    cap = camera_capture(*read_result(res), load_dataset(still))
    two = dataclasses.replace(
        cap.ds, cameras=(*cap.ds.cameras, dataclasses.replace(cap.ds.cameras[0], name="cam1"))
    )
    said = check_camera(dataclasses.replace(cap, ds=two)).message
    assert said.endswith("; camera 'cam0' only: ['cam1'] not tested"), said
    assert c0.detectable["translation_mm_worst"] < 1.0
    c1 = check(res, moved)
    assert c1.detected and c1.exit_code == 3 and "the camera moved by" in c1.message
    # The camera's twist against the truth (its frame; first order in the coupling).
    sd = np.sqrt(np.diag(c1.cov))
    assert np.all(np.abs(c1.theta[:3] - MOVE[0]) < 4 * sd[:3] + 2e-5), (c1.theta, sd)
    assert np.all(np.abs(c1.theta[3:6] - MOVE[1]) < 4 * sd[3:6] + 2e-5), (c1.theta, sd)
    out = tmp_path / "drift.json"
    assert main(["check", str(res), str(moved), "--json", str(out), "--workers", "1"]) == 3
    doc = json.loads(out.read_text())
    assert doc["detected"] and doc["moved"] == "camera" and "T_cam_base_now" in doc
    back = read_product(out)  # the typed record, written again byte for byte
    assert back.residual.noise_variance_factor == doc["residual"]["noise_variance_factor"]
    assert json.dumps(product_json(back), indent=1) == out.read_text()


@pytest.mark.slow
def test_check_refuses_a_capture_of_another_camera_target_or_robot(captures, tmp_path):
    res, still, _ = captures

    def variant(name, edit):
        p = tmp_path / name
        shutil.copytree(still, p)
        meta = json.loads((p / "metadata.json").read_text())
        edit(meta, p)
        (p / "truth.json").unlink()
        (p / "metadata.json").write_text(json.dumps(meta))
        return p

    def zoom(meta, p):
        meta["cameras"][0]["K"][0][0] *= 1.1
        meta["cameras"][0]["K"][1][1] *= 1.1

    with pytest.raises(
        DatasetError, match="metadata.json: camera 'cam0' intrinsics K differ.*another camera"
    ):
        check(res, variant("zoomed", zoom))

    def rename(meta, p):
        meta["targets"][0]["name"] = "another_plate"

    with pytest.raises(DatasetError, match="metadata.json: targets.*another target"):
        check(res, variant("renamed", rename))

    def ur3(meta, p):
        shutil.copyfile(robot_path("ur3"), p / "robot.urdf")

    with pytest.raises(DatasetError, match="robot.urdf: its joint origins.*another robot"):
        check(res, variant("ur3", ur3))


@pytest.mark.slow
def test_eye_in_hand_a_moved_camera_mount_is_detected(tmp_path):
    cfg = SimConfig(resolution=(640, 480), seed=3, eye_in_hand=True)
    q = random_poses(6, 10, 10.0, seed=1)
    still = render_check_capture(cfg, tmp_path / "still", q)
    moved = render_check_capture(cfg, tmp_path / "moved", q, move=MOVE)
    res = truth_result(cfg, still, tmp_path / "result")
    c0, c1 = check(res, still), check(res, moved)
    assert not c0.detected and c1.detected and drift_check_json(c1)["T_flange_cam_now"]
    # The mount's own jitter turns the move's direction (D^-1 E D): its size is kept.
    assert abs(c1.translation_mm[0] - 1e3 * np.linalg.norm(MOVE[0])) < 4 * c1.translation_mm[1] + 0.02
    assert abs(c1.rotation_deg[0] - 0.2) < 4 * c1.rotation_deg[1] + 0.002


@pytest.mark.slow
def test_plan_check_proposes_poses_better_than_random(captures, tmp_path):
    res, _, _ = captures
    out = tmp_path / "poses.csv"
    argv = [
        "plan",
        "--check",
        str(res),
        "--budget",
        "4",
        "--config",
        "candidates=150",
        "--out",
        str(out),
        "--quiet",
    ]
    assert main(argv) == 0
    lines = out.read_text().splitlines()
    assert lines[0].split(",")[0] == "shoulder_pan_joint" and len(lines) == 5
    cp = plan_check(res, 4, candidates=150)
    worst = [s.translation_mm_worst for s in cp.steps]
    assert all(b <= a + 1e-9 for a, b in zip(worst, worst[1:]))
    assert worst[-1] <= cp.random.translation_mm_worst


@pytest.mark.slow
def test_camera_check_statistics_on_analytic_corners(captures):
    """The rendered capture's corners replaced by the calibrated model's prediction plus a
    calibration error drawn from kappa Sigma and corner noise 1.5x the calibration's variance
    (the check estimates it), with and without a move of known non-centrality: the false alarms
    and the power match Fisher's F laws the test uses."""
    res, still, _ = captures
    doc, file = read_result(res)
    cap = camera_capture(doc, file, load_dataset(still))
    ref, views = camera_check_reference(cap)
    pix, _, A, J = (np.asarray(a) for a in view_jacobians(ref.x, ref.problem))
    n = J.shape[-1]
    lam, V = np.linalg.eigh(np.asarray(cap.est.cov)[:n, :n])
    L = V * np.sqrt(np.maximum(lam, 0.0) * ref.factor)
    sigma = np.sqrt(1.5) * ref.sigma_px
    rng = np.random.default_rng(0)
    counts = [len(p) for p in cap.points[:views]]

    def draw(eps):
        d = (J @ (L @ rng.standard_normal(n)) + A @ eps).reshape(pix.shape)
        return [pix[i, :k] + d[i, :k] + sigma * rng.standard_normal((k, 2)) for i, k in enumerate(counts)]

    trials = 200
    null = [check_camera(cap, pixels=draw(np.zeros(6))) for _ in range(trials)]
    assert 0.015 <= np.mean([c.detected for c in null]) <= 0.095  # 5 % +- 2.9 binomial sigma
    assert abs(np.mean([c.residual["noise_variance_factor"] for c in null]) - 1.5) < 0.1
    P = np.linalg.inv(null[0].cov)
    mu, U = np.linalg.eigh(P[:3, :3])
    eps = np.r_[np.sqrt(8.0 / mu[0]) * U[:, 0], 0.0, 0.0, 0.0]
    hits = np.mean([check_camera(cap, pixels=draw(eps)).detected for _ in range(150)])
    expected = float(power(8.0, 6, 0.05, null[0].dof_noise))
    assert abs(hits - expected) < 0.12, (hits, expected)
