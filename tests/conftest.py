import gc
import json
import os
import resource
import time
from collections import Counter
from pathlib import Path

# The suite is compile-bound: LLVM at -O0 compiles XLA's CPU programs about a
# third faster (the 8-trial Monte Carlo program: 45 -> 31 s) and the run time
# it costs (x2) is a fraction of a second per test. Set before JAX starts its
# backend; notebook kernels inherit it. Users' runs keep XLA's default.
os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_backend_optimization_level=0").strip()
# And JAX's own switch, which also skips XLA's expensive HLO passes: another
# ~15 % off the compile of a Monte Carlo trial (27.5 -> 23 s). Read from the
# environment, so notebook kernels and subprocesses get it too.
os.environ["JAX_DISABLE_MOST_OPTIMIZATIONS"] = "1"

import jax  # noqa: E402
import pytest  # noqa: E402

from jaxcal.sim._gl import select_backend

select_backend()  # before anything imports mujoco: headless EGL (or OSMesa) for the rendering tests

jax.config.update("jax_enable_x64", True)
# Compiled programs are cached on disk, so a second run of the suite (and the
# notebook kernels it starts) skips XLA compilation.
# `JAXCAL_TEST_CACHE=DIR` points it elsewhere (an empty directory measures a fresh
# clone's cold run).
CACHE_DIR = Path(
    os.environ.get("JAXCAL_TEST_CACHE") or Path(__file__).resolve().parents[1] / ".cache" / "jax"
)
jax.config.update("jax_compilation_cache_dir", str(CACHE_DIR))
jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
# Both xdist workers share it, and so does every process a test starts (scripts,
# the CLI, notebook kernels, benchmarks) through the environment: otherwise a
# script's `import jaxcal` compiles into the user's `~/.cache/jaxcal/xla`, cold on a
# fresh machine (the demo calibration in a subprocess: 50 CPU s cold, 22 s on the
# programs the suite had stored).
os.environ["JAX_COMPILATION_CACHE_DIR"] = str(CACHE_DIR)
os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "1.0"


#: Memory mappings a worker may hold at the end of a test file before its
#: compiled programs are dropped: files rarely share programs, a file's tests do
#: (a drop inside `test_calibrate.py` at 20,000 cost its later tests their
#: fixture's compiled pipeline) ...
MAX_MAPPINGS = 30_000
#: ... and the limit inside a file, well below the kernel's `vm.max_map_count` (65530).
HARD_MAPPINGS = 50_000


def _mappings() -> int:
    try:
        with open("/proc/self/maps", "rb") as f:
            return f.read().count(b"\n")  # after every test: no Python loop over ~30,000 lines
    except OSError:  # not Linux
        return 0


def pytest_runtest_teardown(item, nextitem):
    """Drop every compiled program when the worker holds many memory mappings.
    XLA's CPU executables hold a few mappings each, and a worker that has
    compiled ~15,000 programs reaches the kernel's `vm.max_map_count`: its next
    compile then aborts or segfaults (the CI crash in test_refine.py). Later
    tests reload what they share from the persistent cache."""
    last_of_file = nextitem is None or nextitem.path != item.path
    if _mappings() > (MAX_MAPPINGS if last_of_file else HARD_MAPPINGS):
        jax.clear_caches()
        gc.collect()


@pytest.fixture
def key():
    return jax.random.key(0)


#: The slowest files first, so that under `make test`'s `--dist loadfile` the two
#: workers end together on the short files instead of one worker finishing a
#: big file alone. The order holds only with `--no-loadscope-reorder` (Makefile):
#: pytest-xdist otherwise queues the files by their number of tests, which put
#: the notebooks (3 tests, minutes) near the end. CPU seconds per file from
#: `JAXCAL_TEST_CPU` on a fresh clone (2026-12-02, after the merges of issues 48,
#: 49, 54 and 55): benchmarks 830 (every benchmark mode; now in two files of about
#: 420 and 300, first: each worker starts on one, longest first, instead of one
#: worker running them all while the other takes the rest),
#: pointfit 164, notebooks 157, calibrate 156, arcfit 144, handeye_capture 129,
#: axisfit 107, plan 100, montecarlo 95, prismatic 92, armcheck 78, links 77,
#: refine 64, handeye 58, arm_model 57, eye_in_hand 55, terms 55, home 51,
#: startup 39, certify 37, then less; tree (2026-12-05) about 200.
SLOW_FIRST = (
    "test_benchmarks",
    "test_benchmarks_captures",
    "test_tree",
    "test_pointfit",
    "test_notebooks",
    "test_calibrate",
    "test_tree_camera",
    "test_arcfit",
    "test_handeye_capture",
    "test_axisfit",
    "test_plan",
    "test_montecarlo",
    "test_prismatic",
    "test_armcheck",
    "test_links",
    "test_check_camera",
    "test_refine",
    "test_handeye",
    "test_arm_model",
    "test_eye_in_hand",
    "test_terms",
    "test_home",
    "test_check_handeye",
    "test_startup",
    "test_certify",
    "test_rolling_shutter",
    "test_poses",
    "test_clocksync",
    "test_schur",
    "test_tracker",
    "test_sim",
    "test_inputs",
    "test_robust",
    "test_dh",
)


def pytest_collection_modifyitems(config, items):
    def rank(item) -> int:
        module = item.module.__name__.rpartition(".")[-1] if item.module is not None else ""
        return SLOW_FIRST.index(module) if module in SLOW_FIRST else len(SLOW_FIRST)

    items.sort(key=rank)  # stable: a file's tests keep their order


#: Per test file, the CPU seconds its tests took (the worker's threads and the
#: subprocesses it waited for), summed over the session: `JAXCAL_TEST_CPU=FILE`
#: appends one JSON line per worker to FILE. On a shared 2-core machine wall
#: times (`--durations`) vary several-fold with the load; CPU time does not, and
#: the suite is CPU-bound, so its wall time is about the total over two.
_CPU: Counter = Counter()
#: ... and per test (its node id), the 150 costliest kept in the same JSON line.
_CPU_TEST: Counter = Counter()


#: ... and per file, the seconds JAX reported spending in tracing, lowering and
#: XLA compilation, and in reading compiled programs from the persistent cache
#: (`jax.monitoring` events): where a file's time goes, without a profiler.
_JAX_S: dict[str, Counter] = {}
_CURRENT = ["-"]
_NODE = ["-"]
_JAX_EVENTS = {
    "/jax/core/compile/jaxpr_trace_duration": "trace",
    "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
    "/jax/core/compile/backend_compile_duration": "compile",
    "/jax/compilation_cache/cache_retrieval_time_sec": "cache_read",
}


def _on_jax_duration(event: str, duration: float, **_) -> None:
    kind = _JAX_EVENTS.get(event)
    if kind is not None:
        _JAX_S.setdefault(_CURRENT[0], Counter())[kind] += duration


if os.environ.get("JAXCAL_TEST_CPU"):
    jax.monitoring.register_event_duration_secs_listener(_on_jax_duration)


#: `JAXCAL_TEST_COMPILES=FILE`: one JSON line per XLA compile (a persistent-cache
#: miss): the program's name, its cache key, the seconds and the test. Programs
#: compiled more than once (by both workers, or again after a cache drop) and
#: programs compiled at many shapes are what the suite could share.
def _log_compiles(path: str) -> None:
    from jax._src import compiler

    write = compiler._compile_and_write_cache

    def logged(backend, computation, devices, options, callbacks, module_name, cache_key):
        start, wall = time.process_time(), time.monotonic()
        out = write(backend, computation, devices, options, callbacks, module_name, cache_key)
        row = {
            "name": module_name, "key": cache_key[-16:], "cpu_s": round(time.process_time() - start, 3),
            "wall_s": round(time.monotonic() - wall, 3), "test": _NODE[0], "worker": os.environ.get("PYTEST_XDIST_WORKER", "main"),
        }  # fmt: skip
        with open(path, "a") as f:
            f.write(json.dumps(row) + "\n")
        return out

    compiler._compile_and_write_cache = logged

    read = compiler._cache_read

    def logged_read(module_name, cache_key, *args):
        start = time.monotonic()
        out = read(module_name, cache_key, *args)
        if out[0] is not None:
            row = {
                "read": module_name, "key": cache_key[-16:], "wall_s": round(time.monotonic() - start, 3),
                "test": _NODE[0], "worker": os.environ.get("PYTEST_XDIST_WORKER", "main"),
            }  # fmt: skip
            with open(path, "a") as f:
                f.write(json.dumps(row) + "\n")
        return out

    compiler._cache_read = logged_read


if os.environ.get("JAXCAL_TEST_COMPILES"):
    _log_compiles(os.environ["JAXCAL_TEST_COMPILES"])


def _cpu_now() -> float:
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + children.ru_utime + children.ru_stime


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    start = _cpu_now()
    _CURRENT[0] = item.path.name
    _NODE[0] = item.nodeid
    yield
    spent = _cpu_now() - start
    _CPU[item.path.name] += spent
    _CPU_TEST[item.nodeid] += spent


def pytest_sessionfinish(session):
    out = os.environ.get("JAXCAL_TEST_CPU")
    if out and _CPU:
        worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
        with open(out, "a") as f:
            f.write(
                json.dumps(
                    {
                        "worker": worker,
                        "cpu_s": {k: round(v, 1) for k, v in _CPU.most_common()},
                        "slowest_tests": {k: round(v, 1) for k, v in _CPU_TEST.most_common(150)},
                        "jax_s": {f: {k: round(v, 1) for k, v in c.items()} for f, c in _JAX_S.items()},
                    }
                )
                + "\n"
            )
