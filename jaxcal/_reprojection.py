"""The reprojection model: every detected corner predicted from the robot, the cameras and the clock.

Corner $k$ of the target seen in view $v$ (one target in one frame) is
predicted at

$$\\hat u_{vk} = \\pi_{K,d}\\big(T_{cam,base}\\;T_{base,flange}(q_v)\\;
T_{flange,target}\\;X_k\\big),\\qquad
q_v = r \\odot q_{log}\\big((t_{cam,v} - \\delta)/(1+\\epsilon)\\big),$$

with $\\pi_{K,d}$ the pinhole projection with OpenCV's distortion model
$(k_1, k_2, p_1, p_2, k_3)$, $T_{base,flange}$ the forward kinematics of the
corrected model, $q_{log}$ the encoder log (commanded positions, motor angle
over the nominal ratio) interpolated at controller time, $r$ the rate
(nominal over true reduction ratio) and $\\delta$ the clock offset. The
residual is $\\hat u_{vk} - u_{vk}$ (px) for every corner of every view:
padded arrays with a mask, vmapped over views. `jaxcal._refine` solves it.

A rolling-shutter camera (line delay $\\ell_c$, s per row) reads its rows
out one after the other: corner $k$ of view $v$, detected at row $y_{vk}$
(px, 0 at the top: the row the frame's time refers to), is seen at
$t_{cam,v} + y_{vk}\\,\\ell_c$, and predicted at the joint angles of that
instant, $q_{vk} = r \\odot q_{log}\\big((t_{cam,v} + y_{vk}\\ell_c -
\\delta)/(1+\\epsilon)\\big)$, each corner through its own chain
(`CornerData.row`, `RefineProblem.line_delay0_s`, `RefineParams.line_delay_us`).
Without rows every corner of a view is seen at $t_{cam,v}$ (a global shutter).

A real arm's joints stand off their rigid angles by the non-geometric terms
(`jaxcal._terms`): every view's joint angles gain $\\Delta_j = \\sum_k e_{j,k}
b_{vjk}$, the coefficients `RefineParams.terms` over the view's basis
(`CornerData.term_basis`, evaluated once at its commanded pose and approach).

This module holds the data (`CornerData`, `RefineProblem`), the unknowns
(`RefineParams`, laid out by `jaxcal._correction.ParameterLayout`) and the
pure functions of the model; no solver.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from ._clocksync import controller_time, interpolate_encoders
from ._correction import KinematicCorrection, apply_correction
from ._device import to_device
from ._geometry import se3_exp, skew
from ._kinematics import REVOLUTE, KinematicModel
from ._terms import correction

_MS = 1e-3


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
    - `line_delay_us`: with rolling-shutter cameras (`CornerData.row`), each
      camera's line-delay increment over `RefineProblem.line_delay0_s` (us per
      row), `(cameras,)`; `None` without. After `angles` in the flattened order.
    - `terms`: with non-geometric terms (`RefineProblem.terms`), their coefficients
      (`jaxcal._terms.names` order); `None` without. Last in the flattened order.
    """

    cam: Float[Array, "6"]
    correction: KinematicCorrection
    rate: Float[Array, " joints"]
    clock_ms: Float[Array, ""]
    intrinsics: Float[Array, "9"]
    other_cams: Float[Array, "others 6"] | None = None
    angles: Float[Array, " views"] | None = None
    line_delay_us: Float[Array, " cameras"] | None = None
    terms: Float[Array, " k"] | None = None


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
    - `sweep_home`: without encoders, the commanded configuration the other
      joints hold in each view (its sweep's home; `None`: zero).
    - `sweep_joint`: without encoders, which joint sweeps alone in each view
      (the others at zero); with `RefineParams.angles` the encoder log is
      not used.
    - `row`: with a rolling shutter, each corner's image row (px, 0 at the top
      row, the one `t_cam` refers to), `(views, corners)`; `None`: every corner
      at its view's `t_cam`.
    - `term_basis`: with non-geometric terms, each view's basis
      (`jaxcal._terms.term_basis` at its commanded pose and approach),
      `(views, joints, k)`; `None` without.
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
    sweep_home: Float[Array, "views joints"] | None = None
    row: Float[Array, "views corners"] | None = None
    term_basis: Float[Array, "views joints k"] | None = None


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

    `line_delay0_s`: with `data.row`, every camera's line delay at the start
    (s per row; the first camera, then `other_cameras`), `(cameras,)`.

    `terms`: the non-geometric term families `params.terms` and `data.term_basis`
    hold (`jaxcal._terms`); `()` without.
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
    line_delay0_s: Float[Array, " cameras"] | None = None
    terms: tuple[str, ...] = eqx.field(static=True, default=())


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
    views: int | None = None,
    sweep_home: np.ndarray | None = None,
    row: list | None = None,
    term_basis: np.ndarray | None = None,
) -> CornerData:
    """Pad per-view corner lists into a `CornerData` (NumPy in, arrays out).

    **Arguments:** `points[v]` `(n_v, 3)` target-frame corners (m) and
    `pixels[v]` `(n_v, 2)` their detections (px) of view `v`; `target`,
    `frame`, `t_cam` `(views,)`; the encoder log `enc_t (T,)`, `enc_q (T, joints)`;
    `camera` `(views,)` (see `CornerData`; default all 0); `sweep_joint`
    `(views,)` for a refinement without encoders; `views`: pad to this many
    views (masked out; frame -1, the first view's stamp), so that captures of
    similar size share the compiled refinement; `row[v]` `(n_v,)`: with a
    rolling shutter, each corner's image row (px; usually `pixels[v][:, 1]`);
    `term_basis` `(views, joints, k)`: with non-geometric terms, each view's basis.
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
    Y = np.zeros((V, P))
    m = np.zeros((V, P), bool)
    if row is not None and len(row) != V:
        raise ValueError(f"make_corner_data: {V} point sets but {len(row)} row sets")
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
        if row is not None:
            y = np.asarray(row[v], np.float64).reshape(-1)
            if len(y) != len(x) or not np.all(np.isfinite(y)):
                raise ValueError(
                    f"make_corner_data: view {v} (frame {frame[v]}) has {len(x)} points but "
                    f"{len(y)} rows, or non-finite rows"
                )
            Y[v, : len(y)] = y
    pad = 0 if views is None else int(views) - V
    if pad < 0:
        raise ValueError(f"make_corner_data: {V} views do not fit in {views}")

    def padded(a, fill, dtype):
        a = np.asarray(a, dtype)
        return np.concatenate([a, np.full((pad,) + a.shape[1:], fill, dtype)])

    X, U, m = padded(X, 0.0, np.float64), padded(U, 0.0, np.float64), padded(m, False, bool)
    Y = None if row is None else padded(Y, 0.0, np.float64)
    camera = None if camera is None else padded(camera, 0, np.int64)
    sweep_joint = None if sweep_joint is None else padded(sweep_joint, 0, np.int64)
    sweep_home = None if sweep_home is None else padded(sweep_home, 0.0, np.float64)
    if term_basis is not None and len(term_basis) != V:
        raise ValueError(f"make_corner_data: {V} point sets but {len(term_basis)} term bases")
    term_basis = None if term_basis is None else padded(term_basis, 0.0, np.float64)
    return CornerData(
        points=to_device(X),
        pixels=to_device(U),
        mask=to_device(m),
        target=to_device(padded(target, 0, np.int64)),
        frame=to_device(padded(frame, -1, np.int64)),
        t_cam=to_device(padded(t_cam, float(np.asarray(t_cam)[0]), np.float64)),
        enc_t=to_device(enc_t),
        enc_q=to_device(enc_q),
        drift_ppm=to_device(np.float64(drift_ppm)),
        camera=None if camera is None else to_device(camera, np.int64),
        sweep_joint=None if sweep_joint is None else to_device(sweep_joint, np.int64),
        sweep_home=None if sweep_home is None else to_device(sweep_home),
        row=None if Y is None else to_device(Y),
        term_basis=None if term_basis is None else to_device(term_basis),
    )


def num_other_cameras(problem: RefineProblem) -> int:
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


def line_delays(params: RefineParams, problem: RefineProblem) -> Float[Array, " cameras"]:
    """Every camera's line delay at `params` (s per row): `line_delay0_s` plus the increments."""
    ell = problem.line_delay0_s
    return ell if params.line_delay_us is None else ell + 1e-6 * params.line_delay_us


def corner_times(params: RefineParams, problem: RefineProblem) -> Float[Array, "views corners"]:
    """Every corner's camera-clock time (s): its view's `t_cam` plus its row times its
    camera's line delay, $t_{cam,v} + y_{vk}\\,\\ell_c$ (`CornerData.row` needed)."""
    data = problem.data
    if data.row is None or problem.line_delay0_s is None:
        raise ValueError("corner_times: needs data.row and problem.line_delay0_s (a rolling shutter)")
    ell = line_delays(params, problem)
    ell_v = ell[0] if data.camera is None else ell[data.camera]
    return data.t_cam[:, None] + data.row * ell_v[..., None]


def joint_positions(
    params: RefineParams, problem: RefineProblem, *, per_corner: bool = False
) -> Float[Array, "views joints"] | Float[Array, "views corners joints"]:
    """Commanded joint positions of every view, $r \\odot q_{log}(t_{ctrl})$ (rad);
    without encoders (`params.angles`), the sweeping joint at its unknown
    angle and the others at its sweep's home (`CornerData.sweep_home`, zero by default).
    With `per_corner` (a rolling shutter), every corner's at its own time
    (`corner_times`), `(views, corners, joints)`."""
    data = problem.data
    if params.angles is not None:
        n = problem.nominal.num_joints
        q = jax.nn.one_hot(data.sweep_joint, n, dtype=params.angles.dtype) * params.angles[:, None]
        return q if data.sweep_home is None else q + data.sweep_home
    offset = problem.offset0_s + _MS * params.clock_ms
    t_cam = corner_times(params, problem) if per_corner else data.t_cam
    t = controller_time(t_cam, offset, data.drift_ppm)
    q = jax.vmap(lambda qj: interpolate_encoders(t, data.enc_t, qj), out_axes=-1)(data.enc_q.T)
    return q * params.rate


def rolling(problem: RefineProblem) -> bool:
    """The corners are seen row by row (`CornerData.row` and line delays given)."""
    return problem.data.row is not None and problem.line_delay0_s is not None


# Nested jit, traced once per signature (see `_arcmodel.arc_terms`).
@jax.jit
def chain(
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
    return _chain_at(params, problem, joint_positions(params, problem))


def _chain_at(
    params: RefineParams, problem: RefineProblem, q: Float[Array, "views joints"]
) -> tuple[Float[Array, "views 3 3"], Float[Array, "views 3"]]:
    """`chain` at the commanded joint positions `q` of every view."""
    model, mounts = apply_correction(problem.nominal, problem.T_flange_marker0, params.correction)
    theta = q + model.zero_offset  # (V, J)
    if params.terms is not None:
        theta = theta + correction(problem.terms, params.terms, problem.data.term_basis)
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
    R, t = chain(params, problem)
    bottom = jnp.broadcast_to(jnp.array([0.0, 0.0, 0.0, 1.0]), (R.shape[0], 1, 4))
    return jnp.concatenate([jnp.concatenate([R, t[..., None]], axis=-1), bottom], axis=-2)


@jax.jit
def corner_chain(
    params: RefineParams, problem: RefineProblem
) -> tuple[Float[Array, "views corners 3 3"], Float[Array, "views corners 3"]]:
    """`chain` of every corner at its own time (a rolling shutter, `rolling(problem)`)."""
    q = joint_positions(params, problem, per_corner=True)  # (V, P, J)
    return jax.vmap(lambda qk: _chain_at(params, problem, qk), in_axes=1, out_axes=1)(q)


def projected_corners(params: RefineParams, problem: RefineProblem) -> Float[Array, "views corners 2"]:
    """Every corner reprojected at `params` (px), padding included; with a rolling
    shutter each corner through the chain at its own time (`corner_chain`)."""
    if rolling(problem):
        R, t = corner_chain(params, problem)
        X = jnp.einsum("vkab,vkb->vka", R, problem.data.points) + t
    else:
        R, t = chain(params, problem)
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
