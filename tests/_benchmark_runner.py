"""Runs benchmarks' `main(argv)` one after another in this one process (tests/test_benchmarks.py).

    python tests/_benchmark_runner.py RUNS.json RECORDS.jsonl

`RUNS.json`: a list of `{"name", "script", "args"}` (`script` a file stem of benchmarks/). Each
run is called as its script's `main(args)`, as `python benchmarks/SCRIPT.py ARGS` would call it,
and one JSON line per run is appended to `RECORDS.jsonl` when it ends: its `name`, `error` (the
traceback, or None), `wall_s` and `cpu_s` (this process's and its waited-for children's). The
runs share the process's imports and compiled programs: a benchmark's smallest size is mostly
compilation, and runs of one design compile it once. `JAXCAL_BENCH_PROFILE=DIR` writes each
run's `cProfile` statistics to `DIR/<name>.prof` (where a run's time goes).
"""

import cProfile
import importlib
import json
import os
import resource
import sys
import time
import traceback
from pathlib import Path

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"


def _cpu() -> float:
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def main(runs: Path, records: Path) -> None:
    sys.path.insert(0, str(BENCH))
    for run in json.loads(runs.read_text()):
        print(f"=== {run['name']}: {run['script']}.py {' '.join(run['args'])}", flush=True)
        t0, c0 = time.perf_counter(), _cpu()
        error = None
        profile = cProfile.Profile() if os.environ.get("JAXCAL_BENCH_PROFILE") else None
        try:
            main = importlib.import_module(run["script"]).main
            code = main(list(run["args"])) if profile is None else profile.runcall(main, list(run["args"]))
            if isinstance(code, int) and code != 0:
                error = f"main returned {code}"
        except SystemExit as e:  # argparse's errors, a script's own exit
            if e.code not in (0, None):
                error = f"SystemExit({e.code!r})\n{traceback.format_exc()}"
        except Exception:  # reported; the next run goes on
            error = traceback.format_exc()
        if profile is not None:
            profile.dump_stats(Path(os.environ["JAXCAL_BENCH_PROFILE"]) / f"{run['name']}.prof")
        record = {
            "name": run["name"],
            "error": error,
            "wall_s": time.perf_counter() - t0,
            "cpu_s": _cpu() - c0,
        }
        with records.open("a") as f:
            f.write(json.dumps(record) + "\n")
        print(f"=== {run['name']}: {'failed' if error else 'ok'} in {record['cpu_s']:.1f} CPU s", flush=True)


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]))
