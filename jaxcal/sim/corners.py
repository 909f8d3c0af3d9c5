"""Analytic corners of a simulated capture: where each target corner is seen, from the truth, without rendering.

A capture `simulate` rendered records its truth: the true arm, the cameras'
and targets' true poses (`truth.json`) and the commanded joint sweeps
(`metadata.json`'s `simulation`). `capture_truth` turns them back into every
target's pose at any controller time, and `CaptureTruth.corners` projects
the targets' corners through the camera's lens (the metadata's `K`, the
simulation's distortion): at the frame's time $t$, or with a rolling shutter
of line delay $\\ell$ at each corner's own row time $t + y\\,\\ell$, $y$ the
row where the corner itself is seen at that time. That row is a fixed point,
$y = v(t + y\\,\\ell)$ with $v$ the corner's image row, found by iteration from
the global shutter's $y$: each step contracts by $|\\dot v|\\,\\ell$, the rows the
image moves in one row's delay (0.08 at 2350 px/s and 33 us per row).
Every row is a point in time: no exposure (motion blur is unbiased where the
target is found, `docs/performance.md`), $t$ being the first row's time, the
controller time a truth frame records.

`analytic_detections` gives the `jaxcal.vision.Detection`s a perfect detector
would return, plus independent Gaussian pixel noise if asked;
`jaxcal.stages.observe` takes them in place of detecting the images, so the
estimator can be run over many draws of detection errors on one capture's
design (`benchmarks/realism.py --analytic-seeds`), or on an arm the capture
was not rendered with (`capture_truth(..., arm=...)`: a compliant arm on a
rigid capture's design; its encoder log, which reads the motors, stays valid).

Captures of `simulate`'s joint-by-joint sweeps only (the motion is rebuilt
from the configuration and checked against the truth's frames).
"""

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import jax
import numpy as np

from .._kinematics import KinematicModel, forward_kinematics
from ..io.dataset import load_dataset, simulation_record, true_poses
from ..vision import Detection
from .arm import ArmModel
from .scene import PlateSpec
from .simulate import SimConfig, angles_at, sweeps_trajectory

#: The fixed point of a corner's row: stop when no row moves more than this (px) ...
ROW_TOLERANCE_PX = 1e-9
#: ... or after this many steps (an image moving a row per row's delay would not converge).
ROW_ITERATIONS = 50


@dataclass(frozen=True, eq=False)
class CameraTruth:
    """A simulated camera: its mount (`world` or a link), its true pose on it, its
    intrinsics (`K`, the lens's OpenCV coefficients) and image size."""

    mount: str
    T_mount_cam: np.ndarray
    K: np.ndarray
    lens: np.ndarray
    width: int
    height: int


@dataclass(frozen=True, eq=False)
class TargetTruth:
    """A simulated target: its link (`world` for a fixed board), true mount and corner points (m)."""

    link: str
    T_link_target: np.ndarray
    points: np.ndarray


@dataclass(frozen=True, eq=False)
class CaptureTruth:
    """Where everything of a simulated capture is at any controller time (see the module docstring).

    - `model`: the true arm; `angles_at(t)`: its true joint angles at controller
      times `t (n,)`, `(n, joints)`.
    - `T_world_base`; `cameras`, `targets`: name -> `CameraTruth`, `TargetTruth`.
    - `frames`: per camera, its frames' frame-table rows and first-row times
      (controller clock), `(rows, t)`, in the frame table's order.
    """

    model: KinematicModel
    angles_at: Callable[[np.ndarray], np.ndarray]
    T_world_base: np.ndarray
    cameras: dict[str, CameraTruth]
    targets: dict[str, TargetTruth]
    frames: dict[str, tuple[np.ndarray, np.ndarray]]
    visible: dict[int, dict[str, bool]]

    def link_poses(self, t) -> np.ndarray:
        """Every link's world pose at controller times `t (n,)`: `(n, links, 4, 4)`."""
        theta = self.angles_at(np.asarray(t, np.float64))
        q = theta - np.asarray(self.model.zero_offset, np.float64)
        return self.T_world_base @ np.asarray(_chain(self.model, q))

    def target_poses(self, camera: str, target: str, t) -> np.ndarray:
        """$T_{cam,target}$ of `target` in `camera` at controller times `t (n,)`: `(n, 4, 4)`."""
        cam, tgt = self.cameras[camera], self.targets[target]
        links = list(self.model.link_names)
        L = self.link_poses(t)

        def world(link: str) -> np.ndarray:
            return (
                np.broadcast_to(np.eye(4), L.shape[:1] + (4, 4))
                if link == "world"
                else L[:, links.index(link)]
            )

        return np.linalg.inv(world(cam.mount) @ cam.T_mount_cam) @ world(tgt.link) @ tgt.T_link_target

    def project(self, camera: str, target: str, t, ids) -> np.ndarray:
        """Corners `ids (n,)` of `target` in `camera`, each at its own controller time `t (n,)`: `(n, 2)` px
        (OpenCV's pixel-centre convention, through the lens)."""
        cam = self.cameras[camera]
        T = self.target_poses(camera, target, t)
        P = np.einsum("nij,nj->ni", T[:, :3, :3], self.targets[target].points[np.asarray(ids)]) + T[:, :3, 3]
        if len(P) == 0:
            return np.zeros((0, 2))
        u = cv2.projectPoints(P.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), cam.K, cam.lens)[0]
        return u.reshape(-1, 2)

    def corners(self, camera: str, target: str, t, ids, line_delay_s: float = 0.0) -> np.ndarray:
        """Corners `ids (n,)` of `target` seen in the frames whose first row is at `t (n,)`
        (controller s): each at its own row's time $t + y\\,\\ell$ with `line_delay_s` $\\ell$
        (the fixed point of the module docstring; 0: a global shutter, every corner at `t`).
        `(n, 2)` px. A `ValueError` if the rows do not settle."""
        t = np.asarray(t, np.float64)
        u = self.project(camera, target, t, ids)
        if not line_delay_s:
            return u
        for _ in range(ROW_ITERATIONS):
            v = self.project(camera, target, t + u[:, 1] * line_delay_s, ids)
            step = float(np.max(np.abs(v[:, 1] - u[:, 1]), initial=0.0))
            u = v
            if step <= ROW_TOLERANCE_PX:
                return u
        raise ValueError(
            f"camera {camera!r}: the corners' rows did not settle in {ROW_ITERATIONS} steps (last {step:.3g} px): "
            f"does the image move a row or more in one row's delay ({line_delay_s:.3g} s)?"
        )


@jax.jit
def _chain(model, q):
    return jax.vmap(lambda qq: forward_kinematics(model, qq))(q)


def capture_truth(dataset, arm: ArmModel | None = None) -> CaptureTruth:
    """The truth of the simulated joint-sweeps capture `dataset` (a path or a loaded `Dataset`) as
    functions of time (see the module docstring). `arm`: the arm whose joints the cameras see
    (default the capture's own, `truth.json`'s `arm`, else rigid).

    A `ValueError` for a capture without a truth or the simulation's record, or whose truth
    frames the rebuilt sweeps do not reproduce (a capture plan's motion, a real capture)."""
    ds = dataset if hasattr(dataset, "truth") else load_dataset(dataset)
    sim = simulation_record(ds.metadata)
    if ds.truth is None or sim is None:
        raise ValueError(
            f"{ds.root}: analytic corners need a simulated capture (truth.json and the simulation)"
        )
    truth = true_poses(ds.truth)
    nominal = ds.load_model()
    config = SimConfig(
        robot=sim.robot,
        frames_per_joint=sim.frames_per_joint,
        fps=sim.fps,
        range_deg=sim.range_deg,
        range_mm=sim.range_mm,
        home_deg=sim.home_deg,
    )
    trajectory = sweeps_trajectory(nominal, config)
    recorded = ArmModel.from_metadata(truth.arm)
    arm = recorded if arm is None else arm
    ratio = np.asarray(nominal.reduction_ratio)
    plates = [  # the payload of a physics arm
        PlateSpec(tg.spec, truth.target_link[tg.name], np.asarray(truth.T_link_target[tg.name], np.float64))
        for tg in ds.targets
        if tg.name in truth.T_link_target
    ]
    angles = angles_at(arm, trajectory, ratio, truth.model, ds.robot_urdf, plates)
    own = (
        angles
        if arm == recorded
        else angles_at(recorded, trajectory, ratio, truth.model, ds.robot_urdf, plates)
    )
    if len(truth.frame_t) and not np.allclose(own(truth.frame_t), truth.frame_theta, rtol=0.0, atol=1e-9):
        raise ValueError(
            f"{ds.root}: the joint sweeps rebuilt from the simulation's record do not reproduce the truth's "
            "joint angles: analytic corners need a capture of simulate's default sweeps"
        )
    lens = np.asarray(sim.distortion, np.float64)
    cameras = {
        c.name: CameraTruth(
            truth.camera_mount[c.name],
            np.asarray(truth.T_mount_cam[c.name], np.float64),
            np.asarray(c.K, np.float64),
            lens,
            int(c.width),
            int(c.height),
        )
        for c in ds.cameras
        if c.name in truth.T_mount_cam
    }
    targets = {
        tg.name: TargetTruth(
            truth.target_link[tg.name],
            np.asarray(truth.T_link_target[tg.name], np.float64),
            np.asarray(tg.spec.points(), np.float64),
        )
        for tg in ds.targets
        if tg.name in truth.T_link_target
    }
    rows = np.asarray(truth.frame_rows, int)
    frames = {}
    for name in cameras:
        mine = np.flatnonzero(np.asarray(truth.frame_cameras) == name)
        mine = mine[np.argsort(rows[mine])]
        frames[name] = (rows[mine], truth.frame_t[mine])
    visible = dict(zip(truth.frame_rows, truth.visible))
    return CaptureTruth(
        truth.model, angles, np.asarray(truth.T_world_base, np.float64), cameras, targets, frames, visible
    )


def analytic_detections(
    truth: CaptureTruth,
    camera: str,
    *,
    like: list | None = None,
    line_delay_s: float = 0.0,
    noise_px: float = 0.0,
    rng: np.random.Generator | None = None,
) -> list[dict[str, Detection]]:
    """Per frame of `camera` (its frame-table rows in order, as `jaxcal.stages.observe` takes
    them), target name -> the `Detection` of its corners where `truth` puts them
    (`CaptureTruth.corners`, with `line_delay_s`), plus independent Gaussian noise of
    `noise_px` per axis drawn from `rng` (in frame, target, corner order).

    `like`: per frame, the detections whose corner ids to use (e.g. the capture's own images
    detected: the same corners as a detector found); default every corner of each target the
    truth marks fully in view. Corners whose position falls outside the image are left out."""
    rows, t = truth.frames[camera]
    if like is not None and len(like) != len(rows):
        raise ValueError(f"`like` has {len(like)} frames, camera {camera!r} {len(rows)}")
    cam = truth.cameras[camera]
    ids = {}  # (frame index, target) -> ids
    for i, row in enumerate(rows):
        for name, tgt in truth.targets.items():
            if like is not None:
                d = like[i].get(name)
                if d is not None and len(d):
                    ids[i, name] = np.asarray(d.ids)
            elif truth.visible.get(int(row), {}).get(name):
                ids[i, name] = np.arange(len(tgt.points))
    out = [{} for _ in rows]
    for name in truth.targets:
        keys = [k for k in ids if k[1] == name]
        if not keys:
            continue
        frame = np.concatenate([np.full(len(ids[k]), k[0]) for k in keys])
        corner = np.concatenate([ids[k] for k in keys])
        u = truth.corners(camera, name, t[frame], corner, line_delay_s)
        for k in keys:
            sel = frame == k[0]
            out[k[0]][name] = (corner[sel], u[sel])
    rng = np.random.default_rng(0) if rng is None else rng
    size = np.array([cam.width, cam.height], np.float64)
    for frame in out:
        for name in list(frame):
            c, u = frame[name]
            if noise_px:
                u = u + noise_px * rng.standard_normal(u.shape)
            inside = np.all((u >= -0.5) & (u <= size - 0.5), axis=1)
            if inside.any():
                frame[name] = Detection(c[inside], u[inside])
            else:
                del frame[name]
    return out
