"""Progress bars for long work (rich), or nothing when disabled."""

import contextlib


def progress(enabled: bool, description: str, *, transient: bool = False):
    """A `rich.progress.Progress` with a description, bar, count and time
    remaining (a context manager; add tasks to it), or a null context
    yielding `None` when not `enabled`."""
    if not enabled:
        return contextlib.nullcontext()
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    return Progress(
        TextColumn(description), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(), transient=transient
    )
