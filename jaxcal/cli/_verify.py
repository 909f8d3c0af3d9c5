"""`jaxcal verify RESULT DATASET`: a stop-and-shoot calibration against held-out samples (jaxcal.verification)."""

import json
import sys
from pathlib import Path

from rich.console import Console
from rich.table import Table

from ..io._files import atomic_file, write_text_atomic
from ._calibrate import MAX_CV_FOLDS
from ._certify import check_output
from ._common import count


def add_verify_parser(sub) -> None:
    p = sub.add_parser(
        "verify",
        help="a stop-and-shoot calibration's result against tracker samples it was not fitted on",
    )
    p.add_argument("result", help="the directory jaxcal calibrate wrote (or its result.json)")
    p.add_argument("dataset", help="a tracker dataset of the same robot and device")
    p.add_argument(
        "--cv",
        type=count(0, MAX_CV_FOLDS),
        default=0,
        help="also K-fold cross-validate on DATASET (K >= 2; 0: no)",
    )
    p.add_argument("--json", help="write the per-sample figures here (atomically)")
    p.add_argument("--plot", help="write a PNG: error per sample and histogram")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --json/--plot file")
    p.set_defaults(func=cmd_verify)


def cmd_verify(args) -> int:
    inputs = [args.result, args.dataset]
    check_output(args.json, inputs, args.overwrite, "--json")
    check_output(args.plot, inputs, args.overwrite, "--plot")
    result = Path(args.result)
    if result.name == "tree_result.json" or (
        (result / "calibrated.urdf").is_file() and not (result / "result.json").is_file()
    ):
        return _verify_tree(args)
    if args.cv == 1 or args.cv < 0:
        raise ValueError(f"--cv {args.cv}: give K >= 2 folds, or 0 for none")
    cv = f", with its {args.cv}-fold cross-validation" if args.cv else ""
    print(f"verifying {args.result} on {args.dataset}{cv} ...", file=sys.stderr, flush=True)
    from ..io.checks import verification_json  # after the line: the verification's modules take seconds
    from ..verification import plot_verification, verify

    v = verify(args.result, args.dataset, cv=args.cv)
    s = v.summary
    deg = s.calibrated_deg is not None
    console = Console(width=max(Console().width, 110))
    t = Table(title=f"jaxcal verify: {s.samples} samples of {v.dataset}")
    cols = ("mean mm", "RMS mm", "max mm") + (("mean deg", "RMS deg", "max deg") if deg else ())
    for col in ("model", *cols):
        t.add_column(col, justify="left" if col == "model" else "right")
    rows = [
        ("nominal robot in the fitted device frame", s.nominal_mm, s.nominal_deg),
        ("calibrated", s.calibrated_mm, s.calibrated_deg),
    ]
    for label, r, a in rows:
        t.add_row(
            label, *(f"{x:.4f}" for x in (r.mean, r.rms, r.max) + ((a.mean, a.rms, a.max) if deg else ()))
        )
    if v.cv is not None:
        c = v.cv
        t.add_row(
            f"{c.folds}-fold CV on this dataset",
            *(
                f"{x:.4f}"
                for x in (c.mean, c.rms, c.max) + ((c.mean_deg, c.rms_deg, c.max_deg) if deg else ())
            ),
        )
    console.print(t)
    console.print(
        f"predicted RMS {s.predicted_rms_mm:.4f} mm (parameters alone {s.parameter_part_rms_mm:.4f} mm): "
        f"measured / predicted {s.measured_over_predicted:.2f}; "
        f"{100 * s.inside_95_bound:.0f} % of the samples inside their predicted 95 % bound"
    )
    if deg:
        console.print(
            f"orientations: predicted RMS {s.predicted_rms_deg:.4f} deg, measured / predicted "
            f"{s.measured_over_predicted_deg:.2f}; {100 * s.inside_95_bound_deg:.0f} % inside their 95 % bound"
        )
    test = v.test
    verdict = "holds on this dataset" if test.holds else "does NOT hold on this dataset (exit 3)"
    console.print(
        f"the calibration {verdict}: whitened measured / predicted {test.ratio:.2f} (limit {test.ratio_limit:.2f}, "
        f"p = {test.p_value:.3g}), {100 * test.inside:.0f} % inside the 95 % bound (at least "
        f"{100 * test.inside_limit:.0f} %, p = {test.p_inside:.3g}); each test at {100 * test.alpha:g} %"
    )
    for n in v.notes:
        console.print(f"[yellow]note:[/yellow] {n}")
    if args.json:
        write_text_atomic(args.json, json.dumps(verification_json(v), indent=1))
        console.print(f"wrote {args.json}")
    if args.plot:
        with atomic_file(args.plot) as tmp:
            plot_verification(v, tmp)
        console.print(f"wrote {args.plot}")
    return v.exit_code


def _verify_tree(args) -> int:
    """A tree calibration's folder against a tree dataset of the same robot (`jaxcal.trees.verify_tree`)."""
    for flag, given in (("--cv", args.cv), ("--plot", args.plot)):
        if given:
            raise ValueError(f"{flag}: not available for a tree calibration ({args.result}); use --json")
    from ..io.tree_dataset import is_tree_dataset, load_tree_dataset
    from ..tree_verification import HOLDS_FACTOR, verify_tree

    if not is_tree_dataset(args.dataset):
        raise ValueError(
            f"{args.dataset}: {args.result} is a tree calibration; give a tree dataset (a folder with tree.json)"
        )
    v = verify_tree(args.result, load_tree_dataset(args.dataset))
    console = Console(width=max(Console().width, 110))
    t = Table(title=f"jaxcal verify: {args.result} on {args.dataset}")
    for col in ("tip", "samples", "calibrated mean mm", "RMS mm", "max mm", "robot file mean mm"):
        t.add_column(col, justify="left" if col == "tip" else "right")
    for tip, f in v["tips"].items():
        t.add_row(
            tip,
            str(f["samples"]),
            *(
                f"{f[k]:.4f}"
                for k in ("calibrated_mean_mm", "calibrated_rms_mm", "calibrated_max_mm", "nominal_mean_mm")
            ),
        )
    console.print(t)
    verdict = "holds on this dataset" if v["holds"] else "does NOT hold on this dataset (exit 3)"
    console.print(
        f"the calibration {verdict}: residuals {v['rms_per_axis_mm']:.4f} mm RMS per axis"
        + (" (each point weighed by its covariance)" if v["weighted_by_covariances"] else "")
        + " against the "
        f"{v['expected_mm']:.4f} mm it expects (its residual noise {v['fit_noise_mm']:.4f} mm"
        + ("" if v["parameters_mm"] is None else f", its parameters' uncertainty {v['parameters_mm']:.4f} mm")
        + f"; ratio {v['ratio']:.2f}, limit {HOLDS_FACTOR:g})"
    )
    for note in v["notes"]:
        console.print(f"[yellow]note:[/yellow] {note}")
    if args.json:
        write_text_atomic(args.json, json.dumps(v, indent=1))
        console.print(f"wrote {args.json}")
    return 0 if v["holds"] else 3
