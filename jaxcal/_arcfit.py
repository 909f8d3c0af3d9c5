"""First error function: the arc fit of one joint's sweep (seed method, step 4).

While joint $j$ turns alone, marker $m$'s position $P_{mt}$ (camera frame) lies
on a circle about the joint axis (direction $V$, through point $Q$), and its
orientation $O_{mt}$ turns about $V$ by the same angle $\\varphi_t$:

$$P_{mt} = Q + R(V, \\varphi_t)(p_m - Q), \\qquad O_{mt} = R(V, \\varphi_t)\\, O_m,$$

with $(p_m, O_m)$ the marker pose at $\\varphi = 0$. With encoders,
$\\varphi_t = r\\,\\alpha_t$ ($\\alpha_t$ the encoder angle, $r$ the rate, i.e.
the ratio of the true to the nominal reduction when $\\alpha$ is the encoder
angle already divided by the nominal ratio). Without encoders every
$\\varphi_t$ is an unknown, gauge-fixed by $\\varphi = 0$ at the first valid
frame, and $r$ is not identifiable.

Parameterisation (minimal, smooth at the solution): the axis line is four
numbers $(u, v, w_1, w_2)$ about a reference frame $(R_{ref}, c)$ from the
closed-form initialisation: $V = \\mathrm{normalize}(R_{ref}[u, v, 1]^T)$ and
$Q = c + R_{ref}[w_1, w_2, 0]^T$ (the point where the line crosses the plane
through $c$ orthogonal to the reference direction). The axis-to-kinematics
fit measures model axes in exactly these coordinates, so the arc fit's
covariance whitens its residuals without linearisation error in the
parameterisation.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jax.custom_derivatives import SymbolicZero
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, Bool, Float, Int

from ._geometry import (
    frame_from_z,
    make_pose,
    matmul,
    matmul_unrolled,
    matvec_unrolled,
    normalize,
    safe_norm,
    skew,
    so3_exp,
    so3_log,
    so3_right_jacobian,
    so3_right_jacobian_inv,
)
from ._linalg import after, nearest_rotation
from ._robust import MIN_DOF, check_loss, robust_scale, sample_weights
from ._schur import block_covariance, block_least_squares, block_leverage

_DEG = np.pi / 180.0
MIN_FRAMES = 5
MIN_SWEEP_DEG = 5.0


class ArcData(eqx.Module):
    """Measurements of one joint sweep, padded to a fixed number of frames.

    **Fields:**
    - `positions`: marker positions in the camera frame (m), `(markers, frames, 3)`.
    - `orientations`: marker orientations `O_cam_marker`, `(markers, frames, 3, 3)`, or None.
    - `encoder`: encoder angles (rad), `(frames,)`, or None (no encoders).
    - `mask`: which entries were observed, `(markers, frames)`; padding is False
      and may hold any value, NaN included.
    - `sqrt_info`: whitening matrices $W$ with $W^T W = \\Sigma^{-1}$ of the
      per-frame error `(position, rotation vector)`, `(markers, frames, 6, 6)`
      (`3, 3` without orientations).
    """

    positions: Float[Array, "markers frames 3"]
    orientations: Float[Array, "markers frames 3 3"] | None
    encoder: Float[Array, " frames"] | None
    mask: Bool[Array, "markers frames"]
    sqrt_info: Float[Array, "markers frames k k"]


def make_arc_data(
    positions,
    orientations=None,
    encoder=None,
    mask=None,
    *,
    sigma_position: float = 1e-4,
    sigma_rotation: float = 1e-3,
    covariances=None,
) -> ArcData:
    """Build `ArcData`, adding a marker axis if absent and filling defaults.

    **Arguments:**
    - `positions`: `(frames, 3)` or `(markers, frames, 3)` (m).
    - `orientations`: matching `(..., 3, 3)` or None.
    - `encoder`: `(frames,)` encoder angles (rad) or None.
    - `mask`: `(frames,)` / `(markers, frames)` bools, default all observed.
    - `sigma_position` (m), `sigma_rotation` (rad): isotropic noise used when no
      `covariances` are given.
    - `covariances`: per-frame covariance of the measurement error
      (position, camera-frame rotation vector $w$ with $O = \\exp([w]_\\times) O_{true}$),
      `(..., frames, 6, 6)` (or `3, 3` without orientations), as
      `jaxcal.vision.estimate_pose` reports it.
    """
    P = jnp.asarray(positions, jnp.float64)
    if P.ndim == 2:
        P = P[None]
        orientations = None if orientations is None else jnp.asarray(orientations, jnp.float64)[None]
        mask = None if mask is None else jnp.asarray(mask)[None]
        covariances = None if covariances is None else jnp.asarray(covariances, jnp.float64)[None]
    M, F = P.shape[:2]
    O = None if orientations is None else jnp.asarray(orientations, jnp.float64)
    k = 3 if O is None else 6
    mask = jnp.ones((M, F), bool) if mask is None else jnp.asarray(mask, bool)
    if covariances is None:
        diag = jnp.array([1.0 / sigma_position] * 3 + [1.0 / sigma_rotation] * 3)[:k]
        W = jnp.broadcast_to(jnp.diag(diag), (M, F, k, k))
    else:
        C = jnp.asarray(covariances, jnp.float64)
        C = jnp.where(mask[..., None, None], C, jnp.eye(k))
        # The residual is (predicted - measured position, log(measured predicted^T)):
        # the position error enters with the opposite sign of the rotation error,
        # so its cross-covariance with the rotation flips (C -> S C S,
        # S = diag(-1, -1, -1, 1, 1, 1)). This matters for PnP poses, whose
        # lateral position and rotation errors are strongly correlated.
        s = jnp.array([-1.0, -1.0, -1.0, 1.0, 1.0, 1.0])[:k]
        C = C * s[:, None] * s[None, :]
        # Sigma^{-1} = L^{-T} L^{-1} with Sigma = L L^T, so W = L^{-1}.
        L = jnp.linalg.cholesky(C)
        W = jax.vmap(jax.vmap(lambda Li: jax.scipy.linalg.solve_triangular(Li, jnp.eye(k), lower=True)))(L)
    enc = None if encoder is None else jnp.asarray(encoder, jnp.float64)
    return ArcData(positions=P, orientations=O, encoder=enc, mask=mask, sqrt_info=W)


class ArcParams(eqx.Module):
    """Unknowns of the arc fit (see module docstring)."""

    line: Float[Array, "4"]
    rate: Float[Array, ""]
    p0: Float[Array, "markers 3"]
    r0: Float[Array, "markers 3"]
    angles: Float[Array, " frames"] | None  # only without encoders


class ArcReference(eqx.Module):
    """Fixed reference of the parameterisation, from the initialisation."""

    R_ref: Float[Array, "3 3"]
    c: Float[Array, "3"]
    O_ref: Float[Array, "markers 3 3"]
    gauge: Float[Array, " frames"]  # 1.0 where the angle is free, 0.0 at the gauge frame


class ArcFitResult(eqx.Module):
    """A fitted joint axis.

    **Fields:**
    - `direction` $V$ (unit, camera frame), `point` $Q$: the axis point closest
      to the markers' centroid (m).
    - `rate` $r$ (NaN without encoders: not identifiable), `has_encoder`.
    - `T_cam_marker0`: marker poses at $\\varphi = 0$ (encoder zero), `(markers, 4, 4)`.
    - `angles`: fitted $\\varphi_t$ (rad), `(frames,)`.
    - `cov`: covariance of $(V, Q, r)$, `(7, 7)` (rank 5: $V$ is unit, $Q$ slides on the line).
    - `meas`, `meas_cov`: the line coordinates $(u, v, w_1, w_2)$ and the
      zero poses $(p_m, r_m)$ with their joint covariance, which the
      axis-to-kinematics fit consumes; `R_ref`, `c`, `O_ref` their reference.
    - `result`: optimistix's result code: `successful` when every round's
      solve converged, else the first failing round's code; `num_steps`: the
      steps of all rounds; `round_results`, `round_steps`: each round's
      (one round without a robust loss; `rounds` IRLS rounds and the inlier
      solve with one).
    - `residual_rms`: RMS of the whitened residuals of the samples the final
      solve used (about 1 when the given noise model is honest);
      `position_rms` (m), `rotation_rms` (rad) over the same samples.
    - `sample_residuals`: each (marker, frame) sample's whitened residual
      norm $\\|W e\\|$ at the solution (noise units, 0 where unobserved),
      `(markers, frames)`; `weights`: the final solve's weights (the
      observation mask without a robust loss; 1 for inliers and 0 for rejected
      samples after the inlier solve); `inlier`: observed samples the final
      solve used; `robust_scale`: the noise scale its residuals show (median
      over the samples it used of $\\|We\\|/m(\\nu)$, $m(\\nu)$ the median of
      $\\chi_\\nu$, $\\nu$ the sample's degrees of freedom; about 1 when the
      noise model is honest; see `jaxcal._robust`).
    - `num_frames`: observed frames.
    """

    direction: Float[Array, "3"]
    point: Float[Array, "3"]
    rate: Float[Array, ""]
    T_cam_marker0: Float[Array, "markers 4 4"]
    angles: Float[Array, " frames"]
    cov: Float[Array, "7 7"]
    rate_var: Float[Array, ""]
    meas: Float[Array, " k"]
    meas_cov: Float[Array, "k k"]
    R_ref: Float[Array, "3 3"]
    c: Float[Array, "3"]
    O_ref: Float[Array, "markers 3 3"]
    result: optx.RESULTS
    num_steps: Int[Array, ""]
    residual_rms: Float[Array, ""]
    position_rms: Float[Array, ""]
    rotation_rms: Float[Array, ""]
    num_frames: Int[Array, ""]
    sample_residuals: Float[Array, "markers frames"]
    weights: Float[Array, "markers frames"]
    inlier: Bool[Array, "markers frames"]
    robust_scale: Float[Array, ""]
    round_results: optx.RESULTS
    round_steps: Int[Array, " rounds"]
    has_encoder: bool = eqx.field(static=True)


# --------------------------------------------------------------------------- model


def line_from_params(line: Float[Array, "4"], R_ref, c) -> tuple[Float[Array, "3"], Float[Array, "3"]]:
    """(point, unit direction) of the line coordinates `(u, v, w1, w2)`."""
    V = normalize(R_ref @ jnp.stack([line[0], line[1], jnp.ones_like(line[0])]))
    Q = c + R_ref[:, :2] @ line[2:]
    return Q, V


def line_to_params(point, direction, R_ref, c, *, sign_free: bool = False) -> Float[Array, "4"]:
    """Inverse of `line_from_params` for any line not parallel to the reference plane.

    With `sign_free`, the direction is flipped to the reference hemisphere
    first (lines without an orientation, e.g. fitted without encoders).
    """
    d = R_ref.T @ direction
    if sign_free:
        d = d * jnp.sign(jnp.where(d[2] == 0, 1.0, d[2]))
    # Where the line crosses the plane through c orthogonal to R_ref[:, 2].
    s = -jnp.dot(point - c, R_ref[:, 2]) / jnp.dot(direction, R_ref[:, 2])
    x = point + s * direction - c
    return jnp.stack([d[0] / d[2], d[1] / d[2], jnp.dot(R_ref[:, 0], x), jnp.dot(R_ref[:, 1], x)])


def _phi(params: ArcParams, ref: ArcReference, data: ArcData) -> Float[Array, " frames"]:
    if data.encoder is not None:
        return params.rate * data.encoder
    return params.angles * ref.gauge


def _arc_terms(
    params: ArcParams, ref: ArcReference, data: ArcData, *, jacobian: bool
) -> tuple[Float[Array, "markers frames k"], Float[Array, "markers frames k 11"] | None]:
    """Whitened residuals and, with `jacobian`, their derivative per marker and frame.

    The derivative is taken with respect to the local parameters of one
    residual, $\\tau = (u, v, w_1, w_2, \\varphi_t, p_m, r_m)$ (11 numbers):
    each residual sees its own marker's zero pose and its own frame's angle
    only. With $R_t = \\exp(\\varphi_t[V]_\\times)$, $y = R_t(p_m - Q)$ and the
    left Jacobian of the axis motion $\\Gamma_t = \\varphi_t I + (1 - \\cos\\varphi_t)[V]_\\times
    + (\\varphi_t - \\sin\\varphi_t)[V]_\\times^2$ (so $R_t(V + dV) = \\exp([\\Gamma_t dV]_\\times) R_t$):

    - position: $\\partial_V = -[y]_\\times\\Gamma_t$, $\\partial_Q = I - R_t$,
      $\\partial_{\\varphi} = V \\times y$, $\\partial_{p_m} = R_t$;
    - rotation $\\theta = \\log(O\\hat O^T)$, through right perturbations
      $\\omega$ of $O\\hat O^T$ and $d\\theta = J_r^{-1}(\\theta)\\,\\omega$:
      $\\omega = -\\Gamma_t\\,dV - V d\\varphi_t - \\hat O J_r(r_m)\\,dr_m$.

    $dV$ and $dQ$ follow from the line coordinates (see `line_from_params`).
    """
    Q, V = line_from_params(params.line, ref.R_ref, ref.c)
    phi = _phi(params, ref, data)
    s, c1 = jnp.sin(phi)[:, None], (1.0 - jnp.cos(phi))[:, None]
    mask = data.mask
    P = jnp.where(mask[..., None], data.positions, 0.0)
    K = skew(V)
    if jacobian:
        n = ref.R_ref @ jnp.stack([params.line[0], params.line[1], jnp.ones_like(params.line[0])])
        E = ref.R_ref[:, :2]  # dQ / dw
        dV_duv = (jnp.eye(3) - jnp.outer(V, V)) @ E / safe_norm(n)  # (3, 2)
        # Gamma_t dV = phi dV + (1 - cos) V x dV + (phi - sin) V x (V x dV), per frame.
        KN = K @ dV_duv
        G_uv = phi[:, None, None] * dV_duv + c1[:, :, None] * KN + (phi[:, None] - s)[:, :, None] * (K @ KN)
        # (I - R_t) E = -(sin K + (1 - cos) K^2) E.
        KE = K @ E
        dpos_dw = -(s[:, :, None] * KE + c1[:, :, None] * (K @ KE))  # (F, 3, 2)
        R_t = jnp.eye(3) + s[:, :, None] * K + c1[:, :, None] * (K @ K)  # (F, 3, 3)

    def one_marker(p0, r0, O_ref, P_m, O_m, W_m, mask_m):
        # Rodrigues about the unit axis, R_t x = x + s_t V x x + (1 - c_t) V x (V x x),
        # with everything that does not depend on the frame hoisted out: the
        # per-frame work is a few multiply-adds.
        d = p0 - Q
        a = jnp.cross(V, d)
        b = jnp.cross(V, a)
        y = d + s * a + c1 * b  # R_t (p0 - Q), (F, 3)
        e = Q + y - P_m
        if jacobian:
            F = y.shape[0]
            dpos_duv = jnp.cross(jnp.swapaxes(G_uv, -1, -2), y[:, None, :])  # -[y]x G: (F, 2, 3)
            D = jnp.concatenate(
                [
                    jnp.swapaxes(dpos_duv, -1, -2),
                    dpos_dw,
                    jnp.cross(V, y)[:, :, None],
                    R_t,
                    jnp.zeros((F, 3, 3)),
                ],
                axis=-1,
            )  # (F, 3, 11)
        if O_m is not None:
            O0 = O_ref @ so3_exp(r0)
            G1 = K @ O0
            G2 = K @ G1
            O_pred = O0 + s[:, :, None] * G1 + c1[:, :, None] * G2  # (F, 3, 3)
            O_m = jnp.where(mask_m[:, None, None], O_m, jnp.eye(3))
            A = matmul_unrolled(O_m, jnp.swapaxes(O_pred, -1, -2))
            theta = so3_log(A)
            e = jnp.concatenate([e, theta], axis=-1)
            if jacobian:
                Jinv = so3_right_jacobian_inv(theta)  # (F, 3, 3)
                omega = jnp.concatenate(
                    [
                        -G_uv,
                        jnp.zeros((F, 3, 2)),
                        -jnp.broadcast_to(V[:, None], (F, 3, 1)),
                        jnp.zeros((F, 3, 3)),
                        -matmul_unrolled(O_pred, so3_right_jacobian(r0)),
                    ],
                    axis=-1,
                )  # (F, 3, 11)
                D = jnp.concatenate([D, matmul_unrolled(Jinv, omega)], axis=-2)
        r = jnp.where(mask_m[:, None], matvec_unrolled(W_m, e), 0.0)
        if not jacobian:
            return r, None
        return r, jnp.where(mask_m[:, None, None], matmul_unrolled(W_m, D), 0.0)

    O_all = data.orientations
    if O_all is None:
        return jax.vmap(lambda p0, r0, Oref, Pm, Wm, mm: one_marker(p0, r0, Oref, Pm, None, Wm, mm))(
            params.p0, params.r0, ref.O_ref, P, data.sqrt_info, mask
        )
    return jax.vmap(one_marker)(params.p0, params.r0, ref.O_ref, P, O_all, data.sqrt_info, mask)


def _flat_jacobian(D: Float[Array, "markers frames k 11"], ref: ArcReference, data: ArcData):
    """The Jacobian with respect to the flattened `ArcParams` (`ravel_pytree`
    order: line, rate, p0, r0[, angles]), assembled from the local derivatives
    by placement (no autodiff), `(markers * frames * k, n)`."""
    M, F, k, _ = D.shape
    eye_m = jnp.eye(M)[:, None, None, :, None]
    cols = [
        D[..., :4],
        (D[..., 4] * data.encoder[None, :, None])[..., None]
        if data.encoder is not None
        else jnp.zeros((M, F, k, 1)),
        (D[..., None, 5:8] * eye_m).reshape(M, F, k, 3 * M),
        (D[..., None, 8:11] * eye_m).reshape(M, F, k, 3 * M),
    ]
    if data.encoder is None:
        cols.append(D[..., 4, None] * (ref.gauge[:, None] * jnp.eye(F))[None, :, None, :])
    return jnp.concatenate(cols, axis=-1).reshape(M * F * k, -1)


@jax.custom_jvp
def arc_residuals(params: ArcParams, args: tuple[ArcReference, ArcData]) -> Float[Array, "markers frames k"]:
    """Whitened residuals of the arc model (the first error function).

    Per marker and frame, $W\\,[\\hat P - P;\\ \\log(O\\,\\hat O^T)]$ (position in
    m, orientation as a camera-frame rotation vector), zero where masked.

    Differentiable in the usual way; the derivative with respect to `params`
    is the closed form of `_arc_terms` (a few multiply-adds per residual,
    where forward-mode autodiff through Rodrigues and the logarithm costs
    about twenty times the residual itself).
    """
    ref, data = args
    return _arc_terms(params, ref, data, jacobian=False)[0]


def _arc_residuals_autodiff(params: ArcParams, args: tuple[ArcReference, ArcData]):
    """`arc_residuals` without its custom derivative (differentiated by JAX)."""
    ref, data = args
    return _arc_terms(params, ref, data, jacobian=False)[0]


def _instantiate(t):
    """Materialise a symbolic zero tangent (`float0` for integer and boolean inputs)."""
    if not isinstance(t, SymbolicZero):
        return t
    if t.dtype == jax.dtypes.float0:
        return np.zeros(t.shape, jax.dtypes.float0)
    return jnp.zeros(t.shape, t.dtype)


def _arc_residuals_jvp(primals, tangents):
    params, args = primals
    t_params, t_args = tangents
    is_zero = lambda x: isinstance(x, SymbolicZero)
    if not all(is_zero(t) for t in jax.tree.leaves(t_args, is_leaf=is_zero)):
        # Derivatives with respect to the data (e.g. implicit differentiation of a fit): autodiff.
        inst = lambda tree: jax.tree.map(_instantiate, tree, is_leaf=is_zero)
        return jax.jvp(_arc_residuals_autodiff, (params, args), (inst(t_params), inst(t_args)))
    ref, data = args
    r, D = _arc_terms(params, ref, data, jacobian=True)
    t = jax.tree.map(_instantiate, t_params, is_leaf=is_zero)
    if data.encoder is None:
        # Without encoders the assembled Jacobian has a column per frame, (markers *
        # frames * k) x frames: contract the local derivatives instead (each residual
        # sees its own frame's angle and marker's zero pose only).
        dr = (
            D[..., :4] @ t.line
            + D[..., 4] * (t.angles * ref.gauge)[None, :, None]
            + jnp.einsum("mfkj,mj->mfk", D[..., 5:8], t.p0)
            + jnp.einsum("mfkj,mj->mfk", D[..., 8:11], t.r0)
        )
        return r, dr
    # One matrix-vector product with the assembled Jacobian: a solver that
    # materialises the linearisation (vmap over basis tangents) gets one small
    # matrix product instead of a contraction per basis vector.
    J = _flat_jacobian(D, ref, data)
    return r, (J @ ravel_pytree(t)[0]).reshape(r.shape)


arc_residuals.defjvp(_arc_residuals_jvp, symbolic_zeros=True)


# --------------------------------------------------------------------------- closed-form initialisation


def _masked_mean(x, w, axis):
    wsum = jnp.maximum(jnp.sum(w, axis=axis), 1e-300)
    return jnp.sum(x * w, axis=axis) / wsum


def _forward_fill(x: Float[Array, " frames"], valid: Bool[Array, " frames"]) -> Float[Array, " frames"]:
    idx = jax.lax.cummax(jnp.where(valid, jnp.arange(x.shape[0]), 0))
    first = jnp.argmax(valid)
    return x[jnp.where(idx < first, first, idx)]


def initialise_arc(data: ArcData) -> tuple[ArcParams, ArcReference]:
    """Closed-form start: axis from relative rotations (or, with positions only,
    the circles' plane normal), algebraic circle fit, rate from a linear fit of
    observed angle against encoder angle.
    """
    mask = data.mask
    w = mask.astype(jnp.float64)
    P = jnp.where(mask[..., None], data.positions, 0.0)
    M, F = mask.shape
    centroids = jax.vmap(lambda Pm, wm: _masked_mean(Pm, wm[:, None], 0))(P, w)  # (M, 3)

    any_valid = jnp.any(mask, axis=0)
    t_ref = jnp.argmax(any_valid)  # first frame where some marker is seen
    m_ref = jnp.argmax(mask[:, t_ref])
    # 1-2. Axis direction: from relative rotations when orientations exist (robust
    #    when the marker sits near the axis, where the circle degenerates); else the
    #    plane normal, the smallest eigenvector of the pooled scatter (each marker
    #    centred on its own centroid; all circles share the axis direction).
    if data.orientations is not None:
        O = jnp.where(mask[..., None, None], data.orientations, jnp.eye(3))
        O_first = jax.vmap(lambda Om, mm: Om[jnp.argmax(mm)])(O, mask)  # (M, 3, 3)
        rel = jax.vmap(lambda Om, O0: jax.vmap(lambda Ot: so3_log(Ot @ O0.T))(Om))(O, O_first)  # (M, F, 3)
        S_rot = jnp.einsum("mfa,mfb->ab", rel * w[..., None], rel)
        _, evecs_r = jnp.linalg.eigh(S_rot)
        V0 = evecs_r[:, -1]
    else:
        X = (P - centroids[:, None, :]) * w[..., None]
        _, evecs = jnp.linalg.eigh(jnp.einsum("mfa,mfb->ab", X, X))
        V0 = evecs[:, 0]
    # 3. Circle centre: algebraic (Kasa) fit, shared 2D centre, one c per marker.
    c_all = _masked_mean(centroids, jnp.any(mask, axis=1).astype(jnp.float64)[:, None], 0)
    R_ref = frame_from_z(V0)
    xy = jnp.einsum("mfa,ak->mfk", P - c_all, R_ref[:, :2])
    A = jnp.concatenate(
        [2.0 * xy, jnp.broadcast_to(jnp.eye(M)[:, None, :], (M, F, M))], axis=-1
    )  # unknowns (a, b, c_1..c_M)
    b = jnp.sum(xy**2, axis=-1)
    A = (A * w[..., None]).reshape(M * F, 2 + M)
    b = (b * w).reshape(M * F)
    # Normal equations with a tiny ridge so markers never seen stay finite.
    sol = jnp.linalg.solve(A.T @ A + 1e-12 * jnp.eye(2 + M), A.T @ b)
    Q0 = c_all + R_ref[:, :2] @ sol[:2]
    # 4. Observed angles about V0, relative to each marker's first frame.
    if data.orientations is not None:
        phi_obs = jnp.einsum("mfa,a->mf", rel, V0)
    else:
        first_idx = jax.vmap(jnp.argmax)(mask)
        d = P - Q0
        d = d - jnp.einsum("mfa,a->mf", d, V0)[..., None] * V0
        d_first = jax.vmap(lambda dm, i: dm[i])(d, first_idx)
        cr = jnp.einsum("mfa,a->mf", jnp.cross(d_first[:, None, :], d), V0)
        dt = jnp.einsum("mfa,ma->mf", d, d_first)
        phi_obs = jnp.arctan2(cr, dt)
    phi_obs = jax.vmap(lambda p, mm: jnp.unwrap(_forward_fill(p, mm)))(phi_obs, mask)

    if data.encoder is not None:
        # Rate and sign from the linear fit phi = r * alpha + b_m, pooled.
        alpha = data.encoder
        a_mean = jax.vmap(lambda wm: _masked_mean(alpha, wm, 0))(w)  # per marker
        p_mean = jax.vmap(lambda pm, wm: _masked_mean(pm, wm, 0))(phi_obs, w)
        da = (alpha[None, :] - a_mean[:, None]) * w
        dp = (phi_obs - p_mean[:, None]) * w
        rate0 = jnp.sum(da * dp) / jnp.maximum(jnp.sum(da * da), 1e-300)
        sign = jnp.where(rate0 < 0, -1.0, 1.0)
        V0 = V0 * sign
        rate0 = rate0 * sign
        R_ref = frame_from_z(V0)
        phi_t = rate0 * alpha
        angles0 = None
        gauge = jnp.ones(F)
    else:
        rate0 = jnp.ones(())
        phi_t = jnp.where(any_valid, phi_obs[m_ref], 0.0)
        # phi_obs of marker m_ref is zero at its first frame, which is t_ref.
        angles0 = phi_t
        gauge = jnp.ones(F).at[t_ref].set(0.0)

    # 5. Marker pose at phi = 0: rotate every observation back and average.
    R_back = jax.vmap(lambda a: so3_exp(-V0 * a))(phi_t)  # (F, 3, 3)
    back = Q0 + jnp.einsum("fab,mfb->mfa", R_back, P - Q0)
    p0 = jax.vmap(lambda bm, wm: _masked_mean(bm, wm[:, None], 0))(back, w)
    if data.orientations is not None:
        # After the circle fit's solve: two LAPACK calls never run side by side (see _linalg).
        O_back = after(jnp.einsum("fab,mfbc->mfac", R_back, O), Q0)
        O0 = nearest_rotation(jnp.einsum("mfab,mf->mab", O_back, w))
    else:
        O0 = jnp.broadcast_to(jnp.eye(3), (M, 3, 3))
    params = ArcParams(
        line=jnp.zeros(4), rate=jnp.asarray(rate0, jnp.float64), p0=p0, r0=jnp.zeros((M, 3)), angles=angles0
    )
    ref = ArcReference(R_ref=R_ref, c=Q0, O_ref=O0, gauge=gauge)
    return params, ref


# --------------------------------------------------------------------------- solve


def _free_mask(params: ArcParams, data: ArcData, ref: ArcReference) -> ArcParams:
    """Which parameters exist for this data (1.0) or are structurally absent (0.0)."""
    has_enc = data.encoder is not None
    has_rot = data.orientations is not None
    return ArcParams(
        line=jnp.ones(4),
        rate=jnp.asarray(1.0 if has_enc else 0.0),
        p0=jnp.ones_like(params.p0),
        r0=jnp.ones_like(params.r0) * (1.0 if has_rot else 0.0),
        angles=None if has_enc else ref.gauge,
    )


def _round_plan(loss: str | None, rounds: int, reject) -> np.ndarray:
    """Which rounds are the hard inlier solve (static): `rounds` soft IRLS
    rounds and, with `reject`, one inlier solve; one plain round without a loss."""
    if loss is None:
        return np.zeros(1, bool)
    if rounds < 1:
        raise ValueError(f"fit_arc: rounds must be at least 1 with a robust loss, got {rounds}")
    return np.array([False] * rounds + ([True] if reject is not None else []))


def fit_arc(
    data: ArcData,
    *,
    loss: str | None = None,
    c: float = 3.0,
    reject: float | None = 3.7,
    rounds: int = 3,
    rtol: float = 1e-8,
    atol: float = 3e-2,
    max_steps: int = 50,
    throw: bool = False,
    scale_covariance: bool = True,
) -> ArcFitResult:
    """Fit one joint's axis (and rate) to a sweep; pure, jittable and vmappable.

    Closed-form initialisation (`initialise_arc`), then Levenberg-Marquardt
    on `arc_residuals`: optimistix's with encoders; without, the same
    iteration by blocks (`jaxcal._schur`), the per-frame angles eliminated by
    the Schur complement, so time and memory grow linearly with the frames.
    The covariance is $(J^T J)^{+}$ of the whitened residuals at the solution
    (by blocks without encoders), times $\\hat\\sigma^2 = \\|r\\|^2/(m - n)$
    when `scale_covariance` (set it False when the given noise model is trusted).

    Robust loss (iteratively reweighted least squares, as `jaxcal._refine.refine`):
    each (marker, frame) sample's whitened residual norm $e$ is put in robust
    sigmas, $z = e/s$ with $s$ the median of $e/m(\\nu)$ ($m(\\nu)$ the median
    of $\\chi_\\nu$, $\\nu = k - h$ the sample's degrees of freedom, $k = 3$ or
    6, $h$ its leverage: a frame's own angle takes one), mapped to the 2-D
    radius with the same tail probability (`jaxcal._robust`), and weighted
    (Cauchy $1/(1 + (z/c)^2)$, Huber $\\min(1, c/z)$); `rounds` solves with
    the weights of the previous solution, then one least-squares solve on the
    inliers ($z <$ `reject`, weight 1; others 0), whose Jacobian gives the
    covariance, scaled by the inlier residual variance: honest standard
    deviations. All rounds are one `lax.scan` (one compiled solver); each
    round's weights come from a converged solution, so which samples are
    rejected does not depend on `max_steps` once every round converges.

    **Arguments:**
    - `data`: an `ArcData` (see `make_arc_data`; `stack_sweeps` for several).
    - `loss`: `"cauchy"`, `"huber"` or `None` (plain least squares, one solve).
    - `c`: the loss constant, `reject`: the inlier threshold (`None`: no
      inlier solve), both as 2-D radii in robust sigmas (a clean sample is
      rejected with probability $e^{-reject^2/2}$, 0.1 % at 3.7); `rounds`:
      IRLS solves before the inlier solve. Ignored without a loss.
    - `rtol`, `atol`, `max_steps`, `throw`: the solver's (optimistix's rules;
      `max_steps` per round). The residuals are whitened, so `atol` is in
      units of the noise: the solver stops when a step moves every
      prediction by less than `atol` standard deviations (Gauss-Newton then
      leaves the iterate ~`atol**2` from the optimum; tighter tolerances only
      chase float64 round-off in the loss). `throw`: raise (through
      `eqx.error_if`) when a round does not converge.

    **Returns:** an `ArcFitResult`.
    """
    check_loss(loss)
    hard_flags = _round_plan(loss, rounds, reject)
    params0, ref = initialise_arc(data)
    free = _free_mask(params0, data, ref)
    mask = data.mask
    mask_f = mask.astype(params0.line.dtype)
    k = data.sqrt_info.shape[-1]
    reject_ = jnp.inf if reject is None else reject
    solve = _solve_dense if data.encoder is not None else _solve_blocks

    def weights_at(params, hard):
        if loss is None:
            return mask_f
        e, h = _sample_stats(params, ref, data, free, mask_f)
        return sample_weights(e, h, mask, k=k, loss=loss, c=c, reject=reject_, hard=hard)[0]

    def body(carry, hard):
        params, steps, ok = carry
        w = weights_at(params, hard)
        new, result, n = solve(params, ref, data, free, w, rtol=rtol, atol=atol, max_steps=max_steps)
        finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in jax.tree.leaves(new)]))
        new = jax.tree.map(lambda a, b: jnp.where(finite, a, b), new, params)
        good = result == optx.RESULTS.successful
        return (new, steps + n, ok & good), (w, result, n)

    (params, steps, ok), (ws, results, round_steps) = jax.lax.scan(
        body, (params0, jnp.asarray(0), jnp.asarray(True)), jnp.asarray(hard_flags)
    )
    first_bad = jnp.argmax(results != optx.RESULTS.successful)
    result = optx.RESULTS.where(ok, optx.RESULTS.successful, jax.tree.map(lambda r: r[first_bad], results))
    if throw:
        params = eqx.error_if(params, ~ok, "fit_arc: a Levenberg-Marquardt solve did not converge")
    params = jax.tree.map(lambda x, f: x * f, params, free)
    return _summarise(
        params,
        ref,
        data,
        free,
        result,
        steps,
        scale_covariance,
        weights=ws[-1],
        round_results=results,
        round_steps=round_steps,
    )


def _solve_dense(params, ref, data, free, w, *, rtol, atol, max_steps):
    """optimistix's Levenberg-Marquardt on the weighted residuals (with encoders: few unknowns)."""

    def fn(p, args):
        ref_, data_, sw = args
        p = jax.tree.map(lambda x, f: x * f, p, free)
        return arc_residuals(p, (ref_, data_)) * sw[..., None]

    solver = optx.LevenbergMarquardt(rtol=rtol, atol=atol)
    sol = optx.least_squares(fn, solver, params, (ref, data, jnp.sqrt(w)), max_steps=max_steps, throw=False)
    return sol.value, sol.result, sol.stats["num_steps"]


def _to_blocks(params: ArcParams, data: ArcData) -> tuple[Float[Array, " n_g"], Float[Array, "frames 1"]]:
    """Global `(line, p0[, r0])` and local (per-frame angle) parameters of a fit without encoders."""
    parts = [params.line, params.p0.reshape(-1)]
    if data.orientations is not None:
        parts.append(params.r0.reshape(-1))
    return jnp.concatenate(parts), params.angles[:, None]


def _from_blocks(g, l, ref: ArcReference, data: ArcData) -> ArcParams:
    """Inverse of `_to_blocks` (the rate, absent, is 0; the gauge frame's angle 0)."""
    M = data.positions.shape[0]
    r0 = (
        g[4 + 3 * M : 4 + 6 * M].reshape(M, 3)
        if data.orientations is not None
        else jnp.zeros((M, 3), g.dtype)
    )
    return ArcParams(
        line=g[:4],
        rate=jnp.zeros((), g.dtype),
        p0=g[4 : 4 + 3 * M].reshape(M, 3),
        r0=r0,
        angles=l[:, 0] * ref.gauge,
    )


def _arc_blocks(g, l, args):
    """The arc model by blocks for `jaxcal._schur`: one block per frame (every
    marker's residuals, weighted by $\\sqrt{w}$), `(frames, markers * k)`, its
    derivatives with respect to the global `(line, p0[, r0])` and to the
    frame's own angle, placed from `_arc_terms`' local derivatives."""
    ref, data, sw = args
    r, D = _arc_terms(_from_blocks(g, l, ref, data), ref, data, jacobian=True)
    r = r * sw[..., None]
    D = D * sw[..., None, None]
    M, F, k, _ = D.shape
    eye_m = jnp.eye(M)[:, None, None, :, None]
    cols = [D[..., :4], (D[..., None, 5:8] * eye_m).reshape(M, F, k, 3 * M)]
    if data.orientations is not None:
        cols.append((D[..., None, 8:11] * eye_m).reshape(M, F, k, 3 * M))
    Jg = jnp.concatenate(cols, axis=-1)
    Jl = D[..., 4:5] * ref.gauge[None, :, None, None]
    to_blocks = lambda x: jnp.moveaxis(x, 1, 0).reshape((F, M * k) + x.shape[3:])  # noqa: E731
    return to_blocks(r), to_blocks(Jg), to_blocks(Jl)


def _solve_blocks(params, ref, data, free, w, *, rtol, atol, max_steps):
    """Levenberg-Marquardt by blocks (`jaxcal._schur`) without encoders: linear in the frames."""
    g, l = _to_blocks(params, data)
    g_mask, l_mask = _to_blocks(free, data)
    sol = block_least_squares(
        _arc_blocks,
        g,
        l,
        (ref, data, jnp.sqrt(w)),
        rtol=rtol,
        atol=atol,
        max_steps=max_steps,
        g_mask=g_mask > 0,
        l_mask=l_mask > 0,
    )
    return _from_blocks(sol.g, sol.l, ref, data), sol.result, sol.num_steps


def _covariance(params, ref, data, free, w):
    """Unscaled covariance blocks and each sample's leverage, with weights `w`.

    **Returns:** `(cov_line_rate (5, 5), cov_meas (k, k), leverage (markers, frames))`.
    """
    M, F = data.mask.shape
    k = data.sqrt_info.shape[-1]
    sw = jnp.sqrt(w)
    has_rot = data.orientations is not None
    if data.encoder is None:
        g, l = _to_blocks(params, data)
        g_mask, l_mask = _to_blocks(free, data)
        _, Jg, Jl = _arc_blocks(g, l, (ref, data, sw))
        cov = block_covariance(Jg, Jl, g_mask=g_mask > 0, l_mask=l_mask > 0)
        h = block_leverage(Jg * g_mask, Jl * l_mask[:, None, :], cov).reshape(F, M, k).sum(-1).T
        cov_lr = jnp.zeros((5, 5), g.dtype).at[:4, :4].set(cov.gg[:4, :4])
        return cov_lr, cov.gg, h
    flat, unravel = ravel_pytree(params)
    free_flat, _ = ravel_pytree(free)
    _, D = _arc_terms(params, ref, data, jacobian=True)
    J = _flat_jacobian(D * sw[..., None, None], ref, data) * free_flat[None, :]
    # Pseudo-inverse restricted to the free parameters (absent ones have zero columns).
    cov = (
        jnp.linalg.pinv(J.T @ J + jnp.diag(1.0 - free_flat), hermitian=True)
        * free_flat[:, None]
        * free_flat[None, :]
    )
    h = jnp.sum((J @ cov) * J, axis=-1).reshape(M, F, k).sum(-1)
    cov_p = unravel_cov(cov, unravel, flat, has_rot)
    return cov_p["line_rate"], cov_p["meas"], h


def _sample_stats(params, ref, data, free, w):
    """Each sample's whitened residual norm and leverage (with design weights `w`), `(markers, frames)` each."""
    e = jnp.linalg.norm(arc_residuals(params, (ref, data)), axis=-1)
    return e, _covariance(params, ref, data, free, w)[2]


def _summarise(
    params,
    ref,
    data,
    free,
    result,
    num_steps,
    scale_covariance,
    *,
    weights=None,
    round_results=None,
    round_steps=None,
) -> ArcFitResult:
    """The `ArcFitResult` at `params` (frozen entries already zero), the
    covariance from the Jacobian with `weights` (default: the mask)."""
    mask = data.mask
    mask_w = mask.astype(jnp.float64)
    w = mask_w if weights is None else weights
    if round_results is None:
        round_results = jax.tree.map(lambda r: r[None], result)
        round_steps = jnp.asarray(num_steps)[None]
    has_enc = data.encoder is not None
    has_rot = data.orientations is not None
    k = data.sqrt_info.shape[-1]
    cov_lr, meas_cov, h = _covariance(params, ref, data, free, w)
    r = arc_residuals(params, (ref, data))
    e = jnp.linalg.norm(r, axis=-1)
    n_obs = k * jnp.sum(w)
    ssr = jnp.sum(w * e**2)
    # Degrees of freedom: observations less the parameters the data determine,
    # the trace of the hat matrix (the free parameters unless some are never
    # observed, e.g. a marker padded in by `stack_sweeps`).
    dof = jnp.maximum(n_obs - jnp.sum(h), 1.0)
    sigma2 = ssr / dof if scale_covariance else 1.0
    cov_lr = cov_lr * sigma2
    meas_cov = meas_cov * sigma2

    Q, V = line_from_params(params.line, ref.R_ref, ref.c)

    # (V, Q, r) covariance by the Jacobian of (line, rate) -> (V, Q, r).
    def vqr(lr):
        Qx, Vx = line_from_params(lr[:4], ref.R_ref, ref.c)
        return jnp.concatenate([Vx, Qx, lr[4:]])

    lr = jnp.concatenate([params.line, params.rate[None]])
    G = jax.jacfwd(vqr)(lr)
    cov_vqr = matmul(matmul(G, cov_lr), G.T)
    # Report Q as the axis point closest to the markers' centroid.
    P = jnp.where(mask[..., None], data.positions, 0.0)
    centroid = _masked_mean(P.reshape(-1, 3), mask_w.reshape(-1)[:, None], 0)
    Q_c = Q + jnp.dot(centroid - Q, V) * V
    O0 = jax.vmap(lambda Oref, r0: Oref @ so3_exp(r0))(ref.O_ref, params.r0)
    T0 = jax.vmap(make_pose)(O0, params.p0)
    # Unwhitened RMS of positions and rotations over the samples the solve used.
    used = (w > 0) & mask
    used_w = used.astype(jnp.float64)
    n_used = jnp.maximum(jnp.sum(used_w), 1)
    raw = _raw_errors(params, ref, data)
    pos_rms = jnp.sqrt(jnp.sum(jnp.sum(raw[..., :3] ** 2, -1) * used_w) / n_used)
    rot_rms = (
        jnp.sqrt(jnp.sum(jnp.sum(raw[..., 3:] ** 2, -1) * used_w) / n_used)
        if raw.shape[-1] == 6
        else jnp.asarray(jnp.nan)
    )
    meas = jnp.concatenate(
        [params.line, params.p0.reshape(-1)] + ([params.r0.reshape(-1)] if has_rot else [])
    )
    nu = jnp.clip(k - h, MIN_DOF, float(k))
    return ArcFitResult(
        direction=V,
        point=Q_c,
        rate=params.rate if has_enc else jnp.asarray(jnp.nan),
        T_cam_marker0=T0,
        angles=_phi(params, ref, data),
        cov=cov_vqr,
        rate_var=cov_lr[4, 4] if has_enc else jnp.asarray(jnp.nan),
        meas=meas,
        meas_cov=meas_cov,
        R_ref=ref.R_ref,
        c=ref.c,
        O_ref=ref.O_ref,
        result=result,
        num_steps=jnp.asarray(num_steps),
        residual_rms=jnp.sqrt(ssr / jnp.maximum(n_obs, 1)),
        position_rms=pos_rms,
        rotation_rms=rot_rms,
        num_frames=jnp.sum(jnp.any(mask, axis=0)),
        sample_residuals=jnp.where(mask, e, 0.0),
        weights=w,
        inlier=used,
        robust_scale=robust_scale(e, nu, used),
        round_results=round_results,
        round_steps=jnp.asarray(round_steps),
        has_encoder=has_enc,
    )


def unravel_cov(cov, unravel, flat, has_rot: bool) -> dict:
    """Blocks of the flat covariance for (line, rate) and (line, p0[, r0])."""
    n = flat.shape[0]
    idx = jax.tree.map(lambda x: x.astype(jnp.int32), unravel(jnp.arange(n, dtype=jnp.float64)))
    line_i = idx.line
    rate_i = idx.rate[None]
    meas_i = jnp.concatenate([line_i, idx.p0.reshape(-1)] + ([idx.r0.reshape(-1)] if has_rot else []))
    lr_i = jnp.concatenate([line_i, rate_i])
    return {"line_rate": cov[jnp.ix_(lr_i, lr_i)], "meas": cov[jnp.ix_(meas_i, meas_i)]}


def _raw_errors(params, ref, data):
    """Unwhitened (position, rotation) errors, by setting W to identity."""
    k = data.sqrt_info.shape[-1]
    eye = jnp.broadcast_to(jnp.eye(k), data.sqrt_info.shape)
    return arc_residuals(params, (ref, eqx.tree_at(lambda d: d.sqrt_info, data, eye)))


# --------------------------------------------------------------------------- several sweeps


def _bucket_size(n: int, bucket: int | str) -> int:
    if bucket == "pow2":
        return 1 << max(n - 1, 0).bit_length()
    if isinstance(bucket, str) or int(bucket) < 1:
        raise ValueError(f"stack_sweeps: bucket must be a positive int or 'pow2', got {bucket!r}")
    return -(-n // int(bucket)) * int(bucket)


def stack_sweeps(
    sweeps,
    orientations=None,
    encoders=None,
    masks=None,
    *,
    covariances=None,
    sigma_position: float = 1e-4,
    sigma_rotation: float = 1e-3,
    bucket: int | str = 64,
) -> ArcData:
    """Stack sweeps of different lengths into one `ArcData` for `jax.vmap(fit_arc)`.

    Every sweep is padded (masked out) to one number of frames, rounded up to
    a bucket so that sweeps of similar length share a compiled program: a
    multiple of `bucket` (default 64) or, with `bucket="pow2"`, the next power
    of two. Markers are padded the same way (never observed) when the sweeps
    have different numbers. Padding holds zeros, identity rotations and
    identity whitening; `fit_arc` ignores it (its results equal those of the
    unpadded sweep to round-off). NumPy glue: call it outside `jit`.

    **Arguments:**
    - `sweeps`: one `ArcData` per joint (from `make_arc_data`), or one
      positions array per joint, `(frames_j, 3)` or `(markers, frames_j, 3)` (m),
      with `orientations`, `encoders`, `masks`, `covariances`: matching lists
      (or None) and the noise levels, as `make_arc_data` takes them.
    - `bucket`: the padding rule (above).

    **Returns:** an `ArcData` with a leading joints axis,
    `(joints, markers, frames, ...)`.
    """
    sweeps = list(sweeps)
    if not sweeps:
        raise ValueError("stack_sweeps: no sweeps")
    if isinstance(sweeps[0], ArcData):
        if any(x is not None for x in (orientations, encoders, masks, covariances)):
            raise ValueError("stack_sweeps: give ArcData sweeps alone, or positions with matching lists")
        if not all(isinstance(d, ArcData) for d in sweeps):
            raise ValueError("stack_sweeps: mix of ArcData and arrays")
        datas = sweeps
    else:
        n = len(sweeps)

        def each(x, name):
            if x is None:
                return [None] * n
            if len(x) != n:
                raise ValueError(f"stack_sweeps: {n} position arrays but {len(x)} {name}")
            return list(x)

        datas = [
            make_arc_data(
                P,
                O,
                e,
                m,
                sigma_position=sigma_position,
                sigma_rotation=sigma_rotation,
                covariances=C,
            )
            for P, O, e, m, C in zip(
                sweeps,
                each(orientations, "orientation arrays"),
                each(encoders, "encoder arrays"),
                each(masks, "masks"),
                each(covariances, "covariance arrays"),
            )
        ]
    has_rot = {d.orientations is not None for d in datas}
    has_enc = {d.encoder is not None for d in datas}
    if len(has_rot) > 1 or len(has_enc) > 1:
        raise ValueError(
            "stack_sweeps: every sweep needs the same inputs (orientations: "
            f"{[d.orientations is not None for d in datas]}, encoders: {[d.encoder is not None for d in datas]})"
        )
    M = max(d.mask.shape[0] for d in datas)
    F = _bucket_size(max(d.mask.shape[1] for d in datas), bucket)
    k = datas[0].sqrt_info.shape[-1]

    def pad(x, fill):
        x = np.asarray(x)
        out = np.broadcast_to(np.asarray(fill, x.dtype), (M, F) + x.shape[2:]).copy()
        out[: x.shape[0], : x.shape[1]] = x
        return out

    return ArcData(
        positions=jnp.asarray(np.stack([pad(d.positions, 0.0) for d in datas])),
        orientations=(
            jnp.asarray(np.stack([pad(d.orientations, np.eye(3)) for d in datas]))
            if has_rot == {True}
            else None
        ),
        encoder=(
            jnp.asarray(np.stack([np.pad(np.asarray(d.encoder), (0, F - d.encoder.shape[0])) for d in datas]))
            if has_enc == {True}
            else None
        ),
        mask=jnp.asarray(np.stack([pad(d.mask, False) for d in datas])),
        sqrt_info=jnp.asarray(np.stack([pad(d.sqrt_info, np.eye(k)) for d in datas])),
    )


def arc_outliers(res: ArcFitResult, mask: Bool[Array, "markers frames"]) -> np.ndarray:
    """The (marker, frame) samples a robust arc fit rejected: observed in
    `mask` and not used by its final solve, as an `(n, 2)` int array (NumPy;
    outside jit, one fit, not a batch)."""
    bad = np.asarray(mask) & ~np.asarray(res.inlier)
    return np.argwhere(bad)


# --------------------------------------------------------------------------- input checks


def validate_arc_data(data: ArcData, joint: str) -> None:
    """Raise a `ValueError` naming `joint` if the sweep cannot give an axis.

    Checks shapes, NaN/inf in observed entries, at least `MIN_FRAMES`
    observed frames, and a sweep of at least `MIN_SWEEP_DEG` degrees.
    """
    P = np.asarray(data.positions)
    mask = np.asarray(data.mask)
    if P.ndim != 3 or P.shape[-1] != 3:
        raise ValueError(f"joint {joint!r}: positions must have shape (markers, frames, 3), got {P.shape}")
    M, F = P.shape[:2]
    if mask.shape != (M, F):
        raise ValueError(f"joint {joint!r}: mask has shape {mask.shape}, positions imply {(M, F)}")
    if data.orientations is not None and np.shape(data.orientations) != (M, F, 3, 3):
        raise ValueError(
            f"joint {joint!r}: orientations have shape {np.shape(data.orientations)}, expected {(M, F, 3, 3)}"
        )
    if data.encoder is not None and np.shape(data.encoder) != (F,):
        raise ValueError(
            f"joint {joint!r}: {np.shape(data.encoder)[0] if np.ndim(data.encoder) else 0} encoder angles "
            f"for {F} frames (lengths must match)"
        )
    if not np.all(np.isfinite(P[mask])):
        t = np.argwhere(mask & ~np.all(np.isfinite(P), axis=-1))[0]
        raise ValueError(f"joint {joint!r}: non-finite position at marker {t[0]}, frame {t[1]}")
    if data.orientations is not None:
        O = np.asarray(data.orientations)
        bad = mask & ~np.all(np.isfinite(O), axis=(-1, -2))
        if bad.any():
            t = np.argwhere(bad)[0]
            raise ValueError(f"joint {joint!r}: non-finite orientation at marker {t[0]}, frame {t[1]}")
    if data.encoder is not None:
        enc = np.asarray(data.encoder)
        bad = mask.any(axis=0) & ~np.isfinite(enc)
        if bad.any():
            raise ValueError(f"joint {joint!r}: non-finite encoder angle at frame {np.flatnonzero(bad)[0]}")
    n_frames = int(mask.any(axis=0).sum())
    if n_frames < MIN_FRAMES:
        raise ValueError(f"joint {joint!r}: only {n_frames} valid frames, at least {MIN_FRAMES} are needed")
    span = sweep_span_deg(data)
    if span < MIN_SWEEP_DEG:
        raise ValueError(
            f"joint {joint!r}: the sweep covers {span:.2f} degrees, at least {MIN_SWEEP_DEG:g} are needed"
        )


def sweep_span_deg(data: ArcData) -> float:
    """Angle swept by the joint (deg): from encoders, else from the measured motion."""
    mask = np.asarray(data.mask)
    seen = mask.any(axis=0)
    if data.encoder is not None:
        enc = np.asarray(data.encoder)[seen]
        return float((enc.max() - enc.min()) / _DEG)
    params, ref = jax.jit(initialise_arc)(data)
    phi = np.asarray(params.angles)[seen]
    return float((phi.max() - phi.min()) / _DEG)
