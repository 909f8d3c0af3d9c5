"""Chessboard corner detectors against the truth on rendered hand-eye captures (issue 35).

`jaxcal handeye` finds chessboards with `cv2.findChessboardCornersSB`; with
`CALIB_CB_ACCURACY` it costs about 140 ms per 640x480 image. This benchmark
renders hand-eye captures (`jaxcal.sim.handeye.simulate_hand_eye`, the
default 8x7-square 25 mm chessboard, 640x480, eye-in-hand and eye-to-hand,
with and without lens distortion), projects the board's true corners with
the capture's true poses and intrinsics (`truth.json`), and runs each
candidate detector on every image: clean, and degraded by the
rolling-shutter preset's sensor noise and JPEG at quality 90
(`jaxcal.sim.camera.CameraModel.degrade`, no motion: a hand-eye frame is
taken stopped). Per detector and image set: the corner error's RMS and 99th
percentile (px, each detected corner against its nearest true corner, so
the labelling does not count), the share of images with the whole grid
found, and the median CPU time per image (`time.process_time`, OpenCV on
one thread).

The candidates: `SB_EXH_ACC` (today's), `SB_EXH`, `SB` (no flags), each of
the last two followed by `cv2.cornerSubPix` with a half-window of
`FRACTION` times the shortest side of a square in the image (px, between 2
and `MAX_HALF`): the window must hold the corner's two edges and nothing of
the neighbouring corners, one square away; `classic_4q`:
`findChessboardCorners` (adaptive threshold, normalised, fast check) and
`find4QuadCornerSubpix`; `classic_subpix`: the same with `cornerSubPix`.

`--images DIR` also runs every detector on real images (no truth) and
reports each one's RMS difference from `SB_EXH_ACC`.

    .venv/bin/python benchmarks/chessboard_detect.py --seeds 0 1 --json results/chessboard_detect.json
"""

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from jaxcal.sim.camera import CameraModel
from jaxcal.sim.handeye import HandEyeSimConfig, simulate_hand_eye

FRACTION = 0.4
MAX_HALF = 10
SUBPIX = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 1e-4)
NOISY = CameraModel(name="noisy", gain_dn=0.094, read_noise_dn=2.0, jpeg_quality=90)
DISTORTION = (-0.08, 0.05, 0.0005, -0.0003, 0.0)


def square_px(pixels: np.ndarray, pattern) -> float:
    """The shortest distance between grid neighbours (px) of a full grid in OpenCV's order."""
    cols, rows = pattern
    g = pixels.reshape(rows, cols, 2)
    d = np.concatenate(
        [
            np.linalg.norm(np.diff(g, axis=1), axis=-1).ravel(),
            np.linalg.norm(np.diff(g, axis=0), axis=-1).ravel(),
        ]
    )
    return float(d.min())


def subpix(grey, pixels, pattern, fraction=FRACTION):
    half = int(np.clip(np.floor(fraction * square_px(pixels, pattern)), 2, MAX_HALF))
    return cv2.cornerSubPix(grey, np.ascontiguousarray(pixels, np.float32), (half, half), (-1, -1), SUBPIX)


def sb(flags, refine=None):
    def run(grey, pattern):
        ok, p = cv2.findChessboardCornersSB(grey, pattern, flags=flags)
        if not ok:
            return None
        p = p.reshape(-1, 1, 2)
        return (refine(grey, p, pattern) if refine else p).reshape(-1, 2)

    return run


def classic(refine):
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FAST_CHECK

    def run(grey, pattern):
        ok, p = cv2.findChessboardCorners(grey, pattern, flags=flags)
        if not ok:
            return None
        if refine == "4q":
            half = int(np.clip(np.floor(FRACTION * square_px(p.reshape(-1, 2), pattern)), 2, MAX_HALF))
            ok, p = cv2.find4QuadCornerSubpix(grey, p, (half, half))
            return p.reshape(-1, 2) if ok else None
        return subpix(grey, p, pattern).reshape(-1, 2)

    return run


EXH, ACC = cv2.CALIB_CB_EXHAUSTIVE, cv2.CALIB_CB_ACCURACY
DETECTORS = {
    "SB_EXH_ACC": sb(EXH | ACC),
    "SB_ACC": sb(ACC),
    "SB_EXH": sb(EXH),
    "SB": sb(0),
    "SB_EXH+subpix": sb(EXH, subpix),
    "SB+subpix": sb(0, subpix),
    "SB+subpix0.25": sb(0, lambda g, p, pat: subpix(g, p, pat, 0.25)),
    "SB_EXH_ACC+subpix": sb(EXH | ACC, subpix),
    "classic_4q": classic("4q"),
    "classic_subpix": classic("subpix"),
}


def classic_then_sb(grey, pattern):
    """`classic_subpix`, and where it finds nothing, `SB_EXH+subpix`."""
    p = DETECTORS["classic_subpix"](grey, pattern)
    return DETECTORS["SB_EXH+subpix"](grey, pattern) if p is None else p


DETECTORS["classic|SB_EXH+subpix"] = classic_then_sb


def true_pixels(capture: Path, points: np.ndarray) -> tuple[list, tuple]:
    truth = json.loads((capture / "truth.json").read_text())
    K = np.asarray(truth["K"]["cam0"])
    dist = np.asarray(truth["config"]["distortion"], np.float64)
    T_rc = np.asarray(truth["T_robot_cam"]["cam0"])
    T_rb = np.asarray(truth["T_robot_board"])
    out = []
    for T_be in np.asarray(truth["T_base_ee"]):
        if truth["arrangement"] == "eye_in_hand":
            T_cb = np.linalg.inv(T_be @ T_rc) @ T_rb
        else:
            T_cb = np.linalg.inv(T_rc) @ T_be @ T_rb
        rvec = cv2.Rodrigues(T_cb[:3, :3])[0]
        uv, _ = cv2.projectPoints(points, rvec, T_cb[:3, 3], K, dist)
        out.append(uv.reshape(-1, 2))
    return out


def render(seeds, frames, tmp: Path) -> list:
    """(name, [(grey, truth (n, 2))]) per image set."""
    config = HandEyeSimConfig()
    points = config.target.points()
    sets = []
    for arrangement in (True, False):
        for dist in ((0.0,) * 5, DISTORTION):
            images = []
            for seed in seeds:
                c = HandEyeSimConfig(eye_in_hand=arrangement, frames=frames, seed=seed, distortion=dist)
                path = simulate_hand_eye(c, tmp / f"{arrangement}_{dist[0]}_{seed}")
                uv = true_pixels(path, points)
                for f in range(frames):
                    grey = cv2.imread(str(path / "images" / "cam0" / f"{f:04d}.png"), cv2.IMREAD_GRAYSCALE)
                    images.append((grey, uv[f]))
            name = f"{'eye_in_hand' if arrangement else 'eye_to_hand'}{'_distorted' if dist[0] else ''}"
            sets.append((name, images))
            rng = np.random.default_rng(7)
            noisy = [(NOISY.degrade(g.astype(np.float32), rng), uv) for g, uv in images]
            sets.append((name + "_noisy_jpeg90", noisy))
    return sets


def measure(detector, images, pattern) -> dict:
    errors, cpu, found, per_image, missed, wrong = [], [], 0, [], 0, 0
    for grey, truth in images:
        t = time.process_time()
        p = detector(grey, pattern)
        cpu.append(time.process_time() - t)
        per_image.append(None)
        if p is None:
            missed += 1
            continue
        d = np.linalg.norm(p[:, None] - truth[None], axis=-1).min(1)
        if d.max() > 3.0:  # a wrong grid: not a detection
            wrong += 1
            continue
        found += 1
        errors.append(d)
        per_image[-1] = float(np.sqrt(np.mean(d**2)))
    e = np.concatenate(errors) if errors else np.full(1, np.nan)
    return {
        "missed": missed,
        "wrong_grid": wrong,
        "rms_px": float(np.sqrt(np.mean(e**2))),
        "p99_px": float(np.percentile(e, 99)),
        "max_px": float(e.max()),
        "rate": found / len(images),
        "cpu_ms": 1e3 * statistics.median(cpu),
        "per_image_rms": per_image,
    }


def calibration_rms(greys, det, pattern) -> float:
    """`cv2.calibrateCamera`'s reprojection RMS (px) on the images where `det` finds the board
    (the labelling each finder returns is its own: OpenCV's order from one image to the next)."""
    cols, rows = pattern
    obj = np.zeros((rows * cols, 3), np.float32)
    obj[:, :2] = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2)
    found = [det(g, pattern) for g in greys]
    pts = [p.reshape(-1, 1, 2).astype(np.float32) for p in found if p is not None]
    if len(pts) < 3:
        return float("nan")
    h, w = greys[0].shape
    rms, *_ = cv2.calibrateCamera([obj] * len(pts), pts, (w, h), None, None)
    return float(rms)


def real_images(folder: Path, pattern) -> dict:
    files = sorted(folder.glob("*.jpg")) + sorted(folder.glob("*.png"))
    greys = [cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) for f in files]
    ref = [DETECTORS["SB_EXH_ACC"](g, pattern) for g in greys]
    out = {}
    for name, det in DETECTORS.items():
        diffs, cpu, found = [], [], 0
        for g, r in zip(greys, ref):
            t = time.process_time()
            p = det(g, pattern)
            cpu.append(time.process_time() - t)
            if p is None:
                continue
            found += 1
            if r is not None:
                diffs.append(np.linalg.norm(p[:, None] - r[None], axis=-1).min(1))
        d = np.concatenate(diffs) if diffs else np.full(1, np.nan)
        out[name] = {
            "calibration_rms_px": calibration_rms(greys, det, pattern),
            "rms_vs_SB_EXH_ACC_px": float(np.sqrt(np.mean(d**2))),
            "p99_vs_SB_EXH_ACC_px": float(np.percentile(d, 99)),
            "rate": found / len(greys),
            "cpu_ms": 1e3 * statistics.median(cpu),
        }
        print(f"  real {name:20s} {out[name]}", flush=True)
    return {"images": len(greys), "pattern": list(pattern), "detectors": out}


def pooled(sets: dict) -> dict:
    """Per detector over every set: the corner RMS and 99th percentile (recomputed from the per-image
    RMS: the mean of squares over equal-sized grids), the detection rate, the median of the sets'
    median CPU times, and on how many images found by both it beats `SB_EXH_ACC`'s per-image RMS."""
    out = {}
    for det in next(iter(sets.values())):
        per = [x for s in sets.values() for x in s[det]["per_image_rms"]]
        ref = [x for s in sets.values() for x in s["SB_EXH_ACC"]["per_image_rms"]]
        both = [(a, b) for a, b in zip(per, ref) if a is not None and b is not None]
        found = [x for x in per if x is not None]
        out[det] = {
            "rms_px": float(np.sqrt(np.mean(np.square(found)))),
            "p99_px_max_over_sets": max(s[det]["p99_px"] for s in sets.values()),
            "rate": len(found) / len(per),
            "missed": sum(s[det]["missed"] for s in sets.values()),
            "wrong_grid": sum(s[det]["wrong_grid"] for s in sets.values()),
            "cpu_ms": statistics.median(s[det]["cpu_ms"] for s in sets.values()),
            "better_than_SB_EXH_ACC": f"{sum(a < b for a, b in both)}/{len(both)}",
            "median_ratio_to_SB_EXH_ACC": float(np.median([a / b for a, b in both])),
        }
    return out


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    p.add_argument("--frames", type=int, default=16)
    p.add_argument("--images", type=Path, help="a folder of real chessboard images (no truth)")
    p.add_argument("--pattern", type=int, nargs=2, default=(9, 6), help="--images' inner corners")
    p.add_argument("--json", type=Path)
    a = p.parse_args(argv)
    cv2.setNumThreads(1)
    pattern = HandEyeSimConfig().target.pattern
    result = {"seeds": a.seeds, "frames": a.frames, "fraction": FRACTION, "sets": {}}
    with tempfile.TemporaryDirectory() as tmp:
        sets = render(a.seeds, a.frames, Path(tmp))
    for name, images in sets:
        result["sets"][name] = {}
        for det_name, det in DETECTORS.items():
            r = measure(det, images, pattern)
            result["sets"][name][det_name] = r
            print(
                f"{name:32s} {det_name:20s} rms {r['rms_px']:.4f} p99 {r['p99_px']:.4f} "
                f"max {r['max_px']:.3f} rate {r['rate']:.3f} cpu {r['cpu_ms']:.1f} ms",
                flush=True,
            )
    result["pooled"] = pooled(result["sets"])
    for name, r in result["pooled"].items():
        print(f"pooled {name:22s} {r}", flush=True)
    if a.images:
        result["real"] = real_images(a.images, tuple(a.pattern))
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps(result, indent=1) + "\n")
    return result


if __name__ == "__main__":
    main()
