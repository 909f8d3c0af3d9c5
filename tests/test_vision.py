"""The vision front end: corners, PnP and its covariance, ArUco, files, pools, intrinsics."""

import cv2
import numpy as np
import pytest

from jaxcal.markers import TargetSpec
from jaxcal.robots import load_robot
from jaxcal.sim import CameraSpec, PlateSpec, build_scene
from jaxcal.sim.simulate import facing_mount
from jaxcal.vision import (
    Detection,
    VisionError,
    calibrate_intrinsics,
    detect,
    detect_frames,
    estimate_pose,
    pose_jacobian,
)

pytestmark = pytest.mark.slow

BOARD = TargetSpec(squares=(9, 7), square_length=0.05, marker_length=0.037, name="board")
MARKER = TargetSpec(kind="aruco", marker_length=0.1, first_id=40, name="marker")  # not on BOARD (ids 0..30)
CAMERA = CameraSpec("cam", 640, 480, T_mount_cam=np.eye(4), distortion=(-0.1, 0.04, 0.0005, -0.0003, 0.0))
# The board 1 m away, seen from four directions (face-on and oblique).
NORMALS = [(0.3, -0.2, -1.0), (0.0, 0.0, -1.0), (0.5, 0.3, -1.0), (-0.4, 0.1, -1.0)]


def render(spec: TargetSpec, T_cam_target: np.ndarray, camera: CameraSpec = CAMERA) -> np.ndarray:
    """A BGR image of `spec` fixed in the world at `T_cam_target` (the arm stands behind the camera)."""
    T_world_base = np.eye(4)
    T_world_base[2, 3] = -3.0
    plates = [PlateSpec(spec, "world", T_cam_target)]
    with build_scene(load_robot("ur5e"), plates=plates, cameras=[camera], T_world_base=T_world_base) as scene:
        return cv2.cvtColor(scene.render(camera.name), cv2.COLOR_RGB2BGR)


def project(spec: TargetSpec, T_cam_target, ids, K=CAMERA.K, dist=CAMERA.dist) -> np.ndarray:
    rvec = cv2.Rodrigues(T_cam_target[:3, :3])[0]
    return cv2.projectPoints(spec.points()[ids], rvec, T_cam_target[:3, 3], K, dist)[0].reshape(-1, 2)


def pose_error(estimate: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """Translation (mm) and rotation (deg) between two poses."""
    R = estimate[:3, :3].T @ truth[:3, :3]
    angle = np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))
    return 1e3 * float(np.linalg.norm(estimate[:3, 3] - truth[:3, 3])), float(np.rad2deg(angle))


@pytest.fixture(scope="module")
def board_views():
    poses = [facing_mount(BOARD, n, (0.05, 0.02, 1.0), up=(0.0, -1.0, 0.0)) for n in NORMALS]
    return [(T, render(BOARD, T)) for T in poses]


@pytest.fixture(scope="module")
def marker_view():
    T = facing_mount(MARKER, (0.2, 0.1, -1.0), (0.02, -0.01, 0.6), up=(0.0, -1.0, 0.0))
    return T, render(MARKER, T)


def test_charuco_corners_agree_with_the_projected_truth(board_views):
    errors = []
    for T, image in board_views:
        for K, dist in [(None, None), (CAMERA.K, CAMERA.dist)]:
            det = detect(image, BOARD, K=K, dist=dist)
            assert det is not None and len(det) >= 40
            assert det.pixels.dtype == np.float64 and np.all(np.diff(det.ids) > 0)
            errors.append(det.pixels - project(BOARD, T, det.ids))
        grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        assert detect(grey, BOARD, K=CAMERA.K, dist=CAMERA.dist) == det  # grey == BGR, same K
    e = np.concatenate(errors)
    rms = float(np.sqrt(np.mean(np.sum(e**2, axis=1))))
    print(f"ChArUco corner RMS {rms:.3f} px, mean {np.round(e.mean(0), 4)} px over {len(e)} corners")
    assert rms < 0.3
    assert np.all(np.abs(e.mean(0)) < 0.05)


def test_pnp_pose_at_one_metre(board_views):
    """Depth is PnP's weak direction; the median over the four views is the figure (as in test_sim)."""
    trans_mm, rot_deg = [], []
    for T, image in board_views:
        det = detect(image, BOARD, K=CAMERA.K, dist=CAMERA.dist)
        pose = estimate_pose(det, BOARD, CAMERA.K, CAMERA.dist)
        assert pose.n_points == len(det) and pose.rms_px < 0.3
        dt, dr = pose_error(pose.T_cam_target, T)
        trans_mm.append(dt)
        rot_deg.append(dr)
        # The truth lies within the stated uncertainty (a loose 5-sigma check).
        assert dt < 5e3 * np.sqrt(np.trace(pose.cov[:3, :3]))
    print(f"PnP at 1 m: {np.round(trans_mm, 3)} mm, {np.round(rot_deg, 4)} deg")
    assert np.median(trans_mm) < 0.5 and max(trans_mm) < 1.5
    assert np.median(rot_deg) < 0.1 and max(rot_deg) < 0.3


def test_pose_jacobian_equals_finite_differences():
    """Columns (p, w): p moves the origin, w rotates on the left, O' = exp([w]x) O."""
    T = facing_mount(BOARD, NORMALS[2], (0.05, 0.02, 1.0), up=(0.0, -1.0, 0.0))
    ids = np.arange(0, BOARD.num_points, 5)
    points = BOARD.points()[ids]
    _, J = pose_jacobian(points, T, CAMERA.K, CAMERA.dist)
    h = 1e-6
    for k in range(6):
        cols = []
        for sign in (1.0, -1.0):
            Tk = T.copy()
            if k < 3:
                Tk[k, 3] += sign * h
            else:
                w = np.zeros(3)
                w[k - 3] = sign * h
                Tk[:3, :3] = cv2.Rodrigues(w)[0] @ T[:3, :3]
            cols.append(project(BOARD, Tk, ids).ravel())
        np.testing.assert_allclose(J[:, k], (cols[0] - cols[1]) / (2 * h), rtol=1e-5, atol=1e-3)


def test_pose_covariance_is_honest():
    """Seeded Monte Carlo: pixel noise on projected truth; whitened pose errors have unit RMS."""
    rng = np.random.default_rng(0)
    sigma = 0.3
    T = facing_mount(BOARD, NORMALS[0], (0.05, 0.02, 1.0), up=(0.0, -1.0, 0.0))
    ids = np.arange(BOARD.num_points)
    clean = project(BOARD, T, ids)
    z = {"given": ([], []), "estimated": ([], [])}
    for _ in range(300):
        det = Detection(ids, clean + sigma * rng.standard_normal(clean.shape))
        for key, s in [("given", sigma), ("estimated", None)]:
            pose = estimate_pose(det, BOARD, CAMERA.K, CAMERA.dist, sigma_px=s)
            e_p = T[:3, 3] - pose.T_cam_target[:3, 3]
            e_w = cv2.Rodrigues(T[:3, :3] @ pose.T_cam_target[:3, :3].T)[0].ravel()
            for e, block, out in [(e_p, slice(0, 3), z[key][0]), (e_w, slice(3, 6), z[key][1])]:
                out.append(np.linalg.solve(np.linalg.cholesky(pose.cov[block, block]), e))
    for key, (zp, zw) in z.items():
        rms_p, rms_w = np.sqrt(np.mean(np.square(zp))), np.sqrt(np.mean(np.square(zw)))
        print(f"sigma {key}: whitened error RMS p {rms_p:.3f}, w {rms_w:.3f}")
        assert 0.8 < rms_p < 1.25 and 0.8 < rms_w < 1.25


def test_inverse_pose_covariance_is_honest():
    """Eye-in-hand data use the camera's pose in the board frame: the inverted
    PnP pose, whose (p, w) covariance must whiten the inverted errors (jointly)."""
    rng = np.random.default_rng(1)
    T = facing_mount(BOARD, NORMALS[2], (0.05, 0.02, 1.0), up=(0.0, -1.0, 0.0))
    Ti = np.linalg.inv(T)
    ids = np.arange(BOARD.num_points)
    clean = project(BOARD, T, ids)
    z = []
    for _ in range(300):
        pose = estimate_pose(
            Detection(ids, clean + 0.3 * rng.standard_normal(clean.shape)),
            BOARD,
            CAMERA.K,
            CAMERA.dist,
            sigma_px=0.3,
        )
        inv = pose.inverse()
        np.testing.assert_allclose(inv.T_cam_target @ pose.T_cam_target, np.eye(4), atol=1e-12)
        e = np.r_[
            Ti[:3, 3] - inv.T_cam_target[:3, 3],
            cv2.Rodrigues(Ti[:3, :3] @ inv.T_cam_target[:3, :3].T)[0].ravel(),
        ]
        z.append(np.linalg.solve(np.linalg.cholesky(inv.cov), e))
    rms = np.sqrt(np.mean(np.square(z), axis=0))
    print("whitened inverse-pose error RMS per component", np.round(rms, 3))
    # Without the cross term -O^T [P]x w, the position block (~1 m lever arm) is far too small.
    assert np.all((rms > 0.8) & (rms < 1.25))


def test_single_aruco_marker(marker_view):
    T, image = marker_view
    det = detect(image, MARKER, K=CAMERA.K, dist=CAMERA.dist)
    assert det is not None and det.ids.tolist() == [0, 1, 2, 3]  # rows of MARKER.points()
    rms = np.sqrt(np.mean(np.sum((det.pixels - project(MARKER, T, det.ids)) ** 2, axis=1)))
    pose = estimate_pose(det, MARKER, CAMERA.K, CAMERA.dist)
    dt, dr = pose_error(pose.T_cam_target, T)
    print(f"ArUco corner RMS {rms:.3f} px; pose {dt:.2f} mm, {dr:.3f} deg at 0.6 m")
    assert rms < 0.3
    assert dt < 3.0 and dr < 0.5
    assert pose.n_points == 4 and pose.sigma_px >= 0.05


def test_wrong_dictionary_or_id_is_not_found(board_views, marker_view):
    _, image = board_views[0]
    assert detect(image, TargetSpec(squares=(9, 7), dictionary="DICT_6X6_50", name="b6")) is None
    assert detect(marker_view[1], TargetSpec(kind="aruco", marker_length=0.1, first_id=41)) is None
    assert detect(marker_view[1], BOARD) is None
    too_few = Detection(np.arange(3), np.zeros((3, 2)))
    assert estimate_pose(too_few, BOARD, CAMERA.K, None) is None


def test_detect_frames_names_a_missing_or_corrupt_file(tmp_path, board_views):
    good = tmp_path / "good.png"
    cv2.imwrite(str(good), board_views[0][1])
    missing = tmp_path / "missing.png"
    with pytest.raises(VisionError, match=r"missing\.png: image file missing"):
        detect_frames([good, missing], [BOARD], progress=False)
    corrupt = tmp_path / "corrupt.png"
    corrupt.write_text("not an image")
    with pytest.raises(VisionError, match=r"corrupt\.png: not a readable image"):
        detect_frames([good, corrupt], [BOARD], progress=False)


def test_process_pool_equals_in_process(tmp_path, board_views, marker_view):
    images = [image for _, image in board_views] + [marker_view[1]]
    paths = []
    for k in range(10):  # 10 files, in an order that a pool could scramble
        paths.append(tmp_path / f"{k:02d}.png")
        cv2.imwrite(str(paths[-1]), images[(3 * k) % len(images)])
    targets = [BOARD, MARKER]
    here = detect_frames(paths, targets, K=CAMERA.K, dist=CAMERA.dist, workers=1, progress=False)
    assert [sorted(d) for d in here[:5]] == [["board"], ["board"], ["board"], ["marker"], ["board"]]
    pooled = detect_frames(paths, targets, K=CAMERA.K, dist=CAMERA.dist, workers=2, pool="process")
    threads = detect_frames(paths, targets, K=CAMERA.K, dist=CAMERA.dist, workers=2, progress=False)
    assert pooled == here and threads == here


def synthetic_views(K, dist, rng, n_views=8, *, tilt_deg=35.0):
    """Projected board corners (0.1 px noise) in `n_views` poses, tilted up to `tilt_deg`."""
    detections = []
    for _ in range(n_views):
        t = np.deg2rad(tilt_deg)
        normal = (rng.uniform(-t, t), rng.uniform(-t, t), -1.0)
        centre = (rng.uniform(-0.1, 0.1), rng.uniform(-0.08, 0.08), rng.uniform(0.8, 1.2))
        T = facing_mount(BOARD, normal, centre, up=(0.0, -1.0, 0.0))
        ids = np.arange(BOARD.num_points)
        pixels = project(BOARD, T, ids, K, dist) + 0.1 * rng.standard_normal((len(ids), 2))
        detections.append(Detection(ids, pixels))
    return detections


def test_calibrate_intrinsics_recovers_the_camera():
    rng = np.random.default_rng(3)
    K = np.array([[610.0, 0.0, 322.0], [0.0, 606.0, 236.0], [0.0, 0.0, 1.0]])
    dist = np.array([-0.12, 0.05, 0.0004, -0.0002, 0.0])
    K_hat, dist_hat, rms = calibrate_intrinsics(synthetic_views(K, dist, rng), BOARD, (640, 480))
    print(
        f"fx, fy, cx, cy error: {np.round(K_hat[[0, 1, 0, 1], [0, 1, 2, 2]] - K[[0, 1, 0, 1], [0, 1, 2, 2]], 3)}"
    )
    assert 0.05 < rms < 0.2  # the 0.1 px noise, per point
    np.testing.assert_allclose(np.diag(K_hat)[:2], np.diag(K)[:2], rtol=5e-3)  # fx, fy within 0.5 %
    np.testing.assert_allclose(K_hat[:2, 2], K[:2, 2], atol=2.0)  # cx, cy within 2 px
    assert abs(dist_hat[0] - dist[0]) < 0.03  # k1 (k2, k3 trade off against each other)


def test_calibrate_intrinsics_refuses_bad_input():
    rng = np.random.default_rng(4)
    K = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
    views = synthetic_views(K, None, rng)
    with pytest.raises(VisionError, match="'marker'.*ChArUco"):
        calibrate_intrinsics(views, MARKER, (640, 480))
    with pytest.raises(VisionError, match="2 usable views"):
        calibrate_intrinsics(views[:2], BOARD, (640, 480))
    flat = synthetic_views(K, None, rng, tilt_deg=0.0)
    with pytest.raises(VisionError, match="'board': the board's orientation varies by only"):
        calibrate_intrinsics(flat, BOARD, (640, 480))
    few_corners = [Detection(v.ids[:5], v.pixels[:5]) for v in views]
    with pytest.raises(VisionError, match="0 usable views"):
        calibrate_intrinsics(few_corners, BOARD, (640, 480))
