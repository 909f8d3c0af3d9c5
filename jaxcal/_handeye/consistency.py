"""Robot poses against images before any solve: relative rotation angles must agree (NumPy).

For frames $f, g$ seen by camera $c$, $A_f = X B_f Y$ gives
$A_f^{-1} A_g = Y^{-1} B_f^{-1} B_g Y$: the board's relative rotation is the
robot's, conjugated. Conjugation keeps the rotation angle, so

$$\\angle(R_{A_f}^T R_{A_g}) = \\angle(R_{B_f}^T R_{B_g})$$

for every pair, whatever $X$ and $Y$, in both arrangements ($B_f$ or its
inverse: the angle of $R^T$ is that of $R$). A capture whose robot poses do
not belong to its images (shuffled, another capture's, rotations misread) breaks
this for most pairs and is refused; a few bad robot poses break it for their
own pairs only and are named. (A quaternion read in the wrong component order
keeps every relative angle: $|q_f \\cdot q_g|$ does not change when the four
components are permuted alike; nor do the translations enter; the solve's
residuals show those instead. A wrong unit of the translations therefore
cannot fire this check, a wrong unit or convention of the rotations can:
`REFUSAL_ADVICE`.)

Board poses come from the measured poses, or from the pixels by a planar
homography (Zhang's decomposition, as `closed.board_poses_from_pixels`, in
NumPy here so that the check runs before anything is compiled).
"""

from dataclasses import dataclass

import numpy as np

from .._npgeom import rotation_angle
from .._rowshift import describe, pairings
from ..errors import InconsistentPosesError
from .checks import plane_frame, spanning_views

#: What can make most relative rotation angles disagree, and so what to check. Only the
#: rotations enter the check, and only through relative angles: the pairing of poses with
#: images, and how the rotation columns are read. The translation unit, a quaternion's
#: component order, inverted (T_ee_base) or transposed rotations and a swapped arrangement
#: keep every angle (conjugation, transposition and a common permutation of a unit
#: quaternion's components leave $|q_f \cdot q_g|$ and $\mathrm{tr}(R_f^T R_g)$ as they
#: are), so they cannot trigger it and are not named.
REFUSAL_ADVICE = (
    "Check that the robot poses are paired with the right images (one row per image, in the images' "
    "order, none missing or extra, each recorded with the robot at rest where the image was taken) and "
    "that their rotations are read as written: the rotation unit (rad or deg), the Euler-angle convention "
    "(xyz_rpy is R = Rz Ry Rx, fixed axes) and the format itself (a rotation vector is not roll, pitch, "
    "yaw). The translation unit, the quaternion component order and inverted poses cannot cause this: "
    "they keep every relative rotation angle"
)
#: Pairs whose camera and robot rotation angles differ by more than this disagree (deg).
CONSISTENCY_TOL_DEG = 2.0
#: Relative rotations smaller than this on both sides say little (their angle is noise): skipped (deg).
MIN_PAIR_ANGLE_DEG = 1.0


def homography_rotations(pixels, mask, K, board_points) -> tuple[np.ndarray, np.ndarray]:
    """Board rotations in the camera frame from undistorted pixels by a planar homography.

    **Arguments:** `pixels` `(cameras, frames, points, 2)` px (undistorted),
    `mask` `(cameras, frames, points)`, `K` `(cameras, 3, 3)`, `board_points`
    `(points, 3)` m, (nearly) coplanar.

    **Returns:** `(R_cam_board (cameras, frames, 3, 3), ok (cameras, frames))`,
    `ok` where a view has at least 4 corners not on one line (`checks.spanning_views`;
    identity elsewhere).
    """
    px, mask, K = np.asarray(pixels, float), np.asarray(mask, bool), np.asarray(K, float)
    C, F = mask.shape[:2]
    U, ab = plane_frame(np.asarray(board_points, float))
    ok = spanning_views(ab, mask)
    R = np.broadcast_to(np.eye(3), (C, F, 3, 3)).copy()
    c, f = np.nonzero(ok)
    if len(c):
        R[c, f] = _homography_rotations(px[c, f], mask[c, f], K[c], U, ab)
    return R, ok


def _homography_rotations(px, mask, K, U, ab) -> np.ndarray:
    """`(views, 3, 3)` for views with at least 4 points: `px` `(views, points, 2)`, `K` `(views, 3, 3)`,
    `U`, `ab`: `checks.plane_frame` of the board points."""
    y = (px[..., 1] - K[:, None, 1, 2]) / K[:, None, 1, 1]
    x = (px[..., 0] - K[:, None, 0, 2] - K[:, None, 0, 1] * y) / K[:, None, 0, 0]
    w = mask.astype(float)
    x, y = np.where(mask, x, 0.0), np.where(mask, y, 0.0)
    # Hartley normalisation of the image side; the plane side is scaled once.
    n = w.sum(-1)
    mx, my = (w * x).sum(-1) / n, (w * y).sum(-1) / n
    spread = np.sqrt((w * ((x - mx[:, None]) ** 2 + (y - my[:, None]) ** 2)).sum(-1) / n)
    s = np.sqrt(2.0) / np.maximum(spread, 1e-12)
    xn, yn = (x - mx[:, None]) * s[:, None], (y - my[:, None]) * s[:, None]
    sa = np.sqrt(2.0) / max(np.sqrt(np.mean(np.sum(ab**2, -1))), 1e-12)
    a = np.broadcast_to(ab * sa, px.shape[:-1] + (2,))
    one, zero = np.ones_like(xn), np.zeros_like(xn)
    a1 = np.stack([a[..., 0], a[..., 1], one], -1)
    z3 = np.stack([zero, zero, zero], -1)
    rows = (
        np.concatenate(
            [
                np.concatenate([a1, z3, -xn[..., None] * a1], -1),
                np.concatenate([z3, a1, -yn[..., None] * a1], -1),
            ],
            axis=-2,
        )
        * np.concatenate([w, w], -1)[..., None]
    )
    # All nine right singular vectors: with exactly 4 points (one square marker) the system has
    # 8 rows, and the homography is the null vector a reduced SVD leaves out.
    _, _, Vt = np.linalg.svd(rows, full_matrices=True)
    Hn = Vt[:, -1, :].reshape(-1, 3, 3)
    T_img_inv = np.zeros((len(px), 3, 3))
    T_img_inv[:, 0, 0] = T_img_inv[:, 1, 1] = 1.0 / s
    T_img_inv[:, 0, 2], T_img_inv[:, 1, 2], T_img_inv[:, 2, 2] = mx, my, 1.0
    H = T_img_inv @ Hn @ np.diag([sa, sa, 1.0])
    lam = 2.0 / (np.linalg.norm(H[:, :, 0], axis=-1) + np.linalg.norm(H[:, :, 1], axis=-1))
    lam = np.where(H[:, 2, 2] < 0, -lam, lam)  # the board is in front of the camera
    r1, r2 = lam[:, None] * H[:, :, 0], lam[:, None] * H[:, :, 1]
    M = np.stack([r1, r2, np.cross(r1, r2)], axis=-1)
    Us, _, Vs = np.linalg.svd(M)
    D = np.ones((len(px), 3))
    D[:, 2] = np.sign(np.linalg.det(Us @ Vs))
    return (Us * D[:, None, :]) @ Vs @ U.T


@dataclass(frozen=True)
class MotionConsistency:
    """How far the robot's relative rotation angles are from the camera's, pair by pair.

    - `pair_error_deg`: `(frames, frames)` $|\\angle_{cam} - \\angle_{robot}|$
      (deg), the mean over the cameras that saw both frames; NaN where no
      camera did, on the diagonal, and where both angles are below
      `MIN_PAIR_ANGLE_DEG`.
    - `tolerance_deg`: pairs above it disagree.
    - `disagreeing_fraction`: of all compared pairs.
    - `inconsistent`: `(frames,)` frames most of whose pairs disagree.
    - `median_error_deg`, `mean_error_deg`: over the compared pairs.
    """

    pair_error_deg: np.ndarray
    tolerance_deg: float
    disagreeing_fraction: float
    inconsistent: np.ndarray
    median_error_deg: float
    mean_error_deg: float

    def inconsistent_frames(self) -> np.ndarray:
        return np.flatnonzero(self.inconsistent)


def motion_consistency(R_cam_board, views, T_base_ee, *, tolerance_deg: float = CONSISTENCY_TOL_DEG):
    """Compare every pair of frames' relative rotation angle, camera against robot.

    **Arguments:** `R_cam_board` `(cameras, frames, 3, 3)` measured board
    rotations, `views` `(cameras, frames)` which are measured, `T_base_ee`
    `(frames, 4, 4)` robot poses, `tolerance_deg`.

    **Returns:** a `MotionConsistency`.
    """
    cam, robot, views = _angles(R_cam_board, views, T_base_ee)
    both = views[:, :, None] & views[:, None, :]
    err = np.abs(cam - robot[None])
    count = both.sum(0)
    mean = np.where(count > 0, np.sum(np.where(both, err, 0.0), 0) / np.maximum(count, 1), np.nan)
    small = (robot < MIN_PAIR_ANGLE_DEG) & (np.max(np.where(both, cam, 0.0), 0) < MIN_PAIR_ANGLE_DEG)
    np.fill_diagonal(mean, np.nan)
    mean = np.where(small, np.nan, mean)
    compared = np.isfinite(mean)
    bad = compared & (mean > tolerance_deg)
    n_pairs = compared.sum() // 2
    frac = float(bad.sum() // 2 / n_pairs) if n_pairs else 0.0
    inconsistent = bad.sum(1) > 0.5 * compared.sum(1)
    values = mean[np.triu(compared, 1)]
    return MotionConsistency(
        pair_error_deg=mean,
        tolerance_deg=float(tolerance_deg),
        disagreeing_fraction=frac,
        inconsistent=inconsistent,
        median_error_deg=float(np.median(values)) if values.size else 0.0,
        mean_error_deg=float(np.mean(values)) if values.size else 0.0,
    )


def _angles(R_cam_board, views, T_base_ee) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every pair's relative rotation angle (deg): the camera's `(cameras, frames, frames)`, the
    robot's `(poses, poses)`; and `views` as booleans."""
    R = np.asarray(R_cam_board, float)
    RB = np.asarray(T_base_ee, float)[:, :3, :3]
    robot = np.degrees(rotation_angle(np.einsum("fji,gjk->fgik", RB, RB)))
    cam = np.degrees(rotation_angle(np.einsum("cfji,cgjk->cfgik", R, R)))
    return cam, robot, np.asarray(views, bool)


#: A shifted pairing (`jaxcal._rowshift.pairings`) explains a refusal when at most this share of
#: its pairs of frames disagree.
SHIFT_FIT = 0.1


def shifted_rows(R_cam_board, views, T_base_ee, *, tolerance_deg: float = CONSISTENCY_TOL_DEG):
    """The pose rows' shift that makes robot and camera agree, when the rows as paired do not:
    `(first, shift, disagreeing_fraction)` or None. From frame `first` on, frame `f` takes the
    robot pose of row `f - shift` (`jaxcal._rowshift.pairings`). Only a pairing that leaves at
    most `SHIFT_FIT` of its pairs disagreeing is returned; the best of them."""
    cam, robot, views = _angles(R_cam_board, views, T_base_ee)
    best = None
    for first, shift, rows in pairings(robot.shape[0]):
        paired = rows >= 0
        pose = rows[paired]
        frac = _disagreeing(
            cam[:, paired][:, :, paired], robot[np.ix_(pose, pose)], views[:, paired], tolerance_deg
        )
        if frac is not None and frac <= SHIFT_FIT and (best is None or frac < best[2]):
            best = (first, shift, frac)
    return best


def _disagreeing(cam, robot, views, tolerance_deg) -> float | None:
    """The share of compared pairs whose mean camera angle differs from the robot's by more than
    `tolerance_deg` (None if no pair is compared): `motion_consistency`'s figure for one pairing."""
    both = views[:, :, None] & views[:, None, :]
    count = both.sum(0)
    err = np.sum(np.where(both, np.abs(cam - robot[None]), 0.0), 0) / np.maximum(count, 1)
    small = (robot < MIN_PAIR_ANGLE_DEG) & (np.max(np.where(both, cam, 0.0), 0) < MIN_PAIR_ANGLE_DEG)
    compared = np.triu((count > 0) & ~small, 1)
    return float(np.mean(err[compared] > tolerance_deg)) if compared.any() else None


def _names(frames, frame_names) -> str:
    labels = [str(frame_names[f]) if frame_names is not None else str(f) for f in frames]
    return ", ".join(labels[:30]) + (f" and {len(labels) - 30} more" if len(labels) > 30 else "")


def check_motion_consistency(
    R_cam_board, views, T_base_ee, *, tolerance_deg: float = CONSISTENCY_TOL_DEG, frame_names=None
) -> MotionConsistency:
    """`motion_consistency`, raising `InconsistentPosesError` when most pairs disagree.

    The message names the frames most of whose pairs disagree (by
    `frame_names` when given, else by index) and the mean disagreement, and the
    pose rows' shift that explains it when one does (`shifted_rows`).
    """
    mc = motion_consistency(R_cam_board, views, T_base_ee, tolerance_deg=tolerance_deg)
    if mc.disagreeing_fraction > 0.5:
        bad = mc.inconsistent_frames()
        found = shifted_rows(R_cam_board, views, T_base_ee, tolerance_deg=tolerance_deg)
        name = (lambda f: str(frame_names[f])) if frame_names is not None else str
        advice = (
            f"The data fit shifted: {describe(found, name, 'frame', 'robot pose')}. Pair each image with the pose the robot "
            "held when it was taken"
            if found is not None
            else REFUSAL_ADVICE
        )
        raise InconsistentPosesError(
            f"robot poses and images disagree: for {100 * mc.disagreeing_fraction:.0f}% of the pairs of frames "
            f"the robot's relative rotation angle differs from the camera's by more than {tolerance_deg:g} deg "
            f"(mean {mc.mean_error_deg:.1f} deg), whatever the hand-eye transform; frames {_names(bad, frame_names)} "
            f"disagree with most others. {advice}"
        )
    return mc
