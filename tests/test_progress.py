"""Progress where no bar can be drawn (a pipe, a log file): a line at once, a line now and
then, a line at the end; and the long commands announce their work before doing it."""

import importlib.util
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
_spec = importlib.util.spec_from_file_location("first_line", ROOT / "benchmarks" / "first_line.py")
_bench = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_bench)
#: The commands `benchmarks/first_line.py` times, each with the start of its first line.
FIRST_LINES = _bench.FIRST_LINES


def _first_line(args: list[str], tmp_path, terminal: bool = False) -> str:
    """The first line a `jaxcal` command writes (`benchmarks/first_line.py`'s harness; its time
    is the benchmark's business, not a test's)."""
    return _bench.first_line(args, tmp_path, terminal=terminal)[0]


@pytest.mark.parametrize("name", [n for n, (_, first) in FIRST_LINES.items() if first])
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


def test_a_run_of_stages_is_never_silent(monkeypatch):
    """`watchdog`: after `LINE_EVERY_S` without a line, `STAGE: still working (t s)` through the
    run's own log; not while a live display (a bar, a spinner) shows life, and not while the
    stages speak for themselves; nothing after the run."""
    import contextlib

    monkeypatch.setattr(_progress, "LINE_EVERY_S", 0.2)
    lines = []

    def wait_for(n):
        deadline = time.monotonic() + 30.0
        while len(lines) < n and time.monotonic() < deadline:
            time.sleep(0.01)

    with _progress.watchdog(lines.append) as beat:
        beat.stage("the point fit")
        wait_for(1)
        assert lines[0].startswith("the point fit: still working (")
        with _progress._live(contextlib.nullcontext()):
            n = len(lines)
            time.sleep(0.8)
            assert len(lines) == n  # the bar shows life
        n = len(lines)
        for _ in range(8):
            beat.log("arc fits")
            time.sleep(0.05)
        assert lines[n:] == ["arc fits"] * 8
    n = len(lines)
    time.sleep(0.5)
    assert len(lines) == n
    # A call that says it is still working in its own lines (`working`) is not said twice.
    with _progress.watchdog(lines.append) as beat:
        beat.stage("clock offset")
        n = len(lines)
        beat.log("estimating the clock offset")
        time.sleep(0.1)  # the watchdog's next line is due before the call's first
        with _progress.working(True, "the clock offset", say=beat.log):
            time.sleep(1.0)
        said = lines[n + 1 :]
        assert said and all(line.startswith("the clock offset: still working (") for line in said), said
    with _progress.watchdog(None) as beat:  # no log: nothing, and no thread
        beat.stage("x")
        beat.log("y")
