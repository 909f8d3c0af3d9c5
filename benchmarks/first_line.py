"""How long every subcommand leaves its user without a word: the seconds from starting a fresh
`jaxcal` process to its first line of output, in a pipe and on a pseudo-terminal (issue 50: within
2 s). `tests/test_progress.py` checks what the line says with the same commands and harness.

Each command runs in an empty temporary directory and is stopped once its first line is out (the
work after it is not timed); `verify`, `certify` and `check` are pointed at a result that is not
there: they name what they read before reading it, then refuse it. Figures are the median of
`--repeats` fresh processes, with the machine's compilation cache as it is (the first line comes
before any compile).

    python benchmarks/first_line.py --json results/first_line.json [--repeats 3] [--commands calibrate,plan]

The JSON: per command its median seconds in a pipe (`pipe_s`) and on a terminal (`terminal_s`),
every repeat (`runs`), the first line each wrote (`lines`), `slowest_s`, the commands over the
2 s bound (`over_2s`), the load average before the runs and the machine.
"""

import argparse
import fcntl
import json
import os
import platform
import pty
import re
import select
import statistics
import struct
import subprocess
import sys
import tempfile
import termios
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SWEEPS, TRACKER = ROOT / "data" / "ur5e_sweeps", ROOT / "data" / "ur5_tracker"
ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]|\x1b\][^\x07]*\x07|[\r\x07]")
BOUND_S = 2.0

#: Every subcommand, the arguments it is timed with and the start of the first line it writes
#: before its work: before compiling (montecarlo: one call that compiles for most of a minute),
#: building a scene and rendering (simulate), detecting, planning or reading its inputs (verify,
#: certify and check name what they read before they read it: a result that is not there is
#: refused after the line).
FIRST_LINES = {
    "calibrate": (["calibrate", str(SWEEPS), "--out", "res"], f"calibrating {SWEEPS} into res"),
    "calibrate-tracker": (
        ["calibrate", str(TRACKER / "grid"), "--device-is-base", "--out", "res"],
        f"calibrating {TRACKER / 'grid'} into res",
    ),
    "demo": (["demo", "--out", "demo"], "jaxcal demo: a perturbed UR5e"),
    "montecarlo": (["montecarlo", "--trials", "4"], "Monte Carlo study of ur5e: 4 trials"),
    "simulate": (
        ["simulate", "--out", "sim", "--resolution", "160x120"],
        "simulating a perturbed ur5e into sim",
    ),
    "simulate-tracker": (["simulate-tracker", "--out", "trk"], "simulating ur3's tracker sweeps into trk"),
    "simulate-handeye": (["simulate-handeye", "--out", "he"], "rendering 16 frames of a chessboard"),
    "handeye": (
        ["handeye", str(ROOT / "data" / "visp_handeye" / "eye_in_hand"), "--out", "he"],
        "hand-eye calibration of ",
    ),
    "plan": (["plan", "--out", "plan.json", "--frames", "24"], "planning 24 stop-and-shoot poses of ur5e"),
    "verify": (["verify", "res", str(TRACKER / "test")], "verifying res on"),
    "certify": (["certify", "res"], "certifying res over its workspace"),
    "check": (["check", "res", str(TRACKER / "test")], "checking"),
    "inspect": (["inspect", str(SWEEPS)], ""),
    "import-bag": (
        ["import-bag", str(ROOT / "data" / "ros" / "ur5e_sweeps_mcap"), "--out", "bag"]
        + ["--images", "/camera/image_raw/compressed", "--joints", "/joint_states"]
        + ["--robot", str(SWEEPS / "robot.urdf"), "--target", str(ROOT / "data" / "ros" / "plate0.json")],
        "importing ",
    ),
    "simulate-plan": (["simulate-plan", "plan.json", "--out", "sim"], "simulating plan plan.json into sim"),
    "import-csv": (
        ["import-csv", str(TRACKER / "source" / "3D_UR5_uncalibrated_grid_cleaned.csv"), "--robot", "ur5_dh"]
        + [
            "--out",
            "grid",
            "--joint-columns",
            ",".join(f"joint_{k}" for k in range(1, 7)),
            "--joint-unit",
            "deg",
        ]
        + ["--xyz", "x_t+x_dif,y_t+y_dif,z_t+z_dif", "--length-unit", "mm", "--sigma-mm", "0.02"]
        + ["--point-mm", "0,0.09,31.0", "--point-name", "smr"],
        "importing ",
    ),
}


def first_line(args: list[str], cwd, terminal: bool = False) -> tuple[str, float]:
    """The first line a `jaxcal` command writes (stdout and stderr together; on a pseudo-terminal
    with `terminal`, rich's control codes removed) and the seconds from its start to that line;
    the command is then stopped."""
    if terminal:
        out_fd, in_fd = pty.openpty()  # the child writes to `in_fd`, a terminal of 200 columns
        fcntl.ioctl(in_fd, termios.TIOCSWINSZ, struct.pack("HHHH", 50, 200, 0, 0))
        stdout = in_fd
    else:
        out_fd, stdout = None, subprocess.PIPE
    env = dict(os.environ, COLUMNS="200", TERM="xterm-256color")
    argv = [sys.executable, "-m", "jaxcal", *args]
    t0 = time.perf_counter()
    p = subprocess.Popen(
        argv, stdout=stdout, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, cwd=cwd, env=env
    )
    fd = out_fd if terminal else p.stdout.fileno()
    if terminal:
        os.close(in_fd)
    text = b""
    try:
        deadline = time.monotonic() + 120.0  # a bound on a hung process
        while time.monotonic() < deadline:
            if select.select([fd], [], [], 1.0)[0]:
                try:
                    chunk = os.read(fd, 4096)
                except OSError:  # the terminal closed: the child ended
                    chunk = b""
                text += chunk
                shown = ANSI.sub("", text.decode(errors="replace"))
                line = shown.strip()
                if line and ("\n" in shown.lstrip() or not chunk):  # a whole line is out
                    return line.splitlines()[0].strip("─ "), time.perf_counter() - t0
                if not chunk:
                    return line, time.perf_counter() - t0
            elif p.poll() is not None and not terminal:
                return p.stdout.read().decode().strip(), time.perf_counter() - t0
        return "", time.perf_counter() - t0
    finally:
        p.kill()
        p.wait()
        if terminal:
            os.close(out_fd)
        else:
            p.stdout.close()


def _plan_file(work: Path) -> None:
    """`simulate-plan`'s input: a small plan, written once by `jaxcal plan` (not timed)."""
    plan = [
        sys.executable,
        "-m",
        "jaxcal",
        "plan",
        "--out",
        str(work / "plan.json"),
        "--frames",
        "24",
        "--quiet",
    ]
    subprocess.run(plan + ["--config", "candidates=200", "--config", "no-mujoco=true"], check=True, cwd=work)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", help="write the figures here")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--commands", help="comma-separated names of FIRST_LINES (default: all)")
    args = parser.parse_args(argv)
    names = args.commands.split(",") if args.commands else list(FIRST_LINES)
    unknown = [n for n in names if n not in FIRST_LINES]
    if unknown:
        parser.error(f"unknown commands {unknown}; known: {', '.join(FIRST_LINES)}")
    report = {"pipe_s": {}, "terminal_s": {}, "runs": {}, "lines": {}, "load": os.getloadavg()[0]}
    with tempfile.TemporaryDirectory(prefix="jaxcal-first-line-") as tmp:
        work = Path(tmp)
        if "simulate-plan" in names:
            print("writing a small plan for simulate-plan (not timed) ...", flush=True)
            _plan_file(work)
        for name in names:
            command, expected = FIRST_LINES[name]
            for mode in ("pipe", "terminal"):
                runs = []
                for k in range(args.repeats):
                    cwd = work / f"{name}-{mode}-{k}"
                    cwd.mkdir()
                    if name == "simulate-plan":
                        (cwd / "plan.json").write_bytes((work / "plan.json").read_bytes())
                    line, seconds = first_line(command, cwd, terminal=mode == "terminal")
                    if expected and expected not in line:
                        raise SystemExit(f"{name} ({mode}): first line {line!r}, expected {expected!r}")
                    runs.append(seconds)
                    report["lines"][name] = line
                report[f"{mode}_s"][name] = statistics.median(runs)
                report["runs"][f"{name} {mode}"] = runs
            print(
                f"{name:18s} pipe {report['pipe_s'][name]:5.2f} s   terminal {report['terminal_s'][name]:5.2f} s"
                f"   {report['lines'][name][:60]!r}",
                flush=True,
            )
    figures = list(report["pipe_s"].values()) + list(report["terminal_s"].values())
    report["slowest_s"] = max(figures)
    report["over_2s"] = sorted(
        {n for mode in ("pipe_s", "terminal_s") for n, s in report[mode].items() if s > BOUND_S}
    )
    report["machine"] = {"cpus": os.cpu_count(), "python": platform.python_version(), "node": platform.node()}
    print(
        f"slowest first line {report['slowest_s']:.2f} s; over {BOUND_S:g} s: {report['over_2s'] or 'none'}"
    )
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(args.json).with_suffix(".tmp")
        tmp.write_text(json.dumps(report, indent=1))
        tmp.replace(args.json)


if __name__ == "__main__":
    main()
