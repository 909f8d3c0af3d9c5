"""Shared pieces of the command line: argument types and JSON output."""

import argparse
import json
from pathlib import Path

import numpy as np

from ..io._files import write_text_atomic


def write_json_atomic(path: Path, payload: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(path, json.dumps(payload, indent=2))


def positive_int(text: str) -> int:
    """An argparse type: an integer >= 1."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return v


def add_study_args(p: argparse.ArgumentParser, trials: int) -> None:
    p.add_argument(
        "--robot",
        default="ur5e",
        help="shipped robot (ur5e, panda, ur10e, iiwa14, ...: data/robots), a URDF or a DH/MDH table file",
    )
    p.add_argument("--trials", type=int, default=trials)
    p.add_argument(
        "--chunk",
        type=int,
        default=None,
        help="trials per vmapped chunk (default 250 on the CPU, all at once on a GPU; see monte_carlo)",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--noise-mm", type=float, default=0.1, help="marker position noise (mm)")
    p.add_argument("--noise-deg", type=float, default=0.05, help="marker orientation noise (deg)")
    p.add_argument("--encoder-noise-deg", type=float, default=0.0)
    p.add_argument("--sweep-deg", type=float, default=60.0, help="angle each joint sweeps (deg)")
    p.add_argument("--frames", type=int, default=40, help="camera frames per joint sweep")


def resolution(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"resolution must look like 640x480, got {text!r}") from None
    return w, h


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
        return tuple(float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"home must look like 0,-20,30,-15,20,0 (deg), got {text!r}"
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
