"""Across processes and hosts: JAX's distributed runtime, joined where the environment asks for
it, and the one thing jaxcal's batch work needs from it beyond JAX's own sharding: its processes.

A Monte Carlo study needs nothing more than the runtime: `jaxcal.monte_carlo` lays its trials
along a mesh of every device of every process (`jaxcal._montecarlo.map_over_devices`), and every
process holds the gathered results. A fleet's calibration shares out its units
(`Processes.share`) and gathers what each process found (`Processes.gather`) so that the first
writes the fleet's summary (`jaxcal.fleet.calibrate_fleet`).

**Starting it.** The same command on every process, with

- `JAX_COORDINATOR_ADDRESS=host:port` (process 0's host and a free port), `JAX_NUM_PROCESSES=N`
  and `JAX_PROCESS_ID=i` (0 to N-1) in each process's environment; or
- under SLURM's `srun` with more than one task (`SLURM_STEP_NUM_TASKS`), nothing: JAX reads the
  job's variables.

`jaxcal montecarlo` and a fleet's `jaxcal calibrate` join the runtime themselves (`join`); a
script calls `join()` before anything else touches JAX. Every process reads the same inputs; a
fleet's output folder must be on a file system every process sees (a cluster's shared one). This
module imports no JAX until asked to join (the command line's parser reads `requested`).
"""

import contextlib
import os
import signal
import socket
import subprocess
import sys
import threading
import time

from . import _interrupt
from ._processes import ONE, PeerError, Processes, current

__all__ = ["ONE", "PeerError", "Processes", "current", "free_port", "join", "leave", "requested", "run_local"]

#: The variables of an explicit start (JAX reads the first itself).
ADDRESS, PROCESSES, PROCESS_ID = "JAX_COORDINATOR_ADDRESS", "JAX_NUM_PROCESSES", "JAX_PROCESS_ID"
#: Set by SLURM's `srun` for each task of a job step: its task count.
SLURM_TASKS = "SLURM_STEP_NUM_TASKS"


def _int(name: str, low: int) -> int:
    raw = os.environ[name]
    try:
        value = int(raw)
    except ValueError:
        raise ValueError(f"environment variable {name}: not a whole number ({raw!r})") from None
    if value < low:
        raise ValueError(f"environment variable {name}: at least {low}, got {value}")
    return value


def requested() -> int:
    """How many processes the environment asks for (1: no distributed run). **Raises**
    ValueError naming the variable that is missing or malformed."""
    explicit = [name for name in (ADDRESS, PROCESSES, PROCESS_ID) if os.environ.get(name, "").strip()]
    if PROCESSES in explicit or PROCESS_ID in explicit:
        missing = sorted({ADDRESS, PROCESSES, PROCESS_ID} - set(explicit))
        if missing:
            raise ValueError(
                f"a distributed run needs {ADDRESS}, {PROCESSES} and {PROCESS_ID} in the environment; "
                f"{', '.join(missing)} missing"
            )
        count, index = _int(PROCESSES, 1), _int(PROCESS_ID, 0)
        if index >= count:
            raise ValueError(f"environment variable {PROCESS_ID}: from 0 to {count - 1}, got {index}")
        return count
    if os.environ.get(SLURM_TASKS, "").strip():
        return _int(SLURM_TASKS, 1)
    return 1


#: How long a process waits for the others to join (s): a process that was never started is
#: reported then, with what this one was told.
JOIN_TIMEOUT_S = 120


def join(say=None) -> Processes:
    """Join JAX's distributed runtime if the environment asks for it (`requested`; once per
    process, before anything else touches JAX) and return this process's place. `say`: where to
    tell that it is joining (a line; default stderr). SIGTERM (a scheduler's cancel, `timeout`)
    then ends the process as Ctrl-C does, not JAX's preemption notice, which would ignore it."""
    count = requested()
    if count == 1:
        return ONE
    import jax

    if not jax.distributed.is_initialized():
        explicit = bool(os.environ.get(PROCESSES, "").strip())
        where = (
            f"process {_int(PROCESS_ID, 0)} of {count} at {os.environ.get(ADDRESS)}"
            if explicit
            else f"{count} SLURM tasks"
        )
        (say or (lambda text: print(text, file=sys.stderr, flush=True)))(
            f"joining a distributed run: {where} ..."
        )
        try:
            if explicit:
                jax.distributed.initialize(
                    num_processes=count, process_id=_int(PROCESS_ID, 0), initialization_timeout=JOIN_TIMEOUT_S
                )
            else:  # SLURM: the job's variables
                jax.distributed.initialize(initialization_timeout=JOIN_TIMEOUT_S)
        except Exception as e:  # noqa: BLE001 - the runtime's errors name no variable
            raise ValueError(
                f"could not join a distributed run ({where}) within {JOIN_TIMEOUT_S} s: every process must "
                f"start, with {PROCESS_ID} 0 to {count - 1} each once and one {ADDRESS} that process 0's "
                f"host can open ({type(e).__name__}: {str(e).splitlines()[0][:200]})"
            ) from None
        _interrupt.also_on(signal.SIGTERM)
    return Processes(jax.process_index(), jax.process_count())


def leave() -> None:
    """Leave the distributed run this process joined, once every process leaves (JAX's shutdown
    barrier): process 0 holds the runtime, and a process still in it when process 0 is gone is
    ended by JAX. Python's exit does it too; the command line, which ends its process at once
    (`jaxcal.cli.run`), calls it."""
    jax = sys.modules.get("jax")
    if jax is not None and jax.distributed.is_initialized():
        jax.distributed.shutdown()


def free_port() -> int:
    """A TCP port free on this host now (for a coordinator on it)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run_local(
    argv: list[str],
    processes: int,
    *,
    env: dict | None = None,
    timeout: float | None = None,
    capture: bool = False,
) -> list[subprocess.CompletedProcess]:
    """Start `argv` as `processes` processes of one distributed run on this host (a coordinator on
    a free local port; `env`: their environment, default this one's) and wait for them all, at
    most `timeout` seconds in all (then `subprocess.TimeoutExpired`, the processes interrupted, or
    killed): the way to try a distributed command on one machine. `capture`: keep their output
    (text), else it is this process's. **Returns:** their `CompletedProcess`es, in process order."""
    base = dict(os.environ if env is None else env)
    base[ADDRESS] = f"127.0.0.1:{free_port()}"
    pipe = {"stdout": subprocess.PIPE, "stderr": subprocess.PIPE, "text": True} if capture else {}
    with _ctrl_c_passed_on():
        running = [
            subprocess.Popen(argv, env=base | {PROCESSES: str(processes), PROCESS_ID: str(i)}, **pipe)
            for i in range(processes)
        ]
    deadline = None if timeout is None else time.monotonic() + timeout
    done = []
    try:
        for p in running:
            left = None if deadline is None else max(deadline - time.monotonic(), 0.0)
            out, err = p.communicate(timeout=left)
            done.append(subprocess.CompletedProcess(argv, p.returncode, out, err))
    finally:
        _end(running)
    return done


@contextlib.contextmanager
def _ctrl_c_passed_on():
    """While processes start: SIGINT handled here, where this process ignores it (a shell's background
    job, a test runner's worker). An ignored signal is inherited across `exec`, a handled one is reset
    to its default: the started processes then take `_end`'s Ctrl-C (Python installs no
    `KeyboardInterrupt` where SIGINT starts ignored), instead of being killed `STOP_S` later. (A
    `preexec_fn` would do it in the child, but forks a multithreaded process the slow, unsafe way.)"""
    ignoring = threading.current_thread() is threading.main_thread() and signal.getsignal(signal.SIGINT) in (
        signal.SIG_IGN,
    )
    if ignoring:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        yield
    finally:
        if ignoring:
            signal.signal(signal.SIGINT, signal.SIG_IGN)


def _end(running: list) -> None:
    """End what still runs: Ctrl-C first (jaxcal leaves nothing behind then), then, for what has
    not ended `STOP_S` seconds later (all of them together), a kill."""
    for p in running:
        if p.poll() is None:
            p.send_signal(signal.SIGINT)
    deadline = time.monotonic() + STOP_S
    for p in running:
        try:
            p.communicate(timeout=max(deadline - time.monotonic(), 0.0))
        except subprocess.TimeoutExpired:
            p.kill()
            p.communicate()


#: How long `run_local` gives an interrupted process to stop before it kills it (s).
STOP_S = 10
