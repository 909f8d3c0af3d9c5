"""`jaxcal calibrate` and `jaxcal demo`: their options and entry points. The work (`._calibrate_run`)
is imported once the command has begun to read its programs ahead, so that the modules' import and
the programs' load overlap."""

import argparse
import contextlib
import sys
from functools import partial
from pathlib import Path

from .. import distributed
from .._configkeys import knob
from ..fleet import is_fleet
from ..io._files import check_output_dir, marked_directory, output_lock, resolved
from ._common import CLOCK_MODES, MAX_WORKERS, count

#: `--cv-folds`: the folds' fits are solved at once (one vmap), memory growing with them.
MAX_CV_FOLDS = 100
#: The families of `jaxcal._terms.TERMS`, here so that the parser imports no JAX (a test keeps them equal).
TERMS = ("compliance", "backlash", "harmonic1", "harmonic2")


def terms_arg(text: str) -> tuple[str, ...] | str:
    """`--terms`: `auto`, `none`, or families comma-separated (`TERMS`)."""
    if text.strip() in ("auto", "none"):
        return "auto" if text.strip() == "auto" else ()
    names = tuple(t.strip() for t in text.split(",") if t.strip())
    if alone := [t for t in names if t in ("auto", "none")]:
        raise argparse.ArgumentTypeError(f"{alone[0]!r} stands alone (it is not a family): {text!r}")
    unknown = [t for t in names if t not in TERMS]
    if unknown:
        raise argparse.ArgumentTypeError(f"unknown terms {unknown}; known: auto, none, {', '.join(TERMS)}")
    if len(set(names)) != len(names):
        raise argparse.ArgumentTypeError(f"a family named twice: {text!r}")
    return names


def _tolerance(text: str) -> float:
    try:
        tol = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not 0.0 < tol < 1.0:
        raise argparse.ArgumentTypeError(f"must be in (0, 1), got {text}")
    return tol


def cmd_calibrate(args) -> int:

    out = Path(args.out)
    datasets = [args.dataset, *args.more]
    fleet, processes = is_fleet(datasets), distributed.current()  # one dataset: one process (`main`)
    if fleet:
        _refuse_in_fleet(args)
    # Before any work: --out may not hold or overlap the dataset, and --overwrite replaces
    # only a result jaxcal wrote; the lock makes a second run on the same --out fail at once
    # (in a distributed run, the first process holds it).
    checked = check_output_dir(out, inputs=datasets, overwrite=args.overwrite, kind="result", what="--out")
    if not args.quiet and processes.first:  # before the calibration's modules are imported: seconds
        what = f"a fleet ({', '.join(datasets)})" if fleet else args.dataset
        print(f"calibrating {what} into {out} ...", flush=True)
    # The programs the last run on DATASET called are read ahead from here on, while the
    # calibration's modules are imported and the images detected (`jaxcal._exported.warm_start`).
    from .._exported import warm_start  # JAX: after the first line

    lock = output_lock(out, what="--out") if processes.first else contextlib.nullcontext()
    with lock, warm_start(f"jaxcal calibrate {resolved(args.dataset)}"):
        from ._calibrate_run import calibrate_dataset, calibrate_fleet_datasets, calibrate_tree_dataset

        if (Path(args.dataset) / "tree.json").is_file() and not fleet:
            return calibrate_tree_dataset(args, out, checked)
        if fleet:
            return calibrate_fleet_datasets(args, datasets, out, checked)
        return calibrate_dataset(args, out, checked)


def _refuse_in_fleet(args) -> None:
    """What a fleet's calibration cannot take, refused before any work (exit 2)."""
    bag = [f for f in ("images", "joints", "camera_info", "robot", "target") if getattr(args, f, None)]
    if bag:
        raise ValueError(
            f"--{bag[0].replace('_', '-')} reads one ROS bag; a fleet reads dataset folders: import each bag with "
            "jaxcal import-bag first"
        )
    if args.region or args.joint_box:
        raise ValueError(
            "--region / --joint-box certify one result; certify a fleet's unit with jaxcal certify OUT/UNIT"
        )
    if args.prior:
        raise ValueError(
            "--prior calibrates one new unit; a fleet's units are calibrated without one (a unit of the prior's "
            "fleet would count its data twice, and the new fleet's prior would be the old one's)"
        )


def cmd_demo(args) -> int:
    if args.eye_in_hand and args.cameras != 1:
        print(
            "jaxcal: error: --eye-in-hand films with one camera (on the flange); drop --cameras",
            file=sys.stderr,
        )
        return 2
    if args.eye_in_hand and args.markers_on_links:
        print("jaxcal: error: choose one of --eye-in-hand and --markers-on-links", file=sys.stderr)
        return 2
    out = Path(args.out)
    # The demo directory (absent, empty or an earlier demo's) holds dataset/ and result/,
    # each replaced atomically; anything else there is refused before any work.
    with marked_directory(out, kind="demo", what="--out"):
        from rich.console import Console

        # Before the simulator's and the calibration's modules are imported: seconds.
        Console(width=max(Console().width, 132)).rule(
            "[bold]jaxcal demo: a perturbed UR5e, rendered, calibrated from its images"
        )
        from ._calibrate_run import demo

        return demo(out, args)


PRIOR_HELP = (
    "a fleet's prior on the robot's parameters: the fleet.json (or its folder) that calibrating 5 or more "
    "units of this robot model from points wrote; a new stop-and-shoot unit's point fit takes it as a Gaussian "
    "prior (result.json's point_fit.prior says how much of each parameter it gave); not for camera captures, "
    "sweeps or a fleet's own run"
)


def add_calibrate_args(p: argparse.ArgumentParser, *, demo: bool = False) -> None:
    """The calibration's options, of `calibrate` and `demo` (where `strict` is a configuration key)."""
    knob(p, "--camera", help="fixed camera of the two-stage fit (default: the first)")
    knob(
        p,
        "--single-camera",
        action="store_true",
        help="refine with the camera key's images only (by default every fixed camera joins the refinement, "
        "each with its own T_cam_base)",
    )
    knob(
        p,
        "--workers",
        type=count(1, MAX_WORKERS),
        help=f"threads for marker detection, 1 to {MAX_WORKERS} (default: all cores)",
    )
    knob(
        p,
        "--clock",
        choices=CLOCK_MODES,
        default="auto",
        help="the camera-controller clock offset: auto (default) estimates it whenever there is an encoder "
        "log and moving joints, and a metadata offset that disagrees is a warning; estimate: always, an "
        "error when it cannot be; given: metadata.json's offset as it is",
    )
    knob(
        p,
        "--refine-intrinsics",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="free the camera's intrinsics in the refinement (default: when metadata.json has no K and "
        "they are self-calibrated from the sweep images)",
    )
    knob(
        p,
        "--estimate-line-delay",
        action="store_true",
        help="take cameras whose line_delay_s metadata.json leaves null for rolling shutters and estimate their "
        'line delay in the refinement (as line_delay_s: "estimate")',
    )
    (partial(knob, p) if demo else p.add_argument)(
        "--strict",
        action="store_true",
        help="write nothing and exit 3 (1 if a solver failed) when a plausibility check fails",
    )
    knob(
        p,
        "--no-refine",
        action="store_true",
        help="stop at the two-stage result (arc + axis fits); by default every corner's reprojection "
        "error is then minimised over all parameters",
    )
    knob(
        p,
        "--arc-loss",
        choices=("cauchy", "huber", "none"),
        default="cauchy",
        help="robust loss of the arc and clock fits; rejected frames are named in result.json (default: cauchy)",
    )
    p.add_argument(
        "--terms",
        type=terms_arg,
        default="auto",
        help="non-geometric joint terms to try, comma-separated, the same names for camera and tracker data: "
        "compliance (each joint yields under gravity, from the robot file's link masses and the metadata's "
        "robot.payload), backlash (lost motion: the link lags its motor's last move, or rests where gravity "
        "preloads it), harmonic1, harmonic2 (a joint's once/twice-per-turn transmission error); each kept only "
        "if cross-validation improves (camera views left out in blocks of consecutive frames). auto (default): "
        "compliance,backlash for camera captures with an encoder log, none for tracker data; none: a rigid arm",
    )
    knob(
        p,
        "--cv-folds",
        type=count(0, MAX_CV_FOLDS),
        default=5,
        help="folds of the cross-validation that gates --terms and is reported "
        f"(0: none, and no term is kept; at most {MAX_CV_FOLDS}: each fold is a fit, all held at once)",
    )
    knob(
        p,
        "--identifiability-tol",
        type=_tolerance,
        default=None,
        metavar="TOL",
        help="threshold of the search for the parameters the data determine, in (0, 1): a parameter is freed "
        "only when its normalised Jacobian column lies farther than TOL from those freed before it; larger "
        "holds more (default: 1e-6 for single-joint sweeps with encoders, else 1e-3)",
    )
    if not demo:  # docs/fleet.md
        p.add_argument("--prior", metavar="FLEET_JSON", help=PRIOR_HELP)
    g = p.add_mutually_exclusive_group()
    g.add_argument(
        "--region",
        help="also certify the accuracy over this Cartesian box x0,y0,z0,x1,y1,z1 (m, base frame): "
        "report.md, the console and certificate.json (as jaxcal certify)",
    )
    g.add_argument("--joint-box", help="also certify over these joint ranges lo:hi,lo:hi,... (deg)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
