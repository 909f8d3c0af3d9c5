"""Marker detection: ChArUco corners and single-ArUco corners in one image, or many files."""

import os
import threading
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from dataclasses import dataclass
from functools import lru_cache
from multiprocessing import get_context

import cv2
import numpy as np

from .._progress import progress as progress_bar
from ..errors import VisionError
from ..markers import TargetSpec, aruco_dictionary

# Fewest features that still fix a pose: 4 ChArUco corners, or the 4 corners of a marker.
MIN_POINTS = 4
_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 1e-4)
# Below this many images per worker, a process pool costs more (worker start-up,
# ~2 s) than it saves (~10 ms per 640x480 image).
_POOL_MIN_PER_WORKER = 32


@dataclass(frozen=True, eq=False)
class Detection:
    """One target's features found in one image.

    - `ids`: (n,) int, feature ids = row indices into `TargetSpec.points()`
      (ChArUco: OpenCV's corner ids; single ArUco: the corner 0..3 in the order
      top-left, top-right, bottom-right, bottom-left, i.e.
      `4 * (marker id - first_id) + corner`). Sorted ascending.
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
    if target.kind == "aruco":
        return cv2.aruco.ArucoDetector(aruco_dictionary(target.dictionary), _aruco_parameters())
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
    `CORNER_REFINE_SUBPIX`, the marker whose id is `target.first_id`.

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
    detector = _detector(target, K_key, dist_key, threading.get_ident())
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
    imports jaxcal, ~2 s) once per process, then every worker is a cheap fork of
    it. Never a plain fork of the caller, which may be running JAX's threads."""
    import multiprocessing

    if "forkserver" not in multiprocessing.get_all_start_methods():
        return get_context("spawn")
    context = get_context("forkserver")
    context.set_forkserver_preload([__name__])
    return context


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
    pool: str = "process",
) -> list[dict[str, Detection]]:
    """Detect every target in every image file.

    Images are read with `cv2.imread(..., IMREAD_GRAYSCALE)`. Long lists are
    spread over a pool of `workers`. The process pool uses the `forkserver`
    context (`spawn` where there is none): the caller may be running JAX,
    which must not be forked. A script that calls this at import time
    therefore needs the usual `if __name__ == "__main__":` guard. The first
    pool of a process pays about 2 s to start the server (it imports
    jaxcal), which is why short lists run here. `pool="thread"` uses threads
    instead (OpenCV releases the GIL while it detects): no start-up cost.

    **Arguments:**

    - `paths`: image files.
    - `targets`: the targets to look for (distinct `name`s).
    - `K`, `dist`: the camera's intrinsics, if known (see `detect`).
    - `workers`: `None`: every core, fewer for short lists (at least
      32 images per worker); `1`: in this process; `k > 1`: exactly k.
    - `progress`: show a rich progress bar.
    - `pool`: `"process"` or `"thread"`.

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
        workers = min(os.cpu_count() or 1, max(1, len(paths) // _POOL_MIN_PER_WORKER))
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
            executor = ThreadPoolExecutor(workers)
        with executor:
            futures = [executor.submit(_detect_chunk, c, targets, K, dist) for c in chunks]
            try:
                for future, chunk in zip(futures, chunks):
                    results.extend(future.result())
                    if bar is not None:
                        bar.advance(task, len(chunk))
            except BaseException:
                for f in futures:
                    f.cancel()
                raise
    return results
