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

import os
import socket
import subprocess

from ._processes import ONE, Processes, current

__all__ = ["ONE", "Processes", "current", "free_port", "join", "requested", "run_local"]

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


def join() -> Processes:
    """Join JAX's distributed runtime if the environment asks for it (`requested`; once per
    process, before anything else touches JAX) and return this process's place."""
    count = requested()
    if count == 1:
        return ONE
    import jax

    if not jax.distributed.is_initialized():
        if os.environ.get(PROCESSES, "").strip():
            jax.distributed.initialize(num_processes=count, process_id=_int(PROCESS_ID, 0))
        else:
            jax.distributed.initialize()  # SLURM: the job's variables
    return Processes(jax.process_index(), jax.process_count())


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
    most `timeout` seconds each (then all are ended and `subprocess.TimeoutExpired` raised): the
    way to try a distributed command on one machine. `capture`: keep their output (text), else it
    is this process's. **Returns:** their `CompletedProcess`es, in process order."""
    base = dict(os.environ if env is None else env)
    base[ADDRESS] = f"127.0.0.1:{free_port()}"
    pipe = {"stdout": subprocess.PIPE, "stderr": subprocess.PIPE, "text": True} if capture else {}
    running = [
        subprocess.Popen(argv, env=base | {PROCESSES: str(processes), PROCESS_ID: str(i)}, **pipe)
        for i in range(processes)
    ]
    done = []
    try:
        for p in running:
            out, err = p.communicate(timeout=timeout)
            done.append(subprocess.CompletedProcess(argv, p.returncode, out, err))
    finally:
        for p in running:
            if p.poll() is None:
                p.kill()
                p.communicate()
    return done
