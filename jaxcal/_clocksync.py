"""Clock synchronisation: encoder angles at the camera's frame times, and the clock offset.

The camera stamps frames on its own clock, the controller stamps the encoder
log on another; they are related by (see `docs/dataset.md`)

$$t_{cam} = \\delta + (1 + \\epsilon)\\,t_{ctrl},$$

with the offset $\\delta$ (s) and the drift $\\epsilon$ (ppm). A frame's
encoder angle is the log interpolated (linearly) at
$t_{ctrl} = (t_{cam} - \\delta)/(1 + \\epsilon)$.

When $\\delta$ is unknown it enters the arc fits of every joint as one shared
parameter: the encoder angles are a differentiable function of it through the
interpolation, and one Levenberg-Marquardt solve over all joints' arc
parameters and $\\delta$ finds it. A constant shift of the angles would be
absorbed by the marker's zero pose, but the sweeps accelerate and decelerate,
so a time shift is not a constant angle shift: that is what makes $\\delta$
observable (and why frames near the ends of a sweep matter).
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, Float, Int

from ._arcfit import ArcData, _free_mask, arc_residuals, initialise_arc

_MS = 1e-3


def controller_time(
    t_cam: Float[Array, "..."], offset_s: Float[Array, ""] | float, drift_ppm: float = 0.0
) -> Float[Array, "..."]:
    """Controller-clock time of camera-clock stamps, $(t_{cam} - \\delta)/(1 + \\epsilon)$ (s)."""
    return (t_cam - offset_s) / (1.0 + 1e-6 * drift_ppm)


def interpolate_encoders(
    t: Float[Array, "..."], enc_t: Float[Array, " T"], enc_q: Float[Array, " T"]
) -> Float[Array, "..."]:
    """The encoder log `(enc_t, enc_q)` linearly interpolated at controller times `t`.

    Differentiable in `t` (the slope of the segment it falls in); clamped to
    the first/last reading outside the log (callers check the overlap first).
    """
    return jnp.interp(t, enc_t, enc_q)


class ClockFit(eqx.Module):
    """The estimated clock offset.

    - `offset_s`, `std_s`: $\\delta$ and its standard deviation (s).
    - `result`, `num_steps`: optimistix's result and step count.
    - `residual_rms`: RMS of the whitened arc residuals at the solution.
    """

    offset_s: Float[Array, ""]
    std_s: Float[Array, ""]
    result: optx.RESULTS
    num_steps: Int[Array, ""]
    residual_rms: Float[Array, ""]


def _with_encoder(data: ArcData, encoder: Float[Array, " frames"]) -> ArcData:
    return eqx.tree_at(lambda d: d.encoder, data, encoder, is_leaf=lambda x: x is None)


def fit_clock_offset(
    data: ArcData,
    t_cam: Float[Array, "joints frames"],
    enc_t: Float[Array, " T"],
    enc_q: Float[Array, "T joints"],
    *,
    offset0_s: float = 0.0,
    drift_ppm: float = 0.0,
    rtol: float = 1e-8,
    atol: float = 1e-2,
    max_steps: int = 100,
    throw: bool = False,
) -> ClockFit:
    """Estimate the camera-controller clock offset from the joint sweeps; pure and jittable.

    One Levenberg-Marquardt solve of every joint's arc model (`arc_residuals`)
    with the encoder angles $\\alpha_{jt} = q_j(t_{ctrl}(t_{cam,jt}; \\delta))$
    interpolated from the log, over all arc parameters and $\\delta$ (solved in
    ms for conditioning). Each joint's arc start is the closed form at
    `offset0_s`.

    **Arguments:**
    - `data`: the sweeps, stacked over joints (`encoder` is ignored and
      replaced by the interpolated log), `(joints, markers, frames, ...)`.
    - `t_cam`: the frames' camera-clock stamps (s), `(joints, frames)`; padding
      may hold anything finite.
    - `enc_t` (s, controller clock), `enc_q`: the encoder log as commanded
      joint positions (`motor / nominal ratio`, rad), `(T, joints)`.
    - `offset0_s`: a start for $\\delta$ (s); `drift_ppm`: the known drift.

    **Returns:** a `ClockFit`.
    """

    def encoders(offset_s):
        t = controller_time(t_cam, offset_s, drift_ppm)
        return jax.vmap(interpolate_encoders, in_axes=(0, None, 1))(t, enc_t, enc_q)

    enc0 = encoders(offset0_s)
    data0 = jax.vmap(_with_encoder)(data, enc0)
    params0, refs = jax.vmap(initialise_arc)(data0)
    free = jax.vmap(_free_mask)(params0, data0, refs)

    def residuals(y, args):
        arc_params, offset_ms = y
        arc_params = jax.tree.map(lambda x, f: x * f, arc_params, free)
        d = jax.vmap(_with_encoder)(data, encoders(offset0_s + _MS * offset_ms))
        return jax.vmap(lambda p, r, dj: arc_residuals(p, (r, dj)))(arc_params, refs, d)

    y0 = (params0, jnp.zeros(()))
    solver = optx.LevenbergMarquardt(rtol=rtol, atol=atol)
    sol = optx.least_squares(residuals, solver, y0, None, max_steps=max_steps, throw=throw)
    flat, unravel = ravel_pytree(sol.value)
    free_flat = ravel_pytree((free, jnp.ones(())))[0]
    J = jax.jacfwd(lambda x: residuals(unravel(x), None).reshape(-1))(flat) * free_flat
    r = residuals(sol.value, None)
    n = jnp.sum(free_flat)
    sigma2 = jnp.sum(r**2) / jnp.maximum(jnp.sum(data.mask) * r.shape[-1] - n, 1.0)
    cov = jnp.linalg.pinv(J.T @ J + jnp.diag(1.0 - free_flat), hermitian=True)
    var_ms = cov[-1, -1] * sigma2
    return ClockFit(
        offset_s=offset0_s + _MS * sol.value[1],
        std_s=_MS * jnp.sqrt(jnp.maximum(var_ms, 0.0)),
        result=sol.result,
        num_steps=sol.stats["num_steps"],
        residual_rms=jnp.sqrt(jnp.sum(r**2) / jnp.maximum(jnp.sum(data.mask) * r.shape[-1], 1.0)),
    )
