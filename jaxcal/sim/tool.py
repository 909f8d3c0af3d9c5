"""A MuJoCo scene for the tool-offset calibration (seed 2): a stylus rotated about a preset axis.

World layout (m): a rotary axis (hinge about world $z$) at `axis_xy` and
height `height`; the tool hangs from it shifted so the axis passes through
the current tool-centre estimate `tcp` (the tool frame's $xy$); the stylus
tip (a red sphere) sits at the true offset `tip_xy` in the tool frame,
`stylus_length` below the axis body. A camera below looks straight up the
axis (OpenCV axes: its $z$ is world $+z$), rolled by `camera_roll` about it,
so the tip images on a circle whose radius is the estimate's error. Moving
`axis_xy` moves the stylus sideways for the principal-point alignment.

`ToolScene.measure_arc(tcp)` and `ToolScene.measure_point(xy)` render the
camera and locate the tip by its red-weighted centroid; they are the
`measure` functions of `jaxcal._tooloffset`'s loops.
"""

import numpy as np

from ._gl import no_backend_error, select_backend
from .scene import CameraSpec, mujoco_quat

select_backend()
import mujoco  # noqa: E402


class ToolScene:
    """The stylus rig (see the module docstring); `close()` frees the renderer."""

    def __init__(
        self,
        tip_xy=(0.006, -0.004),
        *,
        camera_roll: float = np.radians(8.0),
        height: float = 0.25,
        stylus_length: float = 0.05,
        tip_radius: float = 0.003,
        width: int = 320,
        height_px: int = 240,
        fovy_deg: float = 40.0,
    ):
        self.tip_xy = np.asarray(tip_xy, np.float64)
        self.camera_roll = float(camera_roll)
        #: What `jaxcal.calibrate_tool_offset`'s `camera_roll` takes for this camera (looking up the
        #: axis, its x turned by `camera_roll`): the image angle of the axis frame's +x.
        self.image_roll = -self.camera_roll
        self.height = height
        self.stylus_length = stylus_length
        c, s = np.cos(camera_roll), np.sin(camera_roll)
        T = np.eye(4)  # T_world_cam, OpenCV axes: z up the axis, x rolled by camera_roll about it
        T[:3, :3] = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        self.camera = CameraSpec("tool_cam", width, height_px, fovy_deg, T, "world")

        spec = mujoco.MjSpec()
        spec.modelname = "jaxcal_tool"
        spec.visual.global_.offwidth, spec.visual.global_.offheight = width, height_px
        spec.visual.quality.shadowsize = 0
        spec.visual.headlight.ambient = [0.3, 0.3, 0.3]
        world = spec.worldbody
        world.add_light(pos=[0.0, 0.0, 0.1], dir=[0.0, 0.0, 1.0], diffuse=[0.6, 0.6, 0.6])
        axis = world.add_body(name="axis", pos=[0.0, 0.0, height])
        axis.add_joint(name="spin", type=mujoco.mjtJoint.mjJNT_HINGE, axis=[0.0, 0.0, 1.0])
        axis.explicitinertial = True
        axis.mass, axis.inertia = 0.1, [1e-4, 1e-4, 1e-4]
        tool = axis.add_body(name="tool", pos=[0.0, 0.0, 0.0])
        tool.explicitinertial = True
        tool.mass, tool.inertia = 0.05, [1e-5, 1e-5, 1e-5]
        tip = np.array([*self.tip_xy, -stylus_length])
        tool.add_geom(
            type=mujoco.mjtGeom.mjGEOM_CAPSULE,
            fromto=[*self.tip_xy, 0.0, *(tip + [0.0, 0.0, tip_radius]).tolist()],
            size=[0.6 * tip_radius, 0.0, 0.0],
            rgba=[0.35, 0.35, 0.38, 1.0],
            contype=0,
            conaffinity=0,
        )
        tool.add_geom(
            name="tip",
            type=mujoco.mjtGeom.mjGEOM_SPHERE,
            pos=tip,
            size=[tip_radius, 0.0, 0.0],
            rgba=[1.0, 0.0, 0.0, 1.0],
            contype=0,
            conaffinity=0,
        )
        mat = spec.add_material(name="tip_glow")
        mat.emission = 1.0
        spec.geom("tip").material = "tip_glow"
        world.add_camera(
            name="tool_cam",
            pos=[0.0, 0.0, 0.0],
            quat=mujoco_quat(T[:3, :3] @ np.diag([1.0, -1.0, -1.0])),
            fovy=float(fovy_deg),
        )
        self.model = spec.compile()
        self.data = mujoco.MjData(self.model)
        self._axis = self.model.body("axis").id
        self._tool = self.model.body("tool").id
        self._spin = self.model.joint("spin").qposadr[0]
        try:
            self._renderer = mujoco.Renderer(self.model, height=height_px, width=width)
        except Exception as e:  # the GL backends raise assorted types
            raise no_backend_error(e) from e
        # Image scale at the tip's depth (m/px).
        self.depth = height - stylus_length
        self.metres_per_px = self.depth / self.camera.K[0, 0]

    @property
    def K(self) -> np.ndarray:
        return self.camera.K

    def set(self, *, tcp=(0.0, 0.0), angle: float = 0.0, axis_xy=(0.0, 0.0)) -> None:
        """Axis at `axis_xy`, passing through the tool frame's `tcp`, rotated by `angle` (rad)."""
        self.model.body_pos[self._axis] = [*np.asarray(axis_xy, np.float64), self.height]
        self.model.body_pos[self._tool] = [*(-np.asarray(tcp, np.float64)), 0.0]
        self.data.qpos[self._spin] = angle
        mujoco.mj_kinematics(self.model, self.data)
        mujoco.mj_camlight(self.model, self.data)

    def tip_world(self) -> np.ndarray:
        return self.data.geom("tip").xpos.copy()

    def tip_pixel(self) -> np.ndarray:
        """Render and return the tip's image position (px): the red-weighted centroid."""
        self._renderer.update_scene(self.data, camera="tool_cam")
        img = self._renderer.render().astype(np.float64)
        w = np.clip(img[..., 0] - 0.5 * (img[..., 1] + img[..., 2]) - 60.0, 0.0, None)
        if w.sum() <= 0.0:
            return np.full(2, np.nan)
        v, u = np.indices(w.shape)
        return np.array([(u * w).sum(), (v * w).sum()]) / w.sum()

    def measure_arc(self, tcp, angles=None):
        """Rotate about the axis through `tcp` and return `(pixels (n, 2), angles (n,), mask)`."""
        angles = np.radians(np.arange(0.0, 360.0, 30.0)) if angles is None else np.asarray(angles)
        px = []
        for a in angles:
            self.set(tcp=tcp, angle=a)
            px.append(self.tip_pixel())
        px = np.stack(px)
        return px, angles, np.all(np.isfinite(px), axis=1)

    def measure_point(self, axis_xy, tcp=(0.0, 0.0)):
        """Move the stylus (the axis) to `axis_xy` and return the tip's image position (px)."""
        self.set(tcp=tcp, angle=0.0, axis_xy=axis_xy)
        return self.tip_pixel()

    def close(self) -> None:
        self._renderer.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
