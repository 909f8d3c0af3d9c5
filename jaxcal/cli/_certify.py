"""`jaxcal certify RESULT` (jaxcal.certification) and `jaxcal check RESULT CAPTURE` (jaxcal.drift)."""

import importlib
import json
import sys
from pathlib import Path

import numpy as np
from rich.console import Console

from .._configkeys import knob
from .._progress import working
from ..io._files import atomic_file, check_output_file, resolved, write_text_atomic
from ._common import MAX_WORKERS, count, seed

#: `jaxcal.certification.MAX_POSES`, here so that the parser imports no JAX (a test keeps them equal).
MAX_POSES = 100_000


def check(*args, **kwargs):
    """`jaxcal.drift.check`, imported when `jaxcal check` runs: `jaxcal calibrate` imports
    this module for its certificate, and `jaxcal.drift` (SciPy's statistics) is not light."""
    return importlib.import_module("jaxcal.drift").check(*args, **kwargs)


def check_output(path: str | None, inputs: list[str], overwrite: bool, what: str) -> None:
    """Refuse, before any work, an output file in an input, existing without `overwrite`, or in a
    folder that does not exist (`jaxcal.io._files.check_output_file`)."""
    check_output_file(path, inputs=inputs, overwrite=overwrite, what=what)


def _floats(text: str, n: int | None = None) -> list[float]:
    try:
        v = [float(s) for s in text.replace(" ", "").split(",") if s]
    except ValueError:
        raise ValueError(f"--region {text!r}: give comma-separated numbers") from None
    if n is not None and len(v) != n:
        raise ValueError(f"--region {text!r}: give {n} comma-separated numbers, got {len(v)}")
    if not np.all(np.isfinite(v)):
        raise ValueError(f"--region {text!r}: give finite numbers")
    return v


def _joint_box(text: str) -> np.ndarray:
    """`lo:hi,lo:hi,...` per joint (deg for every joint; a prismatic joint's in mm)."""
    try:
        rows = [[float(a) for a in part.split(":")] for part in text.replace(" ", "").split(",")]
    except ValueError:
        raise ValueError(f"--joint-box {text!r}: give lo:hi per joint, comma-separated (deg)") from None
    if any(len(r) != 2 for r in rows) or not np.all(np.isfinite(rows)):
        raise ValueError(f"--joint-box {text!r}: give lo:hi per joint, comma-separated (deg, finite)")
    return np.radians(np.asarray(rows, np.float64))


def add_certify_parsers(sub) -> None:
    p = sub.add_parser(
        "certify",
        help="the tool-point accuracy a calibration supports over a task region (mean, 95 %%, worst pose, map)",
    )
    p.add_argument("result", help="the directory jaxcal calibrate wrote (or its result.json)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--region", help="Cartesian box x0,y0,z0,x1,y1,z1 (m, base frame) the tool point works in")
    g.add_argument("--joint-box", help="joint ranges lo:hi,lo:hi,... (deg), one per joint")
    g.add_argument(
        "--poses", help="CSV of configurations: a header naming the joints, or one column per joint"
    )
    knob(p, "--degrees", action="store_true", help="--poses are in degrees (else rad)")
    knob(
        p,
        "--samples",
        type=count(1, MAX_POSES),
        default=1000,
        help=f"configurations drawn in a box, at most {MAX_POSES:,}",
    )
    knob(p, "--seed", type=seed, default=0, help="seed of the configurations drawn")
    knob(
        p,
        "--frame",
        choices=("fixed", "base"),
        default="fixed",
        help="the error in the camera's / device's frame, or in the base frame (its uncertainty left out)",
    )
    p.add_argument("--json", help="write the certificate here, every pose included (atomically)")
    p.add_argument("--plot", help="write a PNG map of the region's 95 %% bounds")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --json/--plot file")
    p.set_defaults(func=cmd_certify)
    p = sub.add_parser(
        "check",
        help="a short later capture against a calibration: has the device or camera moved? (exit 3 when it has)",
    )
    p.add_argument(
        "result", help="the directory jaxcal calibrate (or jaxcal handeye) wrote, or its result.json"
    )
    p.add_argument(
        "capture",
        help="a short capture of the same robot: tracker samples of the same device and point, or a few images "
        "(~10, at known joint positions: an encoder log) of the calibrated camera and target; for a hand-eye "
        "result, a hand-eye capture (handeye.json, poses.csv, images) of the same camera and target",
    )
    p.add_argument("--joint-offsets", action="store_true", help="also free the joints' zero offsets")
    p.add_argument(
        "--workers",
        type=count(1, MAX_WORKERS),
        help=f"threads detecting the images (default: every core; at most {MAX_WORKERS})",
    )
    p.add_argument("--json", help="write the check's figures here (atomically)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --json file")
    p.set_defaults(func=cmd_check)


def _write_plot(c, path: str) -> None:
    from ..certification import plot_certificate

    with atomic_file(path) as tmp:
        plot_certificate(c, tmp)


def print_certificate(console, c) -> None:
    """The certificate's summary, extrapolation, caveats and notes on the console."""
    s = c.summary
    console.print(
        f"jaxcal certify: {c.kind} result {c.result}, region {c.region.kind} ({s.poses} poses), "
        f"tool point in the {c.frame} frame"
    )
    console.print(
        f"predicted error: mean {s.mean_mm:.4f} mm, RMS {s.rms_mm:.4f} mm, 95 % of the region within "
        f"{s.p95_mm:.4f} mm; worst pose: 95 % bound {s.max_bound95_mm:.4f} mm at q = "
        f"[{', '.join(f'{np.degrees(v):.1f}' for v in s.worst.q)}] deg"
    )
    r = c.rotation
    if r is not None:
        console.print(
            f"predicted orientation error: mean {r.mean_deg:.4f} deg, RMS {r.rms_deg:.4f} deg, 95 % of the region "
            f"within {r.p95_deg:.4f} deg; largest 95 % bound {r.max_bound95_deg:.4f} deg"
        )
    e = c.extrapolation
    if e is not None:
        console.print(
            f"calibrated workspace: {100 * e.share_of_poses_outside_joint_ranges:.0f} % of the poses outside its "
            f"joint ranges (up to {np.degrees(e.max_joint_excess):.1f} deg), predicted error "
            f"{e.error_ratio:.2f}x that over the calibrated configurations ({e.calibrated_rms_mm:.4f} mm RMS)"
        )
    for w in c.caveats:
        console.print(f"[yellow]caveat:[/yellow] {w}")
    for n in c.notes:
        console.print(f"[yellow]note:[/yellow] {n}")


def region_of(args) -> dict:
    """`certify`'s region keywords from `--region` / `--joint-box` (either may be absent)."""
    return {
        "region": _floats(args.region, 6) if getattr(args, "region", None) else None,
        "joint_box": _joint_box(args.joint_box) if getattr(args, "joint_box", None) else None,
    }


def _is_tree_result(path: str) -> bool:
    p = Path(path)
    return p.name == "tree_result.json" or (p / "tree_result.json").is_file()


#: How far (rad, or m) a pose to certify may lie beyond its joint's limits before it is refused.
BEYOND_LIMITS = 0.1


def _within_travel(path: str, q: np.ndarray, pred, degrees: bool) -> None:
    """Refuse poses beyond the joints' limits (by `BEYOND_LIMITS`): a file in the other unit."""
    lo, hi = pred.travel[:, 0] - BEYOND_LIMITS, pred.travel[:, 1] + BEYOND_LIMITS
    out = (q < lo) | (q > hi)
    if out.any():
        i, j = np.argwhere(out)[0]
        hint = "check the file's columns and unit" if degrees else "degrees? give --config degrees=true"
        raise ValueError(
            f"{path}: configuration {i + 1}, joint {pred.joint_names[j]!r} at {q[i, j]:.4g} (rad or m) is beyond its "
            f"limits [{pred.travel[j, 0]:.4g}, {pred.travel[j, 1]:.4g}] ({out.any(axis=1).sum()} configurations): {hint}"
        )


def _certify_tree(args, where: dict) -> int:
    """`jaxcal certify` of a tree calibration: a certificate per measured tip (its device's frame)."""
    if args.plot or args.frame != "fixed":
        raise ValueError(
            f"{'--plot' if args.plot else '--frame base'}: not available for a tree calibration ({args.result}); "
            "each tip is certified in the device's frame, --json writes the figures"
        )
    say = f"certifying {args.result}'s tips"
    print(f"{say} ...", file=sys.stderr, flush=True)
    with working(True, say, stream=sys.stderr):
        from ..certification import certify, read_poses
        from ..tree_verification import tip_predictors

        tips = tip_predictors(args.result)
        names = next(iter(tips.values())).joint_names
        poses = None if not args.poses else read_poses(args.poses, names, degrees=args.degrees)
        if poses is not None:
            _within_travel(args.poses, poses, next(iter(tips.values())), args.degrees)
        certs = {
            tip: certify(pred, **where, poses=poses, samples=args.samples, seed=args.seed)
            for tip, pred in tips.items()
        }
    console = Console(width=max(Console().width, 110))
    for c in certs.values():
        print_certificate(console, c)
    if args.json:
        from ..io.checks import certificate_json

        doc = {"tips": {tip: certificate_json(c) for tip, c in certs.items()}}
        write_text_atomic(args.json, json.dumps(doc, indent=1))
        console.print(f"wrote {args.json}")
    return 0


def cmd_certify(args) -> int:
    for opt, what in ((args.json, "--json"), (args.plot, "--plot")):
        check_output(opt, [args.result], args.overwrite, what)
    where = region_of(args)
    if _is_tree_result(args.result):
        return _certify_tree(args, where)
    what = "its poses" if args.poses else "the region" if args.region or args.joint_box else "its workspace"
    say = f"certifying {args.result} over {what}"
    print(f"{say} ...", file=sys.stderr, flush=True)
    with working(True, say, stream=sys.stderr):
        from .._exported import warm_start  # JAX: after the first line
        from ..certification import certify, read_poses
        from ..io.checks import read_calibration

        poses = None
        if args.poses:
            names = read_calibration(args.result).joint_names
            poses = read_poses(args.poses, names, degrees=args.degrees)
        # The programs the last certificate of this result called are read while this one starts.
        with warm_start(f"jaxcal certify {resolved(args.result)}"):
            c = certify(
                args.result, **where, poses=poses, samples=args.samples, frame=args.frame, seed=args.seed
            )
    console = Console(width=max(Console().width, 110))
    print_certificate(console, c)
    if args.json:
        from ..io.checks import certificate_json

        write_text_atomic(args.json, json.dumps(certificate_json(c), indent=1))
        console.print(f"wrote {args.json}")
    if args.plot:
        _write_plot(c, args.plot)
        console.print(f"wrote {args.plot}")
    return 0


def _check_tree(args):
    """`jaxcal check` of a tree calibration on a tree dataset (`jaxcal.tree_verification.check_tree`)."""
    if args.joint_offsets:
        raise ValueError(f"--joint-offsets: not available for a tree calibration ({args.result})")
    from ..io.tree_dataset import is_tree_dataset, load_tree_dataset
    from ..tree_verification import check_tree

    if not is_tree_dataset(args.capture):
        raise ValueError(
            f"{args.capture}: {args.result} is a tree calibration; give a tree dataset (a folder with tree.json)"
        )
    return check_tree(args.result, load_tree_dataset(args.capture))


def cmd_check(args) -> int:
    check_output(args.json, [args.result, args.capture], args.overwrite, "--json")
    say = f"checking {args.capture} against {args.result}"
    print(f"{say} ...", file=sys.stderr, flush=True)
    with working(True, say, stream=sys.stderr):
        if _is_tree_result(args.result):
            c = _check_tree(args)
        else:
            c = check(args.result, args.capture, joint_offsets=args.joint_offsets, workers=args.workers)
    console = Console(width=max(Console().width, 110))
    colour = "red" if c.exit_code else "green"
    unit = "images" if c.what == "camera" else "samples"
    console.print(f"jaxcal check: {c.samples} {unit} of {c.capture} against {c.result}")
    console.print(f"[{colour}]{c.message}[/{colour}]")
    r = c.rotation_residual_deg
    if r is not None:
        console.print(
            f"orientations against the calibration's prediction (moved by the fitted drift): {r.mean:.4f} deg "
            f"mean, {r.rms:.4f} deg RMS, {r.max:.4f} deg max"
        )
    console.print(f"next: {c.advice}")
    if args.json:
        from ..io.checks import drift_check_json

        write_text_atomic(args.json, json.dumps(drift_check_json(c), indent=1))
        console.print(f"wrote {args.json}")
    return c.exit_code
