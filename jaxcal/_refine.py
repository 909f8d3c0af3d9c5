"""Maximum-likelihood refinement: reprojection adjustment of every detected corner.

Design step 6. The two-stage method (arc fits, then the axis fit) reduces
each frame to a marker pose and each sweep to a line; this stage goes back
to the pixels. Corner $k$ of the target seen in view $v$ (one target in one
frame) is predicted at

$$\\hat u_{vk} = \\pi_{K,d}\\big(T_{cam,base}\\;T_{base,flange}(q_v)\\;
T_{flange,target}\\;X_k\\big),\\qquad
q_v = r \\odot q_{log}\\big((t_{cam,v} - \\delta)/(1+\\epsilon)\\big),$$

with $\\pi_{K,d}$ the pinhole projection with OpenCV's distortion model
$(k_1, k_2, p_1, p_2, k_3)$, $T_{base,flange}$ the forward kinematics of the
corrected model, $q_{log}$ the encoder log (commanded positions, motor angle
over the nominal ratio) interpolated at controller time, $r$ the rate
(nominal over true reduction ratio) and $\\delta$ the clock offset. The
residual is $\\hat u_{vk} - u_{vk}$ (px) for every corner of every view:
padded arrays with a mask, vmapped over views. Under Gaussian pixel noise the
least-squares solution is the maximum-likelihood estimate.

Unknowns (`RefineParams`): the axis fit's `KinematicCorrection` (joint
origin twists, zero offsets, marker mount twists), a twist on
$T_{cam,base}$, the rates, the clock offset and, optionally, increments of
the intrinsics. Parameters the data cannot see are held at their start
values (a fixed mask, see `identifiable_mask`); the solver works on the free
ones only, scaled by the start Jacobian's column norms (Jacobi scaling, so
Levenberg-Marquardt's damping treats metres, radians, milliseconds and
pixels alike).

Robust loss: iteratively reweighted least squares inside the LM residuals
(Cauchy or Huber weights on each corner's residual norm, scale by the
median absolute residual), then one last solve on the inliers (corners
within `reject` robust standard deviations), whose Jacobian gives honest
standard deviations: $\\Sigma = \\hat\\sigma^2 (J^T J)^{-1}$ with
$\\hat\\sigma^2$ the inlier residual variance.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, Bool, Float, Int

from ._axisfit import KinematicCorrection, apply_correction, parameter_names
from ._clocksync import controller_time, interpolate_encoders
from ._geometry import se3_exp, skew
from ._kinematics import REVOLUTE, KinematicModel
from ._linalg import gauss_newton_covariance

_MS = 1e-3
#: Names of the intrinsic increments, in `RefineParams.intrinsics` order.
INTRINSIC_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
#: Median of the norm of a 2-D standard normal vector (Rayleigh), $\\sqrt{2 \\ln 2}$.
_RAYLEIGH_MEDIAN = float(np.sqrt(2.0 * np.log(2.0)))
LOSSES = ("cauchy", "huber", None)
#: The solver's variables are scaled so that every Jacobian column has this
#: norm at the start: optimistix's Levenberg-Marquardt starts with unit
#: damping, so its first steps are near Gauss-Newton ones (the start, the
#: two-stage result, is close) and the trust region shrinks when they fail.
_COLUMN_NORM = 1e4


class RefineParams(eqx.Module):
    """All unknowns of the refinement (flattened by `ravel_pytree` in field order).

    - `cam`: twist on the camera pose, $T_{cam,base} = T_0\\,\\exp(cam)$.
    - `correction`: the axis fit's `KinematicCorrection` (joint origin twists,
      zero offsets, marker mount twists) relative to the nominal model and mounts.
    - `rate`: per joint, joint turn per commanded turn, $\\rho_{nom} / \\rho$.
    - `clock_ms`: clock offset increment over the start value (ms).
    - `intrinsics`: increments of $(f_x, f_y, c_x, c_y)$ (px) and
      $(k_1, k_2, p_1, p_2, k_3)$ of the first camera.
    - `other_cams`: with several fixed cameras, a twist on each further
      camera's pose, $T_{cam_c,base} = T_{c,0}\\,\\exp(\\xi_c)$; `None` with one.
      Last in the flattened order, so a single-camera layout is a prefix.
    - `angles`: without encoders, the sweeping joint's position in every view
      (rad, commanded coordinates: the zero offset is added), the other joints
      at their commanded zero (`CornerData.sweep_joint`); `None` with an
      encoder log. After `other_cams` in the flattened order.
    """

    cam: Float[Array, "6"]
    correction: KinematicCorrection
    rate: Float[Array, " joints"]
    clock_ms: Float[Array, ""]
    intrinsics: Float[Array, "9"]
    other_cams: Float[Array, "others 6"] | None = None
    angles: Float[Array, " views"] | None = None


class CornerData(eqx.Module):
    """Detected corners of every view (one target in one frame), padded.

    - `points`: the corners in their target's frame (m), `(views, corners, 3)`.
    - `pixels`: where they were detected (px, OpenCV's pixel-centre convention).
    - `mask`: which `(view, corner)` entries are real.
    - `target`: the target (marker mount) of each view, `(views,)`.
    - `frame`: the dataset row of each view (for reports), `(views,)`.
    - `t_cam`: each view's camera-clock stamp (s).
    - `enc_t` (s, controller clock), `enc_q` (rad): the encoder log as commanded
      joint positions (motor angle over the nominal ratio), `(T,)`, `(T, joints)`.
    - `drift_ppm`: the known clock drift.
    - `camera`: which camera took each view, `(views,)`: 0 the first (the
      one `T_cam_base0` belongs to), `c` the `RefineProblem.other_cameras`
      entry `c - 1`; `None`: all the first.
    - `sweep_joint`: without encoders, which joint sweeps alone in each view
      (the others at zero); with `RefineParams.angles` the encoder log is
      not used.
    """

    points: Float[Array, "views corners 3"]
    pixels: Float[Array, "views corners 2"]
    mask: Bool[Array, "views corners"]
    target: Int[Array, " views"]
    frame: Int[Array, " views"]
    t_cam: Float[Array, " views"]
    enc_t: Float[Array, " T"]
    enc_q: Float[Array, "T joints"]
    drift_ppm: Float[Array, ""]
    camera: Int[Array, " views"] | None = None
    sweep_joint: Int[Array, " views"] | None = None


class OtherCameras(eqx.Module):
    """Further fixed cameras of a refinement: start poses `T_cam_base0`
    `(others, 4, 4)` and their (fixed) intrinsics `K` `(others, 3, 3)`, `dist`
    `(others, 5)`. They share the robot, the targets and the clock."""

    T_cam_base0: Float[Array, "others 4 4"]
    K: Float[Array, "others 3 3"]
    dist: Float[Array, "others 5"]


class RefineProblem(eqx.Module):
    """Everything fixed during the refinement: the nominal model and mounts
    (the origin of `correction`), the reference camera pose, the start
    intrinsics and clock offset, the corners, and any further cameras.

    `eye_in_hand`: the camera rides on the flange and the target is fixed in
    the world. The chain is the same with the roles swapped, $T_{board,cam}(q)
    = T_{board,base}\\,T_{base,flange}(q)\\,T_{flange,cam}$: `T_cam_base0` and
    `params.cam` then hold $T_{board,base}$, the (single) marker mount holds
    $T_{flange,cam}$, and the corners are projected through its inverse.

    `target_link`: with markers on several links, the link each target rides
    on, as an index into `nominal.link_names` (0 the base, `i + 1` the child
    of joint `i`, `joints + 1` the flange); its mount in
    `T_flange_marker0` / `correction.tool` is then relative to that link.
    `None`: every target on the flange.
    """

    nominal: KinematicModel
    T_flange_marker0: Float[Array, "markers 4 4"]
    T_cam_base0: Float[Array, "4 4"]
    K0: Float[Array, "3 3"]
    dist0: Float[Array, "5"]
    offset0_s: Float[Array, ""]
    data: CornerData
    other_cameras: OtherCameras | None = None
    eye_in_hand: bool = eqx.field(static=True, default=False)
    target_link: Int[Array, " markers"] | None = None


def make_corner_data(
    points: list,
    pixels: list,
    target: np.ndarray,
    frame: np.ndarray,
    t_cam: np.ndarray,
    enc_t: np.ndarray,
    enc_q: np.ndarray,
    drift_ppm: float = 0.0,
    camera: np.ndarray | None = None,
    sweep_joint: np.ndarray | None = None,
) -> CornerData:
    """Pad per-view corner lists into a `CornerData` (NumPy in, arrays out).

    **Arguments:** `points[v]` `(n_v, 3)` target-frame corners (m) and
    `pixels[v]` `(n_v, 2)` their detections (px) of view `v`; `target`,
    `frame`, `t_cam` `(views,)`; the encoder log `enc_t (T,)`, `enc_q (T, joints)`;
    `camera` `(views,)` (see `CornerData`; default all 0); `sweep_joint`
    `(views,)` for a refinement without encoders.
    """
    V = len(points)
    if V == 0:
        raise ValueError("make_corner_data: no views")
    if camera is not None and len(camera) != V:
        raise ValueError(f"make_corner_data: {V} point sets but {len(camera)} camera indices")
    if len(pixels) != V or len(target) != V or len(frame) != V or len(t_cam) != V:
        raise ValueError(
            f"make_corner_data: {V} point sets but {len(pixels)} pixel sets, {len(target)} targets, "
            f"{len(frame)} frames, {len(t_cam)} stamps"
        )
    enc_t = np.asarray(enc_t, np.float64)
    enc_q = np.asarray(enc_q, np.float64)
    if enc_q.ndim != 2 or enc_q.shape[0] != enc_t.shape[0] or enc_t.ndim != 1:
        raise ValueError(f"make_corner_data: encoder log shapes {enc_t.shape} and {enc_q.shape} do not match")
    P = max(len(p) for p in points)
    X = np.zeros((V, P, 3))
    U = np.zeros((V, P, 2))
    m = np.zeros((V, P), bool)
    for v, (x, u) in enumerate(zip(points, pixels)):
        x = np.asarray(x, np.float64).reshape(-1, 3)
        u = np.asarray(u, np.float64).reshape(-1, 2)
        if len(x) != len(u):
            raise ValueError(
                f"make_corner_data: view {v} (frame {frame[v]}) has {len(x)} points, {len(u)} pixels"
            )
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(u))):
            raise ValueError(f"make_corner_data: view {v} (frame {frame[v]}) has NaN or inf corners")
        X[v, : len(x)] = x
        U[v, : len(u)] = u
        m[v, : len(x)] = True
    return CornerData(
        points=jnp.asarray(X),
        pixels=jnp.asarray(U),
        mask=jnp.asarray(m),
        target=jnp.asarray(np.asarray(target, np.int64)),
        frame=jnp.asarray(np.asarray(frame, np.int64)),
        t_cam=jnp.asarray(np.asarray(t_cam, np.float64)),
        enc_t=jnp.asarray(enc_t),
        enc_q=jnp.asarray(enc_q),
        drift_ppm=jnp.asarray(float(drift_ppm)),
        camera=None if camera is None else jnp.asarray(np.asarray(camera, np.int64)),
        sweep_joint=None if sweep_joint is None else jnp.asarray(np.asarray(sweep_joint, np.int64)),
    )


def initial_params(
    correction: KinematicCorrection,
    *,
    cam: Float[Array, "6"] | None = None,
    rate: Float[Array, " joints"] | None = None,
) -> RefineParams:
    """A `RefineParams` from an axis fit's correction (camera twist, rates given
    or zero / one; clock and intrinsic increments zero)."""
    n = correction.zero_offset.shape[0]
    return RefineParams(
        cam=jnp.zeros(6) if cam is None else jnp.asarray(cam, jnp.float64),
        correction=correction,
        rate=jnp.ones(n) if rate is None else jnp.asarray(rate, jnp.float64),
        clock_ms=jnp.zeros(()),
        intrinsics=jnp.zeros(9),
    )


def zero_params(num_joints: int, num_markers: int) -> RefineParams:
    """The start of a refinement from the nominal model (rates one)."""
    return initial_params(
        KinematicCorrection(
            origin=jnp.zeros((num_joints, 6)),
            zero_offset=jnp.zeros(num_joints),
            tool=jnp.zeros((num_markers, 6)),
        )
    )


def refine_parameter_names(
    model: KinematicModel,
    num_markers: int,
    other_cameras: tuple[str, ...] | list[str] = (),
    angles: tuple[str, ...] | list[str] = (),
) -> list[str]:
    """Names of the flattened `RefineParams`: the axis fit's `parameter_names`,
    then the rates, the clock offset, the intrinsics, the further cameras'
    poses (`"{camera}.T_cam_base.tx"`, ...) and, without encoders, the
    per-view joint angles (named by the caller, e.g. `"frame12.elbow_joint"`)."""
    names = parameter_names(model, num_markers)
    names += [f"{j}.rate" for j in model.joint_names]
    names += ["clock_offset_ms"]
    names += [f"intrinsics.{k}" for k in INTRINSIC_NAMES]
    cam = names[:6]
    for c in other_cameras:
        names += [f"{c}.{p}" for p in cam]
    return names + list(angles)


def _groups(n: int, M: int, others: int = 0, angles: int = 0) -> dict[str, np.ndarray]:
    """Index ranges of the parameter groups in the flattened `RefineParams`."""
    sizes = [
        ("cam", 6),
        ("origin", 6 * n),
        ("zero", n),
        ("tool", 6 * M),
        ("rate", n),
        ("clock", 1),
        ("intr", 9),
        ("others", 6 * others),
        ("angles", angles),
    ]
    out, start = {}, 0
    for name, size in sizes:
        out[name] = np.arange(start, start + size)
        start += size
    return out


def default_free(
    num_joints: int,
    num_markers: int,
    *,
    rates: bool = True,
    clock: bool = False,
    intrinsics: bool = False,
    other_cameras: int = 0,
    angles: int = 0,
) -> np.ndarray:
    """Candidate mask: pose and kinematic corrections (every camera's pose and
    every per-view angle included), and the optional groups."""
    g = _groups(num_joints, num_markers, other_cameras, angles)
    free = np.ones(g["intr"][-1] + 1 + g["others"].size + angles, bool)
    free[g["rate"]] = rates
    free[g["clock"]] = clock
    free[g["intr"]] = intrinsics
    return free


def _priority(num_joints: int, num_markers: int, others: int = 0, angles: int = 0) -> np.ndarray:
    """The axis fit's column order (cameras, mount, zero offsets, origins base
    to tip), then rates, clock, intrinsics and per-view angles."""
    g = _groups(num_joints, num_markers, others, angles)
    keys = ("cam", "others", "tool", "zero", "origin", "rate", "clock", "intr", "angles")
    return np.concatenate([g[k] for k in keys])


def _num_others(problem: RefineProblem) -> int:
    return 0 if problem.other_cameras is None else problem.other_cameras.T_cam_base0.shape[-3]


def camera_poses(params: RefineParams, problem: RefineProblem) -> Float[Array, "cameras 4 4"]:
    """Every camera's $T_{cam,base}$ at `params`: the first, then `other_cameras`."""
    T0 = (problem.T_cam_base0 @ se3_exp(params.cam))[None]
    if problem.other_cameras is None:
        return T0
    others = problem.other_cameras.T_cam_base0 @ jax.vmap(se3_exp)(params.other_cams)
    return jnp.concatenate([T0, others])


def project(
    K: Float[Array, "3 3"], dist: Float[Array, "5"], X: Float[Array, "... 3"]
) -> Float[Array, "... 2"]:
    """Pinhole projection with OpenCV's distortion model (as `cv2.projectPoints`).

    $x = X/Z$, $r^2 = x^2 + y^2$, $x'' = x(1 + k_1 r^2 + k_2 r^4 + k_3 r^6) +
    2 p_1 x y + p_2 (r^2 + 2x^2)$ (and symmetrically for $y$), $u = f_x x'' + c_x$.

    **Arguments:** `K` (px), `dist` $(k_1, k_2, p_1, p_2, k_3)$, camera-frame points `X` (m).

    **Returns:** pixels (px).
    """
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    z = X[..., 2]
    x = X[..., 0] / z
    y = X[..., 1] / z
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    u = K[0, 0] * xd + K[0, 1] * yd + K[0, 2]
    v = K[1, 1] * yd + K[1, 2]
    return jnp.stack([u, v], axis=-1)


def camera_matrix(
    params: RefineParams, problem: RefineProblem
) -> tuple[Float[Array, "3 3"], Float[Array, "5"]]:
    """The intrinsics `(K, dist)` at `params`."""
    d = params.intrinsics
    K = problem.K0 + jnp.array([[1.0, 0, 0], [0, 0, 0], [0, 0, 0]]) * d[0]
    K = K + jnp.array([[0.0, 0, 0], [0, 1, 0], [0, 0, 0]]) * d[1]
    K = K + jnp.array([[0.0, 0, 1], [0, 0, 0], [0, 0, 0]]) * d[2]
    K = K + jnp.array([[0.0, 0, 0], [0, 0, 1], [0, 0, 0]]) * d[3]
    return K, problem.dist0 + d[4:]


def joint_positions(params: RefineParams, problem: RefineProblem) -> Float[Array, "views joints"]:
    """Commanded joint positions of every view, $r \\odot q_{log}(t_{ctrl})$ (rad);
    without encoders (`params.angles`), the sweeping joint at its unknown
    angle and the others at zero."""
    data = problem.data
    if params.angles is not None:
        n = problem.nominal.num_joints
        return jax.nn.one_hot(data.sweep_joint, n, dtype=params.angles.dtype) * params.angles[:, None]
    offset = problem.offset0_s + _MS * params.clock_ms
    t = controller_time(data.t_cam, offset, data.drift_ppm)
    q = jax.vmap(lambda qj: interpolate_encoders(t, data.enc_t, qj), out_axes=1)(data.enc_q.T)
    return q * params.rate


def _chain(
    params: RefineParams, problem: RefineProblem
) -> tuple[Float[Array, "views 3 3"], Float[Array, "views 3"]]:
    """Rotation and translation of $T_{cam,target}$ for every view.

    The product $T_{cam,base}\\,T_{base,flange}(q_v)\\,T_{flange,target}$ of
    `forward_kinematics` of the corrected model, written on (rotation,
    translation) pairs with Rodrigues' formula for the joint motions (exact
    for unit axes, no small-angle branch): about half the run time and two
    thirds of the compile time of its Jacobian against the 4x4 chain (the
    tests check both agree).
    """
    model, mounts = apply_correction(problem.nominal, problem.T_flange_marker0, params.correction)
    theta = joint_positions(params, problem) + model.zero_offset  # (V, J)
    V = theta.shape[0]
    if problem.other_cameras is None or problem.data.camera is None:
        T_cb = problem.T_cam_base0 @ se3_exp(params.cam)
        R = jnp.broadcast_to(T_cb[:3, :3], (V, 3, 3))
        t = jnp.broadcast_to(T_cb[:3, 3], (V, 3))
    else:
        T_v = camera_poses(params, problem)[problem.data.camera]
        R, t = T_v[:, :3, :3], T_v[:, :3, 3]
    links = [(R, t)]  # the chain up to each link, for targets on several links
    for i, kind in enumerate(model.joint_types):
        T_p = model.T_parent_joint[i]
        t = t + R @ T_p[:3, 3]
        R = R @ T_p[:3, :3]
        a = model.axis[i]
        if kind == REVOLUTE:
            A = skew(a)
            s, c = jnp.sin(theta[:, i]), jnp.cos(theta[:, i])
            R = R @ (jnp.eye(3) + s[:, None, None] * A + (1.0 - c)[:, None, None] * (A @ A))
        else:
            t = t + R @ a * theta[:, i, None]
        links.append((R, t))
    T_lf = model.T_last_flange
    t = t + R @ T_lf[:3, 3]
    R = R @ T_lf[:3, :3]
    if problem.target_link is not None:
        links.append((R, t))
        k = problem.target_link[problem.data.target]
        R = jnp.stack([r for r, _ in links])[k, jnp.arange(V)]
        t = jnp.stack([tt for _, tt in links])[k, jnp.arange(V)]
    M = mounts[problem.data.target]
    t = t + jnp.einsum("vab,vb->va", R, M[:, :3, 3])
    R = R @ M[:, :3, :3]
    if problem.eye_in_hand:  # T_board_cam above; the camera sees the board through its inverse
        R = jnp.swapaxes(R, -1, -2)
        t = -jnp.einsum("vab,vb->va", R, t)
    return R, t


def target_poses(params: RefineParams, problem: RefineProblem) -> Float[Array, "views 4 4"]:
    """$T_{cam,target}$ of every view at `params`."""
    R, t = _chain(params, problem)
    bottom = jnp.broadcast_to(jnp.array([0.0, 0.0, 0.0, 1.0]), (R.shape[0], 1, 4))
    return jnp.concatenate([jnp.concatenate([R, t[..., None]], axis=-1), bottom], axis=-2)


def projected_corners(params: RefineParams, problem: RefineProblem) -> Float[Array, "views corners 2"]:
    """Every corner reprojected at `params` (px), padding included."""
    R, t = _chain(params, problem)
    X = jnp.einsum("vab,vkb->vka", R, problem.data.points) + t[:, None, :]
    K, dist = camera_matrix(params, problem)
    if problem.other_cameras is None or problem.data.camera is None:
        return project(K, dist, X)
    Ks = jnp.concatenate([K[None], problem.other_cameras.K])[problem.data.camera]
    ds = jnp.concatenate([dist[None], problem.other_cameras.dist])[problem.data.camera]
    return jax.vmap(project)(Ks, ds, X)


def reprojection_residuals(
    params: RefineParams, problem: RefineProblem, weights: Float[Array, "views corners"] | None = None
) -> Float[Array, "views corners 2"]:
    """Reprojected minus detected corner (px), times $\\sqrt{w}$; zero on padding.

    **Arguments:** `params`; `problem`; `weights` per corner (default: the mask).

    **Returns:** `(views, corners, 2)` residuals.
    """
    r = projected_corners(params, problem) - problem.data.pixels
    w = problem.data.mask.astype(r.dtype) if weights is None else weights
    return jnp.where(problem.data.mask[..., None], r * jnp.sqrt(w)[..., None], 0.0)


def _robust_scale(e: Float[Array, "v k"], mask: Bool[Array, "v k"]) -> Float[Array, ""]:
    """Per-coordinate pixel sigma from the median corner residual norm (Rayleigh)."""
    med = jnp.nanmedian(jnp.where(mask, e, jnp.nan))
    return jnp.maximum(med / _RAYLEIGH_MEDIAN, 1e-9)


def robust_weights(e: Float[Array, "..."], loss: str | None, c: float) -> Float[Array, "..."]:
    """IRLS weights of corner residual norms `e` (in robust sigmas).

    Cauchy: $w = 1/(1 + (e/c)^2)$; Huber: $w = \\min(1, c/e)$; `None`: 1.
    """
    if loss is None:
        return jnp.ones_like(e)
    if loss == "cauchy":
        return 1.0 / (1.0 + (e / c) ** 2)
    if loss == "huber":
        return jnp.minimum(1.0, c / jnp.maximum(e, 1e-12))
    raise ValueError(f"loss must be one of {LOSSES}, got {loss!r}")


def identifiable_mask(
    problem: RefineProblem,
    params: RefineParams,
    candidates: Bool[Array, " n"],
    *,
    tol: float = 1e-6,
) -> tuple[Bool[Array, " n"], Float[Array, " n"]]:
    """Which candidate parameters the corners determine, by greedy column selection.

    The reprojection Jacobian's columns are normalised and visited in the
    axis fit's priority order (camera, mounts, zero offsets, origins base to
    tip, then rates, clock, intrinsics); a candidate column is kept when its
    component orthogonal to the kept ones is above `tol` (a rank-revealing,
    column-pivoted Gram-Schmidt with a fixed pivot order). Pure and jittable.

    **Returns:** `(free, independence)` over the flattened `RefineParams`.
    """
    flat, unravel = ravel_pytree(params)
    J = jax.jacfwd(lambda x: reprojection_residuals(unravel(x), problem).reshape(-1))(flat)
    norms = jnp.linalg.norm(J, axis=0)
    Jn = J / jnp.where(norms > 0, norms, 1.0)
    n_joints = problem.nominal.num_joints
    n_angles = 0 if params.angles is None else params.angles.shape[0]
    order = jnp.asarray(
        _priority(n_joints, problem.T_flange_marker0.shape[0], _num_others(problem), n_angles)
    )
    cand = jnp.asarray(candidates, bool)
    m, n = J.shape

    def body(i, carry):
        basis, keep, indep, count = carry
        j = order[i]
        col = Jn[:, j]
        resid = col - basis @ (basis.T @ col)
        resid = resid - basis @ (basis.T @ resid)  # re-orthogonalise
        r = jnp.linalg.norm(resid)
        ok = (r > tol) & (norms[j] > 0) & cand[j]
        basis = jnp.where(ok, basis.at[:, count].set(resid / jnp.where(ok, r, 1.0)), basis)
        return basis, keep.at[j].set(ok), indep.at[j].set(r), count + ok

    init = (jnp.zeros((m, n)), jnp.zeros(n, bool), jnp.zeros(n), jnp.asarray(0))
    _, keep, indep, _ = jax.lax.fori_loop(0, n, body, init)
    return keep, indep


class RefineResult(eqx.Module):
    """The refined calibration.

    - `params`: the solution (`RefineParams`); `model`: the calibrated model
      (reduction ratios $\\rho_{nom}/r$, `T_flange_tool` the first mount);
      `T_cam_base` (the first camera), `T_cam_bases` (every camera,
      `(cameras, 4, 4)`), `T_flange_marker`, `K`, `dist`, `offset_s` (s).
    - `std`, `cov`: standard deviations and covariance of the flattened
      parameters (`refine_parameter_names` order; zero where frozen).
    - `free`: the parameters estimated (the others held at their start).
    - `singular_values`, `singular_vectors` (rows): SVD of the
      column-normalised inlier Jacobian of the free parameters at the
      solution (a near-zero value is an unidentifiable direction).
    - `sigma_px`: the inlier pixel noise (per coordinate) the covariance is scaled by.
    - `residuals`: reprojected minus detected, px, `(views, corners, 2)`;
      `weights`: the last IRLS weights; `inlier`: corners used by the final solve.
    - `result`, `num_steps`: optimistix's result of the final solve and the
      steps of all rounds; `rounds_ok`: every round's solve succeeded.
    """

    params: RefineParams
    model: KinematicModel
    T_cam_base: Float[Array, "4 4"]
    T_cam_bases: Float[Array, "cameras 4 4"]
    T_flange_marker: Float[Array, "markers 4 4"]
    K: Float[Array, "3 3"]
    dist: Float[Array, "5"]
    offset_s: Float[Array, ""]
    std: Float[Array, " n"]
    cov: Float[Array, "n n"]
    free: Bool[Array, " n"]
    singular_values: Float[Array, " f"]
    singular_vectors: Float[Array, "f f"]
    sigma_px: Float[Array, ""]
    residual_rms_px: Float[Array, ""]
    residuals: Float[Array, "views corners 2"]
    weights: Float[Array, "views corners"]
    inlier: Bool[Array, "views corners"]
    result: optx.RESULTS
    num_steps: Int[Array, ""]
    rounds_ok: Bool[Array, ""]
    round_steps: Int[Array, " rounds"]


def refine(
    problem: RefineProblem,
    params0: RefineParams,
    free: np.ndarray,
    *,
    loss: str | None = "cauchy",
    rounds: int = 3,
    c: float = 3.0,
    reject: float | None = 3.7,
    rtol: float = 1e-7,
    atol: float = 1e-7,
    max_steps: int = 50,
) -> RefineResult:
    """Minimise the reprojection error of every corner; pure, jittable, vmappable.

    Levenberg-Marquardt (optimistix, forward-mode Jacobian over the free
    parameters only) on `reprojection_residuals`, Jacobi-scaled at the start.
    With a robust `loss`, `rounds` IRLS solves (weights from each solution's
    corner residual norms in robust sigmas, constant `c`), then, with `reject`,
    a final solve on the corners within `reject` sigmas (weight 1, others 0):
    the maximum-likelihood estimate on the inliers. All rounds are one
    `lax.scan`, so the solver compiles once.

    **Arguments:**
    - `problem`, `params0`: the fixed inputs and the start (frozen parameters
      stay at their `params0` values).
    - `free`: concrete bool mask over the flattened `RefineParams`
      (`refine_parameter_names`), e.g. from `identifiable_mask`; static, so
      vmap over problems with one mask.
    - `loss`: `"cauchy"`, `"huber"` or `None` (plain least squares, one solve).
    - `c`: the loss constant in robust sigmas; `reject`: the inlier threshold of
      the final solve (robust sigmas; `None`: no final solve). Both may be
      traced: `c = reject = inf` with a robust loss is plain least squares
      with the same compiled code.
    - `rtol`, `atol`: optimistix's tolerances, on the scaled variables
      (every start Jacobian column has norm `1e4`, i.e. a unit of the solver
      variable moves the residual by `1e-4` px).

    **Returns:** a `RefineResult`.
    """
    if loss not in LOSSES:
        raise ValueError(f"loss must be one of {LOSSES}, got {loss!r}")
    several = problem.other_cameras is not None
    if (params0.angles is not None) != (problem.data.sweep_joint is not None):
        raise ValueError(
            "refine: without encoders both params0.angles (one per view) and data.sweep_joint are needed; "
            "with encoders, neither"
        )
    if problem.target_link is not None and problem.target_link.shape != (problem.T_flange_marker0.shape[0],):
        raise ValueError(
            f"refine: target_link has shape {problem.target_link.shape}, expected one link per target "
            f"({problem.T_flange_marker0.shape[0]})"
        )
    if problem.eye_in_hand and (several or problem.T_flange_marker0.shape[0] != 1):
        raise ValueError("refine: eye-in-hand takes one camera (the one mount) and no further cameras")
    if several != (params0.other_cams is not None) or (several and problem.data.camera is None):
        raise ValueError(
            "refine: with other_cameras, params0.other_cams (one twist per further camera) and "
            "data.camera (each view's camera) are needed; without, neither"
        )
    flat0, unravel = ravel_pytree(params0)
    try:
        free = np.asarray(free, bool)
    except jax.errors.TracerArrayConversionError:
        raise ValueError("refine: `free` must be a concrete mask (compute it outside jit/vmap)") from None
    if free.shape != flat0.shape:
        raise ValueError(
            f"refine: free mask has shape {free.shape}, expected {flat0.shape} (refine_parameter_names)"
        )
    idx = np.flatnonzero(free)
    if idx.size == 0:
        raise ValueError("refine: no free parameter")
    mask = problem.data.mask
    mask_f = mask.astype(flat0.dtype)

    def residual_x(x_free, w):
        return reprojection_residuals(unravel(flat0.at[idx].set(x_free)), problem, w).reshape(-1)

    x0 = flat0[idx]
    J0 = jax.jacfwd(lambda x: residual_x(x, mask_f))(x0)
    col = jnp.linalg.norm(J0, axis=0)
    scale = _COLUMN_NORM / jnp.where(col > 0, col, 1.0)

    def fn(y, w):
        return residual_x(x0 + scale * y, w)

    def corner_norms(y):
        return jnp.linalg.norm(fn(y, mask_f).reshape(mask.shape + (2,)), axis=-1)

    # Normal equations + Cholesky: the (Jacobi-scaled) Jacobian is tall and
    # well conditioned, and lineax's default QR forms the thin Q, ~500 ms a
    # step for 3000 x 40 on a CPU against 0.2 ms for the Cholesky of J^T J.
    solver = optx.LevenbergMarquardt(rtol=rtol, atol=atol, linear_solver=lx.Normal(lx.Cholesky()))
    robust = loss is not None
    n_soft = rounds if robust else 0
    final_hard = robust and reject is not None
    n_rounds = n_soft + (1 if final_hard or not robust else 0)
    if robust and reject is None:
        n_rounds = max(n_soft, 1)
    hard_flags = jnp.arange(n_rounds) == n_rounds - 1 if final_hard else jnp.zeros(n_rounds, bool)

    def weights_at(y, hard):
        e = corner_norms(y)
        s = _robust_scale(e, mask)
        soft = robust_weights(e / s, loss, c) if robust else jnp.ones_like(e)
        inl = (e / s < (reject if reject is not None else jnp.inf)) if final_hard else jnp.ones_like(mask)
        return jnp.where(hard, inl.astype(e.dtype), soft) * mask_f

    def body(carry, hard):
        y, steps, ok = carry
        w = weights_at(y, hard)
        sol = optx.least_squares(fn, solver, y, w, max_steps=max_steps, throw=False)
        good = sol.result == optx.RESULTS.successful
        y_new = jnp.where(jnp.all(jnp.isfinite(sol.value)), sol.value, y)
        return (y_new, steps + sol.stats["num_steps"], ok & good), (w, sol.result, sol.stats["num_steps"])

    y0 = jnp.zeros_like(x0)
    (y, steps, ok), (ws, results, round_steps) = jax.lax.scan(
        body, (y0, jnp.asarray(0), jnp.asarray(True)), hard_flags
    )
    w = ws[-1]
    result = optx.RESULTS.where(ok, optx.RESULTS.successful, jax.tree.map(lambda r: r[-1], results))
    x = x0 + scale * y
    flat = flat0.at[idx].set(x)
    params = unravel(flat)

    # Uncertainty: Jacobian of the (weighted) residuals at the solution.
    J = jax.jacfwd(lambda xx: residual_x(xx, w))(x)
    r = residual_x(x, w)
    used = w > 0
    n_obs = 2.0 * jnp.sum(w)
    sigma2 = jnp.sum(r**2) / jnp.maximum(n_obs - idx.size, 1.0)
    # One SVD for the covariance and the identifiability report (see _linalg).
    cov_f, sv, Vt = gauss_newton_covariance(J)
    n = flat0.shape[0]
    cov = jnp.zeros((n, n)).at[np.ix_(idx, idx)].set(sigma2 * cov_f)
    raw = projected_corners(params, problem) - problem.data.pixels
    raw = jnp.where(mask[..., None], raw, 0.0)
    inl_rms = jnp.sqrt(
        jnp.sum(jnp.where(used[..., None], raw**2, 0.0)) / jnp.maximum(2.0 * jnp.sum(used), 1.0)
    )

    model, mounts = apply_correction(problem.nominal, problem.T_flange_marker0, params.correction)
    model = eqx.tree_at(
        lambda m: (m.reduction_ratio, m.T_flange_tool),
        model,
        (problem.nominal.reduction_ratio / params.rate, mounts[0]),
    )
    K, dist = camera_matrix(params, problem)
    return RefineResult(
        params=params,
        model=model,
        T_cam_base=problem.T_cam_base0 @ se3_exp(params.cam),
        T_cam_bases=camera_poses(params, problem),
        T_flange_marker=mounts,
        K=K,
        dist=dist,
        offset_s=problem.offset0_s + _MS * params.clock_ms,
        std=jnp.sqrt(jnp.maximum(jnp.diag(cov), 0.0)),
        cov=cov,
        free=jnp.asarray(free),
        singular_values=sv,
        singular_vectors=Vt,
        sigma_px=jnp.sqrt(sigma2),
        residual_rms_px=inl_rms,
        residuals=raw,
        weights=w,
        inlier=used & mask,
        result=result,
        num_steps=steps,
        rounds_ok=ok,
        round_steps=round_steps,
    )


def fisher_std(
    problem: RefineProblem, params: RefineParams, free: np.ndarray, sigma_px: float
) -> Float[Array, " n"]:
    """Cramer-Rao bound: standard deviations from the Fisher information at
    `params` under i.i.d. Gaussian pixel noise `sigma_px` (zero where frozen)."""
    flat, unravel = ravel_pytree(params)
    idx = np.flatnonzero(np.asarray(free, bool))
    J = jax.jacfwd(lambda x: reprojection_residuals(unravel(flat.at[idx].set(x)), problem).reshape(-1))(
        flat[idx]
    )
    cov = sigma_px**2 * jnp.linalg.inv(J.T @ J)
    return jnp.zeros(flat.shape).at[idx].set(jnp.sqrt(jnp.diag(cov)))


def summarize_refinement(
    res: RefineResult,
    names: list[str],
    data: CornerData,
    *,
    corr_threshold: float = 0.95,
    weak_ratio: float = 1e-6,
    outlier_fraction: float = 0.5,
) -> dict:
    """Plain-Python report of a `RefineResult` (NumPy; outside jit).

    **Returns:** a dict with the solver status, `sigma_px`, inlier RMS,
    `correlations` (pairs of free parameters with |rho| above
    `corr_threshold`), `weak_directions` (right singular vectors of the
    column-normalised Jacobian with singular value under `weak_ratio` of the
    largest, each named by its dominant parameters), the number of
    `outlier_corners` (rejected, or weight under 0.1), and `outlier_frames`:
    dataset rows (`data.frame`) with more than `outlier_fraction` of their
    corners outliers.
    """
    free = np.asarray(res.free)
    idx = np.flatnonzero(free)
    cov = np.asarray(res.cov)[np.ix_(idx, idx)]
    sd = np.sqrt(np.maximum(np.diag(cov), 1e-300))
    corr = cov / sd[:, None] / sd[None, :]
    a, b = np.nonzero(np.triu(np.abs(corr) > corr_threshold, k=1))
    pairs = [{"a": names[idx[i]], "b": names[idx[j]], "rho": float(corr[i, j])} for i, j in zip(a, b)]
    sv = np.asarray(res.singular_values)
    Vt = np.asarray(res.singular_vectors)
    weak = []
    for k in np.flatnonzero(sv < weak_ratio * sv[0]):
        v = Vt[k]
        top = np.argsort(-np.abs(v))[:4]
        weak.append(
            {
                "singular_value_ratio": float(sv[k] / sv[0]),
                "parameters": {names[idx[i]]: float(v[i]) for i in top if abs(v[i]) > 0.1},
            }
        )
    real = np.asarray(data.mask)
    bad = (~np.asarray(res.inlier) | (np.asarray(res.weights) < 0.1)) & real
    per_view = bad.sum(-1) / np.maximum(real.sum(-1), 1)
    out_frames = sorted({int(f) for f, p in zip(np.asarray(data.frame), per_view) if p > outlier_fraction})
    return {
        "solver": {
            "result": "successful" if bool(res.result == optx.RESULTS.successful) else "failed",
            "steps": int(res.num_steps),
        },
        "sigma_px": float(res.sigma_px),
        "inlier_rms_px": float(res.residual_rms_px),
        "corners": int(real.sum()),
        "outlier_corners": int(bad.sum()),
        "outlier_frames": out_frames,
        "correlations": pairs,
        "condition_number": float(sv[0] / sv[-1]) if sv.size else float("nan"),
        "weak_directions": weak,
    }


def grid_points(cols: int = 4, rows: int = 3, spacing: float = 0.04) -> np.ndarray:
    """A planar grid of corners in a target frame (m), like a ChArUco board's inner corners."""
    i, j = np.meshgrid(np.arange(cols), np.arange(rows))
    return np.stack([(i.ravel() + 1) * spacing, (j.ravel() + 1) * spacing, np.zeros(i.size)], axis=-1)


def sweep_corner_data(
    points: np.ndarray, num_joints: int, frames: int, range_deg: float, *, dt: float = 0.05
) -> CornerData:
    """Corner views of joint-by-joint sweeps (joint j turns through `range_deg`
    centred on zero in `frames` frames, the others at zero), one target, for
    synthetic studies: the encoder log holds exactly the frames' commanded
    positions at their stamps (`dt` apart), and `pixels` are zero (fill them
    with `projected_corners` of a truth plus noise)."""
    half = 0.5 * np.radians(range_deg)
    ramp = np.linspace(-half, half, frames)
    q = (np.eye(num_joints)[:, None, :] * ramp[None, :, None]).reshape(-1, num_joints)
    V = q.shape[0]
    t = dt * np.arange(V)
    pts = [np.asarray(points, np.float64)] * V
    return make_corner_data(pts, [np.zeros((len(points), 2))] * V, np.zeros(V, int), np.arange(V), t, t, q)
