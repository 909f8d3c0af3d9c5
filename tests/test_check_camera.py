"""`jaxcal check` of camera captures (jaxcal.drift, jaxcal._drift_camera) on rendered images.

The calibration is the scene's truth written as a result (`result.json` and
`estimate.npz`: the true arm as nominal, zero correction, a small covariance),
so that the test needs no calibration run; the check captures are ten rendered
stop-and-shoot images (640x480; the plate is too small to detect at 320x240) of the same scene, the camera unmoved and moved
by 1 mm and 0.2 deg.
"""

import json
import shutil

import jax.numpy as jnp
import numpy as np
import pytest

from jaxcal._correction import Estimate, ParameterLayout
from jaxcal.cli import main
from jaxcal.drift import check
from jaxcal.errors import DatasetError
from jaxcal.io.dataset import load_dataset
from jaxcal.io.result import write_estimate
from jaxcal.robots import robot_path
from jaxcal.sim.drift import random_poses, render_check_capture
from jaxcal.sim.simulate import SimConfig, draw_truth, nominal_robot, scene_layout

CONFIG = SimConfig(resolution=(640, 480), seed=3)
MOVE = (1e-3 * np.array([0.6, 0.6, -0.53]), np.radians(0.2) * np.array([0.0, 0.6, 0.8]))


def _truth_result(path, capture) -> None:
    """The scene's truth as a camera calibration result with a small covariance."""
    nominal, _ = nominal_robot(CONFIG.robot)
    true = draw_truth(nominal, CONFIG)
    # simulate's scene: the true plate mount is the design jittered (seeded), a world camera as designed.
    plates, plates_true, cams, _ = scene_layout(nominal, true, CONFIG, np.random.default_rng(CONFIG.seed))
    layout = ParameterLayout.of(true, 1)
    n = layout.size
    x = np.zeros(n)
    x[layout.index("rate")] = 1.0
    sd = np.zeros(n)
    # A good calibration's: 20 um / 0.001 deg on the camera, 10 um / 10 urad on the arm.
    scales = {"cam": 2e-5, "origin": 1e-5, "zero": 1e-5, "tool": 1e-5, "rate": 2e-6, "clock": 0.01}
    for g, s in scales.items():
        sd[layout.index(g)] = s
    sd[layout.index("intr")[:4]] = 0.02
    mount = plates_true[0].T_link_target
    est = Estimate(
        x=jnp.asarray(x), cov=jnp.asarray(np.diag(sd**2)), free=jnp.asarray(sd > 0), nominal=true,
        T_flange_marker0=jnp.asarray(mount)[None], T_cam_base0=jnp.asarray(np.linalg.inv(cams[0].T_mount_cam)),
        reduction_ratio=jnp.asarray(true.reduction_ratio), layout=layout, mount_names=(plates[0].target.name,),
    )  # fmt: skip
    path.mkdir()
    write_estimate(path / "estimate.npz", est)
    cam = load_dataset(capture).cameras[0]
    doc = {
        "schema": "jaxcal.result",
        "dataset": str(capture),
        "setup": "eye_to_hand",
        "capture": "eye-to-hand, single-joint sweeps, encoder log",
        "camera": cam.name,
        "targets": [plates[0].target.name],
        "intrinsics": {"source": "metadata", "K": np.asarray(cam.K).tolist(), "distortion": [0.0] * 5},
        "clock": {"offset_s": 0.0},
        "refinement": {"sigma_px": 0.05},
    }
    (path / "result.json").write_text(json.dumps(doc))


@pytest.fixture(scope="module")
def captures(tmp_path_factory):
    root = tmp_path_factory.mktemp("check_camera")
    q = random_poses(6, 10, 10.0, seed=1)
    still = render_check_capture(CONFIG, root / "still", q)
    moved = render_check_capture(CONFIG, root / "moved", q, move=MOVE)
    _truth_result(root / "result", still)
    return root / "result", still, moved


@pytest.mark.slow
def test_a_moved_camera_is_detected_and_an_unmoved_one_is_not(captures, tmp_path):
    res, still, moved = captures
    c0 = check(res, still)
    assert not c0.detected and c0.exit_code == 0 and "no drift detected" in c0.message
    assert c0.what == "camera" and c0.samples == 10
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
