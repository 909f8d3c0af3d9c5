"""A synthetic humanoid upper body, and a tracker measuring both its hands at once.

`upper_body_urdf` writes the robot file: a pelvis (the root), a 3-DOF torso (yaw, pitch, roll)
whose fourth joint follows the torso pitch by a `<mimic>` law (as a parallel linkage does), a
chest carrying two 7-DOF arms on shoulder mounts tilted outwards and forwards, and a 2-DOF neck
with a head and a camera. Links carry masses and centres of mass of a light humanoid (a 70 kg
class robot's upper body), so gravity loads the torso with both arms.

`perturb_tree` draws a "true" body from the nominal one (joint origins, zero offsets, the
coupling's multiplier); `elastic_truth` draws joint and lateral compliances of plausible
stiffnesses; `tree_tracker_samples` measures a reflector on each hand at random
stop-and-shoot poses inside the joints' limits, with Gaussian noise, the body bent by gravity.
"""

import tempfile
from dataclasses import dataclass
from pathlib import Path

import equinox as eqx
import jax
import numpy as np

from .._npgeom import rotvec_to_matrix
from .._tree import KinematicTree
from .._treefit import Elastic, TreeSamples, deflected_tips
from ..io.tree_dataset import write_tree_dataset
from ..io.urdf_tree import actuated_limits, load_urdf_tree

#: Joint name, axis, parent link, child link, origin xyz (m), origin rpy (rad), limits (rad).
_TORSO = [
    ("torso_yaw", "0 0 1", "pelvis", "torso_yaw_link", (0.0, 0.0, 0.12), (0, 0, 0), 1.0),
    ("torso_pitch", "0 1 0", "torso_yaw_link", "torso_pitch_link", (0.0, 0.0, 0.08), (0, 0, 0), 0.5),
    ("torso_roll", "1 0 0", "torso_pitch_link", "torso_roll_link", (0.0, 0.0, 0.06), (0, 0, 0), 0.4),
    ("torso_upper_pitch", "0 1 0", "torso_roll_link", "chest", (0.0, 0.0, 0.22), (0, 0, 0), 0.5),
]
_NECK = [
    ("neck_yaw", "0 0 1", "chest", "neck_link", (0.02, 0.0, 0.30), (0, 0, 0), 1.2),
    ("neck_pitch", "0 1 0", "neck_link", "head", (0.0, 0.0, 0.06), (0, 0, 0), 0.6),
]
#: One arm, from its shoulder mount down (the right arm mirrors y): name, axis, xyz, limit.
_ARM = [
    ("shoulder_pitch", "0 1 0", (0.0, 0.0, 0.0), 2.0),
    ("shoulder_roll", "1 0 0", (0.0, 0.05, 0.0), 1.2),
    ("shoulder_yaw", "0 0 1", (0.0, 0.0, -0.14), 1.5),
    ("elbow", "0 1 0", (0.0, 0.0, -0.14), 1.4),
    ("wrist_yaw", "0 0 1", (0.0, 0.0, -0.13), 1.5),
    ("wrist_pitch", "0 1 0", (0.0, 0.0, -0.12), 1.0),
    ("wrist_roll", "1 0 0", (0.0, 0.0, -0.03), 1.0),
]
#: Link masses (kg) and centres of mass (m, link frame).
_MASS = {
    "pelvis": (8.0, (0, 0, 0.05)),
    "torso_yaw_link": (2.0, (0, 0, 0.04)),
    "torso_pitch_link": (2.0, (0, 0, 0.03)),
    "torso_roll_link": (6.0, (0, 0, 0.12)),
    "chest": (9.0, (0.0, 0.0, 0.15)),
    "neck_link": (0.5, (0, 0, 0.03)),
    "head": (2.5, (0.05, 0, 0.08)),
    "shoulder_pitch": (1.2, (0, 0.03, 0)),
    "shoulder_roll": (1.0, (0, 0, -0.07)),
    "shoulder_yaw": (1.6, (0, 0, -0.08)),
    "elbow": (1.0, (0, 0, -0.07)),
    "wrist_yaw": (0.8, (0, 0, -0.06)),
    "wrist_pitch": (0.3, (0, 0, -0.02)),
    "wrist_roll": (0.6, (0, 0, -0.06)),
}
#: The shoulder mounts on the chest: xyz (m) and rpy (rad), left; the right mirrors it.
SHOULDER_XYZ, SHOULDER_RPY = (0.0, 0.19, 0.22), (-0.25, 0.15, 0.0)
#: The hands' tool frames (a reflector, a marker plate) below the last wrist joint (m).
HAND_XYZ = (0.0, 0.0, -0.10)
MIMIC_MULTIPLIER = 0.5
#: The measured tips, and the reflectors' nominal position on each hand (m, hand frame).
HANDS = ("left_hand", "right_hand")
HAND_POINT = (0.02, 0.0, -0.01)


def _joint(name, axis, parent, child, xyz, rpy, limit, mimic="") -> str:
    return (
        f'  <joint name="{name}" type="revolute"><parent link="{parent}"/><child link="{child}"/>'
        f'<origin xyz="{" ".join(map(repr, map(float, xyz)))}" rpy="{" ".join(map(repr, map(float, rpy)))}"/>'
        f'<axis xyz="{axis}"/><limit lower="{-limit}" upper="{limit}" effort="100" velocity="2"/>{mimic}</joint>'
    )


def _link(name, mass_of) -> str:
    if mass_of not in _MASS:
        return f'  <link name="{name}"/>'
    m, c = _MASS[mass_of]
    i = 0.02 * m * 0.1**2
    return (
        f'  <link name="{name}"><inertial><mass value="{m}"/><origin xyz="{" ".join(map(str, c))}"/>'
        f'<inertia ixx="{i}" iyy="{i}" izz="{i}" ixy="0" ixz="0" iyz="0"/></inertial></link>'
    )


def upper_body_urdf(name: str = "upper_body") -> str:
    """The synthetic upper body's URDF text: tips `left_hand`, `right_hand` and `camera`."""
    links = [_link(n, n) for n in ("pelvis", *(j[3] for j in _TORSO), *(j[3] for j in _NECK))]
    joints = [
        _joint(
            *j,
            mimic=f'<mimic joint="torso_pitch" multiplier="{MIMIC_MULTIPLIER}" offset="0"/>'
            if j[0] == "torso_upper_pitch"
            else "",
        )
        for j in _TORSO
    ] + [_joint(*j) for j in _NECK]
    links.append('  <link name="camera"/>')
    joints.append(
        '  <joint name="camera_mount" type="fixed"><parent link="head"/><child link="camera"/>'
        '<origin xyz="0.09 0 0.1" rpy="-1.5707963267948966 0 -1.5707963267948966"/></joint>'
    )
    for side, sign in (("left", 1.0), ("right", -1.0)):
        mount = f"{side}_shoulder_mount"
        links.append(f'  <link name="{mount}"/>')
        xyz = (SHOULDER_XYZ[0], sign * SHOULDER_XYZ[1], SHOULDER_XYZ[2])
        rpy = (sign * SHOULDER_RPY[0], SHOULDER_RPY[1], SHOULDER_RPY[2])
        joints.append(
            f'  <joint name="{mount}_joint" type="fixed"><parent link="chest"/><child link="{mount}"/>'
            f'<origin xyz="{" ".join(map(repr, xyz))}" rpy="{" ".join(map(repr, rpy))}"/></joint>'
        )
        parent = mount
        for jname, axis, jxyz, limit in _ARM:
            child = f"{side}_{jname}_link"
            links.append(_link(child, jname))
            joints.append(
                _joint(
                    f"{side}_{jname}",
                    axis,
                    parent,
                    child,
                    (jxyz[0], sign * jxyz[1], jxyz[2]),
                    (0, 0, 0),
                    limit,
                )
            )
            parent = child
        links.append(f'  <link name="{side}_hand"/>')
        joints.append(
            f'  <joint name="{side}_hand_joint" type="fixed"><parent link="{parent}"/><child link="{side}_hand"/>'
            f'<origin xyz="{" ".join(map(repr, HAND_XYZ))}"/></joint>'
        )
    return f'<?xml version="1.0"?>\n<robot name="{name}">\n' + "\n".join(links + joints) + "\n</robot>\n"


@dataclass(frozen=True)
class BodyScales:
    """Standard deviations of a real body's deviations from its robot file: joint origins
    (mm per axis, deg per axis), zero offsets (deg), the coupling's multiplier (relative). (The
    measured points' mounts on the tips are drawn by the caller.)"""

    origin_mm: float = 1.0
    origin_deg: float = 0.2
    zero_offset_deg: float = 0.3
    coupling_rel: float = 0.01


def perturb_tree(
    tree: KinematicTree, rng: np.random.Generator, scales: BodyScales = BodyScales()
) -> KinematicTree:
    """A "true" body drawn from `tree`: every joint origin moved and turned, zero offsets and
    the coupled joints' multipliers changed (NumPy draws, `rng` seeded)."""
    n = tree.num_joints
    T = np.array(tree.T_parent_joint)
    for j in range(n):
        T[j, :3, 3] += 1e-3 * scales.origin_mm * rng.standard_normal(3)
        T[j, :3, :3] = T[j, :3, :3] @ rotvec_to_matrix(np.deg2rad(scales.origin_deg) * rng.standard_normal(3))
    C = np.array(tree.coupling)
    for j in tree.coupled:
        C[j] *= 1.0 + scales.coupling_rel * rng.standard_normal()
    zero = np.array(tree.zero_offset) + np.deg2rad(scales.zero_offset_deg) * rng.standard_normal(n)
    return eqx.tree_at(
        lambda t: (t.T_parent_joint, t.zero_offset, t.coupling),
        tree,
        tuple(jax.device_put(a) for a in (T, zero, C)),
    )


def elastic_truth(tree: KinematicTree, rng: np.random.Generator, *, lateral: bool = True) -> Elastic:
    """Compliances of plausible stiffnesses (rad per N m): joints of the torso and shoulders
    3-8 kN m/rad, the rest 0.5-2 kN m/rad; lateral stiffness 5-15 kN m/rad where the link
    bends (zero without `lateral`)."""
    n = tree.num_joints
    stiff = np.where(
        [name.startswith(("torso", "left_shoulder", "right_shoulder")) for name in tree.joint_names],
        rng.uniform(3e3, 8e3, n),
        rng.uniform(0.5e3, 2e3, n),
    )
    lateral_k = 1.0 / rng.uniform(5e3, 15e3, (n, 2)) if lateral else np.zeros((n, 2))
    return Elastic(joint=1.0 / stiff, lateral=lateral_k)


def compliance_z(result, truth: Elastic) -> dict[str, float]:
    """How a calibration (`jaxcal.trees.TreeCalibration`) of a drawn body did: each freed
    compliance's (estimate - `truth`) over its standard deviation, by parameter name
    (`JOINT.compliance`, `JOINT.lateral_compliance.1` and `.2`)."""
    params, z = result.parameters(), {}
    for j, name in enumerate(result.tree.joint_names):
        lateral = [(f"{name}.lateral_compliance.{k + 1}", truth.lateral[j, k]) for k in range(2)]
        for key, true in [(f"{name}.compliance", truth.joint[j]), *lateral]:
            if key in params and params[key][1] > 0:
                z[key] = (params[key][0] - float(true)) / params[key][1]
    return z


def random_poses(
    limits: np.ndarray, count: int, rng: np.random.Generator, fraction: float = 0.8
) -> np.ndarray:
    """`count` configurations drawn uniformly inside `fraction` of each actuated joint's range
    (`limits`: `(actuated, 2)` lower and upper, rad; a continuous joint's +-inf: a turn)."""
    limits = np.clip(limits, -np.pi, np.pi)
    mid, half = limits.mean(axis=1), 0.5 * fraction * np.diff(limits, axis=1)[:, 0]
    return mid + half * rng.uniform(-1.0, 1.0, (count, len(limits)))


def tree_tracker_samples(
    true: KinematicTree,
    q: np.ndarray,
    points: np.ndarray,
    T_device: np.ndarray,
    rng: np.random.Generator,
    *,
    noise_mm: float = 0.1,
    elastic: Elastic | None = None,
    device_tip: int = -1,
) -> TreeSamples:
    """A device's measurements of a point on every tip (`points`: `(tips, 3)`, m, tip frames) at
    configurations `q` of the true body bent by gravity (`elastic`), with isotropic Gaussian
    noise of `noise_mm` per axis; `truth` holds the noise-free positions. `T_device`: a fixed
    device's `T_device_root`, or with `device_tip` (a camera on the head) its pose in that tip's
    frame, whose own tip is then not measured."""
    clean = np.asarray(
        deflected_tips(true, elastic, jax.numpy.asarray(q), points, T_device, None, device_tip)
    )
    noisy = clean + 1e-3 * noise_mm * rng.standard_normal(clean.shape)
    measured = np.ones(noisy.shape[:2], bool)
    if device_tip >= 0:
        measured[:, device_tip] = False
    return TreeSamples(q=np.asarray(q), points=noisy, measured=measured, truth=clean)


def simulate_upper_body(
    out,
    *,
    poses: int = 500,
    test_poses: int = 200,
    noise_mm: float = 0.1,
    seed: int = 0,
    overwrite: bool = False,
) -> Path:
    """A tree dataset (`jaxcal.io.tree_dataset.load_tree_dataset`) of the upper body: a tracker measures a
    reflector on each hand at `poses` stop-and-shoot poses (`noise_mm` per axis) of a drawn body
    bent by gravity. `truth.json` holds the drawn compliances, the device's pose, the reflectors'
    mounts and `test_poses` more poses with the hands' noise-free points, to judge a calibration."""
    rng = np.random.default_rng(seed)
    text = upper_body_urdf()
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "upper_body.urdf"
        path.write_text(text)
        nominal = load_urdf_tree(path, tips=list(HANDS))
        limits = actuated_limits(path, nominal)
    true, elastic = perturb_tree(nominal, rng), elastic_truth(nominal, rng)
    T = np.eye(4)
    T[:3, :3] = rotvec_to_matrix(np.array([0.0, 0.0, np.pi]) + 0.05 * rng.standard_normal(3))
    T[:3, 3] = [2.0, 0.1, -0.4]
    points = np.asarray(HAND_POINT) + 2e-3 * rng.standard_normal((len(HANDS), 3))
    q = random_poses(limits, poses + test_poses, rng)
    samples = tree_tracker_samples(true, q, points, T, rng, noise_mm=noise_mm, elastic=elastic)
    truth = {
        "compliance_rad_per_Nm": dict(zip(nominal.joint_names, np.asarray(elastic.joint).tolist())),
        "lateral_compliance_rad_per_Nm": dict(zip(nominal.joint_names, np.asarray(elastic.lateral).tolist())),
        "T_device_root": T.tolist(),
        "points_m": dict(zip(HANDS, points.tolist())),
        "test": {"q": q[poses:].tolist(), "points_m": samples.truth[poses:].tolist()},
    }
    return write_tree_dataset(
        out,
        urdf_text=text,
        tips=HANDS,
        samples=samples.subset(slice(0, poses)),
        tree=nominal,
        noise_mm=noise_mm,
        points=[HAND_POINT] * len(HANDS),
        truth=truth,
        overwrite=overwrite,
    )
