"""`simulate_tracker`: single-joint sweeps (or stop-and-shoot poses) of a
perturbed arm measured by a laser tracker (a retro-reflector on the flange),
written as a tracker dataset.

Pure NumPy / JAX, no rendering. The nominal robot is perturbed into the true
one as `jaxcal simulate` does (joint origins, axis tilts, zero offsets; joint
1's frame stays nominal unless the device frame is the base frame, which
then defines it); the reflector's true mount deviates from its design
position. Each joint sweeps alone about a home configuration; every sample is
the reflector's position in the device frame with isotropic Gaussian noise,
and a fraction of bad samples (a beam break, a reflector bumped) at the
sweep ends sits 0.3-0.5 mm off. With `poses`, the arm instead stops at that
many random configurations inside its joint limits (every joint moves between
samples), and with `compliance` each joint yields under gravity by its
compliance times the gravity torque of the links it carries (the robot file's
masses). The table gives the controller's joint positions (no encoder log, no
clock). Everything the calibration should recover goes to `truth.json` (its
`bad_samples` lists the bad ones, `compliance_rad_per_kNm` the compliances).
"""

import csv
import shutil
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from .._geometry import so3_exp
from .._kinematics import PerturbationScales, anchor_base, forward_kinematics, perturb_model
from .._npgeom import matrix_to_quaternion, pose, rotvec_to_matrix
from ..io._files import atomic_directory
from ..io.dataset import SCHEMA, SCHEMA_VERSION, load_dataset, write_json
from ..io.dh_tables import is_table_file, read_table_file
from ..io.model_json import model_to_json
from ..io.urdf import save_urdf, urdf_outline
from ..robots import link_inertials, load_robot_file, robot_file
from .arm import gravity_deflection
from .motion import check_finite

#: UR3 home of the acceptance case (deg): elbow at -90, wrist 2 at 90.
UR3_HOME_DEG = (0.0, 0.0, -90.0, 0.0, 90.0, 0.0)


@dataclass(frozen=True)
class TrackerSimConfig:
    """What `simulate_tracker` draws (lengths in the units named).

    - `samples_per_joint` evenly spaced samples while each joint sweeps
      `range_deg` centred on its `home_deg` entry (the others hold `home_deg`). The default is a
      UR's home; a robot of another number of joints sweeps about the middle of its joints' limits.
    - `noise_um`: isotropic position noise (1-sigma per axis); `orientation`:
      also a measured orientation (a 6-DoF probe) with `noise_deg`.
    - `bad_fraction` of each sweep's samples, half at each end, are
      `bad_mm` (uniform in the range) off in a random direction.
    - `point_mm`: the reflector's nominal position on the flange (mm);
      `point_error_mm`: the true mount's deviation (1-sigma per axis);
      `point_rotvec_deg`: the nominal mount's rotation (a rotation vector, deg: a
      camera on the flange turned about its axis) and `point_error_deg` its true
      deviation (1-sigma per axis; drawn only when positive, so that other seeds'
      draws stay as they were).
    - `device_is_base`: the device frame is the base frame (a tracker
      registered to the base, or the controller's own tool point); otherwise
      the tracker stands `device_distance` m from the base, turned at random.
    - `origin_mm`, `origin_deg`, `axis_tilt_deg`, `zero_offset_deg`: the
      arm's perturbation (as `jaxcal simulate`; no ratio error: the table
      gives joint positions).
    - `poses`: when positive, that many stop-and-shoot poses drawn uniformly
      within the joint limits (capped at `pose_range_deg` about zero) in place
      of the sweeps; `bad_fraction` of them, at random, are displaced.
    - `compliance`: per joint, rad per kN m of gravity torque (or None: rigid).
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
    point_rotvec_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    point_error_deg: float = 0.0
    device_is_base: bool = False
    device_distance: float = 2.0
    rate_hz: float = 100.0
    origin_mm: float = 1.0
    origin_deg: float = 0.2
    axis_tilt_deg: float = 0.2
    zero_offset_deg: float = 0.5
    poses: int = 0
    pose_range_deg: float = 170.0
    compliance: tuple[float, ...] | None = None

    @property
    def scales(self) -> PerturbationScales:
        """The arm's perturbation scales (`perturb_model`'s); the tracker sees no reduction ratios."""
        return PerturbationScales.of(self, ratio_percent=0.0)

    def check(self, joints: int) -> None:
        check_finite(self, "TrackerSimConfig")
        if self.compliance is not None and len(self.compliance) != joints:
            raise ValueError(f"compliance has {len(self.compliance)} values for a robot with {joints} joints")
        if self.poses < 0 or 0 < self.poses < 10:
            raise ValueError(f"poses must be 0 (sweeps) or at least 10, got {self.poses}")
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


def pose_commands(limits: np.ndarray, config: TrackerSimConfig, rng: np.random.Generator) -> np.ndarray:
    """`(poses, joints)` random configurations inside `limits` `(joints, 2)` (rad), capped at `pose_range_deg`."""
    cap = np.radians(config.pose_range_deg)
    lo, hi = np.maximum(limits[:, 0], -cap), np.minimum(limits[:, 1], cap)
    return lo + (hi - lo) * rng.uniform(size=(config.poses, len(limits)))


def bad_samples(config: TrackerSimConfig, joints: int) -> np.ndarray:
    """Indices of the bad samples: per sweep `bad_fraction` of them, half at each end
    (stop-and-shoot poses: `bad_fraction` of them, spread evenly)."""
    if config.poses:
        k = round(config.bad_fraction * config.poses)
        return (
            np.unique(np.linspace(0, config.poses - 1, k + 2).round().astype(int)[1:-1])
            if k
            else np.zeros(0, int)
        )
    k = round(config.bad_fraction * config.samples_per_joint)
    first, last = (k + 1) // 2, k // 2
    per = np.r_[np.arange(first), config.samples_per_joint - 1 - np.arange(last)].astype(int)
    return np.sort(np.concatenate([j * config.samples_per_joint + per for j in range(joints)]))


def _measure(config, true, T_device_base, T_flange_point, q, rng, inertials=None):
    """The device's samples: positions (and orientations) with noise, bad samples displaced;
    with `config.compliance`, at the joint angles gravity bends the arm to."""
    q_true = np.asarray(q, np.float64)
    if config.compliance is not None:
        q_true = q_true + gravity_deflection(true, q_true, 0.0, config.compliance, inertials)
    flange = np.asarray(jax.vmap(lambda qq: forward_kinematics(true, qq)[-1])(jnp.asarray(q_true)))
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


def _limits(urdf: Path, nominal) -> np.ndarray:
    """`(joints, 2)` joint limits of the robot file (rad; +-pi where it gives none)."""
    lim = (
        read_table_file(urdf).joint_limits()
        if is_table_file(urdf)
        else urdf_outline(urdf, nominal.joint_names).limits
    )
    return np.array(
        [
            (-np.pi, np.pi) if lim[n].lower is None else (lim[n].lower, lim[n].upper)
            for n in nominal.joint_names
        ],
        np.float64,
    )


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
            quat = [] if O is None else [repr(float(v)) for v in matrix_to_quaternion(O[i])]
            w.writerow(
                [
                    i,
                    repr(i / rate_hz),
                    names[joint[i]] if joint[i] >= 0 else "",
                    *(repr(float(v)) for v in P[i]),
                    *quat,
                    *(repr(float(v)) for v in q[i]),
                ]
            )


def simulate_tracker(config: TrackerSimConfig, out, *, overwrite: bool = False) -> Path:
    """Write `config`'s tracker dataset into directory `out` (atomically; the
    rules of `jaxcal.io._files.check_output_dir`, marker kind `"dataset"`).
    Returns the dataset path."""
    urdf = robot_file(config.robot)  # a URDF or a DH/MDH table
    table = is_table_file(urdf)
    nominal = load_robot_file(urdf)
    names = list(nominal.joint_names)
    if config.home_deg == UR3_HOME_DEG and len(names) != len(UR3_HOME_DEG):  # the default, for another arm
        config = replace(config, home_deg=tuple(np.degrees(_limits(urdf, nominal).mean(axis=1)).tolist()))
    config.check(len(names))
    true = perturb_model(nominal, jax.random.key(config.seed), config.scales)
    if not config.device_is_base:
        true = anchor_base(true, nominal)  # the device pose absorbs joint 1's frame
    rng = np.random.default_rng(config.seed)
    T_device_base = _device_pose(config, rng)
    T_point_nominal = pose(
        rotvec_to_matrix(np.radians(config.point_rotvec_deg)), 1e-3 * np.asarray(config.point_mm)
    )
    T_point_true = T_point_nominal.copy()
    T_point_true[:3, 3] += 1e-3 * config.point_error_mm * rng.standard_normal(3)
    if config.point_error_deg > 0:
        turn = rotvec_to_matrix(np.radians(config.point_error_deg) * rng.standard_normal(3))
        T_point_true[:3, :3] = T_point_true[:3, :3] @ turn
    if config.poses:
        q = pose_commands(_limits(urdf, nominal), config, rng)
        joint = np.full(len(q), -1)
    else:
        q, joint = sweep_commands(names, config)
    inertials = link_inertials(urdf) if config.compliance is not None else None
    P, O, bad = _measure(config, true, T_device_base, T_point_true, q, rng, inertials)
    device = "tracker"
    robot_name = f"robot{urdf.suffix}" if table else "robot.urdf"
    meta = {
        "schema": SCHEMA,
        "schema_version": SCHEMA_VERSION,
        "description": f"synthetic {config.robot} tracker {'poses' if config.poses else 'sweeps'} written by "
        f"jaxcal simulate (seed {config.seed})",
        "robot": {
            ("table" if table else "urdf"): robot_name,
            "base_link": nominal.link_names[0],
            "flange_link": nominal.link_names[-1],
            "joints": names,
        },
        "device": {
            "name": device,
            "kind": "laser_tracker",
            "file": "samples.csv",
            "link": nominal.link_names[-1],
            "point": "smr",
            "T_link_point_nominal": T_point_nominal,
            "sigma_m": 1e-6 * config.noise_um,
            "sigma_rad": float(np.radians(config.noise_deg)) if config.orientation else None,
        },
        "simulation": asdict(config),
    }
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
        "compliance_rad_per_kNm": None if config.compliance is None else list(config.compliance),
    }
    with atomic_directory(Path(out), overwrite=overwrite, kind="dataset", what="--out") as tmp:
        shutil.copyfile(urdf, tmp / robot_name)
        write_json(tmp / "metadata.json", meta)
        write_samples(tmp / "samples.csv", names, q, joint, P, O, config.rate_hz)
        write_json(tmp / "truth.json", truth)
        save_urdf(true, tmp / "truth.urdf", source=None if table else urdf)
        load_dataset(tmp)  # the format's every check, before the rename
    return Path(out)
