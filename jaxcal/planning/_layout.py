"""Where the camera and the target go by default: the layout `jaxcal demo` renders, at a taught pose.

Eye-to-hand: the plate on the flange 12 mm out of the tool face, upright as
seen at the taught pose; one camera `distance` away along the plate's normal,
looking slightly down at a plate that faces sideways, or 50 degrees off the
normal (away from the base column) at one that faces up or down. Eye-in-hand:
the camera 3 cm out of the tool face, the board (two squares larger each way)
`distance` in front of it. At the zero configuration this is exactly
`jaxcal.sim.simulate`'s layout (the tests check it), so a plan made with the
defaults films what the demo films.
"""

import jax
import numpy as np

from .._kinematics import KinematicModel, forward_kinematics
from .._npgeom import axis_rotation
from ..io.plan import PlanCamera, PlanTarget
from ..markers import TargetSpec


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """`T_world_cam` (OpenCV axes) of a camera at `eye` looking at `target`."""
    eye, target = np.asarray(eye, np.float64), np.asarray(target, np.float64)
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-6:
        x = np.cross(z, (0.0, 1.0, 0.0))
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    T[:3, 3] = eye
    return T


def facing_mount(spec: TargetSpec, normal, centre, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """`T_link_target` putting `spec`'s printed face at `centre`, facing `normal`,
    upright for a viewer whose up is `up` (all in the link frame)."""
    n = np.asarray(normal, np.float64) / np.linalg.norm(normal)
    up = np.asarray(up, np.float64)
    d = -(up - np.dot(up, n) * n)
    if np.linalg.norm(d) < 1e-6:
        d = np.cross(n, (1.0, 0.0, 0.0))
    d /= np.linalg.norm(d)
    r = np.cross(n, d)
    _, right, down = spec.pattern_extent()
    R = np.stack([r, d, n], axis=1) @ np.stack([right, down, spec.front_normal()], axis=1).T
    top_left, _, _ = spec.pattern_extent()
    w, h = spec.pattern_size
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(centre, np.float64) - R @ (top_left + 0.5 * w * right + 0.5 * h * down)
    return T


def pinhole(width: int, height: int, fovy_deg: float) -> np.ndarray:
    """The intrinsics MuJoCo renders with (`jaxcal.sim.scene.CameraSpec.K`): square
    pixels, $f = (H/2)/\\tan(\\mathrm{fovy}/2)$, principal point at the image centre."""
    f = 0.5 * height / np.tan(0.5 * np.deg2rad(fovy_deg))
    return np.array([[f, 0.0, 0.5 * (width - 1)], [0.0, f, 0.5 * (height - 1)], [0.0, 0.0, 1.0]])


def demo_plate(board: bool = False) -> TargetSpec:
    """The demo's 5x4 ChArUco plate (40 mm squares, 30 mm markers), or with
    `board` the 7x6 board an eye-in-hand camera films."""
    squares = (7, 6) if board else (5, 4)
    return TargetSpec(
        kind="charuco",
        squares=squares,
        square_length=0.04,
        marker_length=0.03,
        name="board0" if board else "plate0",
    )


def default_layout(
    nominal: KinematicModel,
    taught,
    *,
    resolution: tuple[int, int] = (1280, 960),
    fovy_deg: float = 50.0,
    distance: float = 0.9,
    eye_in_hand: bool = False,
    spec: TargetSpec | None = None,
) -> tuple[PlanCamera, PlanTarget]:
    """The demo's camera and target placed at the taught pose (see the module docstring).

    **Arguments:** the nominal robot; the taught pose (commanded, rad);
    `resolution` (px); `fovy_deg`; `distance` (m) camera to plate (or board);
    `eye_in_hand`; `spec`: the target (default `demo_plate(board=eye_in_hand)`).

    **Returns:** `(PlanCamera, PlanTarget)`.
    """
    w, h = resolution
    F = np.asarray(jax.device_get(forward_kinematics(nominal, np.asarray(taught, np.float64))))
    flange = nominal.link_names[-1]
    spec = demo_plate(eye_in_hand) if spec is None else spec
    K = pinhole(w, h, fovy_deg)
    if eye_in_hand:
        T_flange_cam = np.eye(4)
        T_flange_cam[:3, 3] = (0.0, 0.0, 0.03)
        out = F[-1][:3, 2]
        centre = F[-1][:3, 3] + distance * out
        T_board = facing_mount(spec, -out, centre, up=-F[-1][:3, 1])
        return (
            PlanCamera("cam0", w, h, K, np.zeros(5), flange, T_flange_cam),
            PlanTarget(spec, "world", T_board),
        )
    up = F[-1][:3, :3].T @ np.array([0.0, 0.0, 1.0])
    T_mount = facing_mount(spec, (0.0, 0.0, 1.0), (0.0, 0.0, 0.012), up=up)
    centre = (F[-1] @ T_mount)[:3, 3]
    normal = (F[-1] @ T_mount)[:3, :3] @ spec.front_normal()
    horiz = np.array([normal[0], normal[1], 0.0])
    view = normal
    if np.linalg.norm(horiz) < 0.7:
        away = np.array([centre[0], centre[1], 0.0])
        away = away / np.linalg.norm(away) if np.linalg.norm(away) > 1e-6 else np.array([1.0, 0.0, 0.0])
        view = np.cos(np.deg2rad(50.0)) * normal + np.sin(np.deg2rad(50.0)) * away
    d = view
    if np.linalg.norm(horiz) > 0.5:
        d = axis_rotation(np.cross(d, (0.0, 0.0, 1.0)), np.deg2rad(-15.0)) @ d
    T_wc = look_at(centre + distance * d, centre)
    return PlanCamera("cam0", w, h, K, np.zeros(5), "world", T_wc), PlanTarget(spec, flange, T_mount)
