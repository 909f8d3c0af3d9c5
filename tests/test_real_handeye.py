"""Real hand-eye captures that no one here took: ViSP's Franka Panda with a RealSense D435
(`data/visp_handeye`, GPL-2.0-or-later data), eye-in-hand on a chessboard and eye-to-hand on one
AprilTag. `jaxcal handeye` is judged against ViSP's own solver's published answer."""

import importlib.util
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from jaxcal.cli import main

ROOT = Path(__file__).resolve().parents[1] / "data" / "visp_handeye"
REFERENCE = json.loads((ROOT / "reference.json").read_text())


def _convert():
    spec = importlib.util.spec_from_file_location("visp_convert", ROOT / "convert.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _pose(vector) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(vector[3:], float))[0]
    T[:3, 3] = vector[:3]
    return T


@pytest.mark.parametrize("capture", ["eye_in_hand", "eye_to_hand"])
def test_the_captures_are_what_convert_makes_of_visps_files(capture, tmp_path):
    """`handeye.json` and `poses.csv` here are `convert.py`'s reading of ViSP's unchanged files."""
    built = _convert().build(capture, tmp_path, images=False)
    for name in ("handeye.json", "poses.csv"):
        assert (built / name).read_text() == (ROOT / capture / name).read_text(), name


@pytest.mark.parametrize(("capture", "key"), [("eye_in_hand", "T_ee_cam"), ("eye_to_hand", "T_base_cam")])
def test_real_captures_agree_with_visps_solver(capture, key, tmp_path, capsys):
    """Status ok on all 8 frames, and the camera pose within twice its own reported uncertainty
    (the norm of the per-axis std) of ViSP's answer on the same data: two estimators of one
    8-frame capture differ by about their uncertainty, a misread convention (units, the pose's
    direction, the tag's corner order) by centimetres and degrees. Before the 4-corner homography
    fix the one-tag capture was refused as "robot poses and images disagree"."""
    out = tmp_path / "out"
    assert main(["handeye", str(ROOT / capture), "--out", str(out), "--quiet"]) == 0
    r = json.loads((out / "result.json").read_text())
    assert r["status"] == "ok" and not r["reasons"]
    assert len(r["frames"]) == 8 and not any(f["rejected"] for f in r["frames"])
    cam = r["cameras"]["cam0"]
    T = np.asarray(cam["T_robot_cam"]["matrix"])
    ref = _pose(REFERENCE[capture][key])
    dt_mm = 1e3 * np.linalg.norm(T[:3, 3] - ref[:3, 3])
    drot_deg = np.degrees(np.linalg.norm(cv2.Rodrigues(T[:3, :3] @ ref[:3, :3].T)[0]))
    std_t, std_r = (np.linalg.norm(cam["std"][k]) for k in ("translation_mm", "rotation_deg"))
    print(f"{capture}: {dt_mm:.2f} mm / {drot_deg:.3f} deg from ViSP (std {std_t:.2f} mm / {std_r:.3f} deg)")
    assert dt_mm < 2.0 * std_t and drot_deg < 2.0 * std_r
    # The reprojection error is the detector's own: nothing left unmodelled.
    rms, sigma = r["solver"]["pixel_rms_px"], r["solver"]["sigma_px"]
    assert 0.6 < rms / sigma < 1.4, (rms, sigma)
    # Real poses are not exact: the robot noise is estimated from many degrees of freedom.
    text = " ".join(capsys.readouterr().out.split())  # the console wraps its lines
    assert "degrees of freedom (translation / rotation)" in text and "upper bound" not in text, text
    # The default kept the estimate: exact poses predict the frames left out 15-17 % better on these
    # 8 frames, but by 1.1-1.5 standard errors of the per-frame differences (2 needed), and land
    # 3.4 deg (eye-in-hand) from ViSP's answer and every pose-pair method's.
    model = r["robot_noise_model"]
    assert model["model"] == "estimate" and "exact" in [m["model"] for m in model["models"]]
    assert "not kept" in model["basis"] and r["held_out"]["folds"] == 8
