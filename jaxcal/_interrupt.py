"""Ctrl-C on the command line: a command stops within `STOP_S` seconds of SIGINT and leaves
nothing behind (no partial output, no lock file, no temporary file, no child process).

Python's own handling, a `KeyboardInterrupt` raised in the main thread at its next bytecode,
is not enough on its own:

- JAX runs a callback at every garbage collection (`gc.callbacks`), and an exception raised
  in one is printed as "Exception ignored" and dropped: a SIGINT that landed there was lost,
  and the run went on to write its outputs and exit 0 (one try in six, 25 s into `jaxcal
  calibrate`);
- the main thread may be inside XLA (a compile of seconds), where no Python handler runs;
- after a `KeyboardInterrupt`, Python's exit joins the threads that read programs ahead and
  compile (seconds more).

`install()`, which only the `jaxcal` command calls (a script or a notebook keeps Python's own
handling), therefore

1. raises `KeyboardInterrupt` on SIGINT, except inside a garbage-collection callback, where the
   signal is raised again a moment later (by the watcher below) instead of being lost;
2. records that SIGINT came: an output about to be renamed into place (`jaxcal.io._files`)
   calls `checkpoint()` under `committing()`, which raises `KeyboardInterrupt` from then on,
   so an interrupt that was swallowed anyway never lets an output appear;
3. wakes a watcher thread at once (`signal.set_wakeup_fd`, written by the C-level handler
   whatever the main thread is doing): if the process still runs `STOP_S` seconds after the
   signal, the watcher waits for a rename in progress (`committing()`), runs the clean-ups
   registered for what is being written (`partial`: temporary directories and files, lock
   files, detection worker processes), newest first, and ends the process (exit 130).

Everything a command writes is written through `jaxcal.io._files` (temporary directories and
files renamed into place, the lock beside an output), whose helpers register their clean-ups
here; without `install()` the registry is kept but never run, and `checkpoint()` never raises.
"""

import contextlib
import gc
import itertools
import os
import signal
import sys
import threading
import time

#: Seconds after SIGINT by which the process has ended (the watcher's deadline; the clean
#: exit through `KeyboardInterrupt` is usually faster).
STOP_S = 1.5
#: The exit code of an interrupted command (128 + SIGINT, as a shell reports it).
EXIT_CODE = 130

_cleanups: dict[int, object] = {}  # token -> callable, in registration order
_tokens = itertools.count()
_registry = threading.Lock()
_commit = threading.RLock()  # held while an output is renamed into place
_signalled = threading.Event()  # SIGINT came (only once `install()` ran)
_retry = threading.Event()  # the handler ran inside a garbage-collection callback: raise it again
_installed = False


def interrupted() -> bool:
    """Whether SIGINT came since `install()`."""
    return _signalled.is_set()


def checkpoint() -> None:
    """Raise `KeyboardInterrupt` if SIGINT came (`install()`): called before an output is
    renamed into place, so that an interrupt swallowed on the way never commits one."""
    if _signalled.is_set():
        raise KeyboardInterrupt


@contextlib.contextmanager
def committing():
    """Hold the commit lock for a rename into place (the watcher does not clean up halfway
    through one), after `checkpoint()`."""
    with _commit:
        checkpoint()
        yield


@contextlib.contextmanager
def partial(cleanup):
    """Within the block, `cleanup()` (which must not raise, and must be quick) removes what the
    block is writing if the watcher ends the process; the block's own error handling does the
    same on the ordinary path."""
    token = next(_tokens)
    with _registry:
        _cleanups[token] = cleanup
    try:
        yield
    finally:
        with _registry:
            _cleanups.pop(token, None)


def _in_gc_callback(frame) -> bool:
    codes = {getattr(cb, "__code__", None) for cb in gc.callbacks}
    while frame is not None:
        if frame.f_code in codes:
            return True
        frame = frame.f_back
    return False


def _handler(signum, frame) -> None:
    _signalled.set()
    if _in_gc_callback(frame):
        _retry.set()  # an exception raised here would be dropped: the watcher raises SIGINT again
        return
    raise KeyboardInterrupt


def _clean_up() -> None:
    with _registry:
        todo = list(_cleanups.values())[::-1]
    for cleanup in todo:
        try:
            cleanup()
        except Exception:  # noqa: BLE001 - the next clean-up still runs; the process is ending
            pass


def _watch(fd: int) -> None:
    while True:
        try:
            data = os.read(fd, 512)
        except InterruptedError:
            continue
        except OSError:
            return
        if signal.SIGINT in data:
            break
    _signalled.set()
    deadline = time.monotonic() + STOP_S
    while time.monotonic() < deadline:
        if _retry.is_set():
            _retry.clear()
            signal.raise_signal(signal.SIGINT)
        time.sleep(0.02)
    # Still running: whatever swallowed the interrupt or keeps the main thread, end here.
    _commit.acquire(timeout=0.3)
    _clean_up()
    with contextlib.suppress(OSError):
        os.write(2, b"jaxcal: interrupted\n")
    os._exit(EXIT_CODE)


def install() -> None:
    """Handle SIGINT as the module docstring says (from the main thread, once per process)."""
    global _installed
    if _installed or threading.current_thread() is not threading.main_thread():
        return
    r, w = os.pipe()
    os.set_blocking(w, False)
    signal.set_wakeup_fd(w, warn_on_full_buffer=False)
    signal.signal(signal.SIGINT, _handler)
    threading.Thread(target=_watch, args=(r,), name="jaxcal interrupt watcher", daemon=True).start()
    _installed = True


def also_on(signum: int) -> None:
    """Handle `signum` (SIGTERM) as SIGINT where `install()` ran (the command line), else restore
    its default (the process ends): what a scheduler's cancel expects, whatever a library set."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signum, _handler if _installed else signal.SIG_DFL)


def report() -> int:
    """After an interrupt reached the command's top: say so, and the exit code."""
    print("jaxcal: interrupted; nothing unfinished was kept", file=sys.stderr)
    return EXIT_CODE
