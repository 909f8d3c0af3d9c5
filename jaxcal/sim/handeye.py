"""Rendered hand-eye data: arrays for the benchmark, and captures on disk for `jaxcal handeye`.

Impure (MuJoCo, OpenCV); never jitted. `simulate_hand_eye` writes a capture
(`jaxcal.io.handeye`'s format) of any target kind, eye-in-hand or
eye-to-hand, the flange a free body at random wrist poses around a look-at
point (no arm: only the camera and the target are in view). `render_eye_to_hand` moves the wrist
through random poses about the zero configuration, renders the camera,
detects the ChArUco corners with `cv2.aruco.CharucoDetector` and estimates
each board pose with `cv2.solvePnP`, so the same frames feed jaxcal's
image-feature solver (the corners) and OpenCV's pose-pair solvers (the PnP
poses). Used by `benchmarks/handeye.py` and the tests.
"""

import json
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import cv2
import mujoco  # noqa: E402  (after .scene, which selects the GL backend)
import numpy as np

from .._kinematics import forward_kinematics
from ..io._files import atomic_directory
from ..io.handeye import HandEyeCamera, write_hand_eye_description
from ..markers import TargetSpec
from ..robots import load_robot
from .drift import twist_matrix
from .motion import check_finite
from .scene import CameraSpec, PlateSpec, Scene, add_plate, build_scene
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


# --------------------------------------------------------------------------- captures on disk


@dataclass(frozen=True)
class HandEyeSimConfig:
    """A rendered hand-eye capture (see `simulate_hand_eye`).

    - `target`: what is printed on the plate.
    - `eye_in_hand`: camera on the flange and the target on the table; else the
      camera fixed and the target on the flange.
    - `frames`, `resolution` (W, H px), `fovy_deg`, `distortion` (OpenCV k1 k2 p1 p2 k3).
    - `distance` (m): camera to target centre; each view varies it by +-15 %.
    - `tilt_deg`: the view direction turns up to this far from the target's
      normal (at least 8 deg); `roll_deg`: the camera (eye-in-hand) or target
      (eye-to-hand) turns up to this far about the line of sight.
    - `pose_format`, `translation_unit`, `rotation_unit`: how `poses.csv` is written.
    - `robot_error_fraction`: this share of the frames gets its recorded robot
      pose off by `robot_error_deg` (about a random axis) and `robot_error_mm`
      (in a random direction), in the flange frame; the truth lists them.
    - `robot_noise_mm`, `robot_noise_deg`: every recorded robot pose is off by
      Gaussian noise of this standard deviation per axis, in the base frame
      (translation $t + v$, rotation $\\exp(w) R$, the convention of the
      solver's robot corrections): a real robot's pose error.
    - `intrinsics_known`: write K and the distortion (else `null`: self-calibrated).
    - `camera_move`: `(v (m), omega (rad))`, the camera moved by this twist in its own
      frame after the views were placed (a check capture of a moved camera, `jaxcal check`):
      eye-in-hand $T_{ee,cam} \\exp(\\varepsilon)$, eye-to-hand $T_{base,cam} \\exp(\\varepsilon)$.
    """

    target: TargetSpec = field(
        default_factory=lambda: TargetSpec("chessboard", squares=(8, 7), square_length=0.025, name="board")
    )
    eye_in_hand: bool = True
    frames: int = 16
    seed: int = 0
    resolution: tuple[int, int] = (640, 480)
    fovy_deg: float = 50.0
    distortion: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)
    distance: float = 0.5
    tilt_deg: float = 35.0
    roll_deg: float = 90.0
    pose_format: str = "xyz_quat"
    translation_unit: str = "m"
    rotation_unit: str = "rad"
    robot_error_fraction: float = 0.0
    robot_error_deg: float = 2.0
    robot_error_mm: float = 5.0
    robot_noise_mm: float = 0.0
    robot_noise_deg: float = 0.0
    intrinsics_known: bool = True
    camera_move: tuple = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))


#: Ground truth of the simulated rigs (flange frame / base frame, m, rad).
T_EE_CAM = _pose([0.08, -0.12, 1.55], [0.045, -0.03, 0.07])
BOARD_CENTRE_EYE_IN_HAND = np.array([0.6, 0.05, 0.02])
BOARD_CENTRE_EYE_TO_HAND = np.array([0.6, 0.0, 0.2])
#: Eye-to-hand: the fixed camera looks at the target's mean position from this direction.
CAMERA_DIRECTION_EYE_TO_HAND = np.array([-0.05, -0.8, 0.6]) / np.linalg.norm([-0.05, -0.8, 0.6])


def _turn(axis, angle) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(axis, np.float64) / np.linalg.norm(axis) * angle)[0]


def _turn_by(rotvec) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(rotvec, np.float64))[0]


def _tilted(n: np.ndarray, rng, tilt_deg: float) -> np.ndarray:
    """`n` turned by 8 deg to `tilt_deg` about a random axis perpendicular to it."""
    a = rng.normal(size=3)
    a -= (a @ n) * n
    angle = np.radians(rng.uniform(min(8.0, tilt_deg), tilt_deg))
    return _turn(a, angle) @ n


def _in_view(points_base, T_base_cam, K, size, margin: float = 12.0) -> bool:
    T = np.linalg.inv(T_base_cam)
    p = points_base @ T[:3, :3].T + T[:3, 3]
    if np.any(p[:, 2] <= 0.05):
        return False
    uv = p[:, :2] / p[:, 2:] @ K[:2, :2].T + K[:2, 2]
    return bool(np.all((uv >= margin) & (uv <= np.asarray(size) - 1 - margin)))


def _unplaced(config: HandEyeSimConfig) -> str:
    w, h = config.resolution
    return (
        f"simulate_hand_eye: the whole target never fits a {w}x{h} image from {config.distance:g} m "
        f"(tilt up to {config.tilt_deg:g} deg, a {config.fovy_deg:g} deg field of view): raise the distance "
        "or the resolution, or lower the tilt"
    )


def _views(config: HandEyeSimConfig, rng, K, T_ee_board, T_base_board):
    """True flange poses `(frames, 4, 4)` and the fixed camera pose (eye-to-hand) or None."""
    spec = config.target
    outline = spec.image()[1]  # the plate's outer corners: the whole plate must be in view
    size = config.resolution
    poses, tries = [], 0
    if config.eye_in_hand:
        c0 = T_base_board[:3, :3] @ spec.points().mean(0) + T_base_board[:3, 3]
        n0 = T_base_board[:3, :3] @ spec.front_normal()  # from the board toward its viewer
        while len(poses) < config.frames:
            tries += 1
            if tries > 200 * config.frames:
                raise ValueError(_unplaced(config))
            look = c0 + np.append(rng.uniform(-0.03, 0.03, 2), 0.0)
            eye = look + config.distance * rng.uniform(0.85, 1.15) * _tilted(n0, rng, config.tilt_deg)
            up = _turn(look - eye, np.radians(rng.uniform(-config.roll_deg, config.roll_deg))) @ [
                0.0,
                1.0,
                0.0,
            ]
            T_base_cam = look_at(eye, look, up=up)
            corners = outline @ T_base_board[:3, :3].T + T_base_board[:3, 3]
            if _in_view(corners, T_base_cam, K, size):
                poses.append(T_base_cam @ np.linalg.inv(T_EE_CAM))
        return np.stack(poses), None
    camera = BOARD_CENTRE_EYE_TO_HAND + config.distance * CAMERA_DIRECTION_EYE_TO_HAND
    T_base_cam = look_at(camera, BOARD_CENTRE_EYE_TO_HAND)
    while len(poses) < config.frames:
        tries += 1
        if tries > 200 * config.frames:
            raise ValueError(_unplaced(config))
        centre = BOARD_CENTRE_EYE_TO_HAND + rng.uniform(-0.1, 0.1, 3) * config.distance
        to_cam = camera - centre
        n = _tilted(to_cam / np.linalg.norm(to_cam), rng, config.tilt_deg)
        up = _turn(n, np.radians(rng.uniform(-config.roll_deg, config.roll_deg))) @ [0.0, 0.0, 1.0]
        T_base_board = facing_mount(spec, n, centre, up=up)
        corners = outline @ T_base_board[:3, :3].T + T_base_board[:3, 3]
        if _in_view(corners, T_base_cam, K, size):
            poses.append(T_base_board @ np.linalg.inv(T_ee_board))
    return np.stack(poses), T_base_cam


def _perturb(T, rng, deg: float, mm: float) -> np.ndarray:
    a = rng.normal(size=3)
    d = rng.normal(size=3)
    return T @ _pose(np.radians(deg) * a / np.linalg.norm(a), 1e-3 * mm * d / np.linalg.norm(d))


#: Pixels between a target's features (squares; a marker kind's markers) at `distance`, below
#: which the image is rendered finer and averaged (`CameraSpec.pixel_supersample`, up to 4
#: times): a sensor integrates each pixel's light, MuJoCo samples the texture at its centre, and
#: a chessboard drawn that way at 9-13 px per square lies larger than it is (docs/handeye.md, "The
#: simulator's pixels").
MIN_FEATURE_PX = 48.0


def pixel_supersample(K: np.ndarray, target: TargetSpec, distance: float) -> int:
    """How many times finer to render a view of `target` from `distance` (m) through `K`."""
    feature = target.marker_length if target.kind in ("aruco", "aruco_grid") else target.square_length
    side = float(K[1, 1]) * feature / distance
    return int(np.clip(np.ceil(MIN_FEATURE_PX / side), 1, 4))


def simulate_hand_eye(config: HandEyeSimConfig, out, *, overwrite: bool = False) -> Path:
    """Render a hand-eye capture with MuJoCo and write it in the capture format (`jaxcal.io.handeye`).

    The flange is a free (mocap) body posed at random wrist poses around a
    look-at point: eye-in-hand, the camera on the flange views a target on
    the table from `distance`, the view direction tilted by up to `tilt_deg`
    from the target's normal and rolled by up to `roll_deg`; eye-to-hand, a
    fixed camera views the target carried on the flange, the target moved by
    up to a tenth of `distance` along each axis and turned likewise. Every view keeps the whole plate in the
    image. `truth.json` holds the true transforms and robot poses.

    **Returns:** the capture directory.
    """
    check_finite(config, "HandEyeSimConfig")
    rng = np.random.default_rng(config.seed)
    spec = config.target
    width, height = config.resolution
    T_ee_board = facing_mount(spec, (0.0, 0.0, 1.0), (0.0, 0.0, 0.03), up=(1.0, 0.0, 0.0))
    T_base_board = facing_mount(spec, (0.0, 0.0, 1.0), BOARD_CENTRE_EYE_IN_HAND, up=(1.0, 0.0, 0.0))
    if not (np.isfinite(config.distance) and config.distance > 0):
        raise ValueError(
            f"simulate_hand_eye: distance must be a number of metres above zero, got {config.distance}"
        )
    probe = CameraSpec("cam0", width, height, config.fovy_deg, np.eye(4), "world", tuple(config.distortion))
    T_true, T_base_cam = _views(config, rng, probe.K, T_ee_board, T_base_board)
    move = twist_matrix(*config.camera_move)
    T_ee_cam = T_EE_CAM @ move
    if T_base_cam is not None:
        T_base_cam = T_base_cam @ move
    T_mount_cam, mount = (T_ee_cam, "flange") if config.eye_in_hand else (T_base_cam, "world")
    cam = replace(probe, T_mount_cam=T_mount_cam, mount=mount)
    cam = replace(cam, pixel_supersample=pixel_supersample(cam.K, spec, config.distance))
    plate = (
        PlateSpec(spec, "world", T_base_board)
        if config.eye_in_hand
        else PlateSpec(spec, "flange", T_ee_board)
    )
    T_recorded, bad = _recorded(config, rng, T_true)
    names = [f"{i:04d}" for i in range(config.frames)]
    scene = _mocap_scene(plate, cam)
    with atomic_directory(out, overwrite=overwrite, kind="dataset") as tmp:
        (tmp / "images" / cam.name).mkdir(parents=True)
        try:
            for name, T in zip(names, T_true):
                scene.set_flange(T)
                image = scene.render(cam.name)
                cv2.imwrite(
                    str(tmp / "images" / cam.name / f"{name}.png"), cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
                )
        finally:
            scene.close()
        write_hand_eye_description(
            tmp,
            eye_in_hand=config.eye_in_hand,
            cameras=[
                HandEyeCamera(
                    cam.name,
                    width,
                    height,
                    cam.K if config.intrinsics_known else None,
                    cam.dist,
                    f"{cam.name}_optical_frame",
                )
            ],
            target=spec,
            frames=names,
            T_base_ee=T_recorded,
            pose_format=config.pose_format,
            translation_unit=config.translation_unit,
            rotation_unit=config.rotation_unit,
            description=f"rendered by jaxcal simulate-handeye (seed {config.seed})",
        )
        truth = {
            "arrangement": "eye_in_hand" if config.eye_in_hand else "eye_to_hand",
            "T_robot_cam": {cam.name: (T_ee_cam if config.eye_in_hand else T_base_cam).tolist()},
            "T_robot_board": (T_base_board if config.eye_in_hand else T_ee_board).tolist(),
            "K": {cam.name: cam.K.tolist()},
            "T_base_ee": T_true.tolist(),
            "corrupted_frames": [names[f] for f in bad],
            "robot_error": {"deg": config.robot_error_deg, "mm": config.robot_error_mm},
            "robot_noise": {"deg": config.robot_noise_deg, "mm": config.robot_noise_mm},
            "config": {k: v for k, v in asdict(config).items() if k != "target"},
        }
        (tmp / "truth.json").write_text(
            json.dumps(truth, indent=1, default=lambda a: np.asarray(a).tolist()) + "\n"
        )
    return Path(out)


def _recorded(config: HandEyeSimConfig, rng, T_true: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The robot poses as logged: `robot_error_fraction` of them off by the `robot_error_*`, then
    every one with the `robot_noise_*`. **Returns:** `(T_recorded, the frames logged wrong)`."""
    n_bad = int(round(config.robot_error_fraction * config.frames))
    bad = np.sort(rng.choice(config.frames, n_bad, replace=False)) if n_bad else np.zeros(0, int)
    T_recorded = T_true.copy()
    for f in bad:
        T_recorded[f] = _perturb(T_true[f], rng, config.robot_error_deg, config.robot_error_mm)
    if config.robot_noise_mm > 0 or config.robot_noise_deg > 0:
        for T in T_recorded:
            T[:3, :3] = _turn_by(rng.normal(0.0, np.radians(config.robot_noise_deg), 3)) @ T[:3, :3]
            T[:3, 3] += rng.normal(0.0, 1e-3 * config.robot_noise_mm, 3)
    return T_recorded, bad


class _MocapScene(Scene):
    """A `Scene` whose flange is a mocap body posed directly (no arm)."""

    def set_flange(self, T_base_ee) -> None:
        T = np.asarray(T_base_ee, np.float64)
        self.data.mocap_pos[0] = T[:3, 3]
        q = np.zeros(4)
        mujoco.mju_mat2Quat(q, np.ascontiguousarray(T[:3, :3]).ravel())
        self.data.mocap_quat[0] = q
        mujoco.mj_kinematics(self.model, self.data)
        mujoco.mj_camlight(self.model, self.data)


def _mocap_scene(plate: PlateSpec, cam: CameraSpec) -> _MocapScene:
    spec = mujoco.MjSpec()
    spec.modelname = "jaxcal_handeye"
    spec.visual.global_.offwidth = cam.supersample * cam.width
    spec.visual.global_.offheight = cam.supersample * cam.height
    spec.visual.headlight.ambient = [0.45, 0.45, 0.45]
    spec.visual.headlight.diffuse = [0.5, 0.5, 0.5]
    spec.visual.quality.shadowsize = 0
    spec.add_texture(
        name="sky",
        type=mujoco.mjtTexture.mjTEXTURE_SKYBOX,
        builtin=mujoco.mjtBuiltin.mjBUILTIN_GRADIENT,
        rgb1=[0.75, 0.82, 0.9],
        rgb2=[0.25, 0.3, 0.38],
        width=256,
        height=256,
    )
    world = spec.worldbody
    world.add_light(pos=[0.0, 0.0, 3.0], dir=[0.0, 0.0, -1.0], diffuse=[0.5, 0.5, 0.5], castshadow=False)
    world.add_geom(  # a grey table under the eye-in-hand target
        type=mujoco.mjtGeom.mjGEOM_PLANE,
        pos=[0.0, 0.0, 0.0],
        size=[3.0, 3.0, 0.1],
        rgba=[0.5, 0.52, 0.55, 1.0],
        contype=0,
        conaffinity=0,
    )
    flange = world.add_body(name="flange", mocap=True)
    flange.add_geom(
        type=mujoco.mjtGeom.mjGEOM_CYLINDER,
        fromto=[0.0, 0.0, -0.02, 0.0, 0.0, 0.0],
        size=[0.035, 0.0, 0.0],
        rgba=[0.3, 0.3, 0.3, 1.0],
        contype=0,
        conaffinity=0,
    )
    bodies = {"world": world, "flange": flange}
    add_plate(spec, bodies[plate.link], plate, 0)
    T = np.asarray(cam.T_mount_cam, np.float64)
    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(T[:3, :3] @ np.diag([1.0, -1.0, -1.0])).ravel())
    bodies[cam.mount].add_camera(name=cam.name, pos=T[:3, 3], quat=q, fovy=float(cam.fovy_deg))
    return _MocapScene(spec, [plate], [cam], ("world", "flange"), ())
