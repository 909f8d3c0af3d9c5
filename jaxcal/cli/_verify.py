"""`jaxcal verify RESULT DATASET`: a stop-and-shoot calibration against held-out samples (jaxcal.verification)."""

import json

from rich.console import Console
from rich.table import Table

from ..io._files import atomic_file, write_text_atomic
from ..io.checks import verification_json
from ..verification import plot_verification, verify
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
    if args.cv == 1 or args.cv < 0:
        raise ValueError(f"--cv {args.cv}: give K >= 2 folds, or 0 for none")
    v = verify(args.result, args.dataset, cv=args.cv)
    s = v.summary
    console = Console(width=max(Console().width, 110))
    t = Table(title=f"jaxcal verify: {s.samples} samples of {v.dataset}")
    for col in ("model", "mean mm", "RMS mm", "max mm"):
        t.add_column(col, justify="left" if col == "model" else "right")
    for label, r in (("nominal", s.nominal_mm), ("calibrated", s.calibrated_mm)):
        t.add_row(label, *(f"{x:.4f}" for x in (r.mean, r.rms, r.max)))
    if v.cv is not None:
        t.add_row(
            f"{v.cv.folds}-fold CV on this dataset", *(f"{x:.4f}" for x in (v.cv.mean, v.cv.rms, v.cv.max))
        )
    console.print(t)
    console.print(
        f"predicted RMS {s.predicted_rms_mm:.4f} mm (parameters alone {s.parameter_part_rms_mm:.4f} mm): "
        f"measured / predicted {s.measured_over_predicted:.2f}; "
        f"{100 * s.inside_95_bound:.0f} % of the samples inside their predicted 95 % bound"
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
    return 0
