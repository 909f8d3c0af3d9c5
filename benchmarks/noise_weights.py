"""Per-view corner noise against the smear during the exposure (issue 32): does a blurred
view's corner noise call for its own weight in the refinement?

For each rendered realism case (`benchmarks/realism.py --workdir DIR`, its renders reused,
never rendered here), the first camera's detections of the first target are compared with the
truth projected through the simulated lens (as `realism.py --detection-errors` does), view by
view. Each corner's true image velocity is the central difference of its true projection over
the neighbouring frames of its sweep (px/s), its smear the exposure times its speed (px). The
truth is at the frame's stamp and a blurred corner where its row's exposure is on average: the
lag and line delay that move one onto the other are fitted per case (`fit_timing`; a time shift
is the clock's and the line delay's, which the refinement fits, not noise) and taken out. Per
view: the RMS of its corners' errors (px, 2-D norm), along and across the motion, its median
smear, and the image's edge sharpness at the corners (`sharpness`). Then the fit of

    s_v^2 = s_0^2 + (b * smear_v)^2

by least squares on the per-view mean squared errors per axis of the cases with an exposure
(`s_0` per case, `b` shared; `b2` the unconstrained coefficient of the squared smear, negative
when the errors shrink with the smear), and per case the correlations of the per-view RMS
error with the smear and with the sharpness. `rolling_shutter` (the preset's rows are
cross-faded between renders 1 ms apart, a render artefact along the motion, see
`benchmarks/realism.py`) is measured but left out of the fit.

With `--weights`, each case is also calibrated (`jaxcal.calibrate`, defaults) with its views'
residuals divided by a relative noise scale: `plain` (none: the library's result), `rms_px`
(the true per-view RMS error, an oracle no detector has) or `sharpness` (the per-view error
predicted by a line fitted to the sharpness). Run one weighting per process, with
`JAXCAL_NO_CACHE=1` (`weighted_calibration`). The figures are in docs/performance.md
("Per-view noise weights from the smear", 2026-11-27).

    python benchmarks/noise_weights.py --workdir /tmp/realism_work --json results/noise_weights.json
        [--cases exposure_10ms camera_mix ...] [--weights plain|rms_px|sharpness]
"""

import argparse
import json
import shutil
import sys
from pathlib import Path

import cv2
import jax.numpy as jnp
import numpy as np

import jaxcal
import jaxcal._refine as refine_module
from jaxcal.errors import JaxcalError
from jaxcal.io._files import write_text_atomic
from jaxcal.io.dataset import load_dataset
from jaxcal.vision import detect_frames

CASES = (
    "ideal",
    "noise",
    "defocus",
    "jpeg80",
    "exposure_10ms",
    "camera_mix",
    "global_shutter",
    "rolling_shutter",
    "combined",
)
HALF = 5  # the sharpness window's half width (px)
#: Cases measured but not fitted: their errors along the motion are the renderer's, not the blur's.
ARTEFACTS = ("rolling_shutter",)


def fit_timing(errors: np.ndarray, velocities: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """The lag (s) and line delay (s per row) whose time shift best explains the corners'
    errors (px, `(n, 2)`) from their image velocities (px/s) and rows (`pixels[:, 1]`):
    least squares of `errors ~ velocities * (lag + row * line_delay)`."""
    A = np.stack([velocities, velocities * pixels[:, 1:2]], axis=-1).reshape(-1, 2)
    return np.linalg.lstsq(A, np.asarray(errors).reshape(-1), rcond=None)[0]


def sharpness(image: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """Per corner: the largest gradient magnitude over the contrast (max - min) in its window (1/px)."""
    img = image.astype(np.float64)
    gx, gy = cv2.Sobel(img, cv2.CV_64F, 1, 0, ksize=3) / 8.0, cv2.Sobel(img, cv2.CV_64F, 0, 1, ksize=3) / 8.0
    g = np.hypot(gx, gy)
    out = []
    for x, y in np.rint(pixels).astype(int):
        y0, y1, x0, x1 = max(y - HALF, 0), y + HALF + 1, max(x - HALF, 0), x + HALF + 1
        win = img[y0:y1, x0:x1]
        c = float(win.max() - win.min()) if win.size else 0.0
        out.append(float(g[y0:y1, x0:x1].max()) / c if c > 0 else np.nan)
    return np.asarray(out)


def views(dataset: Path) -> list[dict]:
    """Per view of the first camera and target: frame, RMS error (px), median smear (px), median speed
    (px/s), median sharpness (1/px), corners."""
    ds = load_dataset(dataset)
    cam, target = ds.cameras[0], ds.targets[0]
    meta = json.loads((dataset / "metadata.json").read_text())
    lens = np.asarray(meta["simulation"]["distortion"], np.float64)
    exposure = float(cam.exposure_s or 0.0)
    frames = [f for f in ds.truth["frames"] if f["camera"] == cam.name]
    paths = [ds.image_path(f["row"]) for f in frames]
    dets = detect_frames(paths, [target.spec], K=cam.K, dist=cam.dist, progress=False)
    points = target.spec.points()

    def proj(f, ids):
        T = np.asarray(f["T_cam_target"][target.name], np.float64)
        return cv2.projectPoints(points[ids], cv2.Rodrigues(T[:3, :3])[0], T[:3, 3], cam.K, lens)[0][:, 0]

    found = []  # (frame, corners' errors, velocities (px/s), pixels, sharpness)
    for k, (f, det) in enumerate(zip(frames, dets)):
        d = det.get(target.name)
        if d is None:
            continue
        a, b = frames[max(k - 1, 0)], frames[min(k + 1, len(frames) - 1)]
        # neighbours of the same sweep (the arm's joint angles move continuously there)
        dt = b["t"] - a["t"]
        if dt <= 0 or dt > 3.5 * (frames[1]["t"] - frames[0]["t"]):
            a, b, dt = f, f, 1.0
        vel = (proj(b, d.ids) - proj(a, d.ids)) / dt
        image = cv2.imread(str(paths[k]), cv2.IMREAD_GRAYSCALE)
        found.append((f, d.pixels - proj(f, d.ids), vel, d.pixels, sharpness(image, d.pixels)))
    # The truth is at the frame's stamp, a blurred corner where its row's exposure is on average:
    # the lag (s) and line delay (s per row) that move the truth there, fitted as the refinement
    # fits the clock and the line delay (a time shift is not noise).
    timing = np.zeros(2)
    if exposure > 0 or cam.line_delay_s:
        timing = fit_timing(*(np.concatenate([x[i] for x in found]) for i in (1, 2, 3)))
    out = []
    for f, e, vel, pixels, sharp in found:
        e = e - vel * (timing[0] + pixels[:, 1:2] * timing[1])
        speed = np.linalg.norm(vel, axis=1)
        along = np.sum(e * vel, axis=1) / np.maximum(speed, 1e-12)  # the error along the motion (px)
        across = np.sqrt(np.maximum(np.sum(e**2, axis=1) - along**2, 0.0))
        out.append(
            {
                "frame": int(f["frame"]),
                "row": int(f["row"]),
                "rms_px": float(np.sqrt(np.mean(np.sum(e**2, axis=1)))),
                "scatter_px": float(np.sqrt(np.mean(np.sum((e - e.mean(axis=0)) ** 2, axis=1)))),
                "along_rms_px": float(np.sqrt(np.mean(along**2))),
                "across_rms_px": float(np.sqrt(np.mean(across**2))),
                "smear_px": float(np.median(exposure * speed)),
                "speed_px_s": float(np.median(speed)),
                "sharpness": float(np.nanmedian(sharp)),
                "corners": len(e),
                "lag_ms": 1e3 * float(timing[0]),
                "line_delay_us": 1e6 * float(timing[1]),
            }
        )
    return out


def fit(cases: dict) -> dict:
    """`b` shared and `s_0` per case, least squares on the per-view mean squared errors per axis
    (px^2): mse_v = s_0,case^2 + b^2 smear_v^2, over the cases with a smear but `ARTEFACTS`."""
    names = [c for c, rows in cases.items() if any(r["smear_px"] > 0 for r in rows) and c not in ARTEFACTS]
    if not names:
        return {}
    rows = [(i, r) for i, c in enumerate(names) for r in cases[c]]
    A = np.zeros((len(rows), len(names) + 1))
    y = np.zeros(len(rows))
    for k, (i, r) in enumerate(rows):
        A[k, i] = 1.0
        A[k, -1] = r["smear_px"] ** 2
        y[k] = r["rms_px"] ** 2 / 2.0  # per axis
    x, *_ = np.linalg.lstsq(A, y, rcond=None)
    return {
        "b": float(np.sqrt(max(x[-1], 0.0))),
        "b2": float(x[-1]),
        "s0_px": {c: float(np.sqrt(max(x[i], 0.0))) for i, c in enumerate(names)},
    }


def weighted_calibration(dataset: Path, rows: list[dict], key: str | None) -> dict:
    """`jaxcal.calibrate(dataset)` with each view's residuals divided by its relative noise scale
    `row[key]` over their median (1 for the views without one; `key` None: all 1, the plain
    refinement): a study of per-view weights without the library's support, by wrapping
    `jaxcal._refine.reprojection_residuals` (run with `JAXCAL_NO_CACHE=1` so that the
    refinement is traced anew: a process's refinement program is traced once)."""
    n = max(r["row"] for r in rows) + 1
    scale = np.ones(n)
    if key is not None:
        s = np.array([r[key] for r in rows])
        scale[[r["row"] for r in rows]] = s / np.median(s)
    table = jnp.asarray(scale)
    plain = refine_module.reprojection_residuals

    def residuals(params, problem, weights=None):
        s = jnp.take(table, problem.data.frame, mode="clip")
        return plain(params, problem, weights) / s[:, None, None]

    refine_module.reprojection_residuals = residuals
    try:
        result = jaxcal.calibrate(dataset, progress=False)
    except JaxcalError as e:
        return {"refined_mm": None, "two_stage_mm": None, "status": "refused", "reasons": [str(e)[:200]]}
    finally:
        refine_module.reprojection_residuals = plain
    v = result.validation
    return {
        "refined_mm": v["ee_rms_mm_after"],
        "two_stage_mm": v["ee_rms_mm_two_stage"],
        "status": result.status,
    }


def std_gain(rows: list[dict], scale: np.ndarray) -> float:
    """How much weights `1 / scale^2` per view shrink the standard deviation of a parameter every
    corner informs alike (a mean), were each view's corner errors independent with its measured
    RMS: sqrt(var unweighted / var weighted), 1 for equal scales."""
    n = np.array([r["corners"] for r in rows], np.float64)
    var = np.array([r["rms_px"] for r in rows]) ** 2 / 2.0
    w = n / np.asarray(scale) ** 2
    unweighted = np.sum(n * var) / np.sum(n) ** 2
    weighted = np.sum(w**2 * var / n) / np.sum(w) ** 2
    return float(np.sqrt(unweighted / weighted))


def consecutive_correlation(rows: list[dict]) -> float:
    """The correlation of the per-view RMS errors of consecutive frames: near 1 when a view's
    error size is its pose's (smooth along the sweep), near 0 for independent noise."""
    frame = np.array([r["frame"] for r in rows])
    rms = np.array([r["rms_px"] for r in rows])
    k = np.flatnonzero(np.diff(frame) == 1)
    return float(np.corrcoef(rms[k], rms[k + 1])[0, 1])


#: Smear bins of the summary (px).
BINS = (0.0, 0.5, 1.0, 2.0, 3.0, np.inf)


def smear_bins(rows: list[dict]) -> list[dict]:
    """The views' RMS errors (2-D, along and across the motion, px) per smear bin (`BINS`)."""
    smear = np.array([r["smear_px"] for r in rows])
    out = []
    for lo, hi in zip(BINS[:-1], BINS[1:]):
        sel = [r for r, s in zip(rows, smear) if lo <= s < hi]
        if sel:
            out.append(
                {"smear_px": [lo, hi if np.isfinite(hi) else None], "views": len(sel)}
                | {
                    k: float(np.sqrt(np.mean([r[k] ** 2 for r in sel])))
                    for k in ("rms_px", "along_rms_px", "across_rms_px")
                }
            )
    return out


def noisier(case: Path, scratch: Path, noise_dn: float, seed: int = 0) -> Path:
    """A copy of `case` in `scratch` with Gaussian noise of `noise_dn` (DN) added to every image
    (8 bits, one seeded stream per case); the workdir's capture is left as it is."""
    out = scratch / case.name
    if out.exists():
        shutil.rmtree(out)
    shutil.copytree(case, out)
    rng = np.random.default_rng(seed)
    for path in sorted((out / "images").rglob("*.png")):
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED).astype(np.float64)
        image = np.clip(np.rint(image + rng.normal(0.0, noise_dn, image.shape)), 0, 255).astype(np.uint8)
        cv2.imwrite(str(path), image)
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workdir", required=True)
    parser.add_argument("--cases", nargs="*", default=list(CASES))
    parser.add_argument("--json")
    parser.add_argument(
        "--weights",
        nargs="*",
        default=[],
        choices=["plain", "rms_px", "sharpness"],
        help="calibrate each case with these per-view scales: plain (none), the true per-view RMS "
        "error (an oracle), the error predicted from the corners' sharpness (a line fitted per case)",
    )
    parser.add_argument(
        "--added-noise-dn",
        type=float,
        default=0.0,
        help="measure copies of the cases (in --scratch) with this much Gaussian noise added (DN)",
    )
    parser.add_argument("--scratch", help="where the noisier copies go (required with --added-noise-dn)")
    args = parser.parse_args(argv)
    paths = {c: Path(args.workdir) / c for c in args.cases}
    if args.added_noise_dn > 0:
        if not args.scratch:
            parser.error("--added-noise-dn needs --scratch")
        Path(args.scratch).mkdir(parents=True, exist_ok=True)
        paths = {c: noisier(p, Path(args.scratch), args.added_noise_dn) for c, p in paths.items()}
    cases = {c: views(p) for c, p in paths.items()}
    calibrations = {}
    for c, rows in cases.items():
        if "sharpness" in args.weights:
            sharp = np.array([r["sharpness"] for r in rows])
            line = np.polyfit(sharp, [r["rms_px"] for r in rows], 1)
            for r, x in zip(rows, np.polyval(line, sharp)):
                r["predicted_px"] = float(max(x, 0.2 * np.median([q["rms_px"] for q in rows])))
        for w in args.weights:
            key = {"plain": None, "rms_px": "rms_px", "sharpness": "predicted_px"}[w]
            calibrations.setdefault(c, {})[w] = weighted_calibration(paths[c], rows, key)
            print(json.dumps({c: {w: calibrations[c][w]}}), flush=True)
    model = fit(cases)
    summary = {}
    for c, rows in cases.items():
        rms = np.array([r["rms_px"] for r in rows])
        smear = np.array([r["smear_px"] for r in rows])
        sharp = np.array([r["sharpness"] for r in rows])
        row = {
            "views": len(rows),
            "rms_px": float(np.sqrt(np.mean(rms**2))),
            "smear_px_median": float(np.median(smear)),
            "smear_px_max": float(smear.max()),
            "corr_rms_sharpness": float(np.corrcoef(rms, sharp)[0, 1]),
            "lag_ms": rows[0]["lag_ms"],
            "line_delay_us": rows[0]["line_delay_us"],
            "scatter_px": float(np.sqrt(np.mean(np.array([r["scatter_px"] for r in rows]) ** 2))),
            "bins": smear_bins(rows),
            "oracle_std_gain": std_gain(rows, rms),
            "consecutive_rms_correlation": consecutive_correlation(rows),
        }
        if smear.std() > 0:
            row["corr_rms_smear"] = float(np.corrcoef(rms, smear)[0, 1])
            row["corr_scatter_smear"] = float(np.corrcoef([r["scatter_px"] for r in rows], smear)[0, 1])
            if model.get("b", 0.0) > 0 and c in model["s0_px"]:  # else the model is one sigma for all
                s = np.sqrt(model["s0_px"].get(c, 0.0) ** 2 + (model["b"] * smear) ** 2)
                row["corr_rms_model"] = float(np.corrcoef(rms, s)[0, 1])
                row["model_std_gain"] = std_gain(rows, s)
        summary[c] = row
        print(json.dumps({c: row}), flush=True)
    print(json.dumps({"fit": model}), flush=True)
    if args.json:
        out = {
            "added_noise_dn": args.added_noise_dn,
            "fit": model,
            "summary": summary,
            "calibrations": calibrations,
            "views": cases,
        }
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        write_text_atomic(Path(args.json), json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
