"""Detection + PnP throughput of `jaxcal.vision` against calling OpenCV directly.

On a rendered dataset (default: `jaxcal simulate --resolution 640x480
--frames-per-joint 10`, 60 frames of a UR5e with a 5x4 ChArUco plate), time
reading every image, detecting the board and solving its pose:

- `opencv_s`: the peer, OpenCV by hand: `imread` + `CharucoDetector.detectBoard`
  + `cornerSubPix` + `solvePnP` (IPPE) + `solvePnPRefineLM`.
- `jaxcal_s`: `detect_frames(workers=1)` + `estimate_pose` (which adds the
  reprojection Jacobian and the covariance).
- `pool_s`: the same with the process pool over every core (a new pool per
  call, its workers forked from the already running server);
  `pool_first_s`: the first such call, which also starts the server;
  `thread_s`: with `pool="thread"`.

Each figure is the best of `--repeat` runs, the contenders interleaved
(`median_s`: the medians). `overhead_pct` compares wall-clock times,
`overhead_cpu_pct` this process's CPU times (steadier on a busy machine). The 60-frame figure for OpenCV's peer counts
one pose fewer where IPPE fails on 4 oblique corners (jaxcal falls back to
SQPnP).

    python benchmarks/vision.py --json results/vision.json
    python benchmarks/vision.py --dataset data/ur5e_sweeps --frames 4 --repeat 1 --json OUT  # smallest (the tests')
"""

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np


def opencv_by_hand(paths, spec, K, dist) -> int:
    """The peer: what a user writes with OpenCV alone. Returns the poses found."""
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    charuco = cv2.aruco.CharucoParameters()
    charuco.cameraMatrix, charuco.distCoeffs = K, dist.reshape(1, -1)
    detector = cv2.aruco.CharucoDetector(spec.board(), charuco, params)
    points = spec.points()
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 1e-4)
    found = 0
    for p in paths:
        grey = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        corners, ids, _, _ = detector.detectBoard(grey)
        if ids is None or len(ids) < 4:
            continue
        corners = cv2.cornerSubPix(grey, corners, (2, 2), (-1, -1), criteria)
        obj = points[ids.ravel()]
        ok, rvec, tvec = cv2.solvePnP(obj, corners, K, dist, flags=cv2.SOLVEPNP_IPPE)
        if not ok or rvec is None:
            continue
        cv2.solvePnPRefineLM(obj, corners, K, dist, rvec, tvec)
        found += 1
    return found


def with_jaxcal(paths, spec, K, dist, **pool) -> int:
    from jaxcal.vision import detect_frames, estimate_pose

    found = 0
    for frame in detect_frames(paths, [spec], K=K, dist=dist, progress=False, **pool):
        det = frame.get(spec.name)
        if det is not None and estimate_pose(det, spec, K, dist) is not None:
            found += 1
    return found


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", help="a dataset directory (default: render one into a temp dir)")
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--frames", type=int, help="time only the first N frames of the first camera")
    parser.add_argument("--json", help="write the results here")
    args = parser.parse_args(argv)

    from jaxcal.io.dataset import load_dataset

    with tempfile.TemporaryDirectory() as tmp:
        root = args.dataset
        if root is None:
            from jaxcal.sim.simulate import SimConfig, simulate

            root = simulate(
                SimConfig(resolution=(640, 480), frames_per_joint=10), Path(tmp) / "ds", progress=False
            )
        ds = load_dataset(root)
        cam, spec = ds.cameras[0], ds.targets[0].spec
        paths = [
            ds.image_path(i) for i in range(len(ds.frames["file"])) if ds.frames["camera"][i] == cam.name
        ][: args.frames]
        K, dist = cam.K, cam.dist
        cores = os.cpu_count() or 1
        contenders = {
            "opencv_s": lambda: opencv_by_hand(paths, spec, K, dist),
            "jaxcal_s": lambda: with_jaxcal(paths, spec, K, dist, workers=1),
            "pool_s": lambda: with_jaxcal(paths, spec, K, dist, workers=cores),
            "thread_s": lambda: with_jaxcal(paths, spec, K, dist, workers=cores, pool="thread"),
        }
        times = {name: [] for name in contenders}
        cpu = {name: [] for name in contenders}
        found = {}
        for _ in range(args.repeat):
            for name, run in contenders.items():
                start, start_cpu = time.perf_counter(), time.process_time()
                found[name] = run()
                times[name].append(time.perf_counter() - start)
                cpu[name].append(time.process_time() - start_cpu)
        best = {name: min(t) for name, t in times.items()}
        best_cpu = {name: min(cpu[name]) for name in ("opencv_s", "jaxcal_s")}
    if len(set(found.values())) != 1:
        print(f"warning: the contenders found different numbers of poses: {found}", file=sys.stderr)
    results = {
        "frames": len(paths),
        "poses": found["jaxcal_s"],
        "cores": cores,
        **best,
        "overhead_pct": 100.0 * (best["jaxcal_s"] / best["opencv_s"] - 1.0),
        "pool_speedup": best["jaxcal_s"] / best["pool_s"],
        "thread_speedup": best["jaxcal_s"] / best["thread_s"],
        "overhead_cpu_pct": 100.0 * (best_cpu["jaxcal_s"] / best_cpu["opencv_s"] - 1.0),
        "pool_first_s": times["pool_s"][0],
        "median_s": {name: float(np.median(t)) for name, t in times.items()},
        "opencv_ms_per_frame": 1e3 * best["opencv_s"] / len(paths),
        "jaxcal_ms_per_frame": 1e3 * best["jaxcal_s"] / len(paths),
    }
    text = json.dumps(results, indent=2)
    print(text)
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
