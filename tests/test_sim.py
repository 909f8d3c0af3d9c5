"""The MuJoCo synthetic arm: kinematics oracle, camera model, textures, clocks, datasets."""

import json
import re
from pathlib import Path

import cv2
import jax
import numpy as np
import pytest

from jaxcal import forward_kinematics
from jaxcal.errors import OutputError
from jaxcal.io._truth import small_markers
from jaxcal.io.dataset import DatasetError, load_dataset, true_poses
from jaxcal.io.model_json import model_from_json
from jaxcal.markers import TargetSpec
from jaxcal.robots import load_robot
from jaxcal.sim import CameraSpec, PlateSpec, build_scene
from jaxcal.sim._gl import no_backend_error
from jaxcal.sim.simulate import SimConfig, draw_truth, facing_mount, look_at, simulate

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.slow

BOARD = TargetSpec(squares=(5, 4), square_length=0.04, marker_length=0.03, name="board")


def charuco_corners(image, spec: TargetSpec):
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    detector = cv2.aruco.CharucoDetector(spec.board(), cv2.aruco.CharucoParameters(), params)
    corners, ids, _, _ = detector.detectBoard(cv2.cvtColor(image, cv2.COLOR_RGB2GRAY))
    assert ids is not None and len(ids) >= 4, "board not detected"
    return corners[:, 0].astype(np.float64), ids.ravel()


def project(K, T_cam_target, points):
    P = points @ T_cam_target[:3, :3].T + T_cam_target[:3, 3]
    return (P / P[:, 2:]) @ K[:2].T


def world_board_scene(spec, T_world_target, camera):
    """A scene with one board fixed in the world (the arm stands behind the camera)."""
    T_world_base = np.eye(4)
    T_world_base[2, 3] = -3.0
    plates = [PlateSpec(spec, "world", T_world_target)]
    return build_scene(load_robot("ur5e"), plates=plates, cameras=[camera], T_world_base=T_world_base)


@pytest.mark.parametrize("robot", ["ur5e", "panda"])
def test_mujoco_body_poses_equal_jaxcal_fk_of_the_true_model(robot):
    nominal = load_robot(robot)
    true = draw_truth(nominal, SimConfig(robot=robot, seed=3))
    assert (
        np.abs(np.asarray(true.T_parent_joint - nominal.T_parent_joint))[1:].max() > 1e-4
    )  # really perturbed
    T_link_plate = facing_mount(BOARD, (0.0, 0.0, 1.0), (0.0, 0.0, 0.01))
    T_flange_cam = look_at((0.1, 0.0, 0.0), (0.1, 0.0, 1.0))
    scene = build_scene(
        true,
        plates=[PlateSpec(BOARD, true.link_names[-1], T_link_plate)],
        cameras=[CameraSpec("hand", 64, 48, mount=true.link_names[-1], T_mount_cam=T_flange_cam)],
    )
    rng = np.random.default_rng(0)
    fk = jax.jit(forward_kinematics)
    for _ in range(5):
        q = rng.uniform(-np.pi, np.pi, nominal.num_joints)
        scene.set_angles(q + np.asarray(true.zero_offset))
        frames = np.asarray(fk(true, q))
        for name, T in zip(true.link_names, frames):
            np.testing.assert_allclose(scene.body_pose(name), T, atol=1e-9, err_msg=name)
        np.testing.assert_allclose(scene.body_pose("plate:board"), frames[-1] @ T_link_plate, atol=1e-9)
        np.testing.assert_allclose(scene.camera_pose("hand"), frames[-1] @ T_flange_cam, atol=1e-9)
    scene.close()


def test_intrinsics_pixel_centre_convention_and_no_corner_bias():
    """Rendered ChArUco corners land where K (principal point at (W-1)/2, (H-1)/2) projects them.

    The half-pixel alternative (c = W/2) would shift every corner by 0.5 px; a
    texture mapped to texel centres instead of edges would pull corners inward.
    Neither is there: the mean error is far below either effect.
    """
    camera = CameraSpec("cam", 640, 480, fovy_deg=50.0, T_mount_cam=np.eye(4))
    errors, radial = [], []
    rng = np.random.default_rng(1)
    for k in range(4):
        tilt = np.deg2rad(rng.uniform(-30, 30, 2))
        centre = np.array([rng.uniform(-0.15, 0.15), rng.uniform(-0.1, 0.1), 0.8 + 0.1 * k])
        normal = np.array([np.sin(tilt[0]), np.sin(tilt[1]), -1.0])
        T = facing_mount(BOARD, normal, centre, up=(0.0, -1.0, 0.0))
        with world_board_scene(BOARD, T, camera) as scene:
            image = scene.render("cam")
        found, ids = charuco_corners(image, BOARD)
        expected = project(camera.K, T, BOARD.points()[ids])
        errors.append(found - expected)
        d = expected - expected.mean(0)
        radial.append(np.sum(errors[-1] * d / np.linalg.norm(d, axis=1, keepdims=True), axis=1))
        shifted = camera.K.copy()
        shifted[:2, 2] += 0.5
        assert np.abs((found - project(shifted, T, BOARD.points()[ids])).mean(0)).min() > 0.4
    e, r = np.concatenate(errors), np.concatenate(radial)
    rms = float(np.sqrt(np.mean(np.sum(e**2, axis=1))))
    print(
        f"corner RMS {rms:.3f} px, mean {e.mean(0)} px, radial mean {r.mean():+.4f} px over {len(e)} corners"
    )
    assert rms < 0.3
    assert np.all(np.abs(e.mean(0)) < 0.03)
    assert abs(r.mean()) < 0.03


def test_aruco_texture_is_not_mirrored():
    """A single marker decodes with its own id and its corners in OpenCV's order."""
    spec = TargetSpec(kind="aruco", marker_length=0.1, first_id=7, name="m")
    camera = CameraSpec("cam", 320, 240, T_mount_cam=np.eye(4))
    T = facing_mount(spec, (0.2, 0.1, -1.0), (0.02, -0.01, 0.6), up=(0.0, -1.0, 0.0))
    with world_board_scene(spec, T, camera) as scene:
        image = scene.render("cam")
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50), params)
    corners, ids, _ = detector.detectMarkers(cv2.cvtColor(image, cv2.COLOR_RGB2GRAY))
    assert ids is not None and ids.ravel().tolist() == [7]
    np.testing.assert_allclose(corners[0][0], project(camera.K, T, spec.points()), atol=0.5)


def test_pnp_of_a_charuco_plate_at_one_metre():
    """PnP of a rendered 9x7 ChArUco plate 1 m away in 640x480 frames, four view angles.

    Depth is PnP's weak direction: from ~0.1 px corner noise, a plate seen
    face-on is placed to ~1 mm along the line of sight, an oblique one to a
    fraction of that. The median over the four views is the figure.
    """
    spec = TargetSpec(squares=(9, 7), square_length=0.05, marker_length=0.037, name="board")
    camera = CameraSpec("cam", 640, 480, T_mount_cam=np.eye(4))
    trans_mm, rot_deg = [], []
    for normal in [(0.3, -0.2, -1.0), (0.0, 0.0, -1.0), (0.5, 0.3, -1.0), (-0.4, 0.1, -1.0)]:
        T = facing_mount(spec, normal, (0.05, 0.02, 1.0), up=(0.0, -1.0, 0.0))
        with world_board_scene(spec, T, camera) as scene:
            image = scene.render("cam")
        found, ids = charuco_corners(image, spec)
        assert len(ids) >= 40
        ok, rvec, tvec = cv2.solvePnP(spec.points()[ids], found, camera.K, None, flags=cv2.SOLVEPNP_IPPE)
        rvec, tvec = cv2.solvePnPRefineLM(spec.points()[ids], found, camera.K, None, rvec, tvec)
        R = cv2.Rodrigues(rvec)[0]
        trans_mm.append(1e3 * np.linalg.norm(tvec.ravel() - T[:3, 3]))
        rot_deg.append(np.rad2deg(np.arccos(np.clip((np.trace(R.T @ T[:3, :3]) - 1) / 2, -1, 1))))
    print(f"PnP at 1 m, 640x480: {np.round(trans_mm, 3)} mm, {np.round(rot_deg, 4)} deg")
    assert np.median(trans_mm) < 0.5 and max(trans_mm) < 1.5
    assert np.median(rot_deg) < 0.1 and max(rot_deg) < 0.3


def test_lens_distortion_is_applied_to_the_image():
    dist = np.array([-0.2, 0.08, 0.001, -0.0005, 0.0])
    camera = CameraSpec("cam", 640, 480, T_mount_cam=np.eye(4), distortion=tuple(dist))
    T = facing_mount(BOARD, (0.1, 0.1, -1.0), (0.18, 0.12, 0.7), up=(0.0, -1.0, 0.0))
    with world_board_scene(BOARD, T, camera) as scene:
        image = scene.render("cam")
    found, ids = charuco_corners(image, BOARD)
    rvec = cv2.Rodrigues(T[:3, :3])[0]
    expected = cv2.projectPoints(BOARD.points()[ids], rvec, T[:3, 3], camera.K, dist)[0][:, 0]
    undistorted_model = project(camera.K, T, BOARD.points()[ids])
    rms = np.sqrt(np.mean(np.sum((found - expected) ** 2, axis=1)))
    assert rms < 0.3
    assert np.sqrt(np.mean(np.sum((found - undistorted_model) ** 2, axis=1))) > 2.0  # it did distort


def _lens_corner_errors(dist, positions, *detectors):
    """Detected ChArUco corners minus the truth projected through the lens (px), the board
    at each of `positions` (camera frame, m) across a 640x480 image, one array per detector
    of `detectors` on the same renders (default: `jaxcal.vision.detect` alone)."""
    from jaxcal.vision import detect

    detectors = detectors or (detect,)
    camera = CameraSpec("cam", 640, 480, T_mount_cam=np.eye(4), distortion=tuple(dist))
    errors = [[] for _ in detectors]
    for k, centre in enumerate(positions):
        tilt = 0.25 * np.array([np.sin(k), np.cos(1.7 * k), 0.0])
        T = facing_mount(BOARD, tilt - np.array([0.0, 0.0, 1.0]), centre, up=(0.0, -1.0, 0.0))
        with world_board_scene(BOARD, T, camera) as scene:
            image = scene.render("cam")[:, :, ::-1].copy()
        rvec = cv2.Rodrigues(T[:3, :3])[0]
        for found, find in zip(errors, detectors):
            d = find(image, BOARD, K=camera.K, dist=camera.dist)
            truth = cv2.projectPoints(BOARD.points()[d.ids], rvec, T[:3, 3], camera.K, dist)[0][:, 0]
            found.append(d.pixels - truth)
    errors = [np.concatenate(e) for e in errors]
    return errors[0] if len(errors) == 1 else errors


def test_lens_distortion_warp_leaves_the_corners_unbiased():
    """The lens warp samples each pixel's area of a finer render (`jaxcal.sim.scene.SUPERSAMPLE`):
    the corners a detector finds through it scatter about the truth projected through the
    lens as they do through the ideal pinhole, with no common shift (a half-pixel slip between
    the fine and the final pixel grids would move every corner by (s - 1) / 2s px)."""
    lens = (-0.12, 0.05, 0.0, 0.0, 0.0)
    positions = [(x, y, 0.75) for x in (-0.25, -0.08, 0.08, 0.25) for y in (-0.15, 0.0, 0.15)]
    ideal = _lens_corner_errors(np.zeros(5), positions)
    lensed = _lens_corner_errors(lens, positions)
    # The mean over n corners of independent errors of std s is s / sqrt(n): 3 of those allowed.
    bound = 3.0 * np.sqrt(np.mean(ideal**2)) / np.sqrt(len(lensed))
    assert np.all(np.abs(lensed.mean(axis=0)) < bound)
    assert np.sqrt(np.mean(np.sum(lensed**2, axis=1))) < 1.2 * np.sqrt(np.mean(np.sum(ideal**2, axis=1)))


def test_a_lens_is_undistorted_before_the_corners_are_refined():
    """With the lens given, `detect` finds the corners on the image undistorted onto a pinhole
    canvas and maps them back: the refinement then sees straight edges through each corner.
    Under a strong barrel lens its errors against the truth are smaller than those of the
    same detector on the distorted image (measured: 0.074 against 0.089 px RMS)."""
    from jaxcal.vision import detect
    from jaxcal.vision._detect import _camera_key, _detect_in, _grey

    lens = np.array([-0.3, 0.1, 0.0, 0.0, 0.0])
    positions = [(x, y, 0.75) for x in (-0.25, 0.25) for y in (-0.15, 0.15)]

    def as_distorted(image, target, K, dist):
        return _detect_in(_grey(image), target, *_camera_key(K, dist))

    undistorted, distorted = _lens_corner_errors(lens, positions, detect, as_distorted)
    assert len(undistorted) == len(distorted)  # every corner still found
    rms = lambda e: np.sqrt(np.mean(np.sum(e**2, axis=1)))  # noqa: E731
    assert rms(undistorted) < 0.95 * rms(distorted) and abs(undistorted.mean(axis=0)).max() < 0.02


@pytest.mark.parametrize(
    "lens", [[-0.35, 0.1, 0.0, 0.0, -0.005], [-0.4, 0.12, 0.001, -0.002, 0.0], [-0.12, 0.05, 0, 0, 0]]
)
def test_the_undistorted_canvas_holds_every_pixel_of_the_image(lens):
    """The pinhole canvas the corners are found on is as large as the lens needs: every
    pixel of the distorted image, undistorted, lands on it (a fixed 15 % margin lost the
    periphery of the first two lenses); a mild lens gets a small canvas. The lenses bend
    monotonically out to the image's corners, so every pixel has a ray."""
    from jaxcal.vision._detect import _rectify_maps

    K = np.array([[600.0, 0.0, 401.0], [0.0, 600.0, 297.0], [0.0, 0.0, 1.0]])
    dist = np.array(lens)
    h, w = 600, 800
    map_x, map_y, K_rect = _rectify_maps(tuple(K.ravel()), tuple(dist), (h, w))
    H, W = map_x.shape
    u, v = np.meshgrid(np.linspace(0, w - 1, 41), np.linspace(0, h - 1, 31))
    pixels = np.c_[u.ravel(), v.ravel()].reshape(-1, 1, 2)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    on_canvas = cv2.undistortPointsIter(pixels, K, dist, None, K_rect, criteria).reshape(-1, 2)
    rays = np.c_[on_canvas, np.ones(len(on_canvas))] @ np.linalg.inv(K_rect).T
    again = cv2.projectPoints(rays.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, dist)[0]
    assert np.abs(again - pixels).max() < 1e-6  # converged: each pixel's ray is found
    assert on_canvas.min() >= 0.0 and np.all(on_canvas.max(axis=0) <= [W - 1, H - 1])
    # The maps invert it: the canvas point of each pixel samples that pixel.
    x, y = np.round(on_canvas).astype(int).T
    back = np.c_[map_x[y, x], map_y[y, x]]
    assert np.abs(back - pixels.reshape(-1, 2)).max() < 2.0
    if lens[0] == -0.12:
        assert W < 1.1 * w and H < 1.1 * h
    else:
        assert W > 1.4 * w and H > 1.4 * h


def test_no_backend_error_names_the_packages():
    message = str(no_backend_error(RuntimeError("no display")))
    assert "libegl1" in message and "libosmesa6" in message and "MUJOCO_GL" in message


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    config = SimConfig(
        seed=5,
        resolution=(320, 240),
        frames_per_joint=4,
        clock_offset_ms=40.0,
        drop_rate=0.25,
        encoder_noise_counts=0.0,
    )
    return config, load_dataset(simulate(config, tmp_path_factory.mktemp("sim") / "ds", progress=False))


def test_dataset_layout_truth_and_drops(dataset):
    config, ds = dataset
    truth = ds.truth
    n = len(ds.joint_names)
    total = n * config.frames_per_joint
    kept = len(ds.frames["file"])
    assert kept + len(truth["dropped_frames"]) == total and 0 < len(truth["dropped_frames"]) < total
    assert not set(truth["dropped_frames"]) & set(ds.frames["frame"].tolist())
    assert all(ds.image_path(i).is_file() for i in range(kept))
    assert [s[0] for s in ds.segments] == list(ds.joint_names)
    assert ds.clock_offset_s == pytest.approx(0.040)
    nominal = ds.load_model()
    true = model_from_json(truth["model"])
    # The true model differs from the nominal, is what truth.urdf holds, and joint 1 is the gauge.
    assert np.abs(np.asarray(true.reduction_ratio / nominal.reduction_ratio) - 1).max() > 1e-3
    from jaxcal.io.urdf import load_urdf

    again = load_urdf(ds.root / "truth.urdf")
    np.testing.assert_allclose(np.asarray(again.T_parent_joint), np.asarray(true.T_parent_joint), atol=1e-12)
    np.testing.assert_allclose(np.asarray(true.T_parent_joint[0]), np.asarray(nominal.T_parent_joint[0]))
    # Truth poses: the camera sees the plate where FK of the true model puts it.
    frame = truth["frames"][0]
    T_cam_base = np.asarray(truth["cameras"]["cam0"]["T_cam_base"])
    T_fl_plate = np.asarray(truth["targets"]["plate0"]["T_link_target"])
    T = T_cam_base @ np.asarray(forward_kinematics(true, np.asarray(frame["q"])))[-1] @ T_fl_plate
    np.testing.assert_allclose(np.asarray(frame["T_cam_target"]["plate0"]), T, atol=1e-12)


def test_clock_offset_is_in_the_timestamps_and_the_encoder_stream(dataset):
    """Encoders interpolated at (camera stamp - offset) give the true joint angles; at the raw stamp they do not."""
    _, ds = dataset
    true = model_from_json(ds.truth["model"])
    frames = ds.truth["frames"]
    stamps = ds.frames["timestamp"][[f["row"] for f in frames]]
    t_true = np.array([f["t"] for f in frames])
    np.testing.assert_allclose(stamps - t_true, 0.040, atol=1e-12)
    q_true = np.array([f["q"] for f in frames])

    def joint_error(offset):
        motor = np.stack(
            [
                np.interp(stamps - offset, ds.encoder_t, ds.encoder_motor[:, j])
                for j in range(len(ds.joint_names))
            ],
            axis=1,
        )
        return np.abs(motor / np.asarray(true.reduction_ratio) - q_true).max()

    assert joint_error(0.040) < 2e-4  # linear interpolation at 500 Hz of a fast (0.13 s) sweep
    assert joint_error(0.0) > 1e-2


def test_simulate_refuses_a_non_empty_directory_and_leaves_nothing_on_failure(tmp_path):
    out = tmp_path / "ds"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    with pytest.raises(OutputError, match="not empty"):
        simulate(SimConfig(resolution=(64, 48), frames_per_joint=2), out, progress=False)
    assert (out / "keep.txt").read_text() == "mine"
    with pytest.raises(ValueError, match="drop_rate"):
        simulate(SimConfig(drop_rate=1.5), tmp_path / "other", progress=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds"]


def test_load_dataset_errors_name_the_file(dataset, tmp_path):
    import shutil

    _, ds = dataset
    copy = tmp_path / "copy"
    shutil.copytree(ds.root, copy)
    meta = json.loads((copy / "metadata.json").read_text())
    meta["schema_version"] = 99
    (copy / "metadata.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match=r"metadata.json: unknown schema_version 99"):
        load_dataset(copy)
    meta["schema_version"] = 1
    (copy / "metadata.json").write_text(json.dumps(meta))
    lines = (copy / "encoders.csv").read_text().splitlines()
    cells = lines[5].split(",")
    lines[5] = ",".join(cells[:2] + ["nan"] + cells[3:])
    (copy / "encoders.csv").write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match=r"encoders.csv line 6 column 'shoulder_lift_joint'.*NaN"):
        load_dataset(copy)


def test_cli_simulate(tmp_path, capsys):
    from jaxcal.cli import main

    out = tmp_path / "cli"
    args = ["simulate", "--out", str(out), "--resolution", "160x120", "--frames-per-joint", "2", "--quiet"]
    assert main(args) == 0
    said = capsys.readouterr().out
    assert "12 images" in said
    # At 160x120 the plate's markers are a few pixels wide: said when rendered, and named when
    # calibrating finds none (not only the dictionary); data/ur5e_sweeps' (21 px) are not.
    small = re.search(r"markers about (\d+) px wide \(median\), under the 15 px a DICT_4X4_50", said)
    assert small and 2 <= int(small.group(1)) <= 6, said
    assert main(["calibrate", str(out), "--out", str(tmp_path / "res"), "--quiet"]) == 2
    assert (
        "whether the markers are big enough in the images: a 30 mm marker is under the 15 px"
        in capsys.readouterr().err
    )
    ds = load_dataset(ROOT / "data" / "ur5e_sweeps")
    assert small_markers(true_poses(ds.truth), ds.cameras, ds.targets) == []
    assert main(args) == 2
    assert "not empty" in capsys.readouterr().err


def test_arbitrary_trajectory_is_filmed_at_the_frame_rate(tmp_path):
    from jaxcal.sim.motion import free_motion

    q = np.zeros((3, 6))
    q[1, :3] = np.deg2rad([10.0, -8.0, 5.0])
    config = SimConfig(resolution=(160, 120), fps=15.0, encoders=False)
    ds = load_dataset(
        simulate(config, tmp_path / "free", trajectory=free_motion([0.0, 0.4, 0.8], q), progress=False)
    )
    assert ds.segments == ((None, 0.0, 0.8),) and ds.encoder_t is None
    np.testing.assert_allclose(np.diff(ds.frames["timestamp"]), 1 / 15.0, atol=1e-12)
    assert len(ds.frames["file"]) == 12
    theta = np.array([f["theta"] for f in ds.truth["frames"]])
    assert np.ptp(theta[:, 0]) > np.deg2rad(8.0) and np.ptp(theta[:, 3]) < 1e-12


def test_joint_sweeps_take_one_range_per_joint():
    from jaxcal.sim.motion import joint_sweeps

    names = ["a", "b", "c"]
    traj = joint_sweeps(names, (40.0, 40.0, 300.0))
    for j, seg in enumerate(traj.segments):
        assert seg.joint == names[j]
        # Waypoints 3j+1 and 3j+2 are the sweep's ends; the other joints stay at zero.
        lo, hi = traj.q[3 * j + 1], traj.q[3 * j + 2]
        np.testing.assert_allclose(np.degrees(hi[j] - lo[j]), (40.0, 40.0, 300.0)[j])
        assert np.all(np.delete(lo, j) == 0) and np.all(np.delete(hi, j) == 0)
    np.testing.assert_allclose(joint_sweeps(names, 40.0).q, joint_sweeps(names, (40.0,) * 3).q)
    with pytest.raises(ValueError, match="2 angles for 3 joints"):
        joint_sweeps(names, (40.0, 40.0))
