"""The planning scene in JAX: what a frame looks like before it is taken, and how feasible it is.

Everything here is a pure function of the commanded configuration $q$ of one
frame, differentiable, so that the planner can optimise poses by gradient with
the feasibility checks as penalties.

The arm is the collision geometry `jaxcal.sim` renders (capsules between
consecutive joint origins, a drum along each joint axis, the flange disk, the
plate's backing board), each drawn here as a capsule (a segment and a radius)
in its link's frame. A frame is checked by named *margins*, positive when it
passes (the checks of `CHECKS`):

| check            | margin                                                                       | unit |
| ---------------- | ---------------------------------------------------------------------------- | ---- |
| `joint_limits`   | distance of every joint to its URDF limits, less `joint_margin`              | rad  |
| `self_collision` | clearance between capsules of bodies that are not parent and child, less `clearance` | m |
| `scene_collision`| height above the floor of every capsule end the joints can lower (`floor_checked`), less `clearance` | m |
| `in_image`       | distance of every corner to the image border, less `margin_px`               | px   |
| `occlusion`      | clearance between the line of sight to every corner and the arm               | m    |
| `view_angle`     | $\\cos\\alpha - \\cos\\alpha_{max}$, $\\alpha$ between the plate normal and the line of sight | 1 |
| `corner_spacing` | shortest image distance between neighbouring corners, less `min_corner_px`   | px   |
| `distance`       | camera-to-plate distance inside `[min_distance, max_distance]`               | m    |
"""

from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._geometry import pose_inverse, safe_norm
from .._kinematics import REVOLUTE, KinematicModel, forward_kinematics
from .._reprojection import project

#: The named checks of a frame, in the order a rejection reports the first failure.
CHECKS = (
    "joint_limits",
    "self_collision",
    "scene_collision",
    "distance",
    "view_angle",
    "in_image",
    "corner_spacing",
    "occlusion",
)
#: Link radius of the rendered arm (`jaxcal.sim.scene.build_scene`'s default), m.
LINK_RADIUS = 0.035


@dataclass(frozen=True)
class FeasibilityLimits:
    """The limits a frame must meet (defaults: a 1280x960 camera about a metre away).

    - `view_angle_deg`: largest angle between the plate's normal and the line of sight.
    - `margin_px`: every corner at least this far inside the image.
    - `min_corner_px`: neighbouring corners at least this far apart in the image
      (the ChArUco refinement window needs a white gap of 2 px, a quarter of a
      40 mm square with 30 mm markers: 16 px).
    - `min_distance`, `max_distance`: camera-to-plate range, m.
    - `clearance`: collision clearance, m; `joint_margin`: distance from the joint limits, rad.
    """

    view_angle_deg: float = 60.0
    margin_px: float = 20.0
    min_corner_px: float = 16.0
    min_distance: float = 0.3
    max_distance: float = 2.0
    clearance: float = 0.01
    joint_margin: float = 0.02

    def to_dict(self) -> dict:
        return {k: float(getattr(self, k)) for k in self.__dataclass_fields__}


#: Scale of each margin in the optimiser's penalty (a margin of minus one scale costs 1).
PENALTY_SCALES = {
    "joint_limits": 0.05,
    "self_collision": 0.01,
    "scene_collision": 0.01,
    "distance": 0.02,
    "view_angle": 0.05,
    "in_image": 10.0,
    "corner_spacing": 2.0,
    "occlusion": 0.01,
}


class Capsules(eqx.Module):
    """Collision capsules: segment `a`-`b` (m, in the frame of body `body`) and `radius`.

    Bodies: 0 the base, `i + 1` the child link of joint `i`, `joints + 1` the
    flange, `joints + 2` the flange's payload (the plate eye-to-hand, the camera
    eye-in-hand).
    """

    body: Int[Array, " c"]
    a: Float[Array, "c 3"]
    b: Float[Array, "c 3"]
    radius: Float[Array, " c"]


class PlanScene(eqx.Module):
    """Everything a frame's feasibility and its corners depend on, at the nominal robot.

    - `nominal`: the robot; `lower`, `upper`: commanded joint limits (rad; inf without).
    - `T_fixed`: eye-to-hand $T_{cam,base}$; eye-in-hand $T_{board,base}$ (the
      refinement's fixed frame).
    - `T_mount`: eye-to-hand $T_{flange,target}$; eye-in-hand $T_{flange,cam}$.
    - `K`, `dist`, `image` (width, height): the camera.
    - `points` `(N, 3)`: the target's corners (target frame); `edges` `(E, 2)`:
      pairs of neighbouring corners; `normal`: the printed face's normal (target frame).
    - `capsules`, `pairs` `(P, 2)` (capsules that may collide), `occluders`
      (capsules that may hide the target), `floor_z` (m, `-inf` for none),
      `floor_check` `(c, 2)`: which capsule ends (`a`, `b`) the joints can move
      up or down (`floor_checked`), the ends checked against the floor.
    - `eye_in_hand`: the camera rides on the flange (static).
    """

    nominal: KinematicModel
    lower: Float[Array, " joints"]
    upper: Float[Array, " joints"]
    T_fixed: Float[Array, "4 4"]
    T_mount: Float[Array, "4 4"]
    K: Float[Array, "3 3"]
    dist: Float[Array, "5"]
    image: Float[Array, "2"]
    points: Float[Array, "N 3"]
    edges: Int[Array, "E 2"]
    normal: Float[Array, "3"]
    capsules: Capsules
    pairs: Int[Array, "P 2"]
    occluders: Int[Array, " O"]
    floor_z: Float[Array, ""]
    floor_check: Bool[Array, "c 2"]
    eye_in_hand: bool = eqx.field(static=True, default=False)


def plate_box(spec) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
    """The printed plate in its target frame: centre of the backing board (4 mm
    behind the face, as rendered), unit right and down directions, width and
    height with the margin (m)."""
    top_left, right, down = spec.pattern_extent()
    w, h = spec.pattern_size
    m = spec.margin
    centre = top_left + 0.5 * w * right + 0.5 * h * down - 0.004 * spec.front_normal()
    return centre, right, down, w + 2 * m, h + 2 * m


def arm_capsules(model: KinematicModel, plate=None) -> tuple[Capsules, np.ndarray]:
    """The rendered arm's geometry as capsules, and which bodies may hide the target.

    Mirrors `jaxcal.sim.scene.build_scene`: a capsule (cylinder for the last
    link) of radius `LINK_RADIUS` from each body's origin to its child's, a drum
    of radius 1.15 r and half-length 1.2 r along each joint axis, the base's
    column (1.6 r), the flange disk; with `plate` (`plate_box`) the plate's
    backing board on the payload body as three capsules along its longer side.
    Cylinders become capsules (a little larger at their ends: conservative).

    **Returns:** `(capsules, occluder mask)`: the flange disk, the last link
    and the payload lie behind a visible plate and are not occluders.
    """
    n = model.num_joints
    r = LINK_RADIUS
    T_p = np.asarray(model.T_parent_joint)
    axes = np.asarray(model.axis)
    rows = []  # (body, a, b, radius, occluder)
    if np.linalg.norm(T_p[0][:3, 3]) > 1e-6:
        rows.append((0, np.zeros(3), T_p[0][:3, 3], 1.6 * r, True))
    for i in range(n):
        child = T_p[i + 1][:3, 3] if i + 1 < n else np.asarray(model.T_last_flange)[:3, 3]
        if np.linalg.norm(child) > 1e-6:
            rows.append((i + 1, np.zeros(3), child, r, i + 1 < n))
        z = axes[i] / np.linalg.norm(axes[i])
        rows.append((i + 1, -1.2 * r * z, 1.2 * r * z, 1.15 * r, i + 1 < n))
    rows.append((n + 1, np.array([0.0, 0.0, -0.008]), np.zeros(3), 0.04, False))
    if plate is not None:
        c, right, down, w, h = plate
        if h > w:
            right, down, w, h = down, right, h, w
        for y in (-h / 3, 0.0, h / 3):  # three rows of radius h/6 spanning the width: the corners covered
            rows.append((n + 2, c + y * down - 0.5 * w * right, c + y * down + 0.5 * w * right, h / 6, False))
    body, a, b, radius, occ = zip(*rows)
    caps = Capsules(
        body=jnp.asarray(np.array(body)),
        a=jnp.asarray(np.stack(a)),
        b=jnp.asarray(np.stack(b)),
        radius=jnp.asarray(np.array(radius)),
    )
    return caps, np.array(occ)


def collision_pairs(body: np.ndarray, num_joints: int) -> np.ndarray:
    """Pairs of capsules that may touch: on different bodies that are not parent
    and child (MuJoCo's default filter), not both on the rigid end (last link,
    flange, payload); `make_scene` then leaves out the pairs that always touch."""
    parent = {k: k - 1 for k in range(1, num_joints + 3)}
    out = []
    for i in range(len(body)):
        for j in range(i + 1, len(body)):
            bi, bj = int(body[i]), int(body[j])
            if bi == bj or parent.get(bi) == bj or parent.get(bj) == bi:
                continue
            if {bi, bj} <= {num_joints, num_joints + 1, num_joints + 2}:
                continue  # the last link, the flange and its payload are one rigid end
            out.append((i, j))
    return np.array(out, dtype=int).reshape(-1, 2)


def pair_clearances(scene: PlanScene, q: Float[Array, " joints"]) -> Float[Array, " P"]:
    """Clearance (m) of every collision pair of `scene` at configuration `q`."""
    g = frame_geometry(scene, q)
    a, b = _capsules_in_base(scene, g.bodies)
    rad = scene.capsules.radius
    i, j = scene.pairs[:, 0], scene.pairs[:, 1]
    return jax.vmap(segment_distance)(a[i], b[i], a[j], b[j]) - rad[i] - rad[j]


#: A pair of capsules touching in more than this share of random configurations is structural
#: (a shoulder whose links start at one point, the drums of a short wrist): left out of the
#: self-collision check, like MoveIt's "default in collision" pairs; no motion avoids it.
ALWAYS = 0.5


def always_touching(scene: PlanScene, samples: int = 1000) -> np.ndarray:
    """Which of `scene.pairs` touch in more than `ALWAYS` of `samples` random
    configurations within the joint limits (seeded), or never move relative to
    each other (their clearance varies by under 0.1 mm: no motion changes it)."""
    lo = jnp.maximum(scene.lower, -jnp.pi)
    hi = jnp.minimum(scene.upper, jnp.pi)
    q = jax.random.uniform(jax.random.key(0), (samples, lo.shape[0]), minval=lo, maxval=hi)
    d = jax.jit(jax.vmap(lambda qq: pair_clearances(scene, qq)))(q)
    rigid = jnp.max(d, axis=0) - jnp.min(d, axis=0) < 1e-4
    return np.asarray((jnp.mean(d < 0.0, axis=0) > ALWAYS) | rigid)


def corner_edges(points: np.ndarray) -> np.ndarray:
    """Pairs of corners at the shortest spacing of the grid (neighbours along rows and columns)."""
    P = np.asarray(points, np.float64)
    d = np.linalg.norm(P[:, None] - P[None], axis=-1)
    d[np.diag_indices(len(P))] = np.inf
    step = d.min()
    i, j = np.nonzero(np.triu(d < 1.01 * step, 1))
    return np.stack([i, j], axis=1)


def segment_distance(p1, q1, p2, q2) -> Float[Array, ""]:
    """Shortest distance between segments $p_1 q_1$ and $p_2 q_2$ (Ericson, Real-Time
    Collision Detection, 5.1.9), with the degenerate cases made safe to differentiate."""
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    a, e, f = d1 @ d1, d2 @ d2, d2 @ r
    c, b = d1 @ r, d1 @ d2
    eps = 1e-12
    denom = a * e - b * b
    s = jnp.where(
        denom > eps * a * e + eps, jnp.clip((b * f - c * e) / jnp.where(denom > 0, denom, 1.0), 0, 1), 0.0
    )
    t = (b * s + f) / jnp.maximum(e, eps)
    s = jnp.where(
        t < 0,
        jnp.clip(-c / jnp.maximum(a, eps), 0, 1),
        jnp.where(t > 1, jnp.clip((b - c) / jnp.maximum(a, eps), 0, 1), s),
    )
    t = jnp.clip(t, 0, 1)
    return safe_norm(p1 + d1 * s - (p2 + d2 * t))


class FrameGeometry(eqx.Module):
    """One frame at the nominal robot: `T_cam_target`, the corners' pixels `(N, 2)`
    and depths `(N,)`, the camera position and corners in the base frame, the body
    frames `(joints + 3, 4, 4)` in the base frame."""

    T_cam_target: Float[Array, "4 4"]
    pixels: Float[Array, "N 2"]
    depth: Float[Array, " N"]
    camera_base: Float[Array, "3"]
    corners_base: Float[Array, "N 3"]
    bodies: Float[Array, "B 4 4"]


def frame_geometry(scene: PlanScene, q: Float[Array, " joints"]) -> FrameGeometry:
    """The camera, the target and the arm at commanded configuration `q`."""
    F = forward_kinematics(scene.nominal, q)
    payload = F[-1] @ scene.T_mount
    bodies = jnp.concatenate([F, payload[None]])
    if scene.eye_in_hand:
        T_base_cam, T_base_target = payload, pose_inverse(scene.T_fixed)
    else:
        T_base_cam, T_base_target = pose_inverse(scene.T_fixed), payload
    T_ct = pose_inverse(T_base_cam) @ T_base_target
    X = scene.points @ T_ct[:3, :3].T + T_ct[:3, 3]
    corners = scene.points @ T_base_target[:3, :3].T + T_base_target[:3, 3]
    return FrameGeometry(
        T_cam_target=T_ct,
        pixels=project(scene.K, scene.dist, X),
        depth=X[:, 2],
        camera_base=T_base_cam[:3, 3],
        corners_base=corners,
        bodies=bodies,
    )


def _capsules_in_base(scene: PlanScene, bodies):
    T = bodies[scene.capsules.body]
    a = jnp.einsum("cij,cj->ci", T[:, :3, :3], scene.capsules.a) + T[:, :3, 3]
    b = jnp.einsum("cij,cj->ci", T[:, :3, :3], scene.capsules.b) + T[:, :3, 3]
    return a, b


def margins(scene: PlanScene, limits: FeasibilityLimits, q: Float[Array, " joints"]) -> dict[str, Array]:
    """Every check's margin at configuration `q` (positive: passes; see the module docstring).

    **Arguments:** the scene; the limits; commanded joint positions `q` (rad).

    **Returns:** a dict `check -> scalar margin` over `CHECKS`.
    """
    g = frame_geometry(scene, q)
    out = {"joint_limits": jnp.min(jnp.minimum(q - scene.lower, scene.upper - q)) - limits.joint_margin}
    a, b = _capsules_in_base(scene, g.bodies)
    rad = scene.capsules.radius
    i, j = scene.pairs[:, 0], scene.pairs[:, 1]
    dist = jax.vmap(segment_distance)(a[i], b[i], a[j], b[j]) - rad[i] - rad[j]
    out["self_collision"] = jnp.min(dist, initial=jnp.inf) - limits.clearance
    out["scene_collision"] = jnp.min(_floor_heights(scene, a, b), initial=jnp.inf) - limits.clearance
    centre = g.T_cam_target[:3, :3] @ jnp.mean(scene.points, 0) + g.T_cam_target[:3, 3]
    d = safe_norm(centre)
    out["distance"] = jnp.minimum(d - limits.min_distance, limits.max_distance - d)
    n = g.T_cam_target[:3, :3] @ scene.normal
    out["view_angle"] = -(n @ centre) / d - jnp.cos(jnp.deg2rad(limits.view_angle_deg))
    u = g.pixels
    m = limits.margin_px
    border = jnp.minimum(
        jnp.minimum(u[:, 0] - m, scene.image[0] - 1.0 - m - u[:, 0]),
        jnp.minimum(u[:, 1] - m, scene.image[1] - 1.0 - m - u[:, 1]),
    )
    out["in_image"] = jnp.min(jnp.where(g.depth > 0.05, border, -1e3))
    e = scene.edges
    out["corner_spacing"] = jnp.min(safe_norm(u[e[:, 0]] - u[e[:, 1]])) - limits.min_corner_px
    # Lines of sight: from the camera to 1 cm short of each corner, against the occluders.
    ray = g.corners_base - g.camera_base
    end = g.corners_base - 0.01 * ray / safe_norm(ray)[:, None]
    oa, ob, orad = a[scene.occluders], b[scene.occluders], rad[scene.occluders]
    seen = jax.vmap(lambda p: jax.vmap(lambda s, t: segment_distance(g.camera_base, p, s, t))(oa, ob))(end)
    out["occlusion"] = jnp.min(seen - orad[None, :])
    return out


#: Tolerance of "on the joint axis" (m) and "parallel / perpendicular to the floor normal" (of unit
#: vectors): a calibrated URDF's tilts of a few 1e-4 rad still keep heights to a fraction of a mm.
_FLOOR_TOL = 1e-3


def _heights_kept(model: KinematicModel) -> np.ndarray:
    """`(joints,)` bool: entry `j` whether joints `0..j` all keep heights (see `floor_checked`)."""
    n = model.num_joints
    F = np.asarray(forward_kinematics(model, jnp.zeros(n)), np.float64)
    axes = np.asarray(model.axis, np.float64)
    keeps = np.zeros(n, bool)
    for j in range(n):
        axis = F[j + 1][:3, :3] @ axes[j] / np.linalg.norm(axes[j])
        # A revolute axis along the floor normal (base z): its sine to it is small; a slide across it: its cosine.
        off = float(np.hypot(axis[0], axis[1])) if model.joint_types[j] == REVOLUTE else abs(float(axis[2]))
        own = off < _FLOOR_TOL
        keeps[j] = own and (j == 0 or keeps[j - 1])
    return keeps


def floor_fixed_links(model: KinematicModel) -> tuple[str, ...]:
    """The links whose height above the floor no joint can change: the base, and
    each joint's child link while every joint up to it keeps heights (turns about
    the floor normal, or slides across it; see `floor_checked`). A floor contact
    of theirs is the robot's mounting, not something a pose could avoid."""
    keeps = _heights_kept(model)
    names = model.link_names
    fixed = [names[0]] + [names[j + 1] for j in range(model.num_joints) if keeps[j]]
    if keeps.all():  # the flange is rigid on the last link
        fixed.append(names[-1])
    return tuple(dict.fromkeys(fixed))


def floor_checked(model: KinematicModel, capsules: Capsules, T_mount) -> np.ndarray:
    """Which capsule ends the joints can move up or down: those checked against the floor.

    The floor is the plane $z$ = `floor_z` of the base frame. A joint *keeps
    heights* when it turns about an axis parallel to the floor normal or slides
    along one perpendicular to it: it moves every point in a horizontal plane and
    keeps vertical axes vertical and horizontal ones horizontal. So when joints
    $0 \\dots j$ all keep heights at one configuration, they do at every
    configuration, and no motion of theirs changes the height of a point fixed to
    the child link of joint $j$ (the base, a shoulder turning about a vertical
    axis, or bodies on a gantry's horizontal slides). A capsule end that lies on
    the axis of the revolute joint that moves its body is not moved by that joint
    either: it counts as a point of the parent body.

    Such ends keep the height they have at the taught pose, whatever the plan:
    where a robot bolted to its table has them below the table top (the base's
    column, the drum of a vertical first joint), no pose could clear them, and
    counting them would reject every pose. They are left out; every other end is
    checked (a capsule's lowest point is one of its ends less the radius).

    **Arguments:** the nominal robot; its `Capsules` (`arm_capsules`); `T_mount`
    `(4, 4)`: the payload body's pose on the flange.

    **Returns:** `(c, 2)` bool, for ends `a` and `b` of each capsule.
    """
    n = model.num_joints
    T_p = np.asarray(model.T_parent_joint, np.float64)
    axes = np.asarray(model.axis, np.float64)
    axes = axes / np.linalg.norm(axes, axis=1, keepdims=True)
    keeps = _heights_kept(model)
    T_last, T_mount = np.asarray(model.T_last_flange, np.float64), np.asarray(T_mount, np.float64)

    def checked(body: int, p: np.ndarray) -> bool:
        p = np.append(p, 1.0)
        if body == n + 2:  # the payload, rigid on the flange
            body, p = n + 1, T_mount @ p
        if body == n + 1:  # the flange, rigid on the last link
            body, p = n, T_last @ p
        while body > 0 and model.joint_types[body - 1] == REVOLUTE:
            if np.linalg.norm(np.cross(p[:3], axes[body - 1])) > _FLOOR_TOL:
                break  # off the axis of the joint that moves this body
            body, p = body - 1, T_p[body - 1] @ p
        return not (body == 0 or keeps[body - 1])

    bodies, a, b = (np.asarray(x) for x in (capsules.body, capsules.a, capsules.b))
    return np.array([[checked(int(k), pa), checked(int(k), pb)] for k, pa, pb in zip(bodies, a, b)])


def _floor_heights(scene: PlanScene, a, b) -> Float[Array, " e"]:
    """Height above the floor (m) of the lowest point at each checked capsule end
    (`scene.floor_check`), from the ends `a`, `b` `(c, 3)` in the base frame."""
    z = jnp.stack([a[:, 2], b[:, 2]], axis=1) - scene.capsules.radius[:, None] - scene.floor_z
    return jnp.where(scene.floor_check, z, jnp.inf).reshape(-1)


def _body_name(scene: PlanScene, body: int) -> str:
    names = scene.nominal.link_names
    if body < len(names):
        return f"link {names[body]!r}"
    return "the camera on the flange" if scene.eye_in_hand else "the plate on the flange"


def explain(scene: PlanScene, limits: FeasibilityLimits, q) -> str | None:
    """Why configuration `q` fails: the first failing check of `CHECKS` and, for the
    joint limits and the collisions, which joint or bodies, and by how much
    (e.g. "scene_collision: link 'wrist_3_link' reaches 0.052 m below the floor at
    z = 0 m (a clearance of 0.01 m is required)"). `None` when `q` passes."""
    q = jnp.asarray(q, jnp.float64)
    m = {k: float(v) for k, v in margins(scene, limits, q).items()}
    failed = [k for k in CHECKS if not m[k] > 0.0]
    if not failed:
        return None
    check = failed[0]
    g = frame_geometry(scene, q)
    a, b = _capsules_in_base(scene, g.bodies)
    body = np.asarray(scene.capsules.body)
    if check == "scene_collision":
        h = np.asarray(_floor_heights(scene, a, b))
        i = int(np.argmin(h)) // 2
        z, floor = float(h.min()), float(scene.floor_z)
        where = f"reaches {abs(z):.3g} m below" if z < 0 else f"is only {z:.3g} m above"
        return (
            f"scene_collision: {_body_name(scene, int(body[i]))} {where} the floor at z = {floor:g} m "
            f"(a clearance of {limits.clearance:g} m is required)"
        )
    if check == "self_collision":
        d = np.asarray(pair_clearances(scene, q))
        i, j = np.asarray(scene.pairs)[int(np.argmin(d))]
        gap = float(d.min())
        how = f"overlap by {-gap:.3g} m" if gap < 0 else f"are only {gap:.3g} m apart"
        return (
            f"self_collision: {_body_name(scene, int(body[i]))} and {_body_name(scene, int(body[j]))} {how} "
            f"(a clearance of {limits.clearance:g} m is required)"
        )
    if check == "joint_limits":
        qn = np.asarray(q)
        lo, hi = np.asarray(scene.lower), np.asarray(scene.upper)
        k = int(np.argmin(np.minimum(qn - lo, hi - qn)))
        return (
            f"joint_limits: joint {scene.nominal.joint_names[k]!r} at {qn[k]:.4g} rad is not inside its "
            f"limits [{lo[k]:.4g}, {hi[k]:.4g}] rad by {limits.joint_margin:g} rad"
        )
    return f"{check}: margin {m[check]:.3g} (see jaxcal.planning's CHECKS)"


def penalty(
    scene: PlanScene, limits: FeasibilityLimits, q: Float[Array, " joints"], buffer: float = 0.5
) -> Array:
    """The optimiser's feasibility penalty of one frame: $\\sum_k \\max(0, b - m_k/s_k)^2$
    over the checks, margins $m_k$ in units of `PENALTY_SCALES` $s_k$, `buffer` $b$
    scales inside the limit (so that an optimised frame passes with room)."""
    m = margins(scene, limits, q)
    return sum(jnp.square(jax.nn.relu(buffer - m[k] / PENALTY_SCALES[k])) for k in CHECKS)


def make_scene(
    nominal: KinematicModel,
    *,
    K,
    dist,
    image: tuple[int, int],
    T_fixed,
    T_mount,
    points,
    normal,
    lower,
    upper,
    eye_in_hand: bool,
    plate=None,
    floor_z: float | None = None,
) -> PlanScene:
    """A `PlanScene` from NumPy inputs (see `PlanScene`; `plate` the plate's
    `plate_box` when it rides on the flange, for its collisions)."""
    caps, occ = arm_capsules(nominal, None if eye_in_hand else plate)
    scene = PlanScene(
        nominal=nominal,
        lower=jnp.asarray(lower, jnp.float64),
        upper=jnp.asarray(upper, jnp.float64),
        T_fixed=jnp.asarray(T_fixed, jnp.float64),
        T_mount=jnp.asarray(T_mount, jnp.float64),
        K=jnp.asarray(K, jnp.float64),
        dist=jnp.asarray(dist, jnp.float64),
        image=jnp.asarray(image, jnp.float64),
        points=jnp.asarray(points, jnp.float64),
        edges=jnp.asarray(corner_edges(points)),
        normal=jnp.asarray(normal, jnp.float64),
        capsules=caps,
        pairs=jnp.asarray(collision_pairs(np.asarray(caps.body), nominal.num_joints)),
        occluders=jnp.asarray(np.flatnonzero(occ)),
        floor_z=jnp.asarray(-np.inf if floor_z is None else float(floor_z)),
        floor_check=jnp.asarray(floor_checked(nominal, caps, T_mount)),
        eye_in_hand=eye_in_hand,
    )
    keep = ~always_touching(scene)
    return eqx.tree_at(lambda s: s.pairs, scene, scene.pairs[keep])
