"""Rendered check captures for `jaxcal check` (tests, `benchmarks/drift.py`): a few
stop-and-shoot images of the scene `jaxcal simulate` films with the same `SimConfig`
(same seed: the same true arm, plate and camera), the camera moved by a twist."""

import json
from dataclasses import replace
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from .._correction import Estimate, ParameterLayout
from ..io.dataset import load_dataset
from ..io.result import write_estimate
from .motion import Segment, Trajectory
from .simulate import SimConfig, draw_truth, nominal_robot, scene_layout, simulate

#: `truth_result`'s standard deviations: a good calibration's (20 um / 0.001 deg on the
#: camera, 10 um or urad on the arm and mounts, 0.02 px on the focal lengths and centre).
GOOD_CALIBRATION = {"cam": 2e-5, "origin": 1e-5, "zero": 1e-5, "tool": 1e-5, "rate": 2e-6, "clock": 0.01}


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
        config,
        Path(out),
        trajectory=trajectory,
        frame_times=shots,
        layout=(plates_nominal, moved),
        progress=progress,
    )


def truth_result(config: SimConfig, capture, out, *, scales=None, sigma_px: float = 0.05) -> Path:
    """The scene's truth written as a camera calibration result (`result.json` and
    `estimate.npz` in `out`): the true arm as the nominal model, zero correction, a
    diagonal covariance of `scales` (per parameter group, default `GOOD_CALIBRATION`;
    0.02 px on the intrinsics), corner noise `sigma_px`; `capture`: a dataset of the
    scene (its camera's intrinsics). For checks without a calibration run."""
    nominal, _ = nominal_robot(config.robot)
    true = draw_truth(nominal, config)
    plates, plates_true, cams, cams_true = scene_layout(
        nominal, true, config, np.random.default_rng(config.seed)
    )
    eih = config.eye_in_hand
    layout = ParameterLayout.of(true, 1, eye_in_hand=eih)
    x = np.zeros(layout.size)
    x[layout.index("rate")] = 1.0
    sd = np.zeros(layout.size)
    for g, v in (scales or GOOD_CALIBRATION).items():
        sd[layout.index(g)] = v
    sd[layout.index("intr")[:4]] = 0.02
    if eih:  # the fixed frame is the board's, the mount the camera's (on the flange)
        T_fixed, mount = np.linalg.inv(plates_true[0].T_link_target), cams_true[0].T_mount_cam
    else:
        T_fixed, mount = np.linalg.inv(cams[0].T_mount_cam), plates_true[0].T_link_target
    cam = load_dataset(capture).cameras[0]
    est = Estimate(
        x=jnp.asarray(x),
        cov=jnp.asarray(np.diag(sd**2)),
        free=jnp.asarray(sd > 0),
        nominal=true,
        T_flange_marker0=jnp.asarray(mount)[None],
        T_cam_base0=jnp.asarray(T_fixed),
        reduction_ratio=jnp.asarray(true.reduction_ratio),
        layout=layout,
        mount_names=(cam.name if eih else plates[0].target.name,),
    )
    out = Path(out)
    out.mkdir(parents=True)
    write_estimate(out / "estimate.npz", est)
    doc = {
        "schema": "jaxcal.result",
        "dataset": str(capture),
        "setup": "eye_in_hand" if eih else "eye_to_hand",
        "capture": f"{'eye-in-hand' if eih else 'eye-to-hand'}, the truth (jaxcal.sim.drift.truth_result)",
        "camera": cam.name,
        "targets": [plates[0].target.name],
        **({"board": plates[0].target.name} if eih else {}),
        "intrinsics": {
            "source": "metadata",
            "K": np.asarray(cam.K).tolist(),
            "distortion": np.asarray(cam.dist, float).ravel()[:5].tolist(),
        },
        "clock": {"offset_s": 0.0},
        "refinement": {"sigma_px": float(sigma_px)},
    }
    (out / "result.json").write_text(json.dumps(doc))
    return out
