"""Held-out reprojection: frames predicted from their reported robot poses by solves that did not see them (NumPy).

How a user applies a hand-eye result: from the pose the robot reports, where is the target (or the
camera)? `kfold_spread` leaves blocks of consecutive frames out, solves without them and
predicts their corners from their reported robot poses, with no robot correction (a new frame
has none): `reprojection_squares`. Its RMS over every held-out corner is the error a user will
see; beside the in-sample RMS it says how much of the fit the robot poses' noise, or the
corrections that absorbed it, account for.

`robot_pixel_scale` turns pixels into the robot's units: the RMS by which a robot pose error
of 1 mm and 0.1 deg per axis (`noise.ROBOT_SIGMA_START`, a typical robot's absolute error) moves
these views' corners, so that a held-out error $h$ over the detector's noise $\\sigma$ reads as
a robot pose noise of about $\\sqrt{h^2 - \\sigma^2}/s$ times that (`HeldOut.level`): at most,
since the held-out error also holds the fit's own error.
"""

from dataclasses import dataclass

import numpy as np

from .._npgeom import rotvec_to_matrix
from .data import HandEyePixels
from .noise import ROBOT_SIGMA_START

#: Step of the finite differences of `robot_pixel_scale` (m and rad): far below any robot's error,
#: far above float64's round-off on metre-scale poses.
_STEP = 1e-7

#: A reprojection error beyond this (px) means only that the views land far off the image (a
#: point projected from near or behind the camera): no figure is given, only the bound.
ABSURD_PX = 1e5


def px_text(value: float) -> str:
    """`X px` for a reprojection error; beyond `ABSURD_PX`, the bound in words instead of a figure."""
    return f"{value:.3g} px" if value < ABSURD_PX else f"over {ABSURD_PX:.0e} px (far off the image)"


def _project(A: np.ndarray, data: HandEyePixels) -> np.ndarray:
    """Pixels `(cameras, frames, points, 2)` of the board points seen at board poses `A`
    `(cameras, frames, 4, 4)`, as `model._observation_residuals` projects them."""
    p = np.einsum("cfij,pj->cfpi", A[..., :3, :3], np.asarray(data.board_points)) + A[..., None, :3, 3]
    z = np.maximum(p[..., 2], 1e-9)
    x, y = p[..., 0] / z, p[..., 1] / z
    K = np.asarray(data.K)[:, None, None]
    return np.stack([K[..., 0, 0] * x + K[..., 0, 1] * y + K[..., 0, 2], K[..., 1, 1] * y + K[..., 1, 2]], -1)


def _board_poses(T_cam_robot, T_robot_board, T_base_ee, eye_in_hand: bool) -> np.ndarray:
    """$A_{cf} = X_c B_f Y$ with $B_f$ the robot pose (inverted eye-in-hand), `(cameras, frames, 4, 4)`."""
    B = np.linalg.inv(T_base_ee) if eye_in_hand else T_base_ee
    return np.einsum("cij,fjk,kl->cfil", np.asarray(T_cam_robot), B, np.asarray(T_robot_board))


def reprojection_squares(
    T_cam_robot, T_robot_board, data: HandEyePixels, frames
) -> tuple[np.ndarray, np.ndarray]:
    """Per (camera, frame), the sum of squared pixel errors (px^2) of the corners predicted from the
    reported robot pose (no correction) by `T_cam_robot`, `T_robot_board`, and the number of
    coordinates they sum (twice the corners); zero outside `frames` `(frames,)` (a mask).

    **Returns:** `(squares (cameras, frames), coordinates (cameras, frames))`."""
    eye_in_hand = bool(np.all(np.asarray(data.eye_in_hand)))
    A = _board_poses(T_cam_robot, T_robot_board, np.asarray(data.T_base_ee, np.float64), eye_in_hand)
    m = np.asarray(data.mask) & np.asarray(frames, bool)[None, :, None]
    e = np.where(m[..., None], _project(A, data) - np.nan_to_num(np.asarray(data.pixels)), 0.0)
    return np.sum(e**2, axis=(-1, -2)), 2.0 * m.sum(-1)


def robot_pixel_scale(T_cam_robot, T_robot_board, data: HandEyePixels, frames) -> float:
    """RMS per pixel coordinate by which independent robot pose errors of `ROBOT_SIGMA_START` per axis
    (1 mm, 0.1 deg; as `model.corrected_robot` applies them) move the corners of `frames`:
    $\\sqrt{\\sum_i \\sigma_i^2 \\|\\partial u/\\partial \\delta_i\\|^2 / n}$, by central differences."""
    eye_in_hand = bool(np.all(np.asarray(data.eye_in_hand)))
    T = np.asarray(data.T_base_ee, np.float64)
    m = np.asarray(data.mask) & np.asarray(frames, bool)[None, :, None]
    if not m.any():
        return float("nan")
    sigma = np.r_[np.full(3, ROBOT_SIGMA_START[0]), np.full(3, ROBOT_SIGMA_START[1])]
    total = 0.0
    for i in range(6):
        moved = []
        for sign in (1.0, -1.0):
            Ts = T.copy()
            if i < 3:
                Ts[:, i, 3] += sign * _STEP
            else:
                w = np.zeros(3)
                w[i - 3] = sign * _STEP
                Ts[:, :3, :3] = rotvec_to_matrix(w) @ T[:, :3, :3]
            moved.append(_project(_board_poses(T_cam_robot, T_robot_board, Ts, eye_in_hand), data))
        du = (moved[0] - moved[1]) / (2.0 * _STEP)
        total += sigma[i] ** 2 * np.sum(np.where(m[..., None], du, 0.0) ** 2)
    return float(np.sqrt(total / (2.0 * m.sum())))


@dataclass(frozen=True)
class HeldOut:
    """The held-out reprojection of a solve, beside its in-sample one (px, per pixel coordinate).

    - `rms_px`: frames predicted from their reported robot poses by the folds that left them out.
    - `in_sample_px`: the solve's own reprojection RMS (after robot corrections, where it has any).
    - `sigma_px`: the detector's noise.
    - `scale_px`: `robot_pixel_scale` of these views (px per 1 mm / 0.1 deg per axis).
    - `folds`, `frames`: the folds of consecutive frames and the frames held out.
    """

    rms_px: float
    in_sample_px: float
    sigma_px: float
    scale_px: float
    folds: int
    frames: int

    @property
    def level(self) -> float:
        """The robot pose noise per axis that the held-out error's excess over the detector's noise
        reads as, in units of 1 mm and 0.1 deg (`ROBOT_SIGMA_START`): at most that."""
        excess = max(self.rms_px**2 - self.sigma_px**2, 0.0)
        return float(np.sqrt(excess) / self.scale_px) if self.scale_px > 0 else float("inf")

    @property
    def noise(self) -> tuple[float, float]:
        """`(mm, deg)` per axis: the robot pose noise of `level`."""
        return 1e3 * ROBOT_SIGMA_START[0] * self.level, float(np.degrees(ROBOT_SIGMA_START[1]) * self.level)

    def noise_text(self) -> str:
        """`about X mm / Y deg per axis`, the robot pose noise of `level`."""
        mm, deg = self.noise
        if mm > 1e3 or deg > 180.0:
            return "over 1000 mm / 180 deg per axis"
        return f"about {mm:.2g} mm / {deg:.2g} deg per axis"

    def figures(self) -> str:
        """The held-out and in-sample reprojection RMS and the detector's noise, in words."""
        return (
            f"frames left out ({self.folds} folds of consecutive frames) are predicted from their reported "
            f"robot poses to {px_text(self.rms_px)} RMS (in-sample {px_text(self.in_sample_px)}, detector "
            f"{self.sigma_px:.3g} px)"
        )
