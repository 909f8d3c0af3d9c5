"""Rigid-body geometry: SO(3)/SE(3) maps and 3D lines.

Poses are 4x4 homogeneous matrices named `T_a_b` (maps points from frame b into
frame a). Rotations are 3x3 matrices. Every map is safe to differentiate at the
singular points that calibration lives on (zero rotation, parallel lines): the
small-angle branches are Taylor series selected with `jnp.where`, with the
argument of the unused branch replaced so that no NaN leaks into gradients.
"""

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

_SMALL = 1e-6


def skew(w: Float[Array, "*B 3"]) -> Float[Array, "*B 3 3"]:
    """The matrix $[w]_\\times$ with $[w]_\\times v = w \\times v$.

    One concatenation of slices: nine operations where nested stacks of scalars
    take thirty, in a function that every rotation traces (`so3_exp`); programs
    trace and compile in proportion to their operations."""
    w0, w1, w2 = w[..., 0:1], w[..., 1:2], w[..., 2:3]
    zero = jnp.zeros_like(w0)
    K = jnp.concatenate([zero, -w2, w1, w2, zero, -w0, -w1, w0, zero], axis=-1)
    return K.reshape(w.shape[:-1] + (3, 3))


def safe_norm(x: Float[Array, "... n"], axis: int = -1) -> Float[Array, "..."]:
    """Euclidean norm whose gradient is zero (not NaN) at the origin."""
    sq = jnp.sum(x * x, axis=axis)
    is_zero = sq == 0.0
    return jnp.where(is_zero, 0.0, jnp.sqrt(jnp.where(is_zero, 1.0, sq)))


def normalize(x: Float[Array, "... n"]) -> Float[Array, "... n"]:
    """Unit vector along `x` (safe at zero, where it returns zero)."""
    n = safe_norm(x)
    return x / jnp.where(n == 0.0, 1.0, n)[..., None]


def matmul(A: Float[Array, "... n k"], B: Float[Array, "... k m"]) -> Float[Array, "... n m"]:
    """Batched product of small matrices as broadcast-and-sum.

    For 3x3 and 4x4 blocks XLA fuses this into the surrounding elementwise
    code, where a batched `dot_general` is several times slower on CPU. Under
    batched forward-mode products (`vmap` of `jvp`) the reduction can instead
    become one slow fused reduction: `matmul_unrolled` there (measure).
    """
    return jnp.sum(A[..., :, :, None] * B[..., None, :, :], axis=-2)


def matvec(A: Float[Array, "... n k"], x: Float[Array, "... k"]) -> Float[Array, "... n"]:
    """Batched small matrix-vector product (see `matmul`)."""
    return jnp.sum(A * x[..., None, :], axis=-1)


def matmul_unrolled(A: Float[Array, "... n k"], B: Float[Array, "... k m"]) -> Float[Array, "... n m"]:
    """Batched product of small matrices as `k` broadcast multiply-adds (no reduction).

    Same product as `matmul`; XLA's CPU backend fuses the unrolled sum into a
    plain elementwise loop, several times faster than the reduction for the
    6x6 whitening and 3x3 blocks of a residual Jacobian over many frames.
    """
    out = A[..., :, 0, None] * B[..., 0, None, :]
    for j in range(1, A.shape[-1]):
        out = out + A[..., :, j, None] * B[..., j, None, :]
    return out


def matvec_unrolled(A: Float[Array, "... n k"], x: Float[Array, "... k"]) -> Float[Array, "... n"]:
    """Batched small matrix-vector product as `k` multiply-adds (see `matmul_unrolled`)."""
    out = A[..., :, 0] * x[..., 0, None]
    for j in range(1, A.shape[-1]):
        out = out + A[..., :, j] * x[..., j, None]
    return out


def matmul_lanes(A: Float[Array, "n k s"], B: Float[Array, "k m s"]) -> Float[Array, "n m s"]:
    """Small matrix products with the batch *last* (`(n, k, S)`, or `(n, k, 1)` for one
    matrix broadcast over the batch), as `k` multiply-adds over `S`-long lanes.

    The layout of a residual Jacobian assembled for its normal equations: every
    elementwise operation runs over contiguous samples, and $J^TJ$ contracts
    the minor axis, where XLA's CPU backend is fastest.
    """
    out = A[:, 0, None] * B[None, 0]
    for j in range(1, A.shape[1]):
        out = out + A[:, j, None] * B[None, j]
    return out


def matvec_lanes(A: Float[Array, "n k s"], x: Float[Array, "k s"]) -> Float[Array, "n s"]:
    """Small matrix-vector products with the batch last (see `matmul_lanes`)."""
    out = A[:, 0] * x[0]
    for j in range(1, A.shape[1]):
        out = out + A[:, j] * x[j]
    return out


def cross_lanes(a: Float[Array, "3 s"], b: Float[Array, "3 s"]) -> Float[Array, "3 s"]:
    """Cross products with the batch last (see `matmul_lanes`)."""
    return jnp.stack([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


# Nested jit (see `jaxcal._arcmodel.arc_terms`): a program traces the exponential
# once per signature, not at each of its dozens of uses (a Monte Carlo trial traces
# about a fifth faster; the same values).
@jax.jit
def so3_exp(w: Float[Array, "3"]) -> Float[Array, "3 3"]:
    """Rodrigues' formula $\\exp([w]_\\times)$ for a rotation vector `w` (rad)."""
    theta_sq = _norm_sq(w)
    small = theta_sq < _SMALL**2
    safe_sq = jnp.where(small, 1.0, theta_sq)
    theta = jnp.sqrt(safe_sq)
    a = jnp.where(small, 1.0 - theta_sq / 6.0, jnp.sin(theta) / theta)
    b = jnp.where(small, 0.5 - theta_sq / 24.0, (1.0 - jnp.cos(theta)) / safe_sq)
    return a * skew(w) + _skew_sq_plus(w, theta_sq, b, 1.0)


def _norm_sq(w: Float[Array, "3"]) -> Float[Array, ""]:
    # Elementwise, as `_skew_sq_plus`: no reduction for XLA to fuse.
    return w[0] * w[0] + w[1] * w[1] + w[2] * w[2]


def _skew_sq_plus(w: Float[Array, "3"], theta_sq, b, c) -> Float[Array, "3 3"]:
    """$b\\,[w]_\\times^2 + c I$ by $[w]_\\times^2 = ww^T - \\|w\\|^2 I$: elementwise, where
    `K @ K` is a batched 3x3 product under `vmap`, which XLA's CPU backend (jaxlib 0.10) fuses
    into a slow reduction, a noticeable share of the noisy-robot hand-eye solve's step
    (docs/performance.md, Hand-eye)."""
    return b * (w[:, None] * w[None, :]) + (c - b * theta_sq) * jnp.eye(3, dtype=w.dtype)


def so3_log(R: Float[Array, "... 3 3"]) -> Float[Array, "... 3"]:
    """Rotation vector of `R` (inverse of `so3_exp`), accurate near identity.

    Uses $\\theta = \\mathrm{atan2}(\\|s\\|, c)$ with $s = \\mathrm{vee}(R - R^T)/2$,
    $c = (\\mathrm{tr} R - 1)/2$, which is well conditioned everywhere except
    within ~1e-8 rad of $\\pi$ (never the case for calibration residuals).
    """
    s = 0.5 * jnp.stack(
        [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], axis=-1
    )
    c = 0.5 * (R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2] - 1.0)
    sin_theta = safe_norm(s)
    theta = jnp.arctan2(sin_theta, c)
    small = sin_theta < _SMALL
    safe_sin = jnp.where(small, 1.0, sin_theta)
    # theta / sin(theta) -> 1 + theta^2 / 6 as theta -> 0.
    scale = jnp.where(small, 1.0 + sin_theta**2 / 6.0, theta / safe_sin)[..., None]
    return scale * s


def so3_right_jacobian(w: Float[Array, "3"]) -> Float[Array, "3 3"]:
    """Right Jacobian $J_r(w)$ of `so3_exp`: $\\exp(w + \\delta) \\approx \\exp(w)\\exp(J_r(w)\\,\\delta)$.

    $J_r = I - \\frac{1 - \\cos\\theta}{\\theta^2}[w]_\\times
    + \\frac{\\theta - \\sin\\theta}{\\theta^3}[w]_\\times^2$ (Barfoot, *State
    Estimation for Robotics*, eq. 7.87, with the sign of the right Jacobian).
    """
    theta_sq = jnp.dot(w, w)
    small = theta_sq < _SMALL**2
    safe_sq = jnp.where(small, 1.0, theta_sq)
    theta = jnp.sqrt(safe_sq)
    b = jnp.where(small, 0.5 - theta_sq / 24.0, (1.0 - jnp.cos(theta)) / safe_sq)
    c = jnp.where(small, 1.0 / 6.0 - theta_sq / 120.0, (theta - jnp.sin(theta)) / (safe_sq * theta))
    K = skew(w)
    return jnp.eye(3, dtype=w.dtype) - b * K + c * (K @ K)


def so3_right_jacobian_inv(w: Float[Array, "... 3"]) -> Float[Array, "... 3 3"]:
    """Inverse right Jacobian: $\\log(\\exp(w)\\exp(\\delta)) \\approx w + J_r^{-1}(w)\\,\\delta$.

    $J_r^{-1} = I + \\tfrac12[w]_\\times + \\frac{1 - (\\theta/2)\\cot(\\theta/2)}{\\theta^2}[w]_\\times^2$,
    finite for $\\theta \\in [0, \\pi]$ (the range of `so3_log`). Batched over leading axes.
    """
    theta_sq = jnp.sum(w * w, axis=-1)
    # The closed form cancels to ~1e-16 / theta^2 relative error: Taylor below 0.01 rad.
    small = theta_sq < 1e-4
    safe_sq = jnp.where(small, 1.0, theta_sq)
    half = 0.5 * jnp.sqrt(safe_sq)
    d = jnp.where(
        small,
        1.0 / 12.0 + theta_sq / 720.0 + theta_sq**2 / 30240.0,
        (1.0 - half * jnp.cos(half) / jnp.sin(half)) / safe_sq,
    )
    zero = jnp.zeros_like(w[..., 0])
    K = jnp.stack(
        [
            jnp.stack([zero, -w[..., 2], w[..., 1]], axis=-1),
            jnp.stack([w[..., 2], zero, -w[..., 0]], axis=-1),
            jnp.stack([-w[..., 1], w[..., 0], zero], axis=-1),
        ],
        axis=-2,
    )
    KK = w[..., :, None] * w[..., None, :] - theta_sq[..., None, None] * jnp.eye(3, dtype=w.dtype)
    return jnp.eye(3, dtype=w.dtype) + 0.5 * K + d[..., None, None] * KK


def rotation_about(axis: Float[Array, "3"], angle: Float[Array, ""]) -> Float[Array, "3 3"]:
    """Rotation by `angle` (rad) about the unit vector `axis`."""
    return so3_exp(axis * angle)


def make_pose(R: Float[Array, "3 3"], t: Float[Array, "3"]) -> Float[Array, "4 4"]:
    """Homogeneous 4x4 matrix from a rotation and a translation."""
    top = jnp.concatenate([R, t[:, None]], axis=1)
    bottom = jnp.array([[0.0, 0.0, 0.0, 1.0]], dtype=top.dtype)
    return jnp.concatenate([top, bottom], axis=0)


def pose_inverse(T: Float[Array, "4 4"]) -> Float[Array, "4 4"]:
    """Inverse of a rigid transform."""
    R, t = T[:3, :3], T[:3, 3]
    return make_pose(R.T, -R.T @ t)


# Nested jit, as `so3_exp`.
@jax.jit
def se3_exp(xi: Float[Array, "6"]) -> Float[Array, "4 4"]:
    """Exponential map of a twist `xi = (v, w)` (translation first, m and rad).

    $\\exp\\begin{pmatrix}[w]_\\times & v\\\\0&0\\end{pmatrix}$ with the left
    Jacobian $V(w)$ applied to `v`.
    """
    v, w = xi[:3], xi[3:]
    theta_sq = _norm_sq(w)
    small = theta_sq < _SMALL**2
    safe_sq = jnp.where(small, 1.0, theta_sq)
    theta = jnp.sqrt(safe_sq)
    b = jnp.where(small, 0.5 - theta_sq / 24.0, (1.0 - jnp.cos(theta)) / safe_sq)
    c = jnp.where(small, 1.0 / 6.0 - theta_sq / 120.0, (theta - jnp.sin(theta)) / (safe_sq * theta))
    V = b * skew(w) + _skew_sq_plus(w, theta_sq, c, 1.0)
    return make_pose(so3_exp(w), V[:, 0] * v[0] + V[:, 1] * v[1] + V[:, 2] * v[2])


def se3_log(T: Float[Array, "4 4"]) -> Float[Array, "6"]:
    """Twist `(v, w)` of a rigid transform (inverse of `se3_exp`)."""
    w = so3_log(T[:3, :3])
    theta_sq = jnp.dot(w, w)
    small = theta_sq < _SMALL**2
    safe_sq = jnp.where(small, 1.0, theta_sq)
    theta = jnp.sqrt(safe_sq)
    half = 0.5 * theta
    # V^{-1} = I - K/2 + (1/theta^2)(1 - (theta/2) cot(theta/2)) K^2
    d = jnp.where(
        small,
        1.0 / 12.0 + theta_sq / 720.0,
        (1.0 - half * jnp.cos(half) / jnp.sin(half)) / safe_sq,
    )
    K = skew(w)
    V_inv = jnp.eye(3, dtype=T.dtype) - 0.5 * K + d * (K @ K)
    return jnp.concatenate([V_inv @ T[:3, 3], w])


def rpy_to_matrix(rpy: Float[Array, "3"]) -> Float[Array, "3 3"]:
    """URDF roll-pitch-yaw (fixed axes X, Y, Z): $R = R_z(y) R_y(p) R_x(r)$."""
    r, p, y = rpy[0], rpy[1], rpy[2]
    cr, sr, cp, sp, cy, sy = jnp.cos(r), jnp.sin(r), jnp.cos(p), jnp.sin(p), jnp.cos(y), jnp.sin(y)
    return jnp.stack(
        [
            jnp.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr]),
            jnp.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr]),
            jnp.stack([-sp, cp * sr, cp * cr]),
        ]
    )


def matrix_to_rpy(R: Float[Array, "*batch 3 3"], xp=jnp) -> Float[Array, "*batch 3"]:
    """Inverse of `rpy_to_matrix` (pitch in [-pi/2, pi/2]), of one rotation or a stack; `xp=np`
    computes it in NumPy (host code that writes files compiles nothing).

    At gimbal lock (pitch = +-pi/2) only roll -+ yaw is defined; yaw is then
    chosen so that the rebuilt matrix is exact with the roll from `R`.
    """

    def r(a, b):
        return R[..., a, b]

    cp = xp.sqrt(r(0, 0) ** 2 + r(1, 0) ** 2)
    pitch = xp.arctan2(-r(2, 0), cp)
    locked = cp < 1e-10
    roll_free = xp.arctan2(r(2, 1), r(2, 2))
    yaw_free = xp.arctan2(r(1, 0), r(0, 0))
    # Locked: R[0,1] = sin(p) sin(r) cos(y) - sin(y) cos(r), R[1,1] = sin(p) sin(r) sin(y) + cos(y) cos(r).
    roll_locked = xp.where((r(2, 1) == 0) & (r(2, 2) == 0), 0.0, roll_free)
    yaw_locked = xp.where(
        r(2, 0) < 0,
        roll_locked - xp.arctan2(r(0, 1), r(1, 1)),  # pitch = +pi/2
        xp.arctan2(-r(0, 1), r(1, 1)) - roll_locked,  # pitch = -pi/2
    )
    roll = xp.where(locked, 0.0, roll_free)
    yaw = xp.where(locked, yaw_locked - roll_locked, yaw_free)
    return xp.stack([roll, pitch, yaw], axis=-1)


def orthonormal_basis(v: Float[Array, "3"]) -> Float[Array, "3 2"]:
    """Two unit vectors completing the unit vector `v` to a right-handed frame.

    Smooth except where `v` flips hemisphere about its largest component; the
    estimators only evaluate it at a fixed reference direction.
    """
    # Pick the coordinate axis least aligned with v.
    idx = jnp.argmin(jnp.abs(v))
    e = jnp.zeros(3, dtype=v.dtype).at[idx].set(1.0)
    b1 = normalize(jnp.cross(v, e))
    b2 = jnp.cross(v, b1)
    return jnp.stack([b1, b2], axis=1)


def frame_from_z(v: Float[Array, "3"]) -> Float[Array, "3 3"]:
    """A rotation matrix whose third column is the unit vector `v`."""
    B = orthonormal_basis(v)
    return jnp.concatenate([B, v[:, None]], axis=1)


def line_distance(
    p1: Float[Array, "3"], d1: Float[Array, "3"], p2: Float[Array, "3"], d2: Float[Array, "3"]
) -> Float[Array, ""]:
    """Smallest distance between two infinite lines (point, unit direction).

    $d = |(p_2 - p_1) \\cdot (d_1 \\times d_2)| / \\|d_1 \\times d_2\\|$, and for
    (near-)parallel lines the distance of $p_2$ from line 1, blended smoothly
    so the result is continuous as the lines become parallel.
    """
    n = jnp.cross(d1, d2)
    n_norm = safe_norm(n)
    dp = p2 - p1
    parallel_dist = safe_norm(dp - jnp.dot(dp, d1) * d1)
    skew_dist = jnp.abs(jnp.dot(dp, n)) / jnp.where(n_norm < 1e-9, 1.0, n_norm)
    return jnp.where(n_norm < 1e-9, parallel_dist, skew_dist)


def direction_difference(d1: Float[Array, "3"], d2: Float[Array, "3"]) -> Float[Array, ""]:
    """Angle (rad) between two line directions, sign-agnostic (lines, not vectors)."""
    c = jnp.abs(jnp.dot(d1, d2))
    s = safe_norm(jnp.cross(d1, d2))
    return jnp.arctan2(s, c)
