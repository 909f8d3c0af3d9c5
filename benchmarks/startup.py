"""Start-up of jaxcal's commands: what a user waits for from the shell (issue 35).

Every figure is the wall time of a fresh process, the median of `--repeats`
(default 3), each run with `XDG_CACHE_HOME` pointing at a cache of this
benchmark's own (so that nothing else's cache counts, and the cold runs start
from an empty one):

- `import_s`: `python -c "import jaxcal"`.
- `cold_cli_s`: `jaxcal calibrate data/ur5e_sweeps --out DIR` with an empty
  cache (JAX's compiled executables and jaxcal's stored programs); each
  repeat empties it first.
- `warm_cli_s`: the same command again, the cache warm.
- `inprocess_second_s`: `jaxcal.calibrate(data/ur5e_sweeps)` called a second
  time in one process (the work itself), warm cache, measured in the same run
  as `warm_cli_s`.
- `handeye_warm_cli_s`: `jaxcal handeye CAPTURE --out DIR` on a 16-frame
  eye-in-hand capture (rendered once by `jaxcal simulate-handeye`, MuJoCo),
  warm cache; `null` where it cannot render.
- `ee_rms_mm_after_cold`, `ee_rms_mm_after_warm`: the validation's end-effector
  RMS after calibration of the first cold and the first warm run (equal to
  round-off).
- `tracker_cold_cli_s`, `tracker_warm_cli_s`: `jaxcal calibrate data/ur5_tracker/grid
  --device-is-base --out DIR` (the real UR5's 1000 laser-tracker poses, 5-fold
  cross-validation and every output), with an empty and a warm cache;
  `tracker_terms_warm_cli_s`: the same with `--terms compliance,harmonic1,harmonic2`;
  `tracker_verify_warm_cli_s`: `jaxcal verify RESULT data/ur5_tracker/test` on the
  geometric result; `tracker_cv_mean_mm`, `tracker_best_cv_mean_mm`: their
  cross-validated errors (unchanged by any speed-up).
- `stages_s`: where each warm command's seconds go (the median run's): its result's
  `timings_s` (the pipeline's stages, in process) and `outside_s`, the wall time
  around them (start-up, imports, parsing, writing the outputs, exit).

    python benchmarks/startup.py --json results/startup.json [--repeats 3] [--no-cold] [--cache DIR]

The JSON also holds every repeat (`runs`), `load` (the 1-minute load average
before each figure: on a shared machine the figures are only comparable back
to back), `cpu_s` (the median CPU time, user + system, of each shell figure's
processes: less sensitive to other users of the machine than the wall time)
and `machine`.
"""

import argparse
import json
import os
import platform
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATASET = ROOT / "data" / "ur5e_sweeps"
TRACKER = ROOT / "data" / "ur5_tracker"
TERMS = "compliance,harmonic1,harmonic2"
JAXCAL = [sys.executable, "-m", "jaxcal"]

INPROCESS = r"""
import json, sys, time
import jaxcal
jaxcal.calibrate(sys.argv[1], progress=False)
t0 = time.perf_counter()
jaxcal.calibrate(sys.argv[1], progress=False)
print(json.dumps({"second_s": time.perf_counter() - t0}))
"""


def _load() -> float:
    return os.getloadavg()[0]


#: CPU seconds (user + system) of each finished `_run`, in order.
CPU: list[float] = []


def _children_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def _run(cmd: list[str], env: dict) -> float:
    """Wall time of `cmd`; its CPU time goes to `CPU`."""
    c0, t0 = _children_cpu(), time.perf_counter()
    subprocess.run(cmd, env=env, check=True, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    wall = time.perf_counter() - t0
    CPU.append(_children_cpu() - c0)
    return wall


def _calibrate(env: dict, out: Path) -> tuple[float, float]:
    """Wall time of one `jaxcal calibrate` and its result's `ee_rms_mm_after`."""
    shutil.rmtree(out, ignore_errors=True)
    wall = _run([*JAXCAL, "calibrate", str(DATASET), "--out", str(out), "--quiet"], env)
    result = json.loads((out / "result.json").read_text())
    STAGES.append(_stages(result, wall))
    return wall, result["validation"]["ee_rms_mm_after"]


#: Per finished calibration (in order), its stages' seconds (`_stages`).
STAGES: list[dict] = []


def _stages(result: dict, wall: float) -> dict:
    timings = {k: round(v, 3) for k, v in result["timings_s"].items()}
    return timings | {"outside_s": round(wall - timings["total_s"], 3)}


def _median_stages(walls: list[float], stages: list[dict]) -> dict:
    """The stages of the run whose wall time is the median."""
    return stages[sorted(range(len(walls)), key=walls.__getitem__)[len(walls) // 2]]


def _tracker(env: dict, out: Path, *extra: str) -> tuple[float, float]:
    """Wall time of one `jaxcal calibrate` of the real UR5's tracker grid and its CV mean (mm)."""
    shutil.rmtree(out, ignore_errors=True)
    cmd = [*JAXCAL, "calibrate", str(TRACKER / "grid"), "--device-is-base", "--out", str(out), *extra]
    wall = _run(cmd, env)
    result = json.loads((out / "result.json").read_text())
    STAGES.append(_stages(result, wall))
    kept = next(m for m in result["point_fit"]["models"] if m["kept"])
    return wall, kept["cv_mean_mm"]


def _tracker_figures(env: dict, work: Path, args, report: dict) -> None:
    """The real UR5 tracker grid's cold and warm calibrations, with terms, and `verify` (warm)."""
    out = work / "tracker"
    cold = []
    for _ in range(0 if args.cache else 1 if args.no_cold else args.repeats):
        shutil.rmtree(work / "cache", ignore_errors=True)
        report["load"].setdefault("tracker_cold_cli_s", _load())
        cold.append(_tracker(env, out)[0])
    if cold and not args.no_cold:
        _figure("tracker_cold_cli_s", cold, report, CPU[-len(cold) :])
    for name, extra, cv in (
        ("tracker_warm_cli_s", (), "tracker_cv_mean_mm"),
        ("tracker_terms_warm_cli_s", ("--terms", TERMS), "tracker_best_cv_mean_mm"),
    ):
        _tracker(env, out, *extra)  # fills the cache for these terms (a cold one's programs are stored)
        report["load"][name] = _load()
        runs = [_tracker(env, out, *extra) for _ in range(args.repeats)]
        walls = [w for w, _ in runs]
        _figure(name, walls, report, CPU[-len(runs) :])
        report["stages_s"][name] = _median_stages(walls, STAGES[-len(runs) :])
        report[cv] = runs[0][1]
    _tracker(env, out)
    verify = [*JAXCAL, "verify", str(out), str(TRACKER / "test")]
    _run(verify, env)
    report["load"]["tracker_verify_warm_cli_s"] = _load()
    runs = [_run(verify, env) for _ in range(args.repeats)]
    _figure("tracker_verify_warm_cli_s", runs, report, CPU[-len(runs) :])


def _figure(name: str, runs: list[float], report: dict, cpu: list[float] | None = None) -> None:
    report["runs"][name] = runs
    report[name] = statistics.median(runs)
    line = f"{name}: {report[name]:.2f} s (runs {', '.join(f'{r:.2f}' for r in runs)})"
    if cpu:
        report["cpu_s"][name] = statistics.median(cpu)
        line += f", CPU {report['cpu_s'][name]:.2f} s"
    print(line, flush=True)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", help="write the figures here")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--no-cold", action="store_true", help="skip the cold runs (about a minute each)")
    parser.add_argument(
        "--cache",
        help="run on this compilation cache, as it is (no cold runs, nothing emptied: the figures are not "
        "this benchmark's; the tests give theirs to check the script runs)",
    )
    args = parser.parse_args(argv)
    work = Path(tempfile.mkdtemp(prefix="jaxcal-startup-"))
    env = {**os.environ, "XDG_CACHE_HOME": str(work / "cache")}
    # A user's Python keeps its bytecode (`__pycache__`); a machine set up not to (as CI machines
    # often are) would count compiling jaxcal's sources into every start-up.
    for var in ("JAX_COMPILATION_CACHE_DIR", "JAXCAL_NO_CACHE", "PYTHONDONTWRITEBYTECODE"):
        env.pop(var, None)
    if args.cache:
        env["JAX_COMPILATION_CACHE_DIR"] = args.cache
    report: dict = {
        "runs": {},
        "load": {},
        "cpu_s": {},
        "stages_s": {},
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform()},
    }
    try:
        report["load"]["import_s"] = _load()
        _figure(
            "import_s",
            [_run([sys.executable, "-c", "import jaxcal"], env) for _ in range(args.repeats)],
            report,
            CPU[-args.repeats :],
        )
        cold, ee_cold = [], None
        for _ in range(0 if args.cache else 1 if args.no_cold else args.repeats):
            shutil.rmtree(work / "cache", ignore_errors=True)
            report["load"].setdefault("cold_cli_s", _load())
            wall, ee = _calibrate(env, work / "out")
            cold.append(wall)
            ee_cold = ee if ee_cold is None else ee_cold
        if cold and not args.no_cold:
            _figure("cold_cli_s", cold, report, CPU[-len(cold) :])
        report["ee_rms_mm_after_cold"] = ee_cold
        report["load"]["warm_cli_s"] = _load()
        warm = [_calibrate(env, work / "out") for _ in range(args.repeats)]
        _figure("warm_cli_s", [w for w, _ in warm], report, CPU[-len(warm) :])
        report["stages_s"]["warm_cli_s"] = _median_stages([w for w, _ in warm], STAGES[-len(warm) :])
        report["ee_rms_mm_after_warm"] = warm[0][1]
        seconds = []
        for _ in range(args.repeats):
            run = subprocess.run(
                [sys.executable, "-c", INPROCESS, str(DATASET)], env=env, cwd=ROOT, check=True,
                capture_output=True, text=True,
            )  # fmt: skip
            seconds.append(json.loads(run.stdout.strip().splitlines()[-1])["second_s"])
        _figure("inprocess_second_s", seconds, report)
        _handeye(env, work, args.repeats, report)
        _tracker_figures(env, work, args, report)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    print(
        f"ee_rms_mm_after: cold {report['ee_rms_mm_after_cold']!r}, warm {report['ee_rms_mm_after_warm']!r}"
    )
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(report, indent=2) + "\n")


def _handeye(env: dict, work: Path, repeats: int, report: dict) -> None:
    """`handeye_warm_cli_s` on a rendered 16-frame capture (None where rendering fails)."""
    capture = work / "handeye"
    try:
        subprocess.run(
            [*JAXCAL, "simulate-handeye", "--out", str(capture), "--frames", "16"], env=env, cwd=ROOT,
            check=True, capture_output=True,
        )  # fmt: skip
    except subprocess.CalledProcessError as e:
        print(f"handeye: no capture ({e.stderr.decode()[-300:]})", file=sys.stderr)
        report["handeye_warm_cli_s"] = None
        return
    runs = []
    for k in range(repeats + 1):  # the first fills the cache
        out = work / f"handeye_out{k}"
        wall = _run([*JAXCAL, "handeye", str(capture), "--out", str(out)], env)
        if k:
            runs.append(wall)
    report["load"]["handeye_warm_cli_s"] = _load()
    _figure("handeye_warm_cli_s", runs, report, CPU[-len(runs) :])


if __name__ == "__main__":
    main()
