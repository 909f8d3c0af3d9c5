"""Camera intrinsics from views of a planar board (Zhang's method through OpenCV)."""

from collections.abc import Sequence

import cv2
import numpy as np

from ..markers import TargetSpec
from ._detect import Detection, VisionError, target_points

# A view needs enough corners, off one line, to constrain a homography well.
MIN_CORNERS_PER_VIEW = 6
MIN_VIEWS = 3
# Zhang's method needs views of the board in different orientations.
MIN_TILT_SPREAD_DEG = 10.0


def calibrate_intrinsics(
    detections: Sequence[Detection],
    target: TargetSpec,
    image_size: tuple[int, int],
    *,
    flags: int = 0,
) -> tuple[np.ndarray, np.ndarray, float]:
    """Camera matrix and distortion from a board's features seen in several views.

    `cv2.calibrateCamera` on the corners (object points from
    `target.points()`), OpenCV's 5-coefficient model unless `flags` says
    otherwise (e.g. `cv2.CALIB_FIX_K3` with few views).

    **Arguments:**

    - `detections`: one `Detection` of `target` per view; views with fewer than
      6 corners, or all on one line, are skipped.
    - `target`: a board (any kind but a single ArUco marker).
    - `image_size`: `(width, height)`, px.
    - `flags`: OpenCV `CALIB_*` flags.

    **Returns:** `(K (3, 3) px, dist (5,), rms_px)`, `rms_px` OpenCV's
    reprojection RMS over all corners.

    **Raises:** `VisionError` for a single ArUco marker, fewer than 3
    usable views, or views too alike (the board's normal varies by less than
    10 degrees, or the focal length and principal point stay undetermined).
    """
    where = f"target {target.name!r}"
    if target.kind == "aruco":
        raise VisionError(
            f"{where}: intrinsics need a board (ChArUco, chessboard, circle or ArUco grid); "
            "a single ArUco marker has too few corners"
        )
    width, height = (int(v) for v in image_size)
    if width <= 0 or height <= 0:
        raise VisionError(f"{where}: image_size must be (width, height) > 0, got {image_size}")
    points = target_points(target)
    objs, imgs = [], []
    for det in detections:
        if det is None or len(det.ids) < MIN_CORNERS_PER_VIEW:
            continue
        obj = points[det.ids]
        s = np.linalg.svd(obj - obj.mean(0), compute_uv=False)
        if s[1] <= 1e-6 * s[0]:
            continue
        objs.append(obj.astype(np.float32).reshape(-1, 1, 3))
        imgs.append(det.pixels.astype(np.float32).reshape(-1, 1, 2))
    if len(objs) < MIN_VIEWS:
        raise VisionError(
            f"{where}: {len(objs)} usable views (at least {MIN_CORNERS_PER_VIEW} corners off one line), "
            f"need at least {MIN_VIEWS}"
        )
    try:
        rms, K, dist, rvecs, _, std, _, _ = cv2.calibrateCameraExtended(
            objs, imgs, (width, height), None, None, flags=flags
        )
    except cv2.error as e:
        raise VisionError(f"{where}: OpenCV calibration failed ({e}); add views at varied tilts") from None
    normals = np.array([cv2.Rodrigues(r)[0][:, 2] for r in rvecs])
    spread = np.degrees(np.arccos(np.clip(normals @ normals.T, -1.0, 1.0))).max()
    if spread < MIN_TILT_SPREAD_DEG:
        raise VisionError(
            f"{where}: the board's orientation varies by only {spread:.1f} deg over {len(objs)} views; "
            f"tilt it (at least {MIN_TILT_SPREAD_DEG:.0f} deg) for the focal length to be determined"
        )
    std = np.asarray(std).ravel()[:4]
    if not np.all(np.isfinite(std)) or np.any(std > 0.05 * np.array([K[0, 0], K[1, 1], width, height])):
        raise VisionError(
            f"{where}: focal length / principal point undetermined (std {np.round(std, 2)} px); "
            "add views at varied tilts and positions"
        )
    return np.asarray(K, np.float64), np.asarray(dist, np.float64).ravel(), float(rms)
