"""Does `jaxcal check` find a moved device, and only then? Detection power, false alarms, the detectable change.

Per seed: a simulated stop-and-shoot tracker calibration (its truth known).
Then many short check captures of the same arm: `--sizes` samples at random
configurations of the calibrated range, measured with the device moved by a
known twist (a translation of each size along a random direction, or a
rotation of each angle about one), the true arm's points with the capture's
noise; each is checked against the calibration (`jaxcal.drift.check_samples`).

- `false_alarm_rate`: detections at zero drift, over every trial and seed;
- `drift_power_by_mm` / `drift_power_by_deg`: per check size, per shift, the
  share detected; `estimate_within_2sigma`: per check size, the share of the
  detected shifts whose estimate lies within 2 sigma of the truth;
- `detectable_mm_10_images` (here: 10 samples): the smallest translation along
  the worst direction detected with 95 % power in trials, found by scanning
  sizes along that direction; `detectable_mm_bound`: the bound the check's
  Fisher information and the calibration's covariance allow
  (`jaxcal.drift.detectable`), mean over seeds;
- `check_s`: one check after compilation (fit and test).

Usage: python benchmarks/drift.py --seeds 3 --trials 100 --json results/drift.json

`--camera`: the same keys for camera check captures. Per seed a rendered
eye-to-hand calibration (`--resolution`, `--frames` per joint, or with `--demo-camera`
`jaxcal demo`'s capture, calibrated by `jaxcal.calibrate`), then `--trials` rendered check captures of 10
stop-and-shoot images at random configurations (+-10 deg about the sweeps'
home; the 5-pose figures from their first five), each detected and checked
unmoved (`false_alarm_rate`). The moved captures are the same detections
shifted by the change the move makes to each corner's true projection (from
`truth.json`): the detector's own error kept, one rendering per trial instead
of one per shift (`drift_power_by_mm` along random directions, `_by_deg`,
`estimate_within_2sigma`, `detectable_mm_10_images` along each trial's worst
direction). `check_s`: `jaxcal.drift.check` of 10 rendered images at 1280x960
(detection included) after a first call, against the scene's truth written as
a result (`jaxcal.sim.drift.truth_result`), median of 3.

Usage: python benchmarks/drift.py --camera --seeds 5 --trials 20 --json results/drift_camera.json
       python benchmarks/drift.py --camera --demo-camera --seeds 5 --trials 20 \\
           --json results/drift_camera_demo.json [--workdir DIR]

With `--workdir DIR` the calibrations are kept there and reused (`cal<seed>`, `res<seed>`), and
with `--demo-camera` those `benchmarks/certify.py --render demo_sweeps --workdir DIR` left there
(`demo_sweeps_res<seed>`: the same captures) are used.

`--handeye`: `jaxcal handeye` results (rendered, 16 frames, eye-to-hand and eye-in-hand
in turn) checked against rendered 6-frame captures of the same rig at other robot poses,
unmoved (`false_alarm_rate`) and moved 1 mm (`power_1mm`, `estimate_within_2sigma_1mm`);
`detectable_mm_bound` of the unmoved checks.

Usage: python benchmarks/drift.py --handeye --seeds 4 --trials 10 --json results/drift_handeye.json
"""

import argparse
import json
import os

# The checks' small dense linear algebra (SVDs of a few hundred rows) is slowed tenfold by
# OpenBLAS's threads on a shared 2-core machine: one thread (set before NumPy loads).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
import platform
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import jax.numpy as jnp
import numpy as np

import jaxcal
from jaxcal._drift_camera import view_jacobians
from jaxcal._geometry import se3_exp
from jaxcal._reprojection import project
from jaxcal.certification import read_result
from jaxcal.drift import (
    camera_capture,
    camera_check_reference,
    check,
    check_camera,
    check_samples,
    detectable,
    reference,
)
from jaxcal.io._files import write_text_atomic
from jaxcal.io.dataset import load_dataset
from jaxcal.report import write_outputs
from jaxcal.sim.drift import random_poses, render_check_capture, truth_result, twist_matrix
from jaxcal.sim.handeye import HandEyeSimConfig, simulate_hand_eye
from jaxcal.sim.simulate import SimConfig, simulate
from jaxcal.sim.tracker import TrackerSimConfig, simulate_tracker

sys.path.insert(0, str(Path(__file__).parent))
from certify import true_points  # noqa: E402

MM = (0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0)
DEG = (0.0005, 0.001, 0.002, 0.005, 0.02, 0.1, 0.5)


def _moved(y: np.ndarray, eps: np.ndarray) -> np.ndarray:
    T = np.linalg.inv(np.asarray(se3_exp(jnp.asarray(eps))))
    return y @ T[:3, :3].T + T[:3, 3]


def _unit(rng) -> np.ndarray:
    u = rng.standard_normal(3)
    return u / np.linalg.norm(u)


def one_seed(res: Path, sizes, trials: int, sigma: float, rng) -> dict:
    doc = json.loads((res / "result.json").read_text())
    truth = json.loads((Path(doc["dataset"]) / "truth.json").read_text())
    ws = np.asarray(load_dataset(doc["dataset"]).samples.q)
    lo, hi = ws.min(0), ws.max(0)
    out = {"false": [], "mm": {}, "deg": {}, "within": {}, "bound": {}, "trial_detectable": {}, "check_s": []}
    for n in sizes:
        hits_mm = {m: [] for m in MM}
        hits_deg = {d: [] for d in DEG}
        within, bounds, worst = [], [], []
        for _t in range(trials):
            q = lo + (hi - lo) * rng.uniform(size=(n, len(lo)))
            y = true_points(truth, doc["camera"], doc["targets"][0], q) + sigma * rng.standard_normal((n, 3))
            t0 = time.perf_counter()
            ref = reference(doc, q, np.full(n, sigma))
            c = check_samples(ref, y)
            out["check_s"].append(time.perf_counter() - t0)
            out["false"].append(c.detected)
            det = detectable(c.cov)
            bounds.append(det["translation_mm_worst"])
            P = np.linalg.inv(c.cov)
            worst.append((np.linalg.eigh(P[:3, :3])[1][:, 0], y, ref))
            for m in MM:
                eps = np.r_[1e-3 * m * _unit(rng), 0.0, 0.0, 0.0]
                d = check_samples(ref, _moved(y, eps))
                hits_mm[m].append(d.detected)
                if d.detected:
                    within.append(abs(d.translation_mm[0] - m) <= 2.0 * d.translation_mm[1])
            for a in DEG:
                eps = np.r_[0.0, 0.0, 0.0, np.radians(a) * _unit(rng)]
                hits_deg[a].append(check_samples(ref, _moved(y, eps)).detected)
        out["mm"][n] = {m: float(np.mean(h)) for m, h in hits_mm.items()}
        out["deg"][n] = {a: float(np.mean(h)) for a, h in hits_deg.items()}
        out["within"][n] = float(np.mean(within)) if within else None
        out["bound"][n] = float(np.mean(bounds))
        # Scan sizes along each trial's worst direction: the smallest detected in 95 % of trials.
        grid = np.linspace(0.25, 2.5, 19) * out["bound"][n]
        rate = [
            np.mean(
                [check_samples(r, _moved(yy, np.r_[1e-3 * s * u, 0, 0, 0])).detected for u, yy, r in worst]
            )
            for s in grid
        ]
        ok = [s for s, r in zip(grid, rate) if r >= 0.95]
        out["trial_detectable"][n] = float(ok[0]) if ok else None
    return out


CAM_MM = (0.1, 0.2, 0.5, 1.0, 2.0)
CAM_DEG = (0.02, 0.05, 0.1, 0.2, 0.5)
#: Multiples of each trial's bound scanned along its worst direction (`detectable_mm_*_images`).
CAM_GRID = (0.9, 1.0, 1.1, 1.2, 1.35, 1.5)


def _shifted(cap, truth: dict, K, dist, E: np.ndarray, views: int) -> list:
    """The capture's detections moved by the change the camera move `E` (its frame) makes
    to each corner's true projection (the detector's own error kept), first `views` views."""
    rows = {f["row"]: f for f in truth["frames"]}
    name = cap.reference.targets[0]
    Ei = np.linalg.inv(E)
    out = []
    for pts, pix, row in zip(cap.points[:views], cap.pixels[:views], cap.row[:views]):
        T = np.asarray(rows[int(row)]["T_cam_target"][name])
        X = pts @ T[:3, :3].T + T[:3, 3]
        Xm = X @ Ei[:3, :3].T + Ei[:3, 3]
        out.append(pix + np.asarray(project(K, dist, jnp.asarray(Xm)) - project(K, dist, jnp.asarray(X))))
    return out


def _true_pixels(cap, truth: dict, K, dist, views: int) -> list:
    """Per view (the first `views`) the true projections of the detected corners (`truth.json`)."""
    rows = {f["row"]: f for f in truth["frames"]}
    name = cap.reference.targets[0]
    out = []
    for pts, row in zip(cap.points[:views], cap.row[:views]):
        T = np.asarray(rows[int(row)]["T_cam_target"][name])
        out.append(np.asarray(project(K, dist, jnp.asarray(pts @ T[:3, :3].T + T[:3, 3]))))
    return out


def calibration_error_ratio(cap, truth: dict, K, dist, views: int) -> float:
    """The calibration's own error as a check of `views` images sees it, over the variance its
    covariance predicts: $u^T C_d^{-1} u / 6$, $u$ the camera twist fitted (least squares) to the
    true projections, which only the calibration's error moves, and $C_d = P J \\Sigma J^T P^T$ its
    covariance from the calibration's ($P$ the fit's map). About 1 on average over calibrations
    when their covariance is honest; `jaxcal._drift_camera.CALIBRATION_COVARIANCE_FACTOR`."""
    c = _subset(cap, views)
    ref, _ = camera_check_reference(c, pixels=_true_pixels(c, truth, K, dist, views))
    pix, _, A, J = (np.asarray(a) for a in view_jacobians(ref.x, ref.problem))
    m = np.repeat(np.asarray(ref.problem.data.mask), 2, axis=1).reshape(-1)
    r = (pix - np.asarray(ref.problem.data.pixels)).reshape(-1)[m]
    A, J = A.reshape(-1, 6)[m], J.reshape(-1, J.shape[-1])[m]
    P = np.linalg.solve(A.T @ A, A.T)
    u = -P @ r
    n = J.shape[1]
    Cd = P @ J @ np.asarray(cap.est.cov, np.float64)[:n, :n] @ J.T @ P.T
    return float(u @ np.linalg.solve(Cd, u) / 6)


def _subset(cap, views: int):
    """The capture's first `views` views."""
    return replace(
        cap,
        points=cap.points[:views],
        pixels=cap.pixels[:views],
        target=cap.target[:views],
        row=cap.row[:views],
        t_cam=cap.t_cam[:views],
    )


def camera_trial(cap, truth, K, dist, rng) -> dict:
    """One rendered check capture: per size (10 images, 5) the unmoved check, the shifted ones."""
    out = {"calibration_error_ratio": calibration_error_ratio(cap, truth, K, dist, 10)}
    for n in (10, 5):
        c = _subset(cap, n)
        c0 = check_camera(c)
        row = {
            "false": c0.detected,
            "bound": c0.detectable["translation_mm_worst"],
            "mm": {},
            "deg": {},
            "within": [],
        }
        for m in CAM_MM:
            v = 1e-3 * m * _unit(rng)
            d = check_camera(c, pixels=_shifted(c, truth, K, dist, twist_matrix(v, np.zeros(3)), n))
            row["mm"][m] = d.detected
            if d.detected:
                row["within"].append(abs(d.translation_mm[0] - m) <= 2.0 * d.translation_mm[1])
        for a in CAM_DEG:
            E = twist_matrix(np.zeros(3), np.radians(a) * _unit(rng))
            row["deg"][a] = check_camera(c, pixels=_shifted(c, truth, K, dist, E, n)).detected
        row["nu"] = c0.residual["noise_variance_factor"]
        row["statistic"] = c0.statistic / c0.threshold
        P = np.linalg.inv(c0.cov)
        u = np.linalg.eigh(P[:3, :3])[1][:, 0]
        grid = np.asarray(CAM_GRID) * row["bound"]
        row["worst"] = {
            float(g): check_camera(
                c, pixels=_shifted(c, truth, K, dist, twist_matrix(1e-3 * g * u, np.zeros(3)), n)
            ).detected
            for g in grid
        }
        out[n] = row
    return out


def _camera_check_s(tmp: Path, resolution=(1280, 960)) -> float:
    cfg = SimConfig(resolution=resolution, seed=7)
    cap = render_check_capture(cfg, tmp / "hires", random_poses(6, 10, 10.0, seed=7))
    res = truth_result(cfg, cap, tmp / "hires_result")
    check(res, cap)
    times = []
    for _ in range(3):
        t0 = time.perf_counter()
        check(res, cap)
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def _seed_offset(args) -> int:
    """The calibrations' first seed is `--first-seed` plus this."""
    return 0 if args.demo_camera or args.smoke else 300


def _calibration_config(args, s: int) -> SimConfig:
    """The calibration capture of seed `s`: `jaxcal demo`'s with `--demo-camera` (its seed `s`,
    as `benchmarks/certify.py`'s `demo_sweeps`), else `--resolution` and `--frames` (seed 300 + s);
    with `--smoke` data/ur5e_sweeps' design (its seed `s`)."""
    if args.demo_camera or args.smoke:
        from plan import CONFIGS  # benchmarks/plan.py: the demo's capture, data/ur5e_sweeps' design

        return CONFIGS["ur5e_sweeps" if args.smoke else "demo"](s)
    w, h = (int(v) for v in args.resolution.split("x"))
    return SimConfig(resolution=(w, h), seed=300 + s, frames_per_joint=args.frames, range_deg=80.0)


def _calibrated(args, cfg: SimConfig, s: int, tmp: Path) -> Path:
    """The calibration of seed `s`, rendered and calibrated in `tmp`, or with `--workdir` the one
    kept there (`cal<s>`, `res<s>`: calibrated again when only the capture is there; with
    `--demo-camera` also `benchmarks/certify.py --render demo_sweeps`'s, `demo_sweeps_res<s>`)."""
    root = args.workdir or tmp
    cal, res = root / f"cal{s}", root / f"res{s}"
    if args.workdir is not None:
        kept = [res, *([root / f"demo_sweeps_res{s}"] if args.demo_camera else [])]
        for r in kept:
            if (r / "result.json").exists():
                return r
    ds = cal if (cal / "truth.json").exists() else simulate(cfg, cal, progress=False)
    return write_outputs(jaxcal.calibrate(ds, progress=False), res, overwrite=True)


def camera_main(args) -> int:
    rng = np.random.default_rng(0)
    trials = {10: [], 5: []}
    ratios = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for s in range(args.first_seed, args.first_seed + args.seeds):
            cfg = _calibration_config(args, s)
            res = _calibrated(args, cfg, s, tmp)
            doc, file = read_result(res)
            for t in range(args.trials):
                q = random_poses(6, 10, 10.0, seed=1000 * s + t)
                root = render_check_capture(cfg, tmp / f"chk{s}_{t}", q)
                ds_c = load_dataset(root)
                truth = json.loads((root / "truth.json").read_text())
                cam = ds_c.cameras[0]
                K, dist = jnp.asarray(cam.K), jnp.asarray(np.asarray(cam.dist, float)[:5])
                cap = camera_capture(doc, file, ds_c)
                result = camera_trial(cap, truth, K, dist, rng)
                ratios.append((s, result.pop("calibration_error_ratio")))
                for n, row in result.items():
                    trials[n].append(row)
            print(f"seed {s}: done", flush=True)
        check_res = cfg.resolution if args.smoke else (1280, 960)
        check_s = _camera_check_s(tmp, check_res)
    w, h = cfg.resolution
    design = f"{w}x{h}, {cfg.frames_per_joint} frames per joint"
    if args.smoke or args.demo_camera:
        what = "data/ur5e_sweeps' design" if args.smoke else "the demo's capture"
        design = f"{what}: {design}, clock not given"
    out = {
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, CPU only",
        "data": f"rendered UR5e eye-to-hand calibrations ({design}, 80 deg "
        "sweeps) and rendered 10-image stop-and-shoot check captures; moved captures: the detections shifted "
        "by the move's change of the true projections",
        "seeds": args.seeds,
        "first_seed": _seed_offset(args) + args.first_seed,
        "trials_per_seed": args.trials,
        "false_alarm_rate": float(np.mean([r["false"] for r in trials[10]])),
        "false_alarm_rate_5_images": float(np.mean([r["false"] for r in trials[5]])),
        "false_alarm_trials": len(trials[10]),
        "statistic_over_threshold_mean": {
            n: float(np.mean([r["statistic"] for r in rows])) for n, rows in trials.items()
        },
        "noise_variance_factor_mean": float(np.mean([r["nu"] for r in trials[10]])),
        "calibration_error_ratio": float(np.mean([v for _, v in ratios])),
        "calibration_error_ratio_by_seed": {
            str(_seed_offset(args) + s): float(np.mean([v for k, v in ratios if k == s]))
            for s in sorted({k for k, _ in ratios})
        },
        "drift_power_by_mm": {
            n: {m: float(np.mean([r["mm"][m] for r in rows])) for m in CAM_MM} for n, rows in trials.items()
        },
        "drift_power_by_deg": {
            n: {a: float(np.mean([r["deg"][a] for r in rows])) for a in CAM_DEG} for n, rows in trials.items()
        },
        "estimate_within_2sigma": {
            n: float(np.mean(sum((r["within"] for r in rows), []) or [np.nan])) for n, rows in trials.items()
        },
        "detectable_mm_bound": {n: float(np.mean([r["bound"] for r in rows])) for n, rows in trials.items()},
        "check_s": check_s,
        "check_s_setting": f"10 images at {check_res[0]}x{check_res[1]}, detection included, after compilation "
        "(median of 3)",
    }
    for n, rows in trials.items():
        # Sizes relative to each trial's own bound: the smallest multiple detected in 95 % of trials.
        rel = sorted({round(g / r["bound"], 6) for r in rows for g in r["worst"]})
        rate = [
            np.mean([[v for g, v in r["worst"].items() if abs(g / r["bound"] - k) < 1e-6][0] for r in rows])
            for k in rel
        ]
        ok = [k for k, p in zip(rel, rate) if p >= 0.95]
        out[f"detectable_mm_{n}_images"] = float(ok[0] * out["detectable_mm_bound"][n]) if ok else None
        out[f"power_at_bound_multiples_{n}_images"] = {float(k): float(p) for k, p in zip(rel, rate)}
    print(json.dumps(out, indent=1), flush=True)
    args.json.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(args.json, json.dumps(out, indent=2))
    return 0


def handeye_main(args) -> int:
    """`--handeye`: rendered `jaxcal handeye` calibrations (eye-to-hand and eye-in-hand in turn,
    16 frames) and per trial two 6-frame check captures of the same rig at other robot poses,
    the camera unmoved and moved by 1 mm along a random direction (rendered)."""
    rng = np.random.default_rng(1)
    w, h = (int(v) for v in args.resolution.split("x"))
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for s in range(args.seeds):
            cfg = HandEyeSimConfig(frames=16, seed=400 + s, resolution=(w, h), eye_in_hand=bool(s % 2))
            run = jaxcal.calibrate_hand_eye_capture(simulate_hand_eye(cfg, tmp / f"cal{s}"), folds=0)
            res = jaxcal.write_hand_eye_outputs(run, tmp / f"res{s}")
            for t in range(args.trials):
                chk = replace(cfg, frames=6, seed=1000 * (s + 1) + t)
                c0 = check(res, simulate_hand_eye(chk, tmp / f"still{s}_{t}"))
                v = 1e-3 * _unit(rng)
                c1 = check(
                    res, simulate_hand_eye(replace(chk, camera_move=(v, (0, 0, 0))), tmp / f"moved{s}_{t}")
                )
                rows.append(
                    {
                        "eye_in_hand": cfg.eye_in_hand,
                        "false": c0.detected,
                        "bound": c0.detectable["translation_mm_worst"],
                        "nu": c0.residual["noise_variance_factor"],
                        "hit": c1.detected,
                        "within": abs(c1.translation_mm[0] - 1.0) <= 2.0 * c1.translation_mm[1],
                    }
                )
            print(f"seed {s}: done", flush=True)
    out = {
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, CPU only",
        "data": f"rendered hand-eye calibrations ({w}x{h}, 16 frames, chessboard 8x7, eye-to-hand and eye-in-hand in "
        "turn) and rendered 6-frame check captures of the same rig, unmoved and moved 1 mm",
        "seeds": args.seeds,
        "trials_per_seed": args.trials,
        "false_alarm_rate": float(np.mean([r["false"] for r in rows])),
        "power_1mm": float(np.mean([r["hit"] for r in rows])),
        "estimate_within_2sigma_1mm": float(np.mean([r["within"] for r in rows if r["hit"]] or [np.nan])),
        "detectable_mm_bound": float(np.mean([r["bound"] for r in rows])),
        "noise_variance_factor_mean": float(np.mean([r["nu"] for r in rows])),
        "by_arrangement": {
            k: {
                "false_alarm_rate": float(np.mean([r["false"] for r in rows if r["eye_in_hand"] == e])),
                "detectable_mm_bound": float(np.mean([r["bound"] for r in rows if r["eye_in_hand"] == e])),
            }
            for k, e in (("eye_to_hand", False), ("eye_in_hand", True))
            if any(r["eye_in_hand"] == e for r in rows)
        },
    }
    print(json.dumps(out, indent=1), flush=True)
    args.json.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(args.json, json.dumps(out, indent=2))
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, default=3, help="calibrations")
    p.add_argument("--poses", type=int, default=60, help="stop-and-shoot samples per calibration")
    p.add_argument("--trials", type=int, default=40, help="check captures per size and seed")
    p.add_argument("--sizes", default="5,10", help="samples per check capture")
    p.add_argument("--noise-um", type=float, default=10.0)
    p.add_argument("--json", required=True, type=Path)
    p.add_argument(
        "--camera", action="store_true", help="camera check captures (rendered) instead of tracker"
    )
    p.add_argument(
        "--handeye", action="store_true", help="hand-eye results (jaxcal handeye) and rendered check captures"
    )
    p.add_argument(
        "--resolution", default="640x480", help="--camera, --handeye: the calibration's and checks' images"
    )
    p.add_argument("--frames", type=int, default=20, help="--camera: calibration frames per joint")
    p.add_argument(
        "--first-seed",
        type=int,
        default=0,
        help="--camera: the first calibration's seed (300 + this; with --demo-camera this); its check "
        "captures' seeds follow from it",
    )
    p.add_argument(
        "--demo-camera",
        action="store_true",
        help="--camera: calibrate `jaxcal demo`'s capture (1280x960, 40 frames per 80-degree sweep, clock not "
        "given; benchmarks/certify.py's demo_sweeps) instead of --resolution and --frames",
    )
    p.add_argument(
        "--workdir",
        type=Path,
        help="--camera: keep the calibrations here (cal<seed>, res<seed>) and reuse those already there (with "
        "--demo-camera also benchmarks/certify.py --render demo_sweeps --workdir's, demo_sweeps_res<seed>)",
    )
    p.add_argument(
        "--smoke",
        action="store_true",
        help="--camera: the tests' size: the calibrations of data/ur5e_sweeps' design (800x600, 24 frames per "
        "80-degree sweep, clock not given; seed 0 is data/ur5e_sweeps, reused as cal0 in --workdir) instead of "
        "--resolution and --frames or the demo's, and check_s at 800x600",
    )
    args = p.parse_args(argv)
    if args.camera:
        return camera_main(args)
    if args.handeye:
        return handeye_main(args)
    sizes = [int(s) for s in args.sizes.split(",")]
    rng = np.random.default_rng(0)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for s in range(args.seeds):
            cfg = TrackerSimConfig(
                robot="ur5e",
                seed=200 + s,
                poses=args.poses,
                noise_um=args.noise_um,
                bad_fraction=0.0,
                home_deg=None,
            )
            ds = simulate_tracker(cfg, Path(tmp) / f"ds{s}")
            res = write_outputs(jaxcal.calibrate(ds, cv_folds=0, progress=False), Path(tmp) / f"res{s}")
            rows.append(one_seed(res, sizes, args.trials, 1e-6 * args.noise_um, rng))
            print(f"seed {s}: done", flush=True)
    out = {
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, CPU only",
        "data": "simulated UR5e stop-and-shoot tracker calibrations (no rendering)",
        "seeds": args.seeds,
        "trials_per_size_and_seed": args.trials,
        "false_alarm_rate": float(np.mean(np.concatenate([r["false"] for r in rows]))),
        "false_alarm_trials": int(sum(len(r["false"]) for r in rows)),
        "drift_power_by_mm": {
            n: {m: float(np.mean([r["mm"][n][m] for r in rows])) for m in MM} for n in sizes
        },
        "drift_power_by_deg": {
            n: {a: float(np.mean([r["deg"][n][a] for r in rows])) for a in DEG} for n in sizes
        },
        "estimate_within_2sigma": {
            n: float(np.mean([r["within"][n] for r in rows if r["within"][n] is not None])) for n in sizes
        },
        "detectable_mm_bound": {n: float(np.mean([r["bound"][n] for r in rows])) for n in sizes},
        "detectable_mm_trials": {n: [r["trial_detectable"][n] for r in rows] for n in sizes},
        "check_s": float(np.median(np.concatenate([r["check_s"][5:] for r in rows]))),
    }
    ten = 10 if 10 in sizes else sizes[-1]
    vals = [v for v in out["detectable_mm_trials"][ten] if v is not None]
    out["detectable_mm_10_images"] = float(np.mean(vals)) if vals else None
    print(json.dumps({k: v for k, v in out.items() if k != "drift_power_by_deg"}, indent=1), flush=True)
    args.json.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(args.json, json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
