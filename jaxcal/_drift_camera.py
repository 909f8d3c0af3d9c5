"""The drift fit of a camera check capture (`jaxcal check` on a camera result; `jaxcal.drift`).

A few images of the plate taken later at known joint positions (the encoder
log) are predicted by the calibrated refinement model $\\hat x$ (its `estimate.npz`)
with the camera moved by a twist $\\varepsilon = (v, \\omega)$ in its own frame:
$T_{cam,target}' = \\exp(-\\varepsilon)\\, T_{cam,target}(q_v; \\hat x + P\\,\\delta q)$,
which is $T_{cam,base}' = \\exp(-\\varepsilon) T_{cam,base}$ eye-to-hand and the camera
mount $T_{flange,cam}' = T_{flange,cam} \\exp(\\varepsilon)$ eye-in-hand; $\\delta q$ the
joints' zero offsets, optional. The corners' residuals $r(\\theta)$ (px) without
drift are the check images' detector noise plus the calibration's own error,

$$ R = \\nu \\sigma^2 I + \\kappa J \\Sigma J^T = \\nu \\sigma^2 (I + (\\kappa / \\nu) B B^T),
   \\qquad B = J L / \\sigma, $$

$\\sigma$ the refinement's corner noise (`refinement.sigma_px`), $J = \\partial r /
\\partial x$ and $\\Sigma = L L^T$ the calibration's covariance (its single-camera
prefix: the first camera's pose, the robot, the mounts, rates, clock and
intrinsics). Two scales complete it:

- $\\nu$, the check images' own noise variance in units of $\\sigma^2$ (other views,
  other light), a variance component estimated from the check's residuals after the
  drift fit (the fixed point $\\nu \\leftarrow \\nu\\, \\|W r\\|^2 / (m - k)$, most of
  the $m - k$ residual degrees of freedom being the noise's); the test then compares
  $T / k$ with Fisher's $F_{k, m-k}$ rather than $\\chi^2_k / k$ (Hotelling's form for a
  scale estimated from the same data).
- $\\kappa$ (`CALIBRATION_COVARIANCE_FACTOR`): the refinement's covariance assumes
  corner errors independent across views; the detector's errors are correlated over
  neighbouring views (smooth in the plate's pose), and the part of them that the
  calibrated parameters absorb leaves no trace in its residuals, so neither
  $\\sigma$ nor a frame-robust sandwich sees it. On rendered calibrations the camera
  pose error that reaches the check is $\\kappa$ times its predicted variance
  (`benchmarks/drift.py --camera`, `calibration_error_ratio`).

With the thin SVD $B = U S V^T$ the whitening is $W = (\\nu\\sigma^2)^{-1/2} (I + U
(\\mathrm{diag}((1 + \\kappa s^2/\\nu)^{-1/2}) - 1) U^T)$ ($W^T W = R^{-1}$), applied in
$O(m n)$. Levenberg-Marquardt on $W r(\\theta)$ gives $\\hat\\theta$, its covariance $C$ and
the statistic $T = \\hat\\theta^T C^{-1} \\hat\\theta$; `jaxcal.drift` tests it.
"""

from dataclasses import dataclass
from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from ._correction import Estimate, zero_correction
from ._geometry import se3_exp
from ._lsq import normal_inverse
from ._reprojection import CornerData, RefineParams, RefineProblem, camera_matrix, chain, project

#: Gauss-Newton steps of the hand-eye drift fit (`jaxcal._drift_handeye`: the camera's pose
#: alone, a well-conditioned problem; it converges in two or three).
GN_STEPS = 6
#: Most steps of `drift_least_squares` (a check of the pose alone converges in three or four, one
#: that frees the joints' zero offsets may take twenty) ...
LM_STEPS = 40
#: ... its starting damping, relative to the normal matrix's diagonal, and when it stops: a step
#: that lowers the sum of squares by less than `LM_RTOL` of it, or `LM_REFUSED` refused in a row.
LM_DAMPING = 1e-3
LM_RTOL = 1e-12
LM_REFUSED = 4


def drift_least_squares(res, k: int, steps: int = LM_STEPS):
    """Levenberg-Marquardt from zero on the residuals `res(theta)` of `k` drift parameters, for
    at most `steps` steps: a step that does not lower the sum of squares is refused and the
    damping raised tenfold, an accepted one lowers it tenfold. (Undamped Gauss-Newton diverged on
    checks that free the joints' zero offsets: the device's or camera's rotation about the base's
    vertical and the first joint's offset are nearly one direction, the first full step
    overshot by about a radian, and where a fixed number of steps ended depended on the
    arithmetic.) **Returns** `(theta, J^T J, r)` at the last iterate."""

    def step(carry):
        theta, lam, n, refused, _ = carry
        r, A = res(theta), jax.jacfwd(res)(theta)
        H = A.T @ A
        D = jnp.maximum(jnp.diag(H), 1e-12 * jnp.max(jnp.diag(H)))
        trial = theta + jnp.linalg.solve(H + lam * jnp.diag(D), -(A.T @ r))
        r_trial = res(trial)
        ss, ss_trial = r @ r, r_trial @ r_trial
        better = ss_trial < ss
        refused = jnp.where(better, 0, refused + 1)
        done = (better & (ss - ss_trial <= LM_RTOL * ss)) | (refused >= LM_REFUSED)
        lam = jnp.clip(jnp.where(better, lam / 10.0, lam * 10.0), 1e-15, 1e15)
        return jnp.where(better, trial, theta), lam, n + 1, refused, done

    def going(carry):
        return (carry[2] < steps) & ~carry[4]

    start = (jnp.zeros(k), jnp.asarray(LM_DAMPING, jnp.result_type(float)), 0, 0, False)
    theta = jax.lax.while_loop(going, step, start)[0]
    A = jax.jacfwd(res)(theta)
    return theta, A.T @ A, res(theta)


#: $\\kappa$ of the module docstring: the calibration's covariance as the check uses it.
CALIBRATION_COVARIANCE_FACTOR = 2.0
#: Rounds of the noise scale's fixed point: a fit at nu = 1, then one at its estimate.
NOISE_ROUNDS = 2

#: The single-camera groups of the refinement vector (a prefix: `others` and `angles` follow).
PREFIX_GROUPS = ("cam", "origin", "zero", "tool", "rate", "clock", "intr")


@dataclass(frozen=True, eq=False)
class CameraReference:
    """What a camera calibration predicts for a check capture's corners.

    - `problem`: the capture's corners against the calibration's references;
      `x`: the calibration's single-camera vector (the clock increment folded
      into `problem.offset0_s`); `zero`: `(joints, n)` the zero offsets' selector.
    - `U`, `s`, `sigma_px`: the whitening's singular vectors and values, the corner
      noise (see the module docstring); `factor`: $\\kappa$.
    - `corners`, `views`: what the capture gave; `joint_names`; `T_fixed`: the
      calibrated pose the drift moves (`T_cam_base`, or eye-in-hand `T_flange_cam`).
    """

    problem: RefineProblem
    x: jnp.ndarray
    zero: jnp.ndarray
    U: jnp.ndarray
    s: np.ndarray
    sigma_px: float
    corners: int
    views: int
    joint_names: tuple[str, ...]
    T_fixed: np.ndarray
    eye_in_hand: bool
    factor: float = CALIBRATION_COVARIANCE_FACTOR


def _template(n: int, markers: int) -> RefineParams:
    return RefineParams(
        cam=jnp.zeros(6),
        correction=zero_correction(n, markers),
        rate=jnp.ones(n),
        clock_ms=jnp.zeros(()),
        intrinsics=jnp.zeros(9),
    )


def _camera_points(x, eps, problem: RefineProblem):
    """The corners in the (moved) camera frame `(V, P, 3)` and the calibrated intrinsics."""
    n = problem.nominal.num_joints
    _, unravel = ravel_pytree(_template(n, problem.T_flange_marker0.shape[0]))
    params = unravel(x)
    R, t = chain(params, problem)
    X = jnp.einsum("vab,vkb->vka", R, problem.data.points) + t[:, None, :]
    T = se3_exp(-eps)
    return X @ T[:3, :3].T + T[:3, 3], camera_matrix(params, problem)


def _residuals(x, eps, problem: RefineProblem):
    """Reprojected minus detected corners (px), flattened, zero on padding."""
    X, (K, dist) = _camera_points(x, eps, problem)
    r = project(K, dist, X) - problem.data.pixels
    return jnp.where(problem.data.mask[..., None], r, 0.0).reshape(-1)


@jax.jit
def view_jacobians(x, problem: RefineProblem):
    """Per view of `problem` (its pixels ignored): the corners' predicted pixels `(V, P, 2)`,
    their camera-frame positions `(V, P, 3)` (m), and their derivatives `(V, 2P, 6)` by the camera's twist and
    `(V, 2P, n)` by the calibration's vector (for planning a check capture)."""
    X, (K, dist) = _camera_points(x, jnp.zeros(6), problem)
    V = X.shape[0]

    def pix(xx, eps):
        Y, (KK, dd) = _camera_points(xx, eps, problem)
        return project(KK, dd, Y).reshape(V, -1)

    A = jax.jacfwd(pix, argnums=1)(x, jnp.zeros(6))
    J = jax.jacfwd(pix, argnums=0)(x, jnp.zeros(6))
    return project(K, dist, X), X, A, J


@jax.jit
def residual_jacobian(x, problem: RefineProblem):
    """`(r, J)`: the residuals at the calibration and their derivative by its vector."""
    f = partial(_residuals, eps=jnp.zeros(6), problem=problem)
    return f(x), jax.jacfwd(f)(x)


def _whiten(v, U, d, sigma):
    return (v + U @ (d * (U.T @ v))) / sigma


@partial(jax.jit, static_argnames="offsets")
def fit_camera_drift(ref_x, zero, U, d, sigma, problem: RefineProblem, *, offsets: bool):
    """Levenberg-Marquardt on the whitened residuals. **Returns:** `(theta, C, T, rss)` as
    `jaxcal.drift.fit_drift` (theta: the camera's twist, then the zero offsets with `offsets`)."""
    k = 6 + (zero.shape[0] if offsets else 0)

    def res(theta):
        x = ref_x + (theta[6:] @ zero if offsets else 0.0)
        return _whiten(_residuals(x, theta[:6], problem), U, d, sigma)

    theta, info, r = drift_least_squares(res, k)
    return theta, normal_inverse(info), theta @ info @ theta, r @ r


def pad_corners(data: CornerData, corners: int) -> CornerData:
    """`data` with every view padded to `corners` entries (masked out), so that captures of
    one target share the compiled check whatever the detector found."""
    extra = corners - data.points.shape[1]
    if extra <= 0:
        return data
    V = data.points.shape[0]
    return eqx.tree_at(
        lambda d: (d.points, d.pixels, d.mask),
        data,
        (
            jnp.concatenate([data.points, jnp.zeros((V, extra, 3))], axis=1),
            jnp.concatenate([data.pixels, jnp.zeros((V, extra, 2))], axis=1),
            jnp.concatenate([data.mask, jnp.zeros((V, extra), bool)], axis=1),
        ),
    )


def camera_reference(
    est: Estimate, data: CornerData, K0, dist0, offset0_s: float, sigma_px: float, num_corners: int
) -> CameraReference:
    """The `CameraReference` of a calibration `est` for the check corners `data`
    (`K0`, `dist0`: the intrinsics `est`'s increments are relative to; `offset0_s`:
    the check capture's clock offset, s)."""
    lay = est.layout
    idx = np.concatenate([lay.index(g) for g in PREFIX_GROUPS])
    if not np.array_equal(idx, np.arange(len(idx))):
        raise ValueError("the refinement vector's single-camera groups are not its prefix")
    if est.x.shape[0] != lay.size:
        raise ValueError("the estimate is not a refinement's (no intrinsics, rates or clock)")
    x = np.asarray(est.x, np.float64)[: len(idx)].copy()
    x[lay.index("clock")] = 0.0  # the check capture's own clock offset is offset0_s
    cov = np.asarray(est.cov, np.float64)[: len(idx), : len(idx)]
    problem = RefineProblem(
        nominal=est.nominal,
        T_flange_marker0=jnp.asarray(est.T_flange_marker0),
        T_cam_base0=jnp.asarray(est.T_cam_base0),
        K0=jnp.asarray(K0, jnp.float64),
        dist0=jnp.asarray(dist0, jnp.float64),
        offset0_s=jnp.asarray(float(offset0_s)),
        data=data,
        eye_in_hand=lay.eye_in_hand,
    )
    _, J = (np.asarray(a) for a in residual_jacobian(jnp.asarray(x), problem))
    lam, V = np.linalg.eigh(0.5 * (cov + cov.T))
    keep = lam > lam.max() * 1e-14 if lam.max() > 0 else np.zeros(len(lam), bool)
    B = J @ (V[:, keep] * np.sqrt(lam[keep])) / sigma_px
    U, s, _ = np.linalg.svd(B, full_matrices=False)
    zero = np.zeros((len(lay.joints), len(idx)))
    zero[np.arange(len(lay.joints)), lay.index("zero")] = 1.0
    cam = np.asarray(est.T_cam_base0) @ np.asarray(se3_exp(jnp.asarray(x[lay.index("cam")])))
    if lay.eye_in_hand:
        tool = np.asarray(se3_exp(jnp.asarray(x[lay.index("tool")[:6]])))
        T_fixed = np.asarray(est.T_flange_marker0)[0] @ tool
    else:
        T_fixed = cam
    return CameraReference(
        problem=problem,
        x=jnp.asarray(x),
        zero=jnp.asarray(zero),
        U=jnp.asarray(U),
        s=s,
        sigma_px=float(sigma_px),
        corners=int(num_corners),
        views=int(data.points.shape[0]),
        joint_names=tuple(lay.joints),
        T_fixed=T_fixed,
        eye_in_hand=lay.eye_in_hand,
    )


def fit(ref: CameraReference, *, joint_offsets: bool) -> tuple[np.ndarray, np.ndarray, float, float, float]:
    """The drift fit of `ref` (`fit_camera_drift`) with the check's noise scale $\\nu$ estimated
    (see the module docstring): `(theta, C, T, rss, nu)` as NumPy."""
    k = 6 + (ref.zero.shape[0] if joint_offsets else 0)
    dof = 2 * ref.corners - k
    nu = 1.0
    for _ in range(NOISE_ROUNDS):
        d = jnp.asarray(1.0 / np.sqrt(1.0 + ref.factor * ref.s**2 / nu) - 1.0)
        theta, C, T, rss = fit_camera_drift(
            ref.x, ref.zero, ref.U, d, ref.sigma_px * np.sqrt(nu), ref.problem, offsets=joint_offsets
        )
        nu *= float(rss) / dof
    return np.asarray(theta), np.asarray(C), float(T), float(rss), nu / (float(rss) / dof)
