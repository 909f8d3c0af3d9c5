"""How a result was made: `result.json`'s `run` block and `report.md`'s line naming it."""

import datetime
import importlib.metadata
import os
import platform
import shlex


def _plain(value):
    """An option's value as JSON: paths and other objects as text, tuples as lists."""
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return str(value)


def _version(package: str) -> str | None:
    try:
        return importlib.metadata.version(package)
    except importlib.metadata.PackageNotFoundError:
        return None


def run_record(argv: list[str], options: dict) -> dict:
    """The command line `argv` as given, every option's value `options` after the configuration
    is applied (defaults included, so that a default a later release changes shows), the working
    directory its relative paths start from, and the versions of jaxcal, JAX and Python."""
    return {
        "command": shlex.join(str(a) for a in argv),
        "options": {k: _plain(v) for k, v in options.items()},
        "cwd": os.getcwd(),
        "jaxcal": _version("jaxcal") or "0.0.0",
        "jax": _version("jax"),
        "python": platform.python_version(),
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
    }


def made_by(run: dict | None) -> list[str]:
    """`report.md`'s lines naming the command that made the result (none without `run`)."""
    if run is None:
        return []
    return [
        f"Made by `{run['command']}` (jaxcal {run['jaxcal']}, JAX {run['jax']}, {run['date']}); every "
        "option's value is in `result.json`'s `run`.",
        "",
    ]
