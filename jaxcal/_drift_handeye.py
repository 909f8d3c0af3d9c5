"""The drift fit of a hand-eye check capture (`jaxcal check` on a `jaxcal handeye` result).

A few images of the target taken later at recorded robot poses $B_f$ are predicted by the
hand-eye result, $X = T_{cam,robot}$ and $Y = T_{robot,target}$ (see `jaxcal._handeye`),
with the camera moved by a twist $\\varepsilon = (v, \\omega)$ in its own frame:

$$ A_f' = \\exp(-\\varepsilon)\\, X B_f Y, $$

which is $T_{cam,base}' = \\exp(-\\varepsilon) T_{cam,base}$ eye-to-hand and
$T_{ee,cam}' = T_{ee,cam} \\exp(\\varepsilon)$ eye-in-hand (the camera checks' convention,
`jaxcal._drift_camera`). Without drift the corners' residuals $r$ (px) are the detector's
noise, the robot's pose noise (per frame a correction $\\delta_f \\sim N(0, S)$,
`jaxcal._handeye.model.corrected_robot`'s convention, which moves every corner of the view
together) and the calibration's own error ($X = \\hat X \\exp(\\xi_X)$, $Y = \\hat Y
\\exp(\\xi_Y)$, $(\\xi_X, \\xi_Y) \\sim N(0, \\Sigma)$):

$$ R = s_0 I + \\sum_f G_f (S + \\mathrm{diag}(s_t I_3, s_r I_3)) G_f^T + J \\Sigma J^T, $$

$G_f = \\partial r / \\partial \\delta_f$, $J = \\partial r / \\partial (\\xi_X, \\xi_Y)$. Beside the
robot's noise $S$ (the calibration's), each view of the check may carry an error common to its
corners (the detector's view-dependent bias: a whole view moves), and the check images' noise
may differ from the calibration's $\\sigma^2$: $(s_0, s_t, s_r)$ are variance components estimated
from the check itself by restricted maximum likelihood with the drift a fixed effect
(`variance_components`), and the test takes Fisher's F on the $6 (F - 1)$ redundant view-pose
coordinates they rest on. A check has a few hundred corners, so $R$ is formed and factorised
densely ($R = L L^T$, $W = L^{-1}$), inside the compiled programs. Gauss-Newton on $W
r(\\varepsilon)$ gives $\\hat\\varepsilon$, its covariance $C$ and $T = \\hat\\varepsilon^T C^{-1}
\\hat\\varepsilon$, tested by `jaxcal.drift.verdict`.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from ._drift_camera import gauss_newton
from ._geometry import se3_exp
from ._handeye.data import HandEyePixels
from ._handeye.model import HandEyeParams, HandEyeReference, predicted_board_poses
from ._lsq import normal_inverse


class HandEyeCheckData(eqx.Module):
    """One camera's check capture: the robot poses `T_base_ee` `(frames, 4, 4)` (m),
    the undistorted corners `pixels` `(frames, points, 2)` (px) with `mask`, the
    pinhole `K` `(3, 3)`, the target's `board_points` `(points, 3)` (m), the arrangement."""

    T_base_ee: Float[Array, "frames 4 4"]
    pixels: Float[Array, "frames points 2"]
    mask: Bool[Array, "frames points"]
    K: Float[Array, "3 3"]
    board_points: Float[Array, "points 3"]
    eye_in_hand: Bool[Array, ""]


def _residuals(eps, xi, delta, X, Y, data: HandEyeCheckData):
    """Predicted minus detected corners (px) `(frames * points * 2,)`, zero where not detected;
    `xi` `(12,)`: the calibration's error $(\\xi_X, \\xi_Y)$; `delta` `(frames, 6)`: robot corrections."""
    params = HandEyeParams(cam_robot=xi[None, :6], robot_board=xi[6:], robot=delta)
    ref = HandEyeReference(X0=X[None], Y0=Y, active=data.mask.any(-1)[None])
    hand_eye = _as_pixels(data)
    A = se3_exp(-eps) @ predicted_board_poses(params, ref, hand_eye)[0]
    p = jnp.einsum("fij,pj->fpi", A[:, :3, :3], data.board_points) + A[:, None, :3, 3]
    z = jnp.where(p[..., 2:] > 1e-9, p[..., 2:], 1e-9)
    uv = p[..., :2] / z @ data.K[:2, :2].T + data.K[:2, 2]
    return jnp.where(data.mask[..., None], uv - data.pixels, 0.0).reshape(-1)


def _as_pixels(data: HandEyeCheckData):
    """The fields `predicted_board_poses` reads, as a `HandEyePixels`-shaped record."""
    return HandEyePixels(
        T_base_ee=data.T_base_ee,
        pixels=data.pixels[None],
        mask=data.mask[None],
        K=data.K[None],
        board_points=data.board_points,
        sigma_px=jnp.asarray(1.0),
        robot_sigma=None,
        eye_in_hand=data.eye_in_hand,
    )


#: Rounds of the variance components' fixed point (`variance_components`).
COMPONENT_ROUNDS = 25
#: Where the per-view components start: 0.1 mm and 0.1 mrad per axis.
VIEW_START = 1e-4


@jax.jit
def covariance_terms(X, Y, cov, robot_sigma, data: HandEyeCheckData):
    """The pieces of $R$ (see the module docstring), m = 2 frames points: the residuals at zero
    drift `r0` `(m,)` and their derivative by the camera's twist `A` `(m, 6)`; the known part
    `V_fixed` (robot noise and the calibration's error, unit variance on undetected entries); the
    detector's `V0` (1 on detected entries) and the per-view pose bases `Vt`, `Vr` (a frame's pose
    moved by 1 m or 1 rad along each axis)."""
    F = data.T_base_ee.shape[0]
    zero6, zero12, zeroF = jnp.zeros(6), jnp.zeros(12), jnp.zeros((F, 6))
    r0 = _residuals(zero6, zero12, zeroF, X, Y, data)
    A = jax.jacfwd(lambda e: _residuals(e, zero12, zeroF, X, Y, data))(zero6)
    J = jax.jacfwd(lambda xi: _residuals(zero6, xi, zeroF, X, Y, data))(zero12)
    G = jax.jacfwd(lambda d: _residuals(zero6, zero12, d, X, Y, data))(zeroF)  # (m, F, 6)
    Gs = G * robot_sigma
    seen = jnp.repeat(data.mask.reshape(-1), 2).astype(r0.dtype)
    V_fixed = jnp.einsum("afk,bfk->ab", Gs, Gs) + J @ cov @ J.T + jnp.diag(1.0 - seen)
    Vt = jnp.einsum("afk,bfk->ab", G[..., :3], G[..., :3])
    Vr = jnp.einsum("afk,bfk->ab", G[..., 3:], G[..., 3:])
    return r0, A, V_fixed, jnp.diag(seen), Vt, Vr


@jax.jit
def variance_components(r0, A, V_fixed, V0, Vt, Vr, sigma_px):
    """$R = s_0 V_0 + s_t V_t + s_r V_r + V_{fixed}$ with $(s_0, s_t, s_r)$ the detector's
    variance and each view's coherent pose error (translation, rotation; per axis) estimated by
    restricted maximum likelihood, the drift a fixed effect: the fixed point $s_c \\leftarrow s_c\\,
    r^T Q V_c Q r / \\mathrm{tr}(Q V_c)$, $Q = R^{-1} - R^{-1} A (A^T R^{-1} A)^{-1} A^T R^{-1}$
    (Foerstner's iteration, as the hand-eye solve estimates the robot's noise). **Returns:**
    `(R, s)`."""
    Vs = (V0, Vt, Vr)

    def step(s, _):
        R = s[0] * V0 + s[1] * Vt + s[2] * Vr + V_fixed
        Ri = jnp.linalg.inv(R)
        RiA = Ri @ A
        Q = Ri - RiA @ jnp.linalg.solve(A.T @ RiA, RiA.T)
        Qr = Q @ r0
        num = jnp.stack([Qr @ V @ Qr for V in Vs])
        den = jnp.stack([jnp.sum(Q * V) for V in Vs])
        return s * num / jnp.maximum(den, 1e-300), None

    s0 = jnp.stack([sigma_px**2, jnp.asarray(VIEW_START**2), jnp.asarray(VIEW_START**2)])
    s, _ = jax.lax.scan(step, s0, None, length=COMPONENT_ROUNDS)
    return s[0] * V0 + s[1] * Vt + s[2] * Vr + V_fixed, s


@jax.jit
def fit_handeye_drift(X, Y, R, data: HandEyeCheckData):
    """Gauss-Newton on $W r(\\varepsilon)$, $W = L^{-1}$ with $L L^T = R$ (`variance_components`).
    **Returns:** `(theta, C, T, rss)` as `jaxcal.drift.fit_drift` (theta: the camera's twist)."""
    F = data.T_base_ee.shape[0]
    L = jnp.linalg.cholesky(R)

    def res(eps):
        r = _residuals(eps, jnp.zeros(12), jnp.zeros((F, 6)), X, Y, data)
        return jax.scipy.linalg.solve_triangular(L, r, lower=True)

    theta, info, r = gauss_newton(res, 6)
    return theta, normal_inverse(info), theta @ info @ theta, r @ r
