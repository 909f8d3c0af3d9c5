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

import functools
import itertools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, Bool, Float, Int

from . import _lsq
from ._arcfit import ArcFitResult
from ._arcmodel import line_to_params
from ._correction import KinematicCorrection as KinematicCorrection  # re-exported
from ._correction import ParameterLayout, apply_correction, zero_correction
from ._geometry import make_pose, matmul, pose_inverse, se3_exp, skew, so3_log, so3_right_jacobian_inv
from ._kinematics import PRISMATIC, REVOLUTE, KinematicModel, forward_kinematics, joint_axes, joint_motion
from ._linalg import after, nearest_rotation
from ._lsq import LMOptions


class AxisFitParams(eqx.Module):
    """All unknowns of the axis fit: model corrections and `T_cam_base = T0 @ se3_exp(cam)`."""

    cam: Float[Array, "6"]
    correction: KinematicCorrection


def parameter_names(model: KinematicModel, num_markers: int) -> list[str]:
    """Names of the flattened `AxisFitParams` (the order of `ravel_pytree`; see `jaxcal._correction`)."""
    return ParameterLayout.of(model, num_markers).names(refine=False)


class AxisFitProblem(eqx.Module):
    """Everything fixed during the axis fit.

    `home`: per joint sweep (row), the commanded configuration of the other
    joints while it swept, its own entry zero (the encoder zero its arc's
    zero pose refers to); `None`: every sweep from the zero configuration.
    """

    nominal: KinematicModel
    T_flange_marker0: Float[Array, "markers 4 4"]
    T_cam_base0: Float[Array, "4 4"]
    arcs: ArcFitResult  # stacked over joints
    sqrt_info: Float[Array, "joints k k"]
    use_poses: bool = eqx.field(static=True)
    home: Float[Array, "joints joints"] | None = None


def _meas_dim(arcs: ArcFitResult, use_poses: bool) -> int:
    return arcs.meas.shape[-1] if use_poses else 4


def measured_rows(model: KinematicModel, k: int) -> np.ndarray:
    """Which of every sweep's `k` residuals are measured, `(joints, k)` (static):
    all but a prismatic joint's line position $(w_1, w_2)$ (a translation has
    no axis position; `jaxcal._arcfit.fit_line`), which are zeroed."""
    keep = np.ones((model.num_joints, k))
    keep[[j for j, t in enumerate(model.joint_types) if t == PRISMATIC], 2:4] = 0.0
    return keep


def _axis_residuals_autodiff(params: AxisFitParams, problem: AxisFitProblem) -> Float[Array, "joints k"]:
    """`axis_residuals` written with the model's own `joint_axes` and `forward_kinematics`,
    differentiated by JAX (the reference the closed-form Jacobian is tested against)."""
    model, mounts = apply_correction(problem.nominal, problem.T_flange_marker0, params.correction)
    T_cam_base = problem.T_cam_base0 @ se3_exp(params.cam)
    n = model.num_joints
    home = jnp.zeros((n, n)) if problem.home is None else problem.home
    # Joint j's axis and the marker, each at its own sweep's home configuration.
    points, dirs = jax.vmap(lambda q, j: jax.tree.map(lambda a: a[j], joint_axes(model, q)))(
        home, jnp.arange(n)
    )
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
        T_cam_marker = jax.vmap(lambda q: T_cam_base @ forward_kinematics(model, q)[-1] @ mounts)(
            home
        )  # (J, M)
        p_m = T_cam_marker[..., :3, 3]  # (J, M, 3)
        parts = [lines, p_m.reshape(n, -1)]
        if k > 4 + p_m[0].size:  # orientations were measured
            r_m = jax.vmap(
                lambda O_ref, T_j: jax.vmap(lambda Oref_m, T: so3_log(Oref_m.T @ T[:3, :3]))(O_ref, T_j)
            )(arcs.O_ref, T_cam_marker)  # (J, M, 3)
            parts.append(r_m.reshape(n, -1))
        pred = jnp.concatenate(parts, axis=-1)
    e = (pred - arcs.meas[:, :k]) * measured_rows(model, k)
    return jnp.einsum("jab,jb->ja", problem.sqrt_info, e)


def _se3_exp_body_jacobian(xi: Float[Array, "6"]) -> tuple[Float[Array, "4 4"], Float[Array, "6 6"]]:
    """`T = se3_exp(xi)` and $B$ with $T^{-1}\\,dT = (B\\,d\\xi)^\\wedge$ (body twist, `(v, w)`).

    $B$ is the right Jacobian of SE(3), taken here by forward-mode autodiff of the
    6-input map (six tangents through one small function, exact to round-off).
    """
    eye = jnp.eye(6, dtype=xi.dtype)
    T, dT = jax.vmap(lambda e: jax.jvp(se3_exp, (xi,), (e,)), out_axes=(None, 0))(eye)  # dT: (6, 4, 4)
    R = T[:3, :3]
    A = jnp.einsum("ba,kbc->kac", R, dT[:, :3, :3])  # R^T dR per column, skew
    w = jnp.stack([A[:, 2, 1], A[:, 0, 2], A[:, 1, 0]])  # (3, 6)
    v = matmul(R.T, dT[:, :3, 3].T)  # (3, 6)
    return T, jnp.concatenate([v, w])


def _adjoint(T: Float[Array, "4 4"]) -> Float[Array, "6 6"]:
    """$\\mathrm{Ad}_T$ for twists `(v, w)`: body twist -> spatial twist, $(Rv + t \\times Rw,\\ Rw)$."""
    R, t = T[:3, :3], T[:3, 3]
    top = jnp.concatenate([R, matmul(skew(t), R)], axis=1)
    bottom = jnp.concatenate([jnp.zeros((3, 3), T.dtype), R], axis=1)
    return jnp.concatenate([top, bottom])


def _chain(params: AxisFitParams, problem: AxisFitProblem, q, jacobian: bool):
    """One pass over the chain at commanded configuration `q`, in the camera
    frame: the joint frames `(J, 4, 4)` (before each joint's motion), the
    marker poses `(M, 4, 4)` and, with `jacobian`, every parameter's spatial
    twist `(6, n_params)` (see `_axis_terms`)."""
    nominal = problem.nominal
    corr = params.correction
    n = nominal.num_joints
    M = problem.T_flange_marker0.shape[0]
    if jacobian:
        E_c, B_c = _se3_exp_body_jacobian(params.cam)
        E_o, B_o = jax.vmap(_se3_exp_body_jacobian)(corr.origin)
        E_m, B_m = jax.vmap(_se3_exp_body_jacobian)(corr.tool)
    else:
        E_c = se3_exp(params.cam)
        E_o = jax.vmap(se3_exp)(corr.origin)
        E_m = jax.vmap(se3_exp)(corr.tool)
    # Small products as broadcast-and-sum (`matmul`), fused by XLA under vmap.
    T_cb = matmul(problem.T_cam_base0, E_c)
    theta = nominal.zero_offset + corr.zero_offset + q
    T = T_cb
    frames = []
    for i, kind in enumerate(nominal.joint_types):
        T = matmul(matmul(T, nominal.T_parent_joint[i]), E_o[i])
        frames.append(T)
        T = matmul(T, joint_motion(kind, nominal.axis[i], theta[i]))
    T_cm = matmul(matmul(matmul(T, nominal.T_last_flange), problem.T_flange_marker0), E_m)  # (M, 4, 4)
    frames = jnp.stack(frames)  # joint frames in the camera frame, (J, 4, 4)
    if not jacobian:
        return frames, T_cm, None
    points = frames[:, :3, 3]
    dirs = jnp.einsum("jab,jb->ja", frames[:, :3, :3], nominal.axis)
    # Spatial twists of every parameter, (6, n_params), in parameter_names order.
    S_cam = matmul(_adjoint(T_cb), B_c)
    S_origin = jnp.einsum("jab,jbc->ajc", jax.vmap(_adjoint)(frames), B_o).reshape(6, 6 * n)
    zero_cols = []
    for i, kind in enumerate(nominal.joint_types):
        if kind == REVOLUTE:
            zero_cols.append(jnp.concatenate([jnp.cross(points[i], dirs[i]), dirs[i]]))
        else:
            zero_cols.append(jnp.concatenate([dirs[i], jnp.zeros(3, dirs.dtype)]))
    S_zero = jnp.stack(zero_cols, axis=1)
    S_tool = jnp.einsum("mab,mbc->amc", jax.vmap(_adjoint)(T_cm), B_m).reshape(6, 6 * M)
    return frames, T_cm, jnp.concatenate([S_cam, S_origin, S_zero, S_tool], axis=1)


# Nested jit, traced once per signature (see `_arcmodel.arc_terms`).
@functools.partial(jax.jit, static_argnames="jacobian")
def _axis_terms(
    params: AxisFitParams, problem: AxisFitProblem, *, jacobian: bool
) -> tuple[Float[Array, "joints k"], Float[Array, "joints k n"] | None]:
    """Whitened residuals and, with `jacobian`, their closed-form Jacobian with
    respect to the flattened parameters (`parameter_names` order).

    One pass over the chain in the camera frame per sweep home (one pass
    when every sweep starts from zero) ($T_{cam,base} = T_0\\exp(\\xi_c)$,
    joint frames $T_j = T_{j-1}^{+} T^{origin}_j \\exp(\\xi_j)$,
    $T_j^{+} = T_j \\exp(a_j\\theta_j)$). Every parameter enters as a spatial
    (camera-frame) twist $s = (v, \\omega)$: $\\mathrm{Ad}_{T}B(\\xi)$ for a pose
    correction right-multiplying the frame $T$ ($B$ the right Jacobian of
    SE(3)), $(p_i \\times d_i, d_i)$ for a revolute zero offset. A twist moves
    every frame downstream of it: a point $x$ by $v + \\omega \\times x$, a
    direction $d$ by $\\omega \\times d$, and a rotation residual
    $\\log(O_{ref}^T R)$ by $J_l^{-1} O_{ref}^T \\omega$ (left Jacobian of
    SO(3), Barfoot eq. 7.77). The line coordinates' derivative with respect to
    (point, direction) is a 4x6 local Jacobian.
    """
    nominal = problem.nominal
    n = nominal.num_joints
    M = problem.T_flange_marker0.shape[0]
    if problem.home is None:
        frames, T_cm, S = _chain(params, problem, jnp.zeros(n, problem.T_cam_base0.dtype), jacobian)
        frames_j, T_cm_j = frames, jnp.broadcast_to(T_cm, (n,) + T_cm.shape)
        S_j = None if S is None else S[None]
    else:
        # Each sweep's joint at that sweep's home (the axis of joint j depends on joints < j only).
        all_frames, T_cm_j, S_j = jax.vmap(lambda q: _chain(params, problem, q, jacobian))(problem.home)
        frames_j = all_frames[jnp.arange(n), jnp.arange(n)]
    points = frames_j[:, :3, 3]
    dirs = jnp.einsum("jab,jb->ja", frames_j[:, :3, :3], nominal.axis)
    arcs = problem.arcs
    sign_free = not arcs.has_encoder

    def line(p, d, R, c):
        return line_to_params(p, d, R, c, sign_free=sign_free)

    lines = jax.vmap(line)(points, dirs, arcs.R_ref, arcs.c)
    k = _meas_dim(arcs, problem.use_poses)
    pred = [lines]
    with_rot = problem.use_poses and k > 4 + 3 * M
    if problem.use_poses:
        p_m = T_cm_j[..., :3, 3]  # (J, M, 3)
        pred.append(p_m.reshape(n, 3 * M))
        if with_rot:
            A = jnp.einsum("jmba,jmbc->jmac", arcs.O_ref, T_cm_j[..., :3, :3])  # O_ref^T R, (J, M, 3, 3)
            r_m = so3_log(A)
            pred.append(r_m.reshape(n, 3 * M))
    keep = measured_rows(nominal, k)
    e = (jnp.concatenate(pred, axis=-1) - arcs.meas[:, :k]) * keep
    W = problem.sqrt_info
    r = jnp.einsum("jab,jb->ja", W, e)
    if not jacobian:
        return r, None

    v, w = jnp.swapaxes(S_j[:, :3], -1, -2), jnp.swapaxes(S_j[:, 3:], -1, -2)  # (1 or J, n_params, 3)
    layout = ParameterLayout.of(nominal, M)
    line_mask, marker_mask = (jnp.asarray(layout.axis_columns(g), r.dtype) for g in ("line", "marker"))
    dp = (v + jnp.cross(w, points[:, None])) * line_mask[..., None]  # (J, n_params, 3)
    dd = jnp.cross(w, dirs[:, None]) * line_mask[..., None]
    L_p, L_d = jax.vmap(jax.jacfwd(line, argnums=(0, 1)))(points, dirs, arcs.R_ref, arcs.c)  # (J, 4, 3)
    jac = [jnp.einsum("jab,jpb->jap", L_p, dp) + jnp.einsum("jab,jpb->jap", L_d, dd)]
    if problem.use_poses:
        vm, wm = v[:, None], w[:, None]  # (1 or J, 1, n_params, 3)
        dpm = (vm + jnp.cross(wm, p_m[:, :, None])) * marker_mask[None, ..., None]  # (J, M, n_params, 3)
        jac.append(jnp.swapaxes(dpm, -1, -2).reshape(n, 3 * M, -1))
        if with_rot:
            # d log(O_ref^T R) = J_l^{-1}(r) O_ref^T dw, with J_l^{-1}(r) = J_r^{-1}(r)^T.
            G = jnp.einsum("jmba,jmbc->jmac", so3_right_jacobian_inv(r_m), jnp.swapaxes(arcs.O_ref, -1, -2))
            dwm = wm * marker_mask[None, ..., None]  # (1 or J, M, n_params, 3)
            jac.append(
                jnp.einsum("jmab,jmpb->jmap", G, jnp.broadcast_to(dwm, (n,) + dwm.shape[1:])).reshape(
                    n, 3 * M, -1
                )
            )
    D = jnp.concatenate(jac, axis=1) * keep[..., None]  # (J, k, n_params)
    return r, jnp.einsum("jab,jbp->jap", W, D)


def _axis_residuals(params: AxisFitParams, problem: AxisFitProblem) -> Float[Array, "joints k"]:
    """Whitened residuals of the second error function, one row per joint sweep.

    Per joint: the model axis, mapped into the camera frame, in the arc fit's
    line coordinates minus the measured ones (and, with poses, the marker
    position and orientation at zero), whitened by the arc covariance.
    Differentiable as usual; the derivative with respect to `params` is the
    closed form of `_axis_terms` (one pass over the chain), so every solver
    step, the identifiability analysis and the covariance share one small
    Jacobian instead of tracing forward kinematics through autodiff.
    """
    return _axis_terms(params, problem, jacobian=False)[0]


axis_residuals = _lsq.closed_form_jvp(
    _axis_residuals,
    lambda params, problem: _axis_terms(params, problem, jacobian=True),
    _axis_residuals_autodiff,
)


def axis_jacobian(
    params: AxisFitParams, problem: AxisFitProblem
) -> tuple[Float[Array, "joints k"], Float[Array, "joints*k n"]]:
    """`axis_residuals` and their Jacobian with respect to the flattened parameters
    (`parameter_names` order), in closed form: `(joints, k)` and `(joints * k, n)`."""
    r, J = _axis_terms(params, problem, jacobian=True)
    return r, J.reshape(-1, J.shape[-1])


def axis_problem(
    nominal: KinematicModel,
    arcs: ArcFitResult,
    T_flange_marker0: Float[Array, "markers 4 4"],
    T_cam_base0: Float[Array, "4 4"],
    home: Float[Array, "joints joints"] | None = None,
    use_poses: bool | None = None,
) -> AxisFitProblem:
    """The `AxisFitProblem` `fit_axes` solved, rebuilt from its references (an
    `AxisFitResult`'s `T_flange_marker0`, `T_cam_base0`), the marker poses used
    when the arcs had encoders; `home` as `fit_axes` takes it (None: zeros).
    `use_poses` (None: `arcs.has_encoder`, which must then be concrete) lets a
    traced caller say it."""
    use_poses = bool(arcs.has_encoder) if use_poses is None else use_poses
    k = _meas_dim(arcs, use_poses)
    n = nominal.num_joints
    return AxisFitProblem(
        nominal=nominal,
        T_flange_marker0=T_flange_marker0,
        T_cam_base0=T_cam_base0,
        arcs=arcs,
        sqrt_info=jax.vmap(_whitening)(arcs.meas_cov[:, :k, :k]),
        use_poses=use_poses,
        home=jnp.zeros((n, n)) if home is None else jnp.asarray(home, jnp.float64),
    )


def home_jacobian(params: AxisFitParams, problem: AxisFitProblem) -> Float[Array, "joints*k joints joints"]:
    """$\\partial r / \\partial h$: the whitened residuals' derivative with respect to each
    sweep's home configuration (row `j` of `problem.home`, rad), by autodiff of the
    reference residuals: how a joint standing elsewhere than commanded during a sweep
    (gravity sag, backlash) moves the axes the fit compares."""
    n = problem.nominal.num_joints
    home = jnp.zeros((n, n)) if problem.home is None else problem.home

    def residuals(h):
        return _axis_residuals_autodiff(
            params, eqx.tree_at(lambda p: p.home, problem, h, is_leaf=lambda x: x is None)
        )

    return jax.jacfwd(residuals)(home).reshape(-1, n, n)


def _whitening(cov: Float[Array, "k k"]) -> Float[Array, "k k"]:
    """$W$ with $W^T W = \\Sigma^{-1}$ (inverse Cholesky factor), regularised."""
    k = cov.shape[0]
    scale = jnp.sqrt(jnp.maximum(jnp.diag(cov), 1e-300))
    C = cov / scale[:, None] / scale[None, :] + 1e-12 * jnp.eye(k)
    L = jnp.linalg.cholesky(C)
    W = jax.scipy.linalg.solve_triangular(L, jnp.eye(k), lower=True)
    return W / scale[None, :]


def model_axes(model: KinematicModel, home: Float[Array, "joints joints"] | None):
    """Every joint's axis line (base frame) at its own sweep's home configuration
    (row `j` of `home`; `None`: the zero configuration): `(points, directions)`."""
    n = model.num_joints
    if home is None:
        return joint_axes(model, jnp.zeros(n))
    return jax.vmap(lambda q, j: jax.tree.map(lambda a: a[j], joint_axes(model, q)))(home, jnp.arange(n))


def register_lines(
    nominal: KinematicModel, arcs: ArcFitResult, home: Float[Array, "joints joints"] | None = None
) -> Float[Array, "4 4"]:
    """Closed-form `T_cam_base` start: align the nominal axes with the measured ones.

    Rotation by Kabsch on the axis directions (with encoders the signs are
    known; without, every sign pattern is tried and the best kept), then the
    translation by linear least squares on the line offsets,
    $(I - d d^T)(R q + t - Q) = 0$ per joint; each axis at its sweep's `home`.
    When every axis is parallel (a SCARA), the rotation about them comes from
    the lines' offsets as well; a prismatic joint gives its direction only.
    """
    points, dirs = model_axes(nominal, home)
    D = arcs.direction
    w = 1.0 / jnp.maximum(jnp.trace(arcs.cov[:, :3, :3], axis1=-2, axis2=-1), 1e-16)
    w = w / jnp.max(w)
    # A prismatic joint's line has a direction but no position (`fit_line`: NaN point).
    has_point = jnp.asarray([t == REVOLUTE for t in nominal.joint_types])
    w_pos = jnp.where(has_point, w, 0.0)
    Q = jnp.where(has_point[:, None], arcs.point, 0.0)
    # All axes parallel (a SCARA): the directions leave the rotation about them free,
    # and the lines' offsets across the common direction fix it (2-D Procrustes of the
    # centred line points, in units of 10 cm). Other arms: H is the directions' alone.
    parallel = jnp.max(jnp.linalg.norm(jnp.cross(D, D[0]), axis=-1)) < 0.02
    centred = lambda x: x - jnp.sum(w_pos[:, None] * x, 0) / jnp.maximum(jnp.sum(w_pos), 1e-300)  # noqa: E731
    y = centred(Q - jnp.outer(Q @ D[0], D[0]))
    x = centred(points - jnp.outer(points @ dirs[0], dirs[0]))
    H_pos = jnp.where(parallel, jnp.einsum("j,ja,jb->ab", w_pos, y, x) / 0.1**2, 0.0)

    def register(signs):
        H = jnp.einsum("j,ja,jb->ab", w * signs, D, dirs) + H_pos  # sum w s D d^T
        R = nearest_rotation(H)
        dirs_c = dirs @ R.T
        Pj = jnp.eye(3) - dirs_c[:, :, None] * dirs_c[:, None, :]  # (J, 3, 3)
        rhs = jnp.einsum("jab,jb->ja", Pj, Q - points @ R.T)
        A = (Pj * w_pos[:, None, None]).reshape(-1, 3)
        t = jnp.linalg.lstsq(A, (rhs * w_pos[:, None]).reshape(-1))[0]
        # Directions (rad^2) and line offsets (in units of 10 cm) together: when the
        # axes span only a plane (a UR arm at zero), a half turn maps every line
        # onto a line with the opposite sign, and only the offsets tell them apart.
        pos = jnp.einsum("jab,jb->ja", Pj, points @ R.T + t - Q)
        cost = (
            jnp.sum(w * jnp.sum((signs[:, None] * D - dirs_c) ** 2, -1))
            + jnp.sum(w_pos * jnp.sum(pos**2, -1)) / 0.1**2
        )
        return make_pose(R, t), cost

    n = nominal.num_joints
    if arcs.has_encoder:
        T, _ = register(jnp.ones(n))
        return T
    # Every joint's sign, the first's too: without encoders an arc's direction sign is
    # arbitrary (`initialise_arc`), and holding the first at + forced a half turn whenever
    # its arc came out reversed (the offsets then fit a mirrored arm exactly).
    patterns = jnp.array(list(itertools.product([1.0, -1.0], repeat=n)))
    Ts, costs = jax.vmap(register)(patterns)
    return Ts[jnp.argmin(costs)]


def identifiable_mask(
    problem: AxisFitProblem,
    params: AxisFitParams,
    *,
    tol: float = 1e-7,
    candidates: Bool[Array, " n"] | None = None,
) -> tuple[Bool[Array, " n"], Float[Array, " n"]]:
    """Which parameters the measurements determine, by greedy column selection.

    The whitened Jacobian's columns are normalised and visited in the
    priority order of `ParameterLayout.priority`; a column is kept when its component
    orthogonal to the span of the kept ones is above `tol` (a
    column-pivoted, rank-revealing Gram-Schmidt QR with a fixed pivot
    order). Pure and vmappable. `candidates`: the parameters that may be
    freed at all (default all; e.g. the fixed frame's block held where its
    pose is known).

    **Returns:** `(free, independence)` over the flattened parameters; the
    independence is each column's relative distance from the kept span.
    """
    return _independent(problem, axis_jacobian(params, problem)[1], tol=tol, candidates=candidates)


def _independent(problem: AxisFitProblem, J, *, tol: float = 1e-7, candidates=None):
    """`identifiable_mask` from the Jacobian `J` at the parameters."""
    layout = ParameterLayout.of(problem.nominal, problem.T_flange_marker0.shape[0])
    return _lsq.independent_columns(J, layout.priority(refine=False), tol=tol, candidates=candidates)


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
    - `singular_values`: of the whitened Jacobian of the free parameters at the
      solution, its columns scaled to unit norm.
    - `T_cam_base0`, `T_flange_marker0`: the references the corrections are
      relative to (`T_cam_base = T_cam_base0 @ se3_exp(params.cam)`; the
      nominal mounts, `apply_correction` maps them to `T_flange_marker`).
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
    T_cam_base0: Float[Array, "4 4"]
    T_flange_marker0: Float[Array, "markers 4 4"]


def _free_mask(problem: AxisFitProblem, params0: AxisFitParams, J0, free, candidates, search):
    """`fit_axes`' mask of estimated parameters and the search's independence
    ratios (NaN where the mask was given), from the Jacobian `J0` at the start."""
    if free is None:
        return _independent(problem, J0, candidates=candidates)
    size = ravel_pytree(params0)[0].shape
    keep = jnp.asarray(free, bool)
    if keep.shape != size:
        raise ValueError(f"free mask has shape {keep.shape}, expected {size} (see parameter_names)")
    indep = jnp.full(size, jnp.nan)
    if search is None:
        return keep, indep
    found, found_indep = _independent(problem, J0, candidates=candidates)
    return jnp.where(search, found, keep), jnp.where(search, found_indep, indep)


#: `fit_axes`'s solver settings (whitened residuals: `atol` in noise units).
AXIS_OPTIONS = LMOptions(rtol=1e-8, atol=3e-2, max_steps=100)


def fit_axes(
    nominal: KinematicModel,
    arcs: ArcFitResult,
    *,
    T_flange_marker: Float[Array, "markers 4 4"] | None = None,
    T_cam_base0: Float[Array, "4 4"] | None = None,
    use_poses: bool | None = None,
    free: Bool[Array, " n"] | None = None,
    home: Float[Array, "joints joints"] | None = None,
    candidates: Bool[Array, " n"] | None = None,
    search: Bool[Array, ""] | None = None,
    options: LMOptions = AXIS_OPTIONS,
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
    - `home`: per joint sweep (row `j`), the commanded configuration the
      other joints held while joint `j` swept, entry `j` zero (its encoder
      zero); default: every sweep from the zero configuration.
    - `candidates`: without `free`, the parameters the identifiability search
      may free (default all): e.g. `T_cam_base` held at a known `T_cam_base0`.
    - `search`: with `free`, a (traced) switch: where true the search's mask
      replaces `free`. One compiled program then serves a fit that searches
      and one that reuses its mask (the search runs in both).
    - `options`: the solver's `LMOptions` (whitened residuals: `atol` in noise
      units); `throw`: raise when the solve does not converge (optimistix's).

    **Returns:** an `AxisFitResult`.
    """
    n_axes = arcs.direction.shape[0] if arcs.direction.ndim == 2 else 0
    if arcs.direction.ndim != 2 or n_axes != nominal.num_joints:
        raise ValueError(
            f"{n_axes} measured axes for a model with {nominal.num_joints} joints: "
            "stack one arc fit per joint, in joint order"
        )
    if use_poses is None:
        use_poses = arcs.has_encoder
    home, T_cam_base0, T_flange_marker = _references(nominal, arcs, home, T_cam_base0, T_flange_marker)
    k = _meas_dim(arcs, use_poses)
    # After the registration's SVDs: LAPACK calls never run side by side (see _linalg).
    W = jax.vmap(_whitening)(after(arcs.meas_cov[:, :k, :k], T_cam_base0))
    problem = AxisFitProblem(
        nominal=nominal,
        T_flange_marker0=T_flange_marker,
        T_cam_base0=T_cam_base0,
        arcs=arcs,
        sqrt_info=W,
        use_poses=use_poses,
        home=home,
    )
    n = nominal.num_joints
    params0 = AxisFitParams(cam=jnp.zeros(6), correction=zero_correction(n, arcs.T_cam_marker0.shape[1]))
    flat0, unravel = ravel_pytree(params0)
    lm = LMOptions(options.rtol, options.atol, options.max_steps, throw or options.throw)

    def solve(start):
        """The solve over the parameters the start's Jacobian `start = (r0, J0)` identifies."""
        keep, indep = _free_mask(problem, params0, start[1], free, candidates, search)
        keep_f = keep.astype(flat0.dtype)

        def fn(x, problem):
            return axis_residuals(unravel(x * keep_f), problem)

        sol = _lsq.solve(fn, flat0, problem, lm)
        return sol.value * keep_f, keep, indep, sol.result, sol.stats["num_steps"]

    # The Jacobian at the start (the identifiability search) and at the solution (the
    # covariance), one copy of it in the program.
    _, (x, *solved), final = _lsq.start_and_solution(
        lambda x: axis_jacobian(unravel(x), problem), flat0, solve
    )
    return _axis_result(problem, unravel(x), final, *solved)


def _references(nominal: KinematicModel, arcs: ArcFitResult, home, T_cam_base0, T_flange_marker):
    """`fit_axes`'s references, `(home, T_cam_base0, T_flange_marker)`: the sweeps' home
    configurations checked, the camera pose by `register_lines` and the marker mounts from
    the first sweep's encoder zero, where not given."""
    if home is not None:
        home = jnp.asarray(home, jnp.float64)
        if home.shape != (nominal.num_joints, nominal.num_joints):
            raise ValueError(f"home has shape {home.shape}, expected one configuration per joint sweep")
    if T_cam_base0 is None:
        T_cam_base0 = register_lines(nominal, arcs, home)
    if T_flange_marker is None:
        # Marker at the first sweep's encoder zero, seen by that sweep: T_flange_marker =
        # (T_cam_base T_base_flange(home_0))^-1 T_cam_marker0.
        q0 = jnp.zeros(nominal.num_joints) if home is None else home[0]
        T_cam_flange = T_cam_base0 @ forward_kinematics(nominal, q0)[-1]
        T_flange_marker = jnp.einsum("ab,mbc->mac", pose_inverse(T_cam_flange), arcs.T_cam_marker0[0])
    return home, T_cam_base0, T_flange_marker


def _axis_result(
    problem: AxisFitProblem, params: AxisFitParams, rJ, keep, indep, result, num_steps
) -> AxisFitResult:
    """The `AxisFitResult` at the solution `params` (`rJ`: its residuals and Jacobian) of the
    solve (optimistix's `result`, `num_steps`) over the parameters `keep` (frozen ones: zero
    columns, zero variance; one SVD, see `_linalg`)."""
    nominal, arcs = problem.nominal, problem.arcs
    r, J = rJ
    cov, sv, _ = _lsq.covariance(J, keep)
    model, mounts = apply_correction(nominal, problem.T_flange_marker0, params.correction)
    if arcs.has_encoder:
        model = eqx.tree_at(lambda m: m.reduction_ratio, model, nominal.reduction_ratio / arcs.rate)
    return AxisFitResult(
        model=eqx.tree_at(lambda m: m.T_flange_tool, model, mounts[0]),
        T_flange_marker=mounts,
        T_cam_base=problem.T_cam_base0 @ se3_exp(params.cam),
        params=params,
        std=jnp.sqrt(jnp.maximum(jnp.diag(cov), 0.0)),
        cov=cov,
        free=keep,
        independence=indep,
        result=result,
        num_steps=num_steps,
        residual_rms=jnp.sqrt(jnp.mean(r**2)),
        singular_values=sv,
        T_cam_base0=problem.T_cam_base0,
        T_flange_marker0=problem.T_flange_marker0,
    )
