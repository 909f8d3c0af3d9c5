"""Start-up (issue 35): stored programs reloaded and never trusted when damaged or
foreign, `import jaxcal` light, detection without the `__main__` trap, Ctrl-C
leaving no child process."""

import gc
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxcal import _exported

ROOT = Path(__file__).resolve().parents[1]
DATASET = ROOT / "data" / "ur5e_sweeps"


@pytest.fixture
def store(tmp_path, monkeypatch):
    """Stored programs in a folder of the test's own."""
    monkeypatch.setattr(_exported, "programs_dir", lambda: tmp_path)
    return tmp_path


def _program(traces: list, tag: str = ""):
    """A stored program; `tag` makes it another program (its executable then compiles afresh
    rather than from JAX's persistent cache, where an earlier test may have put it)."""

    def solve(x, flag):
        traces.append(1)  # runs only while the program is traced
        y = jnp.where(flag, x @ x.T + jnp.eye(x.shape[0]), x)
        return {"chol": jnp.linalg.cholesky(y), "sum": (y.sum(), jnp.zeros(2, jnp.int32))}

    return _exported.stored_jit(solve, "test_solve", static=("v1", tag) if tag else ("v1",))


def _entry(store: Path) -> Path:
    (path,) = store.glob("test_solve-*.jaxexport")
    return path


def _rewrite_key(path: Path, change) -> None:
    """Rewrite an entry's key (and its checksum, so that only the key is wrong)."""
    blob = path.read_bytes()[len(_exported.MAGIC) :]
    n = int.from_bytes(blob[:8], "little")
    head = json.loads(blob[8 : 8 + n])
    key = json.loads(head["key"])
    change(key)
    head["key"] = json.dumps(key, sort_keys=True)
    text = json.dumps(head).encode()
    path.write_bytes(_exported.MAGIC + len(text).to_bytes(8, "little") + text + blob[8 + n :])


def test_a_stored_program_is_reloaded_without_tracing(store):
    x = jnp.arange(9.0).reshape(3, 3)
    traces: list = []
    first = _program(traces)(x, True)
    assert len(traces) == 1 and _entry(store).is_file()
    again = _program(traces)(x, True)  # a new program object: what a second process sees
    assert len(traces) == 1  # read from the store, not traced
    assert jax.tree.structure(again) == jax.tree.structure(first)
    for a, b in zip(jax.tree.leaves(first), jax.tree.leaves(again)):
        np.testing.assert_array_equal(a, b)
        assert a.dtype == b.dtype
    _program(traces)(jnp.ones((4, 4)), False)  # other shapes: another entry
    assert len(traces) == 2 and len(list(store.glob("test_solve-*.jaxexport"))) == 2


@pytest.mark.parametrize(
    "damage",
    ["flipped byte", "truncated", "empty", "other jax version", "other source", "other program's key"],
)
def test_a_damaged_or_foreign_entry_is_ignored_and_rebuilt(store, damage):
    x = jnp.arange(9.0).reshape(3, 3)
    traces: list = []
    expected = _program(traces)(x, True)
    path = _entry(store)
    blob = path.read_bytes()
    if damage == "flipped byte":
        path.write_bytes(blob[:-100] + bytes([blob[-100] ^ 0xFF]) + blob[-99:])
    elif damage == "truncated":
        path.write_bytes(blob[: len(blob) // 2])
    elif damage == "empty":
        path.write_bytes(b"")
    elif damage == "other jax version":
        _rewrite_key(path, lambda k: k.update(jax="0.0.1"))
    elif damage == "other source":
        _rewrite_key(path, lambda k: k.update(jaxcal_source="0" * 64))
    else:
        _rewrite_key(path, lambda k: k.update(static="'v0'"))
    result = _program(traces)(x, True)
    assert len(traces) == 2  # not trusted: traced again
    for a, b in zip(jax.tree.leaves(expected), jax.tree.leaves(result)):
        np.testing.assert_array_equal(a, b)
    _program(traces)(x, True)  # ... and rebuilt: the next process reads it
    assert len(traces) == 2


def _executable(store: Path) -> Path:
    (path,) = store.glob("test_solve-*.xla")
    return path


def _reads(monkeypatch) -> list:
    """Whether each executable read from beside an entry was used (True) or not (False)."""
    read, seen = _exported._read_executable, []

    def spy(path, exported):
        out = read(path, exported)
        seen.append(out is not None)
        return out

    monkeypatch.setattr(_exported, "_read_executable", spy)
    return seen


@pytest.fixture
def fresh_compiles():
    """JAX's persistent cache keeps nothing new: a program compiled again compiles afresh (only an
    executable XLA compiled is kept beside its entry)."""
    before = jax.config.jax_persistent_cache_min_compile_time_secs
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 1e9)
    yield
    jax.config.update("jax_persistent_cache_min_compile_time_secs", before)


def test_the_executable_is_kept_beside_the_entry_and_loaded(store, monkeypatch, fresh_compiles, request):
    x = jnp.arange(9.0).reshape(3, 3)
    seen = _reads(monkeypatch)
    first = _program([], request.node.name)(x, True)
    assert seen == [False] and _executable(store).name.startswith(_entry(store).stem + ".")
    again = _program([], request.node.name)(
        x, True
    )  # a new program object: loaded, neither traced nor lowered
    assert seen == [False, True]
    for a, b in zip(jax.tree.leaves(first), jax.tree.leaves(again)):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("damage", ["flipped byte", "truncated", "empty", "another layout"])
def test_a_damaged_executable_is_ignored_and_rebuilt(store, monkeypatch, fresh_compiles, request, damage):
    x = jnp.arange(9.0).reshape(3, 3)
    expected = _program([], request.node.name)(x, True)
    path = _executable(store)
    blob = path.read_bytes()
    path.write_bytes(
        {
            "flipped byte": blob[:-100] + bytes([blob[-100] ^ 0xFF]) + blob[-99:],
            "truncated": blob[: len(blob) // 2],
            "empty": b"",
            "another layout": b"JAXCAL-XLA-0\n" + blob[len(_exported.XLA_MAGIC) :],
        }[damage]
    )
    seen = _reads(monkeypatch)
    result = _program([], request.node.name)(x, True)
    for a, b in zip(jax.tree.leaves(expected), jax.tree.leaves(result)):
        np.testing.assert_array_equal(a, b)
    _program([], request.node.name)(x, True)  # ... rebuilt: the next process loads it
    assert seen == [False, True]


def test_the_folder_keeps_to_its_budget_least_recently_used_first(store):
    now = time.time()
    for k, age in enumerate([50, 10, 40, 20, 30]):  # seconds since last used
        path = store / f"f{k}.xla"
        path.write_bytes(b"x" * 1000)
        os.utime(path, (now - age, now - age))
    _exported._keep_within_budget(store, budget=5000)  # within it: nothing goes
    assert len(list(store.iterdir())) == 5
    assert _exported._read_used(store / "f0.xla") == b"x" * 1000  # used now: the newest
    _exported._keep_within_budget(store, budget=4000)  # over it: down to 3000 bytes
    assert sorted(p.name for p in store.iterdir()) == ["f0.xla", "f1.xla", "f3.xla"]


def test_a_file_another_worker_removes_mid_listing_is_skipped(store, monkeypatch):
    """Two processes share the folder: a file removed between the listing and its `stat`
    is left out of the count, the rest still kept to the budget, and the listing closed
    (an unclosed one failed a CI run with a ResourceWarning)."""
    for k in range(4):
        (store / f"f{k}.xla").write_bytes(b"x" * 1000)
    listing, closed = os.scandir, []

    class Gone:  # what the listing returns for a file removed before its stat
        path = str(store / "gone.xla")

        def is_file(self):
            return True

        def stat(self):
            raise FileNotFoundError(self.path)

    class Racing:
        def __init__(self, folder):
            self.entries = listing(folder)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            closed.append(True)
            self.entries.close()

        def __iter__(self):
            yield Gone()
            yield from self.entries

    monkeypatch.setattr(_exported.os, "scandir", Racing)
    _exported._keep_within_budget(store, budget=2500)
    assert closed == [True]
    assert len(list(store.iterdir())) == 1  # 4000 bytes counted, down to 1875: three of four go


def test_an_executable_read_from_jaxs_cache_is_not_kept(store, monkeypatch):
    """XLA serialises an executable it read from JAX's persistent cache without some of its
    functions: only one XLA compiled is kept."""
    compile_ = jax.stages.Lowered.compile

    def from_cache(self, *args, **kwargs):
        out = compile_(self, *args, **kwargs)
        jax.monitoring.record_event("/jax/compilation_cache/cache_hits")
        return out

    monkeypatch.setattr(jax.stages.Lowered, "compile", from_cache)
    _program([])(jnp.eye(3), True)
    assert _entry(store).is_file() and not list(store.glob("*.xla"))


@pytest.mark.parametrize("kept", [True, False])
def test_a_kept_executable_is_not_written_to_jaxs_cache_too(tmp_path, monkeypatch, request, kept):
    """An executable kept beside its entry is serialised once, not a second time into JAX's
    persistent cache; without a folder for the stored programs JAX's cache keeps it as usual."""
    from jax._src import compilation_cache

    monkeypatch.setattr(_exported, "programs_dir", lambda: tmp_path if kept else None)
    put, names = compilation_cache.put_executable_and_time, []

    def spy(cache_key, module_name, *args, **kwargs):
        names.append(module_name)
        return put(cache_key, module_name, *args, **kwargs)

    monkeypatch.setattr(compilation_cache, "put_executable_and_time", spy)
    before = jax.config.jax_persistent_cache_min_compile_time_secs
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)  # every compile is written
    salt = time.time_ns() % 1_000_003  # a program no earlier run put in JAX's cache
    program = _exported.stored_jit(lambda x: x * salt + 1.0, "test_kept", static=(request.node.name, salt))
    try:
        program(jnp.eye(3))
    finally:
        jax.config.update("jax_persistent_cache_min_compile_time_secs", before)
    written = [n for n in names if n.startswith("jit_test_kept")]
    assert (len(written), len(list(tmp_path.glob("*.xla")))) == ((0, 1) if kept else (1, 0)), names


def test_a_loaded_executable_runs_lapack_in_a_fresh_process(tmp_path):
    """A process that runs a loaded executable calling LAPACK before it has lowered anything
    (jaxlib sets up its LAPACK functions lazily, when a program is lowered: unset, the call
    jumps to address 0)."""
    source = """
        import sys
        import jax, jax.numpy as jnp
        import jaxcal
        from jaxcal import _exported
        jax.config.update("jax_compilation_cache_dir", sys.argv[1])
        program = _exported.stored_jit(lambda a: jnp.linalg.cholesky(a @ a.T + jnp.eye(3)), "lapack_check")
        out = program(jnp.arange(9.0).reshape(3, 3))
        print(sorted(p.suffix for p in _exported.programs_dir().iterdir()), float(out.sum()))
    """
    script = tmp_path / "script.py"
    script.write_text(textwrap.dedent(source))
    runs = [
        subprocess.run([sys.executable, str(script), str(tmp_path / "cache")], capture_output=True, text=True)
        for _ in range(2)
    ]
    assert [r.returncode for r in runs] == [0, 0], runs[1].stderr[-2000:]
    assert runs[0].stdout == runs[1].stdout and ".xla" in runs[0].stdout


def test_the_key_names_what_decides_the_program(store):
    """Versions of jaxcal (and its sources), JAX, jaxlib and the traced libraries, the
    XLA flags, x64, the backend, the compiler options, the static configuration,
    the argument tree and shapes."""
    program = _program([])
    leaves, tree = jax.tree.flatten(((jnp.ones((2, 2)), True), {}))
    key = program._key(tree, [_exported._aval(x) for x in leaves])
    for field in (
        "jaxcal", "jaxcal_source", "jax", "jaxlib", "equinox", "optimistix", "lineax", "numpy",
        "xla_flags", "x64", "backend", "compiler_options", "static", "in_tree", "avals",
    ):  # fmt: skip
        assert field in key, field


def _run_script(tmp_path: Path, source: str, timeout: float = 900) -> subprocess.CompletedProcess:
    script = tmp_path / "script.py"
    script.write_text(textwrap.dedent(source))
    return subprocess.run(
        [sys.executable, str(script)], cwd=tmp_path, capture_output=True, text=True, timeout=timeout
    )


def test_import_jaxcal_loads_no_heavy_library(tmp_path):
    run = _run_script(
        tmp_path,
        """
        import sys
        import jaxcal
        heavy = ("cv2", "matplotlib", "rosbags", "mujoco", "yourdfpy", "trimesh", "scipy", "optimistix")
        print(sorted(m for m in heavy if m in sys.modules))
        print(jaxcal.fit_arc.__module__, jaxcal.vision.detect.__module__)
        """,
    )
    assert run.returncode == 0, run.stderr
    assert run.stdout.splitlines() == ["[]", "jaxcal._arcfit jaxcal.vision._detect"]


@pytest.mark.parametrize("method", ["spawn", "forkserver"])
def test_a_script_without_the_main_guard_detects_in_parallel(tmp_path, method):
    """Detection needs no `if __name__ == "__main__":`, whatever the start method."""
    run = _run_script(
        tmp_path,
        f"""
        import multiprocessing
        multiprocessing.set_start_method({method!r}, force=True)
        import jaxcal
        from jaxcal.io.dataset import load_dataset
        ds = load_dataset({str(DATASET)!r})
        paths = [ds.image_path(i) for i in range(40)]
        found = jaxcal.vision.detect_frames(paths, [ds.targets[0].spec], workers=2, progress=False)
        print(sum(len(f) for f in found), len(multiprocessing.active_children()))
        """,
    )
    assert run.returncode == 0, run.stderr
    detected, children = map(int, run.stdout.split())
    assert detected >= 20 and children == 0


@pytest.mark.slow
def test_a_script_without_the_main_guard_calibrates(tmp_path):
    run = _run_script(
        tmp_path,
        f"""
        import multiprocessing
        multiprocessing.set_start_method("spawn", force=True)
        import jaxcal
        result = jaxcal.calibrate({str(DATASET)!r}, progress=False)
        print(result.status, result.validation["ee_rms_mm_after"])
        """,
    )
    assert run.returncode == 0, run.stderr
    status, ee = run.stdout.split()
    assert status == "ok" and float(ee) < 1.0


def _group_members(pgid: int) -> list[int]:
    members = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[2]) == pgid:  # field 5 of /proc/PID/stat: the process group
            members.append(int(stat.parent.name))
    return members


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads /proc")
@pytest.mark.parametrize("pool", ["thread", "process"])
def test_ctrl_c_during_detection_leaves_no_child_process(tmp_path, pool):
    """Ctrl-C (SIGINT to the whole process group, as a terminal sends it) during a
    long detection: the run stops at once with KeyboardInterrupt and no process of
    its group is left."""
    script = tmp_path / "detect.py"
    script.write_text(
        textwrap.dedent(f"""
        import signal
        # As a terminal's shell starts it: pytest-xdist's workers ignore SIGINT, and a child
        # inherits an ignored SIGINT (Python then installs no KeyboardInterrupt handler).
        signal.signal(signal.SIGINT, signal.default_int_handler)
        import jaxcal
        from jaxcal.io.dataset import load_dataset
        ds = load_dataset({str(DATASET)!r})
        paths = [ds.image_path(i % 144) for i in range(144 * 1000)]  # minutes: still running at the Ctrl-C
        print("detecting", flush=True)
        jaxcal.vision.detect_frames(paths, [ds.targets[0].spec], workers=2, progress=False, pool={pool!r})
        """)
    )
    proc = subprocess.Popen(
        [sys.executable, str(script)], cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True, start_new_session=True,
    )  # fmt: skip
    try:
        assert proc.stdout.readline().strip() == "detecting"
        time.sleep(3.0)  # well into the detection (and, for processes, the pool started)
        os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()  # reap it and close its pipes
    assert proc.returncode != 0
    # Threads: the interrupt itself. Processes: the workers, interrupted too, may break the
    # pool before the caller's own KeyboardInterrupt is raised.
    assert (
        "KeyboardInterrupt" in err
        if pool == "thread"
        else ("KeyboardInterrupt" in err or "BrokenProcessPool" in err)
    )
    deadline = time.monotonic() + 10.0  # a forkserver notices its parent's end on its own
    while _group_members(proc.pid) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert _group_members(proc.pid) == []


def test_clear_caches_drops_the_executables_not_the_stored_programs(store):
    traces: list = []
    program = _program(traces)
    program(jnp.eye(3), True)
    assert program.cache_size() == 1
    jax.clear_caches()
    assert program.cache_size() == 0
    program(jnp.eye(3), True)  # read again from the store
    assert len(traces) == 1


def test_warm_start_reads_the_last_runs_programs_ahead(store):
    """A run records the entries it called; the next run with the tag reads them ahead and
    its calls take them (the same results); another tag reads nothing ahead."""
    x = jnp.arange(9.0).reshape(3, 3)
    traces: list = []
    with _exported.warm_start("run a"):
        first = _program(traces)(x, True)
    (manifest,) = store.glob("run-*.json")
    assert [e["program"] for e in json.loads(manifest.read_text())] == ["test_solve"]
    taken = []
    take = _exported._take_ahead

    def spy(file, key, program):
        entry = take(file, key, program)
        taken.append(entry is not None)
        return entry

    with pytest.MonkeyPatch.context() as m:
        m.setattr(_exported, "_take_ahead", spy)
        with _exported.warm_start("run a"):
            while _exported._AHEAD and not next(iter(_exported._AHEAD.values())).done():
                time.sleep(0.01)
            again = _program(traces)(x, True)
        with _exported.warm_start("run b"):
            assert not _exported._AHEAD
            _program(traces)(x, True)
    assert taken == [True, False] and len(traces) == 1
    for a, b in zip(jax.tree.leaves(first), jax.tree.leaves(again)):
        np.testing.assert_array_equal(a, b)


def test_warm_start_reads_nothing_ahead_that_the_process_holds(store):
    """A second run in one process (a notebook's, a test's) finds its programs in memory:
    reading their executables again would be thrown away (seconds of a second calibration).
    Once no program holds the entry, it is read ahead again."""
    x = jnp.arange(9.0).reshape(3, 3)
    traces: list = []
    program = _program(traces)
    with _exported.warm_start("run a"):
        program(x, True)
    with _exported.warm_start("run a"):
        assert not _exported._AHEAD
        program(x, True)
    assert len(traces) == 1
    del program
    gc.collect()
    with _exported.warm_start("run a"):
        assert len(_exported._AHEAD) == 1
        _program(traces)(x, True)
    assert len(traces) == 1 and not _exported._AHEAD


@pytest.mark.parametrize("damage", ["not json", "a path outside", "a damaged entry"])
def test_warm_start_ignores_a_damaged_manifest_or_entry(store, damage):
    x = jnp.arange(9.0).reshape(3, 3)
    traces: list = []
    with _exported.warm_start("run"):
        expected = _program(traces)(x, True)
    (manifest,) = store.glob("run-*.json")
    if damage == "not json":
        manifest.write_text("{")
    elif damage == "a path outside":
        manifest.write_text(json.dumps([{"program": "test_solve", "file": "../x", "compiler_options": None}]))
    else:
        path = _entry(store)
        path.write_bytes(path.read_bytes()[:-10])
    with _exported.warm_start("run"):
        result = _program(traces)(x, True)
    assert len(traces) == (2 if damage == "a damaged entry" else 1)
    for a, b in zip(jax.tree.leaves(expected), jax.tree.leaves(result)):
        np.testing.assert_array_equal(a, b)


def test_nested_warm_starts_record_their_own_runs(store):
    """A command's warm start around the library's (`jaxcal calibrate`: calibrate and outputs)."""
    x = jnp.arange(9.0).reshape(3, 3)
    traces: list = []
    with _exported.warm_start("outer"):
        with _exported.warm_start("inner"):
            _program(traces)(x, True)
        _program(traces)(jnp.ones((4, 4)), False)
    assert not _exported._RECORDING
    runs = sorted(len(json.loads(p.read_text())) for p in store.glob("run-*.json"))
    assert runs == [1, 2]


def test_the_command_ends_with_its_code_and_its_output_out(tmp_path):
    """`python -m jaxcal` (as the `jaxcal` script, `jaxcal.cli.run`) ends the process with
    `os._exit` once a command returns: its exit code and everything it printed, piped and
    so block-buffered, must still come out, for a success and for a refusal."""
    ok = subprocess.run(
        [sys.executable, "-m", "jaxcal", "inspect", str(DATASET)], capture_output=True, text=True, timeout=300
    )
    assert ok.returncode == 0, ok.stderr
    assert ok.stdout.startswith(f"{DATASET}: robot.urdf") and "camera cam0: 800x600, 144 frames" in ok.stdout
    assert "encoder log: 7201 samples" in ok.stdout
    bad = subprocess.run(
        [sys.executable, "-m", "jaxcal", "calibrate", str(tmp_path / "none"), "--out", str(tmp_path / "out")],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert bad.returncode == 2
    assert bad.stderr.strip() == f"jaxcal: error: {tmp_path / 'none'}: dataset directory not found"
    assert not (tmp_path / "out").exists()


def test_a_warm_tracker_calibration_and_its_checks_lower_no_program_of_their_own(tmp_path, monkeypatch):
    """The host code moves arrays with `to_device` and reads solver codes with `result_is`
    (`jaxcal._device`): a warm calibration, its outputs, `verify`, `certify` and `check` then
    lower nothing beside their stored programs (a fresh process's first lowering loads JAX's
    lowering machinery: most of the time a warm `jaxcal verify` has left)."""
    from jax._src import pjit

    import jaxcal
    from jaxcal.certification import certify
    from jaxcal.drift import check
    from jaxcal.verification import verify

    tracker = ROOT / "data" / "ur5_tracker"
    box = np.radians([[-30, 60], [-100, -30], [30, 140], [-120, 30], [50, 145], [-30, 20]])

    def run(out):
        result = jaxcal.calibrate(tracker / "grid", progress=False, device_is_base=True)
        jaxcal.write_outputs(result, out)
        figures = (
            verify(out, tracker / "test").summary["calibrated_mm"]["mean"],
            certify(out, joint_box=box, samples=200),
        )
        return result, figures, check(out, tracker / "test")

    first = run(tmp_path / "first")  # the stored programs, warm
    jax.clear_caches()  # every eager program as in a fresh process
    lowered, real = [], pjit._pjit_call_impl_python

    def counted(*args, **kwargs):
        lowered.append(kwargs.get("name"))
        return real(*args, **kwargs)

    monkeypatch.setattr(pjit, "_pjit_call_impl_python", counted)
    again = run(tmp_path / "again")
    assert lowered == []
    assert again[0].status == first[0].status == "ok"
    assert [m.cv_mean_mm for m in again[0].point_fit.models] == [
        m.cv_mean_mm for m in first[0].point_fit.models
    ]
    assert again[1][0] == first[1][0] and again[1][1].summary.mean_mm == first[1][1].summary.mean_mm
    assert again[2].statistic == first[2].statistic
