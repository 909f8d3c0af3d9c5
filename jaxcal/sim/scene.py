"""A MuJoCo scene built from a jaxcal `KinematicModel`: arm, marker plates, cameras.

Every joint becomes a body whose frame is the model's joint frame
(`T_parent_joint`) and whose hinge/slide axis is the model's axis, so
MuJoCo's kinematics are the model's exactly (the tests check it to 1e-9).
MuJoCo's joint position is the angle the joint really stands at,
$\\theta = q + \\delta$ (`jaxcal.joint_angles`). Links are drawn as capsules
between consecutive joint origins; plates carry the OpenCV-generated texture
of their `TargetSpec` on a quad whose vertices and texture coordinates are
placed from the spec's own frame, so what is printed is what PnP assumes.

Cameras use OpenCV's convention ($z$ forward, $y$ down; MuJoCo's cameras look
down $-z$ with $y$ up, hence a fixed flip). Intrinsics follow from MuJoCo's
vertical field of view and the resolution with square pixels:
$f = (H/2) / \\tan(\\mathrm{fovy}/2)$, and principal point
$c = ((W-1)/2, (H-1)/2)$ because OpenGL puts pixel $i$'s centre at $i + 1/2$
where OpenCV puts it at $i$. Lens distortion (OpenCV's model) is applied to
the rendered image afterwards, as a sensor sees a lens's image: the scene is
rendered `SUPERSAMPLE` times finer, warped there (each fine pixel of the
distorted image takes the ideal image's value where the lens maps it from,
interpolated bilinearly), and averaged over each pixel's area. Warping the
image at its own resolution instead interpolates the renderer's already
sampled edges a fraction of a pixel off its grid: the corners a detector finds
then err alike in neighbouring frames (the error follows the distortion map's
sub-pixel phase, not the noise), which the calibration reads as geometry
(measured in docs/performance.md, "Lens distortion given").
"""

from dataclasses import dataclass, field

import numpy as np

from ..markers import TargetSpec
from ._gl import no_backend_error, select_backend

select_backend()
import cv2  # noqa: E402
import mujoco  # noqa: E402

_CV_FROM_MJ = np.diag([1.0, -1.0, -1.0])  # camera axes: OpenCV (x right, y down, z forward) vs MuJoCo
#: How much finer a camera with lens distortion is rendered before the warp (per axis).
SUPERSAMPLE = 2


def mujoco_quat(R) -> np.ndarray:
    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(R, dtype=np.float64).ravel())
    return q


def placement(T) -> dict:
    """A body's `pos` and `quat` keywords (MjSpec) for the pose `T` (4x4) in its parent."""
    T = np.asarray(T, np.float64)
    return {"pos": T[:3, 3].copy(), "quat": mujoco_quat(T[:3, :3])}


@dataclass(frozen=True, eq=False)
class CameraSpec:
    """A pinhole camera. `T_mount_cam` places it (OpenCV axes) in `mount`'s frame:
    `"world"` for a fixed camera, or a link name (e.g. the flange) for eye-in-hand.

    `distortion`: OpenCV's (k1, k2, p1, p2, k3), applied to the rendered image,
    rendered `lens_supersample` times finer for the warp (1: warped at its own resolution).
    `pixel_supersample`: without a lens, the image is rendered that many times finer and
    averaged over each pixel's area, as a sensor integrates light; MuJoCo samples the
    texture at each pixel's centre, which moves the corners of squares a few pixels wide.
    """

    name: str = "cam0"
    width: int = 640
    height: int = 480
    fovy_deg: float = 50.0
    T_mount_cam: np.ndarray = field(default_factory=lambda: np.eye(4))
    mount: str = "world"
    distortion: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)
    lens_supersample: int = SUPERSAMPLE
    pixel_supersample: int = 1

    @property
    def K(self) -> np.ndarray:
        """Intrinsic matrix (px), OpenCV pixel-centre convention."""
        f = 0.5 * self.height / np.tan(0.5 * np.deg2rad(self.fovy_deg))
        return np.array(
            [[f, 0.0, 0.5 * (self.width - 1)], [0.0, f, 0.5 * (self.height - 1)], [0.0, 0.0, 1.0]]
        )

    @property
    def dist(self) -> np.ndarray:
        return np.asarray(self.distortion, np.float64)

    @property
    def supersample(self) -> int:
        """How much finer the renderer draws this camera (`lens_supersample` with distortion, else
        `pixel_supersample`)."""
        return int(self.lens_supersample) if self.lens else int(self.pixel_supersample)

    @property
    def lens(self) -> bool:
        """The rendered image is warped by a lens distortion."""
        return bool(np.any(self.dist != 0))


@dataclass(frozen=True, eq=False)
class PlateSpec:
    """A target printed on a plate fixed to `link` (a link name of the model, or `"world"`)."""

    target: TargetSpec
    link: str
    T_link_target: np.ndarray


class Scene:
    """The compiled MuJoCo model of one arm with its plates and cameras.

    `set_angles(theta)` poses the arm (true joint angles, rad / m);
    `render(camera)` returns an RGB image (H, W, 3) uint8 of that camera;
    `body_pose(name)` / `camera_pose(name)` read MuJoCo's world poses.
    """

    def __init__(self, spec, plates, cameras, link_names, joint_names):
        self.spec = spec
        self.model = spec.compile()
        self.data = mujoco.MjData(self.model)
        self.plates = tuple(plates)
        self.cameras = {c.name: c for c in cameras}
        self.link_names = tuple(link_names)
        self.joint_names = tuple(joint_names)
        self._qpos = np.array([self.model.joint(n).qposadr[0] for n in joint_names], dtype=int)
        self._renderers: dict = {}
        self.shadows = self.model.vis.quality.shadowsize > 0
        self._undistort_maps: dict = {}
        mujoco.mj_forward(self.model, self.data)

    def set_angles(self, theta) -> None:
        self.data.qpos[self._qpos] = np.asarray(theta, np.float64)
        mujoco.mj_kinematics(self.model, self.data)
        mujoco.mj_camlight(self.model, self.data)

    def set_poses(self, poses) -> None:
        """Place a `mocap_scene`'s bodies at `poses` `(bodies, 4, 4)` (world frame, in
        `link_names`' order)."""
        for name, T in zip(self.link_names, np.asarray(poses, np.float64)):
            k = self.model.body(name).mocapid[0]
            self.data.mocap_pos[k], self.data.mocap_quat[k] = T[:3, 3], mujoco_quat(T[:3, :3])
        mujoco.mj_kinematics(self.model, self.data)
        mujoco.mj_camlight(self.model, self.data)

    def body_pose(self, name: str) -> np.ndarray:
        body = self.data.body(name)
        T = np.eye(4)
        T[:3, :3] = body.xmat.reshape(3, 3)
        T[:3, 3] = body.xpos
        return T

    def camera_pose(self, name: str) -> np.ndarray:
        """`T_world_cam` of camera `name`, OpenCV axes."""
        cam = self.data.camera(name)
        T = np.eye(4)
        T[:3, :3] = cam.xmat.reshape(3, 3) @ _CV_FROM_MJ
        T[:3, 3] = cam.xpos
        return T

    def _renderer(self, cam: CameraSpec):
        key = (cam.supersample * cam.height, cam.supersample * cam.width)
        if key not in self._renderers:
            try:
                r = mujoco.Renderer(self.model, height=key[0], width=key[1])
            except Exception as e:  # the GL backends raise assorted types
                raise no_backend_error(e) from e
            r.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = self.shadows
            r.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = self.shadows
            self._renderers[key] = r
        return self._renderers[key]

    def _distortion_map(self, cam: CameraSpec):
        if cam.name not in self._undistort_maps:
            # For every fine pixel of the distorted image, where it comes from in the fine ideal one:
            # fine pixel j's centre is at (j + 1/2) / s - 1/2 in the image's pixels, and back.
            s = cam.supersample
            u, v = np.meshgrid(
                (np.arange(s * cam.width, dtype=np.float64) + 0.5) / s - 0.5,
                (np.arange(s * cam.height, dtype=np.float64) + 0.5) / s - 0.5,
            )
            pts = np.stack([u.ravel(), v.ravel()], axis=1)[:, None, :]
            ideal = cv2.undistortPointsIter(
                pts,
                cam.K,
                cam.dist,
                R=None,
                P=cam.K,
                criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-6),
            )
            ideal = (s * (ideal.reshape(s * cam.height, s * cam.width, 2) + 0.5) - 0.5).astype(np.float32)
            self._undistort_maps[cam.name] = (ideal[..., 0].copy(), ideal[..., 1].copy())
        return self._undistort_maps[cam.name]

    def render(self, camera: str, rows: tuple[int, int] | None = None) -> np.ndarray:
        """Camera `camera`'s RGB image (H, W, 3), or only its rows `rows = (first, stop)`.

        A band of rows of a camera without lens distortion is rendered on its own: the
        frustum's top and bottom are moved to the band's edges and a viewport of its
        height is drawn (square pixels keep the horizontal extent), which a rolling
        shutter's many renders per frame need. It equals the full image's rows to the
        rasteriser's rounding. With distortion, supersampled (or where the renderer hides its GL
        contexts) the full image is drawn and sliced."""
        cam = self.cameras[camera]
        r = self._renderer(cam)
        r.update_scene(self.data, camera=camera)
        if rows is not None:
            first, stop = int(rows[0]), int(rows[1])
            if not 0 <= first < stop <= cam.height:
                raise ValueError(f"rows {rows} are not a band of camera {camera!r}'s {cam.height} rows")
            if cam.supersample == 1 and (first, stop) != (0, cam.height):
                band = _render_band(r, first, stop, cam.height)
                if band is not None:
                    return band
        image = r.render()
        if cam.lens:
            mx, my = self._distortion_map(cam)
            image = cv2.remap(image, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        if cam.supersample > 1:
            image = cv2.resize(image, (cam.width, cam.height), interpolation=cv2.INTER_AREA)
        return image if rows is None else image[first:stop]

    def close(self) -> None:
        for r in self._renderers.values():
            r.close()
        self._renderers.clear()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _render_band(r, first: int, stop: int, height: int) -> np.ndarray | None:
    """Rows `first:stop` of the `height`-row image of renderer `r` (its scene updated),
    drawn alone; `None` where the renderer does not expose its GL contexts."""
    context, gl = getattr(r, "_mjr_context", None), getattr(r, "_gl_context", None)
    if context is None:
        return None
    if gl is not None:
        gl.make_current()
    scene = r.scene
    rows = stop - first
    saved = [(c.frustum_bottom, c.frustum_top) for c in scene.camera]
    try:
        for c, (bottom, top) in zip(scene.camera, saved):
            pitch = (top - bottom) / height  # a row's height on the near plane
            c.frustum_top, c.frustum_bottom = top - first * pitch, top - stop * pitch
        rect = mujoco.MjrRect(0, 0, r.width, rows)
        mujoco.mjr_render(rect, scene, context)
        band = np.empty((rows, r.width, 3), np.uint8)
        mujoco.mjr_readPixels(band, None, rect, context)
    finally:
        for c, (bottom, top) in zip(scene.camera, saved):
            c.frustum_bottom, c.frustum_top = bottom, top
    return band[::-1]  # OpenGL's rows run bottom-up


# --------------------------------------------------------------------------- building


def add_plate(spec, parent, plate: PlateSpec, index: int) -> None:
    """Add `plate`'s textured face (its `TargetSpec.image()`) and a backing board to body `parent` of `spec`."""
    target = plate.target
    image, corners = target.image()
    rgb = np.ascontiguousarray(np.repeat(image[:, :, None], 3, axis=2))
    tex_name, mat_name, mesh_name = f"tex_plate{index}", f"mat_plate{index}", f"mesh_plate{index}"
    tex = spec.add_texture(
        name=tex_name,
        type=mujoco.mjtTexture.mjTEXTURE_2D,
        width=image.shape[1],
        height=image.shape[0],
        nchannel=3,
    )
    tex.data = rgb.tobytes()
    mat = spec.add_material(name=mat_name)
    mat.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = tex_name
    mat.emission, mat.specular, mat.shininess = 1.0, 0.0, 0.0
    # Quad: corners TL, TR, BR, BL with texture coordinates (s, t) = (u, v) / size,
    # row 0 of the texture at t = 0. Both windings, so either side shows it.
    uv = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    faces = np.array([[0, 1, 2], [0, 2, 3], [0, 2, 1], [0, 3, 2]])
    mesh = spec.add_mesh(
        name=mesh_name,
        uservert=corners.ravel().tolist(),
        usertexcoord=uv.ravel().tolist(),
        userface=faces.ravel().tolist(),
        userfacetexcoord=faces.ravel().tolist(),
    )
    mesh.inertia = mujoco.mjtMeshInertia.mjMESH_INERTIA_SHELL
    body = parent.add_body(name=f"plate:{target.name}", **placement(plate.T_link_target))
    body.explicitinertial = True
    body.mass, body.inertia = 0.05, [1e-5, 1e-5, 1e-5]
    body.add_geom(
        name=f"plate:{target.name}:face",
        type=mujoco.mjtGeom.mjGEOM_MESH,
        meshname=mesh_name,
        material=mat_name,
        contype=0,
        conaffinity=0,
    )
    # A backing board just behind the printed face.
    normal = target.front_normal()
    centre = corners.mean(axis=0) - normal * 0.004
    half = 0.5 * np.array(
        [np.linalg.norm(corners[1] - corners[0]), np.linalg.norm(corners[3] - corners[0]), 0.006]
    )
    right, down = (corners[1] - corners[0]) / (2 * half[0]), (corners[3] - corners[0]) / (2 * half[1])
    R = np.stack([right, down, np.cross(right, down)], axis=1)
    body.add_geom(
        name=f"plate:{target.name}:back",
        type=mujoco.mjtGeom.mjGEOM_BOX,
        size=half.tolist(),
        pos=centre,
        quat=mujoco_quat(R),
        rgba=[0.25, 0.25, 0.28, 1.0],
        contype=0,
        conaffinity=0,
    )


def _add_link_geometry(
    body, offset: np.ndarray, axis: np.ndarray | None, radius: float, rgba, capsule: bool = True
) -> None:
    """A capsule (or cylinder) from the body origin to its child's origin, and a joint drum along the axis."""
    length = float(np.linalg.norm(offset))
    if length > 1e-6:
        body.add_geom(
            type=mujoco.mjtGeom.mjGEOM_CAPSULE if capsule else mujoco.mjtGeom.mjGEOM_CYLINDER,
            fromto=[0.0, 0.0, 0.0, *offset.tolist()],
            size=[radius, 0.0, 0.0],
            rgba=rgba,
            contype=0,
            conaffinity=0,
        )
    if axis is not None:
        z = axis / np.linalg.norm(axis)
        body.add_geom(
            type=mujoco.mjtGeom.mjGEOM_CYLINDER,
            fromto=[*(-1.2 * radius * z).tolist(), *(1.2 * radius * z).tolist()],
            size=[1.15 * radius, 0.0, 0.0],
            rgba=[0.15, 0.3, 0.55, 1.0],
            contype=0,
            conaffinity=0,
        )


def build_scene(
    model,
    *,
    plates=(),
    cameras=(CameraSpec(),),
    T_world_base=None,
    link_radius: float = 0.035,
    floor_z: float | None = None,
    shadows: bool = False,
) -> Scene:
    """Build the MuJoCo scene of `model` (a `KinematicModel`) with `plates` and `cameras`.

    **Arguments:**
    - `model`: the arm as it really is (the truth, in simulations).
    - `plates`: `PlateSpec`s; `link` names one of `model.link_names` or `"world"`.
    - `cameras`: `CameraSpec`s; `mount` is `"world"` or a link name.
    - `T_world_base`: the base's pose in the world (default identity).
    - `floor_z`: height of a grey floor plane (none if `None`).
    - `shadows`: cast shadows (MuJoCo's default look; several times slower on a CPU).
    """
    links, joints = tuple(model.link_names), tuple(model.joint_names)
    for p in plates:
        if p.link != "world" and p.link not in links:
            raise ValueError(f"plate {p.target.name!r}: unknown link {p.link!r}; links are {links}")
    for c in cameras:
        if c.mount != "world" and c.mount not in links:
            raise ValueError(f"camera {c.name!r}: unknown mount {c.mount!r}; use 'world' or one of {links}")
    names = [c.name for c in cameras] + [p.target.name for p in plates]
    if len(set(names)) != len(names):
        raise ValueError(f"camera and target names must be unique, got {names}")

    spec = _environment(cameras, floor_z, shadows)
    bodies = add_arm(spec.worldbody, model, T_world_base, link_radius)

    _mount(spec, bodies, plates, cameras)
    return Scene(spec, plates, cameras, links, joints)


def _mount(spec, bodies: dict, plates, cameras) -> None:
    """The plates and cameras on their bodies (`bodies`: by name)."""
    for i, plate in enumerate(plates):
        add_plate(spec, bodies[plate.link], plate, i)
    for cam in cameras:
        T = np.asarray(cam.T_mount_cam, np.float64)
        bodies[cam.mount].add_camera(
            name=cam.name, pos=T[:3, 3], quat=mujoco_quat(T[:3, :3] @ _CV_FROM_MJ), fovy=float(cam.fovy_deg)
        )


def mocap_scene(links: dict, plates=(), cameras=(CameraSpec(),), link_radius: float = 0.02) -> Scene:
    """A scene of free bodies posed directly (MuJoCo mocap bodies; `Scene.set_poses`), for a
    body no chain of hinges describes (a tree bent by gravity: a link's lateral bend is no
    joint). `links` maps each body's name to the offsets (m, its own frame) its capsules run to
    from its origin; `plates` and `cameras` mount on the bodies by name."""
    spec = _environment(cameras, None, False)
    bodies = {"world": spec.worldbody}
    grey = ([0.78, 0.78, 0.8, 1.0], [0.62, 0.64, 0.68, 1.0])
    for k, (name, offsets) in enumerate(links.items()):
        bodies[name] = spec.worldbody.add_body(name=name, mocap=True)
        for offset in offsets:
            _add_link_geometry(bodies[name], np.asarray(offset, np.float64), None, link_radius, grey[k % 2])
    _mount(spec, bodies, plates, cameras)
    return Scene(spec, plates, cameras, tuple(links), ())


def _environment(cameras, floor_z: float | None, shadows: bool) -> "mujoco.MjSpec":
    """A scene's spec with its off-screen buffer, light, sky and floor (`build_scene`)."""
    spec = mujoco.MjSpec()
    spec.modelname = "jaxcal_scene"
    width = max(c.supersample * c.width for c in cameras) if cameras else 640
    height = max(c.supersample * c.height for c in cameras) if cameras else 480
    spec.visual.global_.offwidth, spec.visual.global_.offheight = int(width), int(height)
    spec.visual.headlight.ambient = [0.45, 0.45, 0.45]
    spec.visual.headlight.diffuse = [0.5, 0.5, 0.5]
    if not shadows:
        spec.visual.quality.shadowsize = 0
    sky = spec.add_texture(
        name="sky",
        type=mujoco.mjtTexture.mjTEXTURE_SKYBOX,
        builtin=mujoco.mjtBuiltin.mjBUILTIN_GRADIENT,
        rgb1=[0.75, 0.82, 0.9],
        rgb2=[0.25, 0.3, 0.38],
        width=256,
        height=256,
    )
    del sky
    world = spec.worldbody
    if floor_z is not None:
        world.add_geom(
            type=mujoco.mjtGeom.mjGEOM_PLANE,
            pos=[0.0, 0.0, floor_z],
            size=[3.0, 3.0, 0.1],
            rgba=[0.55, 0.57, 0.6, 1.0],
            contype=0,
            conaffinity=0,
        )
    world.add_light(pos=[0.0, 0.0, 3.0], dir=[0.0, 0.0, -1.0], diffuse=[0.5, 0.5, 0.5], castshadow=shadows)
    return spec


def add_arm(world, model, T_world_base, link_radius: float) -> dict:
    """The arm's bodies under `world` (base, links, flange), by link name (and `"world"`)."""
    links, joints = tuple(model.link_names), tuple(model.joint_names)
    T_parent_joint = np.asarray(model.T_parent_joint, np.float64)
    axes = np.asarray(model.axis, np.float64)
    T_last_flange = np.asarray(model.T_last_flange, np.float64)
    n = len(joints)
    base = world.add_body(name=links[0], **placement(np.eye(4) if T_world_base is None else T_world_base))
    bodies = {links[0]: base}
    grey = [[0.78, 0.78, 0.8, 1.0], [0.62, 0.64, 0.68, 1.0]]
    _add_link_geometry(base, T_parent_joint[0][:3, 3], None, 1.6 * link_radius, grey[1])
    parent = base
    for i in range(n):
        body = parent.add_body(name=links[i + 1], **placement(T_parent_joint[i]))
        body.explicitinertial = True
        body.mass, body.inertia = 1.0, [1e-3, 1e-3, 1e-3]
        kind = (
            mujoco.mjtJoint.mjJNT_HINGE if model.joint_types[i] == "revolute" else mujoco.mjtJoint.mjJNT_SLIDE
        )
        body.add_joint(
            name=joints[i],
            type=kind,
            axis=axes[i].tolist(),
        )
        child = T_parent_joint[i + 1][:3, 3] if i + 1 < n else T_last_flange[:3, 3]
        _add_link_geometry(body, child, axes[i], link_radius, grey[i % 2], capsule=i + 1 < n)
        bodies[links[i + 1]] = body
        parent = body
    flange = parent.add_body(name=links[-1], **placement(T_last_flange))
    flange.explicitinertial = True
    flange.mass, flange.inertia = 0.1, [1e-4, 1e-4, 1e-4]
    flange.add_geom(
        type=mujoco.mjtGeom.mjGEOM_CYLINDER,
        fromto=[0.0, 0.0, -0.008, 0.0, 0.0, 0.0],
        size=[0.04, 0.0, 0.0],
        rgba=[0.3, 0.3, 0.3, 1.0],
        contype=0,
        conaffinity=0,
    )
    bodies[links[-1]] = flange
    bodies["world"] = world
    return bodies
