"""Stop-and-shoot calibration from measured points: the residual model of point samples.

A measuring device (laser tracker, motion capture, a camera's PnP, the
controller) reports a point on the flange, in its own frame, at poses where
every joint stands still at known commanded positions $q_i$. The model of
sample $i$ is

$$ y_i = T_{dev,base}\\, T_{base,flange}(q_i + \\delta q_i;\\ \\text{model})\\, p, \\qquad
   T_{dev,base} = T_0 \\exp(\\xi_{cam}),\\ p = T_{flange,point,0} \\exp(\\xi_{tool})\\, \\mathbf{0}, $$

with the model corrected by `jaxcal._correction` (a twist on every joint
origin, zero offsets), so the unknowns are exactly the axis fit's vector
(`ParameterLayout.axis_size`: `cam`, `origin`, `zero`, `tool`), and the
tables, covariance and outputs of the two-stage fit apply unchanged.

**Non-geometric terms.** $\\delta q_{i,j} = \\sum_k e_{j,k}\\, b_{j,k}(q_i, a_i)$: joint
angle errors linear in a few coefficients per joint over a basis of the
pose and of how it was approached: `jaxcal._terms`, the one implementation
every observation shares (`compliance`, `backlash`, `harmonic1`, `harmonic2`;
the samples' order is the motion the approach rule follows).

Their coefficients follow the axis-fit vector in the flattened parameters
(`PointLayout`); the identifiability search visits them last, so a term is
freed only where the geometry cannot already explain it.

**Robust fit.** One wrong sample (a joint cell off by degrees, a reflector
bumped) would pull every parameter. Each sample is judged by its deletion residual,
the residual it would have had the fit not used it (from the sample's block
$G_i = J_i C J_i^T$ of the hat matrix, $k = 3$ or 6 rows; `sample_radii`), in robust
sigmas of a scale estimated from the data (`jaxcal._robust`); `fit_points_robust`
continues a least-squares fit with the arc fits' iteratively reweighted rounds
(Cauchy), then one least-squares solve on the inliers gives the estimate and its
covariance.

Everything here is pure and jittable; `fit_points` is one compiled program
for any mask of free parameters and any mask of samples, so K-fold
cross-validation is a vmap over sample masks (`cross_validate`).
"""

from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from . import _lsq
from ._axisfit import AxisFitParams
from ._correction import ParameterLayout
from ._geometry import cross_lanes, se3_exp, skew, so3_log
from ._geometry import matmul_lanes as mml
from ._geometry import matvec_lanes as mvl
from ._kinematics import KinematicModel
from ._options import RobustOptions, robust_terms
from ._robust import deletion_residuals, irls_rounds_evaluated, round_plan, sample_weights
from ._schur import NormalEquations, normal_least_squares
from ._terms import GRAVITY as GRAVITY  # re-exported: the terms live in `jaxcal._terms`
from ._terms import TERMS as TERMS
from ._terms import check_terms, coefficients
from ._terms import gravity_torques as gravity_torques
from ._terms import names as term_names
from ._terms import per_joint as terms_per_joint
from ._terms import term_basis as term_basis

#: The point fit's Levenberg-Marquardt settings: it stops at steps below a thousandth of a
#: standard deviation (whitened residuals), far inside the answer's own uncertainty.
LM_OPTIONS = _lsq.LMOptions(rtol=1e-8, atol=1e-3)
#: ... or once its next step would move the estimate by less than a hundredth of a
#: standard deviation (`normal_least_squares`' `settled`): one evaluation fewer.
SETTLED = 1e-2


@dataclass(frozen=True)
class PointLayout:
    """The point fit's flattened vector: the axis fit's (`ParameterLayout`)
    followed by the coefficients of the non-geometric `terms`, joint-major
    within each family. `orientation`: the samples also measure the point
    frame's orientation (a 6-DoF probe, a motion-capture body, a PnP pose)."""

    base: ParameterLayout
    terms: tuple[str, ...] = ()
    orientation: bool = False

    def __post_init__(self):
        check_terms(self.terms)

    @property
    def num_terms(self) -> int:
        """Coefficients per joint."""
        return terms_per_joint(self.terms)

    @property
    def size(self) -> int:
        return self.base.axis_size + len(self.base.joints) * self.num_terms

    def term_names(self) -> list[str]:
        return term_names(self.terms, self.base.joints)

    def names(self) -> list[str]:
        return self.base.names(refine=False) + self.term_names()

    def split(self, x: Float[Array, " n"]) -> tuple[AxisFitParams, Float[Array, "joints k"]]:
        """The axis-fit parameters and the per-joint term coefficients `(joints, num_terms)`."""
        k = self.base.axis_size
        cam, corr, _ = self.base.split(x[:k])
        e = coefficients(self.terms, x[k:], len(self.base.joints))
        return AxisFitParams(cam=cam, correction=corr), e

    def priority(self) -> np.ndarray:
        """Column order of the identifiability search: the axis fit's, then the terms."""
        return np.concatenate([self.base.priority(refine=False), np.arange(self.base.axis_size, self.size)])


class PointData(eqx.Module):
    """Point samples of one capture (padded: `mask` marks the real, used ones).

    - `q`: commanded joint positions `(samples, joints)` (rad, or m).
    - `y`: measured points in the device frame `(samples, 3)` (m).
    - `sigma`: per-axis 1-sigma of each point `(samples,)` (m).
    - `mask`: samples in the fit.
    - `weight`: each sample's weight in the fit (the robust fit's rounds set it; 1 otherwise).
    - `masses`, `coms`: per joint's child link its mass (kg) and centre of mass
      in that link's frame (m); zeros when no compliance term is fitted.
    - `R`, `sigma_rad`: with orientations, the measured rotation of the point's
      frame in the device frame `(samples, 3, 3)` and its 1-sigma per axis (rad);
      identities and ones otherwise.
    - `approach`: the approach rule's flank of every joint at every sample
      (`jaxcal._terms.approach` along the samples' order), `(samples, joints)`;
      None (zeros) without a `backlash` term.
    """

    q: Float[Array, "samples joints"]
    y: Float[Array, "samples 3"]
    sigma: Float[Array, " samples"]
    mask: Bool[Array, " samples"]
    weight: Float[Array, " samples"]
    masses: Float[Array, " joints"]
    coms: Float[Array, "joints 3"]
    R: Float[Array, "samples 3 3"]
    sigma_rad: Float[Array, " samples"]
    approach: Float[Array, "samples joints"] | None = None


def _basis(problem: "PointProblem") -> Float[Array, "samples joints k"]:
    """The problem's term basis (`jaxcal._terms.term_basis`) at its samples."""
    d = problem.data
    return term_basis(problem.layout.terms, problem.nominal, d.q, d.masses, d.coms, d.approach)


class PointPrior(eqx.Module):
    """A Gaussian prior on the vector `x` (`PointLayout` order; a fleet's, `jaxcal.fleet`): mean
    `mean`, precision `root.T @ root` (zero where it says nothing). Its rows `root @ (x - mean)`
    join the whitened residuals: the fit is the posterior's mode, its covariance the posterior's."""

    root: Float[Array, "q n"]
    mean: Float[Array, " n"]


class PointProblem(eqx.Module):
    """A point fit: the nominal model, the references the corrections are relative to, the data, a prior."""

    nominal: KinematicModel
    T_dev_base0: Float[Array, "4 4"]
    T_flange_point0: Float[Array, "4 4"]
    data: PointData
    layout: PointLayout = eqx.field(static=True)
    prior: PointPrior | None = None


def _rotations(
    axis: Float[Array, "joints 3"], theta: Float[Array, "joints s"]
) -> Float[Array, "joints 3 3 s"]:
    """Rodrigues' rotations about each joint's unit axis by its angles, the samples last."""
    K = jax.vmap(skew)(axis)
    M = jnp.stack([jnp.broadcast_to(jnp.eye(3), K.shape), K, K @ K], axis=-1)  # (joints, 3, 3, 3)
    # One contraction over (1, sin, 1 - cos): written as broadcast multiply-adds, XLA's
    # CPU loop would evaluate the sine and cosine once per matrix entry.
    basis = jnp.stack([jnp.ones_like(theta), jnp.sin(theta), 1.0 - jnp.cos(theta)], axis=1)
    return jnp.einsum("jabk,jks->jabs", M, basis)


class _Chain(eqx.Module):
    """The forward pass of every sample at once, the samples last (`matmul_lanes`'
    layout): the fitted points `y` `(3, s)` and what their Jacobian needs, in the
    device frame: per joint $j$ the rotation of its corrected origin frame `RE`
    `(joints, 3, 3, s)`, that frame's origin `W_t` and the joint's axis `omega`
    `(joints, 3, s)`; the device pose `T_db`; the point frame's rotation `R_p` `(3, 3, s)`."""

    y: Float[Array, "3 s"]
    RE: Float[Array, "joints 3 3 s"]
    W_t: Float[Array, "joints 3 s"]
    omega: Float[Array, "joints 3 s"]
    T_db: Float[Array, "4 4"]
    R_p: Float[Array, "3 3 s"]


def _chain(x, problem: "PointProblem") -> _Chain:
    """The forward pass of every sample (see `_Chain`)."""
    layout, d = problem.layout, problem.data
    params, e = layout.split(x)
    corr = params.correction
    nominal = problem.nominal
    # Each joint's nominal origin times its correction, one constant transform per joint.
    OE = nominal.T_parent_joint @ jax.vmap(se3_exp)(corr.origin)
    T_db = problem.T_dev_base0 @ se3_exp(params.cam)
    mount = problem.T_flange_point0 @ se3_exp(corr.tool[0])
    theta = d.q + nominal.zero_offset + corr.zero_offset
    if layout.terms:
        theta = theta + jnp.sum(e[None] * _basis(problem), axis=2)
    rot = _rotations(nominal.axis, theta.T)
    S = theta.shape[0]
    R = jnp.broadcast_to(T_db[:3, :3, None], (3, 3, S))
    t = jnp.broadcast_to(T_db[:3, 3, None], (3, S))
    RE, W_t = [], []
    for j in range(nominal.num_joints):
        t = t + mvl(R, OE[j, :3, 3, None])
        R = mml(R, OE[j, :3, :3, None])
        RE.append(R)
        W_t.append(t)
        R = mml(R, rot[j])
    RE = jnp.stack(RE)
    F = nominal.T_last_flange @ mount
    return _Chain(
        y=t + mvl(R, F[:3, 3, None]),
        RE=RE,
        W_t=jnp.stack(W_t),
        omega=jnp.sum(RE * nominal.axis[:, None, :, None], axis=2),  # a joint's rotation keeps its axis
        T_db=T_db,
        R_p=mml(R, F[:3, :3, None]),
    )


def predict(x: Float[Array, " n"], problem: "PointProblem") -> Float[Array, "samples 3"]:
    """The model's points in the device frame for every sample (m)."""
    return _chain(x, problem).y.T


def predict_rotation(x: Float[Array, " n"], problem: "PointProblem") -> Float[Array, "samples 3 3"]:
    """The model's rotation of the point's frame in the device frame for every sample."""
    return jnp.moveaxis(_chain(x, problem).R_p, -1, 0)


def rotation_errors(x: Float[Array, " n"], problem: "PointProblem") -> Float[Array, " samples"]:
    """Per sample the angle between the measured orientation and the model's (rad)."""
    e = jax.vmap(so3_log)(jnp.einsum("sba,sbc->sac", problem.data.R, predict_rotation(x, problem)))
    return jnp.linalg.norm(e, axis=1)


def rotation_jacobian(x: Float[Array, " n"], problem: "PointProblem") -> Float[Array, "samples 3 n"]:
    """$\\partial \\log(\\hat R_i(x)^T \\hat R_i(x + \\delta)) / \\partial \\delta$: how the parameters turn
    each sample's predicted orientation, in the point's frame (rad), by forward-mode autodiff."""
    R0 = jax.lax.stop_gradient(predict_rotation(x, problem))

    def turn(v):
        return jax.vmap(so3_log)(jnp.einsum("sba,sbc->sac", R0, predict_rotation(v, problem)))

    return jax.jacfwd(turn)(x)


def _rotation_residuals(x, problem) -> Float[Array, " m"]:
    """Whitened rotation residuals $\\log(R_i^T \\hat R_i) / \\sigma_{rad,i}$ times the samples'
    $\\sqrt{w_i}$, zero for masked samples."""
    d = problem.data
    e = jax.vmap(so3_log)(jnp.einsum("sba,sbc->sac", d.R, predict_rotation(x, problem)))
    w = jnp.where(d.mask, jnp.sqrt(d.weight) / d.sigma_rad, 0.0)
    return (e * w[:, None]).reshape(-1)


def _twist_jacobian(xi: Float[Array, "6"]) -> Float[Array, "6 6"]:
    """$D(\\xi)$: the body twist $(\\rho, \\omega)$ that a change of the twist
    coordinates `xi` applies, $\\exp(\\xi + \\delta) \\approx \\exp(\\xi)\\exp(D\\delta)$
    (the identity at $\\xi = 0$)."""
    E = se3_exp(xi)
    G = jnp.einsum("ba,bck->ack", E[:3, :3], jax.jacfwd(se3_exp)(xi)[:3])  # R^T dE: (3, 4, 6)
    return jnp.concatenate([G[:, 3, :], jnp.stack([G[2, 1], G[0, 2], G[1, 0]])])


def _twist_columns(R: Float[Array, "... 3 3 s"], v: Float[Array, "... 3 s"]) -> Float[Array, "... 6 3 s"]:
    """The motion of a point at `v` from a frame's origin, per unit body twist
    $(\\rho, \\omega)$ of the frame (rotation `R`): $R\\rho + (R\\omega) \\times v$; one
    column per twist coordinate, `(..., 6, 3, s)`."""
    Rc = jnp.swapaxes(R, -3, -2)  # (..., column, row, s)
    v = v[..., None, :, :]
    cross = jnp.stack(
        [
            Rc[..., 1, :] * v[..., 2, :] - Rc[..., 2, :] * v[..., 1, :],
            Rc[..., 2, :] * v[..., 0, :] - Rc[..., 0, :] * v[..., 2, :],
            Rc[..., 0, :] * v[..., 1, :] - Rc[..., 1, :] * v[..., 0, :],
        ],
        axis=-2,
    )
    return jnp.concatenate([Rc, cross], axis=-3)


def _jacobian_factors(x, problem: "PointProblem", c: _Chain):
    """$J = N C$: `N` `(n, 3, s)`, the points' motion per unit body twist of each
    frame (and per radian of each joint-angle column), samples last, and `C`
    `(n, n)`, the block-diagonal map from the twist coordinates to body twists
    (`_twist_jacobian`; the identity elsewhere). `N`'s normal matrix then costs one
    product, and $J^TJ = C^T N N^T C$."""
    layout = problem.layout
    params, _ = layout.split(x)
    corr = params.correction
    n = problem.nominal.num_joints
    S = c.y.shape[1]
    v = c.y[None] - c.W_t  # (joints, 3, s): from each corrected origin to the point
    J_angle = cross_lanes(c.omega.swapaxes(0, 1), v.swapaxes(0, 1)).swapaxes(0, 1)  # (joints, 3, s)
    T_db = jnp.broadcast_to(c.T_db[:3, :3, None], (3, 3, S))
    blocks = [
        _twist_columns(T_db, c.y - c.T_db[:3, 3, None]),
        _twist_columns(c.RE, v).reshape(6 * n, 3, S),
        J_angle,
        jnp.concatenate([jnp.swapaxes(c.R_p, 0, 1), jnp.zeros((3, 3, S), c.y.dtype)]),
    ]
    if layout.terms:
        b = jnp.moveaxis(_basis(problem), 0, -1)
        start = 0
        for t in layout.terms:
            m = TERMS[t]
            # (joints, k, 3, s), joint-major within the family as `PointLayout`
            blocks.append((J_angle[:, None] * b[:, start : start + m, None, :]).reshape(n * m, 3, S))
            start += m
    twists = [_twist_jacobian(params.cam), *jax.vmap(_twist_jacobian)(corr.origin)]
    eye = [jnp.eye(k, dtype=x.dtype) for k in (n, layout.size - 12 - 7 * n) if k]
    C = jax.scipy.linalg.block_diag(*twists, eye[0], _twist_jacobian(corr.tool[0]), *eye[1:])
    return jnp.concatenate(blocks, axis=0), C


def point_jacobian(x: Float[Array, " n"], problem: "PointProblem") -> Float[Array, "samples 3 n"]:
    """$\\partial \\hat y_i / \\partial x$ in closed form (tested against autodiff): a
    frame's twist moves the point by $R\\rho + (R\\omega) \\times v$ (`_twist_columns`: the
    device frame, each corrected joint origin, the point's mount), a joint angle by
    $\\omega_j \\times (\\hat y - o_j)$ (zero offsets, and every joint-angle term times its basis)."""
    N, C = _jacobian_factors(x, problem, _chain(x, problem))
    return jnp.einsum("kas,ki->sai", N, C)


def _weights(problem) -> Float[Array, " samples"]:
    """$\\sqrt{w_i} / \\sigma_i$: each sample's whitening times its weight's root (0 when masked)."""
    d = problem.data
    return jnp.where(d.mask, jnp.sqrt(d.weight) / d.sigma, 0.0)


def _residuals_primal(x, problem):
    r = ((predict(x, problem) - problem.data.y) * _weights(problem)[:, None]).reshape(-1)
    if problem.layout.orientation:
        r = jnp.concatenate([r, _rotation_residuals(x, problem)])
    return r


def _prior_rows(x, problem, keep) -> tuple[Float[Array, " q"], Float[Array, "q n"]]:
    """The prior's rows at `x` over the columns `keep` and their Jacobian (empty without a prior)."""
    if problem.prior is None:
        return jnp.zeros(0, x.dtype), jnp.zeros((0, x.shape[0]), x.dtype)
    U = problem.prior.root * keep[None, :]
    return U @ (x - problem.prior.mean), U


def _with_prior(x, problem, keep, r, H, e) -> tuple[Array, Array, Array]:
    """The residuals `r`, normal matrix `H` and gradient `e` with the prior's rows added."""
    rp, U = _prior_rows(x, problem, keep)
    return jnp.concatenate([r, rp]), H + U.T @ U, e + U.T @ rp


def _normal(x, problem, keep) -> tuple[Array, NormalEquations]:
    """The whitened residuals (positions `(3, s)`-ordered, then the orientations', then the
    prior's rows) and their normal equations over the columns `keep` (the others zero): the
    positions' from `_jacobian_factors`, the orientations' (when measured) by
    forward-mode autodiff."""
    w = _weights(problem)
    c = _chain(x, problem)
    r = ((c.y - problem.data.y.T) * w).reshape(-1)
    N, C = _jacobian_factors(x, problem, c)
    N = (N * w).reshape(x.shape[0], -1)
    C = C * keep[None, :]
    H, e = C.T @ (N @ N.T) @ C, C.T @ (N @ r)
    if problem.layout.orientation:
        rr = _rotation_residuals(x, problem)
        Jr = jax.jacfwd(_rotation_residuals)(x, problem) * keep[None, :]
        r, H, e = jnp.concatenate([r, rr]), H + Jr.T @ Jr, e + Jr.T @ rr
    r, H, e = _with_prior(x, problem, keep, r, H, e)
    return r, NormalEquations(H=H, e=e)


def _residuals_terms(x, problem):
    """The whitened residuals and their Jacobian in `_residuals_primal`'s order."""
    r = _residuals_primal(x, problem)
    J = (point_jacobian(x, problem) * _weights(problem)[:, None, None]).reshape(-1, x.shape[0])
    if problem.layout.orientation:
        J = jnp.concatenate([J, jax.jacfwd(_rotation_residuals)(x, problem)])
    return r, J


def _residuals_autodiff(x, problem):
    d = problem.data
    r = (predict(x, problem) - d.y) * (jnp.sqrt(d.weight) / d.sigma)[:, None]
    r = jnp.where(d.mask[:, None], r, 0.0).reshape(-1)
    if problem.layout.orientation:
        r = jnp.concatenate([r, _rotation_residuals(x, problem)])
    return r


#: Whitened residuals $(\\hat y_i - y_i) / \\sigma_i$, zero for masked samples, flattened,
#: with the closed-form Jacobian (`point_jacobian`).
point_residuals = _lsq.closed_form_jvp(_residuals_primal, _residuals_terms, _residuals_autodiff)


def _sample_blocks(x, problem, keep) -> tuple[Float[Array, "k samples"], Float[Array, "n k samples"]]:
    """Each sample's whitened residual $r_i$ and Jacobian block $J_i$ over the columns `keep`
    (the others zero), without the samples' weights, the samples last (`matmul_lanes`' layout;
    `k` = 3, or 6 with orientations): what its deletion residual needs
    (`jaxcal._robust.deletion_residuals`)."""
    d = problem.data
    unweighted = eqx.tree_at(lambda q: q.data.weight, problem, jnp.ones_like(d.weight))
    w = _weights(unweighted)
    c = _chain(x, unweighted)
    N, C = _jacobian_factors(x, unweighted, c)
    n, _, S = N.shape
    r = (c.y - d.y.T) * w
    J = ((C * keep[None, :]).T @ N.reshape(n, 3 * S)).reshape(n, 3, S) * w
    if problem.layout.orientation:
        rr = _rotation_residuals(x, unweighted).reshape(S, 3).T
        Jr = jax.jacfwd(_rotation_residuals)(x, unweighted).reshape(S, 3, n).T * keep[:, None, None]
        r, J = jnp.concatenate([r, rr]), jnp.concatenate([J, Jr], axis=1)
    return r, J


class PointFitResult(eqx.Module):
    """A point fit's answer.

    - `x`, `std`, `cov`: the flattened parameters (`PointLayout` order), their
      1-sigma and covariance (scaled by the residual variance when `scale`).
    - `free`: estimated parameters; the others are held at nominal.
    - `independence`: each column's distance from the span kept before it.
    - `std_alone`: each parameter's 1-sigma were it the only one free (the noise
      model's, unscaled, at the start; NaN for a given mask of free parameters): a
      parameter whose `std_alone` exceeds its plausible magnitude is one the data
      cannot see (`fit_points`' `scale`).
    - `sigma2`: the residual variance factor $\\hat\\sigma^2$ (1 when the noise
      model is exact).
    - `rms_m`: RMS distance between measured and fitted points of the fitted
      samples (the inliers of a robust fit) (m).
    - `weights`: each sample's weight in the last solve: 1 for an inlier, 0 for a
      sample the robust fit rejected or the mask leaves out.
    - `radius`: a robust fit's per-sample deletion residual at the solution, as the
      2-D radius with the same tail probability, in robust sigmas
      (`jaxcal._robust.sample_weights`; 0 where masked, NaN without a robust loss);
      `robust_scale`: the noise scale those sigmas are of (whitened units; NaN without).
    - `result`, `num_steps`: optimistix's (every solve's steps summed).
    """

    x: Float[Array, " n"]
    std: Float[Array, " n"]
    cov: Float[Array, "n n"]
    free: Bool[Array, " n"]
    independence: Float[Array, " n"]
    std_alone: Float[Array, " n"]
    sigma2: Float[Array, ""]
    rms_m: Float[Array, ""]
    weights: Float[Array, " samples"]
    radius: Float[Array, " samples"]
    robust_scale: Float[Array, ""]
    result: optx.RESULTS
    num_steps: Int[Array, ""]


def fit_points(
    problem: PointProblem,
    candidates: Bool[Array, " n"],
    *,
    tol: float,
    free: Bool[Array, " n"] | None = None,
    options: _lsq.LMOptions | None = None,
    scale: Float[Array, " n"] | None = None,
) -> PointFitResult:
    """Solve the point fit by least squares; pure, jittable and vmappable (over
    `problem.data.mask` for folds). `fit_points_robust` continues from its answer.

    **Arguments:**
    - `problem`: the `PointProblem` (its samples weighted by `data.weight`).
    - `candidates`: the parameters that may be freed (e.g. the fixed frame held
      when it is the base; the point mount's rotation never shows in a point).
    - `tol`: independence threshold of the identifiability search (each
      column's distance from the span of those kept before it, columns
      normalised; see `_lsq.independent_columns`).
    - `free`: a given mask instead of the search.
    - `options`: the Levenberg-Marquardt settings (default `LM_OPTIONS`).
    - `scale`: each parameter's plausible magnitude (m, rad; `inf`: any): the search
      does not free a parameter the data cannot see, one that alone would be known
      no better than that (`std_alone` above it: the zero offset of a joint whose
      axis runs through the measured point). Ignored with `free`.

    **Returns:** a `PointFitResult`; the covariance is
    $\\hat\\sigma^2 (J^TWJ)^{+}$ over the free columns, or with a prior (`problem.prior`) the
    posterior's, and the search frees a parameter the prior does not cover only where the
    data alone would.
    """
    layout = problem.layout
    options = LM_OPTIONS if options is None else options
    x0 = jnp.zeros(layout.size)
    first = None
    if free is None:
        r0, ne0 = _normal(x0, problem, jnp.ones(layout.size, x0.dtype))
        h = jnp.diag(ne0.H)
        std_alone = jnp.where(h > 0, 1.0 / jnp.sqrt(jnp.where(h > 0, h, 1.0)), jnp.inf)
        cand = jnp.asarray(candidates, bool)
        if scale is not None:
            cand = cand & (std_alone <= jnp.asarray(scale))
        if problem.prior is not None:  # a parameter the prior does not cover: freed where the data free it
            _, U = _prior_rows(x0, problem, jnp.ones(layout.size, x0.dtype))
            Hd = ne0.H - U.T @ U
            seen, _ = _lsq.independent_columns_normal(Hd, layout.priority(), tol=tol, candidates=cand)
            cand = cand & (seen | jnp.any(U != 0, axis=0))
        keep, indep = _lsq.independent_columns_normal(ne0.H, layout.priority(), tol=tol, candidates=cand)
    else:
        keep, indep = jnp.asarray(free, bool), jnp.full(layout.size, jnp.nan)
        std_alone = jnp.full(layout.size, jnp.nan)
    kf = keep.astype(x0.dtype)
    if free is None and problem.prior is None:  # the search's linearisation, over the kept columns
        first = (r0, NormalEquations(H=ne0.H * kf[:, None] * kf[None, :], e=ne0.e * kf))
    x, sol = _solve(problem, kf, x0, options, first)
    solved = (sol.residuals, sol.normal.H, problem.data.weight)
    return _summary(problem, x, (keep, indep, std_alone), solved, sol.result, sol.num_steps)


def _solve(problem, kf, x, options, first=None):
    """Levenberg-Marquardt from `x` over the columns `kf` (the others held at zero)."""

    def normal(x, p):
        return _normal(x * kf, p, kf)

    o = options
    sol = normal_least_squares(
        normal, x, problem, rtol=o.rtol, atol=o.atol, max_steps=o.max_steps, first=first, settled=SETTLED
    )
    return sol.x * kf, sol


def _summary(problem, x, search, solved, result, steps) -> PointFitResult:
    """A `PointFitResult` from the solution `x`, the search's `(free, independence, std_alone)` and
    the solve's weighted residuals, normal matrix and sample weights `solved`: the covariance
    scaled by the residual variance of the samples fitted (no robust radii: NaN)."""
    keep, indep, std_alone = search
    r, H, w = solved
    inlier = problem.data.mask & (w > 0)
    k = 6 if problem.layout.orientation else 3
    if problem.prior is None:
        sigma2 = _lsq.residual_variance(r, k * jnp.sum(inlier), jnp.sum(keep))
        cov = _lsq.covariance_normal(H, keep, sigma2)
    else:
        # sigma^2 from the data's rows over what the data determine; the posterior (H_d / sigma^2 + P)^-1.
        _, U = _prior_rows(jnp.zeros_like(H[0]), problem, keep.astype(H.dtype))
        P = U.T @ U
        Hd = H - P
        seen = jnp.trace(_lsq.covariance_normal(H, keep) @ Hd)
        sigma2 = _lsq.residual_variance(r[: r.shape[0] - U.shape[0]], k * jnp.sum(inlier), seen)
        cov = _lsq.covariance_normal(Hd + sigma2 * P, keep, sigma2)
    S = w.shape[0]  # the positions lead `r`, `(3, samples)`-ordered, weighted by the root of `w`
    unweighted = problem.data.sigma / jnp.sqrt(jnp.where(inlier, w, 1.0))
    dist2 = jnp.sum((r[: 3 * S].reshape(3, S) * unweighted) ** 2, axis=0)
    rms = jnp.sqrt(jnp.sum(jnp.where(inlier, dist2, 0.0)) / jnp.maximum(jnp.sum(inlier), 1))
    return PointFitResult(
        x=x,
        std=jnp.sqrt(jnp.maximum(jnp.diag(cov), 0.0)),
        cov=cov,
        free=keep,
        independence=indep,
        std_alone=std_alone,
        sigma2=sigma2,
        rms_m=rms,
        weights=jnp.where(problem.data.mask, w, 0.0),
        radius=jnp.full(w.shape, jnp.nan),
        robust_scale=jnp.asarray(jnp.nan),
        result=result,
        num_steps=steps,
    )


def _deletion(x, keep, problem):
    """Each sample's deletion residual norm and degrees of freedom at `x` under the samples'
    weights (`jaxcal._robust.deletion_residuals`), and the weighted residuals and normal matrix."""
    d = problem.data
    r, J = _sample_blocks(x, problem, keep.astype(x.dtype))  # (k, s), (n, k, s)
    w = jnp.where(d.mask, d.weight, 0.0)
    n, k, S = J.shape
    Jf = J.reshape(n, k * S)
    H = (Jf * jnp.tile(w, k)[None, :]) @ Jf.T
    rw = (r * jnp.sqrt(w)).reshape(-1)  # positions first, as `_normal`'s
    rw, H, _ = _with_prior(x, problem, keep.astype(x.dtype), rw, H, jnp.zeros_like(x))
    # G_i = J_i C J_i^T, the samples last: one product and a sum over the parameters.
    CJ = (_lsq.covariance_normal(H, keep) @ Jf).reshape(n, k, S)
    G = jnp.moveaxis(jnp.sum(CJ[:, :, None, :] * J[:, None, :, :], axis=0), -1, 0)
    dist, nu = deletion_residuals(r.T, G, d.weight, d.mask)
    return dist, nu, rw, H


def sample_radii(
    x: Float[Array, " n"], free: Bool[Array, " n"], problem: PointProblem
) -> tuple[Float[Array, " samples"], Float[Array, ""]]:
    """Each sample's deletion residual at `x` (the fit of the parameters `free` under the
    samples' weights), as the 2-D radius of the same tail probability in robust sigmas,
    and the scale (`jaxcal._robust.sample_weights`): a clean sample's radius exceeds
    3.7 with probability $10^{-3}$, a sample the fit leaves out (weight 0) is judged by
    its prediction error. 0 for masked samples."""
    d, nu, _, _ = _deletion(x, jnp.asarray(free, bool), problem)
    _, z, s = sample_weights(d, nu, problem.data.mask, loss=None, c=1.0, reject=jnp.inf, hard=False)
    return z, s


def fit_points_robust(
    problem: PointProblem,
    fit: PointFitResult,
    robust: RobustOptions,
    options: _lsq.LMOptions | None = None,
) -> PointFitResult:
    """The robust point fit, from the least-squares one `fit` (`fit_points`, whose free
    parameters it keeps): the arc fits' rounds (the module docstring;
    `jaxcal._robust.irls_rounds_evaluated`), each reweighting the samples by their
    deletion residuals, Cauchy or Huber (`robust.loss`, `robust.c`), then one solve on the
    inliers (within `robust.reject` robust sigmas), whose Jacobian gives the covariance.
    Pure and jittable.

    **Returns:** a `PointFitResult` whose `weights` are the inliers' (1) and the rejected
    samples' (0), and `radius` each sample's deletion residual in robust sigmas at the
    solution (`sample_radii`).
    """
    options = LM_OPTIONS if options is None else options
    loss, c, reject, rounds = robust_terms(robust)
    mask, prior = problem.data.mask, problem.data.weight
    keep = jnp.asarray(fit.free, bool)
    kf = keep.astype(fit.x.dtype)
    reject_ = jnp.inf if reject is None else reject

    def weighted(w):
        return eqx.tree_at(lambda q: q.data.weight, problem, prior * w)

    def weights_at(x, w, hard):
        """The next round's weights, and the fit's terms at `x` under the weights `w`."""
        d, nu, rw, H = _deletion(x, keep, weighted(w))
        w_next, z, s = sample_weights(d, nu, mask, loss=loss, c=c, reject=reject_, hard=hard)
        return w_next, (rw, H, z, s)

    def solve(x, w):
        x_new, sol = _solve(weighted(w), kf, x, options)
        return x_new, sol.result, sol.num_steps

    out, (r, H, z, s) = irls_rounds_evaluated(
        solve, weights_at, fit.x, mask.astype(fit.x.dtype), round_plan(loss, rounds, reject)
    )
    result = optx.RESULTS.where(fit.result == optx.RESULTS.successful, out.result, fit.result)
    search = (keep, fit.independence, fit.std_alone)
    res = _summary(
        problem, out.value, search, (r, H, prior * out.weights), result, fit.num_steps + out.num_steps
    )
    return eqx.tree_at(lambda f: (f.radius, f.robust_scale), res, (z, s))


def prediction_std(x, cov, problem: PointProblem) -> Float[Array, " samples"]:
    """Per sample, the RMS over the three axes of the fitted point's standard
    deviation from the parameters' covariance (m): $\\sqrt{\\mathrm{tr}(J_i C J_i^T)/3}$."""
    J = point_jacobian(x, problem)
    var = jnp.einsum("sai,ij,saj->s", J, cov, J)
    return jnp.sqrt(jnp.maximum(var, 0.0) / 3.0)


def fold_masks(num: int, folds: int, seed: int = 0) -> np.ndarray:
    """`(folds, num)` training masks of a shuffled K-fold split (each sample held out once)."""
    if not 2 <= folds <= num:
        raise ValueError(f"cross-validation needs 2 <= folds <= samples ({num}), got {folds}")
    order = np.random.default_rng(seed).permutation(num)
    test = np.zeros((folds, num), bool)
    for k, chunk in enumerate(np.array_split(order, folds)):
        test[k, chunk] = True
    return ~test


def cross_validate(
    problem: PointProblem, candidates, free, train: Bool[Array, "folds samples"], options=None
):
    """K-fold cross-validation: per fold, the fit on the training samples with
    the mask of free parameters `free` (fixed, so folds are comparable), and
    the distances of the held-out samples from their prediction (m) and, with
    orientations, the angles of their orientations from it (rad).

    **Returns:** `(distances (folds, samples), test mask (folds, samples), angles
    (folds, samples))`, the angles zero without orientations.
    """
    base = problem.data.mask

    def one(tr):
        p = eqx.tree_at(lambda q: q.data.mask, problem, base & tr)
        res = fit_points(p, candidates, tol=0.0, free=free, options=options)
        d = jnp.linalg.norm(predict(res.x, problem) - problem.data.y, axis=1)
        a = rotation_errors(res.x, problem) if problem.layout.orientation else jnp.zeros_like(d)
        return d, a

    dist, angle = jax.vmap(one)(jnp.asarray(train))
    return dist, base[None, :] & ~jnp.asarray(train), angle
