"""Across processes (`jaxcal.distributed`): the environment that asks for a distributed run, and
two local processes of one run giving what one process gives, for a Monte Carlo study and a
fleet's calibration (issue 52 item 3)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from jaxcal import distributed, fleet
from jaxcal.cli import main
from jaxcal.distributed import ADDRESS, PROCESS_ID, PROCESSES, SLURM_TASKS, Processes, requested, run_local
from jaxcal.errors import OutputError
from jaxcal.fleet import without_timings
from jaxcal.sim.tracker import TrackerSimConfig, simulate_tracker

ROOT = Path(__file__).resolve().parents[1]
# test_fleet.py's tracker capture (its compiled programs serve both files).
KW = dict(robot="ur5e", noise_um=10.0, bad_fraction=0.0, home_deg=None, pose_range_deg=120.0, poses=48)
NAMES = (ADDRESS, PROCESSES, PROCESS_ID, SLURM_TASKS)


@pytest.fixture
def clean_env(monkeypatch):
    for name in NAMES:
        monkeypatch.delenv(name, raising=False)
    return monkeypatch


def test_the_environment_asks_for_a_distributed_run_by_name(clean_env):
    assert requested() == 1
    clean_env.setenv(SLURM_TASKS, "4")  # srun with four tasks
    assert requested() == 4
    clean_env.setenv(PROCESSES, "2")
    with pytest.raises(ValueError, match=f"{ADDRESS}, {PROCESS_ID} missing"):
        requested()
    clean_env.setenv(ADDRESS, "127.0.0.1:1234")
    clean_env.setenv(PROCESS_ID, "2")
    with pytest.raises(ValueError, match=f"{PROCESS_ID}: from 0 to 1, got 2"):
        requested()
    clean_env.setenv(PROCESS_ID, "one")
    with pytest.raises(ValueError, match=f"{PROCESS_ID}: not a whole number"):
        requested()
    clean_env.setenv(PROCESS_ID, "1")
    assert requested() == 2
    # Dealt round-robin: every item to exactly one process.
    shares = [list(Processes(i, 3).share(8)) for i in range(3)]
    assert shares == [[0, 3, 6], [1, 4, 7], [2, 5]]
    assert Processes().gather({"a": 1}) == [{"a": 1}]


def test_a_command_of_one_process_refuses_a_distributed_run(clean_env, capsys):
    clean_env.setenv(SLURM_TASKS, "2")
    assert main(["verify", "nowhere", "nothing"]) == 2
    err = capsys.readouterr().err
    assert "jaxcal verify runs in one process, and the environment asks for 2" in err
    assert SLURM_TASKS in err


def _env() -> dict:
    """This environment for the processes of a run: one device each (no forced device count), the
    suite's other XLA flags kept (its quick compiles)."""
    env = {k: v for k, v in os.environ.items() if k not in NAMES}
    env["XLA_FLAGS"] = " ".join(f for f in env.get("XLA_FLAGS", "").split() if "force_host_platform" not in f)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    return env


@pytest.mark.slow
def test_two_processes_calibrate_a_fleet_as_one_does(tmp_path):
    """Two local processes of one distributed `jaxcal calibrate FLEET`: the units dealt between
    them, the folder written once, equal to one process's (timings apart; every unit's parameters
    bit for bit), nothing left beside it, and both processes exit with the fleet's code. (Their
    Monte Carlo: `benchmarks/montecarlo.py --processes 2`, in tests/test_benchmarks.py.)"""
    fleet = tmp_path / "fleet"
    for seed in range(4):
        simulate_tracker(TrackerSimConfig(seed=40 + seed, **KW), fleet / f"unit{seed:02d}")
    (fleet / "broken").mkdir()
    (fleet / "broken" / "metadata.json").write_text((fleet / "unit00" / "metadata.json").read_text())
    two = tmp_path / "two"
    argv = [
        sys.executable,
        "-m",
        "jaxcal",
        "calibrate",
        str(fleet),
        "--out",
        str(two),
        "--config",
        "cv-folds=0",
    ]
    runs = run_local(argv, 2, env=_env(), timeout=600, capture=True)
    assert [r.returncode for r in runs] == [3, 3], (
        runs[0].stderr[-3000:] + runs[1].stderr[-3000:]
    )  # a refused unit
    # Each process says its own units (dealt round-robin); the first, the fleet's summary.
    assert "(process 1 of 2) unit 2/5 unit00: ok" in runs[1].stdout and "unit 2/5" not in runs[0].stdout
    assert "(process 0 of 2) unit 1/5 broken: refused" in runs[0].stdout and "wrote" not in runs[1].stdout
    single = tmp_path / "one"
    assert main(["calibrate", str(fleet), "--out", str(single), "--config", "cv-folds=0", "--quiet"]) == 3
    docs = [json.loads((d / "fleet.json").read_text()) for d in (single, two)]
    assert without_timings(docs[0]) == without_timings(docs[1])
    assert sorted(p.name for p in two.iterdir()) == sorted(p.name for p in single.iterdir())
    for unit in ("unit00", "unit03"):
        a, b = (json.loads((d / unit / "result.json").read_text())["parameters"] for d in (single, two))
        assert [p["estimate"] for p in a] == [p["estimate"] for p in b]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fleet", "one", "two"], "a lock or temporary left"


def test_a_refused_output_stops_every_process(tmp_path):
    """An --out jaxcal did not write: each process refuses it by name, none waits for another."""
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("mine")
    argv = [sys.executable, "-m", "jaxcal", "calibrate", str(tmp_path / "a"), str(tmp_path / "b")]
    argv += ["--out", str(tmp_path / "mine"), "--quiet"]
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    runs = run_local(argv, 2, env=_env(), timeout=300, capture=True)
    assert [r.returncode for r in runs] == [2, 2]
    for r in runs:
        assert f"--out {tmp_path / 'mine'}" in r.stderr, r.stderr[-2000:]
    assert (tmp_path / "mine" / "notes.txt").read_text() == "mine"


class _PeerElsewhere(Processes):
    """Process 0 of 2 whose peer runs on another host and does not see process 0's folders."""

    def gather(self, obj):
        sees = isinstance(obj, tuple) and isinstance(obj[1], bool)  # (host, sees the folder)
        return [obj, ("host-b", False) if sees else (None, None)]


def test_an_output_folder_one_process_cannot_see_is_refused_by_every_process(tmp_path):
    """A fleet's --out on a disk of one host only: refused before any unit, naming the process,
    its host and the folder; nothing is left beside --out."""
    with pytest.raises(
        OutputError, match=r"--out .*out: process 1 \(on host-b\) of 2 cannot see .*\.out\..*\.tmp"
    ):
        with fleet._shared_folder(
            tmp_path / "out", _PeerElsewhere(0, 2), inputs=(), kind="result", what="--out"
        ):
            raise AssertionError("a unit was calibrated")
    assert list(tmp_path.iterdir()) == []


def test_the_processes_of_a_run_run_one_command_line(tmp_path):
    """Processes given different options (here --out) are refused before any work, by name."""
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    argv = ["calibrate", str(tmp_path / "a"), str(tmp_path / "b"), "--out"]
    code = f"import sys, os; from jaxcal.cli import main; sys.exit(main({argv!r} + [{str(tmp_path)!r} + '/out' + os.environ['JAX_PROCESS_ID']]))"
    runs = run_local([sys.executable, "-c", code], 2, env=_env(), timeout=120, capture=True)
    assert [r.returncode for r in runs] == [2, 2]
    assert "must run one command line; process 0 of 2 has" in runs[0].stderr, runs[0].stderr[-2000:]
    assert f"--out {tmp_path}/out1" in runs[0].stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a", "b"]


_STOPS = """
import sys
from jaxcal.distributed import PeerError, join
p = join()
if p.index == 1:
    p.fail("its robot file is missing")
    sys.exit(2)
try:
    p.gather("mine")
except PeerError as e:
    print(e)
    sys.exit(2)
"""


def test_a_process_that_stops_stops_the_others():
    """The others are told (`Processes.fail`), instead of waiting for a process that has gone."""
    runs = run_local([sys.executable, "-c", _STOPS], 2, env=_env(), timeout=120, capture=True)
    assert [r.returncode for r in runs] == [2, 2], [r.stderr[-1500:] for r in runs]
    assert runs[0].stdout.strip() == "process 1 of 2 stopped: its robot file is missing"


def test_processes_past_their_time_are_interrupted_even_from_a_process_that_ignores_ctrl_c(monkeypatch):
    """A launcher that ignores SIGINT (a shell's background job, pytest-xdist's worker) passes the
    ignoring on: its processes must still take `run_local`'s Ctrl-C, not wait out `STOP_S` and die."""
    import signal

    killed = []
    monkeypatch.setattr(
        subprocess.Popen, "kill", lambda self: killed.append(self.pid) or os.kill(self.pid, 9)
    )
    before = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        with pytest.raises(subprocess.TimeoutExpired):
            run_local([sys.executable, "-c", "import time; time.sleep(60)"], 2, env=_env(), timeout=3.0)
    finally:
        signal.signal(signal.SIGINT, before)
    assert killed == []


def test_the_local_launcher_gives_each_process_its_place():
    code = "from jaxcal.distributed import join; p = join(); print(p.index, p.count)"
    runs = run_local([sys.executable, "-c", code], 2, env=_env(), timeout=120, capture=True)
    assert [r.stdout.split() for r in runs] == [["0", "2"], ["1", "2"]], [r.stderr[-1000:] for r in runs]
    assert distributed.current() == distributed.ONE  # this process joined nothing
