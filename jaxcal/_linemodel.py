"""The line model of a prismatic joint's sweep (`jaxcal._arcfit.fit_line`):
the whitened residuals with their closed-form Jacobian, the closed-form start
(`initialise_line`) and which unknowns exist (`line_free_mask`).

While prismatic joint $j$ slides alone, marker $m$ translates along the
joint's direction $V$ (unit, camera frame) and keeps its orientation:

$$P_{mt} = p_m + V\\,s\\,q_t, \\qquad O_{mt} = O_m,$$

with $q_t$ the commanded position from the encoder (m: motor angle over the
nominal ratio), $s$ the scale (true travel per commanded travel, the
prismatic counterpart of the arc's rate: the true ratio is the nominal one
over $s$) and $(p_m, O_m)$ the marker pose at encoder zero. The unknowns are
the arc fit's (`ArcParams`), with the line's position $(w_1, w_2)$ absent:
a translation has no axis position to observe. Without encoders the travel
per frame is unknown, so $s$ is not observable at all (and the pipeline
refuses such a sweep).
"""

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._arcdata import ArcData
from ._arcmodel import ArcParams, ArcReference, arc_angles, flat_jacobian, line_from_params, masked_mean
from ._geometry import (
    frame_from_z,
    matmul_unrolled,
    matvec_unrolled,
    safe_norm,
    so3_exp,
    so3_log,
    so3_right_jacobian,
    so3_right_jacobian_inv,
)
from ._linalg import nearest_rotation
from ._lsq import closed_form_jvp

#: The shortest travel a prismatic sweep must cover (mm of commanded position).
MIN_TRAVEL_MM = 5.0


def line_terms(
    params: ArcParams, ref: ArcReference, data: ArcData, *, jacobian: bool
) -> tuple[Float[Array, "markers frames k"], Float[Array, "markers frames k 11"] | None]:
    """Whitened residuals and, with `jacobian`, their derivative per marker and
    frame with respect to the arc fit's local parameters
    $\\tau = (u, v, w_1, w_2, \\varphi_t, p_m, r_m)$ (see `jaxcal._arcmodel.arc_terms`),
    here with $\\varphi_t = s\\,q_t$ the travel (m):

    - position $e = p_m + \\varphi_t V - P$: $\\partial_{(u,v)} = \\varphi_t\\,\\partial V/\\partial(u, v)$,
      $\\partial_\\varphi = V$, $\\partial_{p_m} = I$, nothing on $(w_1, w_2)$;
    - rotation $\\theta = \\log(O\\hat O^T)$, $\\hat O = O_{ref}\\exp(r_m)$:
      $d\\theta = -J_r^{-1}(\\theta)\\,\\hat O J_r(r_m)\\,dr_m$.
    """
    _, V = line_from_params(params.line, ref.R_ref, ref.c)
    phi = arc_angles(params, ref, data)  # travel (m), (F,)
    mask = data.mask
    P = jnp.where(mask[..., None], data.positions, 0.0)
    if jacobian:
        n = ref.R_ref @ jnp.stack([params.line[0], params.line[1], jnp.ones_like(params.line[0])])
        dV_duv = (jnp.eye(3) - jnp.outer(V, V)) @ ref.R_ref[:, :2] / safe_norm(n)  # (3, 2)

    def one_marker(p0, r0, O_ref, P_m, O_m, W_m, mask_m):
        e = p0 + phi[:, None] * V - P_m  # (F, 3)
        F = e.shape[0]
        if jacobian:
            D = jnp.concatenate(
                [
                    phi[:, None, None] * dV_duv,
                    jnp.zeros((F, 3, 2)),
                    jnp.broadcast_to(V[:, None], (F, 3, 1)),
                    jnp.broadcast_to(jnp.eye(3), (F, 3, 3)),
                    jnp.zeros((F, 3, 3)),
                ],
                axis=-1,
            )  # (F, 3, 11)
        if O_m is not None:
            O0 = O_ref @ so3_exp(r0)
            O_m = jnp.where(mask_m[:, None, None], O_m, jnp.eye(3))
            theta = so3_log(matmul_unrolled(O_m, jnp.broadcast_to(O0.T, (F, 3, 3))))
            e = jnp.concatenate([e, theta], axis=-1)
            if jacobian:
                dr = -matmul_unrolled(
                    so3_right_jacobian_inv(theta), jnp.broadcast_to(O0 @ so3_right_jacobian(r0), (F, 3, 3))
                )
                D = jnp.concatenate([D, jnp.concatenate([jnp.zeros((F, 3, 8)), dr], axis=-1)], axis=-2)
        r = jnp.where(mask_m[:, None], matvec_unrolled(W_m, e), 0.0)
        if not jacobian:
            return r, None
        return r, jnp.where(mask_m[:, None, None], matmul_unrolled(W_m, D), 0.0)

    if data.orientations is None:
        return jax.vmap(lambda p0, r0, Oref, Pm, Wm, mm: one_marker(p0, r0, Oref, Pm, None, Wm, mm))(
            params.p0, params.r0, ref.O_ref, P, data.sqrt_info, mask
        )
    return jax.vmap(one_marker)(params.p0, params.r0, ref.O_ref, P, data.orientations, data.sqrt_info, mask)


def _line_residuals(
    params: ArcParams, args: tuple[ArcReference, ArcData]
) -> Float[Array, "markers frames k"]:
    """Whitened residuals of the line model, per marker and frame (zero where masked)."""
    ref, data = args
    return line_terms(params, ref, data, jacobian=False)[0]


def _line_jacobian(params: ArcParams, args: tuple[ArcReference, ArcData]):
    ref, data = args
    r, D = line_terms(params, ref, data, jacobian=True)
    return r, flat_jacobian(D, ref, data)


#: `line_residuals(params, (ref, data))`: the whitened residuals, differentiated
#: in closed form (`line_terms` placed by `flat_jacobian`); encoders required.
line_residuals = closed_form_jvp(_line_residuals, _line_jacobian, _line_residuals)


def initialise_line(data: ArcData) -> tuple[ArcParams, ArcReference]:
    """Closed-form start: the translation per unit of encoder travel $b = V s$
    by a pooled linear regression $P_{mt} = \\bar P_m + b\\,(q_t - \\bar q_m)$
    over the markers, $V = b/\\|b\\|$, $s = \\|b\\|$ (positive: $V$ points the way
    the encoder counts up), $p_m = \\bar P_m - b\\,\\bar q_m$, and the mean
    orientation (encoders required)."""
    mask = data.mask
    w = mask.astype(jnp.float64)
    P = jnp.where(mask[..., None], data.positions, 0.0)
    q = data.encoder
    q_mean = jax.vmap(lambda wm: masked_mean(q, wm, 0))(w)  # (M,)
    P_mean = jax.vmap(lambda Pm, wm: masked_mean(Pm, wm[:, None], 0))(P, w)  # (M, 3)
    dq = (q[None, :] - q_mean[:, None]) * w
    b = jnp.einsum("mf,mfa->a", dq, P - P_mean[:, None, :]) / jnp.maximum(jnp.sum(dq * dq), 1e-300)
    s0 = safe_norm(b)
    V0 = b / jnp.maximum(s0, 1e-300)
    p0 = P_mean - q_mean[:, None] * b
    M, F = mask.shape
    if data.orientations is not None:
        O = jnp.where(mask[..., None, None], data.orientations, jnp.eye(3))
        O0 = nearest_rotation(jnp.einsum("mfab,mf->mab", O, w))
    else:
        O0 = jnp.broadcast_to(jnp.eye(3), (M, 3, 3))
    c = masked_mean(P_mean, jnp.any(mask, axis=1).astype(jnp.float64)[:, None], 0)
    params = ArcParams(line=jnp.zeros(4), rate=s0, p0=p0, r0=jnp.zeros((M, 3)), angles=None)
    return params, ArcReference(R_ref=frame_from_z(V0), c=c, O_ref=O0, gauge=jnp.ones(F))


def line_free_mask(params: ArcParams, data: ArcData) -> ArcParams:
    """Which parameters the line model has: the direction `(u, v)` (not the
    line's position), the scale, the zero poses (orientations when measured)."""
    return ArcParams(
        line=jnp.array([1.0, 1.0, 0.0, 0.0]),
        rate=jnp.asarray(1.0),
        p0=jnp.ones_like(params.p0),
        r0=jnp.ones_like(params.r0) * (1.0 if data.orientations is not None else 0.0),
        angles=None,
    )
