"""Real hand-eye captures that no one here took: ViSP's Franka Panda with a RealSense D435
(`data/visp_handeye`, GPL-2.0-or-later data), eye-in-hand on a chessboard and eye-to-hand on one
AprilTag. `jaxcal handeye` is judged against ViSP's own solver's published answer."""

import importlib.util
import json
import re
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
    """All 8 frames kept, and the camera pose within twice its own reported uncertainty
    (the norm of the per-axis std) of ViSP's answer on the same data: two estimators of one
    8-frame capture differ by about their uncertainty, a misread convention (units, the pose's
    direction, the tag's corner order) by centimetres and degrees. Before the 4-corner homography
    fix the one-tag capture was refused as "robot poses and images disagree"."""
    out = tmp_path / "out"
    reference = str(ROOT / "reference.json")
    code = main(["handeye", str(ROOT / capture), "--out", str(out), "--quiet", "--reference", reference])
    r = json.loads((out / "result.json").read_text())
    if capture == "eye_to_hand":
        assert code == 0 and r["status"] == "ok" and not r["reasons"]
        # One tag's four corners a view: the lens test cannot run, and the result says so.
        assert any("the lens test did not run" in n for n in r["notes"]), r["notes"]
        assert "lens_test" not in r["cameras"]["cam0"] and "image_scale" in r["cameras"]["cam0"]
    else:
        # The chessboard's PnP distances fall 12.7 % short of those the Franka's motion implies, 6.4
        # standard errors (the jackknife's over the 8 frames): the square size ViSP states (23.6 mm), the
        # focal length or the robot's kinematics is off, and the camera's depth with it, in ViSP's answer
        # as in jaxcal's. The tag's eye-to-hand capture, same camera and robot, is at 1.00.
        # Its corners' residuals also grow with the distance from the image's centre, as a lens the
        # metadata's zero distortion leaves out (ViSP's intrinsics: the camera's factory K, no lens).
        assert code == 3 and r["status"] == "suspect"
        scale, lens = r["reasons"]
        assert "PnP's distances are -12.7 % (+/- 2.0 %)" in scale, scale
        assert "as a lens's radial distortion does" in lens and "cameras[].distortion" in lens, lens
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
    # --reference says the same in the user's words: the distance from ViSP's answer in millimetres and
    # degrees and, per axis, in the result's own standard deviations, naming an axis beyond two. Eye-to-hand
    # (7 degrees of freedom of rotation noise) lies 4.1 of them from ViSP on ry: printed, not hidden.
    pattern = (
        rf"against {re.escape(reference)}: ([0-9.]+) mm / ([0-9.]+) deg, per axis (.*?) deviations: (\w+)"
    )
    said = re.search(pattern, text)
    assert said is not None, text
    assert float(said[1]) == pytest.approx(dt_mm, abs=1e-3)
    assert float(said[2]) == pytest.approx(drot_deg, abs=1e-4)
    e = np.concatenate([T[:3, 3] - ref[:3, 3], cv2.Rodrigues(T[:3, :3] @ ref[:3, :3].T)[0].ravel()])
    std = np.concatenate(
        [1e-3 * np.asarray(cam["std"]["translation_mm"]), np.radians(cam["std"]["rotation_deg"])]
    )
    z = e / std
    assert [float(v) for v in re.findall(r"-?[0-9.]+", said[3])] == pytest.approx(np.round(z, 2), abs=0.011)
    assert said[4] == ("within" if np.max(np.abs(z)) <= 2 else "off"), said[0]
    assert np.max(np.abs(z)) == pytest.approx({"eye_in_hand": 0.41, "eye_to_hand": 4.09}[capture], abs=0.05)
    # ... and next to the status, which judges the capture, not this difference.
    tied = (
        f"{reference} disagrees with camera(s) cam0 beyond 2 standard deviations (above): the status judges"
    )
    assert (tied in text) == (capture == "eye_to_hand"), text
    # The default kept the estimate: exact poses predict the frames left out 15-17 % better on these
    # 8 frames, but by 1.1-1.5 standard errors of the per-frame differences (2 needed), and land
    # 3.4 deg (eye-in-hand) from ViSP's answer and every pose-pair method's.
    model = r["robot_noise_model"]
    assert model["model"] == "estimate" and "exact" in [m["model"] for m in model["models"]]
    assert "not kept" in model["basis"] and r["held_out"]["folds"] == 8


def test_a_reference_file_is_read_as_the_capture_needs_it(tmp_path):
    """`jaxcal handeye --reference`: ViSP's file (one block per arrangement, 6-vectors in m and rad),
    a 4x4 matrix (under its key, or alone), a jaxcal result's own `cameras` block and the pose keyed
    by camera (a simulated capture's truth.json) all give the same pose; a file of the
    other arrangement's pose, or a pose that is not rigid, is refused naming the file and field."""
    from jaxcal.errors import DatasetError
    from jaxcal.io.handeye import load_hand_eye_capture, read_reference

    capture = load_hand_eye_capture(ROOT / "eye_in_hand")
    want = _pose(REFERENCE["eye_in_hand"]["T_ee_cam"])
    got = read_reference(ROOT / "reference.json", capture)
    np.testing.assert_allclose(got["cam0"], want, atol=1e-12)
    for doc in (
        {"T_ee_cam": want.tolist()},
        {"cameras": {"cam0": {"T_robot_cam": {"matrix": want.tolist()}}}},
        want.tolist(),  # the pose alone
        {"T_robot_cam": {"cam0": want.tolist()}},  # simulate-handeye's truth.json
    ):
        (tmp_path / "ref.json").write_text(json.dumps(doc))
        np.testing.assert_allclose(read_reference(tmp_path / "ref.json", capture)["cam0"], want, atol=1e-12)
    bad = want.copy()
    bad[0, 0] = 2.0
    for doc, words in (
        ({"T_base_cam": want.tolist()}, "another arrangement's pose"),
        ({"T_ee_cam": bad.tolist()}, "not a rigid transform"),
        ({"T_ee_cam": [0.1, 0.2]}, "4x4 matrix or [tx, ty, tz, rx, ry, rz]"),
        ({"cameras": {"other": {"T_ee_cam": want.tolist()}}}, "no pose for camera 'cam0'"),
    ):
        (tmp_path / "ref.json").write_text(json.dumps(doc))
        with pytest.raises(DatasetError, match=re.escape(words)) as e:
            read_reference(tmp_path / "ref.json", capture)
        assert "ref.json" in str(e.value)
