"""A head camera filming marker plates on both hands of a kinematic tree: the seed's method on
a humanoid (issue 51's rendered tree capture).

`tree_scene` builds a MuJoCo scene of a `KinematicTree` in which every link is a mocap body
(`jaxcal.sim.scene.mocap_scene`) posed from jaxcal's forward kinematics of the bent body (a
link's lateral bend is no MuJoCo joint), with a ChArUco plate on each measured tip and the
camera on its own tip. `film_hands` renders the capture at stop-and-shoot poses, detects each
plate and takes its origin from PnP with the covariance PnP gives (the pixel noise pooled over
the capture): `TreeSamples` in the camera's frame, for
`jaxcal.trees.calibrate_tree(..., device_on=CAMERA_TIP)`, which weighs each point by its
covariance (PnP sees across the image far better than in depth). `reaching_poses` and
`poses_in_view` draw poses at which every plate is inside the picture and faces the camera;
`film_upper_body` does it all for a drawn synthetic upper body, and `simulate_head_camera`
writes it as a tree dataset (`jaxcal simulate --robot upper_body`).
"""

import dataclasses
import tempfile
from dataclasses import dataclass
from pathlib import Path

import cv2
import jax
import jax.numpy as jnp
import numpy as np

from .._progress import progress
from .._tree import KinematicTree, tip_poses, tips_from_frames
from .._treefit import Elastic, TreeSamples, deflected_frames
from ..io.tree_dataset import write_tree_dataset
from ..io.urdf_tree import actuated_limits, load_urdf_tree
from ..markers import TargetSpec
from ..vision import detect, estimate_pose
from .humanoid import HANDS, elastic_truth, perturb_tree, upper_body_urdf
from .scene import CameraSpec, PlateSpec, Scene, mocap_scene

#: The tip the camera rides on (the upper body's `camera` link: OpenCV axes, looking forward).
CAMERA_TIP = "camera"
#: The head camera: 640x480 behind a 70 degree lens (vertical).
CAMERA = CameraSpec(name="head", width=640, height=480, fovy_deg=70.0, mount=CAMERA_TIP)


#: Where the synthetic upper body's joints stand when its head camera sees both hands (rad, by
#: the joint's name without its side): neck bent down, arms forward, elbows and wrists raised.
REACH = {
    "neck_yaw": (-0.4, 0.4),
    "neck_pitch": (0.1, 0.6),
    "shoulder_pitch": (-1.7, -0.8),
    "elbow": (-1.2, 0.0),
    "wrist_pitch": (-0.8, 0.4),
}


def reaching_poses(
    tree: KinematicTree, limits: np.ndarray, count: int, rng: np.random.Generator
) -> np.ndarray:
    """`count` configurations drawn uniformly inside `REACH` for the joints it names (either
    side) and inside 80 % of each other actuated joint's `limits`: candidates for
    `poses_in_view`."""
    limits = np.clip(np.asarray(limits, np.float64), -np.pi, np.pi)
    mid, half = limits.mean(axis=1), 0.4 * np.diff(limits, axis=1)[:, 0]
    lo, hi = mid - half, mid + half
    for a, name in enumerate(tree.actuated_names):
        box = REACH.get(name.removeprefix("left_").removeprefix("right_"))
        if box is not None:
            lo[a], hi[a] = max(box[0], limits[a, 0]), min(box[1], limits[a, 1])
    return lo + (hi - lo) * rng.uniform(0.0, 1.0, (count, len(lo)))


def hand_plate(tip: str, first_id: int, offset: float = 0.03) -> PlateSpec:
    """A 3x3 ChArUco plate (4 cm squares) on tip `tip`, its printed face along the tip's +x,
    `offset` (m) out from the tip's origin, centred on that axis."""
    target = TargetSpec(
        squares=(3, 3),
        square_length=0.04,
        marker_length=0.03,
        first_id=first_id,
        margin=0.008,
        name=f"{tip}_plate",
    )
    R = np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # face (target -z) along +x
    centre = target.image()[1].mean(axis=0)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, np.array([offset, 0.0, 0.0]) - R @ centre
    return PlateSpec(target=target, link=tip, T_link_target=T)


@dataclass(frozen=True)
class Capture:
    """A filmed capture: the plates' origins as `TreeSamples` (camera frame, with PnP's
    covariances; `truth` the noise-free origins where the body was drawn), each tip's plate,
    the corner noise pooled over the capture (px), and how many frames saw each plate."""

    samples: TreeSamples
    plates: dict
    sigma_px: float
    seen: dict


def _check(tree: KinematicTree, plates, camera: CameraSpec) -> None:
    """Refuse plates or a camera on what is not a tip of `tree`, and plates whose markers share
    ids (a detector would take one for the other)."""
    for what, on in [
        *((f"plate {p.target.name!r}", p.link) for p in plates),
        (f"camera {camera.name!r}", camera.mount),
    ]:
        if on not in tree.tip_names:
            raise ValueError(
                f"{what} sits on {on!r}, which is not a tip of the tree: tips are {tree.tip_names}"
            )
    for k, a in enumerate(plates):
        for b in plates[k + 1 :]:
            shared = sorted(set(a.target.marker_ids.tolist()) & set(b.target.marker_ids.tolist()))
            if a.target.dictionary == b.target.dictionary and shared:
                raise ValueError(
                    f"plates {a.target.name!r} and {b.target.name!r} share marker ids {shared}: give each its own "
                    "first_id (hand_plate's)"
                )


def tree_scene(tree: KinematicTree, plates, camera: CameraSpec = CAMERA) -> Scene:
    """The MuJoCo scene of `tree` (`jaxcal.sim.scene.mocap_scene`): a body per link, drawn to
    its children's joint origins, then one per tip (`tip:NAME`, carrying the `plates` on that
    tip and the camera on `camera.mount`, at `camera.T_mount_cam` in it), in `_bodies`' order."""
    links = {
        name: [np.asarray(tree.T_parent_joint[j][:3, 3]) for j, p in enumerate(tree.parent) if p + 1 == k]
        for k, name in enumerate(tree.link_names)
    }
    _check(tree, plates, camera)
    links.update({f"tip:{t}": [] for t in tree.tip_names})
    plates = [PlateSpec(p.target, f"tip:{p.link}", p.T_link_target) for p in plates]
    return mocap_scene(links, plates, [dataclasses.replace(camera, mount=f"tip:{camera.mount}")])


@jax.jit
def _bodies(tree, elastic, q):
    """Every link's and tip's pose (root frame) at each configuration of `q`, bent by gravity."""

    def one(q):
        frames = deflected_frames(tree, q, elastic)
        return jnp.concatenate([frames, tips_from_frames(tree, frames)])

    return jax.vmap(one)(q)


def poses_in_view(
    tree: KinematicTree,
    candidates: np.ndarray,
    plates,
    count: int,
    camera: CameraSpec = CAMERA,
    margin_px: float = 30.0,
    facing: float = 0.5,
) -> np.ndarray:
    """The first `count` of `candidates` `(m, actuated)` at which every plate's outer corners
    project `margin_px` inside the picture of `camera` (on its tip of `tree`) and the plate
    faces it (the cosine between its printed face's normal and the ray to the camera at least
    `facing`). Raises `ValueError` when fewer qualify."""
    _check(tree, plates, camera)
    candidates = np.asarray(candidates, np.float64)
    if candidates.ndim != 2 or candidates.shape[1] != tree.num_actuated:
        raise ValueError(f"candidates must be (poses, {tree.num_actuated}), got shape {candidates.shape}")
    kinds = dict(zip(tree.joint_names, tree.joint_types))
    revolute = np.asarray([kinds[n] != "prismatic" for n in tree.actuated_names])
    if len(candidates) and np.abs(candidates[:, revolute]).max(initial=0.0) > 2 * np.pi:
        raise ValueError(
            f"candidates reach {np.abs(candidates[:, revolute]).max():.4g} rad at a revolute joint: degrees? give radians"
        )
    tips = np.asarray(jax.vmap(tip_poses, in_axes=(None, 0))(tree, jnp.asarray(candidates)))
    cam = tips[:, tree.tip_names.index(camera.mount)] @ np.asarray(camera.T_mount_cam)
    ok = np.ones(len(candidates), bool)
    for plate in plates:
        T = np.linalg.inv(cam) @ tips[:, tree.tip_names.index(plate.link)] @ plate.T_link_target
        corners = plate.target.image()[1]
        c = np.einsum("nab,kb->nka", T[:, :3, :3], corners) + T[:, None, :3, 3]
        uv = np.einsum("ab,nkb->nka", camera.K, c)
        uv = uv[..., :2] / np.maximum(uv[..., 2:], 1e-9)
        inside = (uv[..., 0] > margin_px) & (uv[..., 0] < camera.width - margin_px)
        inside &= (uv[..., 1] > margin_px) & (uv[..., 1] < camera.height - margin_px)
        normal = T[:, :3, :3] @ plate.target.front_normal()
        centre = c.mean(axis=1)
        cos = -np.einsum("na,na->n", normal, centre) / np.linalg.norm(centre, axis=1)
        ok &= inside.all(axis=1) & (c[..., 2] > 0.1).all(axis=1) & (cos >= facing)
    if ok.sum() < count:
        raise ValueError(
            f"only {int(ok.sum())} of {len(candidates)} candidate poses show every plate to camera "
            f"{camera.name!r}; {count} wanted: draw more candidates"
        )
    return np.asarray(candidates)[np.flatnonzero(ok)[:count]]


def _measure(scene: Scene, camera: CameraSpec, image: np.ndarray, plate: PlateSpec):
    """Plate `plate`'s PnP pose estimate in `image` (grey), or None where it is not found."""
    det = detect(image, plate.target, K=camera.K, dist=camera.dist)
    return None if det is None else estimate_pose(det, plate.target, camera.K, camera.dist)


def film_hands(
    scene: Scene,
    tree: KinematicTree,
    q: np.ndarray,
    elastic: Elastic | None = None,
    show_progress: bool = True,
) -> Capture:
    """Render `scene`'s camera at each configuration of `q` of the true body `tree` (bent by
    `elastic`), detect every plate and measure its origin by PnP: `Capture`. A plate not
    found in a frame is unmeasured there; the covariances carry the corner noise pooled over
    every detection (each frame's own estimate, from a dozen corners, varies by a fifth)."""
    camera = next(iter(scene.cameras.values()))
    tips_of = [p.link.removeprefix("tip:") for p in scene.plates]  # tree_scene's bodies
    links, on = len(tree.link_names), [tree.tip_names.index(t) for t in tips_of]
    bodies = np.asarray(_bodies(tree, elastic, jnp.asarray(q, jnp.float64)))
    cam_body = links + tree.tip_names.index(camera.mount.removeprefix("tip:"))
    n, tips = len(q), len(tree.tip_names)
    points, truth = np.zeros((n, tips, 3)), np.zeros((n, tips, 3))
    cov, measured = np.tile(np.eye(3), (n, tips, 1, 1)), np.zeros((n, tips), bool)
    scales, residual, dof = np.ones((n, tips)), 0.0, 0
    with progress(show_progress, f"filming the hands at {n} poses") as bar:
        task = bar.add_task("film", total=n) if bar is not None else None
        for i in range(n):
            scene.set_poses(bodies[i])
            image = cv2.cvtColor(scene.render(camera.name), cv2.COLOR_RGB2GRAY)
            T_cam = bodies[i, cam_body] @ np.asarray(camera.T_mount_cam)
            for plate, t in zip(scene.plates, on):
                truth[i, t] = (np.linalg.inv(T_cam) @ bodies[i, links + t] @ plate.T_link_target)[:3, 3]
                est = _measure(scene, camera, image, plate)
                if est is not None:
                    measured[i, t], points[i, t] = True, est.T_cam_target[:3, 3]
                    cov[i, t], scales[i, t] = est.cov[:3, :3], est.sigma_px
                    residual += est.rms_px**2 * est.n_points
                    dof += 2 * est.n_points - 6
            if bar is not None:
                bar.update(task, advance=1)
    sigma_px = float(np.sqrt(residual / max(dof, 1)))
    cov = cov * (sigma_px / scales)[..., None, None] ** 2
    seen = {tip: int(measured[:, t].sum()) for tip, t in zip(tips_of, on)}
    keep = measured.any(axis=1)
    samples = TreeSamples(q[keep], points[keep], measured[keep], truth[keep], cov[keep])
    return Capture(samples, dict(zip(tips_of, scene.plates)), sigma_px, seen)


@dataclass(frozen=True)
class FilmedBody:
    """`film_upper_body`'s capture: the robot file's tree `nominal` (tips: both hands and the
    camera) and its `limits`, the drawn body (`true`, bent by `elastic`), the `capture` and
    the plates' drawn origins on the tips (`points`, the camera's tip: zeros), for
    `calibrate_tree(nominal, capture.samples, points=points, device_on=CAMERA_TIP)`."""

    nominal: KinematicTree
    limits: np.ndarray
    true: KinematicTree
    elastic: Elastic
    capture: Capture
    points: np.ndarray


def film_upper_body(
    poses: int, *, seed: int = 0, mount_mm: float = 2.0, show_progress: bool = True
) -> FilmedBody:
    """The synthetic upper body (`jaxcal.sim.humanoid`) drawn from `seed` (its geometry and
    compliances), a plate on each hand mounted `mount_mm` (per axis) off its drawing, filmed by
    the head camera at `poses` stop-and-shoot poses where both plates are in view."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "upper_body.urdf"
        path.write_text(upper_body_urdf())
        nominal = load_urdf_tree(path, tips=[*HANDS, CAMERA_TIP])
        limits = actuated_limits(path, nominal)
    rng = np.random.default_rng(seed)
    true, elastic = perturb_tree(nominal, rng), elastic_truth(nominal, rng)
    drawn = [hand_plate(hand, 10 * k) for k, hand in enumerate(HANDS)]
    mounted = []
    for plate in drawn:
        T = plate.T_link_target.copy()
        T[:3, 3] += 1e-3 * mount_mm * rng.standard_normal(3)
        mounted.append(PlateSpec(plate.target, plate.link, T))
    candidates = reaching_poses(nominal, limits, 150 * poses, rng)
    q = poses_in_view(nominal, candidates, drawn, poses)
    with tree_scene(true, mounted) as scene:
        capture = film_hands(scene, true, q, elastic, show_progress=show_progress)
    points = np.array([p.T_link_target[:3, 3] for p in drawn] + [[0.0, 0.0, 0.0]])
    return FilmedBody(nominal, limits, true, elastic, capture, points)


def simulate_head_camera(
    out,
    *,
    poses: int = 200,
    test_poses: int = 50,
    seed: int = 0,
    overwrite: bool = False,
    show_progress: bool = True,
) -> Path:
    """A tree dataset (`jaxcal.io.tree_dataset`) of the upper body's head camera filming both
    hands: `film_upper_body` at `poses` poses, each plate's origin with its PnP covariance
    (`TIP.cov_xx` ... columns), the device on the camera's tip. `truth.json` holds the drawn
    compliances and `test_poses` more filmed poses with the plates' noise-free origins (camera
    frame), to judge a calibration."""
    body = film_upper_body(poses + test_poses, seed=seed, show_progress=show_progress)
    samples, tips = body.capture.samples, body.nominal.tip_names
    fit, test = samples.subset(slice(0, poses)), samples.subset(slice(poses, None))
    truth = {
        "compliance_rad_per_Nm": dict(zip(body.nominal.joint_names, np.asarray(body.elastic.joint).tolist())),
        "lateral_compliance_rad_per_Nm": dict(
            zip(body.nominal.joint_names, np.asarray(body.elastic.lateral).tolist())
        ),
        "corner_noise_px": body.capture.sigma_px,
        "test": {"q": test.q.tolist(), "points_m": test.truth.tolist()},
    }
    return write_tree_dataset(
        out,
        urdf_text=upper_body_urdf(),
        tips=list(tips),
        samples=dataclasses.replace(fit, truth=None),
        tree=body.nominal,
        noise_mm=None,
        points=body.points,
        truth=truth,
        device_on=CAMERA_TIP,
        overwrite=overwrite,
    )
