"""Benchmark: a real UR5 measured by a laser tracker, calibrated by jaxcal and by an independent SciPy fit.

Public data (`data/ur5_tracker`, from pauljac7700/serial_robots_datasets, MIT; see
`data/README.md`): 1000 grid poses to calibrate on, 20 random poses to test on,
the tracker registered to the robot's base (`--device-is-base`).

1. From the command line, as a user runs it (its entry, `jaxcal.cli.main`, called in this
   process): `jaxcal calibrate data/ur5_tracker/grid --device-is-base` (geometric model; with
   `--terms compliance`; with every term offered, `compliance,harmonic1,harmonic2`, the best
   model cross-validation keeps), then `jaxcal verify RESULT data/ur5_tracker/test` on each:
   test mean, RMS and max (mm), the 5-fold cross-validation on the grid, and the test RMS the
   calibration predicts (covariance and residual scale) over the measured one.
2. Side by side in the same run: an independent NumPy/SciPy implementation of the same
   model (`benchmarks/_scipy_tracker.py`: standard DH with Hayati's beta, base frame,
   tool point, identifiable columns by pivoted QR, `scipy.optimize.least_squares`) on
   the same samples: its test error, and the warm fit time of each
   (`fit_ms`: jaxcal's compiled point fit, identifiability search and covariance
   included, median of 35; `scipy_fit_ms`: `least_squares` alone, median of 7),
   measured in alternating rounds (`--rounds`, 7) in one process so that both see the same load;
   `speedup` is the median of the rounds' ratios.
3. `cold_fit_s`: jaxcal's first fit in a fresh process with an empty compilation
   cache (tracing and compiling included; with `--cache DIR` that cache, not cold).
4. Corrupted copies of the grid (issue 49): 1, 5 and 20 of its 1000 rows with one joint cell
   turned by 2-10 deg (`corrupt`, seeded), each calibrated and verified as in 1 (geometric):
   `ur5_bad_rows_<n>_test_mean_mm` (the held-out mean), `ur5_bad_rows_<n>_named` (the samples the
   robust point fit rejected and named) and `_named_correctly` (of them, the corrupted ones);
   `--bad-rows` chooses the counts.

`fit_ms` times the least-squares fit (identifiability search, solve, covariance), the work
SciPy's `least_squares` does; `screen_ms` the robust screen `jaxcal calibrate` runs after it
(every sample's deletion residual, `jaxcal._pointfit.sample_radii`; on clean data the robust
rounds do not run), `cold_screen_s` its first call.

Run:

    .venv/bin/python benchmarks/real_tracker.py --json results/real_tracker.json

The JSON holds the keys named in issue 31 (`ur5_test_mean_mm`, ..., `speedup`,
`cold_fit_s`), those of issue 49 (`ur5_bad_rows_<n>_...`) and the per-model detail under
`models` and `bad_rows`.
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

GRID = ROOT / "data" / "ur5_tracker" / "grid"
TEST = ROOT / "data" / "ur5_tracker" / "test"
#: The thesis that published the data: MDH calibration plus a neural-network residual model.
THESIS_MEAN_MM = 0.1549

#: Models calibrated from the CLI: name -> extra arguments.
MODELS = {
    "geometric": [],
    "compliance": ["--terms", "compliance"],
    "best": ["--terms", "compliance,harmonic1,harmonic2"],
}

#: The geometric point fit of the dataset at `sys.argv[1]`, set up in a fresh process (`_fit`
#: and `_radii` imported, `problem`, `cand`, `scale` built; `t0` when jaxcal's import began):
#: the start of the scripts here and in benchmarks/peers.py that time the compiled fit.
POINT_FIT_SETUP = """
import json, sys, time
import numpy as np
import jax
jax.config.update("jax_enable_x64", True)
t0 = time.perf_counter()
from jaxcal.io.dataset import load_dataset
from jaxcal._correction import ParameterLayout
from jaxcal._pointfit import PointLayout
from jaxcal.stages._points import _fit, _radii, candidates, plausible_scale, point_problem
from jaxcal.stages.limits import Limits
ds = load_dataset(sys.argv[1])
nominal, s = ds.load_model(), ds.samples
layout = PointLayout(ParameterLayout.of(nominal, 1, fixed_name="T_device_base"))
problem = point_problem(nominal, layout, s.q, s.position, s.sigma_m, np.ones(len(s.q), bool), np.eye(4),
                        np.asarray(ds.point.T_link_target))
cand = candidates(layout, fixed_frame_free=False)
scale = plausible_scale(layout, nominal, Limits())
"""

COLD = (
    POINT_FIT_SETUP
    + """
t1 = time.perf_counter()
res = jax.block_until_ready(_fit(problem, cand, 1e-3, scale))
t2 = time.perf_counter()
jax.block_until_ready(_radii(problem, res))
t3 = time.perf_counter()
# Warm calls interleaved with SciPy's fits of the same samples, so that both see the
# same machine load: the speedup is the median of the rounds' ratios.
sys.path.insert(0, sys.argv[2])
import _scipy_tracker as ref
qg, yg = ref.load_samples(sys.argv[1] + "/samples.csv")
ts, ss, ratios, screens = [], [], [], []
for _ in range(int(sys.argv[3])):
    round_ts = []
    for _ in range(5):
        a = time.perf_counter()
        fit = jax.block_until_ready(_fit(problem, cand, 1e-3, scale))
        round_ts.append(time.perf_counter() - a)
        a = time.perf_counter()
        jax.block_until_ready(_radii(problem, fit))
        screens.append(time.perf_counter() - a)
    s_fit = ref.fit(qg, yg)["fit_s"]
    ts += round_ts
    ss.append(s_fit)
    ratios.append(s_fit / float(np.median(round_ts)))
print(json.dumps({"cold_fit_s": t2 - t1, "cold_screen_s": t3 - t2, "setup_s": t1 - t0,
                  "fit_ms": 1e3 * float(np.median(ts)), "fit_ms_min": 1e3 * float(min(ts)),
                  "screen_ms": 1e3 * float(np.median(screens)), "scipy_fit_ms": 1e3 * float(np.median(ss)),
                  "speedup": float(np.median(ratios)), "free": int(np.sum(res.free))}))
"""
)


def _jaxcal(*args: str) -> subprocess.CompletedProcess:
    """`jaxcal ARGS` through the command line's own entry (`jaxcal.cli.main`) in this process: the
    same parsing, checks, outputs and exit code, while the runs share one start-up and their
    compiled programs (one `python -m jaxcal` each costs seconds of importing and tracing)."""
    import contextlib
    import io

    from jaxcal.cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = main(list(args))
        except SystemExit as e:  # argparse's own exit
            code = e.code if isinstance(e.code, int) else 2
    return subprocess.CompletedProcess(["jaxcal", *args], code, out.getvalue(), err.getvalue())


def cli_models(workdir: Path) -> dict:
    """Calibrate each model from the CLI, then verify it on the test poses."""
    out = {}
    for name, extra in MODELS.items():
        result = workdir / name
        t0 = time.perf_counter()
        p = _jaxcal("calibrate", str(GRID), "--device-is-base", "--quiet", "--out", str(result), *extra)
        wall = time.perf_counter() - t0
        if p.returncode != 0:
            raise RuntimeError(f"jaxcal calibrate ({name}) exited {p.returncode}:\n{p.stdout}\n{p.stderr}")
        verdict = workdir / f"{name}_verify.json"
        p = _jaxcal(
            "verify", str(result), str(TEST), "--json", str(verdict), "--plot", str(workdir / f"{name}.png")
        )
        if p.returncode != 0:
            raise RuntimeError(f"jaxcal verify ({name}) exited {p.returncode}:\n{p.stdout}\n{p.stderr}")
        doc = json.loads((result / "result.json").read_text())
        v = json.loads(verdict.read_text())["summary"]
        kept = next(m for m in doc["point_fit"]["models"] if m["kept"])
        out[name] = {
            "status": doc["status"],
            "reasons": doc["reasons"],
            "terms_kept": kept["terms"],
            "models_tried": doc["point_fit"]["models"],
            "free_parameters": int(sum(doc["point_fit"]["free"])),
            "held": doc["point_fit"]["held"],
            "term_rows": [r for r in doc["point_fit"]["term_rows"] if r["free"]],
            "test_mm": v["calibrated_mm"],
            "nominal_test_mm": v["nominal_mm"],
            "cv_mean_mm": kept["cv_mean_mm"],
            "predicted_over_measured": 1.0 / v["measured_over_predicted"],
            "inside_95_bound": v["inside_95_bound"],
            "calibrate_wall_s": wall,
        }
    return out


#: Corrupted copies of the grid: this many rows each get one joint cell turned.
BAD_ROWS = (1, 5, 20)
#: The joints a corruption turns: the first five. The reflector sits 0.09 mm off the last joint's
#: axis, so a wrist 3 turned by 10 deg moves it by 16 um, under the scatter of the clean samples
#: (about 60 um): invisible, and harmless to the calibration.
BAD_JOINTS = 5


def corrupt(n: int, out: Path, seed: int = 49) -> list[dict]:
    """A copy of the grid in `out` with `n` rows' one joint cell turned by 2-10 deg (either
    sign; rows, joints and angles drawn with `seed`). Returns what was turned."""
    import shutil

    rng = np.random.default_rng(seed + n)
    shutil.copytree(GRID, out)
    lines = (out / "samples.csv").read_text().splitlines()
    header = lines[0].split(",")
    first = header.index("z") + 1  # the joint columns follow x, y, z
    turned = []
    for row in sorted(rng.choice(len(lines) - 1, n, replace=False).tolist()):
        joint = int(rng.integers(BAD_JOINTS))
        deg = float(rng.uniform(2.0, 10.0) * rng.choice([-1.0, 1.0]))
        cells = lines[1 + row].split(",")
        cells[first + joint] = repr(float(cells[first + joint]) + float(np.radians(deg)))
        lines[1 + row] = ",".join(cells)
        turned.append({"sample": int(cells[0]), "joint": header[first + joint], "deg": deg})
    (out / "samples.csv").write_text("\n".join(lines) + "\n")
    return turned


def bad_rows(workdir: Path, counts=BAD_ROWS) -> dict:
    """Each corrupted copy calibrated (geometric) and verified from the command line."""
    out = {}
    for n in counts:
        data, result = workdir / f"grid_bad_{n}", workdir / f"bad_{n}"
        turned = corrupt(n, data)
        p = _jaxcal("calibrate", str(data), "--device-is-base", "--quiet", "--out", str(result))
        if p.returncode not in (0, 3):
            raise RuntimeError(
                f"jaxcal calibrate (bad rows {n}) exited {p.returncode}:\n{p.stdout}\n{p.stderr}"
            )
        verdict = workdir / f"bad_{n}_verify.json"
        p = _jaxcal("verify", str(result), str(TEST), "--json", str(verdict))
        if p.returncode != 0:
            raise RuntimeError(f"jaxcal verify (bad rows {n}) exited {p.returncode}:\n{p.stdout}\n{p.stderr}")
        doc = json.loads((result / "result.json").read_text())
        named = doc["point_fit"]["outliers"]
        bad = {t["sample"] for t in turned}
        out[n] = {
            "status": doc["status"],
            "turned": turned,
            "named": named,
            "named_correctly": sum(o["sample"] in bad for o in named),
            "test_mm": json.loads(verdict.read_text())["summary"]["calibrated_mm"],
            "notes": doc["notes"],
        }
    return out


def jaxcal_timing(rounds: int = 7, cache: str | None = None) -> dict:
    """The point fit's first call (empty cache, or `cache`) and warm calls, in a fresh process."""
    with tempfile.TemporaryDirectory() as empty:
        env = dict(os.environ, JAX_COMPILATION_CACHE_DIR=cache or empty)
        p = subprocess.run(
            [sys.executable, "-c", COLD, str(GRID), str(ROOT / "benchmarks"), str(rounds)],
            cwd=ROOT,
            capture_output=True,
            text=True,
            env=env,
            check=True,
        )
    return json.loads(p.stdout.strip().splitlines()[-1])


def scipy_reference() -> dict:
    import _scipy_tracker as ref

    qg, yg = ref.load_samples(GRID / "samples.csv")
    qt, yt = ref.load_samples(TEST / "samples.csv")
    res = ref.fit(qg, yg)
    err = ref.test_errors_mm(res, qt, yt)
    return {
        "free_parameters": int(res["n_free"]),
        "parameters": int(res["n_params"]),
        "test_mean_mm": float(err.mean()),
        "test_rms_mm": float(np.sqrt(np.mean(err**2))),
        "test_max_mm": float(err.max()),
    }


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", metavar="OUT", help="also write the JSON here (atomically)")
    parser.add_argument("--workdir", help="keep the results and plots here (default: a temporary directory)")
    parser.add_argument(
        "--rounds", type=int, default=7, help="timing rounds (5 jaxcal fits, 1 SciPy fit each)"
    )
    parser.add_argument(
        "--bad-rows",
        type=lambda v: tuple(int(x) for x in v.split(",")),
        default=BAD_ROWS,
        metavar="N,N,...",
        help=f"the corrupted copies' numbers of turned rows (default {','.join(map(str, BAD_ROWS))})",
    )
    parser.add_argument(
        "--cache",
        help="the timing process's compilation cache (default: a fresh empty one, the cold measurement; "
        "the tests give a warm one to check the script runs: cold_fit_s is then not cold)",
    )
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(args.workdir) if args.workdir else Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        print("calibrating the real UR5 with each model, and verifying on its held-out poses ...", flush=True)
        models = cli_models(work)
        print(f"the grid with {', '.join(map(str, args.bad_rows))} rows turned ...", flush=True)
        bad = bad_rows(work, args.bad_rows)
    print(f"timing the point fit ({args.rounds} rounds, a fresh process) ...", flush=True)
    timing = jaxcal_timing(args.rounds, args.cache)
    print("SciPy's fit of the same model ...", flush=True)
    scipy = scipy_reference()
    geo, comp, best = models["geometric"], models["compliance"], models["best"]
    out = {
        "ur5_test_mean_mm": geo["test_mm"]["mean"],
        "ur5_test_rms_mm": geo["test_mm"]["rms"],
        "ur5_test_max_mm": geo["test_mm"]["max"],
        "ur5_uncalibrated_test_mean_mm": geo["nominal_test_mm"]["mean"],
        "ur5_cv_mean_mm": geo["cv_mean_mm"],
        "ur5_compliance_test_mean_mm": comp["test_mm"]["mean"],
        "ur5_best_test_mean_mm": best["test_mm"]["mean"],
        "ur5_best_terms": best["terms_kept"],
        "ur5_predicted_over_measured": geo["predicted_over_measured"],
        "thesis_test_mean_mm": THESIS_MEAN_MM,
        "scipy_test_mean_mm": scipy["test_mean_mm"],
        "scipy_minus_jaxcal_test_mean_um": 1e3 * (scipy["test_mean_mm"] - geo["test_mm"]["mean"]),
        **{f"ur5_bad_rows_{n}_test_mean_mm": b["test_mm"]["mean"] for n, b in bad.items()},
        **{f"ur5_bad_rows_{n}_named": len(b["named"]) for n, b in bad.items()},
        **{f"ur5_bad_rows_{n}_named_correctly": b["named_correctly"] for n, b in bad.items()},
        "fit_ms": timing["fit_ms"],
        "screen_ms": timing["screen_ms"],
        "scipy_fit_ms": timing["scipy_fit_ms"],
        "speedup": timing["speedup"],
        "cold_fit_s": timing["cold_fit_s"],
        "cold_screen_s": timing["cold_screen_s"],
        "statuses": {k: m["status"] for k, m in models.items()},
        "models": models,
        "bad_rows": bad,
        "scipy": scipy,
        "timing": timing,
        "machine": {"cpus": os.cpu_count(), "python": sys.version.split()[0]},
        "date": time.strftime("%Y-%m-%d"),
    }
    text = json.dumps(out, indent=1)
    print(text if not args.json else f"held-out mean {out['ur5_test_mean_mm']:.4f} mm; wrote {args.json}")
    if args.json:
        from jaxcal.io._files import write_text_atomic

        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        write_text_atomic(args.json, text)
    return out


if __name__ == "__main__":
    main()
