"""Rendered hand-eye data: a UR5e carries a ChArUco plate in front of a fixed camera (eye-to-hand).

Impure (MuJoCo, OpenCV); never jitted. `render_eye_to_hand` moves the wrist
through random poses about the zero configuration, renders the camera,
detects the ChArUco corners with `cv2.aruco.CharucoDetector` and estimates
each board pose with `cv2.solvePnP`, so the same frames feed jaxcal's
image-feature solver (the corners) and OpenCV's pose-pair solvers (the PnP
poses). Used by `benchmarks/handeye.py` and the tests.
"""

import cv2
import numpy as np

from .._kinematics import forward_kinematics
from ..markers import TargetSpec
from ..robots import load_robot
from .scene import CameraSpec, PlateSpec, build_scene
from .simulate import facing_mount, look_at


def _pose(rotvec, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(rotvec, np.float64))[0]
    T[:3, 3] = np.asarray(t, np.float64).ravel()
    return T


def render_eye_to_hand(
    frames: int,
    seed: int = 0,
    *,
    resolution: tuple[int, int] = (640, 480),
    fovy_deg: float = 50.0,
    distance: float = 0.6,
    min_corners: int = 6,
) -> dict:
    """Render `frames` views of a 5x4 ChArUco plate (4 cm squares) on a UR5e's flange.

    The camera looks at the plate from `distance` (m) at the zero
    configuration; every frame adds uniform joint offsets (6 deg on the first
    three joints, 20-25 deg on the wrist) and is kept when the plate faces the
    camera within 60 deg and at least `min_corners` corners are detected.

    **Returns:** a dict of NumPy arrays: `T_base_ee` `(frames, 4, 4)` (exact),
    `pixels` `(frames, 12, 2)` (px, NaN where undetected), `mask`,
    `T_cam_board` (PnP), `K`, `points` (board frame, m), and the truth
    `T_base_cam`, `T_ee_board`; `tries` = frames rendered.
    """
    rng = np.random.default_rng(seed)
    model = load_robot("ur5e")
    n = model.num_joints
    q0 = np.zeros(n)
    F0 = np.asarray(forward_kinematics(model, q0))
    spec = TargetSpec(squares=(5, 4), square_length=0.04, marker_length=0.03, name="plate")
    up = F0[-1][:3, :3].T @ np.array([0.0, 0.0, 1.0])
    T_flange_board = facing_mount(spec, (0.0, 0.0, 1.0), (0.0, 0.0, 0.012), up=up)
    T_base_board0 = F0[-1] @ T_flange_board
    normal = T_base_board0[:3, :3] @ spec.front_normal()
    centre = T_base_board0[:3, :3] @ spec.points().mean(0) + T_base_board0[:3, 3]
    d = normal + np.array([0.0, 0.0, 0.3])
    T_base_cam = look_at(centre + distance * d / np.linalg.norm(d), centre)
    cam = CameraSpec("cam0", *resolution, fovy_deg, T_base_cam, "world")
    scene = build_scene(model, plates=[PlateSpec(spec, model.link_names[-1], T_flange_board)], cameras=[cam])
    detector = cv2.aruco.CharucoDetector(spec.board())
    points = spec.points()
    T_base_ee, corners, mask, T_cam_board = [], [], [], []
    spread = np.radians([6.0, 6.0, 6.0, 20.0, 20.0, 25.0])
    tries = 0
    try:
        while len(T_base_ee) < frames and tries < 20 * frames:
            tries += 1
            q = q0 + rng.uniform(-1.0, 1.0, n) * spread
            scene.set_angles(q)
            T_be = scene.body_pose(model.link_names[-1])
            A = np.linalg.inv(T_base_cam) @ T_be @ T_flange_board
            P = points @ A[:3, :3].T + A[:3, 3]
            facing = -(A[:3, :3] @ spec.front_normal()) @ (P.mean(0) / np.linalg.norm(P.mean(0)))
            if facing < np.cos(np.radians(60.0)):
                continue
            gray = cv2.cvtColor(scene.render("cam0"), cv2.COLOR_RGB2GRAY)
            ch_corners, ch_ids, _, _ = detector.detectBoard(gray)
            if ch_ids is None or len(ch_ids) < min_corners:
                continue
            ids = ch_ids.ravel()
            uv = np.full((len(points), 2), np.nan)
            uv[ids] = ch_corners.reshape(-1, 2)
            ok, rvec, tvec = cv2.solvePnP(points[ids], ch_corners.reshape(-1, 2), cam.K, None)
            if not ok:
                continue
            T_base_ee.append(T_be)
            corners.append(uv)
            mask.append(np.isfinite(uv[:, 0]))
            T_cam_board.append(_pose(rvec.ravel(), tvec))
    finally:
        scene.close()
    return dict(
        T_base_ee=np.stack(T_base_ee),
        pixels=np.stack(corners),
        mask=np.stack(mask),
        T_cam_board=np.stack(T_cam_board),
        K=cam.K,
        points=points,
        T_base_cam=T_base_cam,
        T_ee_board=T_flange_board,
        tries=tries,
    )
