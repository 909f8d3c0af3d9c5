"""The hand-eye solve: robust then plain Levenberg-Marquardt, outlier rejection, covariance."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, Bool, Float, Int

from .._geometry import pose_inverse
from .._linalg import after
from .._lsq import LMOptions, normal_pinv
from .blocks import block_bread, solve_by_blocks
from .closed import initialise_hand_eye
from .common import least_squares, pose_error
from .data import HandEyeData, HandEyePixels, HandEyePoses
from .jacobian import solve_pixels
from .model import (
    HandEyeParams,
    HandEyeReference,
    corrected_robot,
    group_sizes,
    hand_eye_residuals,
    robot_correction,
    robust_residuals,
    transforms,
    with_whitening,
)
from .noise import ROBOT_SIGMA_START, robot_sigma6, solve_estimating_noise


class HandEyeResult(eqx.Module):
    """A hand-eye calibration.

    **Fields:**
    - `T_cam_robot`: per camera, `(cameras, 4, 4)`: $T_{cam\\_base}$ (eye-to-hand)
      or $T_{cam\\_ee}$ (eye-in-hand); `T_robot_cam` its inverse
      ($T_{base\\_cam}$ or $T_{ee\\_cam}$, the camera's pose on the robot).
    - `T_robot_board`: $T_{ee\\_board}$ (eye-to-hand) or $T_{base\\_board}$ (eye-in-hand).
    - `std_cam_robot`, `std_robot_cam` `(cameras, 6)`, `std_robot_board` `(6,)`:
      standard deviations of (translation (m), rotation vector (rad)) of each
      transform, both in its parent frame: $\\delta t = \\hat t - t$ and
      $\\hat R = \\exp(\\delta w) R$. From $(J^T J)^{-1}$ of the whitened
      residuals (robot corrections marginalised), scaled by the residual
      variance `variance_factor` where it exceeds 1; and, when
      `scale_covariance`, replaced per component by the frame-robust variance
      (`cov_frames`) where that is significantly larger (by more than twice
      its own sampling spread, $1 + 2\\sqrt{2/G}$ times, $G$ the frames kept):
      errors shared within a frame that the pixel noise model misses.
    - `cov`: that covariance of the flat parameter vector (tangent deltas).
    - `cov_frames`: the cluster-robust covariance, one cluster per frame
      (errors shared by a frame's corners: robot pose error, view-dependent
      detector bias; see `_frame_robust_covariance`).
    - `variance_factor`: $\\|r\\|^2 / (m - n)$, the residual variance in units
      of the stated noise (about 1 when the noise model is honest).
    - `T_base_ee`: the robot poses used (corrected when `robot_sigma` was given).
    - `robot_sigma` `(6,)`: the robot pose noise the solve used, (translation m x3,
      rotation rad x3): as given, or estimated (`robot_sigma_estimated`, see
      `noise`); None for exact robot poses. `robot_dof` `(2,)`: the redundancies
      $(r_t, r_r)$ of its translation and rotation priors (the degrees of
      freedom an estimate rests on: relative standard error about $1/\\sqrt{2r}$);
      None for exact robot poses.
    - `robot_rms` `(frames,)`: whitened RMS of each frame's robot correction,
      $\\|\\delta_f / \\sigma_{robot}\\| / \\sqrt 6$ (NaN for exact robot poses and for
      frames no kept view saw).
    - `residual_rms`: RMS of the whitened observation residuals over the kept
      groups (about 1 when the noise model is honest); `pixel_rms` (px, NaN for
      pose data).
    - `group_rms`: whitened RMS per (camera, frame) `(cameras, frames)`, NaN where unobserved.
    - `rejected`: (camera, frame) groups rejected as outliers; `num_rejected`.
    - `stage_result`, `stage_steps` `(2,)`: optimistix's result code and step
      count of each Levenberg-Marquardt stage (robust, then plain).
    - `result`: the first unsuccessful stage's code (successful when both
      are); `num_steps`: the steps of both stages together.
    - `T_cam_robot_start`, `T_robot_board_start`: the closed-form solution on the
      groups kept (`solve_axzb`), which the optimum should be near.
    """

    T_cam_robot: Float[Array, "cameras 4 4"]
    T_robot_cam: Float[Array, "cameras 4 4"]
    T_robot_board: Float[Array, "4 4"]
    std_cam_robot: Float[Array, "cameras 6"]
    std_robot_cam: Float[Array, "cameras 6"]
    std_robot_board: Float[Array, "6"]
    cov: Float[Array, "n n"]
    cov_frames: Float[Array, "n n"]
    variance_factor: Float[Array, ""]
    T_base_ee: Float[Array, "frames 4 4"]
    robot_sigma: Float[Array, "6"] | None
    robot_sigma_estimated: Bool[Array, ""]
    robot_dof: Float[Array, "2"] | None
    robot_rms: Float[Array, " frames"]
    residual_rms: Float[Array, ""]
    pixel_rms: Float[Array, ""]
    group_rms: Float[Array, "cameras frames"]
    rejected: Bool[Array, "cameras frames"]
    num_rejected: Int[Array, ""]
    result: optx.RESULTS
    num_steps: Int[Array, ""]
    stage_result: optx.RESULTS
    stage_steps: Int[Array, "2"]
    T_cam_robot_start: Float[Array, "cameras 4 4"]
    T_robot_board_start: Float[Array, "4 4"]
    eye_in_hand: Bool[Array, ""]

    def _named(self, want_eye_in_hand: bool, name: str, value):
        # Read outside jit (the flag may be batched under vmap: all trials share it).
        eye_in_hand = bool(np.all(np.asarray(self.eye_in_hand)))
        if eye_in_hand != want_eye_in_hand:
            kind = "eye-in-hand" if eye_in_hand else "eye-to-hand"
            raise AttributeError(f"{name} is not defined for an {kind} calibration")
        return value

    @property
    def T_cam_base(self) -> Float[Array, "cameras 4 4"]:
        """Eye-to-hand: base -> camera."""
        return self._named(False, "T_cam_base", self.T_cam_robot)

    @property
    def T_base_cam(self) -> Float[Array, "cameras 4 4"]:
        """Eye-to-hand: the camera's pose in the base frame."""
        return self._named(False, "T_base_cam", self.T_robot_cam)

    @property
    def T_ee_board(self) -> Float[Array, "4 4"]:
        """Eye-to-hand: the board's pose on the end effector."""
        return self._named(False, "T_ee_board", self.T_robot_board)

    @property
    def T_cam_ee(self) -> Float[Array, "cameras 4 4"]:
        """Eye-in-hand: end effector -> camera."""
        return self._named(True, "T_cam_ee", self.T_cam_robot)

    @property
    def T_ee_cam(self) -> Float[Array, "cameras 4 4"]:
        """Eye-in-hand: the camera's pose on the end effector."""
        return self._named(True, "T_ee_cam", self.T_robot_cam)

    @property
    def T_base_board(self) -> Float[Array, "4 4"]:
        """Eye-in-hand: the board's pose in the base frame."""
        return self._named(True, "T_base_board", self.T_robot_board)

    def rejected_frames(self) -> np.ndarray:
        """Indices of the frames rejected in any camera (NumPy; call outside jit)."""
        return np.flatnonzero(np.asarray(self.rejected).any(axis=0))


#: `calibrate_hand_eye`'s solver settings (per stage).
HAND_EYE_OPTIONS = LMOptions(rtol=1e-8, atol=1e-6, max_steps=200)


def calibrate_hand_eye(
    data: HandEyeData,
    *,
    reject_outliers: bool | Bool[Array, ""] = True,
    outlier_threshold: float = 3.0,
    min_outlier_scale: float = 0.1,
    loss_scale: float = 2.0,
    options: LMOptions = HAND_EYE_OPTIONS,
    throw: bool = False,
    scale_covariance: bool = True,
    by_blocks: bool = True,
    closed_form_jacobian: bool = True,
    estimate_robot_noise: bool | Bool[Array, ""] = False,
    start: tuple[Float[Array, "cameras 4 4"], Float[Array, "4 4"]] | None = None,
) -> HandEyeResult:
    """Hand-eye calibration (eye-to-hand or eye-in-hand, one or more cameras); pure, jittable, vmappable.

    Minimises $\\sum_{c,f} \\|r_{cf}\\|^2 + \\sum_f \\|\\delta_f/\\sigma_{robot}\\|^2$
    over $X_c$, $Y$ (and robot corrections $\\delta_f$), with $r_{cf}$ the
    whitened reprojection errors of camera $c$ at robot pose $f$ (or the
    whitened pose error for `HandEyePoses`). See the module docstring for the
    pipeline. Validate inputs first (`make_hand_eye_*` do).

    **Arguments:**
    - `data`: `HandEyePixels` or `HandEyePoses`.
    - `reject_outliers`: solve with a Cauchy loss first, reject (camera, frame)
      groups whose whitened RMS exceeds `outlier_threshold` times
      max(median group RMS, `min_outlier_scale`), and (pixels with noisy
      robot poses) frames whose robot correction's whitened RMS exceeds
      `outlier_threshold` times max(its median, 1), then re-solve without them.
      Which are rejected depends on the robust stage's optimum only: once it
      has converged, not on `max_steps`.
    - `loss_scale`: Cauchy scale $b$ (whitened units) of the robust solve.
    - `options`: the solver's `LMOptions` (`max_steps` per stage; tolerances on the
      tangent deltas in m/rad and on the whitened residuals); `throw`: optimistix's.
    - `scale_covariance`: multiply the covariance by $\\max(1, \\|r\\|^2/(m - n))$:
      when the residuals are larger than the stated noise, the stated noise
      was optimistic and the covariance grows with them; when smaller, the
      stated noise is kept (a small residual may be luck or overfitting).
    - `by_blocks`: pixels with noisy robot poses: solve and take the covariance
      by the Schur complement over the per-pose corrections (`blocks`; the same
      optimum, linear in the frames); False: dense Levenberg-Marquardt over all
      unknowns (optimistix), the reference. No effect on other data.
    - `closed_form_jacobian`: pixels with exact robot poses: Levenberg-Marquardt
      and the covariance on the hand-written Jacobian (`jacobian.pixel_terms`,
      the same optimum at a fraction of autodiff's cost); False: autodiff, the
      reference. No effect on other data.
    - `estimate_robot_noise` (pixels; may be traced): estimate the robot pose noise,
      translation and rotation apart, as a variance component (`noise`), from
      `data.robot_sigma` (None: 1 mm, 0.1 deg); rejection, covariance and `robot_rms`
      use the estimate. False: the robot noise as given (None: exact poses).
    - `start`: `(T_cam_robot, T_robot_board)` to start from (e.g. the full data's optimum, for
      re-solves of a subset); None: the closed form (`initialise_hand_eye`). The start is also
      the result's `T_cam_robot_start`, `T_robot_board_start`.


    **Returns:** a `HandEyeResult`.
    """
    data = _estimation_start(data, estimate_robot_noise, by_blocks)
    estimate = jnp.asarray(estimate_robot_noise, bool)
    X0, Y0 = initialise_hand_eye(data) if start is None else start
    params0 = _unknowns(data)
    observed = jnp.any(data.mask, axis=-1) if isinstance(data, HandEyePixels) else data.mask
    blocks = by_blocks and params0.robot is not None  # pixels with per-pose robot corrections
    closed = closed_form_jacobian and isinstance(data, HandEyePixels) and params0.robot is None

    (params, active, sigma), (results, steps, lins, dofs) = _run_stages(
        data,
        params0,
        observed,
        (X0, Y0),
        jnp.asarray(reject_outliers, bool),
        estimate,
        (blocks, closed),
        (loss_scale, options, outlier_threshold, min_outlier_scale),
    )
    data = _with_robot_sigma(data, sigma)
    # The last stage is plain and its groups are the summary's: its linearisation is the summary's.
    lin = jax.tree.map(lambda x: x[1], lins)
    result = _first_failure(results)
    if throw:
        params = result.error_if(params, result != optx.RESULTS.successful)
    X0_kept, Y0_kept = _kept_start(data, observed, active, params, (X0, Y0))
    params, lin = after((params, lin), X0_kept, Y0_kept)
    ref = with_whitening(params, HandEyeReference(X0=X0, Y0=Y0, active=active), data)
    out = _summarise(params, ref, data, observed & ~active, scale_covariance, blocks, closed, lin)
    return eqx.tree_at(
        lambda r: (
            r.result,
            r.num_steps,
            r.stage_result,
            r.stage_steps,
            r.T_cam_robot_start,
            r.T_robot_board_start,
            r.robot_sigma_estimated,
            r.robot_dof,
        ),
        out,
        (result, jnp.sum(steps), results, steps, X0_kept, Y0_kept, estimate & blocks, _last(dofs)),
        is_leaf=lambda x: x is None,
    )


def _first_failure(results: optx.RESULTS) -> optx.RESULTS:
    """The solve's code from the stages' `(2,)` codes: the first unsuccessful one's, else successful."""
    first, last = (jax.tree.map(lambda x, i=i: x[i], results) for i in (0, 1))
    return optx.RESULTS.where(first == optx.RESULTS.successful, last, first)


def _unknowns(data: HandEyeData) -> HandEyeParams:
    """The solve's unknowns at zero: each camera's and the board's twist, and (pixels with
    noisy robot poses) one correction per robot pose; for pose data the noisy robot poses
    are marginalised instead (`model.pose_error_covariance`)."""
    C, F = data.mask.shape[:2]
    return HandEyeParams(
        cam_robot=jnp.zeros((C, 6)),
        robot_board=jnp.zeros(6),
        robot=None if data.robot_sigma is None or isinstance(data, HandEyePoses) else jnp.zeros((F, 6)),
    )


def _kept_start(data, observed, active, params, start):
    """The closed form again on the kept groups only: what the verdict compares the optimum
    with (the first start also saw the outliers); ordered after the solve `params`. With
    nothing rejected the kept groups are all the data: the first `start`, not computed again."""
    X0, Y0 = start
    kept = data.mask & (active[..., None] if isinstance(data, HandEyePixels) else active)
    return jax.lax.cond(
        jnp.any(observed & ~active),
        lambda: initialise_hand_eye(after(eqx.tree_at(lambda d: d.mask, data, kept), params)),
        lambda: (X0, Y0),
    )


def _estimation_start(data, estimate_robot_noise, by_blocks: bool):
    """`data` with a start for the robot noise estimate where it has none; refuses what cannot be estimated.

    Exact robot poses (`data.robot_sigma` None) have no corrections, so estimating their noise is
    another program: the flag must then be a Python (or concrete) bool, decided at trace time. A
    traced flag with exact poses once took 1 mm / 0.1 deg "as given" when False; it is refused."""
    if isinstance(estimate_robot_noise, jax.core.Tracer):
        if data.robot_sigma is None:
            raise ValueError(
                "estimate_robot_noise is traced but data.robot_sigma is None (exact robot poses): whether "
                "to add robot corrections decides the program; pass a Python bool, or give data a "
                "robot_sigma (the estimate's start) to switch the estimate on and off as traced data"
            )
    elif not bool(estimate_robot_noise):
        return data
    if isinstance(data, HandEyePoses) or not by_blocks:
        raise ValueError(
            "estimate_robot_noise: the robot noise is estimated from pixels (HandEyePixels), by blocks only"
        )
    if data.robot_sigma is not None:
        return data
    start = robot_sigma6(*ROBOT_SIGMA_START).astype(data.pixels.dtype)
    return eqx.tree_at(lambda d: d.robot_sigma, data, start, is_leaf=lambda x: x is None)


def _run_stages(data, params0, observed, start, reject_outliers, estimate, paths, options):
    """The two Levenberg-Marquardt stages of `calibrate_hand_eye` (a `lax.scan`): robust, with
    rejection, then plain on the groups kept; with robot corrections, each re-run while the robot
    noise is estimated. `start` `(X0, Y0)`; `paths` `(blocks, closed)` (see `_solve`); `options`
    `(loss_scale, LMOptions, outlier_threshold, min_outlier_scale)`.

    **Returns:** `((params, active, robot_sigma), (results, steps, lins, dofs))`, per stage.
    """
    X0, Y0 = start
    blocks, closed = paths
    loss_scale, lm, outlier_threshold, min_outlier_scale = options

    def solve_at(params, active, robust, d):
        ref = with_whitening(params, HandEyeReference(X0=X0, Y0=Y0, active=active), d)
        return _solve(params, (ref, d, loss_scale, robust), blocks, closed, lm)

    def stage(carry, robust):
        # One Levenberg-Marquardt, traced once and run per stage: robust (Cauchy)
        # then plain on the groups the robust stage kept; with noisy robot poses,
        # re-run while the robot noise is estimated (`noise.solve_estimating_noise`).
        params, active, sigma = carry
        if blocks:
            value, code, steps, lin, sigma, dof = solve_estimating_noise(
                lambda p, s: solve_at(p, active, robust, _with_robot_sigma(data, s)),
                params,
                sigma,
                jnp.any(active, axis=0),
                robust,
                estimate,
            )
        else:
            value, code, steps, lin = solve_at(params, active, robust, data)
            dof = None
        d = _with_robot_sigma(data, sigma)
        ref = with_whitening(value, HandEyeReference(X0=X0, Y0=Y0, active=active), d)
        rms = _group_rms(value, ref, d)
        scale = jnp.maximum(jnp.nanmedian(rms), min_outlier_scale)
        reject = robust & active & (rms > outlier_threshold * scale)
        if value.robot is not None:
            # A robot pose far outside its stated noise is absorbed by its correction
            # (the pixels then fit): reject the frame on the correction's size.
            p = jnp.where(jnp.any(active, axis=0), _prior_rms(value, d), jnp.nan)
            p_scale = jnp.maximum(jnp.nanmedian(p), 1.0)
            reject = reject | (robust & active & (p > outlier_threshold * p_scale)[None])
        return (value, active & ~reject, sigma), (code, steps, lin, dof)

    # `reject_outliers` is traced, so both settings share one compiled solver; when False
    # the first stage is plain too and the second starts from its optimum.
    stages = jnp.stack([reject_outliers, jnp.asarray(False)])
    carry0 = (params0, observed, data.robot_sigma)
    return jax.lax.scan(stage, carry0, stages)


def _last(stacked):
    """The plain stage's entry of a per-stage output (None stays None)."""
    return None if stacked is None else stacked[1]


def _with_robot_sigma(data, sigma):
    """`data` with the robot noise `sigma` (unchanged when None: exact robot poses)."""
    if sigma is None:
        return data
    return eqx.tree_at(lambda d: d.robot_sigma, data, sigma)


def _solve(params, args, blocks: bool, closed: bool, options: LMOptions):
    """One Levenberg-Marquardt stage: by blocks (noisy robot poses), on the closed-form
    Jacobian (pixels, exact robot poses) or optimistix's on autodiff's. **Returns:**
    `(params, result, num_steps, lin)`, `lin` the solver's linearisation at `params`
    where it has one: the Jacobian blocks `(r, J_g, J_l)` by blocks, the normal equations
    `(r, J^T J, per-group gradients)` on the closed form, None for optimistix's."""
    if blocks:
        return solve_by_blocks(params, args, options)
    if closed:
        return solve_pixels(params, args, options)
    sol = least_squares(robust_residuals, params, args, dataclasses.replace(options, throw=False))
    return sol.value, sol.result, sol.stats["num_steps"], None


def _prior_rms(params, data) -> Float[Array, " frames"]:
    """Whitened RMS of each frame's robot correction (pixels with robot corrections)."""
    return jnp.sqrt(jnp.mean((params.robot / data.robot_sigma) ** 2, axis=-1))


def _group_rms(params, ref, data) -> Float[Array, "cameras frames"]:
    r, _ = hand_eye_residuals(params, (ref, data))
    n = group_sizes(ref, data)
    return jnp.where(n > 0, jnp.sqrt(jnp.sum(r**2, axis=-1) / jnp.maximum(n, 1.0)), jnp.nan)


def _frame_gradients(J, r, ref, data) -> Float[Array, "frames n"]:
    """$g_f = J_f^T r_f$: the gradient of frame $f$'s residuals (all cameras and its robot prior)."""
    C, F = ref.active.shape
    per_group = 2 * data.mask.shape[-1] if isinstance(data, HandEyePixels) else 6
    n_obs, n = C * F * per_group, J.shape[1]
    g = jnp.einsum("cfkn,cfk->fn", J[:n_obs].reshape(C, F, per_group, n), r[:n_obs].reshape(C, F, per_group))
    if r.shape[0] > n_obs:  # the robot corrections' prior, one block per frame
        g = g + jnp.einsum("fkn,fk->fn", J[n_obs:].reshape(F, 6, n), r[n_obs:].reshape(F, 6))
    return g


def _frame_robust_covariance(g, bread, ref) -> Float[Array, "n n"]:
    """The cluster-robust (sandwich) covariance with one cluster per frame.

    $B \\big(\\sum_f g_f g_f^T\\big) B \\cdot G/(G-1)$, $g_f = J_f^T r_f$ the
    gradient of frame $f$'s residuals (all cameras and its robot prior;
    `_frame_gradients`, or `blocks.block_bread`), $B = (J^T J)^{-1}$, $G$ the
    frames kept. Unlike $s^2 B$ it does not assume
    the errors independent within a frame: a frame's corners share its robot
    pose error and the detector's view-dependent bias, which move the whole
    view together (the model's $\\sigma$ sees them only as a little extra
    pixel noise). Same expectation as $B$ when the noise model holds.
    """
    kept = jnp.sum(jnp.any(ref.active, axis=0))
    meat = g.T @ g * kept / jnp.maximum(kept - 1.0, 1.0)
    return bread @ meat @ bread


def _bread(params, ref, data, blocks: bool, closed: bool = False, lin=None):
    """$(J^TJ)^{+}$ of the plain residuals at `params`, the per-frame gradients and $\\|r\\|^2$:
    by blocks (`blocks.block_bread`), from the closed form's normal equations
    (`jacobian.pixel_normal`: `lin` required) or from autodiff's dense Jacobian; from `lin`, the
    solver's plain linearisation at `params`, where given (see `_solve`)."""
    if blocks:
        return block_bread(params, ref, data, lin)
    if closed:  # the solver's normal equations and each group's gradient (`jacobian.pixel_normal`)
        r_all, H, G = lin
        return normal_pinv(H), jnp.sum(G, axis=0), jnp.sum(r_all**2)
    flat, unravel = ravel_pytree(params)

    def flat_res(x):
        r, prior = hand_eye_residuals(unravel(x), (ref, data))
        return jnp.concatenate([r.reshape(-1)] + ([] if prior is None else [prior.reshape(-1)]))

    J = jax.jacfwd(flat_res)(flat)
    r_all = flat_res(flat)
    bread = normal_pinv(J.T @ J)
    return bread, _frame_gradients(J, r_all, ref, data), jnp.sum(r_all**2)


def _summarise(
    params, ref, data, rejected, scale_covariance, blocks=False, closed=False, lin=None
) -> HandEyeResult:
    """The result at `params`: covariance, standard deviations, residual statistics (solver
    fields left None); `lin`: the solver's plain linearisation at `params` (see `_bread`)."""
    flat, unravel = ravel_pytree(params)
    bread, grads, ssr = _bread(params, ref, data, blocks, closed, lin)
    n_obs = jnp.sum(group_sizes(ref, data))
    n_prior = 0 if params.robot is None else params.robot.size
    dof = jnp.maximum(n_obs + n_prior - flat.size, 1.0)
    variance_factor = ssr / dof
    cov = bread * jnp.maximum(variance_factor, 1.0) if scale_covariance else bread
    cov_frames = _frame_robust_covariance(grads, bread, ref)

    X, Y = transforms(params, ref)
    Xi = jax.vmap(pose_inverse)(X)

    def errors(x):
        Xx, Yx = transforms(unravel(x), ref)
        Xix = jax.vmap(pose_inverse)(Xx)
        return jnp.concatenate(
            [
                jax.vmap(pose_error)(Xx, X).reshape(-1),
                jax.vmap(pose_error)(Xix, Xi).reshape(-1),
                pose_error(Yx, Y),
            ]
        )

    G = jax.jacfwd(errors)(flat)
    var = jnp.einsum("ia,ab,ib->i", G, cov, G)
    if scale_covariance:
        # The frame-robust variance where it exceeds the model's by more than its own sampling
        # spread (two standard deviations of a variance estimated from `kept` frames).
        var_frames = jnp.einsum("ia,ab,ib->i", G, cov_frames, G)
        kept = jnp.maximum(jnp.sum(jnp.any(ref.active, axis=0)), 2.0)
        var = jnp.where(var_frames > var * (1.0 + 2.0 * jnp.sqrt(2.0 / kept)), var_frames, var)
    std = jnp.sqrt(jnp.maximum(var, 0.0))
    C = X.shape[0]
    r_obs, _ = hand_eye_residuals(params, (ref, data))
    ssr_obs = jnp.sum(r_obs**2)
    is_px = isinstance(data, HandEyePixels)
    marginalised = isinstance(data, HandEyePoses) and data.robot_sigma is not None
    delta = robot_correction(params, ref, data) if marginalised else params.robot
    F = data.T_base_ee.shape[0]
    robot_rms = (
        jnp.full(F, jnp.nan)
        if delta is None
        # NaN for a frame no camera's kept view saw (rejected): its correction is just the prior's zero.
        else jnp.where(
            jnp.any(ref.active, axis=0), jnp.sqrt(jnp.mean((delta / data.robot_sigma) ** 2, axis=-1)), jnp.nan
        )
    )
    return HandEyeResult(
        T_cam_robot=X,
        T_robot_cam=Xi,
        T_robot_board=Y,
        std_cam_robot=std[: 6 * C].reshape(C, 6),
        std_robot_cam=std[6 * C : 12 * C].reshape(C, 6),
        std_robot_board=std[12 * C :],
        cov=cov,
        cov_frames=cov_frames,
        variance_factor=variance_factor,
        T_base_ee=corrected_robot(data.T_base_ee, delta),
        robot_sigma=data.robot_sigma,
        robot_sigma_estimated=jnp.asarray(False),
        robot_dof=None,
        robot_rms=robot_rms,
        residual_rms=jnp.sqrt(ssr_obs / jnp.maximum(n_obs, 1.0)),
        pixel_rms=jnp.sqrt(ssr_obs / jnp.maximum(n_obs, 1.0)) * data.sigma_px
        if is_px
        else jnp.asarray(jnp.nan),
        group_rms=_group_rms(
            params,
            # Its own whitening, factorised after the covariance's (see _linalg).
            with_whitening(after(params, cov), HandEyeReference(ref.X0, ref.Y0, ref.active | rejected), data),
            data,
        ),
        rejected=rejected,
        num_rejected=jnp.sum(rejected),
        result=None,
        num_steps=None,
        stage_result=None,
        stage_steps=None,
        T_cam_robot_start=None,
        T_robot_board_start=None,
        eye_in_hand=data.eye_in_hand,
    )
