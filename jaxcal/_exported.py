"""Traced programs kept on disk beside the compile cache, so that a second process
reloads them instead of tracing them again.

JAX's persistent cache (`jaxcal._cache`) keeps compiled executables, but it finds
one by hashing the lowered program: every process still traces and lowers each
solver before it can look the executable up, and for jaxcal's big stage programs
that costs far more than running them. `stored_jit(fun, name, static)` is a
`jax.jit` whose traced program is a `jax.export.Exported`, serialised once per
argument shapes (the size buckets of `jaxcal._buckets` keep those few) into
`<compile cache>/jaxcal-programs/`. A later process deserialises it and calls it
through `jax.jit(exported.call)`, whose lowering is a copy of the stored module
and whose executable comes from the persistent cache. A process with no entry
exports the program first and calls it the same way, so the numbers do not depend
on whether the program was reloaded.

An entry is used only when everything that decides the program matches: the
program's name and static configuration, the argument tree and avals, jaxcal's
version and a digest of its source files, the versions of JAX, jaxlib and the
libraries that trace into it (equinox, optimistix, lineax, NumPy), `XLA_FLAGS`,
the x64 flag and the backend. Each file carries that key and a SHA-256 of its
payload, checked before anything is deserialised; an entry that is stale,
truncated, corrupted or written for another key is ignored and rebuilt (written
atomically). The entries, like the compile cache's executables, are trusted
only as far as the user's own cache directory is.

Beside each entry, the executable XLA compiled from it is kept too (`<entry>.<host>.xla`,
with `jax.experimental.serialize_executable`): a later process loads it directly,
without lowering the entry or hashing it for the persistent cache, which on a
program of tens of thousands of instructions saves about as much as XLA's own
load. It is named after the entry and a digest of the host's CPU (the machine code
is the host's), carries a SHA-256 of its payload checked before XLA sees a byte,
and is used only on a single-device backend; anything else falls back to lowering
and the persistent cache. An executable kept here is not also written to the
persistent cache (it would be serialised twice), so a missing or damaged one is
compiled again. It is byte for byte the executable the entry compiles to, so the
numbers do not depend on it either.

Every program and executable read is stamped as used (its modification time); the
folder keeps to `BUDGET_BYTES`, the least recently used files going first, since
each jaxcal version (each edit of its sources) writes programs of its own.

A run's programs are called one after another, and each first call waits for
its entry and its executable to be read (XLA's part without Python's lock).
`warm_start(tag)` reads ahead, on background threads, the entries the last run
with the same tag called, in the order it called them, while the run does its
other work; a call takes an entry read ahead only when its own key is the
file's (and its compiler options the same), so the results never depend on it.

Without a cache directory (`JAXCAL_NO_CACHE=1`) nothing is written and every
process exports its programs in memory.
"""

import contextlib
import functools
import hashlib
import importlib.metadata
import json
import os
import pickle
import platform
import re
import tempfile
import threading
import weakref
import zlib
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import jax
import numpy as np

from ._cache import QUICK_COMPILE

#: Folder (inside JAX's compile-cache directory) of the stored programs.
FOLDER = "jaxcal-programs"
#: First bytes of an entry; a new layout gets a new magic.
MAGIC = b"JAXCAL-EXPORTED-1\n"
#: First bytes of a compiled executable beside an entry.
XLA_MAGIC = b"JAXCAL-XLA-2\n"
#: Most bytes the stored programs and executables may take; past it the least recently used
#: files go (a stored program costs only its trace and compile when it is needed again).
BUDGET_BYTES = 1 << 30
#: Libraries whose code is traced into the programs.
_TRACED_LIBRARIES = ("jax", "jaxlib", "equinox", "optimistix", "lineax", "numpy")
#: Custom calls bound to this process's Python objects: a program holding one is never stored.
_PROCESS_BOUND = re.compile(rb"callback", re.IGNORECASE)


@functools.cache
def _source_digest() -> str:
    """SHA-256 of jaxcal's Python sources: a program traced from other code is another program."""
    root = Path(__file__).resolve().parent
    h = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        h.update(str(path.relative_to(root)).encode() + b"\0" + path.read_bytes() + b"\0")
    return h.hexdigest()


def _version(name: str) -> str:
    try:
        return importlib.metadata.version(name)
    except importlib.metadata.PackageNotFoundError:
        return "none"


@functools.cache
def _environment() -> dict:
    return {
        "jaxcal": _version("jaxcal"),
        "jaxcal_source": _source_digest(),
        **{lib: _version(lib) for lib in _TRACED_LIBRARIES},
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
    }


def _environment_now() -> dict:
    return {**_environment(), "x64": bool(jax.config.jax_enable_x64), "backend": jax.default_backend()}


def programs_dir() -> Path | None:
    """Where stored programs go: beside JAX's compile cache, or `None` when it is off."""
    cache = jax.config.jax_compilation_cache_dir
    return Path(cache) / FOLDER if cache else None


def _aval(x) -> tuple:
    """`(shape, dtype)` of an array, a `jax.ShapeDtypeStruct` or an aval."""
    a = x if isinstance(x, (jax.ShapeDtypeStruct, jax.core.ShapedArray)) else jax.typeof(x)
    return tuple(int(d) for d in a.shape), a.dtype


def _strong(x):
    """`x` with a strong type: a Python scalar or weakly typed array as a NumPy array of
    its dtype. Programs are keyed and traced on strong types, so that an integer output
    fed back in (weak in JAX) finds the same program."""
    if isinstance(x, jax.ShapeDtypeStruct):
        return jax.ShapeDtypeStruct(x.shape, x.dtype)
    a = jax.typeof(x)
    return np.asarray(x, a.dtype) if getattr(a, "weak_type", False) else x


def _flatten(args, kwargs):
    leaves, in_tree = jax.tree.flatten((args, kwargs))
    leaves = [_strong(x) for x in leaves]
    return leaves, in_tree, [_aval(x) for x in leaves]


class _Entry:
    """One program for one argument tree and shapes: the exported module, the jitted call and
    the output tree."""

    def __init__(self, name: str, exported, out_tree, compiler_options, file: str | None = None):
        self.name = name
        self.exported = exported
        self.out_tree = out_tree
        self.compiler_options = compiler_options
        self.file = file  # the entry's file name in `programs_dir()`, when stored

        def call(*leaves):
            return exported.call(*leaves)

        # What JAX's logs and events name it; a stored entry's program is named after its file
        # too, so that its first compile is XLA's own and not a copy from JAX's persistent cache
        # (an executable read from there serialises incompletely: `_write_executable`).
        call.__name__ = call.__qualname__ = name if file is None else f"{name}_{file.rsplit('-', 1)[-1][:8]}"
        self.jitted = jax.jit(call, compiler_options=compiler_options)
        self._compiled = None
        self._runtime_ready = False
        self._lock = threading.Lock()

    def compiled(self):
        """The executable, once: the one stored beside the entry, else lowered and compiled (or
        read from JAX's persistent cache) and then stored beside it."""
        with self._lock:
            if self._compiled is None:
                path = _executable_path(self.file)
                self._compiled = _read_executable(path, self.exported)
                self._runtime_ready = self._compiled is None  # lowering readies the runtime
                if self._compiled is None:
                    specs = [jax.ShapeDtypeStruct(a.shape, a.dtype) for a in self.exported.in_avals]
                    _CACHE_HIT.hit = False
                    with _kept_here(path):
                        self._compiled = self.jitted.lower(*specs).compile()
                    if not _CACHE_HIT.hit:
                        _write_executable(path, self._compiled)
            return self._compiled

    def runnable(self):
        """The executable, with the runtime ready to run it: what lowering the entry would have
        done first (`_ready_runtime`) is done before an executable read from disk first runs."""
        compiled = self.compiled()
        if not self._runtime_ready:
            _ready_runtime(self.exported)
            self._runtime_ready = True
        return compiled

    def out_info(self):
        specs = [jax.ShapeDtypeStruct(a.shape, a.dtype) for a in self.exported.out_avals]
        return jax.tree.unflatten(self.out_tree, specs)


class StoredProgram:
    """A `jax.jit` of `fun` whose traced programs persist across processes (module docstring).

    Every argument leaf is traced (as `jax.jit` without static arguments); what
    else decides the program (closure values, the function's configuration) must
    be in `static`, which names the entry with `name`. `compiler_options`: XLA's,
    as `jax.jit`'s (default `QUICK_COMPILE`; `None` for XLA's defaults).
    """

    def __init__(self, fun, name: str, static=(), compiler_options=QUICK_COMPILE):
        self.fun = fun
        self.name = name
        self.static = repr(static)
        self.compiler_options = None if compiler_options is None else dict(compiler_options)
        self._entries: dict = {}
        self._lock = threading.Lock()
        functools.update_wrapper(self, fun)
        _register_with_jax(self)
        _PROGRAMS.add(self)

    def held_files(self) -> set[str]:
        """The stored entries (file names) this process holds in memory."""
        with self._lock:
            return {e.file for e in self._entries.values() if e.file is not None}

    def __call__(self, *args, **kwargs):
        leaves, in_tree, avals = _flatten(args, kwargs)
        entry = self._entry(in_tree, avals)
        return jax.tree.unflatten(entry.out_tree, entry.runnable()(*leaves))

    def out_info(self, *args, **kwargs):
        """The output's shapes and dtypes (a pytree of `jax.ShapeDtypeStruct`), without running it."""
        _, in_tree, avals = _flatten(args, kwargs)
        return self._entry(in_tree, avals).out_info()

    def compile(self, *args, **kwargs) -> None:
        """Load or export, lower and compile the program for these arguments (arrays or
        `jax.ShapeDtypeStruct`s), so that a call with such arguments finds it compiled."""
        _, in_tree, avals = _flatten(args, kwargs)
        self._entry(in_tree, avals).compiled()

    def cache_size(self) -> int:
        """How many programs (argument trees and shapes) this process holds."""
        return len(self._entries)

    def cache_clear(self) -> None:
        """Drop this process's executables (`jax.clear_caches()` calls it); the stored
        programs stay on disk and are read again when next called."""
        with self._lock:
            self._entries.clear()

    def cache_info(self) -> str:
        return f"{self.name}: {len(self._entries)} programs"

    def cache_keys(self) -> list:
        return list(self._entries)

    # ------------------------------------------------------------------ entries

    def _key(self, in_tree, avals) -> dict:
        return {
            "name": self.name,
            "static": self.static,
            "in_tree": str(in_tree),
            "avals": [[list(s), str(d)] for s, d in avals],
            "compiler_options": sorted((k, str(v)) for k, v in (self.compiler_options or {}).items()),
            **_environment_now(),
        }

    def _entry(self, in_tree, avals) -> _Entry:
        memo = (in_tree, tuple(avals))
        with self._lock:
            entry = self._entries.get(memo)
            if entry is None:
                entry = self._entries[memo] = self._load_or_export(in_tree, avals)
        if _RECORDING and entry.file is not None:
            for used in _RECORDING:
                used.setdefault(entry.file, entry)
        return entry

    def _load_or_export(self, in_tree, avals) -> _Entry:
        key = self._key(in_tree, avals)
        text = json.dumps(key, sort_keys=True).encode()
        folder = programs_dir()
        path = None
        if folder is not None:
            path = folder / f"{self.name}-{hashlib.sha256(text).hexdigest()[:40]}.jaxexport"
            entry = _take_ahead(path.name, text, self) or _read(path, self, text, avals)
            if entry is not None:
                return entry
        exported, out_tree = self._export(in_tree, avals)
        if path is not None:
            _write(path, text, exported, out_tree)
        return _Entry(self.name, exported, out_tree, self.compiler_options, path and path.name)

    def _export(self, in_tree, avals):
        out_trees = []

        def flat(*leaves):
            args, kwargs = jax.tree.unflatten(in_tree, leaves)
            out, tree = jax.tree.flatten(self.fun(*args, **kwargs))
            out_trees.append(tree)
            return out

        flat.__name__ = self.name
        specs = [jax.ShapeDtypeStruct(s, d) for s, d in avals]
        # Entries are keyed by the exact jaxlib, so its own (unstable) custom calls are safe.
        exported = jax.export.export(
            jax.jit(flat), disabled_checks=[jax.export.DisabledSafetyCheck.custom_call("ALL")]
        )(*specs)
        return exported, out_trees[-1]


def _register_with_jax(program: StoredProgram) -> None:
    """Let `jax.clear_caches()` drop `program`'s executables, as it drops `jax.jit`'s
    (JAX's registry is private: without it they live as long as the program)."""
    try:
        from jax._src import util

        util.register_cache(program, f"jaxcal stored program {program.name}")
    except (ImportError, AttributeError):
        pass


def stored_jit(fun, name: str, static=(), compiler_options=QUICK_COMPILE) -> StoredProgram:
    """`StoredProgram(fun, name, static, compiler_options)`: by default
    `jaxcal._cache.quick_jit(fun)`, whose traced programs are stored beside the
    compile cache (module docstring)."""
    return StoredProgram(fun, name, static, compiler_options)


# ---------------------------------------------------------------------- files


def _read_file(path: Path, key: bytes | None = None):
    """`(key, exported, out_tree)` of the entry at `path` if it is whole (and written for
    `key` when given), else `None`."""
    blob = _read_used(path)
    if blob is None:
        return None
    try:
        if not blob.startswith(MAGIC):
            return None
        body = blob[len(MAGIC) :]
        head_len = int.from_bytes(body[:8], "little")
        head = json.loads(body[8 : 8 + head_len])
        payload = body[8 + head_len :]
        if key is not None and head.get("key") != key.decode():
            return None
        if head.get("sha256") != hashlib.sha256(payload).hexdigest():
            return None
        tree_len = int(head["tree_bytes"])
        out_tree = jax.tree.structure(pickle.loads(payload[:tree_len]))
        exported = jax.export.deserialize(bytearray(payload[tree_len:]))
        if len(exported.out_avals) != out_tree.num_leaves:
            return None
        return head["key"], exported, out_tree
    except Exception:  # noqa: BLE001 - any damage means: rebuild it
        return None


def _read_used(path: Path) -> bytes | None:
    """The bytes at `path` (None if unreadable); its modification time becomes now, the
    last use `_keep_within_budget` goes by."""
    try:
        blob = path.read_bytes()
    except OSError:
        return None
    with contextlib.suppress(OSError):
        os.utime(path)
    return blob


def _keep_within_budget(folder: Path, budget: int | None = None) -> None:
    """Remove the least recently used files of `folder` until it holds at most `budget`
    bytes (default `BUDGET_BYTES`), down to three quarters of it. Files another process
    removes first, or holds open, only cost that process a rebuild."""
    budget = BUDGET_BYTES if budget is None else budget
    files = []
    try:
        with os.scandir(folder) as entries:  # closed however the listing ends
            for e in entries:
                try:
                    if e.is_file():
                        st = e.stat()
                        files.append((st.st_mtime, st.st_size, Path(e.path)))
                except OSError:  # removed by another process since the listing: not ours to count
                    continue
    except OSError:
        return
    total = sum(size for _, size, _ in files)
    if total <= budget:
        return
    for _, size, path in sorted(files, key=lambda f: f[0]):
        if total <= 0.75 * budget:
            break
        with contextlib.suppress(OSError):
            path.unlink()
            total -= size


def _write_atomic(path: Path, data: bytes) -> None:
    """Write `data` to `path` through a temporary file beside it: a reader sees the old file or
    the new one, never part of one."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name, suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _read(path: Path, program: StoredProgram, key: bytes, avals) -> _Entry | None:
    """The entry at `path` if it is whole and written for exactly `key`, else `None`."""
    found = _read_file(path, key)
    if found is None or [_aval(a) for a in found[1].in_avals] != list(avals):
        return None
    return _Entry(program.name, found[1], found[2], program.compiler_options, path.name)


def _write(path: Path, key: bytes, exported, out_tree) -> None:
    """Store an entry atomically; a program that cannot be stored is simply not stored."""
    try:
        if _PROCESS_BOUND.search(exported.mlir_module_serialized):
            return
        skeleton = pickle.dumps(jax.tree.unflatten(out_tree, list(range(out_tree.num_leaves))))
        if jax.tree.structure(pickle.loads(skeleton)) != out_tree:
            return
        payload = skeleton + bytes(exported.serialize())
        head = json.dumps(
            {"key": key.decode(), "sha256": hashlib.sha256(payload).hexdigest(), "tree_bytes": len(skeleton)}
        ).encode()
        path.parent.mkdir(parents=True, exist_ok=True)
        _write_atomic(path, MAGIC + len(head).to_bytes(8, "little") + head + payload)
        _keep_within_budget(path.parent)
    except Exception:  # noqa: BLE001 - a read-only or full cache only costs the next process a trace
        return


#: Whether this thread's last compile was read from JAX's persistent cache. XLA serialises
#: such an executable without some of its functions (jaxlib 0.10: "Function ... not found"
#: when it runs after loading), so only an executable XLA compiled is kept.
_CACHE_HIT = threading.local()


def _note_cache_hit(event: str, **_) -> None:
    if event == "/jax/compilation_cache/cache_hits":
        _CACHE_HIT.hit = True


jax.monitoring.register_event_listener(_note_cache_hit)


@functools.cache
def _host_digest() -> str:
    """A digest of the host's CPU model and features: a stored executable is machine code for it."""
    h = hashlib.sha256(f"{platform.machine()}|{platform.processor()}".encode())
    try:
        with open("/proc/cpuinfo", "rb") as f:
            for line in f:
                if line.split(b":")[0].strip() in (b"model name", b"flags", b"Features", b"CPU part"):
                    h.update(line)
                elif not line.strip():  # the first processor's block is enough
                    break
    except OSError:
        pass
    return h.hexdigest()[:16]


def _executable_path(file: str | None) -> Path | None:
    """Where the executable of the entry `file` is kept on this host (None: not stored, or a
    backend of several devices, whose executables name their devices)."""
    folder = programs_dir()
    if file is None or folder is None or jax.device_count() != 1:
        return None
    return folder / f"{file.removesuffix('.jaxexport')}.{_host_digest()}.xla"


def _kept_here(path: Path | None):
    """While compiling an executable that is kept at `path`: JAX's persistent cache is read but
    not written, so the executable is not serialised and compressed a second time for a copy
    that only a process without `path` would read (a cold `jaxcal calibrate` writes each of
    its big programs once). Without `path` (no cache, several devices) the cache writes as
    usual."""
    if path is None:
        return contextlib.nullcontext()
    from jax._src import config

    return config.persistent_cache_min_compile_time_secs(float("inf"))


def _read_executable(path: Path | None, exported):
    """The executable at `path` if it is whole and takes `exported`'s arguments, else `None`."""
    if path is None:
        return None
    blob = _read_used(path)
    if blob is None:
        return None
    try:
        if not blob.startswith(XLA_MAGIC):
            return None
        digest, payload = blob[len(XLA_MAGIC) : len(XLA_MAGIC) + 64], blob[len(XLA_MAGIC) + 64 :]
        if digest.decode() != hashlib.sha256(payload).hexdigest():
            return None
        serialized, in_tree, out_tree = pickle.loads(zlib.decompress(payload))
        from jax._src.export._export import _ensure_backends_initialized  # noqa: F401 - `_ready_runtime` needs it
        from jax.experimental import serialize_executable

        compiled = serialize_executable.deserialize_and_load(serialized, in_tree, out_tree)
        args = jax.tree.leaves(compiled.args_info)
        if [(tuple(a.shape), a.dtype) for a in args] != [_aval(a) for a in exported.in_avals]:
            return None
        return compiled
    except Exception:  # noqa: BLE001 - any damage means: compile it again
        return None


def _ready_runtime(exported) -> None:
    """Set up the runtime's kernels that are set up lazily, as lowering `exported` would: on the
    CPU, jaxlib's LAPACK, whose functions are null until then (the first call would jump to
    address 0). A CPU program that calls no LAPACK skips it (it imports SciPy's LAPACK
    wrappers, a third of a second); done where the program first runs, so that a read ahead
    does not wait for it."""
    platforms = tuple(exported.platforms)
    if platforms != ("cpu",) or b"lapack" in exported.mlir_module_serialized:
        from jax._src.export import _export

        _export._ensure_backends_initialized(platforms)


def _write_executable(path: Path | None, compiled) -> None:
    """Keep `compiled` at `path`, atomically; an executable that cannot be kept is not."""
    if path is None:
        return
    try:
        from jax.experimental import serialize_executable

        # zlib at its fastest: a seventh of the size, 20 ms for a 5 MB executable, 7 ms back.
        payload = zlib.compress(pickle.dumps(serialize_executable.serialize(compiled)), 1)
        _write_atomic(path, XLA_MAGIC + hashlib.sha256(payload).hexdigest().encode() + payload)
        _keep_within_budget(path.parent)
    except Exception:  # noqa: BLE001 - a read-only or full cache, or an executable XLA cannot serialise
        return


# ---------------------------------------------------------------------- reading ahead

#: Threads that read entries ahead. XLA reads an executable without Python's lock, but a
#: second thread bought nothing measurable on two cores (warm `jaxcal calibrate
#: data/ur5e_sweeps`, alternating runs: docs/performance.md), so one keeps it simple.
AHEAD_THREADS = 1
#: Every stored program of this process: `warm_start` does not read ahead an entry one of them
#: holds already (a second calibration in one process would load its executables again, only
#: for them to be dropped).
_PROGRAMS: "weakref.WeakSet[StoredProgram]" = weakref.WeakSet()
#: Entries read ahead by `warm_start`, by file name: futures of `(key, _Entry)` or `None`.
_AHEAD: dict[str, Future] = {}
_AHEAD_LOCK = threading.Lock()
#: The entries each running `warm_start` has seen called, by file name, in call order.
_RECORDING: list[dict] = []


def _take_ahead(file: str, key: bytes, program: StoredProgram) -> _Entry | None:
    """The entry `file` read ahead, if it was written for exactly `key` and is compiled with
    `program`'s options; `None` (read it here) when it was not read ahead or not yet begun."""
    with _AHEAD_LOCK:
        future = _AHEAD.pop(file, None)
    if future is None or future.cancel():
        return None
    try:
        found = future.result()
    except Exception:  # noqa: BLE001 - read it again on this thread
        return None
    if found is None or found[0] != key.decode() or found[1].compiler_options != program.compiler_options:
        return None
    return found[1]


def _read_ahead(path: Path, name: str, compiler_options) -> tuple[str, _Entry] | None:
    found = _read_file(path)
    if found is None:
        return None
    entry = _Entry(name, found[1], found[2], compiler_options, path.name)
    entry.compiled()
    return found[0], entry


def _manifest(folder: Path, tag: str) -> Path:
    text = json.dumps([tag, _environment_now()], sort_keys=True).encode()
    return folder / f"run-{hashlib.sha256(text).hexdigest()[:40]}.json"


@contextlib.contextmanager
def warm_start(tag: str):
    """Within the block, read ahead the entries the last block with this `tag` called (on
    `AHEAD_THREADS` background threads, in the order they were called); when the block ends
    without an error, record the entries it called for the next (module docstring)."""
    folder = programs_dir()
    if folder is None:
        yield
        return
    manifest = _manifest(folder, tag)
    try:
        before = json.loads(manifest.read_text())
        files = [(str(e["program"]), str(e["file"]), e["compiler_options"]) for e in before]
    except (OSError, ValueError, KeyError, TypeError, RecursionError):  # damaged: the next run rewrites it
        before, files = None, []
    used: dict = {}
    pool = ThreadPoolExecutor(AHEAD_THREADS, thread_name_prefix="jaxcal programs ahead")
    mine = []
    held = set().union(*(p.held_files() for p in list(_PROGRAMS)))
    with _AHEAD_LOCK:
        for name, file, options in files:
            if file not in _AHEAD and file not in held and "/" not in file and os.sep not in file:
                _AHEAD[file] = pool.submit(_read_ahead, folder / file, name, options)
                mine.append(file)
    _RECORDING.append(used)
    try:
        yield
    finally:
        _RECORDING[:] = [u for u in _RECORDING if u is not used]  # by identity: nested runs record alike
        with _AHEAD_LOCK:
            for file in mine:
                future = _AHEAD.pop(file, None)
                if future is not None:
                    future.cancel()
        pool.shutdown(wait=False, cancel_futures=True)
    after = [
        {"program": e.name, "file": file, "compiler_options": e.compiler_options} for file, e in used.items()
    ]
    if after and after != before:
        _write_manifest(manifest, after)


def _write_manifest(path: Path, entries: list) -> None:
    try:
        _write_atomic(path, json.dumps(entries).encode())
    except OSError:  # a read-only cache only costs the next run its head start
        return
