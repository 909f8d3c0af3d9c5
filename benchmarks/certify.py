"""Is `jaxcal certify` honest? Its 95 % bounds against the true errors of simulated calibrations.

Per design and seed: simulate a capture with a known truth, calibrate it, write
the result, certify it over `--configs` random configurations (the joints'
whole travel, the fixed frame), and compare with the true error at those
configurations (the calibrated tool point against the true one, both in the
fixed frame: the device's or the camera's):

- `certificate_coverage`: per design, the share of configurations whose true
  error lies within its certified 95 % bound, over all seeds (and per seed);
- `certificate_ratios`: per design and seed, the measured over predicted RMS;
- `certificate_tightness`: per design, the median over seeds of the certified
  region 95 % bound over the measured 95th percentile of the true errors.

Designs: `tracker_poses` (stop-and-shoot tracker samples, no rendering) and,
with `--camera RESULT ...`, rendered camera calibrations already written (each
result directory's dataset must hold `truth.json`), and with `--render demo_sweeps
planned`, rendered here (`rendered_results`). Usage:

    python benchmarks/certify.py --seeds 5 --json results/certify.json [--camera DIR ...]
    python benchmarks/certify.py --seeds 5 --render demo_sweeps planned --render-seeds 5 \
        --json results/certify.json [--workdir DIR [--reuse]] [--first-seed 5 --plan DIR/planned_ds0/plan.json]
"""

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxcal
from jaxcal.certification import certify
from jaxcal.errors import DatasetError
from jaxcal.io._files import write_text_atomic
from jaxcal.io.model_json import model_from_json
from jaxcal.report import write_outputs
from jaxcal.sim.tracker import TrackerSimConfig, simulate_tracker


def true_points(truth: dict, fixed: str, target: str, q: np.ndarray) -> np.ndarray:
    """The true tool point in the fixed frame at every configuration (m)."""
    model = model_from_json(truth["model"])
    T = np.asarray(truth["cameras"][fixed]["T_cam_base"])
    p = np.asarray(truth["targets"][target]["T_link_target"])
    F = np.asarray(jax.vmap(lambda qq: jaxcal.forward_kinematics(model, qq)[-1])(jnp.asarray(q)))
    return np.einsum("ab,nbc,cd->nad", T, F, p)[:, :3, 3]


def score(res: Path, configs: int, seed: int) -> dict | None:
    """Certify `res` and score it against its dataset's truth (None: refused, a failed calibration)."""
    doc = json.loads((res / "result.json").read_text())
    truth = json.loads((Path(doc["dataset"]) / "truth.json").read_text())
    fixed = doc["T_device_base" if "T_device_base" in doc else "T_cam_base"]["matrix"]
    t0 = time.perf_counter()
    try:
        c = certify(res, samples=configs, seed=seed)
    except DatasetError as e:  # a calibration that failed has nothing to certify: left out, said
        print(f"not certified: {e}", flush=True)
        return None
    seconds = time.perf_counter() - t0
    T = np.asarray(fixed)
    y_cal = c.points @ T[:3, :3].T + T[:3, 3]
    y_true = true_points(truth, doc["camera"], doc["targets"][0], c.q)
    err = 1e3 * np.linalg.norm(y_cal - y_true, axis=1)
    return {
        "result": str(res),
        "coverage": float(np.mean(err <= c.bound95_mm)),
        "measured_rms_mm": float(np.sqrt(np.mean(err**2))),
        "predicted_rms_mm": c.summary["rms_mm"],
        "ratio": float(np.sqrt(np.mean(err**2)) / c.summary["rms_mm"]),
        "certified_p95_mm": c.summary["p95_mm"],
        "measured_p95_mm": float(np.quantile(err, 0.95)),
        "tightness": float(c.summary["p95_mm"] / np.quantile(err, 0.95)),
        "caveats": list(c.caveats),
        "covariance_model": doc.get("covariance_model"),  # None: written before the key
        "certify_s": seconds,
        "inside": err <= c.bound95_mm,
    }


def tracker_results(seeds: int, poses: int, root: Path) -> list[Path]:
    out = []
    for s in range(seeds):
        cfg = TrackerSimConfig(
            robot="ur5e", seed=100 + s, poses=poses, noise_um=10.0, bad_fraction=0.0, home_deg=None
        )
        ds = simulate_tracker(cfg, root / f"ds{s}")
        out.append(write_outputs(jaxcal.calibrate(ds, cv_folds=0, progress=False), root / f"res{s}"))
    return out


def rendered_results(
    seeds: int,
    root: Path,
    designs: list[str],
    reuse: bool = False,
    first_seed: int = 0,
    plan=None,
    smoke: bool = False,
) -> dict[str, list[Path]]:
    """Rendered camera captures calibrated here, `seeds` per design from `first_seed`:
    `demo_sweeps` (the demo's: 1280x960, 40 frames per 80-degree sweep, clock not given)
    and `planned` (`jaxcal.plan`'s 240 stop-and-shoot poses for the UR5e, as
    `benchmarks/plan.py`, rendered by `render_plan`; or the plan file `plan`, e.g. the
    `plan.json` an earlier run's captures hold); the seed draws the true arm, mounts and
    noise. With `reuse`, a capture already rendered in `root` (`<design>_ds<seed>/truth.json`)
    is calibrated again instead of rendered (and planned). `smoke`: `demo_sweeps` at data/ur5e_sweeps'
    design (800x600, 24 frames per sweep: seed 0 is data/ur5e_sweeps)."""
    from plan import CONFIGS  # benchmarks/plan.py: the demo's capture

    from jaxcal.sim.plan import MujocoChecker, render_plan
    from jaxcal.sim.simulate import simulate

    plans = [] if plan is None else [jaxcal.load_plan(plan)]

    def planned(d, s):
        if not plans:
            t0 = time.perf_counter()
            plans.append(
                jaxcal.plan(
                    "ur5e", seed=0, checker_factory=MujocoChecker, frames=240, steps=150, starts=3,
                    candidates=2000,
                ).plan
            )  # fmt: skip
            print(f"planned {plans[0].frames} poses in {time.perf_counter() - t0:.0f} s", flush=True)
        return render_plan(plans[0], d, seed=s, overwrite=True, progress=False)

    makers = {}
    if "demo_sweeps" in designs:
        demo = CONFIGS["ur5e_sweeps" if smoke else "demo"]
        makers["demo_sweeps"] = lambda d, s: simulate(demo(s), d, overwrite=True, progress=False)
    if "planned" in designs:
        makers["planned"] = planned
    out = {}
    for name, make in makers.items():
        out[name] = []
        for s in range(first_seed, first_seed + seeds):
            t0 = time.perf_counter()
            ds = root / f"{name}_ds{s}"
            if not (reuse and (ds / "truth.json").exists()):
                ds = make(ds, s)
            res = write_outputs(
                jaxcal.calibrate(ds, progress=False), root / f"{name}_res{s}", overwrite=reuse
            )
            print(f"{name} seed {s}: rendered and calibrated in {time.perf_counter() - t0:.0f} s", flush=True)
            out[name].append(res)
    return out


def summarise(rows: list[dict]) -> dict:
    return {
        "coverage": float(np.mean(np.concatenate([r["inside"] for r in rows]))),
        "ratios": [r["ratio"] for r in rows],
        "tightness": float(np.median([r["tightness"] for r in rows])),
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, default=5, help="tracker calibrations")
    p.add_argument("--poses", type=int, default=60, help="stop-and-shoot samples per tracker calibration")
    p.add_argument("--configs", type=int, default=1000, help="random test configurations per calibration")
    p.add_argument("--camera", nargs="*", default=[], type=Path, help="rendered camera results (truth.json)")
    p.add_argument(
        "--render",
        nargs="*",
        default=[],
        choices=["demo_sweeps", "planned"],
        help="render and calibrate these camera designs here, --render-seeds each",
    )
    p.add_argument("--render-seeds", type=int, default=5, help="seeds per rendered design")
    p.add_argument("--first-seed", type=int, default=0, help="the first rendered seed")
    p.add_argument(
        "--plan",
        type=Path,
        help="the planned design's plan file (e.g. an earlier capture's plan.json): not planned again",
    )
    p.add_argument("--workdir", type=Path, help="keep the rendered captures and results here")
    p.add_argument(
        "--reuse",
        action="store_true",
        help="with --workdir: calibrate the captures already rendered there again (no rendering)",
    )
    p.add_argument(
        "--smoke",
        action="store_true",
        help="the tests' size: demo_sweeps rendered at data/ur5e_sweeps' design (800x600, 24 frames per "
        "80-degree sweep; seed 0 is data/ur5e_sweeps, reused with --workdir --reuse) instead of the demo's",
    )
    p.add_argument("--json", required=True, type=Path)
    args = p.parse_args(argv)
    designs = {}
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        rows = [
            score(r, args.configs, k)
            for k, r in enumerate(tracker_results(args.seeds, args.poses, Path(tmp)))
        ]
        rows = [r for r in rows if r is not None]
        designs["tracker_poses"] = rows
        print(f"tracker: {args.seeds} calibrations in {time.perf_counter() - t0:.0f} s", flush=True)
    if args.camera:
        designs["camera"] = [row for k, r in enumerate(args.camera) if (row := score(r, args.configs, k))]
    if args.render:
        with tempfile.TemporaryDirectory() as tmp:
            work = args.workdir or Path(tmp)
            rendered = rendered_results(
                args.render_seeds, work, args.render, args.reuse, args.first_seed, args.plan, args.smoke
            )
            for name, results in rendered.items():
                designs[name] = [
                    row for k, r in enumerate(results) if (row := score(r, args.configs, args.first_seed + k))
                ]
    out = {
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, CPU only",
        "configs": args.configs,
        "certificate_coverage": {},
        "certificate_ratios": {},
        "certificate_tightness": {},
        "designs": {},
    }
    for name, rows in designs.items():
        s = summarise(rows)
        out["certificate_coverage"][name] = s["coverage"]
        out["certificate_ratios"][name] = s["ratios"]
        out["certificate_tightness"][name] = s["tightness"]
        out["designs"][name] = [{k: v for k, v in r.items() if k != "inside"} for r in rows]
        print(
            f"{name}: coverage {s['coverage']:.3f}, measured/predicted RMS "
            f"{', '.join(f'{x:.2f}' for x in s['ratios'])}, tightness (median) {s['tightness']:.2f}",
            flush=True,
        )
    args.json.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(args.json, json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
