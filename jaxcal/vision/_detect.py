"""Target detection in one image, or many files: ChArUco corners, ArUco markers and grids, chessboards, circle grids."""

import os
import threading
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from dataclasses import dataclass
from functools import lru_cache
from multiprocessing import get_context

import cv2
import numpy as np

from .. import _interrupt
from .._progress import progress as progress_bar
from ..errors import VisionError
from ..markers import GRID_KINDS, TargetSpec, aruco_dictionary

# Fewest features that still fix a pose: 4 ChArUco corners, or the 4 corners of a marker.
MIN_POINTS = 4
_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 1e-4)
# Below this many images per worker, another worker costs more than it saves: a
# process's start-up; for threads, their chunks' hand-over.
_POOL_MIN_PER_WORKER = 32
_THREAD_MIN_PER_WORKER = 4


@dataclass(frozen=True, eq=False)
class Detection:
    """One target's features found in one image.

    - `ids`: (n,) int, feature ids = row indices into `TargetSpec.points()`
      (ChArUco: OpenCV's corner ids; single ArUco and ArUco grids: the corner
      0..3 in the order top-left, top-right, bottom-right, bottom-left, i.e.
      `4 * (marker id - first_id) + corner`; chessboards and circle grids:
      the grid index, see `jaxcal.markers`). Sorted ascending.
    - `pixels`: (n, 2) float64, where they are in the (distorted) image, px,
      OpenCV's pixel-centre convention (the centre of pixel (0, 0) is (0, 0)),
      sub-pixel refined.
    """

    ids: np.ndarray
    pixels: np.ndarray

    def __post_init__(self):
        ids = np.asarray(self.ids, np.int64).ravel()
        pixels = np.asarray(self.pixels, np.float64).reshape(-1, 2)
        if len(ids) != len(pixels):
            raise ValueError(f"Detection: {len(ids)} ids but {len(pixels)} pixels")
        object.__setattr__(self, "ids", ids)
        object.__setattr__(self, "pixels", pixels)

    def __len__(self) -> int:
        return len(self.ids)

    def __eq__(self, other) -> bool:
        if not isinstance(other, Detection):
            return NotImplemented
        return np.array_equal(self.ids, other.ids) and np.array_equal(self.pixels, other.pixels)

    __hash__ = None


# --------------------------------------------------------------------------- detectors


def _aruco_parameters():
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    return params


def _camera_key(K, dist):
    if K is None:
        return None, None
    K = np.asarray(K, np.float64)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        raise VisionError(f"camera matrix K must be a finite 3x3 array, got shape {K.shape}")
    d = np.zeros(5) if dist is None else np.asarray(dist, np.float64).ravel()
    if not np.all(np.isfinite(d)):
        raise VisionError("distortion coefficients contain NaN or inf")
    return tuple(K.ravel().tolist()), tuple(d.tolist())


@lru_cache(maxsize=64)
def target_points(target: TargetSpec) -> np.ndarray:
    """`target.points()`, computed once per target (read-only)."""
    points = target.points()
    points.flags.writeable = False
    return points


@lru_cache(maxsize=32)
def _detector(target: TargetSpec, K: tuple | None, dist: tuple | None, thread: int):
    # Keyed on the spec's printed fields (its `name` does not take part in ==),
    # and on the thread: OpenCV's detectors are not documented as thread-safe.
    if target.kind in ("aruco", "aruco_grid"):
        return cv2.aruco.ArucoDetector(aruco_dictionary(target.dictionary), _aruco_parameters())
    if target.kind in GRID_KINDS:
        return None
    charuco = cv2.aruco.CharucoParameters()
    if K is not None:
        charuco.cameraMatrix = np.asarray(K, np.float64).reshape(3, 3)
        charuco.distCoeffs = np.asarray(dist, np.float64).reshape(1, -1)
    return cv2.aruco.CharucoDetector(target.board(), charuco, _aruco_parameters())


def _grey(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.dtype != np.uint8:
        raise VisionError(f"images must be uint8, got {image.dtype}")
    if image.ndim == 2:
        return image
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.ndim == 3 and image.shape[2] == 1:
        return image[:, :, 0]
    raise VisionError(f"expected a grey (H, W) or BGR (H, W, 3) image, got shape {image.shape}")


def _refine_window(target: TargetSpec, pixels: np.ndarray, ids: np.ndarray) -> int:
    """Half-size (px) of the `cornerSubPix` window: inside the white gap between a
    chessboard corner and the nearest marker, so no marker edge enters it.

    `ids` sorted ascending; the square's pixel length is the shortest distance
    between detected neighbours (same row next column, or next row). Below 2
    (or with no neighbours) it returns 0: keep OpenCV's own refinement.
    """
    cols = target.squares[0] - 1
    steps = []
    for step, valid in [(1, ids % cols != cols - 1), (cols, np.ones(len(ids), bool))]:
        pos = np.minimum(np.searchsorted(ids, ids + step), len(ids) - 1)
        hit = valid & (ids[pos] == ids + step)
        steps.append(np.linalg.norm(pixels[pos[hit]] - pixels[hit], axis=1))
    steps = np.concatenate(steps)
    if not len(steps):
        return 0
    gap_px = 0.5 * float(steps.min()) * (1.0 - target.marker_length / target.square_length)
    return int(min(np.floor(gap_px), 10))


def detect(image: np.ndarray, target: TargetSpec, *, K=None, dist=None) -> "Detection | None":
    """Find `target`'s features in one image.

    ChArUco: OpenCV's `CharucoDetector` (given `K`/`dist` when known, so the
    corners are interpolated through the camera model), then `cornerSubPix` on
    the chessboard corners with a window kept inside the white gap between
    the corner and the nearest marker. Single ArUco: `ArucoDetector` with
    `CORNER_REFINE_SUBPIX`, the marker whose id is `target.first_id`. ArUco
    (or AprilTag) grid: every board marker seen once. Chessboard:
    `findChessboardCornersSB` (exhaustive) and `cornerSubPix` (`_refine_chessboard`); circle grids:
    `findCirclesGrid`; both find the whole grid or nothing, and their ids are
    then fixed so that the target frame does not depend on how the board
    lies in the image (`_orient_grid`). With non-zero `dist`, all of this runs on
    the image undistorted onto a padded pinhole canvas and the features are mapped
    back through the lens (`_detect_rectified`).

    **Arguments:**

    - `image`: (H, W) grey or (H, W, 3) BGR, uint8.
    - `target`: what to look for.
    - `K`, `dist`: the camera's intrinsics (3, 3) px and OpenCV distortion
      coefficients, if known.

    **Returns:** a `Detection`, or `None` when the target is not found or has
    fewer than 4 features (ChArUco corners) / not all 4 marker corners.
    """
    grey = _grey(image)
    K_key, dist_key = _camera_key(K, dist)
    if dist_key is not None and any(dist_key):
        return _detect_rectified(grey, target, K_key, dist_key)
    return _detect_in(grey, target, K_key, dist_key)


def _detect_in(grey: np.ndarray, target: TargetSpec, K_key: tuple | None, dist_key: tuple | None):
    """`detect` on the image as it is (`K_key`, `dist_key`: `_camera_key`'s)."""
    if target.kind in GRID_KINDS:
        return _detect_grid(grey, target)
    detector = _detector(target, K_key, dist_key, threading.get_ident())
    if target.kind == "aruco_grid":
        return _detect_marker_grid(grey, target, detector)
    if target.kind == "aruco":
        corners, ids, _ = detector.detectMarkers(grey)
        if ids is None:
            return None
        hits = np.flatnonzero(ids.ravel() == target.first_id)
        if len(hits) != 1:  # absent, or ambiguous (the same id twice in view)
            return None
        return Detection(np.arange(4), corners[hits[0]].reshape(4, 2))
    corners, ids, _, _ = detector.detectBoard(grey)
    if ids is None or len(ids) < MIN_POINTS:
        return None
    ids = ids.ravel().astype(np.int64)
    order = np.argsort(ids)
    ids, pixels = ids[order], corners.reshape(-1, 2)[order]
    half = _refine_window(target, pixels, ids)
    if half >= 2:
        pixels = cv2.cornerSubPix(
            grey, np.ascontiguousarray(pixels), (half, half), (-1, -1), _SUBPIX_CRITERIA
        )
    return Detection(ids, pixels)


#: The most the rectified canvas may add on each side, as a share of the image's size: a
#: barrel lens's periphery lands outside the original frame once undistorted, by as much
#: as the lens bends it; a wider reach would be a fisheye, which this model does not fit.
RECTIFY_MARGIN_MAX = 0.5


def _rectify_margins(K: np.ndarray, dist: np.ndarray, shape: tuple) -> tuple[int, int]:
    """`(mx, my)`, the pixels to add on each side of an (H, W) image's pinhole canvas so that
    every pixel of the distorted image lands on it once undistorted: the overhang of the
    undistorted image border, plus two pixels, capped at `RECTIFY_MARGIN_MAX`. Border points
    the inverse lens model does not reach (beyond the fold of a strong barrel polynomial)
    are left out."""
    h, w = shape
    s = np.linspace(0.0, 1.0, 65)
    border = np.concatenate(
        [
            np.c_[s * (w - 1), np.zeros_like(s)],
            np.c_[s * (w - 1), np.full_like(s, h - 1)],
            np.c_[np.zeros_like(s), s * (h - 1)],
            np.c_[np.full_like(s, w - 1), s * (h - 1)],
        ]
    )
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    flat = cv2.undistortPointsIter(border.reshape(-1, 1, 2), K, dist, None, K, criteria).reshape(-1, 2)
    rays = np.c_[flat, np.ones(len(flat))] @ np.linalg.inv(K).T
    back = cv2.projectPoints(rays.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, dist)[0].reshape(-1, 2)
    flat = flat[np.linalg.norm(back - border, axis=1) < 0.05]
    if not len(flat):
        return int(RECTIFY_MARGIN_MAX * w), int(RECTIFY_MARGIN_MAX * h)
    over_x = max(0.0, -flat[:, 0].min(), flat[:, 0].max() - (w - 1))
    over_y = max(0.0, -flat[:, 1].min(), flat[:, 1].max() - (h - 1))
    mx = min(int(np.ceil(over_x)) + 2, int(RECTIFY_MARGIN_MAX * w))
    my = min(int(np.ceil(over_y)) + 2, int(RECTIFY_MARGIN_MAX * h))
    return mx, my


@lru_cache(maxsize=8)
def _rectify_maps(K: tuple, dist: tuple, shape: tuple) -> tuple:
    """`(map_x, map_y, K_rect)`: OpenCV's maps from a margin-padded pinhole canvas with the
    camera's focal lengths (`K_rect`) to the distorted image of `shape` (H, W)."""
    h, w = shape
    K = np.asarray(K, np.float64).reshape(3, 3)
    dist = np.asarray(dist, np.float64)
    mx, my = _rectify_margins(K, dist, shape)
    K_rect = K.copy()
    K_rect[0, 2] += mx
    K_rect[1, 2] += my
    map_x, map_y = cv2.initUndistortRectifyMap(K, dist, None, K_rect, (w + 2 * mx, h + 2 * my), cv2.CV_32FC1)
    return map_x, map_y, K_rect


def _detect_rectified(grey: np.ndarray, target: TargetSpec, K: tuple, dist: tuple) -> "Detection | None":
    """`target` found in the image undistorted onto a pinhole canvas, its features mapped
    back through the lens. A lens bends a square's edges through each corner, and the
    sub-pixel refinement, which takes them for straight lines, errs by amounts that change
    slowly as a corner crosses the image: errors that agree from one frame to the next of a
    sweep and bias its fit (docs/performance.md, "The other camera cases over the same seeds").
    On the canvas the edges are straight again."""
    map_x, map_y, K_rect = _rectify_maps(K, dist, grey.shape)
    canvas = cv2.remap(grey, map_x, map_y, cv2.INTER_CUBIC, borderMode=cv2.BORDER_CONSTANT, borderValue=128)
    found = _detect_in(canvas, target, *_camera_key(K_rect, None))
    if found is None:
        return None
    rays = np.c_[found.pixels, np.ones(len(found.pixels))] @ np.linalg.inv(K_rect).T
    K_mat = np.asarray(K, np.float64).reshape(3, 3)
    pixels = cv2.projectPoints(rays.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K_mat, np.asarray(dist))[0]
    return Detection(found.ids, pixels.reshape(-1, 2))


def _detect_marker_grid(grey: np.ndarray, target: TargetSpec, detector) -> "Detection | None":
    """The 4 corners of every board marker seen exactly once, ids `4 (id - first_id) + corner`."""
    corners, ids, _ = detector.detectMarkers(grey)
    if ids is None:
        return None
    ids = ids.ravel().astype(np.int64) - target.first_id
    inside = (ids >= 0) & (ids < target.num_markers)
    unique, counts = np.unique(ids[inside], return_counts=True)
    keep = inside & np.isin(ids, unique[counts == 1])  # a repeated id is ambiguous: drop it
    if not keep.any():
        return None
    feature = (4 * ids[keep][:, None] + np.arange(4)).ravel()
    pixels = np.concatenate([np.asarray(corners[k]).reshape(4, 2) for k in np.flatnonzero(keep)])
    order = np.argsort(feature)
    return Detection(feature[order], pixels[order])


def _detect_grid(grey: np.ndarray, target: TargetSpec) -> "Detection | None":
    if target.kind == "chessboard":
        ok, pixels = cv2.findChessboardCornersSB(grey, target.pattern, flags=cv2.CALIB_CB_EXHAUSTIVE)
        if ok:
            pixels = _refine_chessboard(grey, target, pixels)
    else:
        flags = cv2.CALIB_CB_SYMMETRIC_GRID if target.kind == "circles" else cv2.CALIB_CB_ASYMMETRIC_GRID
        ok, pixels = cv2.findCirclesGrid(grey, target.pattern, flags=flags)
        if not ok:  # the clustering variant copes with stronger perspective
            ok, pixels = cv2.findCirclesGrid(grey, target.pattern, flags=flags | cv2.CALIB_CB_CLUSTERING)
    if not ok or pixels is None:
        return None
    pixels = np.asarray(pixels, np.float64).reshape(-1, 2)
    ids = _orient_grid(grey, target, pixels)
    if ids is None:
        return None
    order = np.argsort(ids)
    return Detection(ids[order], pixels[order])


#: `cornerSubPix`'s half-window on a chessboard, as a share of the shortest square side in the image.
CHESSBOARD_WINDOW = 0.4


def _refine_chessboard(grey: np.ndarray, target: TargetSpec, pixels: np.ndarray) -> np.ndarray:
    """A full chessboard grid (OpenCV's order) refined by `cornerSubPix`.

    The half-window is `CHESSBOARD_WINDOW` times the shortest side of a square in the
    image (px; 2 to 10): the window then holds the corner's own two edges and none of
    its neighbours' (one square away), even where the board is foreshortened. On rendered
    captures this is twice as accurate as `findChessboardCornersSB`'s `CALIB_CB_ACCURACY`
    at a quarter of its CPU (docs/performance.md, "Chessboard corners").
    """
    cols, rows = target.pattern
    grid = np.asarray(pixels, np.float64).reshape(rows, cols, 2)
    side = min(
        np.linalg.norm(np.diff(grid, axis=1), axis=-1).min(),
        np.linalg.norm(np.diff(grid, axis=0), axis=-1).min(),
    )
    half = int(np.clip(np.floor(CHESSBOARD_WINDOW * side), 2, 10))
    start = np.ascontiguousarray(pixels, np.float32).reshape(-1, 1, 2)
    return cv2.cornerSubPix(grey, start, (half, half), (-1, -1), _SUBPIX_CRITERIA)


@lru_cache(maxsize=32)
def _grid_relabellings(target: TargetSpec) -> tuple[np.ndarray, ...]:
    """Every relabelling of the grid's points by a turn or a mirror image that maps
    the point set onto itself (the labellings OpenCV's grid finders may return)."""
    P = target_points(target)[:, :2]
    c = P.mean(0)
    scale = np.max(np.abs(P - c)) + 1e-12
    out = []
    for mirror in (1.0, -1.0):
        for k in range(4):
            a = 0.5 * np.pi * k
            R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]) @ np.diag([mirror, 1.0])
            Q = (P - c) @ R.T + c
            d = np.linalg.norm(Q[:, None] - P[None], axis=-1)
            perm = np.argmin(d, axis=1)
            if np.max(d[np.arange(len(P)), perm]) < 1e-9 * scale and len(set(perm.tolist())) == len(P):
                out.append(perm)
    return tuple(out)


def _orient_grid(grey: np.ndarray, target: TargetSpec, pixels: np.ndarray) -> "np.ndarray | None":
    """Feature ids for a full grid in OpenCV's order, or None for a grid that is not the target.

    OpenCV's grid finders order the points by how the grid lies in the image,
    so the same board turned by 180 degrees comes back with id 0 at the other
    end. Of the relabellings that map the grid onto itself, keep those whose
    plane-to-image homography preserves orientation (the target frame's z
    points away from the camera, so a board seen from the front has a
    positive Jacobian determinant), then, for a chessboard, the one that puts
    the most squares on their printed colour (square (0, 0) black), sampled
    at every square's centre through the homography. A chessboard grid with
    more than `MAX_WRONG_SQUARES` of its squares on the wrong colour is
    refused: the finder took the board's outer edge for a row of corners (a
    grid shifted by one square). A symmetric target (`TargetSpec.symmetric`)
    keeps its first candidate: the hand-eye front end resolves it from the
    robot's motion.
    """
    P = target_points(target)[:, :2]
    best, best_score = None, -np.inf
    for perm in _grid_relabellings(target):
        H, _ = cv2.findHomography(P[perm], pixels, 0)
        if H is None:
            continue
        c = np.append(P.mean(0), 1.0)
        w = H[2] @ c
        if np.linalg.det(H) * w <= 0:  # mirrored: not the printed face
            continue
        score = _chessboard_score(grey, target, H) if target.kind == "chessboard" else 0.0
        if score > best_score:
            best, best_score = perm, score
    if best is None or (target.kind == "chessboard" and best_score < 1.0 - 2.0 * MAX_WRONG_SQUARES):
        return None
    return best


#: Share of a chessboard's squares allowed on the wrong colour (sampling at an edge, glare).
MAX_WRONG_SQUARES = 0.03


def _chessboard_score(grey: np.ndarray, target: TargetSpec, H: np.ndarray) -> float:
    """Share of the squares whose centre is on its printed side of the black/white threshold
    (square (0, 0) black), minus the share on the wrong side: 1 for a perfect match, -1 inverted."""
    cols, rows = target.squares
    b, a = np.mgrid[0:rows, 0:cols]
    centres = np.stack([(a.ravel() + 0.5), (b.ravel() + 0.5)], 1) * target.square_length
    uv = cv2.perspectiveTransform(centres.reshape(-1, 1, 2), H).reshape(-1, 2)
    h, w = grey.shape
    inside = (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)
    u, v = np.clip(np.round(uv).astype(int), 0, [w - 1, h - 1]).T
    value = grey[v, u].astype(np.float64)
    black = (a + b).ravel() % 2 == 0
    if not (black & inside).any() or not (~black & inside).any():
        return -1.0
    threshold = 0.5 * (np.median(value[black & inside]) + np.median(value[~black & inside]))
    right = np.where(black, value < threshold, value > threshold)[inside]
    return float(2.0 * right.mean() - 1.0)


# --------------------------------------------------------------------------- many files


def _detect_file(path: str, targets: tuple, K, dist) -> dict:
    if not os.path.isfile(path):
        raise VisionError(f"{path}: image file missing")
    image = cv2.imread(path, cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise VisionError(f"{path}: not a readable image")
    found = {}
    for target in targets:
        try:
            det = detect(image, target, K=K, dist=dist)
        except cv2.error as e:
            raise VisionError(f"{path}: OpenCV failed on target {target.name!r}: {e}") from None
        if det is not None:
            found[target.name] = det
    return found


def _detect_chunk(paths: list, targets: tuple, K, dist) -> list:
    return [_detect_file(p, targets, K, dist) for p in paths]


@lru_cache(maxsize=1)
def _process_context():
    """`forkserver`, its server preloaded with this module: the server starts (and
    imports jaxcal) once per process, then every worker is a cheap fork of it.
    Never a plain fork of the caller, which may be running JAX's threads."""
    import multiprocessing

    if "forkserver" not in multiprocessing.get_all_start_methods():
        return get_context("spawn")
    context = get_context("forkserver")
    context.set_forkserver_preload([__name__])
    return context


def _stop(executor, futures) -> None:
    """An interrupted or failed run: drop the chunks not started and end the workers now
    (a process pool's workers are terminated, so that Ctrl-C leaves no child process)."""
    for f in futures:
        f.cancel()
    processes = _terminate(executor, shutdown=True)
    for proc in processes:
        proc.join(timeout=5)


def _terminate(executor, shutdown: bool = False) -> list:
    """Terminate a process pool's workers (a thread pool has none), the executor shut down first
    when `shutdown`; the workers. Also what `jaxcal._interrupt` runs when it ends the process."""
    processes = list((getattr(executor, "_processes", None) or {}).values())
    if shutdown:
        executor.shutdown(wait=False, cancel_futures=True)
    for proc in processes:
        proc.terminate()
    return processes


def _init_worker() -> None:
    cv2.setNumThreads(1)  # one image per core; OpenCV's own threads would oversubscribe


def detect_frames(
    paths: Sequence,
    targets: Sequence[TargetSpec],
    *,
    K=None,
    dist=None,
    workers: int | None = None,
    progress: bool = True,
    pool: str = "thread",
) -> list[dict[str, Detection]]:
    """Detect every target in every image file.

    Images are read with `cv2.imread(..., IMREAD_GRAYSCALE)`. Long lists are
    spread over a pool of `workers` threads: OpenCV releases Python's lock
    while it reads and detects, so threads run in parallel without starting a
    process, whatever the start method, from any script (no `__main__` guard
    needed). `pool="process"` uses processes instead (the `forkserver`
    context, `spawn` where there is none: the caller may be running JAX, which
    must not be forked); its first pool starts a server that imports jaxcal,
    and a script that calls it at import time needs the usual
    `if __name__ == "__main__":` guard. An interrupted run (Ctrl-C) or a
    failed image ends the pool's workers before the exception propagates.

    **Arguments:**

    - `paths`: image files.
    - `targets`: the targets to look for (distinct `name`s).
    - `K`, `dist`: the camera's intrinsics, if known (see `detect`).
    - `workers`: `None`: every core, fewer for short lists (at least
      4 images per thread, 32 per process); `1`: in the calling thread;
      `k > 1`: exactly k.
    - `progress`: show a rich progress bar.
    - `pool`: `"thread"` (default) or `"process"`.

    **Returns:** one dict per path, in the order of `paths`: target name ->
    `Detection`, only for the targets found.

    **Raises:** `VisionError` naming a missing or unreadable file.
    """
    paths = [str(p) for p in paths]
    targets = tuple(targets)
    for t in targets:
        if not isinstance(t, TargetSpec):
            raise VisionError(f"targets must be TargetSpec, got {type(t).__name__}")
    names = [t.name for t in targets]
    if len(set(names)) != len(names):
        raise VisionError(f"targets must have distinct names, got {names}")
    if pool not in ("process", "thread"):
        raise VisionError(f"pool must be 'process' or 'thread', got {pool!r}")
    _camera_key(K, dist)  # check once, here, not in every worker
    K = None if K is None else np.asarray(K, np.float64)
    dist = None if dist is None else np.asarray(dist, np.float64)
    if workers is None:
        per_worker = _POOL_MIN_PER_WORKER if pool == "process" else _THREAD_MIN_PER_WORKER
        workers = min(os.cpu_count() or 1, max(1, len(paths) // per_worker))
    elif int(workers) < 1:
        raise VisionError(f"workers must be >= 1, got {workers}")
    workers = max(1, min(int(workers), len(paths)))
    results: list = []
    with progress_bar(progress and len(paths) > 0, f"detecting markers in {len(paths)} images") as bar:
        task = bar.add_task("detect", total=len(paths)) if bar is not None else None
        if workers == 1:
            for p in paths:
                results.append(_detect_file(p, targets, K, dist))
                if bar is not None:
                    bar.advance(task)
            return results
        # Small chunks keep the bar moving and the cores balanced; each chunk is one task.
        size = max(1, min(16, len(paths) // (4 * workers)))
        chunks = [paths[i : i + size] for i in range(0, len(paths), size)]
        if pool == "process":
            executor = ProcessPoolExecutor(workers, mp_context=_process_context(), initializer=_init_worker)
        else:
            executor = ThreadPoolExecutor(workers, thread_name_prefix="jaxcal detect")
        futures = []
        try:
            with _interrupt.partial(lambda: _terminate(executor)):
                futures = [executor.submit(_detect_chunk, c, targets, K, dist) for c in chunks]
                for future, chunk in zip(futures, chunks):
                    results.extend(future.result())
                    if bar is not None:
                        bar.advance(task, len(chunk))
        except BaseException:
            _stop(executor, futures)
            raise
        executor.shutdown()
    return results
