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

import functools
from collections.abc import Callable
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, Bool, Float, Int

from . import _lsq
from ._arcdata import MIN_FRAMES, MIN_SWEEP_DEG, ArcData
from ._arcmodel import (
    ArcParams,
    ArcReference,
    arc_angles,
    arc_residuals,
    arc_terms,
    flat_jacobian,
    free_mask,
    initialise_arc,
    line_from_params,
    masked_mean,
)
from ._geometry import (
    make_pose,
    matmul,
    so3_exp,
)
from ._kinematics import PRISMATIC, REVOLUTE
from ._linemodel import MIN_TRAVEL_MM, initialise_line, line_free_mask, line_residuals, line_terms
from ._lsq import LMOptions
from ._options import RobustOptions, robust_terms
from ._robust import (
    deletion_residuals,
    irls_rounds_evaluated,
    irls_rounds_reweighted,
    robust_scale,
    round_plan,
    sample_weights,
)
from ._schur import block_covariance, block_least_squares

_DEG = np.pi / 180.0


class _Model(NamedTuple):
    """A sweep's model: its whitened residuals `residuals(params, (ref, data))`
    and their local derivatives `terms(params, ref, data, jacobian=...)`."""

    residuals: Callable
    terms: Callable


_ARC = _Model(arc_residuals, arc_terms)
_LINE = _Model(line_residuals, line_terms)


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
      over the samples it used of $d/m(\\nu)$, $d$ the deletion residual,
      $m(\\nu)$ the median of $\\chi_\\nu$, $\\nu$ the sample's degrees of
      freedom; about 1 when the noise model is honest; see `jaxcal._robust`).
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


# --------------------------------------------------------------------------- solve

#: `fit_arc`'s and `fit_line`'s solver settings: whitened residuals, so `atol` in noise units.
ARC_OPTIONS = LMOptions(rtol=1e-8, atol=3e-2, max_steps=50)


def fit_arc(
    data: ArcData,
    *,
    robust: RobustOptions | None = None,
    options: LMOptions = ARC_OPTIONS,
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
    each (marker, frame) sample is judged by its deletion residual $d$, the
    residual it would have if the fit (with the weights it was solved with)
    had not used it, $d^2 = r^T[(I - wG)(I + (1 - w)G)]^{+} r$ with
    $G = J_i C J_i^T$ from the covariance's per-sample blocks (for $w = 1$,
    $r^T(I - H_{ii})^{-1}r$): a sample at a sweep's end, which decides the
    angle scale and pulls the fit towards itself, cannot hide behind its own
    small residual. $d$ is put in robust sigmas, $z = d/s$ with $s$ the median
    of $d/m(\\nu)$ ($m(\\nu)$ the median of $\\chi_\\nu$, $\\nu = k$ less the
    directions the sample alone determines, $k = 3$ or 6: a one-marker
    frame's own angle takes one), mapped to the 2-D radius with the same tail
    probability (`jaxcal._robust`), and weighted
    (Cauchy $1/(1 + (z/c)^2)$, Huber $\\min(1, c/z)$); `rounds` solves with
    the weights of the previous solution, then one least-squares solve on the
    inliers ($z <$ `reject`, weight 1; others 0), whose Jacobian gives the
    covariance, scaled by the inlier residual variance: honest standard
    deviations. All rounds are one `lax.scan` (one compiled solver); each
    round's weights come from a converged solution, so which samples are
    rejected does not depend on `max_steps` once every round converges.

    **Arguments:**
    - `data`: an `ArcData` (see `make_arc_data`; `stack_sweeps` for several).
    - `robust`: a `RobustOptions` (`loss` `"cauchy"` or `"huber"`; `c` the loss
      constant and `reject` the inlier threshold (`None`: no inlier solve),
      both as 2-D radii in robust sigmas: a clean sample is rejected with
      probability $e^{-reject^2/2}$, 0.1 % at 3.7; `rounds` IRLS solves before
      the inlier solve), or `None`: plain least squares, one solve.
    - `options`: the solver's `LMOptions` (`rtol`, `atol`, `max_steps` per
      round; optimistix's rules). The residuals are whitened, so `atol` is in
      units of the noise: the solver stops when a step moves every
      prediction by less than `atol` standard deviations (Gauss-Newton then
      leaves the iterate ~`atol**2` from the optimum; tighter tolerances only
      chase float64 round-off in the loss). `throw`: raise (through
      `eqx.error_if`) when a round does not converge.

    **Returns:** an `ArcFitResult`.
    """
    params0, ref = initialise_arc(data)
    solve = functools.partial(_solve_dense, model=_ARC) if data.encoder is not None else _solve_blocks
    fit = functools.partial(
        _fit, robust=robust, options=options, throw=throw, scale_covariance=scale_covariance
    )
    return fit(_ARC, solve, params0, ref, free_mask(params0, data, ref), data, name="fit_arc")


def _fit(
    model, solve, params0, ref, free, data, *, robust, options: LMOptions, throw, scale_covariance, name
) -> ArcFitResult:
    """The IRLS rounds and the summary shared by `fit_arc` and `fit_line`."""
    loss, c, reject, rounds = robust_terms(robust)
    rtol, atol, max_steps = options.rtol, options.atol, options.max_steps
    hard_flags = round_plan(loss, rounds, reject)
    mask = data.mask
    mask_f = mask.astype(params0.line.dtype)
    reject_ = jnp.inf if reject is None else reject

    def weights_at(params, w, hard):
        """The next round's weights, and the terms of the fit at `params` under `w`."""
        terms = _terms(model, params, ref, data, free, w)
        d, nu = terms[-1]
        return sample_weights(d, nu, mask, loss=loss, c=c, reject=reject_, hard=hard)[0], terms

    def solve_with(params, w):
        return solve(params, ref, data, free, w, rtol=rtol, atol=atol, max_steps=max_steps)

    def frozen(params):
        return jax.tree.map(lambda x, f: x * f, params, free)

    if loss is None:
        out = irls_rounds_reweighted(solve_with, lambda p, w, hard: mask_f, params0, mask_f, hard_flags)
        terms = None
    else:
        # The rounds' last evaluation, at the solution (frozen entries zero) under its weights,
        # is the summary's: one copy of the Jacobian in the program.
        out, terms = irls_rounds_evaluated(solve_with, weights_at, params0, mask_f, hard_flags, frozen)
    params, steps, ok, result = out.value, out.num_steps, out.ok, out.result
    if throw:
        params = eqx.error_if(params, ~ok, f"{name}: a Levenberg-Marquardt solve did not converge")
    return _summarise(
        model,
        frozen(params),
        ref,
        data,
        free,
        result,
        steps,
        scale_covariance,
        weights=out.weights,
        round_results=out.round_results,
        round_steps=out.round_steps,
        terms=terms,
    )


def fit_line(
    data: ArcData,
    *,
    robust: RobustOptions | None = None,
    options: LMOptions = ARC_OPTIONS,
    throw: bool = False,
    scale_covariance: bool = True,
) -> ArcFitResult:
    """Fit one prismatic joint's direction and scale to a sweep; pure, jittable and vmappable.

    The prismatic counterpart of `fit_arc` (the model is in `jaxcal._linemodel`):
    the markers translate by $V\\,s\\,q_t$ and keep their orientation. Closed-form
    start (a linear regression of position on encoder position), then
    optimistix's Levenberg-Marquardt on the whitened residuals, with the same
    robust rounds, covariance and arguments as `fit_arc`.

    Encoders are required: without them the travel of every frame is an
    unknown and the scale $s$ (m per commanded m) is not observable.

    **Returns:** an `ArcFitResult` of the same structure as `fit_arc`'s (so
    sweeps of both kinds stack): `direction` $V$ (the way the encoder counts
    up), `rate` the scale $s$ (`rate_var` its variance), `angles` the travel
    $s\\,q_t$ (m), `T_cam_marker0` the marker poses at encoder zero, `point`
    NaN (a translation has no axis position; `cov`'s point rows are zero), and
    in `meas` the line position $(w_1, w_2)$ zero with unit variance in
    `meas_cov`, uncorrelated: a placeholder the axis fit ignores.
    """
    if data.encoder is None:
        raise ValueError(
            "fit_line: a prismatic sweep needs encoder positions: without them the scale "
            "(travel per commanded travel) is not observable"
        )
    params0, ref = initialise_line(data)
    fit = functools.partial(
        _fit, robust=robust, options=options, throw=throw, scale_covariance=scale_covariance
    )
    solve = functools.partial(_solve_dense, model=_LINE)
    res = fit(_LINE, solve, params0, ref, line_free_mask(params0, data), data, name="fit_line")
    eye_w = jnp.zeros(res.meas.shape[0]).at[2:4].set(1.0)
    return eqx.tree_at(
        lambda r: (r.point, r.meas_cov), res, (jnp.full(3, jnp.nan), res.meas_cov + jnp.diag(eye_w))
    )


def fit_joint_sweeps(data: ArcData, joint_types: tuple[str, ...], **kwargs) -> ArcFitResult:
    """Every joint's sweep fitted by its kind, stacked in joint order: `fit_arc`
    (vmapped) for the revolute joints, `fit_line` for the prismatic ones.

    **Arguments:** `data` stacked over joints (`stack_sweeps`); `joint_types`
    (static) one per joint; `kwargs` go to both fits.
    """
    kinds = tuple(joint_types)
    if len(kinds) != data.mask.shape[0]:
        raise ValueError(f"fit_joint_sweeps: {len(kinds)} joint types for {data.mask.shape[0]} sweeps")
    rev = [j for j, k in enumerate(kinds) if k == REVOLUTE]
    pri = [j for j, k in enumerate(kinds) if k == PRISMATIC]
    if not pri:
        return jax.vmap(lambda d: fit_arc(d, **kwargs))(data)
    take = lambda idx: jax.tree.map(lambda x: x[np.asarray(idx)], data)  # noqa: E731
    parts = [jax.vmap(lambda d: fit_line(d, **kwargs))(take(pri))]
    if rev:
        parts.insert(0, jax.vmap(lambda d: fit_arc(d, **kwargs))(take(rev)))
    order = np.argsort(np.asarray(rev + pri))
    return jax.tree.map(lambda *xs: jnp.concatenate(xs)[order], *parts)


def _solve_dense(params, ref, data, free, w, *, rtol, atol, max_steps, model):
    """optimistix's Levenberg-Marquardt on the weighted residuals (with encoders: few unknowns)."""

    def fn(p, args):
        ref_, data_, sw = args
        p = jax.tree.map(lambda x, f: x * f, p, free)
        return model.residuals(p, (ref_, data_)) * sw[..., None]

    sol = _lsq.solve(fn, params, (ref, data, jnp.sqrt(w)), _lsq.LMOptions(rtol, atol, max_steps))
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
    frame's own angle, placed from `arc_terms`' local derivatives."""
    ref, data, sw = args
    r, D = arc_terms(_from_blocks(g, l, ref, data), ref, data, jacobian=True)
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


def _covariance(model, params, ref, data, free, w):
    """Unscaled covariance blocks under weights `w`, and each sample's block $G_i = J_i C J_i^T$.

    $C = (J^T W J)^{+}$ over the free parameters, $J_i$ the sample's unweighted
    (whitened) Jacobian block: $w_i G_i$ is its block of the hat matrix, whose
    trace is its leverage (see `jaxcal._robust.deletion_residuals`). Only
    per-sample blocks are formed: memory stays linear in the frames.

    **Returns:** `(cov_line_rate (5, 5), cov_meas, G (markers, frames, k, k))`.
    """
    M, F = data.mask.shape
    k = data.sqrt_info.shape[-1]
    sw = jnp.sqrt(w)
    has_rot = data.orientations is not None
    if data.encoder is None:
        g, l = _to_blocks(params, data)
        g_mask, l_mask = _to_blocks(free, data)
        _, Jg, Jl = _arc_blocks(g, l, (ref, data, jnp.ones_like(sw)))
        Jg, Jl = Jg * g_mask, Jl * l_mask[:, None, :]
        sw_rows = jnp.repeat(sw.T, k, axis=1)[..., None]  # block rows are (marker, component)
        cov = block_covariance(Jg * sw_rows, Jl * sw_rows, g_mask=g_mask > 0, l_mask=l_mask > 0)
        A = Jg.reshape(F, M, k, -1)
        B = Jl.reshape(F, M, k, -1)
        cross = jnp.einsum("fmai,fij,fmbj->fmab", A, cov.gl, B)
        G = (
            jnp.einsum("fmai,ij,fmbj->fmab", A, cov.gg, A)
            + cross
            + jnp.swapaxes(cross, -1, -2)
            + jnp.einsum("fmai,fij,fmbj->fmab", B, cov.ll, B)
        )
        cov_lr = jnp.zeros((5, 5), g.dtype).at[:4, :4].set(cov.gg[:4, :4])
        return cov_lr, cov.gg, jnp.swapaxes(G, 0, 1)
    flat, unravel = ravel_pytree(params)
    free_flat, _ = ravel_pytree(free)
    _, D = model.terms(params, ref, data, jacobian=True)
    J = flat_jacobian(D, ref, data) * free_flat[None, :]
    Jw = J * jnp.repeat(sw.reshape(-1), k)[:, None]
    # Pseudo-inverse restricted to the free parameters (absent ones have zero columns).
    cov = _lsq.normal_pinv(Jw.T @ Jw, free_flat)
    Jb = J.reshape(M, F, k, -1)
    G = jnp.einsum("mfai,mfbi->mfab", Jb @ cov, Jb)
    cov_p = unravel_cov(cov, unravel, flat, has_rot)
    return cov_p["line_rate"], cov_p["meas"], G


def _terms(model, params, ref, data, free, w):
    """The fit's terms at `params` under weights `w`: `(r, (cov_lr, cov_meas, G), (d, nu))`, the
    residuals, `_covariance`'s blocks and each sample's deletion residual norm and degrees of
    freedom, `(markers, frames)` each (`jaxcal._robust.deletion_residuals`)."""
    r = model.residuals(params, (ref, data))
    cov = _covariance(model, params, ref, data, free, w)
    return r, cov, deletion_residuals(r, cov[2], w, data.mask)


def _summarise(
    model,
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
    terms=None,
) -> ArcFitResult:
    """The `ArcFitResult` at `params` (frozen entries already zero), the
    covariance from the Jacobian with `weights` (default: the mask); `terms`: `_terms` there,
    when the caller has them."""
    mask = data.mask
    mask_w = mask.astype(jnp.float64)
    w = mask_w if weights is None else weights
    if round_results is None:
        round_results = jax.tree.map(lambda r: r[None], result)
        round_steps = jnp.asarray(num_steps)[None]
    has_enc = data.encoder is not None
    has_rot = data.orientations is not None
    k = data.sqrt_info.shape[-1]
    r, (cov_lr, meas_cov, hat), (d, nu) = (
        _terms(model, params, ref, data, free, w) if terms is None else terms
    )
    e = jnp.linalg.norm(r, axis=-1)
    h = w * jnp.trace(hat, axis1=-2, axis2=-1)  # leverages
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
    centroid = masked_mean(P.reshape(-1, 3), mask_w.reshape(-1)[:, None], 0)
    Q_c = Q + jnp.dot(centroid - Q, V) * V
    O0 = jax.vmap(lambda Oref, r0: Oref @ so3_exp(r0))(ref.O_ref, params.r0)
    T0 = jax.vmap(make_pose)(O0, params.p0)
    # Unwhitened RMS of positions and rotations over the samples the solve used.
    used = (w > 0) & mask
    used_w = used.astype(jnp.float64)
    n_used = jnp.maximum(jnp.sum(used_w), 1)
    raw = _raw_errors(model, params, ref, data)
    pos_rms = jnp.sqrt(jnp.sum(jnp.sum(raw[..., :3] ** 2, -1) * used_w) / n_used)
    rot_rms = (
        jnp.sqrt(jnp.sum(jnp.sum(raw[..., 3:] ** 2, -1) * used_w) / n_used)
        if raw.shape[-1] == 6
        else jnp.asarray(jnp.nan)
    )
    meas = jnp.concatenate(
        [params.line, params.p0.reshape(-1)] + ([params.r0.reshape(-1)] if has_rot else [])
    )
    return ArcFitResult(
        direction=V,
        point=Q_c,
        rate=params.rate if has_enc else jnp.asarray(jnp.nan),
        T_cam_marker0=T0,
        angles=arc_angles(params, ref, data),
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
        robust_scale=robust_scale(d, nu, used),
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


def _raw_errors(model, params, ref, data):
    """Unwhitened (position, rotation) errors, by setting W to identity."""
    k = data.sqrt_info.shape[-1]
    eye = jnp.broadcast_to(jnp.eye(k), data.sqrt_info.shape)
    return model.residuals(params, (ref, eqx.tree_at(lambda d: d.sqrt_info, data, eye)))


def arc_outliers(res: ArcFitResult, mask: Bool[Array, "markers frames"]) -> np.ndarray:
    """The (marker, frame) samples a robust arc fit rejected: observed in
    `mask` and not used by its final solve, as an `(n, 2)` int array (NumPy;
    outside jit, one fit, not a batch)."""
    bad = np.asarray(mask) & ~np.asarray(res.inlier)
    return np.argwhere(bad)


# --------------------------------------------------------------------------- input checks


def validate_arc_data(data: ArcData, joint: str, kind: str = REVOLUTE) -> None:
    """Raise a `ValueError` naming `joint` if the sweep cannot give an axis.

    Checks shapes, NaN/inf in observed entries, at least `MIN_FRAMES`
    observed frames, and a sweep of at least `MIN_SWEEP_DEG` degrees; a
    prismatic joint's sweep (`kind`) needs encoder positions and a travel of
    at least `MIN_TRAVEL_MM` (`fit_line`).
    """
    if kind == PRISMATIC and data.encoder is None:
        raise ValueError(
            f"joint {joint!r}: a prismatic joint's sweep needs encoder positions: from images alone "
            "its direction is seen but not its scale (travel per commanded travel)"
        )
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
    if kind == PRISMATIC:
        enc = np.asarray(data.encoder)[mask.any(axis=0)]
        travel = float(enc.max() - enc.min()) * 1e3
        if travel < MIN_TRAVEL_MM:
            raise ValueError(
                f"joint {joint!r}: the prismatic sweep travels {travel:.2f} mm, at least {MIN_TRAVEL_MM:g} are needed"
            )
        return
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
