"""The arc model of `jaxcal._arcfit`: its unknowns (`ArcParams`), their
reference frame (`ArcReference`), the line coordinates, the whitened
residuals with their closed-form Jacobian, and the closed-form start
(`initialise_arc`). See `jaxcal._arcfit` for the maths."""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.custom_derivatives import SymbolicZero
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, Bool, Float

from ._arcdata import ArcData
from ._geometry import (
    frame_from_z,
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
from ._lsq import instantiate


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


def arc_angles(params: ArcParams, ref: ArcReference, data: ArcData) -> Float[Array, " frames"]:
    if data.encoder is not None:
        return params.rate * data.encoder
    return params.angles * ref.gauge


# A nested jit: the residual function is called from several places in one
# stage program (solver steps, covariance, diagnostics); JAX traces a jitted
# callee once per argument signature and inlines the cached jaxpr, which cuts
# a cold calibrate's tracing by a fifth. Results are unchanged.
@functools.partial(jax.jit, static_argnames="jacobian")
def arc_terms(
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
    phi = arc_angles(params, ref, data)
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


def flat_jacobian(D: Float[Array, "markers frames k 11"], ref: ArcReference, data: ArcData):
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
    is the closed form of `arc_terms` (a few multiply-adds per residual,
    where forward-mode autodiff through Rodrigues and the logarithm costs
    about twenty times the residual itself).
    """
    ref, data = args
    return arc_terms(params, ref, data, jacobian=False)[0]


def _arc_residuals_autodiff(params: ArcParams, args: tuple[ArcReference, ArcData]):
    """`arc_residuals` without its custom derivative (differentiated by JAX)."""
    ref, data = args
    return arc_terms(params, ref, data, jacobian=False)[0]


def _arc_residuals_jvp(primals, tangents):
    params, args = primals
    t_params, t_args = tangents
    is_zero = lambda x: isinstance(x, SymbolicZero)
    if not all(is_zero(t) for t in jax.tree.leaves(t_args, is_leaf=is_zero)):
        # Derivatives with respect to the data (e.g. implicit differentiation of a fit): autodiff.
        inst = lambda tree: jax.tree.map(instantiate, tree, is_leaf=is_zero)
        return jax.jvp(_arc_residuals_autodiff, (params, args), (inst(t_params), inst(t_args)))
    ref, data = args
    r, D = arc_terms(params, ref, data, jacobian=True)
    t = jax.tree.map(instantiate, t_params, is_leaf=is_zero)
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
    J = flat_jacobian(D, ref, data)
    return r, (J @ ravel_pytree(t)[0]).reshape(r.shape)


arc_residuals.defjvp(_arc_residuals_jvp, symbolic_zeros=True)


# --------------------------------------------------------------------------- closed-form initialisation


def masked_mean(x, w, axis):
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
    centroids = jax.vmap(lambda Pm, wm: masked_mean(Pm, wm[:, None], 0))(P, w)  # (M, 3)

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
    c_all = masked_mean(centroids, jnp.any(mask, axis=1).astype(jnp.float64)[:, None], 0)
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
        a_mean = jax.vmap(lambda wm: masked_mean(alpha, wm, 0))(w)  # per marker
        p_mean = jax.vmap(lambda pm, wm: masked_mean(pm, wm, 0))(phi_obs, w)
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
    p0 = jax.vmap(lambda bm, wm: masked_mean(bm, wm[:, None], 0))(back, w)
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


def free_mask(params: ArcParams, data: ArcData, ref: ArcReference) -> ArcParams:
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
