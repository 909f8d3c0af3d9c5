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
coordinates they rest on. $R$ is never formed: it is a diagonal plus, per frame, a rank-6 block
($G_f$'s columns) plus the rank-12 $J \\Sigma J^T$, so every solve with it goes through the
Woodbury identity (`CheckCovariance`), O(m) for m residuals where the dense $R$ cost O(m^3) a
round (m = 1344 for 16 views of a 42-corner board). Gauss-Newton on $r(\\varepsilon)$ weighted
by $R^{-1}$ gives $\\hat\\varepsilon$, its covariance $C$ and $T = \\hat\\varepsilon^T C^{-1}
\\hat\\varepsilon$, tested by `jaxcal.drift.verdict`.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from ._drift_camera import GN_STEPS
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


def residuals(eps, xi, delta, X, Y, data: HandEyeCheckData):
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


class CovarianceTerms(eqx.Module):
    """The pieces of $R$ (see the module docstring), m = 2 frames points, a frame's n = 2 points
    rows consecutive: the residuals at zero drift `r0` `(m,)` and their derivative by the camera's
    twist `A` `(m, 6)`; each frame's derivative by its own pose correction `G` `(frames, n, 6)` (a
    frame's pose moved by 1 m or 1 rad along each axis: $V_t$, $V_r$ and the robot's noise are
    block diagonal); the calibration's error as `H` `(m, 12)`, $H H^T = J \\Sigma J^T$; `seen` `(m,)`
    (1 on detected entries: $V_0$; undetected ones have unit variance and zero rows); the robot's
    pose variance `robot_var` `(6,)`."""

    r0: Float[Array, " m"]
    A: Float[Array, "m 6"]
    G: Float[Array, "frames n 6"]
    H: Float[Array, "m 12"]
    seen: Float[Array, " m"]
    robot_var: Float[Array, " 6"]


class CheckCovariance(eqx.Module):
    """$R = \\mathrm{diag}(d) + \\mathrm{blockdiag}_f(E_f E_f^T) + H H^T$ factorised for solves:
    $B = \\mathrm{diag}(d) + \\mathrm{blockdiag}_f(E_f E_f^T)$ by Woodbury within each frame
    (`Kc`: the Cholesky factors of $I_6 + E_f^T D^{-1} E_f$), then $R = B + H H^T$ by Woodbury
    again (`BiH` $= B^{-1} H$, `Cc`: the Cholesky factor of $I_{12} + H^T B^{-1} H$). A solve costs
    O(m 6^2 + m 12), never an m x m matrix."""

    d: Float[Array, "frames n"]
    E: Float[Array, "frames n 6"]
    Kc: Float[Array, "frames 6 6"]
    BiH: Float[Array, "m 12"]
    Cc: Float[Array, "12 12"]


def _block_solve(d, E, Kc, X: Float[Array, "frames n k"]) -> Float[Array, "frames n k"]:
    """$B^{-1} X$, frame by frame: $D^{-1} X - D^{-1} E K^{-1} E^T D^{-1} X$ (`CheckCovariance`)."""
    Z = X / d[..., None]
    t = jnp.einsum("fni,fnk->fik", E, Z)
    u = jax.vmap(lambda c, b: jax.scipy.linalg.cho_solve((c, True), b))(Kc, t)
    return Z - jnp.einsum("fni,fik->fnk", E / d[..., None], u)


def solve(cov: CheckCovariance, X: Float[Array, "m k"]) -> Float[Array, "m k"]:
    """$R^{-1} X$ (`CheckCovariance`)."""
    F, n = cov.d.shape
    Y = _block_solve(cov.d, cov.E, cov.Kc, X.reshape(F, n, -1)).reshape(X.shape)
    return Y - cov.BiH @ jax.scipy.linalg.cho_solve((cov.Cc, True), cov.BiH.T @ X)


def factor(terms: CovarianceTerms, s: Float[Array, " 3"]) -> CheckCovariance:
    """$R = s_0 V_0 + s_t V_t + s_r V_r + V_{fixed}$ of `terms` at the components `s`, factorised."""
    F, n, _ = terms.G.shape
    seen = terms.seen.reshape(F, n)
    d = s[0] * seen + (1.0 - seen)
    M = terms.robot_var + jnp.repeat(s[1:], 3)
    E = terms.G * jnp.sqrt(M)
    K = jnp.eye(6) + jnp.einsum("fni,fnj->fij", E / d[..., None], E)
    Kc = jnp.linalg.cholesky(K)
    BiH = _block_solve(d, E, Kc, terms.H.reshape(F, n, -1)).reshape(terms.H.shape)
    Cc = jnp.linalg.cholesky(jnp.eye(12) + terms.H.T @ BiH)
    return CheckCovariance(d, E, Kc, BiH, Cc)


@jax.jit
def covariance_terms(X, Y, cov, robot_sigma, data: HandEyeCheckData) -> CovarianceTerms:
    """The `CovarianceTerms` of a check capture against the calibrated `X`, `Y` with covariance
    `cov` `(12, 12)` and robot pose noise `robot_sigma` `(6,)`. A frame's residuals depend on its
    own robot correction only, so one correction shared by all frames gives each frame's block."""
    F, P = data.mask.shape
    zero6, zero12, zeroF = jnp.zeros(6), jnp.zeros(12), jnp.zeros((F, 6))
    r0 = residuals(zero6, zero12, zeroF, X, Y, data)
    A = jax.jacfwd(lambda e: residuals(e, zero12, zeroF, X, Y, data))(zero6)
    J = jax.jacfwd(lambda xi: residuals(zero6, xi, zeroF, X, Y, data))(zero12)
    G = jax.jacfwd(lambda d: residuals(zero6, zero12, jnp.broadcast_to(d, (F, 6)), X, Y, data))(zero6)
    w, V = jnp.linalg.eigh(0.5 * (cov + cov.T))
    H = J @ (V * jnp.sqrt(jnp.maximum(w, 0.0)))
    seen = jnp.repeat(data.mask.reshape(-1), 2).astype(r0.dtype)
    return CovarianceTerms(r0, A, G.reshape(F, 2 * P, 6), H, seen, robot_sigma**2)


def _projected(cov: CheckCovariance, terms: CovarianceTerms):
    """$Q r$, $\\mathrm{diag}(Q)$ and each frame's $\\mathrm{diag}(G_f^T Q_{ff} G_f)$ `(frames, 6)`
    with $Q = R^{-1} - R^{-1} A (A^T R^{-1} A)^{-1} A^T R^{-1} = B^{-1} - Z Z^T$, $Z = [B^{-1} H
    C_c^{-T}, R^{-1} A S_c^{-T}]$ ($S_c$ the Cholesky factor of $A^T R^{-1} A$)."""
    F, n, _ = terms.G.shape
    tri = jax.scipy.linalg.solve_triangular
    RiA = solve(cov, terms.A)
    Sc = jnp.linalg.cholesky(0.5 * (terms.A.T @ RiA + RiA.T @ terms.A))
    # X L^{-T} as X times the small triangle's inverse: XLA's triangular solve with m right-hand
    # sides costs 8 ms at m = 1344, the product 0.05 ms.
    Z = jnp.concatenate(
        [cov.BiH @ tri(cov.Cc, jnp.eye(12), lower=True).T, RiA @ tri(Sc, jnp.eye(6), lower=True).T], axis=1
    )
    Bir = _block_solve(cov.d, cov.E, cov.Kc, terms.r0.reshape(F, n, 1)).reshape(-1)
    Qr = Bir - Z @ (Z.T @ terms.r0)
    W = tri(cov.Kc, jnp.swapaxes(cov.E / cov.d[..., None], 1, 2), lower=True)  # (F, 6, n)
    diag_Q = (1.0 / cov.d - jnp.sum(W**2, axis=1)).reshape(-1) - jnp.sum(Z**2, axis=1)
    BiG = _block_solve(cov.d, cov.E, cov.Kc, terms.G)
    GZ = jnp.einsum("fni,fnk->fik", terms.G, Z.reshape(F, n, -1))
    diag_G = jnp.sum(terms.G * BiG, axis=1) - jnp.sum(GZ**2, axis=2)
    return Qr, diag_Q, diag_G


@jax.jit
def variance_components(terms: CovarianceTerms, sigma_px) -> tuple[CheckCovariance, Float[Array, " 3"]]:
    """$R = s_0 V_0 + s_t V_t + s_r V_r + V_{fixed}$ with $(s_0, s_t, s_r)$ the detector's
    variance and each view's coherent pose error (translation, rotation; per axis) estimated by
    restricted maximum likelihood, the drift a fixed effect: the fixed point $s_c \\leftarrow s_c\\,
    r^T Q V_c Q r / \\mathrm{tr}(Q V_c)$, $Q = R^{-1} - R^{-1} A (A^T R^{-1} A)^{-1} A^T R^{-1}$
    (Foerstner's iteration, as the hand-eye solve estimates the robot's noise), each round on the
    factors of `CheckCovariance` (O(m), no m x m matrix). **Returns:** `(R factorised, s)`."""
    F, n, _ = terms.G.shape

    def step(s, _):
        Qr, diag_Q, diag_G = _projected(factor(terms, s), terms)
        GQr = jnp.einsum("fni,fn->fi", terms.G, Qr.reshape(F, n))
        num = jnp.stack([jnp.sum(terms.seen * Qr**2), jnp.sum(GQr[:, :3] ** 2), jnp.sum(GQr[:, 3:] ** 2)])
        den = jnp.stack([jnp.sum(terms.seen * diag_Q), jnp.sum(diag_G[:, :3]), jnp.sum(diag_G[:, 3:])])
        return s * num / jnp.maximum(den, 1e-300), None

    s0 = jnp.stack([sigma_px**2, jnp.asarray(VIEW_START**2), jnp.asarray(VIEW_START**2)])
    s, _ = jax.lax.scan(step, s0, None, length=COMPONENT_ROUNDS)
    return factor(terms, s), s


@jax.jit
def fit_handeye_drift(X, Y, R: CheckCovariance, data: HandEyeCheckData):
    """Gauss-Newton on $r(\\varepsilon)$ weighted by $R^{-1}$ (`variance_components`; the steps of
    `jaxcal._drift_camera.gauss_newton` on $W r$, $W^T W = R^{-1}$, without forming $W$).
    **Returns:** `(theta, C, T, rss)` as `jaxcal.drift.fit_drift` (theta: the camera's twist)."""
    F = data.T_base_ee.shape[0]

    def weighted(eps):
        r = residuals(eps, jnp.zeros(12), jnp.zeros((F, 6)), X, Y, data)
        A = jax.jacfwd(lambda e: residuals(e, jnp.zeros(12), jnp.zeros((F, 6)), X, Y, data))(eps)
        Ri = solve(R, jnp.concatenate([r[:, None], A], axis=1))
        AtRiA = A.T @ Ri[:, 1:]
        return 0.5 * (AtRiA + AtRiA.T), A.T @ Ri[:, 0], r @ Ri[:, 0]

    def step(theta, _):
        H, g, _ = weighted(theta)
        return theta + jnp.linalg.solve(H, -g), None

    theta, _ = jax.lax.scan(step, jnp.zeros(6), None, length=GN_STEPS)
    weight, _, rss = weighted(theta)
    return theta, normal_inverse(weight), theta @ weight @ theta, rss
