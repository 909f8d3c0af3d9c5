"""Compile budget of `jaxcal calibrate`: cold (empty compilation cache) and a second dataset.

Each measurement runs in a fresh subprocess with its own empty persistent
cache directory, so nothing compiled before counts:

1. `cold_calibrate_s`: wall time of `jaxcal.calibrate(data/ur5e_sweeps)`
   (detection, clock, arcs, axes, refinement, validation), with the time
   JAX spent tracing, lowering and compiling (`compile_s`, from JAX's own
   monitoring events) and its share per jitted entry point. The two-stage fit's
   programs compile on a background thread while the clock fit compiles and runs
   (`jaxcal.stages._programs.compile_two_stage_ahead`), so on two cores the JAX
   time can exceed the wall time.
2. `second_dataset_compile_s`: in the same process, a second dataset with
   other frame counts (the first with every third frame of two sweeps
   dropped): the compilation it still needs. With size buckets it reuses the
   first dataset's programs.

    python benchmarks/compile.py --json results/compile.json

The JSON holds `dataset`, `cold_calibrate_s`, `cold_jax_compile_s`,
`cold_process_s`, `second_dataset_compile_s`, `second_dataset_wall_s`, the
per-entry-point detail `first` and `second`, and `machine`. With `--cache DIR`
the child uses that compilation cache instead of an empty one (and keeps
`XLA_FLAGS`): the figures are then not cold.
"""

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATASET = ROOT / "data" / "ur5e_sweeps"

CHILD = r"""
import json, sys, time, collections
from pathlib import Path
import jax
from jax._src import monitoring
from jax._src import dispatch

events = collections.defaultdict(float)
names = collections.Counter()
KEYS = {dispatch.JAXPR_TRACE_EVENT: "trace", dispatch.JAXPR_TO_MLIR_MODULE_EVENT: "lower",
        dispatch.BACKEND_COMPILE_EVENT: "compile"}

def listener(event, duration, **kwargs):
    if event in KEYS:
        events[KEYS[event]] += duration
        if KEYS[event] == "compile":
            names[kwargs.get("fun_name", "?")] += duration

try:
    monitoring.register_event_duration_secs_listener(listener)
except TypeError:
    pass

import jaxcal

def run(ds):
    before = dict(events); per_before = collections.Counter(names)
    t = time.perf_counter()
    r = jaxcal.calibrate(ds, progress=False, workers=int(sys.argv[3]))
    wall = time.perf_counter() - t
    spent = {k: events[k] - before.get(k, 0.0) for k in KEYS.values()}
    per = {k: round(v - per_before.get(k, 0.0), 2) for k, v in names.items() if v - per_before.get(k, 0.0) > 0.2}
    return {"wall_s": wall, "trace_s": spent["trace"], "lower_s": spent["lower"], "compile_s": spent["compile"],
            "jax_s": sum(spent.values()), "per_program_compile_s": dict(sorted(per.items(), key=lambda kv: -kv[1])),
            "ee_rms_mm_after": r.validation["ee_rms_mm_after"] if r.validation else None}

if __name__ == "__main__":
    first = run(sys.argv[1])
    second = run(sys.argv[2])
    print(json.dumps({"first": first, "second": second}))
"""


def _second_dataset(tmp: Path) -> Path:
    """`data/ur5e_sweeps` with every third frame of two sweeps dropped (other frame counts)."""
    import csv

    dst = tmp / "second"
    shutil.copytree(DATASET, dst)
    meta = json.loads((dst / "metadata.json").read_text())
    segs = [s for s in meta["motion"] if s["joint"] in ("shoulder_lift_joint", "wrist_2_joint")]
    offset = (meta.get("clock") or {}).get("offset_s") or 0.04
    rows = list(csv.reader((dst / "frames.csv").read_text().splitlines()))
    keep, kept_rows, k = [rows[0]], [], 0
    for i, r in enumerate(rows[1:]):
        t_ctrl = float(r[2]) - offset
        if any(s["start"] <= t_ctrl <= s["end"] for s in segs):
            k += 1
            if k % 3 == 0:
                continue
        keep.append(r)
        kept_rows.append(i)
    with open(dst / "frames.csv", "w", newline="") as f:
        csv.writer(f).writerows(keep)
    truth = json.loads((dst / "truth.json").read_text())
    new_row = {old: new for new, old in enumerate(kept_rows)}
    truth["frames"] = [dict(f, row=new_row[f["row"]]) for f in truth["frames"] if f["row"] in new_row]
    (dst / "truth.json").write_text(json.dumps(truth))
    return dst


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", help="write the figures here")
    parser.add_argument("--workers", type=int, default=2, help="detection processes")
    parser.add_argument(
        "--cache",
        help="persistent compilation cache of the child (default: a fresh empty one, the cold measurement; "
        "the tests give a warm one to check the script runs)",
    )
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        second = _second_dataset(tmp)
        env = dict(os.environ, JAX_COMPILATION_CACHE_DIR=args.cache or str(tmp / "cache"))
        if args.cache is None:
            env.pop("XLA_FLAGS", None)
        t = time.perf_counter()
        what = "calibrating two datasets in a fresh process" + (
            " with an empty compilation cache" if args.cache is None else ""
        )
        print(f"{what} (a minute or two) ...", flush=True)
        child = subprocess.Popen(
            [sys.executable, "-c", CHILD, str(DATASET), str(second), str(args.workers)],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        while True:  # this process imports no jaxcal (its environment would reach the child): lines by hand
            try:
                stdout, stderr = child.communicate(timeout=8.0)
                break
            except subprocess.TimeoutExpired:
                print(f"{what}: still working ({time.perf_counter() - t:.0f} s)", flush=True)
        out = subprocess.CompletedProcess(child.args, child.returncode, stdout, stderr)
        total = time.perf_counter() - t
    if out.returncode != 0:
        print(out.stderr[-4000:], file=sys.stderr)
        return 1
    r = json.loads(out.stdout.strip().splitlines()[-1])
    result = {
        "dataset": str(DATASET.relative_to(ROOT)),
        "cold_calibrate_s": round(r["first"]["wall_s"], 2),
        "cold_jax_compile_s": round(r["first"]["jax_s"], 2),
        "cold_process_s": round(total, 2),
        "second_dataset_compile_s": round(r["second"]["jax_s"], 2),
        "second_dataset_wall_s": round(r["second"]["wall_s"], 2),
        "first": r["first"],
        "second": r["second"],
        "machine": f"{os.cpu_count()} cores",
    }
    print(
        json.dumps(result, indent=2)
        if not args.json
        else f"cold calibrate {result['cold_calibrate_s']} s; wrote {args.json}"
    )
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
