"""`jaxcal handeye` and `jaxcal simulate-handeye`."""

import sys
import time
from pathlib import Path

import numpy as np

from .._configkeys import knob
from ..io._files import check_output_dir, output_lock, resolved
from ._common import MAX_WORKERS, count, finite, positive, resolution, run_record, seed

# --------------------------------------------------------------------------- hand-eye

#: Bounds of `handeye --folds` (each fold a solve), `--max-steps` and `simulate-handeye --frames`.
MAX_FOLDS, MAX_STEPS, MAX_FRAMES = 100, 100_000, 2000

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


def _robot_noise_support(r) -> str:
    """How many residual degrees of freedom (translation / rotation) the estimated robot noise
    rests on; under 2 the poses fit the images exactly and the figure is only a bound."""
    from .._handeye import ROBOT_SIGMA_OPTIONS

    if not bool(np.all(np.asarray(r.robot_sigma_estimated))):
        return ""
    t, w = (float(d) for d in np.asarray(r.robot_dof)[:2])
    text = f", from {t:.0f} / {w:.0f} degrees of freedom (translation / rotation)"
    thin = [what for what, d in (("translation", t), ("rotation", w)) if d < 2.0]
    if thin:
        text += (
            f": the {' and '.join(thin)} noise rests on almost none (the fit takes up what the images leave), so "
            "its figure is only an upper bound"
        )
    return text + f" (set it with {ROBOT_SIGMA_OPTIONS})"


def cmd_handeye(args) -> int:
    """`jaxcal handeye CAPTURE --out DIR`: exit 0 (ok), 3 (suspect, see result.json), 2 (refused input)."""

    if args.robot_sigma_mm is None and args.robot_sigma_deg is not None:
        print(
            "jaxcal: error: robot-sigma-deg needs robot-sigma-mm (--config robot-sigma-mm=MM: the robot noise of --robot-noise given)",
            file=sys.stderr,
        )
        return 2
    if args.robot_noise == "given" and args.robot_sigma_mm is None:
        print(
            "jaxcal: error: --robot-noise given needs robot-sigma-mm (--config robot-sigma-mm=MM, and robot-sigma-deg)",
            file=sys.stderr,
        )
        return 2
    if args.robot_noise in ("exact", "estimate") and args.robot_sigma_mm is not None:
        print(
            f"jaxcal: error: --robot-noise {args.robot_noise} takes no robot-sigma-mm/robot-sigma-deg "
            "(they are the noise of --robot-noise given, and of auto's given candidate)",
            file=sys.stderr,
        )
        return 2
    out = Path(args.out)
    checked = check_output_dir(
        out, inputs=[args.capture], overwrite=args.overwrite, kind="result", what="--out"
    )
    if not args.quiet:  # before the calibration's modules are imported: seconds
        print(f"hand-eye calibration of {args.capture} into {out} ...", flush=True)
    # The solver the last run on this capture called is read from the first moment the capture is
    # known, while the calibration's modules are imported and the images detected.
    from .._exported import warm_start  # JAX: after the first line

    with output_lock(out, what="--out"), warm_start(f"jaxcal handeye {resolved(args.capture)}"):
        from ..report import warm_up_plots

        plots = warm_up_plots()  # matplotlib loads while the capture is calibrated
        code = _handeye(args, out, checked)
        plots.join()
        return code


def _handeye(args, out: Path, checked) -> int:
    from rich.console import Console

    from .._handeye import describe_robot_noise
    from ..handeye import calibrate_hand_eye_capture
    from ..io.handeye_results import ros2_static_transform_args, write_hand_eye_outputs

    console = Console(width=max(Console().width, 120))
    # The sigmas of --robot-noise given (and of auto's given candidate); alone, they mean given.
    robot = (
        None
        if args.robot_sigma_mm is None
        else (
            1e-3 * args.robot_sigma_mm,
            np.radians(0.05 if args.robot_sigma_deg is None else args.robot_sigma_deg),
        )
    )
    capture, reference = args.capture, None
    if args.reference:  # read and checked before the calibration, against the capture's cameras
        from ..io.handeye import load_hand_eye_capture, read_reference

        capture = load_hand_eye_capture(args.capture)
        reference = read_reference(args.reference, capture)
    t0 = time.perf_counter()
    run = calibrate_hand_eye_capture(
        capture,
        robot_noise=args.robot_noise,
        robot_sigma_translation=None if robot is None else robot[0],
        robot_sigma_rotation=None if robot is None else robot[1],
        sigma_px=args.sigma_px,
        folds=args.folds,
        max_steps=args.max_steps,
        workers=args.workers,
        progress=not args.quiet,
        log=lambda text: console.print(f"[dim]{text}[/dim]"),
    )
    write_hand_eye_outputs(run, out, overwrite=args.overwrite, checked=checked, made=run_record(args))
    r = run.result
    cap = run.capture
    what = "T_ee_cam (camera on the flange)" if cap.eye_in_hand else "T_base_cam (fixed camera)"
    disagree = []  # cameras the reference puts more than REFERENCE_Z standard deviations away
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
        console.print(f"  ros2 run tf2_ros static_transform_publisher {ros2_static_transform_args(run, c)}")
        if run.truth_error is not None:
            console.print(
                f"  against the truth: {1e3 * run.truth_error[c, 0]:.3f} mm, {np.degrees(run.truth_error[c, 1]):.4f} deg"
            )
        if reference is not None:
            line, off = against_reference(T, sd, reference[cam.name])
            console.print(f"  against {args.reference}: {line}")
            disagree += [cam.name] if off else []
    console.print(
        f"reprojection RMS {float(r.pixel_rms):.3f} px (detector {run.observations.sigma_px:.3f} px), "
        f"{len(run.rejected)} frame(s) rejected of {run.frames}"
    )
    console.print(describe_robot_noise(r) + _robot_noise_support(r))
    for f, why in sorted(run.rejected.items()):
        console.print(f"  rejected frame {cap.frames[f]}: {why}")
    for note in run.verdict.notes:
        console.print(f"[yellow]note:[/yellow] {note}")
    for reason in run.verdict.reasons:
        console.print(f"[red]suspect:[/red] {reason}")
    if disagree:
        console.print(
            f"[yellow]note:[/yellow] {args.reference} disagrees with camera(s) {', '.join(disagree)} beyond "
            f"{REFERENCE_Z:g} standard deviations (above): the status judges the capture (its fit, noise and "
            "coverage), not this difference; one of the two answers is wrong, or the standard deviations are "
            "optimistic"
        )
    console.print(
        f"status [bold]{run.verdict.status}[/bold]; wrote {out}/ (result.json, camera_*.yaml, ros_*.launch.yaml, "
        f"easy_handeye_*.yaml, report.md) in {time.perf_counter() - t0:.1f} s"
    )
    return run.exit_code


def cmd_simulate_handeye(args) -> int:
    print(
        f"rendering {args.frames} frames of a {args.target_kind}, {args.arrangement}, into {args.out} ...",
        flush=True,
    )  # before the simulator's modules are imported: seconds
    from ..markers import TargetSpec
    from ..sim.handeye import HandEyeSimConfig, simulate_hand_eye

    fields = dict(SIM_TARGETS[args.target_kind])
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
        robot_noise_mm=args.robot_noise_mm,
        robot_noise_deg=args.robot_noise_deg,
        intrinsics_known=not args.unknown_intrinsics,
    )
    start = time.perf_counter()
    try:
        out = simulate_hand_eye(config, args.out, overwrite=args.overwrite)
    except FileExistsError as e:
        print(f"jaxcal: error: {e}", file=sys.stderr)
        return 2
    print(
        f"wrote {out}: {args.frames} frames, {args.target_kind}, {args.arrangement} "
        f"({time.perf_counter() - start:.1f} s)"
    )
    return 0


#: A result off a known answer by more than this many standard deviations on one axis is named.
REFERENCE_Z = 2.0


def against_reference(T: np.ndarray, std6: np.ndarray, T_ref: np.ndarray) -> tuple[str, bool]:
    """How far a camera's pose `T` (its per-axis standard deviations `std6`: m, rad) lies from a
    known answer `T_ref`, in millimetres and degrees and, per axis, in standard deviations (the
    convention of `jaxcal._handeye.assess.pose_difference`), and whether an axis is off by more
    than `REFERENCE_Z` of them."""
    from .._handeye.assess import pose_difference

    e = pose_difference(T, T_ref)
    z = e / np.where(np.asarray(std6) > 0, std6, np.nan)
    worst = int(np.nanargmax(np.abs(z))) if np.any(np.isfinite(z)) else 0
    axes = ("x", "y", "z", "rx", "ry", "rz")
    off = bool(np.nanmax(np.abs(z)) > REFERENCE_Z)
    words = (
        f"within {REFERENCE_Z:g} standard deviations on every axis"
        if not off
        else f"off by {abs(z[worst]):.1f} standard deviations on {axes[worst]} (more than {REFERENCE_Z:g}: the "
        "result or the reference is wrong, or the standard deviations are optimistic)"
    )
    line = (
        f"{1e3 * np.linalg.norm(e[:3]):.3f} mm / {np.degrees(np.linalg.norm(e[3:])):.4f} deg, per axis "
        f"{np.round(z[:3], 2).tolist()} (translation) {np.round(z[3:], 2).tolist()} (rotation) standard "
        f"deviations: {words}"
    )
    return line, off


def add_handeye_parsers(sub) -> None:
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
    knob(p, "--sigma-px", type=finite, help="detector noise, px (default: estimated from per-view PnP)")
    p.add_argument(
        "--robot-noise",
        choices=("auto", "exact", "estimate", "given"),
        default=None,
        help="model of the robot's reported poses: exact (no corrections), estimate (a correction per pose, "
        "the noise estimated from the data), given (a correction per pose with the keys robot-sigma-mm/-deg), or "
        "auto: the one that predicts frames left out best (default; given alone when robot-sigma-mm is)",
    )
    knob(
        p,
        "--robot-sigma-mm",
        type=finite,
        help="robot pose noise per axis, mm, of --robot-noise given: each pose gets a correction with this prior",
    )
    knob(
        p,
        "--robot-sigma-deg",
        type=finite,
        help="robot pose noise per axis, deg (with robot-sigma-mm; 0.05 when only that is given)",
    )
    knob(
        p,
        "--folds",
        type=count(0, MAX_FOLDS),
        default=10,
        help=f"k of the k-fold spread and of the held-out comparison of --robot-noise auto (0: skip both; "
        f"auto then estimates the noise; at most {MAX_FOLDS})",
    )
    knob(
        p,
        "--max-steps",
        type=count(1, MAX_STEPS),
        default=200,
        help=f"Levenberg-Marquardt steps per stage, at most {MAX_STEPS:,}",
    )
    knob(
        p,
        "--workers",
        type=count(1, MAX_WORKERS),
        default=None,
        help=f"threads for marker detection (default: all cores; at most {MAX_WORKERS})",
    )
    p.add_argument(
        "--reference",
        metavar="FILE",
        help="a known answer (JSON: the camera's pose as a 4x4 matrix or [tx, ty, tz, rx, ry, rz] in m and "
        "rad, or a jaxcal result.json): the result's difference from it in mm, deg and standard deviations",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=cmd_handeye)
    p = sub.add_parser(
        "simulate-handeye", help="render a hand-eye capture (MuJoCo): a target, a camera, random wrist poses"
    )
    p.add_argument("--out", required=True, help="capture directory (must be empty or absent)")
    p.add_argument("--overwrite", action="store_true", help="replace a non-empty --out")
    p.add_argument("--target-kind", choices=tuple(SIM_TARGETS), default="chessboard")
    knob(p, "--dictionary", help="ArUco/AprilTag dictionary of a marker target (e.g. DICT_APRILTAG_36h11)")
    p.add_argument("--arrangement", choices=("eye-in-hand", "eye-to-hand"), default="eye-in-hand")
    p.add_argument(
        "--frames", type=count(3, MAX_FRAMES), default=16, help=f"robot poses, at most {MAX_FRAMES}"
    )
    p.add_argument("--seed", type=seed, default=0)
    p.add_argument("--resolution", type=resolution, default=(640, 480), help="WxH pixels")
    p.add_argument("--distance", type=positive, default=0.5, help="camera to target, m")
    knob(p, "--distortion", type=finite, nargs=5, default=[0.0] * 5, metavar=("K1", "K2", "P1", "P2", "K3"))
    knob(p, "--pose-format", choices=("matrix", "xyz_quat", "xyz_rpy", "xyz_rotvec"), default="xyz_quat")
    knob(p, "--translation-unit", choices=("m", "mm"), default="m")
    knob(p, "--rotation-unit", choices=("rad", "deg"), default="rad")
    knob(p, "--robot-error-fraction", type=finite, default=0.0, help="share of robot poses recorded wrong")
    knob(p, "--robot-error-deg", type=finite, default=2.0)
    knob(p, "--robot-error-mm", type=finite, default=5.0)
    knob(
        p,
        "--robot-noise-mm",
        type=finite,
        default=0.0,
        help="robot pose noise on every recorded pose, mm per axis",
    )
    knob(
        p,
        "--robot-noise-deg",
        type=finite,
        default=0.0,
        help="robot pose noise on every recorded pose, deg per axis",
    )
    knob(p, "--unknown-intrinsics", action="store_true", help="write K = null (self-calibrated)")
    p.set_defaults(func=cmd_simulate_handeye)
