"""Maximum-likelihood refinement: reprojection adjustment of every detected corner.

Design step 6. The two-stage method (arc fits, then the axis fit) reduces
each frame to a marker pose and each sweep to a line; this stage goes back
to the pixels. Corner $k$ of the target seen in view $v$ (one target in one
frame) is predicted at

$$\\hat u_{vk} = \\pi_{K,d}\\big(T_{cam,base}\\;T_{base,flange}(q_v)\\;
T_{flange,target}\\;X_k\\big),\\qquad
q_v = r \\odot q_{log}\\big((t_{cam,v} - \\delta)/(1+\\epsilon)\\big),$$

with $\\pi_{K,d}$ the pinhole projection with OpenCV's distortion model
$(k_1, k_2, p_1, p_2, k_3)$, $T_{base,flange}$ the forward kinematics of the
corrected model, $q_{log}$ the encoder log (commanded positions, motor angle
over the nominal ratio) interpolated at controller time, $r$ the rate
(nominal over true reduction ratio) and $\\delta$ the clock offset. The
residual is $\\hat u_{vk} - u_{vk}$ (px) for every corner of every view:
padded arrays with a mask, vmapped over views. Under Gaussian pixel noise the
least-squares solution is the maximum-likelihood estimate.

Unknowns (`RefineParams`): the axis fit's `KinematicCorrection` (joint
origin twists, zero offsets, marker mount twists), a twist on
$T_{cam,base}$, the rates, the clock offset and, optionally, increments of
the intrinsics. Parameters the data cannot see are held at their start
values (a fixed mask, see `identifiable_mask`); the solver works on the free
ones only, scaled by the start Jacobian's column norms (Jacobi scaling, so
Levenberg-Marquardt's damping treats metres, radians, milliseconds and
pixels alike).

Robust loss: iteratively reweighted least squares inside the LM residuals
(Cauchy or Huber weights on each corner's residual norm, scale by the
median absolute residual), then one last solve on the inliers (corners
within `reject` robust standard deviations), whose Jacobian gives honest
standard deviations: $\\Sigma = \\hat\\sigma^2 (J^T J)^{-1}$ with
$\\hat\\sigma^2$ the inlier residual variance.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, Bool, Float, Int

from . import _lsq
from ._correction import INTRINSIC_NAMES as INTRINSIC_NAMES  # re-exported
from ._correction import KinematicCorrection, ParameterLayout, apply_correction, zero_correction
from ._device import result_is
from ._geometry import se3_exp
from ._kinematics import KinematicModel
from ._lsq import LMOptions
from ._options import RobustOptions, robust_terms
from ._reprojection import (  # re-exported: the model the refinement solves
    CornerData as CornerData,
)
from ._reprojection import OtherCameras as OtherCameras
from ._reprojection import RefineParams as RefineParams
from ._reprojection import RefineProblem as RefineProblem
from ._reprojection import camera_matrix as camera_matrix
from ._reprojection import camera_poses as camera_poses
from ._reprojection import grid_points as grid_points
from ._reprojection import joint_positions as joint_positions
from ._reprojection import line_delays as line_delays
from ._reprojection import make_corner_data as make_corner_data
from ._reprojection import num_other_cameras
from ._reprojection import project as project
from ._reprojection import projected_corners as projected_corners
from ._reprojection import reprojection_residuals as reprojection_residuals
from ._reprojection import rolling as rolling
from ._reprojection import sweep_corner_data as sweep_corner_data
from ._reprojection import target_poses as target_poses
from ._robust import Rounds, check_loss, irls_rounds, loss_weights, robust_scale, round_plan
from ._terms import per_joint as terms_per_joint

_MS = 1e-3
#: Median of the norm of a 2-D standard normal vector (Rayleigh), $\\sqrt{2 \\ln 2}$.
#: The solver's variables are scaled so that every Jacobian column has this
#: norm at the start: optimistix's Levenberg-Marquardt starts with unit
#: damping, so its first steps are near Gauss-Newton ones (the start, the
#: two-stage result, is close) and the trust region shrinks when they fail.
_COLUMN_NORM = 1e4


def initial_params(
    correction: KinematicCorrection,
    *,
    cam: Float[Array, "6"] | None = None,
    rate: Float[Array, " joints"] | None = None,
) -> RefineParams:
    """A `RefineParams` from an axis fit's correction (camera twist, rates given
    or zero / one; clock and intrinsic increments zero)."""
    n = correction.zero_offset.shape[0]
    return RefineParams(
        cam=jnp.zeros(6) if cam is None else jnp.asarray(cam, jnp.float64),
        correction=correction,
        rate=jnp.ones(n) if rate is None else jnp.asarray(rate, jnp.float64),
        clock_ms=jnp.zeros(()),
        intrinsics=jnp.zeros(9),
    )


def zero_params(num_joints: int, num_markers: int) -> RefineParams:
    """The start of a refinement from the nominal model (rates one)."""
    return initial_params(zero_correction(num_joints, num_markers))


def layout(problem: RefineProblem, params: RefineParams) -> ParameterLayout:
    """The `ParameterLayout` of a refinement (names of the further cameras and
    the per-view angles are placeholders: only the sizes matter here)."""
    n_angles = 0 if params.angles is None else params.angles.shape[0]
    n_delays = 0 if params.line_delay_us is None else params.line_delay_us.shape[0]
    return ParameterLayout.of(
        problem.nominal,
        problem.T_flange_marker0.shape[0],
        other_cameras=tuple(f"camera{c + 1}" for c in range(num_other_cameras(problem))),
        angles=tuple(f"view{v}" for v in range(n_angles)),
        eye_in_hand=problem.eye_in_hand,
        line_delays=tuple(f"camera{c}" for c in range(n_delays)),
        terms=problem.terms if params.terms is not None else (),
    )


def refine_parameter_names(
    model: KinematicModel,
    num_markers: int,
    other_cameras: tuple[str, ...] | list[str] = (),
    angles: tuple[str, ...] | list[str] = (),
) -> list[str]:
    """Names of the flattened `RefineParams` (see `jaxcal._correction.ParameterLayout`):
    the axis fit's names, then the rates, the clock offset, the intrinsics,
    the further cameras' poses (`"{camera}.T_cam_base.tx"`, ...) and, without
    encoders, the per-view joint angles (named by the caller, e.g.
    `"frame12.elbow_joint"`)."""
    return ParameterLayout.of(
        model, num_markers, other_cameras=tuple(other_cameras), angles=tuple(angles)
    ).names()


def default_free(
    num_joints: int,
    num_markers: int,
    *,
    rates: bool = True,
    clock: bool = False,
    intrinsics: bool = False,
    other_cameras: int = 0,
    angles: int = 0,
) -> np.ndarray:
    """Candidate mask (`ParameterLayout.candidates`): pose and kinematic
    corrections (every camera's pose and every per-view angle included), and
    the optional groups."""
    lay = ParameterLayout.sized(num_joints, num_markers, other_cameras, angles)
    return lay.candidates(rates=rates, clock=clock, intrinsics=intrinsics)


def identifiable_mask(
    problem: RefineProblem,
    params: RefineParams,
    candidates: Bool[Array, " n"],
    *,
    tol: float = 1e-6,
) -> tuple[Bool[Array, " n"], Float[Array, " n"]]:
    """Which candidate parameters the corners determine, by greedy column selection.

    The reprojection Jacobian's columns are normalised and visited in the
    axis fit's priority order (camera, mounts, zero offsets, origins base to
    tip, then rates, clock, intrinsics); a candidate column is kept when its
    component orthogonal to the kept ones is above `tol` (a rank-revealing,
    column-pivoted Gram-Schmidt with a fixed pivot order). Pure and jittable.

    **Returns:** `(free, independence)` over the flattened `RefineParams`.
    """
    flat, unravel = ravel_pytree(params)
    J = jax.jacfwd(lambda x: reprojection_residuals(unravel(x), problem).reshape(-1))(flat)
    return _lsq.independent_columns(J, layout(problem, params).priority(), tol=tol, candidates=candidates)


class RefineResult(eqx.Module):
    """The refined calibration.

    - `params`: the solution (`RefineParams`); `model`: the calibrated model
      (reduction ratios $\\rho_{nom}/r$, `T_flange_tool` the first mount);
      `T_cam_base` (the first camera), `T_cam_bases` (every camera,
      `(cameras, 4, 4)`), `T_flange_marker`, `K`, `dist`, `offset_s` (s).
    - `std`, `cov`: standard deviations and covariance of the flattened
      parameters (`refine_parameter_names` order; zero where frozen): the
      model's covariance `cov_model`, or along the directions where it is
      larger beyond its sampling spread, the cluster-robust covariance with one
      cluster per view (`jaxcal._lsq.cluster_covariance`, `larger_covariance`),
      which does not take a view's corner errors to be independent (a robot
      pose error or the detector's bias moves a view's corners together).
    - `free`: the parameters estimated (the others held at their start).
    - `singular_values`, `singular_vectors` (rows): SVD of the
      column-normalised inlier Jacobian of the free parameters at the
      solution (a near-zero value is an unidentifiable direction).
    - `sigma_px`: the inlier pixel noise (per coordinate) the covariance is scaled by.
    - `residuals`: reprojected minus detected, px, `(views, corners, 2)`;
      `weights`: the last IRLS weights; `inlier`: corners used by the final solve.
    - `result`, `num_steps`: optimistix's result of the final solve and the
      steps of all rounds; `rounds_ok`: every round's solve succeeded.
    - `line_delay_s`: with rolling shutters, every camera's line delay (s per
      row); `None` without.
    - `cov_model`: the model's covariance $\\hat\\sigma^2 (J^TJ)^+$ (corner errors
      independent), beside `cov`.
    - `jacobian`, `angle_jacobian`: with `refine(..., jacobian=True)`, the unweighted
      residuals' (`residuals` flattened) Jacobian at the solution in the free parameters
      `(rows, free)` and in every joint's angle `(rows, joints)` (a view's joint-angle
      correction, the non-geometric terms' column times their basis); `None` otherwise.
    - `view_scores`: per view the final solve's gradient $J_v^Tr_v$ over the free parameters
      (in `free`'s order), for sandwiches that group views (`jaxcal._lsq.hac_covariance`, with
      `view_information`); `None` with per-view angles.
    """

    params: RefineParams
    model: KinematicModel
    T_cam_base: Float[Array, "4 4"]
    T_cam_bases: Float[Array, "cameras 4 4"]
    T_flange_marker: Float[Array, "markers 4 4"]
    K: Float[Array, "3 3"]
    dist: Float[Array, "5"]
    offset_s: Float[Array, ""]
    std: Float[Array, " n"]
    cov: Float[Array, "n n"]
    free: Bool[Array, " n"]
    singular_values: Float[Array, " f"]
    singular_vectors: Float[Array, "f f"]
    sigma_px: Float[Array, ""]
    residual_rms_px: Float[Array, ""]
    residuals: Float[Array, "views corners 2"]
    weights: Float[Array, "views corners"]
    inlier: Bool[Array, "views corners"]
    result: optx.RESULTS
    num_steps: Int[Array, ""]
    rounds_ok: Bool[Array, ""]
    round_steps: Int[Array, " rounds"]
    line_delay_s: Float[Array, " cameras"] | None = None
    cov_model: Float[Array, "n n"] | None = None
    jacobian: Float[Array, "rows f"] | None = None
    angle_jacobian: Float[Array, "rows joints"] | None = None
    view_scores: Float[Array, "views f"] | None = None


#: `refine`'s solver settings, on the scaled variables: every start Jacobian column has
#: norm `1e4`, so a unit of a solver variable moves the residuals by `1e-4` px.
REFINE_OPTIONS = LMOptions(rtol=1e-7, atol=1e-7, max_steps=50)
#: `refine`'s robust loss: three Cauchy rounds at 3 robust sigmas, then the inliers within 3.7.
REFINE_ROBUST = RobustOptions(loss="cauchy", c=3.0, reject=3.7, rounds=3)


def refine(
    problem: RefineProblem,
    params0: RefineParams,
    free: np.ndarray,
    *,
    options: LMOptions = REFINE_OPTIONS,
    robust: RobustOptions | None = REFINE_ROBUST,
    jacobian: bool = False,
) -> RefineResult:
    """Minimise the reprojection error of every corner; pure, jittable, vmappable.

    Levenberg-Marquardt (optimistix's iteration on the normal equations,
    `jaxcal._lsq.solve_normal`; forward-mode Jacobian over the free
    parameters only) on `reprojection_residuals`, Jacobi-scaled at the start.
    With a `robust` loss, `robust.rounds` IRLS solves (weights from each solution's
    corner residual norms in robust sigmas, constant `robust.c`), then, with
    `robust.reject`, a final solve on the corners within `reject` sigmas (weight 1,
    others 0): the maximum-likelihood estimate on the inliers. All rounds are one
    `lax.scan`, so the solver compiles once.

    **Arguments:**
    - `problem`, `params0`: the fixed inputs and the start (frozen parameters
      stay at their `params0` values).
    - `free`: concrete bool mask over the flattened `RefineParams`
      (`refine_parameter_names`), e.g. from `identifiable_mask`; static, so
      vmap over problems with one mask.
    - `options`: the solver's `LMOptions`, its tolerances on the scaled variables
      (every start Jacobian column has norm `1e4`, i.e. a unit of the solver
      variable moves the residual by `1e-4` px).
    - `robust`: the `RobustOptions` (`None`: plain least squares, one solve). Its
      `c` and `reject` may be traced: `c = reject = inf` with a robust loss is plain
      least squares with the same compiled code.
    - `jacobian`: also return the Jacobians at the solution (`RefineResult.jacobian`,
      `angle_jacobian`): what a linearised refit (cross-validation of the non-geometric
      terms, `jaxcal.stages._terms`) needs.

    **Returns:** a `RefineResult`.
    """
    loss, c, reject, rounds = robust_terms(robust)
    flat0, unravel, free, idx = _checked(problem, params0, free, loss)
    mask = problem.data.mask
    mask_f = mask.astype(flat0.dtype)

    def residual_x(x_free, w):
        return reprojection_residuals(unravel(flat0.at[idx].set(x_free)), problem, w).reshape(-1)

    x0 = flat0[idx]

    def solve(start):
        """The rounds from `x0`, Jacobi-scaled by the start's Jacobian `start = (r0, J0)`."""
        scale = _jacobi_scale(start[1])

        def fn(y, w):
            return residual_x(x0 + scale * y, w)

        # Normal equations + Cholesky (`solve_normal`): the (Jacobi-scaled) Jacobian is
        # tall and well conditioned, and lineax's default QR forms the thin Q, orders of
        # magnitude slower a step for thousands of rows than the Cholesky of J^T J; the lean
        # loop takes optimistix's steps in a program that compiles sooner (docs/performance.md).
        out = _rounds(fn, jnp.zeros_like(x0), mask, loss, rounds, c, reject, options)
        return x0 + scale * out.value, out

    # The unweighted residuals (px, zero on padding) and their Jacobian at the start (for the
    # scaling) and at the solution (the covariance: the final solve's weights scale its rows,
    # exactly what weighting inside the pass computes; and the result's residuals).
    _, (x, out), (raw, J) = _lsq.start_and_solution(
        lambda xx: _lsq.value_and_jacfwd(lambda z: residual_x(z, mask_f), xx), x0, solve
    )
    params = unravel(flat0.at[idx].set(x))
    sw = jnp.repeat(jnp.sqrt(out.weights).reshape(-1), 2)
    covs = _covariances(J * sw[:, None], raw * sw, out.weights, idx, flat0.shape[0], params0.angles is None)
    res = _result(problem, params, free, out, covs, raw.reshape(mask.shape + (2,)))
    if not jacobian:
        return res
    flat = flat0.at[idx].set(x)
    zero = layout(problem, params0).index("zero")

    def shifted(dz):  # every view's joint angles moved by dz: the zero offsets' columns
        return reprojection_residuals(unravel(flat.at[zero].add(dz)), problem, mask_f).reshape(-1)

    J_angle = jax.jacfwd(shifted)(jnp.zeros(zero.size, flat.dtype))
    return eqx.tree_at(
        lambda r: (r.jacobian, r.angle_jacobian), res, (J, J_angle), is_leaf=lambda v: v is None
    )


def _jacobi_scale(J0):
    """The solver's variable scales: each free parameter's step that moves the start
    residuals by `_COLUMN_NORM` (Jacobi scaling of the start Jacobian `J0`)."""
    col = jnp.linalg.norm(J0, axis=0)
    return _COLUMN_NORM / jnp.where(col > 0, col, 1.0)


def _result(problem: RefineProblem, params: RefineParams, free, out: Rounds, covs, raw) -> RefineResult:
    """The `RefineResult` at the solution `params` of the rounds `out`, with the final
    solve's covariances `covs` (`_covariances`) and reprojection residuals `raw` (px, zero
    on padding): the model and mounts the corrections give, the camera, the residuals and
    the inliers' RMS."""
    cov, cov_model, sigma2, sv, Vt, scores = covs
    mask, w = problem.data.mask, out.weights
    used = w > 0
    inl_rms = jnp.sqrt(
        jnp.sum(jnp.where(used[..., None], raw**2, 0.0)) / jnp.maximum(2.0 * jnp.sum(used), 1.0)
    )
    model, mounts = apply_correction(problem.nominal, problem.T_flange_marker0, params.correction)
    model = eqx.tree_at(
        lambda m: (m.reduction_ratio, m.T_flange_tool),
        model,
        (problem.nominal.reduction_ratio / params.rate, mounts[0]),
    )
    K, dist = camera_matrix(params, problem)
    return RefineResult(
        params=params,
        model=model,
        T_cam_base=problem.T_cam_base0 @ se3_exp(params.cam),
        T_cam_bases=camera_poses(params, problem),
        T_flange_marker=mounts,
        K=K,
        dist=dist,
        offset_s=problem.offset0_s + _MS * params.clock_ms,
        std=jnp.sqrt(jnp.maximum(jnp.diag(cov), 0.0)),
        cov=cov,
        free=jnp.asarray(free),
        singular_values=sv,
        singular_vectors=Vt,
        sigma_px=jnp.sqrt(sigma2),
        residual_rms_px=inl_rms,
        residuals=raw,
        weights=w,
        inlier=used & mask,
        result=out.result,
        num_steps=out.num_steps,
        rounds_ok=out.ok,
        round_steps=out.round_steps,
        line_delay_s=line_delays(params, problem) if rolling(problem) else None,
        cov_model=cov_model,
        view_scores=scores,
    )


def _covariances(J, r, w, idx, n, per_view: bool = True):
    """`(cov, cov_model, sigma2, sv, Vt, scores)` of the final solve (see `RefineResult`): the
    model's $\\hat\\sigma^2 (J^TJ)^+$ and the covariance it becomes where the views' sandwich is
    larger than it beyond its own spread; one SVD (see `_linalg`) and one small `eigh` after it.
    With `per_view` (static), each view's gradient."""
    sigma2 = _lsq.residual_variance(r, 2.0 * jnp.sum(w), idx.size)
    bread, sv, Vt = _lsq.covariance(J)
    V = w.shape[0]
    # Per view the gradient J_v^T r_v of its corners: one cluster each (padded views: zero).
    scores = jnp.einsum("vkn,vk->vn", J.reshape(V, -1, idx.size), r.reshape(V, -1))
    robust = _lsq.cluster_covariance(bread, scores, n_obs=2.0 * jnp.sum(w > 0))
    views = jnp.maximum(jnp.sum(jnp.any(scores != 0.0, axis=1)), 2.0)
    cov_f = _lsq.larger_covariance(J, sv, Vt, sigma2, robust, 2.0 * jnp.sqrt(2.0 / views))
    cov = jnp.zeros((n, n)).at[np.ix_(idx, idx)].set(cov_f)
    cov_model = jnp.zeros((n, n)).at[np.ix_(idx, idx)].set(sigma2 * bread)
    return cov, cov_model, sigma2, sv, Vt, scores if per_view else None


def _checked(problem: RefineProblem, params0: RefineParams, free, loss):
    """`refine`'s static checks; `(flat0, unravel, free, free indices)`."""
    check_loss(loss)
    several = problem.other_cameras is not None
    if (params0.angles is not None) != (problem.data.sweep_joint is not None):
        raise ValueError(
            "refine: without encoders both params0.angles (one per view) and data.sweep_joint are needed; "
            "with encoders, neither"
        )
    if problem.target_link is not None and problem.target_link.shape != (problem.T_flange_marker0.shape[0],):
        raise ValueError(
            f"refine: target_link has shape {problem.target_link.shape}, expected one link per target "
            f"({problem.T_flange_marker0.shape[0]})"
        )
    if problem.eye_in_hand and (several or problem.T_flange_marker0.shape[0] != 1):
        raise ValueError("refine: eye-in-hand takes one camera (the one mount) and no further cameras")
    if (params0.line_delay_us is not None) != rolling(problem):
        raise ValueError(
            "refine: a rolling shutter needs data.row, problem.line_delay0_s and params0.line_delay_us "
            "(one per camera); a global shutter none of them"
        )
    if (params0.terms is not None) != (problem.data.term_basis is not None) or (
        params0.terms is not None
        and (
            not problem.terms
            or params0.terms.shape != (problem.nominal.num_joints * terms_per_joint(problem.terms),)
            or problem.data.term_basis.shape[-1] != terms_per_joint(problem.terms)
        )
    ):
        raise ValueError(
            "refine: non-geometric terms need problem.terms, data.term_basis (views, joints, k) and "
            "params0.terms (joints * k); without terms, none of them"
        )
    if several != (params0.other_cams is not None) or (several and problem.data.camera is None):
        raise ValueError(
            "refine: with other_cameras, params0.other_cams (one twist per further camera) and "
            "data.camera (each view's camera) are needed; without, neither"
        )
    flat0, unravel = ravel_pytree(params0)
    try:
        free = np.asarray(free, bool)
    except jax.errors.TracerArrayConversionError:
        raise ValueError("refine: `free` must be a concrete mask (compute it outside jit/vmap)") from None
    if free.shape != flat0.shape:
        raise ValueError(
            f"refine: free mask has shape {free.shape}, expected {flat0.shape} (refine_parameter_names)"
        )
    idx = np.flatnonzero(free)
    if idx.size == 0:
        raise ValueError("refine: no free parameter")
    return flat0, unravel, free, idx


def _rounds(fn, y0, mask, loss, rounds, c, reject, options) -> Rounds:
    """The robust solves, one `lax.scan`: `rounds` IRLS solves (weights from each
    solution's corner residual norms in robust sigmas), then with `reject` a
    final solve on the inliers (`irls_rounds`)."""
    mask_f = mask.astype(y0.dtype)
    robust = loss is not None
    final_hard = robust and reject is not None
    hard_flags = round_plan(loss, rounds, reject)
    nu = jnp.full(mask.shape, 2.0)  # a corner's residual has two coordinates

    def weights_at(y, hard):
        e = jnp.linalg.norm(fn(y, mask_f).reshape(mask.shape + (2,)), axis=-1)
        s = robust_scale(e, nu, mask)
        soft = loss_weights(e / s, loss, c)
        inl = (e / s < (reject if reject is not None else jnp.inf)) if final_hard else jnp.ones_like(mask)
        return jnp.where(hard, inl.astype(e.dtype), soft) * mask_f

    def solve(y, w):
        sol = _lsq.solve_normal(fn, y, w, options)
        return sol.value, sol.result, sol.stats["num_steps"]

    return irls_rounds(solve, weights_at, y0, hard_flags)


def fisher_std(
    problem: RefineProblem, params: RefineParams, free: np.ndarray, sigma_px: float
) -> Float[Array, " n"]:
    """Cramer-Rao bound: standard deviations from the Fisher information at
    `params` under i.i.d. Gaussian pixel noise `sigma_px` (zero where frozen)."""
    return _fisher_std(problem, params, jnp.asarray(np.flatnonzero(np.asarray(free, bool))), sigma_px)


@jax.jit
def _fisher_std(problem, params, idx, sigma_px):
    """`fisher_std` as one compiled program (the free indices are data, their count the shape)."""
    flat, unravel = ravel_pytree(params)
    J = jax.jacfwd(lambda x: reprojection_residuals(unravel(flat.at[idx].set(x)), problem).reshape(-1))(
        flat[idx]
    )
    cov = _lsq.normal_inverse(J.T @ J, sigma_px**2)
    return jnp.zeros(flat.shape).at[idx].set(jnp.sqrt(jnp.diag(cov)))


def summarize_refinement(
    res: RefineResult,
    names: list[str],
    data: CornerData,
    *,
    corr_threshold: float = 0.95,
    weak_ratio: float = 1e-6,
    outlier_fraction: float = 0.5,
) -> dict:
    """Plain-Python report of a `RefineResult` (NumPy; outside jit).

    **Returns:** a dict with the solver status, `sigma_px`, inlier RMS,
    `correlations` (pairs of free parameters with |rho| above
    `corr_threshold`), `weak_directions` (right singular vectors of the
    column-normalised Jacobian with singular value under `weak_ratio` of the
    largest, each named by its dominant parameters), the number of
    `outlier_corners` (rejected, or weight under 0.1), and `outlier_frames`:
    dataset rows (`data.frame`) with more than `outlier_fraction` of their
    corners outliers.
    """
    free = np.asarray(res.free)
    idx = np.flatnonzero(free)
    cov = np.asarray(res.cov)[np.ix_(idx, idx)]
    sd = np.sqrt(np.maximum(np.diag(cov), 1e-300))
    corr = cov / sd[:, None] / sd[None, :]
    a, b = np.nonzero(np.triu(np.abs(corr) > corr_threshold, k=1))
    pairs = [{"a": names[idx[i]], "b": names[idx[j]], "rho": float(corr[i, j])} for i, j in zip(a, b)]
    sv = np.asarray(res.singular_values)
    Vt = np.asarray(res.singular_vectors)
    weak = []
    for k in np.flatnonzero(sv < weak_ratio * sv[0]):
        v = Vt[k]
        top = np.argsort(-np.abs(v))[:4]
        weak.append(
            {
                "singular_value_ratio": float(sv[k] / sv[0]),
                "parameters": {names[idx[i]]: float(v[i]) for i in top if abs(v[i]) > 0.1},
            }
        )
    real = np.asarray(data.mask)
    bad = (~np.asarray(res.inlier) | (np.asarray(res.weights) < 0.1)) & real
    per_view = bad.sum(-1) / np.maximum(real.sum(-1), 1)
    out_frames = sorted({int(f) for f, p in zip(np.asarray(data.frame), per_view) if p > outlier_fraction})
    return {
        "solver": {
            "result": "successful" if result_is(res.result) else "failed",
            "steps": int(res.num_steps),
        },
        "sigma_px": float(res.sigma_px),
        "inlier_rms_px": float(res.residual_rms_px),
        "corners": int(real.sum()),
        "outlier_corners": int(bad.sum()),
        "outlier_frames": out_frames,
        "correlations": pairs,
        "condition_number": float(sv[0] / sv[-1]) if sv.size else float("nan"),
        "weak_directions": weak,
    }
