"""Command line: `jaxcal demo | calibrate | simulate | montecarlo | handeye | simulate-handeye`.

- `demo`: render a perturbed UR5e filming a ChArUco plate (MuJoCo), calibrate
  it from the images, print a before/after table, write the report.
- `calibrate DATASET --out DIR`: images -> calibrated robot, camera pose, report.
- `simulate`: render a synthetic dataset (see docs/dataset.md).
- `montecarlo`: vmapped sensitivity study on analytic marker poses.
- `handeye CAPTURE --out DIR`: classic hand-eye from a folder of images and robot poses.
- `simulate-handeye`: render a hand-eye capture (see docs/handeye.md).
"""

import argparse
import json
import sys
import time
from pathlib import Path

import jax
import numpy as np
import optimistix as optx
from rich.console import Console
from rich.table import Table

from . import _montecarlo as mc
from ._axisfit import parameter_names
from ._cache import enable_compilation_cache
from ._handeye_capture import calibrate_hand_eye_capture
from .io._files import check_output_dir, marked_directory, output_lock, write_text_atomic
from .io.dataset import load_dataset
from .io.handeye_results import static_transform_args, write_hand_eye_outputs
from .markers import TargetSpec
from .pipeline import calibrate
from .planning import load_plan
from .planning._cli import add_plan_parser, run_plan
from .report import write_outputs
from .robots import load_robot


def _write_json_atomic(path: Path, payload: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(path, json.dumps(payload, indent=2))


def _setup(args):
    noise = mc.NoiseModel(
        position_mm=args.noise_mm, orientation_deg=args.noise_deg, encoder_deg=args.encoder_noise_deg
    )
    plan = mc.SweepPlan(range_deg=args.sweep_deg, frames=args.frames)
    return mc.default_setup(load_robot(args.robot), noise=noise, plan=plan)


def _detailed_trial(setup, key, free):
    """One trial with everything kept (truth, arc fits, axis fit, errors), jitted whole."""

    @jax.jit
    def run(setup, key, free):
        k_truth, k_noise, k_val = jax.random.split(key, 3)
        true, T_cam_base, T_flange_marker = mc.draw_trial_truth(setup, k_truth)
        data = mc.trial_sweeps(setup, true, T_cam_base, T_flange_marker, k_noise)
        arcs, fit = mc.fit_sweeps(setup.nominal, data, free=free)
        q_val = jax.random.uniform(k_val, (1000, setup.nominal.num_joints), minval=-np.pi, maxval=np.pi)
        s = mc.score(fit, true, T_cam_base, T_flange_marker, setup.nominal, q_val)
        return true, T_cam_base, T_flange_marker, arcs, fit, s

    return run(setup, key, free)


def _single_trial_report(console, setup, seed: int) -> bool:

    setup = mc.dynamic_setup(setup)
    free = jax.jit(mc.nominal_free_mask)(setup)
    true, T_cam_base, T_flange_marker, arcs, fit, s = _detailed_trial(setup, jax.random.key(seed), free)
    t = Table(title="Arc fits (one per joint sweep)")
    for col in (
        "joint",
        "frames",
        "pos RMS mm",
        "rot RMS deg",
        "ratio true",
        "ratio est",
        "axis err deg",
        "solver",
    ):
        t.add_column(col, justify="right")
    arc_ok = np.asarray(arcs.result == optx.RESULTS.successful)
    for j, name in enumerate(setup.nominal.joint_names):
        code = "ok" if arc_ok[j] else "FAILED"
        t.add_row(
            name,
            str(int(arcs.num_frames[j])),
            f"{1e3 * float(arcs.position_rms[j]):.3f}",
            f"{np.degrees(float(arcs.rotation_rms[j])):.4f}",
            f"{float(true.reduction_ratio[j]):.3f}",
            f"{float(fit.model.reduction_ratio[j]):.3f}",
            f"{float(s['axis_dir_deg'][j]):.4f}",
            f"{code} ({int(arcs.num_steps[j])} steps)",
        )
    console.print(t)
    names = parameter_names(setup.nominal, 1)
    frozen = [n for n, f in zip(names, np.asarray(fit.free)) if not f]
    console.print(
        f"[bold]Identifiability:[/bold] {int(np.sum(fit.free))} of {len(names)} parameters estimated; "
        f"held at nominal (the camera cannot see them): {', '.join(frozen)}"
    )
    t = Table(title="Before / after (tool point in the camera frame, 1000 random configurations)")
    t.add_column("")
    t.add_column("nominal model", justify="right")
    t.add_column("calibrated", justify="right")
    t.add_row("EE RMS mm", f"{float(s['ee_rms_mm_nominal']):.3f}", f"{float(s['ee_rms_mm']):.4f}")
    t.add_row("EE max mm", "", f"{float(s['ee_max_mm']):.4f}")
    console.print(t)
    T = np.asarray(fit.T_cam_base)
    sd = np.asarray(fit.std[:6])
    console.print(
        f"T_cam_base: t = {np.round(T[:3, 3] * 1e3, 2).tolist()} mm "
        f"(std {np.round(sd[:3] * 1e3, 3).tolist()} mm, {np.round(np.degrees(sd[3:]), 4).tolist()} deg)"
    )
    ok = bool(fit.result == optx.RESULTS.successful) and bool(arc_ok.all())
    console.print(
        f"Axis fit: {'ok' if ok else 'FAILED'} in {int(fit.num_steps)} steps, residual RMS {float(fit.residual_rms):.3f}"
    )
    return ok


def _summary_table(console, summary: dict, title: str):
    t = Table(title=title)
    t.add_column("metric")
    t.add_column("value", justify="right")
    for k, v in summary.items():
        t.add_row(k, f"{v:.4g}" if isinstance(v, float) else str(v))
    console.print(t)


def cmd_montecarlo(args) -> int:

    setup = _setup(args)
    ok = True
    if args.detail:
        console = Console(width=max(Console().width, 132))
        console.rule("[bold]One trial in detail: UR5e, joint-by-joint sweeps, analytic marker poses")
        t0 = time.perf_counter()
        ok = _single_trial_report(console, setup, args.seed)
        console.print(f"(single trial incl. compilation: {time.perf_counter() - t0:.1f} s)")
    else:
        console = Console(stderr=True)
    t0 = time.perf_counter()
    result = mc.monte_carlo(setup, jax.random.key(args.seed), args.trials, chunk=args.chunk)
    jax.block_until_ready(result)
    summary = mc.summarize(result) | {"seconds": time.perf_counter() - t0}
    _summary_table(console, summary, f"Monte Carlo: {args.trials} trials in one jit call")
    if args.json:
        _write_json_atomic(Path(args.json), summary)
    ok = ok and summary["success_rate"] == 1.0 if args.detail else summary["success_rate"] > 0
    return 0 if ok else 1


def _positive_int(text: str) -> int:
    """An argparse type: an integer >= 1."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return v


def _calibration_tables(console, result) -> None:
    t = Table(title=f"Joint sweeps (camera {result.camera})")
    for col in (
        "joint",
        "frames",
        "pos RMS mm",
        "rot RMS deg",
        "ratio nominal",
        "ratio est",
        "std",
        "solver",
    ):
        t.add_column(col, justify="right")
    v = result.validation
    if v is not None:
        t.add_column("ratio true", justify="right")
        t.add_column("axis err deg", justify="right")
    for k, a in enumerate(result.arcs):
        row = [
            a["joint"],
            str(a["frames"]),
            f"{a['position_rms_mm']:.3f}",
            f"{a['rotation_rms_deg']:.3f}",
            f"{a['ratio_nominal']:.3f}",
            "n/a" if a["ratio"] is None else f"{a['ratio']:.3f}",
            "n/a" if a["ratio_std"] is None else f"{a['ratio_std']:.3f}",
            f"{a['solver']['result']} ({a['solver']['steps']})",
        ]
        if v is not None:
            e = v["parameter_errors"][a["joint"]]
            row += [f"{v['true_ratios'][k]:.3f}", f"{e['axis_direction_deg']:.3f}"]
        t.add_row(*row)
    console.print(t)
    T, sd = result.T_cam_base, result.std_cam
    if result.eye_in_hand:
        Tf = result.T_flange_target[0]
        console.print(
            f"eye-in-hand: T_flange_cam t = {np.round(Tf[:3, 3] * 1e3, 2).tolist()} mm; the board "
            f"{result.board} relative to the base:"
        )
    console.print(
        f"{'T_board_base' if result.eye_in_hand else 'T_cam_base'}: t = {np.round(T[:3, 3] * 1e3, 2).tolist()} mm "
        f"(std {np.round(sd[:3] * 1e3, 3).tolist()} mm, {np.round(np.degrees(sd[3:]), 4).tolist()} deg)"
    )
    errs = (v or {}).get("other_cameras", {})
    for oc in result.other_cameras:
        To, so = oc["T_cam_base"], oc["std_cam"]
        line = (
            f"T_cam_base of {oc['camera']} ({oc['views']} views): t = {np.round(To[:3, 3] * 1e3, 2).tolist()} mm "
            f"(std {np.round(so[:3] * 1e3, 3).tolist()} mm, {np.round(np.degrees(so[3:]), 4).tolist()} deg)"
        )
        if oc["camera"] in errs:
            e = errs[oc["camera"]]
            line += (
                f"; pose relative to {result.camera} off the truth by {e['refined']['trans_mm']:.3f} mm, "
                f"{e['refined']['rot_deg']:.4f} deg (PnP start {e['start']['trans_mm']:.3f} mm)"
            )
        console.print(line)
    c = result.clock
    console.print(
        f"clock offset: {1e3 * c['offset_s']:.2f} ms"
        + (f" (estimated, std {1e3 * c['std_s']:.2f} ms)" if c["estimated"] else " (from the metadata)")
    )
    console.print(
        f"held at nominal (the camera cannot see them): {len(result.frozen)} parameters, see report.md"
    )
    if v is not None:
        t = Table(title=f"Before / after, against the truth ({v['ee_point']}, 1000 random configurations)")
        t.add_column("")
        t.add_column("nominal model", justify="right")
        refined = bool(v.get("refined"))
        if refined:
            t.add_column("two-stage", justify="right")
        t.add_column("refined" if refined else "calibrated", justify="right")

        def row(label, before, key):
            cells = [label, before] + ([f"{v[key + '_two_stage']:.3f}"] if refined else [])
            t.add_row(*cells, f"{v[key + '_after']:.3f}")

        row("EE RMS mm", f"{v['ee_rms_mm_before']:.3f}", "ee_rms_mm")
        row("EE max mm", f"{v['ee_max_mm_before']:.3f}", "ee_max_mm")
        pad = [""] if refined else []
        ce = v["T_cam_base_error"]
        t.add_row(
            f"{'T_board_base' if result.eye_in_hand else 'T_cam_base'} error",
            "",
            *pad,
            f"{ce['trans_mm']:.3f} mm, {ce['rot_deg']:.4f} deg",
        )
        ratio = [
            abs(e["ratio_percent"]) for e in v["parameter_errors"].values() if e["ratio_percent"] is not None
        ]
        if ratio:
            t.add_row("max ratio error %", "", *pad, f"{max(ratio):.4f}")
        if v.get("clock_offset_error_ms") is not None and c["estimated"]:
            t.add_row("clock offset error ms", "", *pad, f"{v['clock_offset_error_ms']:.3f}")
        console.print(t)
    r = result.refinement
    if r is not None:
        console.print(
            f"refinement: {r['corners']} corners in {r['frames']} frames, {r['free_parameters']} parameters, "
            f"inlier RMS {r['inlier_rms_px']:.3f} px (sigma {r['sigma_px']:.3f} px), "
            f"{r['outlier_corners']} outlier corners, {r['solver']['result']} ({r['solver']['steps']} steps)"
        )
    for w in result.warnings:
        console.print(f"[yellow]note:[/yellow] {w}")


#: Exit codes of `jaxcal calibrate` / `demo` by result status (2: bad input, before any result).
EXIT_CODES = {"ok": 0, "failed": 1, "suspect": 3}


def _run_calibration(console, dataset, out: Path, args, *, overwrite: bool, checked=None) -> int:
    t0 = time.perf_counter()
    result = calibrate(
        dataset,
        camera=args.camera,
        workers=args.workers,
        progress=not args.quiet,
        estimate_clock=True if args.estimate_clock else None,
        trust_clock=args.trust_clock,
        refine_intrinsics=args.refine_intrinsics,
        refine=not args.no_refine,
        other_cameras=not args.single_camera,
        log=lambda text: console.print(f"[dim]{text}[/dim]"),
    )
    _calibration_tables(console, result)
    code = EXIT_CODES[result.status]
    for reason in result.reasons:
        console.print(f"[red]{result.status}:[/red] {reason}")
    if args.strict and code != 0:
        console.print(f"[red]--strict: the calibration is {result.status}; nothing written[/red]")
        return code
    write_outputs(result, out, overwrite=overwrite, inputs=[dataset], checked=checked)
    console.print(
        f"wrote {out}/: result.json, calibrated.urdf, "
        + "".join(f"camera_{c}.yaml, " for c in [result.camera] + [c["camera"] for c in result.other_cameras])
        + "report.md "
        f"({time.perf_counter() - t0:.1f} s)"
    )
    if code:
        console.print(
            f"[red]calibration {result.status.upper()}: see the reasons above and result.json 'status'[/red]"
        )
    return code


def cmd_calibrate(args) -> int:

    out = Path(args.out)
    # Before any work: --out may not hold or overlap the dataset, and --overwrite replaces
    # only a result jaxcal wrote; the lock makes a second run on the same --out fail at once.
    checked = check_output_dir(
        out, inputs=[args.dataset], overwrite=args.overwrite, kind="result", what="--out"
    )
    with output_lock(out, what="--out"):
        console = Console(width=max(Console().width, 132))
        return _run_calibration(console, args.dataset, out, args, overwrite=args.overwrite, checked=checked)


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
        return _demo(out, args)


def _demo(out: Path, args) -> int:
    from .sim.simulate import SimConfig, simulate

    console = Console(width=max(Console().width, 132))
    console.rule("[bold]jaxcal demo: a perturbed UR5e, rendered, calibrated from its images")
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
    )
    trajectory = None
    what = f"{args.frames_per_joint} frames per {_fmt_degrees(sweep)}-degree sweep" + (
        "" if np.ndim(sweep) == 0 else "s"
    )
    if args.markers_on_links:
        from .sim.motion import random_motion

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
    return _run_calibration(console, dataset, out / "result", args, overwrite=True)


def _add_calibrate_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--camera", help="fixed camera of the two-stage fit (default: the first)")
    p.add_argument(
        "--single-camera",
        action="store_true",
        help="refine with --camera's images only (by default every fixed camera joins the refinement, "
        "each with its own T_cam_base)",
    )
    p.add_argument(
        "--workers", type=_positive_int, help="processes for marker detection, >= 1 (default: all cores)"
    )
    p.add_argument(
        "--estimate-clock",
        action="store_true",
        help="estimate the clock offset (the default whenever there is an encoder log)",
    )
    p.add_argument(
        "--trust-clock",
        action="store_true",
        help="use metadata.json's clock offset as it is (by default it is checked against the estimate, "
        "which is used)",
    )
    p.add_argument(
        "--refine-intrinsics",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="free the camera's intrinsics in the refinement (default: when metadata.json has no K and "
        "they are self-calibrated from the sweep images)",
    )
    p.add_argument(
        "--strict",
        action="store_true",
        help="write nothing and exit 3 (1 if a solver failed) when a plausibility check fails",
    )
    p.add_argument(
        "--no-refine",
        action="store_true",
        help="stop at the two-stage result (arc + axis fits); by default every corner's reprojection "
        "error is then minimised over all parameters",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def _add_study_args(p: argparse.ArgumentParser, trials: int) -> None:
    p.add_argument("--robot", default="ur5e", help="shipped robot: ur5e or panda")
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


def _resolution(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"resolution must look like 640x480, got {text!r}") from None
    return w, h


def _degrees(text: str) -> float | tuple[float, ...]:
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


def _home(text: str) -> tuple[float, ...]:
    """One angle per joint, in degrees ("0,-20,30,-15,20,0")."""
    try:
        return tuple(float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"home must look like 0,-20,30,-15,20,0 (deg), got {text!r}"
        ) from None


def _fmt_degrees(v) -> str:
    return f"{v:g}" if np.ndim(v) == 0 else ",".join(f"{x:g}" for x in v)


#: The eye-in-hand demo's sweeps: the camera spins about its own axis with the
#: last joint, which keeps the board in view over a wide sweep (and pins that
#: axis, which passes near the camera, down); the others turn it away from the board.
EYE_IN_HAND_SWEEP = (40.0, 40.0, 40.0, 40.0, 40.0, 300.0)
#: ... and the board 0.6 m in front of the camera (at 0.9 m the EE error about triples).
EYE_IN_HAND_BOARD_M = 0.6
#: The markers-on-every-link demo's random motion, +- about zero.
LINKS_AMPLITUDE_DEG = 25.0


def cmd_simulate(args) -> int:
    from .sim.simulate import SimConfig, simulate

    if args.plan is not None:
        return _simulate_plan(args)
    robot_file = [args.robot] if Path(args.robot).exists() else []
    check_output_dir(args.out, inputs=robot_file, overwrite=args.overwrite, kind="dataset", what="--out")

    config = SimConfig(
        robot=args.robot,
        seed=args.seed,
        resolution=args.resolution,
        frames_per_joint=args.frames_per_joint,
        range_deg=args.sweep_deg,
        home_deg=args.home_deg,
        markers=args.markers,
        dictionary=args.dictionary,
        cameras=args.cameras,
        eye_in_hand=args.eye_in_hand,
        markers_on_links=args.markers_on_links,
        clock_offset_ms=args.clock_offset_ms,
        clock_drift_ppm=args.clock_drift_ppm,
        clock_jitter_ms=args.clock_jitter_ms,
        clock_known=not args.unknown_clock_offset,
        drop_rate=args.drop_rate,
        grayscale=args.grayscale,
        encoders=not args.no_encoders,
        distortion=tuple(args.distortion),
    )
    trajectory = None
    if args.random_motion is not None:
        from .sim.motion import random_motion
        from .sim.simulate import nominal_robot

        names = nominal_robot(args.robot)[0].joint_names
        trajectory = random_motion(names, args.random_motion, args.motion_amplitude_deg, seed=args.seed)
    start = time.perf_counter()
    with output_lock(args.out, what="--out"):
        out = simulate(
            config, args.out, trajectory=trajectory, overwrite=args.overwrite, progress=not args.quiet
        )

    ds = load_dataset(out)
    visible = sum(all(f["visible"].values()) for f in ds.truth["frames"])
    print(
        f"wrote {out}: {len(ds.frames['file'])} images from {len(ds.cameras)} camera(s), "
        f"{len(ds.truth['dropped_frames'])} dropped, targets fully in view in {visible} "
        f"({time.perf_counter() - start:.1f} s)"
    )
    return 0


# --------------------------------------------------------------------------- capture planning


def cmd_plan(args) -> int:
    """`jaxcal plan` (docs/plan.md), with MuJoCo's contact and line-of-sight checks."""
    from .sim.plan import MujocoChecker

    return run_plan(args, Console(width=max(Console().width, 120)), MujocoChecker)


def _simulate_plan(args) -> int:
    """`jaxcal simulate --plan PLAN --out DIR`: render exactly the plan."""
    from .sim.plan import render_plan

    check_output_dir(args.out, inputs=[args.plan], overwrite=args.overwrite, kind="dataset", what="--out")
    p = load_plan(args.plan)
    start = time.perf_counter()
    with output_lock(args.out, what="--out"):
        out = render_plan(
            p,
            args.out,
            seed=args.seed,
            overwrite=args.overwrite,
            progress=not args.quiet,
            grayscale=args.grayscale,
        )
    ds = load_dataset(out)
    visible = sum(all(f["visible"].values()) for f in ds.truth["frames"])
    print(
        f"wrote {out}: {len(ds.frames['file'])} images of plan {args.plan} ({p.frames} frames), targets fully in "
        f"view in {visible} ({time.perf_counter() - start:.1f} s)"
    )
    return 0


# --------------------------------------------------------------------------- hand-eye

#: Targets `jaxcal simulate-handeye --target` renders (sizes for 640x480 at about 0.5 m).
SIM_TARGETS = {
    "chessboard": dict(kind="chessboard", squares=(8, 7), square_length=0.025, margin=0.02),
    "circles": dict(kind="circles", squares=(7, 6), square_length=0.03, marker_length=0.015, margin=0.02),
    "acircles": dict(kind="acircles", squares=(4, 11), square_length=0.02, marker_length=0.013, margin=0.02),
    "charuco": dict(kind="charuco", squares=(7, 5), square_length=0.03, marker_length=0.022, margin=0.02),
    "aruco_grid": dict(
        kind="aruco_grid", squares=(4, 3), square_length=0.05, marker_length=0.04, margin=0.02
    ),
    "apriltag": dict(
        kind="aruco_grid",
        dictionary="DICT_APRILTAG_36h11",
        squares=(4, 3),
        square_length=0.05,
        marker_length=0.04,
        margin=0.02,
    ),
}


def cmd_handeye(args) -> int:
    """`jaxcal handeye CAPTURE --out DIR`: exit 0 (ok), 3 (suspect, see result.json), 2 (refused input)."""

    out = Path(args.out)
    checked = check_output_dir(
        out, inputs=[args.capture], overwrite=args.overwrite, kind="result", what="--out"
    )
    with output_lock(out, what="--out"):
        return _handeye(args, out, checked)


def _handeye(args, out: Path, checked) -> int:
    console = Console(width=max(Console().width, 120))
    robot = (
        None
        if args.robot_sigma_mm is None
        else (1e-3 * args.robot_sigma_mm, np.radians(args.robot_sigma_deg))
    )
    t0 = time.perf_counter()
    run = calibrate_hand_eye_capture(
        args.capture,
        robot_sigma_translation=None if robot is None else robot[0],
        robot_sigma_rotation=None if robot is None else robot[1],
        sigma_px=args.sigma_px,
        folds=args.folds,
        max_steps=args.max_steps,
        workers=args.workers,
        progress=not args.quiet,
        log=lambda text: console.print(f"[dim]{text}[/dim]"),
    )
    write_hand_eye_outputs(run, out, overwrite=args.overwrite, checked=checked)
    r = run.result
    cap = run.capture
    what = "T_ee_cam (camera on the flange)" if cap.eye_in_hand else "T_base_cam (fixed camera)"
    for c, cam in enumerate(cap.cameras):
        T, sd = np.asarray(r.T_robot_cam[c]), np.asarray(r.std_robot_cam[c])
        console.print(
            f"camera {cam.name}: {what} t = {np.round(1e3 * T[:3, 3], 2).tolist()} mm, "
            f"std {1e3 * np.linalg.norm(sd[:3]):.3f} mm / {np.degrees(np.linalg.norm(sd[3:])):.4f} deg"
            + (
                f", {run.kfold.folds}-fold spread {1e3 * np.linalg.norm(run.kfold.std_robot_cam[c, :3]):.3f} mm / "
                f"{np.degrees(np.linalg.norm(run.kfold.std_robot_cam[c, 3:])):.4f} deg"
                if run.kfold is not None
                else ""
            )
        )
        console.print(
            f"  ros2 run tf2_ros static_transform_publisher {static_transform_args(run, c)['ros2']}"
        )
        if run.truth_error is not None:
            console.print(
                f"  against the truth: {1e3 * run.truth_error[c, 0]:.3f} mm, {np.degrees(run.truth_error[c, 1]):.4f} deg"
            )
    console.print(
        f"reprojection RMS {float(r.pixel_rms):.3f} px (detector {run.observations.sigma_px:.3f} px), "
        f"{len(run.rejected)} frame(s) rejected of {run.frames}"
    )
    for f, why in sorted(run.rejected.items()):
        console.print(f"  rejected frame {cap.frames[f]}: {why}")
    for note in run.verdict.notes:
        console.print(f"[yellow]note:[/yellow] {note}")
    for reason in run.verdict.reasons:
        console.print(f"[red]suspect:[/red] {reason}")
    console.print(
        f"status [bold]{run.verdict.status}[/bold]; wrote {out}/ (result.json, camera_*.yaml, ros_*.launch.yaml, "
        f"easy_handeye_*.yaml, report.md) in {time.perf_counter() - t0:.1f} s"
    )
    return run.exit_code


def cmd_simulate_handeye(args) -> int:
    from .sim.handeye import HandEyeSimConfig, simulate_hand_eye

    fields = dict(SIM_TARGETS[args.target])
    if args.dictionary is not None:
        fields["dictionary"] = args.dictionary
    config = HandEyeSimConfig(
        target=TargetSpec(name="target", **fields),
        eye_in_hand=args.arrangement == "eye-in-hand",
        frames=args.frames,
        seed=args.seed,
        resolution=args.resolution,
        distortion=tuple(args.distortion),
        distance=args.distance,
        pose_format=args.pose_format,
        translation_unit=args.translation_unit,
        rotation_unit=args.rotation_unit,
        robot_error_fraction=args.robot_error_fraction,
        robot_error_deg=args.robot_error_deg,
        robot_error_mm=args.robot_error_mm,
        intrinsics_known=not args.unknown_intrinsics,
    )
    start = time.perf_counter()
    try:
        out = simulate_hand_eye(config, args.out, overwrite=args.overwrite)
    except FileExistsError as e:
        print(f"jaxcal: error: {e}", file=sys.stderr)
        return 2
    print(
        f"wrote {out}: {args.frames} frames, {args.target}, {args.arrangement} "
        f"({time.perf_counter() - start:.1f} s)"
    )
    return 0


def _add_handeye_parsers(sub) -> None:
    p = sub.add_parser(
        "handeye",
        help="hand-eye calibration from a capture: images and robot poses (docs/handeye.md)",
        description="Hand-eye calibration of a capture (docs/handeye.md). Exit codes: 0 ok; 3 the result is "
        "suspect (reasons in result.json and on screen); 2 the input was refused (bad capture, robot poses "
        "that do not match the images, too little motion); 1 an unexpected failure.",
    )
    p.add_argument("capture", help="capture directory (handeye.json, poses.csv, images/)")
    p.add_argument("--out", required=True, help="result directory (must be empty or absent)")
    p.add_argument("--overwrite", action="store_true", help="replace a non-empty --out")
    p.add_argument("--sigma-px", type=float, help="detector noise, px (default: estimated from per-view PnP)")
    p.add_argument(
        "--robot-sigma-mm",
        type=float,
        help="robot pose noise, mm: each pose gets a correction with this prior",
    )
    p.add_argument(
        "--robot-sigma-deg", type=float, default=0.05, help="robot pose noise, deg (with --robot-sigma-mm)"
    )
    p.add_argument("--folds", type=int, default=10, help="k of the k-fold spread (0: skip)")
    p.add_argument("--max-steps", type=int, default=200, help="Levenberg-Marquardt steps per stage")
    p.add_argument("--workers", type=int, default=1, help="threads for marker detection")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=cmd_handeye)
    p = sub.add_parser(
        "simulate-handeye", help="render a hand-eye capture (MuJoCo): a target, a camera, random wrist poses"
    )
    p.add_argument("--out", required=True, help="capture directory (must be empty or absent)")
    p.add_argument("--overwrite", action="store_true", help="replace a non-empty --out")
    p.add_argument("--target", choices=tuple(SIM_TARGETS), default="chessboard")
    p.add_argument(
        "--dictionary", help="ArUco/AprilTag dictionary of a marker target (e.g. DICT_APRILTAG_36h11)"
    )
    p.add_argument("--arrangement", choices=("eye-in-hand", "eye-to-hand"), default="eye-in-hand")
    p.add_argument("--frames", type=int, default=16)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--resolution", type=_resolution, default=(640, 480), help="WxH pixels")
    p.add_argument("--distance", type=float, default=0.5, help="camera to target, m")
    p.add_argument(
        "--distortion", type=float, nargs=5, default=[0.0] * 5, metavar=("K1", "K2", "P1", "P2", "K3")
    )
    p.add_argument(
        "--pose-format", choices=("matrix", "xyz_quat", "xyz_rpy", "xyz_rotvec"), default="xyz_quat"
    )
    p.add_argument("--translation-unit", choices=("m", "mm"), default="m")
    p.add_argument("--rotation-unit", choices=("rad", "deg"), default="rad")
    p.add_argument(
        "--robot-error-fraction", type=float, default=0.0, help="share of robot poses recorded wrong"
    )
    p.add_argument("--robot-error-deg", type=float, default=2.0)
    p.add_argument("--robot-error-mm", type=float, default=5.0)
    p.add_argument("--unknown-intrinsics", action="store_true", help="write K = null (self-calibrated)")
    p.set_defaults(func=cmd_simulate_handeye)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="jaxcal", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser(
        "demo", help="render a perturbed UR5e, calibrate it from the images, show before/after"
    )
    p.add_argument("--out", default="jaxcal-demo", help="where the dataset and the results go")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--resolution", type=_resolution, default=(1280, 960), help="WxH pixels")
    p.add_argument("--frames-per-joint", type=int, default=40)
    p.add_argument(
        "--sweep-deg",
        type=_degrees,
        default=None,
        help="angle each joint sweeps (deg), one or one per joint (default 80; eye-in-hand "
        + _fmt_degrees(EYE_IN_HAND_SWEEP)
        + ")",
    )
    p.add_argument("--cameras", type=int, default=1, help="fixed cameras filming the arm")
    p.add_argument(
        "--eye-in-hand", action="store_true", help="the camera on the flange, a ChArUco board in the world"
    )
    p.add_argument(
        "--markers-on-links",
        action="store_true",
        help="a plate on every link, every joint moving at once (random waypoints, as many frames as the "
        "sweeps would take); sequential initialisation, then the refinement",
    )
    _add_calibrate_args(p)
    p.set_defaults(func=cmd_demo)
    p = sub.add_parser("calibrate", help="calibrate robot and camera from a dataset (docs/dataset.md)")
    p.add_argument("dataset", help="dataset directory")
    p.add_argument(
        "--out",
        required=True,
        help="result directory: absent or empty, never the dataset, inside it or around it",
    )
    p.add_argument("--overwrite", action="store_true", help="replace a result directory jaxcal wrote")
    _add_calibrate_args(p)
    p.set_defaults(func=cmd_calibrate)
    p = sub.add_parser("montecarlo", help="vmapped Monte Carlo sensitivity study (analytic marker poses)")
    _add_study_args(p, trials=1000)
    p.add_argument("--json", help="write the summary here (atomically)")
    p.add_argument("--detail", action="store_true", help="first show one trial in detail")
    p.set_defaults(func=cmd_montecarlo)
    p = sub.add_parser(
        "simulate", help="render a perturbed arm's calibration dataset (MuJoCo) into a directory"
    )
    p.add_argument("--robot", default="ur5e", help="shipped robot (ur5e, panda) or a URDF file")
    p.add_argument("--out", required=True, help="dataset directory (must be empty or absent)")
    p.add_argument("--overwrite", action="store_true", help="replace a dataset jaxcal wrote")
    p.add_argument("--seed", type=int, default=0)
    # The defaults film the demo's capture (EE RMS 0.19 mm refined; the former 640x480, 30 frames per
    # 40-degree sweep gave 1.2 mm): see docs/plan.md, and `--plan` for a planned capture (0.04 mm).
    p.add_argument("--resolution", type=_resolution, default=(1280, 960), help="WxH pixels")
    p.add_argument("--frames-per-joint", type=int, default=40)
    p.add_argument(
        "--sweep-deg", type=_degrees, default=80.0, help="angle each joint sweeps (deg), one or one per joint"
    )
    p.add_argument(
        "--home-deg",
        type=_home,
        default=None,
        help="the configuration every sweep starts from and the others hold, one angle per joint "
        "(deg, e.g. 0,-20,30,-15,20,0; default zero)",
    )
    p.add_argument("--markers", choices=("charuco", "aruco"), default="charuco")
    p.add_argument("--dictionary", default="DICT_4X4_50", help="OpenCV ArUco dictionary")
    p.add_argument("--cameras", type=int, default=1, help="fixed cameras (eye-to-hand)")
    p.add_argument("--eye-in-hand", action="store_true", help="camera on the flange, board in the world")
    p.add_argument("--markers-on-links", action="store_true", help="a plate on every link too")
    p.add_argument(
        "--random-motion",
        type=float,
        metavar="SECONDS",
        help="move every joint at once through random waypoints for this long, filmed throughout "
        "(default: joint-by-joint sweeps); calibrated with --markers-on-links",
    )
    p.add_argument(
        "--motion-amplitude-deg", type=float, default=25.0, help="random motion range, +- about zero"
    )
    p.add_argument("--clock-offset-ms", type=float, default=0.0, help="camera clock minus controller clock")
    p.add_argument("--clock-drift-ppm", type=float, default=0.0)
    p.add_argument("--clock-jitter-ms", type=float, default=0.0)
    p.add_argument("--unknown-clock-offset", action="store_true", help="leave the offset out of the metadata")
    p.add_argument("--drop-rate", type=float, default=0.0, help="probability that a frame is lost")
    p.add_argument("--no-encoders", action="store_true", help="write no encoder log")
    p.add_argument("--grayscale", action="store_true", help="write single-channel PNGs")
    p.add_argument(
        "--distortion", type=float, nargs=5, default=[0.0] * 5, metavar=("K1", "K2", "P1", "P2", "K3")
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument(
        "--plan", help="render exactly this capture plan (docs/plan.md): its camera, target and motion"
    )
    p.set_defaults(func=cmd_simulate)
    _add_handeye_parsers(sub)
    add_plan_parser(sub, cmd_plan)
    args = parser.parse_args(argv)
    enable_compilation_cache()
    try:
        return args.func(args)
    except (ValueError, OSError) as e:
        print(f"jaxcal: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
