"""Rendered check captures for `jaxcal check` (tests, `benchmarks/drift.py`): a few
stop-and-shoot images of the scene `jaxcal simulate` films with the same `SimConfig`
(same seed: the same true arm, plate and camera), the camera moved by a twist."""

from dataclasses import replace
from pathlib import Path

import numpy as np

from .motion import Segment, Trajectory
from .simulate import SimConfig, draw_truth, nominal_robot, scene_layout, simulate


def twist_matrix(v, w) -> np.ndarray:
    """$\\exp((v, \\omega))$ as a 4x4 (first order in the coupling; exact rotation)."""
    w = np.asarray(w, np.float64)
    a = np.linalg.norm(w)
    K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    R = np.eye(3) if a == 0 else np.eye(3) + np.sin(a) / a * K + (1 - np.cos(a)) / a**2 * K @ K
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(v, np.float64)
    return T


def stop_and_shoot(q: np.ndarray, move_s: float = 1.0, hold_s: float = 0.4) -> tuple[Trajectory, np.ndarray]:
    """A trajectory from the zero configuration through the configurations `q` `(P, joints)`,
    holding at each, and the frames' controller times (mid-hold)."""
    n = q.shape[1]
    times, way, shots = [0.0], [np.zeros(n)], []
    for p in q:
        t = times[-1]
        times += [t + move_s, t + move_s + hold_s]
        way += [p, p]
        shots.append(t + move_s + 0.5 * hold_s)
    times.append(times[-1] + move_s)
    way.append(np.zeros(n))
    return Trajectory(times, way, [Segment(None, 0.0, times[-1])]), np.asarray(shots)


def random_poses(joints: int, count: int, amplitude_deg: float = 10.0, seed: int = 0) -> np.ndarray:
    """`count` configurations uniform within +-`amplitude_deg` of zero on every joint (rad)."""
    rng = np.random.default_rng(seed)
    return np.radians(amplitude_deg) * rng.uniform(-1.0, 1.0, (count, joints))


def render_check_capture(
    config: SimConfig, out, q: np.ndarray, *, move=((0.0,) * 3, (0.0,) * 3), progress: bool = False
) -> Path:
    """Render stop-and-shoot images at `q` of `config`'s scene with the camera moved by
    `move = (v (m), omega (rad))` in its own frame: eye-to-hand $T_{world,cam} \\exp(\\varepsilon)$,
    eye-in-hand the mount $T_{flange,cam} \\exp(\\varepsilon)$ (before the mount's own jitter,
    which the seed repeats). Returns the dataset path."""
    nominal, _ = nominal_robot(config.robot)
    true = draw_truth(nominal, config)
    plates_nominal, _, cameras, _ = scene_layout(nominal, true, config, np.random.default_rng(config.seed))
    E = twist_matrix(*move)
    moved = [replace(cameras[0], T_mount_cam=cameras[0].T_mount_cam @ E), *cameras[1:]]
    trajectory, shots = stop_and_shoot(np.asarray(q, np.float64))
    return simulate(
        config, Path(out), trajectory=trajectory, frame_times=shots, layout=(plates_nominal, moved),
        progress=progress,
    )  # fmt: skip
