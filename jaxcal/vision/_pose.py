"""Marker pose from one detection (PnP) with its covariance."""

from dataclasses import dataclass

import cv2
import numpy as np

from .._lsq import normal_inverse
from .._npgeom import skew
from ..markers import TargetSpec
from ._detect import MIN_POINTS, Detection, VisionError, target_points

# Floor on the residual-estimated pixel noise: rendered or very clean corners can
# fit to a few hundredths of a pixel, which would make the covariance overconfident.
SIGMA_FLOOR_PX = 0.05


@dataclass(frozen=True, eq=False)
class PoseEstimate:
    """A target's pose in the camera frame, from PnP on one `Detection`.

    - `T_cam_target`: (4, 4), maps target-frame points (m) into the camera frame.
    - `cov`: (6, 6) covariance of the error $(p, w)$: $p$ the target origin in
      the camera frame (m), $w$ a camera-frame *left* rotation perturbation
      (rad), $O_{true} = \\exp([w]_\\times) O_{est}$. This is the error the arc
      fit whitens: $(\\hat P - P, \\log(O_{meas} O_{pred}^T))$.
    - `rms_px`: reprojection RMS over points, $\\sqrt{\\sum_i \\|r_i\\|^2 / n}$, px.
    - `n_points`: features used.
    - `sigma_px`: the pixel noise (per coordinate) `cov` was scaled by, px.
    """

    T_cam_target: np.ndarray
    cov: np.ndarray
    rms_px: float
    n_points: int
    sigma_px: float

    def inverse(self) -> "PoseEstimate":
        """The target's view of the camera: $T_{target,cam} = T_{cam,target}^{-1}$
        with its covariance in the same $(p, w)$ convention (now in the target
        frame), for eye-in-hand data, where the camera moves and the board stays.

        With $T = (O, P)$: $O' = O^T$, $P' = -O^T P$; to first order
        $w' = -O^T w$ and $p' = -O^T p - O^T [P]_\\times w$, so
        $\\Sigma' = A \\Sigma A^T$ with $A = \\begin{pmatrix} -O^T & -O^T[P]_\\times \\\\
        0 & -O^T \\end{pmatrix}$.
        """
        O, P = self.T_cam_target[:3, :3], self.T_cam_target[:3, 3]
        T = np.eye(4)
        T[:3, :3] = O.T
        T[:3, 3] = -O.T @ P
        A = np.zeros((6, 6))
        A[:3, :3] = -O.T
        A[:3, 3:] = -O.T @ skew(P[None])[0]
        A[3:, 3:] = -O.T
        return PoseEstimate(T, A @ self.cov @ A.T, self.rms_px, self.n_points, self.sigma_px)


def pose_jacobian(points: np.ndarray, T_cam_target: np.ndarray, K, dist) -> tuple[np.ndarray, np.ndarray]:
    """Projected pixels and their Jacobian w.r.t. the $(p, w)$ pose error.

    With $P_c = \\exp([w]_\\times) R X + t + p$, $\\partial u / \\partial p =
    \\partial u / \\partial P_c$ (OpenCV's `projectPoints` Jacobian w.r.t. `tvec`,
    distortion included) and $\\partial u / \\partial w = -\\partial u /
    \\partial P_c \\, [R X]_\\times$.

    **Arguments:** `points` (n, 3) target frame, m; `T_cam_target` (4, 4);
    `K` (3, 3); `dist` OpenCV coefficients or `None`.

    **Returns:** `(pixels (n, 2), J (2n, 6))`, rows `(u_0, v_0, u_1, ...)`,
    columns $(p, w)$.
    """
    points = np.ascontiguousarray(points, np.float64).reshape(-1, 3)
    R, t = T_cam_target[:3, :3], T_cam_target[:3, 3]
    rvec = cv2.Rodrigues(R)[0]
    pixels, jac = cv2.projectPoints(points, rvec, t, np.asarray(K, np.float64), _dist(dist))
    Jt = jac[:, 3:6].reshape(-1, 2, 3)
    Jw = -np.einsum("nij,njk->nik", Jt, skew(points @ R.T))
    J = np.concatenate([Jt, Jw], axis=2).reshape(-1, 6)
    return pixels.reshape(-1, 2), J


def _dist(dist) -> np.ndarray:
    return np.zeros(5) if dist is None else np.asarray(dist, np.float64).ravel()


def _se3(rvec, tvec) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(rvec, np.float64))[0]
    T[:3, 3] = np.asarray(tvec, np.float64).ravel()
    return T


def estimate_pose(
    det: Detection, target: TargetSpec, K, dist, *, sigma_px: float | None = None
) -> "PoseEstimate | None":
    """PnP of one detection, with the pose covariance from the reprojection Jacobian.

    ChArUco: `SOLVEPNP_IPPE` (planar) to start, then `solvePnPRefineLM` on all
    corners. Single ArUco: `SOLVEPNP_IPPE_SQUARE`, then the same refinement.
    Distortion is handled by OpenCV's projection model throughout.

    The covariance is $s^2 (J^T J)^{-1}$ with $J$ the Jacobian of the projected
    pixels w.r.t. the $(p, w)$ error (see `PoseEstimate`). $s$ is `sigma_px`
    if given, else estimated from the residual, $s^2 = \\sum r^2 / (2n - 6)$
    (2n pixel coordinates, 6 pose parameters), floored at 0.05 px.

    **Arguments:**

    - `det`: the detection (feature ids index `target.points()`).
    - `target`: the target detected.
    - `K`: (3, 3) camera matrix, px. `dist`: OpenCV distortion coefficients or `None`.
    - `sigma_px`: known pixel noise per coordinate, px.

    **Returns:** a `PoseEstimate`, or `None` with fewer than 4 points, with
    the points on one line, or if PnP fails.
    """
    K = np.asarray(K, np.float64)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        raise VisionError(f"target {target.name!r}: camera matrix K must be a finite 3x3 array")
    dist = _dist(dist)
    if sigma_px is not None and not sigma_px > 0:
        raise VisionError(f"target {target.name!r}: sigma_px must be > 0, got {sigma_px}")
    all_points = target_points(target)
    if len(det.ids) and (det.ids.min() < 0 or det.ids.max() >= len(all_points)):
        raise VisionError(
            f"target {target.name!r}: feature ids {det.ids.min()}..{det.ids.max()} outside "
            f"0..{len(all_points) - 1}"
        )
    n = len(det.ids)
    if n < MIN_POINTS:
        return None
    obj, img = all_points[det.ids], det.pixels
    centred = obj - obj.mean(0)
    s = np.linalg.svd(centred, compute_uv=False)
    if s[1] <= 1e-9 * s[0]:  # collinear: the rotation about the line is free
        return None
    if target.kind == "aruco":
        if sorted(det.ids.tolist()) != [0, 1, 2, 3]:
            return None
        order = np.argsort(det.ids)
        obj, img = obj[order], img[order]
        flags = cv2.SOLVEPNP_IPPE_SQUARE
    else:
        flags = cv2.SOLVEPNP_IPPE
    try:
        ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist, flags=flags)
        if not ok or rvec is None or tvec is None:  # IPPE can fail on 4 oblique points
            ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist, flags=cv2.SOLVEPNP_SQPNP)
        if not ok or rvec is None or tvec is None:
            return None
        rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, dist, rvec, tvec)
    except cv2.error:
        return None
    T = _se3(rvec, tvec)
    if T[2, 3] <= 0:
        return None
    projected, J = pose_jacobian(obj, T, K, dist)
    r = (projected - img).ravel()
    rms = float(np.sqrt(np.sum(r**2) / n))
    if sigma_px is None:
        dof = 2 * n - 6
        sigma = SIGMA_FLOOR_PX if dof <= 0 else max(float(np.sqrt(np.sum(r**2) / dof)), SIGMA_FLOOR_PX)
    else:
        sigma = float(sigma_px)
    JtJ = J.T @ J
    if not np.all(np.isfinite(JtJ)) or np.linalg.cond(JtJ) > 1e14:
        return None
    cov = normal_inverse(JtJ, sigma**2)
    cov = 0.5 * (cov + cov.T)
    return PoseEstimate(T_cam_target=T, cov=cov, rms_px=rms, n_points=n, sigma_px=sigma)


#: Target kinds whose features are circles' centres.
CIRCLE_KINDS = ("circles", "acircles")

#: Points on each circle's rim whose image's area centroid stands for the blob's centre.
CIRCLE_RIM_POINTS = 96


def circle_centre_shift(target: TargetSpec, ids: np.ndarray, T_cam_target: np.ndarray, K, dist) -> np.ndarray:
    """Where a circle grid's blobs lie from the images of their circles' centres, `(len(ids), 2)` px.

    A circle seen at a slant images as an ellipse, and the centre a blob detector finds (the
    ellipse's, its area centroid) is not the image of the circle's centre: it lies further from
    the vanishing line, by about f (r/Z)^2 sin(2 tilt) / 2 (Heikkila, "Geometric camera
    calibration using circular control points", 2000), the same in every view at the same
    slant. Here it is each rim's projection (`CIRCLE_RIM_POINTS`, OpenCV's model with the
    distortion) reduced to its area centroid, minus the projected centre, at the pose
    `T_cam_target` (a pose from the blobs themselves is close enough: the shift changes with
    the pose only at second order). Other target kinds: zeros."""
    ids = np.asarray(ids)
    if target.kind not in CIRCLE_KINDS:
        return np.zeros((len(ids), 2))
    centres = target_points(target)[ids]
    t = 2.0 * np.pi * np.arange(CIRCLE_RIM_POINTS) / CIRCLE_RIM_POINTS
    rim = 0.5 * target.marker_length * np.stack([np.cos(t), np.sin(t), np.zeros_like(t)], axis=1)
    points = np.concatenate([centres, (centres[:, None, :] + rim).reshape(-1, 3)])
    rvec = cv2.Rodrigues(np.asarray(T_cam_target, np.float64)[:3, :3])[0]
    tvec = np.asarray(T_cam_target, np.float64)[:3, 3]
    uv = cv2.projectPoints(points, rvec, tvec, np.asarray(K, np.float64), _dist(dist))[0].reshape(-1, 2)
    centre_px, rims = uv[: len(ids)], uv[len(ids) :].reshape(len(ids), CIRCLE_RIM_POINTS, 2)
    x, y = rims[..., 0], rims[..., 1]
    xn, yn = np.roll(x, -1, axis=1), np.roll(y, -1, axis=1)
    cross = x * yn - xn * y  # the shoelace formula's terms: twice each triangle's signed area
    area = cross.sum(axis=1)
    centroid = np.stack([((x + xn) * cross).sum(axis=1), ((y + yn) * cross).sum(axis=1)], axis=1)
    return centroid / (3.0 * area[:, None]) - centre_px
