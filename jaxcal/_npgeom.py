"""Rotations and poses in NumPy, for what runs outside compiled programs: file I/O,
simulation, scene layout and checks of results (the compiled maths has its JAX
twins in `jaxcal._geometry`).

Conventions as everywhere in jaxcal: rotation vectors in rad, quaternions in
(x, y, z, w) order with $w \\ge 0$, 4x4 homogeneous poses.
"""

import numpy as np


def skew(v) -> np.ndarray:
    """Cross-product matrices: `(..., 3)` -> `(..., 3, 3)`, $[v]_\\times u = v \\times u$."""
    v = np.asarray(v, np.float64)
    z = np.zeros(v.shape[:-1])
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    return np.stack([np.stack([z, -w, y], -1), np.stack([w, z, -x], -1), np.stack([-y, x, z], -1)], -2)


def axis_rotation(axis, angle) -> np.ndarray:
    """Rodrigues' rotations about `axis` (normalised here) by `angle` (rad, a scalar
    or `(...)`): `(3, 3)` or `(..., 3, 3)`."""
    axis = np.asarray(axis, np.float64)
    K = skew(axis / np.linalg.norm(axis))
    angle = np.asarray(angle, np.float64)
    s, c = np.sin(angle)[..., None, None], np.cos(angle)[..., None, None]
    return np.eye(3) + s * K + ((1 - c) * K) @ K


def rotvec_to_matrix(w) -> np.ndarray:
    """Rodrigues' formula for rotation vectors, `(..., 3)` rad -> `(..., 3, 3)`."""
    w = np.asarray(w, np.float64)
    theta = np.linalg.norm(w, axis=-1)[..., None, None]
    Kx = skew(w)
    small = theta < 1e-8
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    return np.eye(3) + a * Kx + b * (Kx @ Kx)


def se3_exp(xi) -> np.ndarray:
    """`jaxcal._geometry.se3_exp` in NumPy: the pose of a twist `(v, w)` (translation first,
    m and rad), `(4, 4)`."""
    xi = np.asarray(xi, np.float64)
    v, w = xi[:3], xi[3:]
    theta, K = np.linalg.norm(w), skew(w)
    if theta < 1e-8:
        V = np.eye(3) + 0.5 * K + (K @ K) / 6.0
    else:
        V = np.eye(3) + (1.0 - np.cos(theta)) / theta**2 * K + (theta - np.sin(theta)) / theta**3 * (K @ K)
    return pose(rotvec_to_matrix(w), V @ v)


def rotation_angle(R) -> np.ndarray:
    """Rotation angle of `(..., 3, 3)` rotations (rad), accurate near 0 and pi."""
    R = np.asarray(R, np.float64)
    s = 0.5 * np.linalg.norm(_antisymmetric(R), axis=-1)
    c = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    return np.arctan2(s, c)


def _antisymmetric(R: np.ndarray) -> np.ndarray:
    """$(R_{32} - R_{23}, R_{13} - R_{31}, R_{21} - R_{12})$, `(..., 3)`."""
    return np.stack(
        [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1
    )


def so3_log(R) -> np.ndarray:
    """Rotation vectors of `(..., 3, 3)` rotations (rad), `(..., 3)`; near pi, where
    the antisymmetric part vanishes, the axis comes from $R + I$."""
    R = np.asarray(R, np.float64)
    s = 0.5 * _antisymmetric(R)
    c = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    sn = np.linalg.norm(s, axis=-1)
    theta = np.arctan2(sn, c)
    near_pi = (sn < 1e-6) & (c < 0)
    scale = np.where(sn < 1e-12, 1.0, theta / np.where(sn < 1e-12, 1.0, sn))
    w = scale[..., None] * s
    if np.any(near_pi):
        B = (R[near_pi] + np.eye(3)) / 2.0
        col = np.argmax(np.linalg.norm(B, axis=-2), axis=-1)
        axis = B[np.arange(len(col)), :, col]
        w[near_pi] = np.pi * axis / np.linalg.norm(axis, axis=-1, keepdims=True)
    return w


def quaternion_to_matrix(q_xyzw) -> np.ndarray:
    """Rotation matrices `(..., 3, 3)` of unit quaternions `(..., 4)` in (x, y, z, w) order."""
    x, y, z, w = np.moveaxis(np.asarray(q_xyzw, np.float64), -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def matrix_to_quaternion(R) -> np.ndarray:
    """Unit quaternions (x, y, z, w), `w >= 0`, of rotation matrices `(..., 3, 3)` -> `(..., 4)`
    (Shepperd's method: each from the largest of the trace and the diagonal)."""
    R = np.asarray(R, np.float64)
    t = np.trace(R, axis1=-2, axis2=-1)
    k = np.argmax(np.stack([t, R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]], -1), axis=-1)
    out = np.zeros((*R.shape[:-2], 4))
    with np.errstate(invalid="ignore", divide="ignore"):
        s = 2.0 * np.sqrt(np.maximum(1.0 + t, 0.0))
        w = [
            (R[..., 2, 1] - R[..., 1, 2]) / s,
            (R[..., 0, 2] - R[..., 2, 0]) / s,
            (R[..., 1, 0] - R[..., 0, 1]) / s,
        ]
        cases = [np.stack([*w, 0.25 * s], -1)]
        for i in range(3):
            j, m = (i + 1) % 3, (i + 2) % 3
            s = 2.0 * np.sqrt(np.maximum(1.0 + R[..., i, i] - R[..., j, j] - R[..., m, m], 0.0))
            q = [None] * 4
            q[3] = (R[..., m, j] - R[..., j, m]) / s
            q[i], q[j], q[m] = 0.25 * s, (R[..., j, i] + R[..., i, j]) / s, (R[..., m, i] + R[..., i, m]) / s
            cases.append(np.stack(q, -1))
    for c, q in enumerate(cases):
        out = np.where((k == c)[..., None], q, out)
    return np.where(out[..., 3:] >= 0, out, -out)


def nearest_rotation(M) -> np.ndarray:
    """The rotation nearest `M` `(3, 3)` in the Frobenius norm (Procrustes, by the SVD)."""
    U, _, Vt = np.linalg.svd(np.asarray(M, np.float64))
    return U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt


def fit_sandwich(R, F, A, B=None, rounds: int = 20) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rotations $A$, $B$ with $R_i \\approx A F_i B$ for rotations `R`, `F` `(N, 3, 3)` (a
    fixed frame's and a mount's, around a chain's link rotations), least squares by alternating
    Procrustes from `A` (`B` held when given). **Returns:** `(A, B, each row's misfit angle (rad))`."""
    R, F, A = (np.asarray(a, np.float64) for a in (R, F, A))
    held = B is not None
    for _ in range(1 if held else rounds):
        if not held:
            B = nearest_rotation(np.einsum("nba,nbc->ac", A @ F, R))
        A = nearest_rotation(np.einsum("nab,ncb->ac", R, F @ B))
    return A, B, rotation_angle(np.einsum("nba,nbc->nac", A @ F @ B, R))


def pose(R=None, t=(0.0, 0.0, 0.0)) -> np.ndarray:
    """The 4x4 pose of a rotation `R` (identity when None) and translation `t`."""
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R
    T[:3, 3] = np.asarray(t, np.float64).ravel()
    return T


def pose_inverse(T) -> np.ndarray:
    """The inverse of `(..., 4, 4)` rigid poses: $[R^T, -R^T t]$."""
    T = np.asarray(T, np.float64)
    R_t = np.swapaxes(T[..., :3, :3], -1, -2)
    out = np.zeros_like(T)
    out[..., :3, :3] = R_t
    out[..., :3, 3] = -np.einsum("...ab,...b->...a", R_t, T[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def line_distance(p1, d1, p2, d2) -> float:
    """Smallest distance between two lines (point, unit direction): along their common
    normal, or for (near-)parallel lines the distance of `p2` from line 1 (as
    `jaxcal._geometry.line_distance`)."""
    p1, d1, p2, d2 = (np.asarray(a, np.float64) for a in (p1, d1, p2, d2))
    n = np.cross(d1, d2)
    n_norm = float(np.linalg.norm(n))
    dp = p2 - p1
    if n_norm < 1e-9:
        return float(np.linalg.norm(dp - np.dot(dp, d1) * d1))
    return abs(float(np.dot(dp, n))) / n_norm


def kabsch(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """The rigid transform $T$ minimising $\\sum \\|T a_i - b_i\\|^2$ (NumPy; points `(n, 3)`)."""
    ca, cb = A.mean(0), B.mean(0)
    U, _, Vt = np.linalg.svd((A - ca).T @ (B - cb))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, cb - R @ ca
    return T
