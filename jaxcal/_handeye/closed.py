"""Closed-form hand-eye start: board poses by planar homography, then $A = X B Y$ by Shah's method."""

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from .._geometry import make_pose, pose_inverse
from .._linalg import nearest_rotation
from .checks import spanning_views
from .data import HandEyeData, HandEyePixels
from .model import robot_motion


def _plane_frame(points: Float[Array, "points 3"]) -> tuple[Float[Array, "4 4"], Float[Array, "points 2"]]:
    """`T_board_plane` (plane frame: z along the normal) and the points' plane coordinates."""
    c = jnp.mean(points, axis=0)
    _, V = jnp.linalg.eigh((points - c).T @ (points - c))
    e1, e2 = V[:, 2], V[:, 1]
    R = jnp.stack([e1, e2, jnp.cross(e1, e2)], axis=1)
    ab = (points - c) @ R[:, :2]
    return make_pose(R, c), ab


def _homography_pose(uv, w, K, ab, T_board_plane):
    """`T_cam_board` from one view by a normalised DLT homography and Zhang's decomposition."""
    # Normalised image coordinates (K is upper triangular: no factorisation needed).
    y = (uv[:, 1] - K[1, 2]) / K[1, 1]
    xy = jnp.stack([(uv[:, 0] - K[0, 2] - K[0, 1] * y) / K[0, 0], y], axis=1)
    wsum = jnp.maximum(jnp.sum(w), 1.0)
    mean_xy = jnp.sum(xy * w[:, None], 0) / wsum
    s_xy = jnp.sqrt(2.0) / jnp.maximum(jnp.sqrt(jnp.sum(jnp.sum((xy - mean_xy) ** 2, -1) * w) / wsum), 1e-12)
    mean_ab = jnp.sum(ab * w[:, None], 0) / wsum
    s_ab = jnp.sqrt(2.0) / jnp.maximum(jnp.sqrt(jnp.sum(jnp.sum((ab - mean_ab) ** 2, -1) * w) / wsum), 1e-12)
    x_n, a_n = (xy - mean_xy) * s_xy, (ab - mean_ab) * s_ab
    one, zero = jnp.ones_like(a_n[:, :1]), jnp.zeros((a_n.shape[0], 3))
    a1 = jnp.concatenate([a_n, one], axis=1)
    rows = (
        jnp.concatenate(
            [
                jnp.concatenate([a1, zero, -x_n[:, :1] * a1], axis=1),
                jnp.concatenate([zero, a1, -x_n[:, 1:] * a1], axis=1),
            ],
            axis=0,
        )
        * jnp.concatenate([w, w])[:, None]
    )
    _, V = jnp.linalg.eigh(rows.T @ rows)
    Hn = V[:, 0].reshape(3, 3)
    T_img_inv = jnp.array([[1.0 / s_xy, 0.0, mean_xy[0]], [0.0, 1.0 / s_xy, mean_xy[1]], [0.0, 0.0, 1.0]])
    T_pl = jnp.array([[s_ab, 0.0, -s_ab * mean_ab[0]], [0.0, s_ab, -s_ab * mean_ab[1]], [0.0, 0.0, 1.0]])
    H = T_img_inv @ Hn @ T_pl
    lam = 2.0 / (jnp.linalg.norm(H[:, 0]) + jnp.linalg.norm(H[:, 1]))
    lam = jnp.where(H[2, 2] < 0, -lam, lam)  # the board is in front of the camera
    r1, r2, t = lam * H[:, 0], lam * H[:, 1], lam * H[:, 2]
    R = nearest_rotation(jnp.stack([r1, r2, jnp.cross(r1, r2)], axis=1))
    return make_pose(R, t) @ pose_inverse(T_board_plane)


def board_poses_from_pixels(
    data: HandEyePixels,
) -> tuple[Float[Array, "cameras frames 4 4"], Bool[Array, "cameras frames"]]:
    """Per-view board poses by homography (closed form), and which views had enough corners
    spanning the board (`checks.spanning_views`)."""
    T_bp, ab = _plane_frame(data.board_points)
    w = data.mask.astype(jnp.float64)
    uv = jnp.where(data.mask[..., None], data.pixels, 0.0)
    pose = jax.vmap(
        lambda uv_c, w_c, K: jax.vmap(lambda u, ww: _homography_pose(u, ww, K, ab, T_bp))(uv_c, w_c)
    )
    A = pose(uv, w, data.K)
    ok = spanning_views(ab, data.mask, xp=jnp)  # corners on one line leave the homography free
    return jnp.where(ok[..., None, None], A, jnp.eye(4)), ok


def solve_axzb(
    A: Float[Array, "cameras frames 4 4"],
    B: Float[Array, "frames 4 4"],
    weight: Float[Array, "cameras frames"],
) -> tuple[Float[Array, "cameras 4 4"], Float[Array, "4 4"]]:
    """Closed form of $A_{cf} = X_c B_f Y$ for every camera's $X_c$ and the shared $Y$.

    Rotations (Shah's Kronecker method, several cameras sharing $W = Y^{-1}$):
    $R_{X_c} = R_{A} R_W R_B^T$ is linear in $R_W$, $\\mathrm{vec} R_{X_c} =
    M_{cf}\\,\\mathrm{vec} R_W$ with orthogonal $M_{cf}$; minimising
    $\\sum \\|M_{cf} w - x_c\\|^2$ at fixed $\\|w\\|$ gives $w$ = the top
    eigenvector of $\\sum_c n_c S_c^T S_c$ ($S_c$ the weighted mean of
    $M_{cf}$) and $x_c = S_c w$, both projected on SO(3). Translations:
    $R_A t_W - t_{X_c} = R_{X_c} t_B - t_A$ by least squares. Exact on
    noise-free data with rotations about two non-parallel axes.
    """
    C, F = weight.shape
    RA, RB = A[..., :3, :3], B[:, :3, :3]
    M = jnp.einsum("cfik,fjl->cfijkl", RA, RB).reshape(C, F, 9, 9)
    n_c = jnp.sum(weight, axis=1)
    S = jnp.einsum("cf,cfab->cab", weight, M) / jnp.maximum(n_c, 1e-300)[:, None, None]
    G = jnp.einsum("c,cba,cbd->ad", n_c, S, S)
    _, V = jnp.linalg.eigh(G)
    w = V[:, -1]
    w = jnp.where(jnp.linalg.det(w.reshape(3, 3)) < 0, -w, w)
    # R_W and every R_X in one batched SVD (see _linalg).
    R = nearest_rotation(jnp.concatenate([w[None], S @ w]).reshape(1 + C, 3, 3))
    R_W, R_X = R[0], R[1:]
    # Translations: unknowns (t_W, t_X1..t_XC).
    sel = jnp.eye(C)[:, None, :, None, None] * jnp.eye(3)  # (C, 1, C, 3, 3)
    J = jnp.concatenate(
        [RA[:, :, None], -jnp.broadcast_to(sel, (C, F, C, 3, 3))], axis=2
    )  # (C, F, 1 + C, 3, 3): blocks [R_A, -E_c]
    J = jnp.moveaxis(J, 2, 3).reshape(C, F, 3, 3 * (1 + C))
    b = jnp.einsum("cij,fj->cfi", R_X, B[:, :3, 3]) - A[..., :3, 3]
    Jw = J * jnp.sqrt(weight)[..., None, None]
    bw = b * jnp.sqrt(weight)[..., None]
    Jf, bf = Jw.reshape(-1, 3 * (1 + C)), bw.reshape(-1)
    z = jnp.linalg.solve(Jf.T @ Jf + 1e-12 * jnp.eye(3 * (1 + C)), Jf.T @ bf)
    W = make_pose(R_W, z[:3])
    X = jax.vmap(make_pose)(R_X, z[3:].reshape(C, 3))
    return X, pose_inverse(W)


def initialise_hand_eye(data: HandEyeData) -> tuple[Float[Array, "cameras 4 4"], Float[Array, "4 4"]]:
    """Closed-form start `(X, Y)`: homography board poses (pixels) then `solve_axzb`."""
    if isinstance(data, HandEyePixels):
        A, ok = board_poses_from_pixels(data)
    else:
        ok = data.mask
        A = jnp.where(ok[..., None, None], data.T_cam_board, jnp.eye(4))
    return solve_axzb(A, robot_motion(data.T_base_ee, data.eye_in_hand), ok.astype(jnp.float64))
