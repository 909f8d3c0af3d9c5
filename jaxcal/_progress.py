"""Progress for long work: a rich bar on a terminal (or in Jupyter), one line at a time
in a pipe or a log, nothing when disabled."""

import contextlib
import sys
import threading
import time

#: In a pipe, a line of progress at most this often (s), besides the first and the last: no
#: silence of more than 10 s.
LINE_EVERY_S = 8.0

#: When jaxcal last wrote a line of progress (`time.monotonic`), and how many live displays (rich
#: bars and spinners, which show life themselves) are on screen: what `watchdog` reads.
_LAST_LINE = [time.monotonic()]
_LIVE = [0]


def _said() -> None:
    _LAST_LINE[0] = time.monotonic()


@contextlib.contextmanager
def _live(display):
    """`display` (a rich bar or spinner) entered, counted as live while it is."""
    _LIVE[0] += 1
    try:
        with display as shown:
            yield shown
    finally:
        _LIVE[0] -= 1


class LineProgress:
    """What a rich bar shows, as plain lines for a pipe or a log file (where a bar is drawn
    only when it ends): `description ...` at once, `description: k/N (t s)` at most every
    `LINE_EVERY_S`, and `description: N/N in t s` at the end. The subset of
    `rich.progress.Progress` that jaxcal's loops use: `add_task`, `advance`, `update`."""

    def __init__(self, description: str):
        self.description = description
        self.tasks: dict[int, list] = {}

    def __enter__(self):
        self.start = self.last = time.monotonic()
        self._line(f"{self.description} ...")
        return self

    def __exit__(self, *exc):
        if exc[0] is None:
            for done, total in self.tasks.values():
                self._line(f"{self.description}: {done}/{total} in {time.monotonic() - self.start:.1f} s")
        return False

    def add_task(self, name: str, total: int | None = None, **_) -> int:
        self.tasks[len(self.tasks)] = [0, total]
        return len(self.tasks) - 1

    def update(self, task: int, *, advance: float = 0, completed: float | None = None, **_) -> None:
        entry = self.tasks[task]
        entry[0] = int(completed if completed is not None else entry[0] + advance)
        now = time.monotonic()
        if now - self.last >= LINE_EVERY_S:
            self.last = now
            self._line(f"{self.description}: {entry[0]}/{entry[1]} ({now - self.start:.0f} s)")

    def advance(self, task: int, advance: float = 1) -> None:
        self.update(task, advance=advance)

    def _line(self, text: str) -> None:
        _said()
        print(text, flush=True)


def progress(enabled: bool, description: str, *, transient: bool = False):
    """A `rich.progress.Progress` with a description, bar, count and time
    remaining (a context manager; add tasks to it) on a terminal or in Jupyter, a
    `LineProgress` elsewhere (a pipe, a log), or a null context yielding `None` when
    not `enabled`."""
    if not enabled:
        return contextlib.nullcontext()
    from rich.console import Console

    console = Console()
    if not (console.is_terminal or console.is_jupyter):
        return LineProgress(description)
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    return _live(
        Progress(
            TextColumn(description),
            BarColumn(),
            MofNCompleteColumn(),
            TimeRemainingColumn(),
            transient=transient,
        )
    )


@contextlib.contextmanager
def working(enabled: bool, description: str, *, stream=None, say=None):
    """Around one long call that reports nothing itself (a compile, one jitted batch): a line
    `description: still working (t s)` every `LINE_EVERY_S` until the call returns, through
    `say` (a callable taking a line: the caller's own channel of progress) or, without it, to
    `stream` (default stdout), where on a terminal a rich spinner stands instead; so a pipe or
    a log is never silent for long. Nothing when not `enabled`."""
    if not enabled:
        yield
        return
    if say is None:
        from rich.console import Console

        console = Console(stderr=stream is sys.stderr)
        if console.is_terminal:
            with _live(console.status(description)):
                yield
            return

        def say(line):
            print(line, file=stream or sys.stdout, flush=True)

    done = threading.Event()
    start = time.monotonic()

    def tick():
        while not done.wait(LINE_EVERY_S):
            _said()  # for `watchdog`
            say(f"{description}: still working ({time.monotonic() - start:.0f} s)")

    thread = threading.Thread(target=tick, name="jaxcal progress", daemon=True)
    thread.start()
    _LIVE[0] += 1  # its own lines: `watchdog` says nothing over them
    try:
        yield
    finally:
        _LIVE[0] -= 1
        done.set()
        thread.join()


class _Watchdog:
    """`watchdog`'s state: the stage now running and since when."""

    def __init__(self, log):
        self._log = log
        self.name, self.since = "starting", time.monotonic()

    def log(self, text: str) -> None:
        _said()
        self._log(text)

    def stage(self, name: str) -> None:
        self.name, self.since = name, time.monotonic()


@contextlib.contextmanager
def watchdog(log):
    """Around a run of stages that report through `log` (a callable taking a line, or None: no
    watchdog): yields an object whose `log` is `log` noted, and whose `stage(name)` names the
    stage now running. Whenever jaxcal has written no line of progress for `LINE_EVERY_S` and no
    live display (bar, spinner) is on screen, a line `name: still working (t s)` goes to `log`:
    a stage that runs long without a word of its own (a compile, a search) is never silent."""
    beat = _Watchdog(log if log is not None else (lambda text: None))
    if log is None:
        yield beat
        return
    done = threading.Event()
    _said()

    def tick():
        while not done.wait(min(0.5, LINE_EVERY_S / 4)):
            now = time.monotonic()
            if _LIVE[0] == 0 and now - _LAST_LINE[0] >= LINE_EVERY_S:
                beat.log(f"{beat.name}: still working ({now - beat.since:.0f} s)")

    thread = threading.Thread(target=tick, name="jaxcal watchdog", daemon=True)
    thread.start()
    try:
        yield beat
    finally:
        done.set()
        thread.join()
