"""The robot's pose noise estimated from the data: a variance component (Helmert / Förstner, REML's fixed point).

**Model.** With pixels and noisy robot poses each pose $f$ gets a correction
$\\delta_f = (v_f, w_f)$ (translation m, base-frame rotation vector rad, as
`model.corrected_robot`) with the prior $\\delta_f \\sim \\mathcal N(0,
\\mathrm{diag}(\\sigma_t^2 I_3, \\sigma_r^2 I_3))$: in the least-squares
problem, six pseudo-observations $0 = \\delta_{f,i}$ with residuals
$\\delta_{f,i}/\\sigma_i$ beside the whitened corners. The pixel noise is the
detector's (estimated per view from PnP's residuals, which no robot error
touches); $\\sigma_t$ and $\\sigma_r$ are unknown.

**Estimate.** Förstner's variance-component iteration (Förstner 1979; Koch,
*Parameter Estimation and Hypothesis Testing in Linear Models*, §3.6): each
group $k$ of observations (here the translation and the rotation priors) has
the redundancy $r_k = \\sum_{i \\in k} (1 - h_i)$, $h_i$ the leverage of its
residual (the diagonal of the hat matrix; for the prior on $\\delta_{f,i}$,
$h_i = \\mathrm{Cov}(\\hat\\delta_f)_{ii} / \\sigma_i^2$), and

$$\\sigma_k^2 \\leftarrow \\frac{\\sum_{i \\in k} \\hat\\delta_i^2}{r_k},$$

re-solving between updates, until it stops changing: then each group's
whitened residual sum of squares equals its share of the degrees of freedom
(the redundancy numbers add up to $m - n$), and the fixed point is the REML
estimate (its iteration, Koch §3.6.3). Frames no kept view saw have
$h = 1$: they neither count nor move it. The relative standard error of
$\\hat\\sigma_k$ is about $1/\\sqrt{2 r_k}$ (`robot_dof`).

**Two scales, not one.** The two components are separable from pixels: each
view fixes the camera's full pose on the board, and a robot rotation error
$w_f$ turns the camera by $w_f$, which no translation error can do, while a
translation error $v_f$ moves it without turning it. So the rotation prior's
residuals are the views' rotations and the translation prior's the views'
positions less the rotation's lever arm, and both redundancies are a sizeable
part of $3F$ (an in-plane tilt and an in-plane shift of a narrow view are
nearly confounded, which lowers them and is what they then report). Only
where a camera saw no pose of the target would one scale be forced, and
such frames carry no information about either.

**Outliers.** A wrong robot pose (a few degrees) inflates a mean of squares:
in the robust stage the update is the median over frames of each frame's
ratio $\\sum_i \\hat\\delta_{f,i}^2 / r_{f}$, over the median of a
$\\chi^2_{r_f}/r_f$ (Wilson-Hilferty), so that the rejection that follows
measures the frames against the noise of the others; the plain stage then
uses the mean (the REML step above) over the kept frames.
"""

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from .._schur import block_covariance

#: Floor of an estimated robot noise (m, rad): below it a robot pose is exact for any camera.
MIN_ROBOT_SIGMA = 1e-6
#: Ceiling (m, rad): beyond it the robot poses are not poses of these images at all.
MAX_ROBOT_SIGMA = 1.0
#: Start of the estimate (m, rad): 1 mm and 0.1 deg, a robot's typical absolute error.
ROBOT_SIGMA_START = (1e-3, 1.7453292519943296e-3)
#: The iteration stops when no variance moves by more than this fraction.
ROBOT_SIGMA_RTOL = 1e-3
#: ... or after this many updates.
ROBOT_SIGMA_MAX_UPDATES = 30


def robot_sigma6(translation, rotation) -> Float[Array, "6"]:
    """`(translation x3, rotation x3)` from the two scales."""
    return jnp.concatenate([jnp.full(3, translation), jnp.full(3, rotation)])


def robot_leverage(lin, sigma: Float[Array, "6"]) -> Float[Array, "frames 6"]:
    """$h_{f,i} = \\mathrm{Cov}(\\hat\\delta_f)_{ii} / \\sigma_i^2$ from the block solver's
    linearisation `(r, J_g, J_l)` (`blocks.linearise`; the rows of frame $f$ end with
    its six prior residuals $\\delta_{f,i}/\\sigma_i$)."""
    _, Jg, Jl = lin
    ll = block_covariance(Jg, Jl).ll
    return jnp.diagonal(ll, axis1=-2, axis2=-1) / sigma**2


def robot_noise_update(
    delta: Float[Array, "frames 6"],
    lin,
    sigma: Float[Array, "6"],
    frames: Bool[Array, " frames"],
    robust: Bool[Array, ""],
) -> tuple[Float[Array, "6"], Float[Array, "2"]]:
    """One variance-component update of the robot noise (see the module docstring).

    **Arguments:** `delta` the corrections at the optimum for `sigma`; `lin` the
    block linearisation there; `frames` the frames a kept view saw; `robust`: the
    median form (robust stage) instead of the mean (REML).

    **Returns:** `(sigma, dof)`: the updated `(translation m x3, rotation rad x3)`
    and the redundancies $(r_t, r_r)$ the update rests on.
    """
    r = jnp.clip(1.0 - robot_leverage(lin, sigma), 0.0, 1.0) * frames[:, None]
    s2 = jnp.where(frames[:, None], delta**2, 0.0)
    r2 = jnp.stack([r[:, :3].sum(-1), r[:, 3:].sum(-1)], -1)  # (frames, 2)
    q2 = jnp.stack([s2[:, :3].sum(-1), s2[:, 3:].sum(-1)], -1)
    dof = r2.sum(0)
    mean = q2.sum(0) / jnp.maximum(dof, 1e-12)
    # Robust: the median of each frame's ratio, over the median of chi2_k / k (Wilson-Hilferty).
    usable = frames[:, None] & (r2 > 0.1)
    k = jnp.maximum(r2, 0.1)
    ratio = jnp.where(usable, q2 / (k * jnp.maximum((1.0 - 2.0 / (9.0 * k)) ** 3, 0.2)), jnp.nan)
    median = jnp.nanmedian(ratio, axis=0)
    var = jnp.where(robust, median, mean)
    old = jnp.stack([sigma[0], sigma[3]]) ** 2
    # Nothing to go on (no redundancy, no usable frame): keep the old value.
    var = jnp.where((dof > 1e-6) & jnp.isfinite(var), var, old)
    scale = jnp.clip(jnp.sqrt(var), MIN_ROBOT_SIGMA, MAX_ROBOT_SIGMA)
    return robot_sigma6(scale[0], scale[1]), dof


def solve_estimating_noise(solve, params, sigma, frames, robust, estimate):
    """Solve, update the robot noise, re-solve from there, until it settles (a `lax.while_loop`).

    **Arguments:** `solve(params, sigma) -> (params, result, num_steps, lin)` one
    Levenberg-Marquardt stage at that robot noise (block linearisation); `params`,
    `sigma` the start; `frames` `(frames,)` the frames a kept view saw; `robust` the
    median update; `estimate` (traced): False runs `solve` once at `sigma`.

    **Returns:** `(params, result, num_steps, lin, sigma, dof)`: the last solve, the
    noise it ran at (the fixed point when estimating) and its redundancies.
    """
    value, code, steps, lin = solve(params, sigma)
    new, dof = robot_noise_update(value.robot, lin, sigma, frames, robust)

    def moving(state):
        _, _, _, _, old, new, _, k = state
        change = jnp.max(jnp.abs(new**2 / old**2 - 1.0))
        return estimate & (k < ROBOT_SIGMA_MAX_UPDATES) & (change > ROBOT_SIGMA_RTOL)

    def step(state):
        value, _, steps, _, _, sigma, _, k = state
        value, code, more, lin = solve(value, sigma)
        new, dof = robot_noise_update(value.robot, lin, sigma, frames, robust)
        return value, code, steps + more, lin, sigma, new, dof, k + 1

    state = (value, code, steps, lin, sigma, new, dof, jnp.asarray(0))
    value, code, steps, lin, sigma, _, dof, _ = jax.lax.while_loop(moving, step, state)
    return value, code, steps, lin, sigma, dof
