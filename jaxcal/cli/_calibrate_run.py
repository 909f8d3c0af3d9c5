"""The work of `jaxcal calibrate` and `jaxcal demo` (`._calibrate` holds their options and entry
points): run the pipeline, print its tables, write its files. Imported only when a command runs,
after the programs it will call have begun to load (`jaxcal._exported.warm_start`)."""

import json
import time
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

from .. import distributed
from .._exported import warm_start
from .._progress import working
from ..io._files import note_written, resolved, write_text_atomic
from ..io.tree_dataset import load_tree_dataset
from ..pipeline import calibrate
from ..report import certificate_section, output_files, warm_up_plots, write_outputs
from ..robots import load_robot
from ..summary import (
    TextTable,
    clock_line,
    fmt,
    joints_table,
    refinement_line,
    terms_tables,
    truth_line,
    truth_table,
)
from ..trees import calibrate_tree, save_tree_calibration, unmeasured_tips
from ._common import EYE_IN_HAND_BOARD_M, EYE_IN_HAND_SWEEP, LINKS_AMPLITUDE_DEG, fmt_degrees, run_record
from ._rosbag import dataset_of


def _point_fit_table(console, result) -> None:
    pf = result.point_fit
    fitted = result.frames.used("poses")
    t = Table(
        title=f"Point fit ({fitted}{'' if fitted == pf.poses else f' of {pf.poses}'} stop-and-shoot poses)"
    )
    deg = pf.residual_deg is not None
    cols = ("CV mean mm", "CV RMS mm", "CV max mm") + (
        ("CV mean deg", "CV RMS deg", "CV max deg") if deg else ()
    )
    for col in ("model", "free parameters", *cols, "kept"):
        t.add_column(col, justify="left" if col == "model" else "right")
    for m in pf.models:
        values = (m.cv_mean_mm, m.cv_rms_mm, m.cv_max_mm) + (
            (m.cv_mean_deg, m.cv_rms_deg, m.cv_max_deg) if deg else ()
        )
        cv = [fmt(x, ".4f") if x is not None else "-" for x in values]
        t.add_row("+".join(["geometric", *m.terms]), str(m.free), *cv, "yes" if m.kept else "")
    console.print(t)
    r, a = pf.residual_mm, pf.residual_deg
    rotation = (
        "" if a is None else f"; orientations {a.mean:.4f} deg mean, {a.rms:.4f} deg RMS, {a.max:.4f} deg max"
    )
    console.print(
        f"fitted residual {r.mean:.4f} mm mean, {r.rms:.4f} mm RMS, {r.max:.4f} mm max{rotation} (scatter "
        f"{pf.robust_scale:.2f} x the samples' sigma); held at nominal: {len(pf.held)} parameters"
        + (f", {len(pf.unseen)} of them unseen by the samples" if pf.unseen else "")
    )
    if pf.outliers:
        console.print(f"rejected by the robust fit ({len(pf.outliers)} of {pf.poses} poses):")
        for o in pf.outliers:
            console.print(
                f"  sample {o.sample} ({o.line}): {o.distance_mm:.3f} mm from the calibrated model, "
                f"{o.radius:.1f} robust sigmas"
            )
    for row in pf.term_rows:
        if row.free:
            console.print(f"  {row.name} = {row.estimate:.6g} +- {row.std:.2g}")


def _calibration_tables(console, result) -> None:
    if result.point_fit is not None:
        _point_fit_table(console, result)
    if result.arcs:
        _sweeps_table(console, result)
    _result_tables(console, result)


def _rich(table: TextTable) -> Table:
    t = Table(title=table.title)
    for k, col in enumerate(table.header):
        t.add_column(col, justify="left" if k == 0 else "right")
    for row in table.rows:
        t.add_row(*row)
    return t


def _sweeps_table(console, result) -> None:
    console.print(_rich(joints_table(result)))
    f = result.frames
    lost = {
        "without a target (out of view, turned away or blurred)": f.no_target,
        "outside the encoder log": f.outside_encoder_log,
        "in no single-joint sweep": f.not_in_a_sweep,
    }
    if any(lost.values()):  # why a joint's row counts fewer frames than it was filmed in
        console.print(
            f"frames: {f.images} images, the target found in {f.target_found}; "
            + ", ".join(f"{n} {why}" for why, n in lost.items() if n)
        )


def _result_tables(console, result) -> None:
    v = result.validation
    T, sd = result.T_cam_base, result.std_cam
    if result.eye_in_hand:
        Tf = result.T_flange_target[0]
        console.print(
            f"eye-in-hand: T_flange_cam t = {np.round(Tf[:3, 3] * 1e3, 2).tolist()} mm; the board "
            f"{result.board} relative to the base:"
        )
    console.print(
        f"{result.kind.fixed_frame}: t = {np.round(T[:3, 3] * 1e3, 2).tolist()} mm "
        f"(std {np.round(sd[:3] * 1e3, 3).tolist()} mm, {np.round(np.degrees(sd[3:]), 4).tolist()} deg)"
    )
    errs = {e.camera: e for e in (v.other_cameras or ())} if v is not None else {}
    for oc in result.other_cameras:
        To, so = oc.T_cam_base, oc.std_cam
        line = (
            f"T_cam_base of {oc.camera} ({oc.views} views): t = {np.round(To[:3, 3] * 1e3, 2).tolist()} mm "
            f"(std {np.round(so[:3] * 1e3, 3).tolist()} mm, {np.round(np.degrees(so[3:]), 4).tolist()} deg)"
        )
        if oc.camera in errs:
            e = errs[oc.camera]
            line += (
                f"; pose relative to {result.camera} off the truth by {e.refined.trans_mm:.3f} mm, "
                f"{e.refined.rot_deg:.4f} deg (PnP start {e.start.trans_mm:.3f} mm)"
            )
        console.print(line)
    if result.kind.images or result.clock.estimated:  # tracker samples carry their own joint positions
        console.print(clock_line(result))
    console.print(
        f"held at nominal (the {result.kind.sensor} cannot see them): "
        f"{len(result.frozen)} parameters, see report.md"
    )
    table = truth_table(result)
    if table is not None:
        console.print(_rich(table))
        line = truth_line(result)
        if line is not None:
            console.print(line)
    if result.refinement is not None:
        console.print(f"refinement: {refinement_line(result)}")
    if result.point_fit is None:  # a point fit's terms are in its own table
        for table in terms_tables(result):
            console.print(_rich(table))
        for n in result.terms.notes if result.terms is not None else ():
            console.print(f"[yellow]note:[/yellow] {n}")
    for w in result.warnings:
        console.print(f"[yellow]note:[/yellow] {w}")


#: Exit codes of `jaxcal calibrate` / `demo` by result status (2: bad input, before any result).
EXIT_CODES = {"ok": 0, "failed": 1, "suspect": 3}


def _plots_expected(dataset) -> bool:
    """Whether the result will have plots: a capture of images (arcs) or a simulated dataset (the
    errors against its truth); a measuring device's samples without a truth have none."""
    root = Path(dataset)
    return not (root / "samples.csv").is_file() or (root / "truth.json").is_file()


def _run_calibration(console, dataset, out: Path, args, *, overwrite: bool, checked=None) -> int:
    # While it calibrates, matplotlib loads where it will plot (the caller reads the programs ahead).
    plots = warm_up_plots() if _plots_expected(dataset) else None
    code = _calibrate_and_write(console, dataset, out, args, overwrite=overwrite, checked=checked)
    if plots is not None:
        plots.join()
    return code


def calibrate_fleet_datasets(args, datasets: list, out: Path, checked) -> int:
    """`jaxcal calibrate DS1 DS2 ...` (or a folder of datasets): every unit calibrated in this
    process and written into `out/<unit>/`, then the fleet's summary (`jaxcal.fleet`)."""
    from ..fleet import calibrate_fleet, fleet_datasets

    console = Console(width=max(Console().width, 132))
    units, run, processes = fleet_datasets(datasets), run_record(args), distributed.current()
    tag = f"(process {processes.index} of {processes.count}) " if processes.count > 1 else ""
    say = (lambda text: None) if args.quiet else (lambda text: console.print(tag + text, highlight=False))
    if processes.first:
        say(f"{len(units)} units: {', '.join(u.name for u in units[:8])}{' ...' if len(units) > 8 else ''}")
    started = []

    def one(path):
        first = not started  # its compiles (the first run only) show their progress; the rest are quick
        started.append(path)
        return calibrate(path, progress=first and not args.quiet, **_options(args))

    def write(result, folder):
        write_outputs(result, folder, inputs=[result.dataset], run=run)

    summary = calibrate_fleet(
        datasets,  # expanded again there, as named (a unit without metadata.json is refused, not expanded)
        out,
        calibrate=one,
        write=write,
        overwrite=args.overwrite,
        checked=checked,
        strict=args.strict,
        say=say,
        processes=processes,
    )
    if not processes.first:
        return summary.exit_code
    for o in summary.outliers[:10]:
        console.print(
            f"[yellow]stands out:[/yellow] {o.unit} {o.parameter} {o.z:+.1f} robust spreads from the fleet"
        )
    counts = ", ".join(
        f"{sum(u.status == k for u in summary.units)} {k}" for k in ("ok", "suspect", "failed", "refused")
    )
    console.print(
        f"wrote {out}/: one folder per calibrated unit, fleet.json, fleet.md ({counts}; "
        f"{_standing_out(summary)}{'; ' + summary.note if summary.note else ''}; "
        f"{summary.timings_s['total']:.1f} s)"
    )
    return summary.exit_code


def _standing_out(summary) -> str:
    """`N unit(s) stand out (M figure(s))`: the units the summary names, and in how many parameters
    or residuals."""
    units = len({o.unit for o in summary.outliers})
    return f"{units} unit{'' if units == 1 else 's'} standing out" + (
        f" ({len(summary.outliers)} figure{'' if len(summary.outliers) == 1 else 's'})" if units else ""
    )


def calibrate_dataset(args, out: Path, checked) -> int:
    """`jaxcal calibrate`'s work, inside its lock on --out: DATASET (or its bag, imported) calibrated
    and written."""
    console = Console(width=max(Console().width, 132))
    with dataset_of(args, say=lambda text: console.print(f"[dim]{text}[/dim]")) as dataset:
        return _run_calibration(console, dataset, out, args, overwrite=args.overwrite, checked=checked)


def _options(args) -> dict:
    """`jaxcal.calibrate`'s keywords from the command line's options."""
    return dict(
        camera=args.camera,
        workers=args.workers,
        clock=args.clock,
        refine_intrinsics=args.refine_intrinsics,
        estimate_line_delay=getattr(args, "estimate_line_delay", False),
        refine=not args.no_refine,
        other_cameras=not args.single_camera,
        arc_loss=None if args.arc_loss == "none" else args.arc_loss,
        device_is_base=getattr(args, "device_is_base", False),
        terms=args.terms,
        cv_folds=args.cv_folds,
        identifiability_tol=args.identifiability_tol,
        prior=getattr(args, "prior", None),
    )


def _calibrate_and_write(console, dataset, out: Path, args, *, overwrite: bool, checked=None) -> int:
    t0 = time.perf_counter()
    result = calibrate(
        dataset,
        progress=not args.quiet,
        log=lambda text: console.print(f"[dim]{text}[/dim]"),
        **_options(args),
    )
    _calibration_tables(console, result)
    code = EXIT_CODES[result.status]
    for reason in result.reasons:
        console.print(f"[red]{result.status}:[/red] {reason}")
    for note in result.verdict.notes if result.verdict is not None else ():
        console.print(f"[yellow]verdict note:[/yellow] {note}")
    if args.strict and code != 0:
        console.print(f"[red]--strict: the calibration is {result.status}; nothing written[/red]")
        return code
    # The DH tables' Jacobian and the plots: seconds the first time.
    with working(not args.quiet, f"writing {out}", say=lambda text: console.print(f"[dim]{text}[/dim]")):
        write_outputs(
            result, out, overwrite=overwrite, inputs=[dataset], checked=checked, run=run_record(args)
        )
    extra = _certificate(console, out, args)
    console.print(
        f"wrote {out}/: {', '.join(output_files(result) + extra)}, report.md ({time.perf_counter() - t0:.1f} s)"
    )
    if code:
        console.print(
            f"[red]calibration {result.status.upper()}: see the reasons above and result.json 'status'[/red]"
        )
    else:
        noted = result.verdict.notes if result.verdict is not None else ()
        console.print(
            "[green]calibration ok[/green]: every check passed (result.json 'status')"
            + (f"; {len(noted)} verdict note(s) above (result.json 'notes')" if noted else "")
        )
    return code


def _certificate(console, out: Path, args) -> list[str]:
    """With `--region` / `--joint-box`: the accuracy certificate over it, on the console, in
    `report.md` and `certificate.json` (the files written)."""
    if not (getattr(args, "region", None) or getattr(args, "joint_box", None)):
        return []
    # Imported only here: a calibration without a certificate does not load its modules.
    from ..certification import certify
    from ..io.checks import certificate_json
    from ._certify import print_certificate, region_of

    c = certify(out, **region_of(args))
    print_certificate(console, c)
    write_text_atomic(out / "certificate.json", json.dumps(certificate_json(c), indent=1))
    note_written(out, "certificate.json")
    report = out / "report.md"
    text = report.read_text()
    head, sep, tail = text.partition("\n## Plots")
    write_text_atomic(report, head + "\n".join(certificate_section(c)) + sep + tail)
    return ["certificate.json"]


def demo(out: Path, args) -> int:
    """`jaxcal demo`'s work, inside its --out directory: render, calibrate, write."""
    from ..sim.simulate import SimConfig, simulate

    console = Console(width=max(Console().width, 132))  # its first line is `cmd_demo`'s
    sweep = (
        args.sweep_deg if args.sweep_deg is not None else (EYE_IN_HAND_SWEEP if args.eye_in_hand else 80.0)
    )
    config = SimConfig(
        robot="ur5e",
        seed=args.seed,
        resolution=args.resolution,
        frames_per_joint=args.frames_per_joint,
        range_deg=sweep,
        clock_offset_ms=40.0,
        clock_known=False,
        cameras=args.cameras,
        eye_in_hand=args.eye_in_hand,
        camera_distance=EYE_IN_HAND_BOARD_M if args.eye_in_hand else 0.9,
        markers_on_links=args.markers_on_links,
        camera=args.camera_model,
        arm=args.arm,
    )
    trajectory = None
    what = f"{args.frames_per_joint} frames per {fmt_degrees(sweep)}-degree sweep" + (
        "" if np.ndim(sweep) == 0 else "s"
    )
    if args.markers_on_links:
        from ..sim.motion import random_motion

        names = load_robot("ur5e").joint_names
        seconds = args.frames_per_joint * len(names) / config.fps
        trajectory = random_motion(names, seconds, LINKS_AMPLITUDE_DEG, seed=args.seed)
        what = (
            f"every joint at once, +-{LINKS_AMPLITUDE_DEG:g} deg, {seconds:g} s at {config.fps:g} fps, "
            "a plate on every link"
        )
    t0 = time.perf_counter()
    dataset = simulate(
        config, out / "dataset", trajectory=trajectory, overwrite=True, progress=not args.quiet
    )
    console.print(
        f"rendered {dataset} ({args.resolution[0]}x{args.resolution[1]}, {what}, "
        + ("camera on the flange, board in the world, " if args.eye_in_hand else "")
        + f"clock offset 40 ms, not given to the calibration) in {time.perf_counter() - t0:.1f} s"
    )
    # The programs the last demo with this dataset called are read ahead while it calibrates.
    with warm_start(f"jaxcal calibrate {resolved(dataset)}"):
        return _run_calibration(console, dataset, out / "result", args, overwrite=True)


def calibrate_tree_dataset(args, out: Path, checked) -> int:
    """`jaxcal calibrate` on a tree dataset (`tree.json`: `jaxcal.trees`): the tree calibrated from
    its tips' points and written into `out` (calibrated.urdf, tree_result.json, a table per tip)."""
    console = Console(width=max(Console().width, 132))
    t0 = time.perf_counter()
    ds = load_tree_dataset(args.dataset)
    result = calibrate_tree(
        ds.tree,
        ds.samples,
        noise_mm=None if ds.samples.covariance is not None else ds.noise_mm,
        families=ds.families,
        points=ds.points,
        limits=ds.limits,
        device_on=ds.device_on,
        show_progress=not args.quiet,
    )
    held = ", ".join(f"{len(v)} {k}" for k, v in result.held.items())
    seen = [t for t, s in zip(ds.tree.tip_names, ds.samples.measured.any(axis=0)) if s and t != ds.device_on]
    console.print(
        f"{len(ds.samples.q)} poses measuring {', '.join(seen)}: residual noise {result.fit.noise_mm:.4f} mm "
        f"(stated {ds.noise_mm:.4g}{', the covariances RMS' if ds.samples.covariance is not None else ''}); terms kept: {', '.join(result.fit.families) or 'none'}; "
        f"{int(result.fit.free.sum())} parameters freed, held ({held})"
    )
    if ds.truth is not None and "test" in ds.truth:
        test = np.asarray(ds.truth["test"]["points_m"])
        measured = [k for k, t in enumerate(ds.tree.tip_names) if t != ds.device_on]
        error = np.linalg.norm((result.predict(ds.truth["test"]["q"]) - test)[:, measured], axis=-1).mean()
        console.print(
            f"against the simulator's truth: {1e3 * error:.4f} mm mean over {len(test)} held-out poses"
        )
    for note in result.notes:
        console.print(f"[yellow]{result.status}:[/yellow] {note}")
    if args.strict and result.status != "ok":
        console.print(f"[red]--strict: the calibration is {result.status}; nothing written[/red]")
        return EXIT_CODES[result.status]
    save_tree_calibration(
        result, out, source_urdf=ds.urdf, overwrite=args.overwrite, inputs=(ds.folder,), checked=checked
    )
    console.print(
        f"wrote {out}/: calibrated.urdf, tree_result.json, tree_covariance.json, "
        + ", ".join(f"{t}_mdh.json" for t in ds.tree.tip_names)
        + f" ({time.perf_counter() - t0:.1f} s); calibration {result.status}"
    )
    unseen = unmeasured_tips(result)
    if unseen:
        console.print(
            f"[yellow]note:[/yellow] {', '.join(f'{t}_mdh.json' for t in unseen)}: tip(s) never measured, their "
            "tables hold the robot file's values (their 'held' list)"
        )
    return EXIT_CODES[result.status]
