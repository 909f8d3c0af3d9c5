"""Progress where no bar can be drawn (a pipe, a log file): a line at once, a line now and
then, a line at the end; and the long commands announce their work before doing it."""

import fcntl
import os
import pty
import re
import select
import struct
import subprocess
import sys
import termios
import time
from pathlib import Path

import pytest

from jaxcal import _progress


def test_in_a_pipe_progress_is_lines_first_now_and_then_and_last(monkeypatch, capsys):
    monkeypatch.setattr(_progress, "LINE_EVERY_S", 0.0)  # a line at every step
    with _progress.progress(True, "rendering 3 images") as bar:
        assert isinstance(bar, _progress.LineProgress)  # pytest's capture is not a terminal
        task = bar.add_task("render", total=3)
        for _ in range(3):
            bar.advance(task)
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "rendering 3 images ..."
    assert [line.split(" (")[0] for line in lines[1:4]] == [f"rendering 3 images: {k}/3" for k in (1, 2, 3)]
    assert lines[4].startswith("rendering 3 images: 3/3 in ") and lines[4].endswith(" s")
    assert len(lines) == 5


def test_progress_off_is_silent(capsys):
    with _progress.progress(False, "x") as bar:
        assert bar is None
    assert capsys.readouterr().out == ""


def test_an_interrupted_loop_prints_no_last_line(capsys):
    with pytest.raises(KeyboardInterrupt), _progress.progress(True, "detecting markers in 4 images") as bar:
        bar.add_task("detect", total=4)
        raise KeyboardInterrupt
    assert capsys.readouterr().out.splitlines() == ["detecting markers in 4 images ..."]


ROOT = Path(__file__).resolve().parents[1]
SWEEPS, TRACKER = ROOT / "data" / "ur5e_sweeps", ROOT / "data" / "ur5_tracker"
ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]|\x1b\][^\x07]*\x07|[\r\x07]")


def _first_line(args: list[str], tmp_path, terminal: bool = False) -> str:
    """The first line a `jaxcal` command writes (stdout and stderr together; on a pseudo-terminal
    with `terminal`, rich's control codes removed); the command is then stopped."""
    if terminal:
        out_fd, in_fd = pty.openpty()  # the child writes to `in_fd`, a terminal of 200 columns
        fcntl.ioctl(in_fd, termios.TIOCSWINSZ, struct.pack("HHHH", 50, 200, 0, 0))
        stdout = in_fd
    else:
        out_fd, stdout = None, subprocess.PIPE
    env = dict(os.environ, COLUMNS="200", TERM="xterm-256color")
    argv = [sys.executable, "-m", "jaxcal", *args]
    p = subprocess.Popen(
        argv, stdout=stdout, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, cwd=tmp_path, env=env
    )
    fd = out_fd if terminal else p.stdout.fileno()
    if terminal:
        os.close(in_fd)
    text = b""
    try:
        deadline = time.monotonic() + 120.0  # a bound on a hung process, not a timing check
        while time.monotonic() < deadline:
            if select.select([fd], [], [], 1.0)[0]:
                try:
                    chunk = os.read(fd, 4096)
                except OSError:  # the terminal closed: the child ended
                    chunk = b""
                text += chunk
                line = ANSI.sub("", text.decode(errors="replace")).strip()
                if line and ("\n" in line or not chunk):
                    return line.splitlines()[0].strip("─ ")
                if not chunk:
                    return line
            elif p.poll() is not None and not terminal:
                return p.stdout.read().decode()
        return ""
    finally:
        p.kill()
        p.wait()
        if terminal:
            os.close(out_fd)
        else:
            p.stdout.close()


#: Every subcommand that can run longer than a few seconds, and the start of the line it writes
#: before its work: before compiling (montecarlo: one call that compiles for most of a minute),
#: building a scene and rendering (simulate), detecting, planning or reading its inputs (verify,
#: certify and check name what they read before they read it: a result that is not there is
#: refused after the line).
FIRST_LINES = {
    "calibrate": (["calibrate", str(SWEEPS), "--out", "res"], "detecting plate0 in 144 frames"),
    "calibrate-tracker": (
        ["calibrate", str(TRACKER / "grid"), "--device-is-base", "--out", "res"],
        "point fit: 1000 stop-and-shoot poses",
    ),
    "demo": (["demo", "--out", "demo"], "jaxcal demo: a perturbed UR5e"),
    "montecarlo": (["montecarlo", "--trials", "4"], "Monte Carlo: 4 trials of "),
    "simulate": (
        ["simulate", "--out", "sim", "--resolution", "160x120"],
        "simulating a perturbed ur5e into sim",
    ),
    "simulate-tracker": (["simulate-tracker", "--out", "trk"], "simulating ur3's tracker sweeps into trk"),
    "simulate-handeye": (["simulate-handeye", "--out", "he"], "rendering 16 frames of a chessboard"),
    "handeye": (["handeye", str(ROOT / "data" / "visp_handeye" / "eye_in_hand"), "--out", "he"], "detecting"),
    "plan": (["plan", "--out", "plan.json", "--frames", "24"], "candidates: 2000 random poses"),
    "verify": (["verify", "res", str(TRACKER / "test")], "verifying res on"),
    "certify": (["certify", "res"], "certifying res over its workspace"),
    "check": (["check", "res", str(TRACKER / "test")], "checking"),
}


@pytest.mark.parametrize("name", list(FIRST_LINES))
def test_long_commands_say_what_they_do_before_doing_it(name, tmp_path):
    args, first = FIRST_LINES[name]
    assert _first_line(args, tmp_path).startswith(first)


@pytest.mark.parametrize("name", ["calibrate", "plan", "certify"])
def test_on_a_terminal_too(name, tmp_path):
    """On a terminal rich draws the bars; the first text is still what the command does."""
    args, first = FIRST_LINES[name]
    assert first in _first_line(args, tmp_path, terminal=True)


def test_a_long_call_in_a_pipe_says_it_is_still_working(monkeypatch):
    """`working`: around one call that reports nothing (a compile), a line every
    `LINE_EVERY_S` in a pipe, and none after the call returns."""
    import io

    monkeypatch.setattr(_progress, "LINE_EVERY_S", 0.01)
    stream = io.StringIO()
    with _progress.working(True, "Monte Carlo: 4 trials", stream=stream):
        deadline = time.monotonic() + 60.0
        while stream.getvalue().count("\n") < 2 and time.monotonic() < deadline:
            time.sleep(0.01)
    after = stream.getvalue()
    time.sleep(0.05)
    assert stream.getvalue() == after  # the ticker stopped with the call
    lines = after.splitlines()
    assert len(lines) >= 2 and all(
        line.startswith("Monte Carlo: 4 trials: still working (") for line in lines
    )
    with _progress.working(False, "x", stream=stream):
        pass
    assert stream.getvalue() == after


def test_a_long_call_reports_through_the_callers_own_channel(monkeypatch):
    """`working(say=log)`: the lines go where the caller's progress goes (plan's and handeye's
    `log`, the calibration's `Options.say`), terminal or not."""
    monkeypatch.setattr(_progress, "LINE_EVERY_S", 0.01)
    lines = []
    with _progress.working(True, "choosing 24 poses", say=lines.append):
        deadline = time.monotonic() + 60.0
        while not lines and time.monotonic() < deadline:
            time.sleep(0.01)
    assert lines and lines[0].startswith("choosing 24 poses: still working (")
