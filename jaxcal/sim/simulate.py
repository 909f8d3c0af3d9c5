"""`simulate`: a perturbed arm filmed by rendered cameras, written as a dataset.

The nominal robot (what the calibrator is given) is perturbed into the true
one (seeded: joint origins, axis tilts, zero offsets, reduction ratios; joint
1's frame stays nominal because it *defines* the base frame, the same gauge
as `jaxcal.monte_carlo`). The marker plate's mount and the cameras' poses
get their own true deviations from their nominal (design) values. Each joint
sweeps alone; the encoders log motor angles at their rate; the cameras
render frames at theirs, stamped by their own clock. Everything the
calibration should recover is written to `truth.json` beside the images.
"""

import shutil
from dataclasses import asdict, dataclass, field, replace
from functools import partial
from pathlib import Path

import cv2
import jax
import numpy as np

from .._kinematics import PerturbationScales, anchor_base, forward_kinematics, perturb_model
from .._npgeom import axis_rotation
from .._progress import progress as progress_bar
from ..io.dataset import (
    SCHEMA,
    SCHEMA_VERSION,
    CameraInfo,
    TargetInfo,
    atomic_directory,
    load_dataset,
    write_encoders,
    write_frames,
    write_json,
)
from ..io.model_json import model_to_json
from ..io.urdf import load_urdf, save_urdf
from ..markers import TargetSpec
from ..planning._layout import facing_mount as facing_mount
from ..planning._layout import look_at as look_at
from ..robots import link_inertials, link_inertias, robot_path, shipped
from .arm import ArmModel, ArmMotion, arm_model
from .camera import CameraModel, camera_model
from .motion import ClockModel, check_finite, encoder_stream, joint_sweeps, true_angles
from .motion import frame_times as frame_times_of
from .physics import PhysicsMotion, flange_payload
from .scene import CameraSpec, PlateSpec, build_scene


@dataclass(frozen=True)
class SimConfig:
    """Everything `simulate` needs; the defaults make the demo's dataset.

    Perturbations (standard deviations): `origin_mm`, `origin_deg`,
    `axis_tilt_deg`, `zero_offset_deg`, `ratio_percent` for the arm;
    `mount_mm`, `mount_deg` for the marker plate (or eye-in-hand camera)
    mount and the camera placement. `grayscale` writes 8-bit single-channel
    PNGs (what a machine-vision camera gives; a third of the size).
    A sweep turns a revolute joint through `range_deg` and moves a prismatic
    one through `range_mm` (its entry of `range_deg` is ignored); with
    `sweep_back` > 0 it is filmed on the way back too, that many times slower
    (`jaxcal.sim.motion.joint_sweeps`' `back_s`: two speeds).
    `camera`: how the cameras expose and degrade their frames, a preset's
    name (`jaxcal.sim.camera.PRESETS`) or a `CameraModel`; `ideal` (one
    instant, noise-free) by default. `arm`: how the arm deviates from a rigid
    one with perfect encoders (gravity compliance, backlash, encoder counts and
    latency), a preset's name (`jaxcal.sim.arm.ARM_PRESETS`) or an `ArmModel`;
    `ideal` (rigid) by default. `encoder_noise_counts`: the encoders' noise in
    counts of the ideal arm's encoder (2^17 per motor turn; `ArmModel.encoder`).
    """

    robot: str = "ur5e"
    seed: int = 0
    resolution: tuple[int, int] = (640, 480)
    fovy_deg: float = 50.0
    cameras: int = 1
    camera_distance: float = 0.9
    eye_in_hand: bool = False
    distortion: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)
    markers: str = "charuco"
    dictionary: str = "DICT_4X4_50"
    squares: tuple[int, int] = (5, 4)
    square_length: float = 0.04
    marker_length: float = 0.03
    markers_on_links: bool = False
    frames_per_joint: int = 30
    range_deg: float | tuple[float, ...] = 40.0
    range_mm: float = 100.0
    home_deg: tuple[float, ...] | None = None
    fps: float = 30.0
    sweep_back: float = 0.0
    clock_offset_ms: float = 0.0
    clock_drift_ppm: float = 0.0
    clock_jitter_ms: float = 0.0
    clock_known: bool = True
    drop_rate: float = 0.0
    grayscale: bool = False
    encoders: bool = True
    encoder_rate_hz: float = 500.0
    encoder_noise_counts: float = 0.5
    origin_mm: float = 1.0
    origin_deg: float = 0.2
    axis_tilt_deg: float = 0.2
    zero_offset_deg: float = 0.5
    ratio_percent: float = 1.0
    mount_mm: float = 2.0
    mount_deg: float = 1.0
    link_plates: tuple = field(default=(), repr=False)
    camera: str | CameraModel = "ideal"
    arm: str | ArmModel = "ideal"

    def check(self) -> None:
        check_finite(self, "SimConfig")
        w, h = self.resolution
        if w < 32 or h < 32:
            raise ValueError(f"resolution {w}x{h} is too small (at least 32x32)")
        if self.cameras < 1:
            raise ValueError("at least one camera")
        if self.eye_in_hand and self.cameras != 1:
            raise ValueError("eye-in-hand simulates one camera on the flange")
        if self.frames_per_joint < 2:
            raise ValueError("frames_per_joint must be at least 2")
        if self.sweep_back < 0.0:
            raise ValueError(
                f"sweep_back must be >= 0 (0: the way back is not filmed), got {self.sweep_back}"
            )
        if not 0.0 <= self.drop_rate < 1.0:
            raise ValueError(f"drop_rate must be in [0, 1), got {self.drop_rate}")
        if self.markers not in ("charuco", "aruco"):
            raise ValueError(f"markers must be 'charuco' or 'aruco', got {self.markers!r}")
        if camera_model(self.camera).distortion is not None and any(self.distortion):
            raise ValueError("give the lens distortion once: in the camera model or in `distortion`")
        arm_model(self.arm)

    @property
    def scales(self) -> PerturbationScales:
        """The arm's perturbation scales (`perturb_model`'s), from this config's fields."""
        return PerturbationScales.of(self)

    def with_lens(self) -> "SimConfig":
        """This config, checked, with the camera model's lens distortion (if it has one) as `distortion`."""
        self.check()
        lens = camera_model(self.camera).distortion
        return self if lens is None else replace(self, distortion=tuple(float(x) for x in lens))


# --------------------------------------------------------------------------- geometry helpers


def _jitter(T, rng, mm, deg) -> np.ndarray:
    w = np.deg2rad(deg) * rng.standard_normal(3)
    angle = np.linalg.norm(w)
    dT = np.eye(4)
    if angle > 0:
        dT[:3, :3] = axis_rotation(w, angle)
    dT[:3, 3] = 1e-3 * mm * rng.standard_normal(3)
    return np.asarray(T) @ dT


# --------------------------------------------------------------------------- the run


def nominal_robot(robot: str):
    """The nominal model and URDF path of a shipped robot's name or a URDF file."""
    if robot in shipped():
        path = robot_path(robot)
    else:
        path = Path(robot)
        if not path.is_file():
            raise ValueError(
                f"robot {robot!r} is neither a shipped robot ({shipped()}; and upper_body, the synthetic humanoid) "
                "nor a file"
            )
    return load_urdf(path), path


def sweep_ranges(nominal, config: SimConfig) -> np.ndarray:
    """Every joint's sweep as `joint_sweeps` takes it (degrees, turned into
    radians there): `range_deg`, and for a prismatic joint `range_mm` in the
    same units (its metres as if they were radians)."""
    ranges = np.broadcast_to(np.asarray(config.range_deg, np.float64), (nominal.num_joints,)).copy()
    prismatic = np.asarray([t == "prismatic" for t in nominal.joint_types])
    ranges[prismatic] = np.degrees(config.range_mm * 1e-3)
    return ranges


def draw_truth(nominal, config: SimConfig):
    """The true arm: `nominal` perturbed with `config`'s scales (seeded), joint 1's frame kept."""
    true = perturb_model(nominal, jax.random.key(config.seed), config.scales)
    return anchor_base(true, nominal)


def _target_spec(
    config: SimConfig, name: str, first_id: int, *, world: bool = False, small: bool = False
) -> TargetSpec:
    if config.markers == "aruco":
        return TargetSpec(
            kind="aruco",
            dictionary=config.dictionary,
            marker_length=config.marker_length * 2.5,
            first_id=first_id,
            name=name,
        )
    squares = tuple(config.squares)
    if world:  # the board an eye-in-hand camera looks at: larger, seen from further
        squares = (squares[0] + 2, squares[1] + 2)
    scale = 1.0
    if small:  # the plates on the links, filmed from further away: 4x4 larger squares (8 markers each)
        squares, scale = (4, 4), 1.5
    return TargetSpec(
        kind="charuco",
        dictionary=config.dictionary,
        squares=squares,
        square_length=scale * config.square_length,
        marker_length=scale * config.marker_length,
        first_id=first_id,
        name=name,
    )


def scene_layout(nominal, true, config: SimConfig, rng):
    """The scene `simulate` films: nominal and true plates and cameras, placed
    from the zero configuration (or `config.home_deg`).

    **Arguments:** `nominal` and `true` (`KinematicModel`s, e.g. from
    `nominal_robot` and `draw_truth`), `config` (`SimConfig`), `rng` (a NumPy
    `Generator`: the true mounts' jitter).

    **Returns:** `(plates_nominal, plates_true, cameras_nominal, cameras_true)`,
    lists of `PlateSpec` and `CameraSpec` (`build_scene` takes the true ones).
    """
    links = nominal.link_names
    w, h = config.resolution
    n = nominal.num_joints
    q0 = np.zeros(n) if config.home_deg is None else np.radians(config.home_deg)
    F0 = np.asarray(jax.device_get(forward_kinematics(nominal, q0)))
    flange = links[-1]
    out_flange = F0[-1][:3, 2]  # the flange's z axis points out of the tool face
    plates_nominal, cameras = [], []
    ids = 0
    if not config.eye_in_hand:
        spec = _target_spec(config, "plate0", ids)
        ids += spec.num_markers
        up = F0[-1][:3, :3].T @ np.array([0.0, 0.0, 1.0])  # upright as seen at the zero configuration
        T_mount = facing_mount(spec, (0.0, 0.0, 1.0), (0.0, 0.0, 0.012), up=up)
        plates_nominal.append(PlateSpec(spec, flange, T_mount))
        centre = (F0[-1] @ T_mount)[:3, 3]
        normal = (F0[-1] @ T_mount)[:3, :3] @ spec.front_normal()
        yaws = [0.0] if config.cameras == 1 else np.linspace(-25.0, 25.0, config.cameras)
        horiz = np.array([normal[0], normal[1], 0.0])
        view = normal
        if np.linalg.norm(horiz) < 0.7:
            # A plate facing up or down (e.g. the Panda's flange at zero): view it from 50 deg off
            # its normal, from the side away from the arm's base column, which would hide it.
            away = np.array([centre[0], centre[1], 0.0])
            away = away / np.linalg.norm(away) if np.linalg.norm(away) > 1e-6 else np.array([1.0, 0.0, 0.0])
            view = np.cos(np.deg2rad(50.0)) * normal + np.sin(np.deg2rad(50.0)) * away
        aim, distance = centre, config.camera_distance
        if config.markers_on_links:
            # Frame the whole arm: aim at the middle of the plates-to-be and back off until
            # all of them fit in 84 % of the vertical field of view.
            mids = [
                (F0[i] @ np.r_[0.5 * np.asarray(nominal.T_parent_joint[i])[:3, 3], 1.0])[:3]
                for i in range(1, n)
            ]
            pts = np.stack([centre, *mids])
            aim = 0.5 * (pts.min(0) + pts.max(0))
            extent = np.max(np.linalg.norm(pts - aim, axis=1))
            distance = max(distance, extent / np.tan(0.42 * np.deg2rad(config.fovy_deg)))
        for k, yaw in enumerate(yaws):
            d = axis_rotation((0.0, 0.0, 1.0), np.deg2rad(yaw)) @ view
            if np.linalg.norm(horiz) > 0.5:  # look slightly down at a plate that faces sideways
                d = axis_rotation(np.cross(d, (0.0, 0.0, 1.0)), np.deg2rad(-15.0)) @ d
            eye = aim + distance * d
            T_wc = look_at(eye, aim)
            cameras.append(
                CameraSpec(f"cam{k}", w, h, config.fovy_deg, T_wc, "world", tuple(config.distortion))
            )
        if config.markers_on_links:
            eye = cameras[0].T_mount_cam[:3, 3]
            for i in range(1, n):
                link = links[i]
                child = np.asarray(nominal.T_parent_joint[i])[:3, 3]
                mid_link = 0.5 * child
                T_wl = F0[i]
                to_cam = np.linalg.inv(T_wl[:3, :3]) @ (eye - (T_wl @ np.r_[mid_link, 1.0])[:3])
                to_cam /= np.linalg.norm(to_cam)
                spec = _target_spec(config, f"plate{i}", ids, small=True)
                ids += spec.num_markers
                up = np.linalg.inv(T_wl[:3, :3]) @ np.array([0.0, 0.0, 1.0])
                # On stalks, alternately above and below the arm, so that the plates of
                # short neighbouring links (the wrist's) do not hide each other.
                side = up - (up @ to_cam) * to_cam
                side /= np.linalg.norm(side)
                centre_i = mid_link + 0.06 * to_cam + (0.22 if i % 2 else -0.22) * side
                T_mount = facing_mount(spec, to_cam, centre_i, up=up)
                plates_nominal.append(PlateSpec(spec, link, T_mount))
    else:
        T_flange_cam = np.eye(4)
        T_flange_cam[:3, 3] = (0.0, 0.0, 0.03)
        cameras.append(
            CameraSpec("cam0", w, h, config.fovy_deg, T_flange_cam, flange, tuple(config.distortion))
        )
        spec = _target_spec(config, "board0", ids, world=True)
        centre = F0[-1][:3, 3] + config.camera_distance * out_flange
        up = F0[-1][:3, 1] * -1.0  # upright in the camera's view (image y is down)
        plates_nominal.append(PlateSpec(spec, "world", facing_mount(spec, -out_flange, centre, up=up)))
    # The truth: mounts and the eye-in-hand camera deviate from their design.
    plates_true, cameras_true = _true_layout(plates_nominal, cameras, config, rng)
    return plates_nominal, plates_true, cameras, cameras_true


def _true_layout(plates_nominal, cameras, config: SimConfig, rng):
    """The plates' true mounts and a flange camera's true pose: the design, jittered."""
    plates_true = [
        PlateSpec(p.target, p.link, _jitter(p.T_link_target, rng, config.mount_mm, config.mount_deg))
        for p in plates_nominal
    ]
    cameras_true = [
        replace(c, T_mount_cam=_jitter(c.T_mount_cam, rng, config.mount_mm, config.mount_deg))
        if c.mount != "world"
        else c
        for c in cameras
    ]
    return plates_true, cameras_true


def _visible(spec: TargetSpec, T_cam_target, cam: CameraSpec, margin_px: float = 2.0) -> bool:
    P = (T_cam_target[:3, :3] @ spec.points().T).T + T_cam_target[:3, 3]
    if np.any(P[:, 2] <= 0.05):
        return False
    facing = -(T_cam_target[:3, :3] @ spec.front_normal()) @ (P.mean(0) / np.linalg.norm(P.mean(0)))
    if facing < np.cos(np.deg2rad(75.0)):
        return False
    p = (cam.K @ (P / P[:, 2:]).T).T[:, :2]
    return bool(np.all((p >= -0.5 + margin_px) & (p <= np.array([cam.width, cam.height]) - 0.5 - margin_px)))


def simulate(
    config: SimConfig,
    out,
    *,
    trajectory=None,
    overwrite: bool = False,
    progress: bool = True,
    frame_times=None,
    layout=None,
    notes: dict | None = None,
) -> Path:
    """Render `config`'s synthetic dataset into directory `out` (atomically).

    `trajectory`: a `jaxcal.sim.motion.Trajectory` of commanded joint positions
    (e.g. `free_motion(times, q)`), filmed at `config.fps` over its segments;
    default: joint-by-joint sweeps of `config.frames_per_joint` frames.
    `frame_times`, `layout`, `notes`: a capture plan's frames, design and
    records (`jaxcal.sim.plan.render_plan`; see `_layouts` and `_metadata`).
    Refuses a non-empty `out` unless `overwrite` and it is a dataset jaxcal
    wrote (see `jaxcal.io._files.check_output_dir`); `out` gets the `.jaxcal`
    marker of kind `"dataset"`. Returns the dataset path.
    """
    config = config.with_lens()  # checked
    optics = camera_model(config.camera)
    out = Path(out)
    nominal, urdf_path = nominal_robot(config.robot)
    true = draw_truth(nominal, config)
    rng = np.random.default_rng(config.seed)
    plates_nominal, plates_true, cameras_nominal, cameras_true = _layouts(nominal, true, config, rng, layout)
    if optics.lens_supersample is not None:  # the lens warped at the camera model's resolution
        cameras_true = [replace(c, lens_supersample=int(optics.lens_supersample)) for c in cameras_true]
    names = nominal.joint_names
    nominal_ratio = np.asarray(nominal.reduction_ratio)
    arm = arm_model(config.arm)
    trajectory, angles, clock, encoder, (enc_t, enc_motor), t_frames, keep = _motion(
        config,
        nominal,
        arm,
        trajectory,
        frame_times,
        rng,
        lambda traj: arm_motion(arm, traj, nominal_ratio, true, urdf_path, plates_true),
    )
    theta = angles(t_frames)
    noise_rng = np.random.default_rng([config.seed, 1])  # the camera's own draws: the capture stays the same
    q_true = theta - np.asarray(true.zero_offset)
    link_poses = np.asarray(jax.device_get(jax.vmap(forward_kinematics, in_axes=(None, 0))(true, q_true)))
    stamps = clock.stamp(t_frames, rng)
    link_index = {name: i for i, name in enumerate(nominal.link_names)}

    def T_world(link: str, f: int) -> np.ndarray:
        return np.eye(4) if link == "world" else link_poses[f, link_index[link]]

    scene = build_scene(
        true, plates=plates_true, cameras=cameras_true, floor_z=None if config.eye_in_hand else -0.6
    )
    row_camera, row_frame, row_stamp, row_file = [], [], [], []  # frames.csv's columns
    truth_frames = []
    todo = [(f, c) for f in np.flatnonzero(keep) for c in cameras_true]
    with atomic_directory(out, overwrite=overwrite, inputs=(urdf_path,), kind="dataset") as tmp, scene:
        for c in cameras_true:
            (tmp / "images" / c.name).mkdir(parents=True)
        bar = progress_bar(progress, f"rendering {len(todo)} images")
        with bar as p:
            task = p.add_task("render", total=len(todo)) if p is not None else None
            for f, cam in todo:
                render_at = _renderer_at(scene, cam.name, t_frames[f], theta[f], angles)
                image = optics.capture(render_at, t_frames[f], cam.height, noise_rng, config.grayscale)
                rel = f"images/{cam.name}/{f:06d}.png"
                _write_image(tmp / rel, image)
                row_camera.append(cam.name)
                row_frame.append(int(f))
                row_stamp.append(float(stamps[f]))
                row_file.append(rel)
                poses, visible = _seen_targets(cam, plates_true, lambda link: T_world(link, f))
                truth_frames.append(
                    {
                        "row": len(row_file) - 1,
                        "camera": cam.name,
                        "frame": int(f),
                        "t": float(t_frames[f]),
                        "theta": theta[f],
                        "q": q_true[f],
                        "T_cam_target": poses,
                        "visible": visible,
                    }
                )
                if p is not None:
                    p.advance(task)

        shutil.copyfile(urdf_path, tmp / "robot.urdf")
        save_urdf(true, tmp / "truth.urdf", source=urdf_path)
        write_frames(tmp / "frames.csv", row_camera, row_frame, row_stamp, row_file)
        if config.encoders:
            write_encoders(tmp / "encoders.csv", enc_t, enc_motor, names)
        for name, text in (notes or {}).get("files", {}).items():
            (tmp / name).write_text(text)
        meta = _metadata(config, nominal, cameras_nominal, plates_nominal, encoder, trajectory, notes, optics)
        write_json(tmp / "metadata.json", meta)
        truth = _truth(config, true, cameras_true, plates_true) | (
            {} if arm == ArmModel() else {"arm": arm.metadata(true.joint_types)}
        )
        write_json(
            tmp / "truth.json",
            truth | {"dropped_frames": np.flatnonzero(~keep).tolist(), "frames": truth_frames},
        )
        load_dataset(tmp)  # the format's every check, before the rename: nothing unreadable is kept
    return out


def _motion(config: SimConfig, nominal, arm: ArmModel, trajectory, frame_times, rng, motion_of):
    """The capture's motion and its records: `(trajectory, angles_at, clock, encoder, (enc_t,
    enc_motor), t_frames, keep)`, the commanded trajectory (default: joint-by-joint sweeps), the
    true joint angles along it (`motion_of(trajectory)`: `arm_motion`'s pair, whose motor
    angles, when given, the encoders read), the camera clock, the encoder model and its log,
    the frames' controller times and which frames are kept (drawn from `rng` in this order:
    the log's noise, then the dropped frames)."""
    names = nominal.joint_names
    sweeps = trajectory is None
    if sweeps:
        trajectory = sweeps_trajectory(nominal, config)
    elif trajectory.q.shape[1] != len(names):
        raise ValueError(f"trajectory has {trajectory.q.shape[1]} joints, the robot {len(names)}")
    angles, motor = motion_of(trajectory)
    clock = ClockModel(
        config.fps, config.clock_offset_ms, config.clock_drift_ppm, config.clock_jitter_ms, config.drop_rate
    )
    encoder = arm.encoder(config.encoder_rate_hz, config.encoder_noise_counts)
    log = encoder_stream(trajectory, np.asarray(nominal.reduction_ratio), encoder, rng, motor)
    t_frames = (
        np.concatenate(frame_times_of(trajectory, config.frames_per_joint if sweeps else None, clock))
        if frame_times is None
        else np.asarray(frame_times, np.float64)
    )
    keep = rng.random(len(t_frames)) >= clock.drop_rate
    return trajectory, angles, clock, encoder, log, t_frames, keep


def sweeps_trajectory(nominal, config: SimConfig):
    """The commanded motion of `config`'s joint-by-joint sweeps (`simulate`'s default):
    `config.frames_per_joint` frames at `config.fps` over each sweep, about the zero
    configuration or `config.home_deg`."""
    home = None if config.home_deg is None else np.radians(config.home_deg)
    return joint_sweeps(
        nominal.joint_names,
        sweep_ranges(nominal, config),
        sweep_s=config.frames_per_joint / config.fps,
        home=home,
        back_s=config.sweep_back * config.frames_per_joint / config.fps or None,
    )


def angles_at(arm: ArmModel, trajectory, nominal_ratio, true, urdf_path, plates=()):
    """`angles_at(t)`: the true arm's joint angles at controller times `t` (`arm_motion`'s)."""
    return arm_motion(arm, trajectory, nominal_ratio, true, urdf_path, plates)[0]


def arm_motion(arm: ArmModel, trajectory, nominal_ratio, true, urdf_path, plates=()):
    """`(angles_at, motor_at)`: the true arm's joint angles at controller times `t` and the
    motor angles its encoders read there (`None`: the command's, `encoder_stream`'s default).
    Rigid; `jaxcal.sim.arm.ArmMotion` with the robot file's masses for compliance; or, for an
    arm with `dynamics`, MuJoCo's physics (`jaxcal.sim.physics.PhysicsMotion`: the robot
    file's inertias, the target `plates` on links as payload), whose encoders read the motors."""
    if arm.dynamics is not None:
        motion = PhysicsMotion(arm, trajectory, nominal_ratio, true, link_inertias(urdf_path), plates)
        return motion.angles, motion.motor
    if arm.rigid:
        return partial(
            true_angles,
            trajectory,
            nominal_ratio=nominal_ratio,
            true_ratio=true.reduction_ratio,
            true_zero_offset=true.zero_offset,
        ), None
    inertials = link_inertials(urdf_path) if arm.compliance is not None else None
    return ArmMotion(arm, trajectory, nominal_ratio, true, inertials).angles, None


def _renderer_at(scene, camera: str, t_frame: float, theta_frame, angles_at):
    """`render_at(t, rows)`: `camera`'s render (its rows `rows`, or all for `None`) with the
    arm where it stands at controller time `t` (the frame's own angles at its own time,
    exactly as without a camera model)."""

    def render_at(t: float, rows=None) -> np.ndarray:
        scene.set_angles(theta_frame if t == t_frame else angles_at(t))
        return scene.render(camera, rows)

    return render_at


def _write_image(path: Path, image: np.ndarray) -> None:
    """An RGB (H, W, 3) or grey (H, W) uint8 image as a PNG."""
    if not cv2.imwrite(str(path), image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2BGR)):
        raise OSError(f"could not write {path}")


def _seen_targets(cam, plates, T_world) -> tuple[dict, dict]:
    """Each plate's true pose in camera `cam` and whether it is fully in view
    (`T_world(link)`: the link's world pose in this frame)."""
    T_cw = np.linalg.inv(T_world(cam.mount) @ cam.T_mount_cam)
    poses = {p.target.name: T_cw @ T_world(p.link) @ p.T_link_target for p in plates}
    return poses, {p.target.name: _visible(p.target, poses[p.target.name], cam) for p in plates}


def _layouts(nominal, true, config: SimConfig, rng, layout=None):
    """Nominal and true plates and cameras: placed from `config`, or `layout =
    (plates, cameras)` as designed (a capture plan's), the true plate mounts (and
    a flange camera's pose) deviating from the design as always."""
    if layout is None:
        return scene_layout(nominal, true, config, rng)
    plates_nominal, cameras_nominal = (list(x) for x in layout)
    plates_true, cameras_true = _true_layout(plates_nominal, cameras_nominal, config, rng)
    return plates_nominal, plates_true, cameras_nominal, cameras_true


def _metadata(
    config: SimConfig, nominal, cameras_nominal, plates_nominal, encoder, trajectory, notes=None, optics=None
) -> dict:
    """`metadata.json` of a rendered dataset: what a user would know (the nominal robot and cameras).
    A plan's `notes`: `metadata` (keys added at the top), `segments` (one dict per
    recorded segment, added to its `motion` entry); `files` are written by `simulate`."""
    optics = camera_model(config.camera) if optics is None else optics
    cameras_meta = [
        CameraInfo(c.name, c.width, c.height, c.K, c.dist, c.mount, **optics.metadata(c.height)).to_dict()
        for c in cameras_nominal
    ]
    targets_meta = [TargetInfo(p.target, p.link, p.T_link_target).to_dict() for p in plates_nominal]
    dynamics = arm_model(config.arm).dynamics
    # What a physics arm's flange carries, as its user would state it: the plates' design.
    payload = (
        None
        if dynamics is None
        else flange_payload(plates_nominal, dynamics.payload_kg, nominal.link_names[-1])
    )
    return {
        "schema": SCHEMA,
        "schema_version": SCHEMA_VERSION,
        "description": f"synthetic {config.robot} dataset rendered by jaxcal simulate (seed {config.seed})",
        "robot": {
            "urdf": "robot.urdf",
            "base_link": nominal.link_names[0],
            "flange_link": nominal.link_names[-1],
            "joints": list(nominal.joint_names),
        }
        | ({} if payload is None else {"payload": payload}),
        "cameras": cameras_meta,
        "targets": targets_meta,
        "encoders": {
            "file": "encoders.csv",
            "quantity": "motor_angle",
            "unit": "rad",
            "rate_hz": encoder.rate_hz,
            "counts_per_rev": encoder.counts_per_rev,
        }
        if config.encoders
        else None,
        "clock": {"offset_s": 1e-3 * config.clock_offset_ms if config.clock_known else None},
        "motion": [
            {"joint": s.joint, "start": s.start, "end": s.end}
            | ({} if s.home is None else {"home": list(s.home)})
            | extra
            for s, extra in zip(
                trajectory.segments, (notes or {}).get("segments") or [{}] * len(trajectory.segments)
            )
        ],
        "simulation": {k: v for k, v in asdict(config).items() if k != "link_plates"},
    } | (notes or {}).get("metadata", {})


def _truth(config: SimConfig, true, cameras_true, plates_true) -> dict:
    """`truth.json` of a rendered dataset, without its per-frame records."""
    T_world_cams = {c.name: c.T_mount_cam for c in cameras_true if c.mount == "world"}
    return {
        "model": model_to_json(true),
        "T_world_base": np.eye(4),
        "cameras": {
            c.name: {
                "mount": c.mount,
                "T_mount_cam": c.T_mount_cam,
                **({"T_cam_base": np.linalg.inv(T_world_cams[c.name])} if c.name in T_world_cams else {}),
            }
            for c in cameras_true
        },
        "targets": {p.target.name: {"link": p.link, "T_link_target": p.T_link_target} for p in plates_true},
        "clock": {
            "offset_s": 1e-3 * config.clock_offset_ms,
            "drift_ppm": config.clock_drift_ppm,
            "jitter_ms": config.clock_jitter_ms,
        },
    }
