"""Second error function: measured joint axes -> kinematic parameters + camera-to-base.

Seed method, step 5. The arc fits give, in the camera frame, every joint's axis
line (measured with the other joints at their commanded zero) and, with
encoders, the marker pose at the zero configuration. The model predicts both:
joint $j$'s axis is `joint_axes(model, 0)[j]` mapped by $T_{cam,base}$, and the
marker pose is $T_{cam,base}\\,T_{base,flange}(0)\\,T_{flange,marker}$. We
solve for corrections to the nominal model and for $T_{cam,base}$.

Residuals are expressed in each arc fit's own line coordinates
$(u, v, w_1, w_2)$ (see `jaxcal._arcfit`): the model line's gnomonic
direction about the measured reference direction and its crossing point with
the measured reference plane. Their norms are the direction difference and
the line-to-line distance ($d_2$ and $d_1$ of the method) near the solution,
they are smooth where the distance is not (at zero), parallel lines are no
special case, and the arc fit's covariance whitens them exactly. The marker
zero poses enter the same way, in the arc fit's $(p_m, r_m)$ coordinates.

Identifiability: the camera sees lines, not frames, so some corrections
cannot be told apart (the base frame's rotation about and translation along
joint 1's axis against $T_{cam,base}$, a joint frame's spin about its own
axis against its zero offset, ...). `identifiable_mask` finds them
numerically by a rank-revealing, column-pivoted Gram-Schmidt of the
whitened Jacobian in a fixed priority order, and they are held at nominal.
"""

import itertools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, Bool, Float, Int

from ._arcfit import ArcFitResult, line_to_params
from ._geometry import make_pose, matmul, pose_inverse, se3_exp, so3_log
from ._kinematics import KinematicModel, forward_kinematics, joint_axes

_POSE_NAMES = ("tx", "ty", "tz", "rx", "ry", "rz")


class KinematicCorrection(eqx.Module):
    """Corrections to a nominal model, the unknowns of a kinematic calibration.

    - `origin`: per joint, a twist $(v, \\omega)$ (m, rad) right-multiplying the
      origin, `T_parent_joint @ se3_exp(origin[j])` (i.e. in the joint frame).
    - `zero_offset`: added to the zero offsets (rad).
    - `tool`: per marker, a twist right-multiplying the marker mount
      `T_flange_marker`.
    """

    origin: Float[Array, "joints 6"]
    zero_offset: Float[Array, " joints"]
    tool: Float[Array, "markers 6"]


class AxisFitParams(eqx.Module):
    """All unknowns of the axis fit: model corrections and `T_cam_base = T0 @ se3_exp(cam)`."""

    cam: Float[Array, "6"]
    correction: KinematicCorrection


def apply_correction(
    model: KinematicModel, T_flange_marker: Float[Array, "markers 4 4"], corr: KinematicCorrection
) -> tuple[KinematicModel, Float[Array, "markers 4 4"]]:
    """The corrected model and marker mounts."""
    dT = jax.vmap(se3_exp)(corr.origin)
    new = eqx.tree_at(
        lambda m: (m.T_parent_joint, m.zero_offset),
        model,
        (matmul(model.T_parent_joint, dT), model.zero_offset + corr.zero_offset),
    )
    mounts = matmul(T_flange_marker, jax.vmap(se3_exp)(corr.tool))
    return new, mounts


def parameter_names(model: KinematicModel, num_markers: int) -> list[str]:
    """Names of the flattened `AxisFitParams` (the order of `ravel_pytree`)."""
    names = [f"T_cam_base.{p}" for p in _POSE_NAMES]
    for j in model.joint_names:
        names += [f"{j}.origin.{p}" for p in _POSE_NAMES]
    names += [f"{j}.zero_offset" for j in model.joint_names]
    marker = ["marker"] if num_markers == 1 else [f"marker{m}" for m in range(num_markers)]
    for mk in marker:
        names += [f"{mk}.mount.{p}" for p in _POSE_NAMES]
    return names


def _priority(model: KinematicModel, num_markers: int) -> np.ndarray:
    """Column order for the identifiability search: camera first, then the
    marker mount, zero offsets, and the joint origins from base to tip (a
    dependent column is frozen, so earlier groups are preferred)."""
    n = model.num_joints
    idx = np.arange(6 + 6 * n + n + 6 * num_markers)
    cam = idx[:6]
    origin = idx[6 : 6 + 6 * n]
    zero = idx[6 + 6 * n : 6 + 7 * n]
    tool = idx[6 + 7 * n :]
    return np.concatenate([cam, tool, zero, origin])


class AxisFitProblem(eqx.Module):
    """Everything fixed during the axis fit."""

    nominal: KinematicModel
    T_flange_marker0: Float[Array, "markers 4 4"]
    T_cam_base0: Float[Array, "4 4"]
    arcs: ArcFitResult  # stacked over joints
    sqrt_info: Float[Array, "joints k k"]
    use_poses: bool = eqx.field(static=True)


def _meas_dim(arcs: ArcFitResult, use_poses: bool) -> int:
    return arcs.meas.shape[-1] if use_poses else 4


def axis_residuals(params: AxisFitParams, problem: AxisFitProblem) -> Float[Array, "joints k"]:
    """Whitened residuals of the second error function, one row per joint sweep."""
    model, mounts = apply_correction(problem.nominal, problem.T_flange_marker0, params.correction)
    T_cam_base = problem.T_cam_base0 @ se3_exp(params.cam)
    q0 = jnp.zeros(model.num_joints)
    points, dirs = joint_axes(model, q0)
    points_c = points @ T_cam_base[:3, :3].T + T_cam_base[:3, 3]
    dirs_c = dirs @ T_cam_base[:3, :3].T
    arcs = problem.arcs
    sign_free = not arcs.has_encoder
    lines = jax.vmap(lambda p, d, R, c: line_to_params(p, d, R, c, sign_free=sign_free))(
        points_c, dirs_c, arcs.R_ref, arcs.c
    )
    k = _meas_dim(arcs, problem.use_poses)
    pred = lines
    if problem.use_poses:
        T_cam_marker = T_cam_base @ forward_kinematics(model, q0)[-1] @ mounts  # (M, 4, 4)
        p_m = T_cam_marker[:, :3, 3]  # (M, 3)
        parts = [lines, jnp.broadcast_to(p_m.reshape(-1), (lines.shape[0], p_m.size))]
        if k > 4 + p_m.size:  # orientations were measured
            r_m = jax.vmap(
                lambda O_ref: jax.vmap(lambda Oref_m, T: so3_log(Oref_m.T @ T[:3, :3]))(O_ref, T_cam_marker)
            )(arcs.O_ref)  # (J, M, 3)
            parts.append(r_m.reshape(lines.shape[0], -1))
        pred = jnp.concatenate(parts, axis=-1)
    e = pred - arcs.meas[:, :k]
    return jnp.einsum("jab,jb->ja", problem.sqrt_info, e)


def _whitening(cov: Float[Array, "k k"]) -> Float[Array, "k k"]:
    """$W$ with $W^T W = \\Sigma^{-1}$ (inverse Cholesky factor), regularised."""
    k = cov.shape[0]
    scale = jnp.sqrt(jnp.maximum(jnp.diag(cov), 1e-300))
    C = cov / scale[:, None] / scale[None, :] + 1e-12 * jnp.eye(k)
    L = jnp.linalg.cholesky(C)
    W = jax.scipy.linalg.solve_triangular(L, jnp.eye(k), lower=True)
    return W / scale[None, :]


def register_lines(nominal: KinematicModel, arcs: ArcFitResult) -> Float[Array, "4 4"]:
    """Closed-form `T_cam_base` start: align the nominal axes with the measured ones.

    Rotation by Kabsch on the axis directions (with encoders the signs are
    known; without, every sign pattern is tried and the best kept), then the
    translation by linear least squares on the line offsets,
    $(I - d d^T)(R q + t - Q) = 0$ per joint.
    """
    points, dirs = joint_axes(nominal, jnp.zeros(nominal.num_joints))
    D = arcs.direction
    w = 1.0 / jnp.maximum(jnp.trace(arcs.cov[:, :3, :3], axis1=-2, axis2=-1), 1e-16)
    w = w / jnp.max(w)

    def register(signs):
        H = jnp.einsum("j,ja,jb->ab", w * signs, D, dirs)  # sum w s D d^T
        U, _, Vt = jnp.linalg.svd(H)
        S = jnp.diag(jnp.array([1.0, 1.0, jnp.sign(jnp.linalg.det(U @ Vt))]))
        R = U @ S @ Vt
        dirs_c = dirs @ R.T
        Pj = jnp.eye(3) - dirs_c[:, :, None] * dirs_c[:, None, :]  # (J, 3, 3)
        rhs = jnp.einsum("jab,jb->ja", Pj, arcs.point - points @ R.T)
        A = (Pj * w[:, None, None]).reshape(-1, 3)
        t = jnp.linalg.lstsq(A, (rhs * w[:, None]).reshape(-1))[0]
        # Directions (rad^2) and line offsets (in units of 10 cm) together: when the
        # axes span only a plane (a UR arm at zero), a half turn maps every line
        # onto a line with the opposite sign, and only the offsets tell them apart.
        pos = jnp.einsum("jab,jb->ja", Pj, points @ R.T + t - arcs.point)
        cost = (
            jnp.sum(w * jnp.sum((signs[:, None] * D - dirs_c) ** 2, -1))
            + jnp.sum(w * jnp.sum(pos**2, -1)) / 0.1**2
        )
        return make_pose(R, t), cost

    n = nominal.num_joints
    if arcs.has_encoder:
        T, _ = register(jnp.ones(n))
        return T
    patterns = jnp.array(list(itertools.product([1.0, -1.0], repeat=n - 1)))
    patterns = jnp.concatenate([jnp.ones((patterns.shape[0], 1)), patterns], axis=1)
    Ts, costs = jax.vmap(register)(patterns)
    return Ts[jnp.argmin(costs)]


def identifiable_mask(
    problem: AxisFitProblem, params: AxisFitParams, *, tol: float = 1e-7
) -> tuple[Bool[Array, " n"], Float[Array, " n"]]:
    """Which parameters the measurements determine, by greedy column selection.

    The whitened Jacobian's columns are normalised and visited in the
    priority order of `_priority`; a column is kept when its component
    orthogonal to the span of the kept ones is above `tol` (a
    column-pivoted, rank-revealing Gram-Schmidt QR with a fixed pivot
    order). Pure and vmappable.

    **Returns:** `(free, independence)` over the flattened parameters; the
    independence is each column's relative distance from the kept span.
    """
    flat, unravel = ravel_pytree(params)
    J = jax.jacfwd(lambda x: axis_residuals(unravel(x), problem).reshape(-1))(flat)
    norms = jnp.linalg.norm(J, axis=0)
    Jn = J / jnp.where(norms > 0, norms, 1.0)
    order = jnp.asarray(_priority(problem.nominal, problem.T_flange_marker0.shape[0]))
    m, n = J.shape
    basis0 = jnp.zeros((m, n))

    def body(i, carry):
        basis, keep, indep, count = carry
        col = Jn[:, order[i]]
        resid = col - basis @ (basis.T @ col)
        resid = resid - basis @ (basis.T @ resid)  # re-orthogonalise
        r = jnp.linalg.norm(resid)
        ok = (r > tol) & (norms[order[i]] > 0)
        basis = jnp.where(ok, basis.at[:, count].set(resid / jnp.where(ok, r, 1.0)), basis)
        return basis, keep.at[order[i]].set(ok), indep.at[order[i]].set(r), count + ok

    init = (basis0, jnp.zeros(n, bool), jnp.zeros(n), jnp.asarray(0))
    _, keep, indep, _ = jax.lax.fori_loop(0, n, body, init)
    return keep, indep


class AxisFitResult(eqx.Module):
    """Calibrated model and camera pose from the axis fit.

    - `model`: the calibrated `KinematicModel` (reduction ratios from the arcs
      when encoders were used), `T_flange_marker`: calibrated marker mounts.
    - `T_cam_base`: the camera-to-base transform (maps base points into the camera).
    - `params`, `std`: the fitted corrections (`AxisFitParams`) and their
      standard deviations (flattened, in `parameter_names` order; 0 where frozen).
    - `free`: which parameters were estimated; the others are held at nominal
      because the data cannot see them (`independence` tells how far each
      was from the span of the kept ones; NaN when the mask was given).
    - `cov`: covariance of the flattened parameters.
    - `result`, `num_steps`: optimistix's result and step count.
    - `residual_rms`: RMS of the whitened residuals.
    - `singular_values`: of the whitened Jacobian of the free parameters at the solution.
    """

    model: KinematicModel
    T_flange_marker: Float[Array, "markers 4 4"]
    T_cam_base: Float[Array, "4 4"]
    params: AxisFitParams
    std: Float[Array, " n"]
    cov: Float[Array, "n n"]
    free: Bool[Array, " n"]
    independence: Float[Array, " n"]
    result: optx.RESULTS
    num_steps: Int[Array, ""]
    residual_rms: Float[Array, ""]
    singular_values: Float[Array, " n"]


def fit_axes(
    nominal: KinematicModel,
    arcs: ArcFitResult,
    *,
    T_flange_marker: Float[Array, "markers 4 4"] | None = None,
    T_cam_base0: Float[Array, "4 4"] | None = None,
    use_poses: bool | None = None,
    free: Bool[Array, " n"] | None = None,
    rtol: float = 1e-8,
    atol: float = 3e-2,
    max_steps: int = 100,
    throw: bool = False,
) -> AxisFitResult:
    """Solve the axis-to-kinematics problem; pure, jittable and vmappable.

    **Arguments:**
    - `nominal`: the datasheet model (its `T_flange_tool` is ignored; the
      marker mounts are `T_flange_marker`).
    - `arcs`: the arc fits of every joint, stacked (vmap `fit_arc` over joints),
      in joint order.
    - `T_flange_marker`: nominal marker mounts `(markers, 4, 4)`; default:
      derived from the measured zero pose and the initial `T_cam_base`.
    - `T_cam_base0`: a start for the camera pose; default `register_lines`.
    - `use_poses`: use the marker zero poses (default: when encoders were used,
      since only then is the zero configuration known in the sweep).
    - `free`: a mask of parameters to estimate, flattened in
      `parameter_names` order (default: `identifiable_mask` at the start).
      Pass a mask computed once for many trials to freeze the same ones.

    **Returns:** an `AxisFitResult`.
    """
    n_axes = arcs.direction.shape[0] if arcs.direction.ndim == 2 else 0
    if arcs.direction.ndim != 2 or n_axes != nominal.num_joints:
        raise ValueError(
            f"{n_axes} measured axes for a model with {nominal.num_joints} joints: "
            "stack one arc fit per joint, in joint order"
        )
    n_markers = arcs.T_cam_marker0.shape[1]
    if use_poses is None:
        use_poses = arcs.has_encoder
    if T_cam_base0 is None:
        T_cam_base0 = register_lines(nominal, arcs)
    if T_flange_marker is None:
        # Marker at zero, seen by the first joint's sweep: T_flange_marker =
        # (T_cam_base T_base_flange(0))^-1 T_cam_marker0.
        T_cam_flange = T_cam_base0 @ forward_kinematics(nominal, jnp.zeros(nominal.num_joints))[-1]
        T_flange_marker = jnp.einsum("ab,mbc->mac", pose_inverse(T_cam_flange), arcs.T_cam_marker0[0])
    k = _meas_dim(arcs, use_poses)
    W = jax.vmap(_whitening)(arcs.meas_cov[:, :k, :k])
    problem = AxisFitProblem(
        nominal=nominal,
        T_flange_marker0=T_flange_marker,
        T_cam_base0=T_cam_base0,
        arcs=arcs,
        sqrt_info=W,
        use_poses=use_poses,
    )
    n = nominal.num_joints
    params0 = AxisFitParams(
        cam=jnp.zeros(6),
        correction=KinematicCorrection(
            origin=jnp.zeros((n, 6)), zero_offset=jnp.zeros(n), tool=jnp.zeros((n_markers, 6))
        ),
    )
    flat0, unravel = ravel_pytree(params0)
    if free is None:
        keep, indep = identifiable_mask(problem, params0)
    else:
        keep = jnp.asarray(free, bool)
        if keep.shape != flat0.shape:
            raise ValueError(
                f"free mask has shape {keep.shape}, expected {flat0.shape} (see parameter_names)"
            )
        indep = jnp.full(flat0.shape, jnp.nan)
    keep_f = keep.astype(flat0.dtype)

    def fn(x, problem):
        return axis_residuals(unravel(x * keep_f), problem)

    solver = optx.LevenbergMarquardt(rtol=rtol, atol=atol)
    sol = optx.least_squares(fn, solver, flat0, problem, max_steps=max_steps, throw=throw)
    x = sol.value * keep_f
    params = unravel(x)
    J = jax.jacfwd(lambda y: fn(y, problem).reshape(-1))(x) * keep_f[None, :]
    cov = (
        jnp.linalg.pinv(J.T @ J + jnp.diag(1.0 - keep_f), hermitian=True) * keep_f[:, None] * keep_f[None, :]
    )
    r = fn(x, problem)
    model, mounts = apply_correction(nominal, T_flange_marker, params.correction)
    if arcs.has_encoder:
        model = eqx.tree_at(lambda m: m.reduction_ratio, model, nominal.reduction_ratio / arcs.rate)
    return AxisFitResult(
        model=eqx.tree_at(lambda m: m.T_flange_tool, model, mounts[0]),
        T_flange_marker=mounts,
        T_cam_base=T_cam_base0 @ se3_exp(params.cam),
        params=params,
        std=jnp.sqrt(jnp.maximum(jnp.diag(cov), 0.0)),
        cov=cov,
        free=keep,
        independence=indep,
        result=sol.result,
        num_steps=sol.stats["num_steps"],
        residual_rms=jnp.sqrt(jnp.mean(r**2)),
        singular_values=jnp.linalg.svd(J, compute_uv=False),
    )
