"""Input checks shared by the hand-eye and TCP-touch data (NumPy, outside jit; `spanning_views` also traces)."""

import numpy as np

from .._npgeom import so3_log
from ..errors import (
    DegenerateMotionError,
    IntrinsicsError,
    NoiseLevelError,
    NonFiniteError,
    NotARotationError,
    ShapeError,
)

MIN_POSES = 3
MIN_ROTATION_DEG = 5.0
MIN_AXIS_SEPARATION_DEG = 5.0
MIN_POINTS_PER_VIEW = 4
#: A view's corners must span the board's plane: the smaller principal spread of
#: their plane coordinates at least this fraction of the larger. Corners on one
#: line (one row of a partly hidden board) leave its homography, and so the
#: view's closed-form pose, undetermined.
MIN_VIEW_SPREAD_RATIO = 1e-3
_ROTATION_TOL = 1e-6


def plane_frame(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`(R_board_plane (3, 3), ab (points, 2))`: the best-fit plane of (nearly) coplanar board
    points (z along its normal) and the points' coordinates in it, about their centroid."""
    d = points - points.mean(0)
    _, V = np.linalg.eigh(d.T @ d)
    U = np.stack([V[:, 2], V[:, 1], np.cross(V[:, 2], V[:, 1])], axis=1)
    return U, d @ U[:, :2]


def spanning_views(ab, mask, xp=np):
    """Which views have at least `MIN_POINTS_PER_VIEW` corners spanning the plane.

    `ab` `(points, 2)`: the board points' coordinates in the board's plane;
    `mask` `(..., points)`. NumPy or, with `xp=jax.numpy`, traceable: the 2 x 2
    spread of each view's corners and its eigenvalues in closed form.
    """
    w = mask.astype(ab.dtype)
    n = xp.maximum(w.sum(-1), 1.0)
    m = (w[..., None] * ab).sum(-2) / n[..., None]
    d = ab - m[..., None, :]
    sxx, syy, sxy = (
        (w * d[..., 0] ** 2).sum(-1),
        (w * d[..., 1] ** 2).sum(-1),
        (w * d[..., 0] * d[..., 1]).sum(-1),
    )
    half, disc = 0.5 * (sxx + syy), xp.sqrt(0.25 * (sxx - syy) ** 2 + sxy**2)
    return (mask.sum(-1) >= MIN_POINTS_PER_VIEW) & (half - disc > MIN_VIEW_SPREAD_RATIO**2 * (half + disc))


def check_intrinsics(K: np.ndarray) -> None:
    """Refuse camera matrices that are not `[[fx, s, cx], [0, fy, cy], [0, 0, 1]]` with
    finite entries and positive focal lengths (`K` `(cameras, 3, 3)`), naming the camera."""
    for c, Kc in enumerate(np.asarray(K, float)):
        if not np.all(np.isfinite(Kc)):
            raise NonFiniteError(f"K of camera {c}: non-finite entries {Kc.tolist()}")
        if Kc[0, 0] <= 0 or Kc[1, 1] <= 0:
            raise IntrinsicsError(
                f"K of camera {c}: focal lengths must be positive (px), got fx = {Kc[0, 0]:g}, fy = {Kc[1, 1]:g}"
            )
        tol = 1e-9 * max(abs(Kc[0, 0]), abs(Kc[1, 1]))  # round-off of a K read from text
        if max(abs(Kc[1, 0]), abs(Kc[2, 0]), abs(Kc[2, 1])) > tol or abs(Kc[2, 2] - 1.0) > 1e-9:
            raise IntrinsicsError(
                f"K of camera {c}: must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]] (is it transposed?), "
                f"got {Kc.tolist()}"
            )


def check_sigma(name: str, value) -> None:
    """Refuse a noise level (or levels) that is not finite and positive, naming it."""
    v = np.asarray(value, float)
    if not (np.all(np.isfinite(v)) and np.all(v > 0)):
        raise NoiseLevelError(f"{name} must be finite and positive, got {v.tolist()}")


def _at(i: int, shape: tuple) -> tuple[int, ...]:
    """The index tuple of flat index `i` (plain ints, for messages)."""
    return tuple(int(k) for k in np.unravel_index(i, shape))


def check_rotations(T, name: str) -> None:
    """Raise a `ValueError` naming `name` unless every `T[..., :3, :3]` is a rotation.

    The tolerance is `1e-6` on $\\|R^T R - I\\|_\\infty$ and on $|\\det R - 1|$;
    non-finite entries and a bottom row other than `(0, 0, 0, 1)` are errors too.
    """
    T = np.asarray(T, dtype=np.float64)
    if T.shape[-2:] != (4, 4):
        raise ShapeError(f"{name}: expected 4x4 poses, got shape {T.shape}")
    flat = T.reshape(-1, 4, 4)
    bad = ~np.all(np.isfinite(flat), axis=(-1, -2))
    if bad.any():
        raise NonFiniteError(f"{name}: non-finite pose at index {_at(np.flatnonzero(bad)[0], T.shape[:-2])}")
    R = flat[:, :3, :3]
    orth = np.max(np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)), axis=(-1, -2))
    det = np.linalg.det(R)
    bad = (orth > _ROTATION_TOL) | (np.abs(det - 1.0) > _ROTATION_TOL)
    if bad.any():
        i = np.flatnonzero(bad)[0]
        raise NotARotationError(
            f"{name}: pose {_at(i, T.shape[:-2])} is not a rotation "
            f"(det = {det[i]:.6g}, max |R^T R - I| = {orth[i]:.3g})"
        )
    bottom = np.max(np.abs(flat[:, 3] - np.array([0.0, 0.0, 0.0, 1.0])), axis=-1)
    if np.any(bottom > _ROTATION_TOL):
        i = np.flatnonzero(bottom > _ROTATION_TOL)[0]
        raise NotARotationError(
            f"{name}: pose {_at(i, T.shape[:-2])} has bottom row {flat[i, 3]}, not (0, 0, 0, 1)"
        )


def check_motion_diversity(T_base_ee, name: str = "robot poses") -> None:
    """Raise a `ValueError` unless the poses rotate about two non-parallel axes (seed 4).

    Every pair of poses gives a relative rotation $R_i^T R_j$ (end-effector
    frame). At least one must turn by `MIN_ROTATION_DEG` or more, and among
    those turning that much, one axis must differ by at least
    `MIN_AXIS_SEPARATION_DEG` (sign-agnostic) from the axis of the largest.
    """
    R = np.asarray(T_base_ee, dtype=np.float64)[..., :3, :3]
    n = R.shape[0]
    i, j = np.triu_indices(n, 1)
    rel = np.swapaxes(R[i], -1, -2) @ R[j]
    w = so3_log(rel)
    ang = np.degrees(np.linalg.norm(w, axis=-1))
    big = ang >= MIN_ROTATION_DEG
    if not big.any():
        raise DegenerateMotionError(
            f"{name}: the largest rotation between two poses is {ang.max() if ang.size else 0.0:.2f} deg; "
            f"hand-eye calibration needs rotations of at least {MIN_ROTATION_DEG:g} deg about at least two "
            "non-parallel axes"
        )
    axes = w[big] / np.linalg.norm(w[big], axis=-1, keepdims=True)
    ref = axes[np.argmax(ang[big])]
    sep = np.degrees(np.arccos(np.clip(np.abs(axes @ ref), 0.0, 1.0)))
    if sep.max() < MIN_AXIS_SEPARATION_DEG:
        raise DegenerateMotionError(
            f"{name}: every rotation of at least {MIN_ROTATION_DEG:g} deg is about one axis "
            f"(end-effector frame {np.array2string(ref, precision=3)}, within {sep.max():.2f} deg); "
            f"add a rotation of at least {MIN_ROTATION_DEG:g} deg about a second, non-parallel axis"
        )
