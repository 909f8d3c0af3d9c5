"""Benchmark: a fleet of simulated units calibrated in one `jaxcal calibrate` against one process
per unit (issue 52).

`--units` UR5e units are simulated (`jaxcal.sim.tracker`, `--poses` stop-and-shoot tracker poses
each, the tracker 2 m from the base and turned, 10 um noise; each unit's joint origins, axes and zero
offsets drawn at the simulator's scales: a population), then:

- `fleet_s`: the wall time of one `jaxcal calibrate FOLDER --out DIR` over all of
  them (a fresh process, the compilation cache warm from a first, untimed run on one unit);
- `single_s`: the wall times of `jaxcal calibrate UNIT --out DIR` for the first
  `--singles` units, one fresh process each (the same warm cache): what calibrating the fleet
  unit by unit costs, `single_s_mean` x units (`singles_extrapolated_s`); `speedup` the ratio;
- `max_parameter_difference`: the largest difference between a unit's parameters in the fleet's
  result and in its own calibration (SI units: m, rad), over the single runs;
- `outliers`, `statuses`: what the fleet's summary named; `population_std_mm`: the fleet's
  estimated spread of the robots' joint origins (the median over the origin translations, mm),
  against the simulator's 1 mm per axis (`origin_mm`);
- the fleet as prior (`--prior-poses`, 0: skipped): a new unit of the same population measured at
  `--prior-poses` poses, calibrated with `--prior fleet.json` and without, and at `--poses` without:
  each one's end-effector error against the simulator's truth (`ee_rms_mm`, the validation's) and
  its cross-validated distance from the measured points (`cv_mean_mm`, what the data show);
  `prior_30_over_full_1000` (named for the issue's sizes) is the first ratio with the prior,
  `noprior_30_over_full_1000` without; `prior_share_mean` the prior's mean share of the
  parameters' information. `--population-scale` scales the population's spread (the simulator's
  origin, axis and zero-offset scales).
- across processes (`--processes N`, 1: skipped): the same fleet calibrated by N local processes of one
  distributed run (`jaxcal.distributed.run_local`, the units dealt between them): `processes.fleet_s`,
  `processes.wall_ratio` (one process's wall time over theirs), `processes.max_parameter_difference`
  (every unit against the one-process fleet's) and `processes.summary_equal` (`fleet.json` the same,
  timings apart).

    python benchmarks/fleet.py --units 20 --poses 1000 --singles 3 --json results/fleet.json
    python benchmarks/fleet.py --units 20 --poses 1000 --singles 1 --population-scale 0.05 --json OUT
    python benchmarks/fleet.py --units 20 --poses 1000 --singles 1 --prior-poses 0 --processes 2 --json OUT
"""

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

KW = dict(
    robot="ur5e", noise_um=10.0, bad_fraction=0.0, home_deg=None, pose_range_deg=120.0, device_is_base=True
)


def _jaxcal(args: list[str], env: dict) -> float:
    """Seconds of a fresh `python -m jaxcal ARGS` (quiet), which must not fail to run (exit 0 or 3)."""
    t0 = time.perf_counter()
    done = subprocess.run(
        [sys.executable, "-m", "jaxcal", *args, "--quiet"], capture_output=True, text=True, env=env
    )
    seconds = time.perf_counter() - t0
    if done.returncode not in (0, 3):
        raise RuntimeError(f"jaxcal {' '.join(args)} exited {done.returncode}: {done.stderr[-2000:]}")
    return seconds


def _parameters(result_json: Path) -> dict[str, float]:
    return {p["name"]: p["estimate"] for p in json.loads(result_json.read_text())["parameters"]}


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--units", type=int, default=20, help="units in the fleet (at least 2)")
    parser.add_argument("--poses", type=int, default=1000, help="tracker poses per unit (at least 10)")
    parser.add_argument("--singles", type=int, default=3, help="units also calibrated one process each")
    parser.add_argument("--cv-folds", type=int, default=5, help="each calibration's cross-validation folds")
    parser.add_argument(
        "--prior-poses", type=int, default=30, help="the new unit's short capture (0: no prior part)"
    )
    parser.add_argument(
        "--population-scale",
        type=float,
        default=1.0,
        help="the population's spread over the simulator's scales",
    )
    parser.add_argument(
        "--processes", type=int, default=1, help="also the fleet over this many local processes (1: not)"
    )
    parser.add_argument("--json", metavar="OUT", help="also write the JSON here")
    args = parser.parse_args(argv)
    if args.units < 2 or args.poses < 10 or not 1 <= args.singles <= args.units or args.processes < 1:
        parser.error("--units >= 2, --poses >= 10, 1 <= --singles <= --units, --processes >= 1")
    if args.prior_poses and (args.prior_poses < 24 or args.units < 5):
        parser.error("--prior-poses: at least 24 (four per joint), and a fleet of at least 5 units")
    kw = KW | {
        k: v * args.population_scale
        for k, v in dict(origin_mm=1.0, origin_deg=0.2, axis_tilt_deg=0.2, zero_offset_deg=0.5).items()
    }
    from jaxcal.sim.tracker import TrackerSimConfig, simulate_tracker

    env = dict(os.environ)
    config = ["--config", f"cv-folds={args.cv_folds}"]
    with tempfile.TemporaryDirectory(prefix="jaxcal-fleet-") as tmp:
        work = Path(tmp)
        print(f"simulating {args.units} UR5e units of {args.poses} tracker poses ...", flush=True)
        for k in range(args.units):
            simulate_tracker(
                TrackerSimConfig(seed=100 + k, poses=args.poses, **kw), work / "fleet" / f"unit{k:03d}"
            )
        print("a first calibration of one unit (not timed: it fills the compilation cache) ...", flush=True)
        _jaxcal(["calibrate", str(work / "fleet" / "unit000"), "--out", str(work / "warm"), *config], env)
        print(f"the fleet in one process: jaxcal calibrate {work / 'fleet'} ...", flush=True)
        fleet_s = _jaxcal(["calibrate", str(work / "fleet"), "--out", str(work / "out"), *config], env)
        single_s, differences = [], []
        for k in range(args.singles):
            name = f"unit{k:03d}"
            print(f"unit {name} alone ({k + 1}/{args.singles}) ...", flush=True)
            single_s.append(
                _jaxcal(["calibrate", str(work / "fleet" / name), "--out", str(work / name), *config], env)
            )
            mine, alone = (_parameters(d / "result.json") for d in (work / "out" / name, work / name))
            differences += [abs(mine[n] - alone[n]) for n in alone]
        summary = json.loads((work / "out" / "fleet.json").read_text())
        prior = _prior_part(work, args, kw, config, env) if args.prior_poses else {}
        processes = _processes_part(work, args, config, env, fleet_s) if args.processes > 1 else {}
    origins = [
        p["population_std"] * 1e3
        for p in summary["parameters"]
        if ".origin." in p["name"] and p["name"].rsplit(".", 1)[1] in ("x", "y", "z") and p["unit"] == "m"
    ]
    mean = float(np.mean(single_s))
    report = {
        "units": args.units,
        "poses": args.poses,
        "cv_folds": args.cv_folds,
        "fleet_s": fleet_s,
        "fleet_per_unit_s": fleet_s / args.units,
        "single_s": single_s,
        "single_s_mean": mean,
        "singles_extrapolated_s": mean * args.units,
        "speedup": mean * args.units / fleet_s,
        "max_parameter_difference": float(max(differences)),
        "statuses": {u["name"]: u["status"] for u in summary["units"]},
        "outliers": [(o["unit"], o["parameter"], round(o["z"], 1)) for o in summary["outliers"]],
        "population_std_mm": float(np.median(origins)) if origins else None,
        "population_scale": args.population_scale,
        **prior,
        **processes,
        "machine": f"{platform.machine()}, {os.cpu_count()} cores",
        "date": time.strftime("%Y-%m-%d %H:%M"),
    }
    print(
        f"{args.units} units: fleet {fleet_s:.1f} s ({fleet_s / args.units:.2f} s a unit), one process a unit "
        f"{mean:.2f} s ({report['speedup']:.1f}x); largest parameter difference "
        f"{report['max_parameter_difference']:.2e}; outliers {report['outliers']}"
    )
    if prior:
        print(
            f"a new unit, end-effector error against the truth: {args.prior_poses} poses with the fleet's prior "
            f"{prior['ee_rms_mm']['short_prior']:.4f} mm, without {prior['ee_rms_mm']['short']:.4f} mm, "
            f"{args.poses} poses without {prior['ee_rms_mm']['full']:.4f} mm (ratios "
            f"{prior['prior_30_over_full_1000']:.2f}, {prior['noprior_30_over_full_1000']:.2f}); the prior gave "
            f"{prior['prior_share_mean']:.0%} of the information"
        )
    if processes:
        q = processes["processes"]
        print(
            f"the fleet over {q['count']} local processes: {q['fleet_s']:.1f} s ({q['wall_ratio']:.2f}x one "
            f"process's); largest parameter difference {q['max_parameter_difference']:.1e}, summary "
            f"{'the same' if q['summary_equal'] else 'DIFFERENT'}"
        )
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1))
    return report


def _processes_part(work: Path, args, config: list, env: dict, fleet_s: float) -> dict:
    """The fleet calibrated again by `--processes` local processes of one distributed run."""
    from jaxcal.distributed import run_local
    from jaxcal.fleet import without_timings

    out = work / "out_processes"
    print(f"the fleet over {args.processes} local processes ...", flush=True)
    argv = [
        sys.executable,
        "-m",
        "jaxcal",
        "calibrate",
        str(work / "fleet"),
        "--out",
        str(out),
        *config,
        "--quiet",
    ]
    t0 = time.perf_counter()
    runs = run_local(argv, args.processes, env=env, capture=True)
    seconds = time.perf_counter() - t0
    if any(r.returncode not in (0, 3) for r in runs):
        raise RuntimeError("the distributed fleet failed: " + " | ".join(r.stderr[-1500:] for r in runs))
    differences = [
        abs(mine[n] - theirs[n])
        for unit in sorted(p.name for p in (work / "out").iterdir() if (p / "result.json").exists())
        for mine, theirs in [tuple(_parameters(d / unit / "result.json") for d in (work / "out", out))]
        for n in mine
    ]
    one, many = (without_timings(json.loads((d / "fleet.json").read_text())) for d in (work / "out", out))
    return {
        "processes": {
            "count": args.processes,
            "fleet_s": seconds,
            "wall_ratio": fleet_s / seconds,
            "max_parameter_difference": float(max(differences)),
            "summary_equal": one == many,
            "exit_codes": [r.returncode for r in runs],
        }
    }


def _prior_part(work: Path, args, kw: dict, config: list, env: dict) -> dict:
    """A new unit of the population, short with the fleet's prior and without, and full without."""
    from jaxcal.sim.tracker import TrackerSimConfig, simulate_tracker

    runs = {"short_prior": args.prior_poses, "short": args.prior_poses, "full": args.poses}
    docs = {}
    for name, poses in runs.items():
        data = work / f"new_{poses}"
        if not data.exists():
            simulate_tracker(TrackerSimConfig(seed=999, poses=poses, **kw), data)
        extra = ["--prior", str(work / "out" / "fleet.json")] if name == "short_prior" else []
        print(f"a new unit, {poses} poses{' with the prior' if extra else ''} ...", flush=True)
        _jaxcal(["calibrate", str(data), "--out", str(work / name), *config, *extra], env)
        docs[name] = json.loads((work / name / "result.json").read_text())
    ee = {k: d["validation"]["ee_rms_mm_after"] for k, d in docs.items()}
    cv = {
        k: next(m.get("cv_mean_mm") for m in d["point_fit"]["models"] if m["kept"]) for k, d in docs.items()
    }
    folds = args.cv_folds > 0
    share = docs["short_prior"]["point_fit"]["prior"]["share"]
    return {
        "prior_poses": args.prior_poses,
        "ee_rms_mm": ee,
        "cv_mean_mm": cv,
        "prior_30_over_full_1000": ee["short_prior"] / ee["full"],
        "noprior_30_over_full_1000": ee["short"] / ee["full"],
        "cv_prior_30_over_full_1000": cv["short_prior"] / cv["full"] if folds else None,
        "cv_noprior_30_over_full_1000": cv["short"] / cv["full"] if folds else None,
        "prior_share_mean": float(np.mean(share)),
        "prior_parameters": len(share),
    }


if __name__ == "__main__":
    main()
