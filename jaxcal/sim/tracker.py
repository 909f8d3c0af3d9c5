"""`simulate_tracker`: single-joint sweeps of a perturbed arm measured by a
laser tracker (a retro-reflector on the flange), written as a tracker dataset.

Pure NumPy / JAX, no rendering. The nominal robot is perturbed into the true
one as `jaxcal simulate` does (joint origins, axis tilts, zero offsets; joint
1's frame stays nominal unless the device frame is the base frame, which
then defines it); the reflector's true mount deviates from its design
position. Each joint sweeps alone about a home configuration; every sample is
the reflector's position in the device frame with isotropic Gaussian noise,
and a fraction of bad samples (a beam break, a reflector bumped) at the
sweep ends sits 0.3-0.5 mm off. The table gives the controller's joint
positions (no encoder log, no clock). Everything the calibration should
recover goes to `truth.json` (its `bad_samples` lists the bad ones).
"""

import csv
import shutil
from dataclasses import asdict, dataclass
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from .._geometry import so3_exp
from .._kinematics import PerturbationScales, anchor_base, forward_kinematics, perturb_model
from ..io._files import atomic_directory
from ..io.dataset import SCHEMA, SCHEMA_VERSION, write_json
from ..io.model_json import model_to_json
from ..io.urdf import load_urdf, save_urdf
from ..robots import robot_path, shipped

#: UR3 home of the acceptance case (deg): elbow at -90, wrist 2 at 90.
UR3_HOME_DEG = (0.0, 0.0, -90.0, 0.0, 90.0, 0.0)


@dataclass(frozen=True)
class TrackerSimConfig:
    """What `simulate_tracker` draws (lengths in the units named).

    - `samples_per_joint` evenly spaced samples while each joint sweeps
      `range_deg` centred on its `home_deg` entry (the others hold `home_deg`).
    - `noise_um`: isotropic position noise (1-sigma per axis); `orientation`:
      also a measured orientation (a 6-DoF probe) with `noise_deg`.
    - `bad_fraction` of each sweep's samples, half at each end, are
      `bad_mm` (uniform in the range) off in a random direction.
    - `point_mm`: the reflector's nominal position on the flange (mm);
      `point_error_mm`: the true mount's deviation (1-sigma per axis).
    - `device_is_base`: the device frame is the base frame (a tracker
      registered to the base, or the controller's own tool point); otherwise
      the tracker stands `device_distance` m from the base, turned at random.
    - `origin_mm`, `origin_deg`, `axis_tilt_deg`, `zero_offset_deg`: the
      arm's perturbation (as `jaxcal simulate`; no ratio error: the table
      gives joint positions).
    """

    robot: str = "ur3"
    seed: int = 0
    samples_per_joint: int = 300
    range_deg: float | tuple[float, ...] = 120.0
    home_deg: tuple[float, ...] | None = UR3_HOME_DEG
    noise_um: float = 10.0
    orientation: bool = False
    noise_deg: float = 0.01
    bad_fraction: float = 0.02
    bad_mm: tuple[float, float] = (0.3, 0.5)
    point_mm: tuple[float, float, float] = (80.0, 40.0, 60.0)
    point_error_mm: float = 0.5
    device_is_base: bool = False
    device_distance: float = 2.0
    rate_hz: float = 100.0
    origin_mm: float = 1.0
    origin_deg: float = 0.2
    axis_tilt_deg: float = 0.2
    zero_offset_deg: float = 0.5

    def check(self, joints: int) -> None:
        if self.samples_per_joint < 10:
            raise ValueError(f"samples_per_joint must be at least 10, got {self.samples_per_joint}")
        if not 0.0 <= self.bad_fraction < 0.5:
            raise ValueError(f"bad_fraction must be in [0, 0.5), got {self.bad_fraction}")
        if self.home_deg is not None and len(self.home_deg) != joints:
            raise ValueError(f"home_deg has {len(self.home_deg)} angles for a robot with {joints} joints")
        if np.ndim(self.range_deg) and len(self.range_deg) != joints:
            raise ValueError(f"range_deg has {len(self.range_deg)} angles for a robot with {joints} joints")
        if not np.all(np.asarray(self.range_deg) > 0):
            raise ValueError(f"range_deg must be positive, got {self.range_deg}")


def _rotation(rng: np.random.Generator) -> np.ndarray:
    """A uniformly random rotation (QR of a Gaussian matrix, signs fixed)."""
    Q, R = np.linalg.qr(rng.standard_normal((3, 3)))
    Q = Q * np.sign(np.diag(R))
    return Q if np.linalg.det(Q) > 0 else -Q


def _device_pose(config: TrackerSimConfig, rng: np.random.Generator) -> np.ndarray:
    """$T_{device,base}$: the identity, or a tracker `device_distance` m away, turned at random."""
    if config.device_is_base:
        return np.eye(4)
    heading = rng.uniform(0.0, 2 * np.pi)
    T_base_device = np.eye(4)
    T_base_device[:3, :3] = _rotation(rng)
    T_base_device[:3, 3] = config.device_distance * np.array([np.cos(heading), np.sin(heading), 0.15])
    return np.linalg.inv(T_base_device)


def sweep_commands(names, config: TrackerSimConfig) -> tuple[np.ndarray, np.ndarray]:
    """`(q, joint)`: every sample's commanded joint positions (rad) and the joint sweeping."""
    n = len(names)
    home = np.zeros(n) if config.home_deg is None else np.radians(np.asarray(config.home_deg, np.float64))
    half = np.broadcast_to(np.radians(config.range_deg) / 2, (n,))
    qs, joints = [], []
    for j in range(n):
        q = np.tile(home, (config.samples_per_joint, 1))
        q[:, j] = home[j] + np.linspace(-half[j], half[j], config.samples_per_joint)
        qs.append(q)
        joints.append(np.full(config.samples_per_joint, j))
    return np.concatenate(qs), np.concatenate(joints)


def bad_samples(config: TrackerSimConfig, joints: int) -> np.ndarray:
    """Indices of the bad samples: per sweep `bad_fraction` of them, half at each end."""
    k = round(config.bad_fraction * config.samples_per_joint)
    first, last = (k + 1) // 2, k // 2
    per = np.r_[np.arange(first), config.samples_per_joint - 1 - np.arange(last)].astype(int)
    return np.sort(np.concatenate([j * config.samples_per_joint + per for j in range(joints)]))


def _measure(config, true, T_device_base, T_flange_point, q, rng):
    """The device's samples: positions (and orientations) with noise, bad samples displaced."""
    flange = np.asarray(jax.vmap(lambda qq: forward_kinematics(true, qq)[-1])(jnp.asarray(q)))
    T = T_device_base @ flange @ T_flange_point
    P = T[:, :3, 3] + 1e-6 * config.noise_um * rng.standard_normal((len(q), 3))
    bad = bad_samples(config, true.num_joints)
    u = rng.standard_normal((len(bad), 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    P[bad] += 1e-3 * rng.uniform(*config.bad_mm, (len(bad), 1)) * u
    O = None
    if config.orientation:
        w = np.radians(config.noise_deg) * rng.standard_normal((len(q), 3))
        O = np.asarray(jax.vmap(so3_exp)(jnp.asarray(w))) @ T[:, :3, :3]
    return P, O, bad


def _quaternion(R: np.ndarray) -> np.ndarray:
    """`(x, y, z, w)` of a rotation matrix (Shepperd's method, w >= 0)."""
    w = np.sqrt(max(1.0 + np.trace(R), 0.0)) / 2
    if w > 0.1:
        v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / (4 * w)
        return np.r_[v, w]
    i = int(np.argmax(np.diag(R)))
    j, k = (i + 1) % 3, (i + 2) % 3
    x = np.sqrt(max(1.0 + R[i, i] - R[j, j] - R[k, k], 0.0)) / 2
    out = np.zeros(4)
    out[i] = x
    out[j] = (R[j, i] + R[i, j]) / (4 * x)
    out[k] = (R[k, i] + R[i, k]) / (4 * x)
    out[3] = (R[k, j] - R[j, k]) / (4 * x)
    return out * (1 if out[3] >= 0 else -1)


def write_samples(path: Path, names, q, joint, P, O, rate_hz: float) -> None:
    """`samples.csv`: sample, timestamp, joint, x, y, z[, qx, qy, qz, qw], the joint positions."""
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(
            [
                "sample",
                "timestamp",
                "joint",
                "x",
                "y",
                "z",
                *(("qx", "qy", "qz", "qw") if O is not None else ()),
                *names,
            ]
        )
        for i in range(len(q)):
            quat = [] if O is None else [repr(float(v)) for v in _quaternion(O[i])]
            w.writerow(
                [
                    i,
                    repr(i / rate_hz),
                    names[joint[i]],
                    *(repr(float(v)) for v in P[i]),
                    *quat,
                    *(repr(float(v)) for v in q[i]),
                ]
            )


def simulate_tracker(config: TrackerSimConfig, out, *, overwrite: bool = False) -> Path:
    """Write `config`'s tracker dataset into directory `out` (atomically; the
    rules of `jaxcal.io._files.check_output_dir`, marker kind `"dataset"`).
    Returns the dataset path."""
    urdf = robot_path(config.robot) if config.robot in shipped() else Path(config.robot)
    if not urdf.is_file():
        raise ValueError(f"robot {config.robot!r} is neither a shipped robot ({shipped()}) nor a file")
    nominal = load_urdf(urdf)
    names = list(nominal.joint_names)
    config.check(len(names))
    scales = PerturbationScales(
        origin_mm=config.origin_mm, origin_deg=config.origin_deg, axis_tilt_deg=config.axis_tilt_deg,
        zero_offset_deg=config.zero_offset_deg, ratio_percent=0.0,
    )  # fmt: skip
    true = perturb_model(nominal, jax.random.key(config.seed), scales)
    if not config.device_is_base:
        true = anchor_base(true, nominal)  # the device pose absorbs joint 1's frame
    rng = np.random.default_rng(config.seed)
    T_device_base = _device_pose(config, rng)
    T_point_nominal = np.eye(4)
    T_point_nominal[:3, 3] = 1e-3 * np.asarray(config.point_mm, np.float64)
    T_point_true = T_point_nominal.copy()
    T_point_true[:3, 3] += 1e-3 * config.point_error_mm * rng.standard_normal(3)
    q, joint = sweep_commands(names, config)
    P, O, bad = _measure(config, true, T_device_base, T_point_true, q, rng)
    device = "tracker"
    meta = {
        "schema": SCHEMA,
        "schema_version": SCHEMA_VERSION,
        "description": f"synthetic {config.robot} tracker sweeps written by jaxcal simulate (seed {config.seed})",
        "robot": {"urdf": "robot.urdf", "base_link": nominal.link_names[0],
                  "flange_link": nominal.link_names[-1], "joints": names},
        "device": {
            "name": device, "kind": "laser_tracker", "file": "samples.csv", "link": nominal.link_names[-1],
            "point": "smr", "T_link_point_nominal": T_point_nominal, "sigma_m": 1e-6 * config.noise_um,
            "sigma_rad": float(np.radians(config.noise_deg)) if config.orientation else None,
        },
        "simulation": asdict(config),
    }  # fmt: skip
    truth = {
        "model": model_to_json(true),
        "T_world_base": np.eye(4),
        "cameras": {
            device: {
                "mount": "world",
                "T_mount_cam": np.linalg.inv(T_device_base),
                "T_cam_base": T_device_base,
            }
        },
        "targets": {"smr": {"link": nominal.link_names[-1], "T_link_target": T_point_true}},
        "clock": {"offset_s": 0.0},
        "bad_samples": bad.tolist(),
    }
    with atomic_directory(Path(out), overwrite=overwrite, kind="dataset", what="--out") as tmp:
        shutil.copyfile(urdf, tmp / "robot.urdf")
        write_json(tmp / "metadata.json", meta)
        write_samples(tmp / "samples.csv", names, q, joint, P, O, config.rate_hz)
        write_json(tmp / "truth.json", truth)
        save_urdf(true, tmp / "truth.urdf", source=urdf)
    return Path(out)
