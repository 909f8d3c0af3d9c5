"""`jaxcal montecarlo`: its options, and its entry point, which says what it does before the
study's modules (JAX, the simulator) are imported (the work: `._study_run`)."""

import argparse
import sys

from .._configkeys import knob
from ._common import count, degrees, non_negative, seed

#: `jaxcal._montecarlo.MAX_TRIALS` and `.MAX_FRAMES`, here so that the parser imports no JAX (a
#: test keeps them equal).
MAX_TRIALS, MAX_FRAMES = 1_000_000, 2000


def add_study_args(p: argparse.ArgumentParser, trials: int) -> None:
    p.add_argument(
        "--robot",
        default="ur5e",
        help="shipped robot (ur5e, panda, ur10e, iiwa14, ...: data/robots), a URDF or a DH/MDH table file",
    )
    p.add_argument(
        "--trials", type=count(1, MAX_TRIALS), default=trials, help=f"trials, at most {MAX_TRIALS:,}"
    )
    knob(
        p,
        "--chunk",
        type=count(1, MAX_TRIALS),
        default=None,
        help="trials per vmapped chunk: the memory a run takes (default 250 on the CPU, on a GPU all at once "
        "up to 10,000; see monte_carlo)",
    )
    p.add_argument("--seed", type=seed, default=0)
    p.add_argument(
        "--noise-mm",
        type=non_negative,
        default=0.1,
        help="marker position noise, 1-sigma per axis, the same on every axis (mm); a calibration's arc fits "
        "report position_rms_mm, the 3-D RMS: about 1.7x this, and more along the camera's line of sight",
    )
    p.add_argument(
        "--noise-deg",
        type=non_negative,
        default=0.05,
        help="marker orientation noise, 1-sigma per axis (deg); rotation_rms_deg is the 3-D RMS",
    )
    knob(p, "--encoder-noise-deg", type=non_negative, default=0.0)
    p.add_argument(
        "--sweep-deg", type=degrees, default=60.0, help="angle each joint sweeps (deg), one for every joint"
    )
    p.add_argument(
        "--frames-per-joint",
        type=count(3, MAX_FRAMES),
        default=40,
        help=f"camera frames per joint sweep, at most {MAX_FRAMES}",
    )


def cmd_montecarlo(args) -> int:
    print(f"Monte Carlo study of {args.robot}: {args.trials:,} trials ...", file=sys.stderr, flush=True)
    from ._study_run import run_montecarlo

    return run_montecarlo(args)
