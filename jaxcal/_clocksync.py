"""Clock synchronisation: encoder angles at the camera's frame times, and the clock offset.

The camera stamps frames on its own clock, the controller stamps the encoder
log on another; they are related by (see `docs/dataset.md`)

$$t_{cam} = \\delta + (1 + \\epsilon)\\,t_{ctrl},$$

with the offset $\\delta$ (s) and the drift $\\epsilon$ (ppm). A frame's
encoder angle is the log interpolated (`interpolate_encoders`) at
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
from jaxtyping import Array, Bool, Float, Int

from . import _lsq
from ._arcdata import ArcData
from ._arcmodel import arc_residuals, free_mask, initialise_arc
from ._lsq import LMOptions
from ._options import RobustOptions, robust_terms
from ._robust import (
    deletion_residuals,
    irls_rounds_evaluated,
    irls_rounds_reweighted,
    round_plan,
    sample_weights,
)

_MS = 1e-3


def controller_time(
    t_cam: Float[Array, "..."], offset_s: Float[Array, ""] | float, drift_ppm: float = 0.0
) -> Float[Array, "..."]:
    """Controller-clock time of camera-clock stamps, $(t_{cam} - \\delta)/(1 + \\epsilon)$ (s)."""
    return (t_cam - offset_s) / (1.0 + 1e-6 * drift_ppm)


#: Where a frame's stamp sits in its exposure (`metadata.json` `cameras[].stamp`): the fraction of the exposure before it.
STAMP_FRACTION = {"start": 0.0, "middle": 0.5, "end": 1.0}


def exposure_middle(t_cam, exposure_s: float | None, stamp: str | None):
    """The camera-clock time of the middle of the exposure of frames stamped `t_cam`:
    $t_{cam} + (1/2 - f)\\,E$ for exposure $E$ and a stamp a fraction $f$ into it
    (`STAMP_FRACTION`). Unchanged when the exposure or the stamp's meaning is unknown
    (`None`): the stamp is then taken for the middle."""
    if exposure_s is None or stamp is None:
        return t_cam
    return t_cam + (0.5 - STAMP_FRACTION[stamp]) * exposure_s


def encoder_slopes(enc_t: Float[Array, " T"], enc_q: Float[Array, " T"]) -> Float[Array, " T"]:
    """The log's rate at each sample: the slope at $t_i$ of the parabola through its
    neighbours, $m_i = (h_{i-1} d_i + h_i d_{i-1}) / (h_{i-1} + h_i)$ with
    $h_i = t_{i+1} - t_i$ and $d_i = (q_{i+1} - q_i)/h_i$; the end samples take
    their segment's $d$ (0 across a repeated time)."""
    h = jnp.diff(enc_t)
    d = jnp.where(h > 0.0, jnp.diff(enc_q) / jnp.where(h > 0.0, h, 1.0), 0.0)
    hl, hr, dl, dr = h[:-1], h[1:], d[:-1], d[1:]
    span = hl + hr
    inner = jnp.where(span > 0.0, (hr * dl + hl * dr) / jnp.where(span > 0.0, span, 1.0), 0.0)
    return jnp.concatenate([d[:1], inner, d[-1:]])


#: Log segments this long or shorter (s) are read linearly, longer ones by the cubic Hermite form
#: (`interpolate_encoders`): a log at 200 Hz or faster reads as before the cubic was added.
LINEAR_UP_TO_S = 5e-3


def interpolate_encoders(
    t: Float[Array, "..."], enc_t: Float[Array, " T"], enc_q: Float[Array, " T"]
) -> Float[Array, "..."]:
    """The encoder log `(enc_t, enc_q)` interpolated at controller times `t`: linearly on
    segments up to `LINEAR_UP_TO_S` long, by a cubic Hermite segment on longer ones.

    On segment $[t_i, t_{i+1}]$ of length $h$, with $s = (t - t_i)/h$, the cubic is
    $q = H_{00}(s) q_i + H_{10}(s) h m_i + H_{01}(s) q_{i+1} + H_{11}(s) h m_{i+1}$
    (the cubic Hermite basis) with the slopes $m_i$ of `encoder_slopes`. A linear
    interpolation errs by up to $h^2 \\max|\\ddot q| / 8$, a bias wherever the joint
    accelerates (0.03 deg at 50 Hz through a cosine sweep of 80 deg in 0.8 s); the
    three-point slopes err by $h^2 \\dddot q / 6$, which the basis weighs by at most
    $h/4$, so the cubic errs by at most $h^3 \\max|\\dddot q| / 24 + h^4 \\max|q^{(4)}| / 384$
    (the second term: the Hermite cubic's own error with exact slopes). Both pass
    through every sample. Differentiable in `t`; clamped to the first/last reading
    outside the log (callers check the overlap first).
    """
    linear = jnp.interp(t, enc_t, enc_q)
    m = encoder_slopes(enc_t, enc_q)
    i = jnp.clip(jnp.searchsorted(enc_t, t, side="right") - 1, 0, enc_t.shape[0] - 2)
    h = enc_t[i + 1] - enc_t[i]
    s = jnp.where(h > 0.0, (t - enc_t[i]) / jnp.where(h > 0.0, h, 1.0), 0.0)
    s = jnp.where(s < 0.0, 0.0, jnp.where(s > 1.0, 1.0, s))  # not jnp.clip: its gradient halves at a tie
    s2, s3 = s * s, s * s * s
    cubic = (
        (2.0 * s3 - 3.0 * s2 + 1.0) * enc_q[i]
        + (s3 - 2.0 * s2 + s) * h * m[i]
        + (3.0 * s2 - 2.0 * s3) * enc_q[i + 1]
        + (s3 - s2) * h * m[i + 1]
    )
    return jnp.where(h > LINEAR_UP_TO_S, cubic, linear)


class ClockFit(eqx.Module):
    """The estimated clock offset.

    - `offset_s`, `std_s`: $\\delta$ and its standard deviation (s).
    - `result`: optimistix's result (`successful` when every round converged,
      else the first failing round's code); `num_steps`: the steps of all
      rounds; `round_results`, `round_steps`: each round's.
    - `residual_rms`: RMS of the whitened arc residuals the final solve used.
    - `sample_residuals`: each (joint, marker, frame) sample's whitened
      residual norm at the solution, `(joints, markers, frames)` (0 where
      unobserved); `weights`: the final solve's weights; `inlier`: the
      observed samples it used (see `jaxcal._arcfit.fit_arc`).
    """

    offset_s: Float[Array, ""]
    std_s: Float[Array, ""]
    result: optx.RESULTS
    num_steps: Int[Array, ""]
    residual_rms: Float[Array, ""]
    sample_residuals: Float[Array, "joints markers frames"]
    weights: Float[Array, "joints markers frames"]
    inlier: Bool[Array, "joints markers frames"]
    round_results: optx.RESULTS
    round_steps: Int[Array, " rounds"]


def _with_encoder(data: ArcData, encoder: Float[Array, " frames"]) -> ArcData:
    return eqx.tree_at(lambda d: d.encoder, data, encoder, is_leaf=lambda x: x is None)


def _deletion(J, cov, r, w, mask):
    """Deletion residuals (`jaxcal._robust`) of the `(joints, markers, frames)` samples
    from the unweighted Jacobian `J` and the weighted fit's covariance `cov`:
    per sample $G_i = J_i C J_i^T$, a $k \\times k$ block."""
    Jb = J.reshape(r.shape + (-1,))
    hat = jnp.einsum("...ai,...bi->...ab", Jb @ cov, Jb)
    return deletion_residuals(r, hat, w, mask)


#: `fit_clock_offset`'s solver settings (whitened residuals: `atol` in noise units).
CLOCK_OPTIONS = LMOptions(rtol=1e-8, atol=1e-2, max_steps=100)


def fit_clock_offset(
    data: ArcData,
    t_cam: Float[Array, "joints frames"],
    enc_t: Float[Array, " T"],
    enc_q: Float[Array, "T joints"],
    *,
    offset0_s: float = 0.0,
    drift_ppm: float = 0.0,
    robust: RobustOptions | None = None,
    options: LMOptions = CLOCK_OPTIONS,
    throw: bool = False,
) -> ClockFit:
    """Estimate the camera-controller clock offset from the joint sweeps; pure and jittable.

    One Levenberg-Marquardt solve of every joint's arc model (`arc_residuals`)
    with the encoder angles $\\alpha_{jt} = q_j(t_{ctrl}(t_{cam,jt}; \\delta))$
    interpolated from the log, over all arc parameters and $\\delta$ (solved in
    ms for conditioning). Each joint's arc start is the closed form at
    `offset0_s`.

    With a robust `loss`, the rounds of `jaxcal._arcfit.fit_arc`: IRLS
    solves weighting each (joint, marker, frame) sample by its deletion
    residual in robust sigmas (the residual it would have if the joint
    problem, offset included, had not used it; `jaxcal._robust`; one scale
    per joint), then a least-squares
    solve on the inliers whose Jacobian gives $\\delta$'s standard deviation.
    A corrupted frame otherwise pulls the offset, which every joint shares.

    **Arguments:**
    - `data`: the sweeps, stacked over joints (`encoder` is ignored and
      replaced by the interpolated log), `(joints, markers, frames, ...)`.
    - `t_cam`: the frames' camera-clock stamps (s), `(joints, frames)`; padding
      may hold anything finite.
    - `enc_t` (s, controller clock), `enc_q`: the encoder log as commanded
      joint positions (`motor / nominal ratio`, rad), `(T, joints)`.
    - `offset0_s`: a start for $\\delta$ (s); `drift_ppm`: the known drift.
    - `robust`: a `RobustOptions`, as `fit_arc`'s (default `None`: plain least squares).
    - `options`: the solver's `LMOptions` (`max_steps` per round); `throw`: raise
      (`eqx.error_if`) when a round does not converge.

    **Returns:** a `ClockFit`.
    """
    loss, c, reject, rounds = robust_terms(robust)
    hard_flags = round_plan(loss, rounds, reject)
    residuals, params0, free = _joint_problem(data, t_cam, enc_t, enc_q, offset0_s, drift_ppm)
    mask = data.mask
    mask_f = mask.astype(jnp.float64)
    k = data.sqrt_info.shape[-1]
    free_flat = ravel_pytree((free, jnp.ones(())))[0]

    def unweighted(y):
        """The residuals (0/1 weights: the mask) and their Jacobian over the free parameters,
        one forward pass; weights `w` scale their rows by `rows(w)`."""
        flat, unravel = ravel_pytree(y)
        r, J = _lsq.value_and_jacfwd(lambda x: residuals(unravel(x), mask_f).reshape(-1), flat)
        return r.reshape(mask.shape + (k,)), J * free_flat

    def rows(w):
        return jnp.repeat(jnp.sqrt(w).reshape(-1), k)

    def terms(y, w):
        """`(r, J, Jw, cov)`: the unweighted residuals at `y` and their Jacobian, it weighted by
        `w`, and the unscaled $(J^T W J)^{+}$ over the free parameters."""
        r, J = unweighted(y)
        Jw = J * rows(w)[:, None]
        return r, J, Jw, _lsq.normal_pinv(Jw.T @ Jw, free_flat)

    def weights_at(y, w, hard):
        """The next round's weights, and the `terms` at `y` under `w` (less `J`)."""
        r, J, Jw, cov = terms(y, w)
        d, nu = _deletion(J, cov, r, w, mask)
        reject_ = jnp.inf if reject is None else reject
        weigh = lambda d_j, nu_j, m_j: sample_weights(  # noqa: E731
            d_j, nu_j, m_j, loss=loss, c=c, reject=reject_, hard=hard
        )[0]
        return jax.vmap(weigh)(d, nu, mask), (r, Jw, cov)  # one noise scale per joint

    def solve(y, w):
        sol = _lsq.solve_normal(residuals, y, w, options)
        return sol.value, sol.result, sol.stats["num_steps"]

    y0 = (params0, jnp.zeros(()))
    if loss is None:
        out = irls_rounds_reweighted(solve, lambda y, w, hard: mask_f, y0, mask_f, hard_flags)
        r, _, Jw, cov = terms(out.value, out.weights)
        last = r, Jw, cov
    else:  # the rounds' last evaluation, at the solution under its weights: one copy of the Jacobian
        out, last = irls_rounds_evaluated(solve, weights_at, y0, mask_f, hard_flags)
    y = out.value
    if throw:
        y = eqx.error_if(y, ~out.ok, "fit_clock_offset: a Levenberg-Marquardt solve did not converge")
    r, Jw, cov = last
    return _clock_fit(y, out, (Jw, cov), r, data, offset0_s)


def _joint_problem(data: ArcData, t_cam, enc_t, enc_q, offset0_s, drift_ppm):
    """Every joint's arc problem with the clock offset an unknown: `(residuals, start, free)`,
    `residuals((arc_params, offset_ms), w)` the arc residuals (weights `w`) with the encoder
    angles interpolated at the offset, the start each joint's closed form at `offset0_s`
    and `free` its arc parameters' mask."""

    def encoders(offset_s):
        t = controller_time(t_cam, offset_s, drift_ppm)
        return jax.vmap(interpolate_encoders, in_axes=(0, None, 1))(t, enc_t, enc_q)

    enc0 = encoders(offset0_s)
    data0 = jax.vmap(_with_encoder)(data, enc0)
    params0, refs = jax.vmap(initialise_arc)(data0)
    free = jax.vmap(free_mask)(params0, data0, refs)

    def residuals(y, w):
        arc_params, offset_ms = y
        arc_params = jax.tree.map(lambda x, f: x * f, arc_params, free)
        d = jax.vmap(_with_encoder)(data, encoders(offset0_s + _MS * offset_ms))
        r = jax.vmap(lambda p, r, dj: arc_residuals(p, (r, dj)))(arc_params, refs, d)
        return r * jnp.sqrt(w)[..., None]

    return residuals, params0, free


def _clock_fit(y, out, jac_cov, raw, data: ArcData, offset0_s) -> ClockFit:
    """The `ClockFit` at the last round's solution `y` (of the rounds `out`), from its
    weighted Jacobian and covariance `jac_cov` and its unweighted residuals `raw`: the offset's
    standard deviation scaled by the residual variance over the parameters the data determine
    (the hat matrix's trace)."""
    J, cov = jac_cov
    w, mask, k = out.weights, data.mask, data.sqrt_info.shape[-1]
    r = raw * jnp.sqrt(w)[..., None]
    n = jnp.sum((J @ cov) * J)  # the parameters the data determine (trace of the hat matrix)
    n_obs = jnp.sum(w) * k
    sigma2 = jnp.sum(r**2) / jnp.maximum(n_obs - n, 1.0)
    var_ms = cov[-1, -1] * sigma2
    e = jnp.linalg.norm(raw, axis=-1)
    return ClockFit(
        offset_s=offset0_s + _MS * y[1],
        std_s=_MS * jnp.sqrt(jnp.maximum(var_ms, 0.0)),
        result=out.result,
        num_steps=out.num_steps,
        residual_rms=jnp.sqrt(jnp.sum(r**2) / jnp.maximum(n_obs, 1.0)),
        sample_residuals=jnp.where(mask, e, 0.0),
        weights=w,
        inlier=(w > 0) & mask,
        round_results=out.round_results,
        round_steps=out.round_steps,
    )
