"""Shared pieces of the command line: argument types (`finite` and `count`: `jaxcal._argtypes`)."""

import argparse

import numpy as np

from .._argtypes import count as count
from .._argtypes import finite as finite
from .._argtypes import non_negative as non_negative
from .._argtypes import positive as positive
from .._argtypes import resolution as _resolution
from ..io._images import MAX_PIXELS, MAX_SIDE

#: Bounds of the options that size a simulated capture (work, memory and disk grow with them).
MAX_CAMERAS = 8
MAX_FRAMES_PER_JOINT = 2000
MAX_SAMPLES_PER_JOINT = 100_000
MAX_MOTION_S = 600.0
#: `--workers`: threads (or processes) detecting markers.
MAX_WORKERS = 256
#: `--seed`: what NumPy's and JAX's generators take.
seed = count(0, 2**32 - 1)
#: `--resolution`: `WxH` pixels, as the dataset reader takes them.
resolution = _resolution(MAX_SIDE, MAX_PIXELS)


def seconds(hi: float):
    """An argparse type: a duration in (0, `hi`] seconds."""

    def parse(text: str) -> float:
        v = finite(text)
        if not 0.0 < v <= hi:
            raise argparse.ArgumentTypeError(f"expected seconds in (0, {hi:g}], got {text!r}")
        return v

    return parse


def degrees(text: str) -> float | tuple[float, ...]:
    """One angle for every joint ("40") or one per joint ("40,40,40,40,40,300")."""
    try:
        v = tuple(float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"angles must look like 40 or 40,40,40,40,40,300, got {text!r}"
        ) from None
    if any(not 0.0 < x <= 360.0 for x in v):
        raise argparse.ArgumentTypeError(f"each sweep must be in (0, 360] degrees, got {text!r}")
    return v[0] if len(v) == 1 else v


def home(text: str) -> tuple[float, ...]:
    """One angle per joint, in degrees ("0,-20,30,-15,20,0")."""
    try:
        return tuple(finite(x) for x in text.split(","))
    except (ValueError, argparse.ArgumentTypeError):
        raise argparse.ArgumentTypeError(
            f"home must look like 0,-20,30,-15,20,0 (deg, finite), got {text!r}"
        ) from None


def fmt_degrees(v) -> str:
    return f"{v:g}" if np.ndim(v) == 0 else ",".join(f"{x:g}" for x in v)


#: The eye-in-hand demo's sweeps: the camera spins about its own axis with the
#: last joint, which keeps the board in view over a wide sweep (and pins that
#: axis, which passes near the camera, down); the others turn it away from the board.

EYE_IN_HAND_SWEEP = (40.0, 40.0, 40.0, 40.0, 40.0, 300.0)
#: ... and the board 0.6 m in front of the camera (at 0.9 m the EE error about triples).
EYE_IN_HAND_BOARD_M = 0.6
#: The markers-on-every-link demo's random motion, +- about zero.
LINKS_AMPLITUDE_DEG = 25.0
#: `--clock`'s choices: `jaxcal.stages.CLOCK_MODES`, here so that building the parser imports no
#: stage (tests/test_clock_option.py checks that the two agree).
CLOCK_MODES = ("auto", "estimate", "given")


def run_record(args) -> dict:
    """How a result was made (`jaxcal.io._provenance.run_record`) from the command line's
    namespace: the command as given and every option after the configuration."""
    from ..io._provenance import run_record as record

    options = {
        k: v
        for k, v in vars(args).items()
        if not k.startswith("_") and k not in ("func", "foreign", "command")
    }
    return record(["jaxcal", *getattr(args, "_argv", [args.command])], options)
