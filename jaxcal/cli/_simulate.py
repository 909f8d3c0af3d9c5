"""`jaxcal simulate` (a rendered dataset), `simulate-tracker`, `simulate-plan` and `jaxcal plan`.

Built into the parser of each of these commands, this module imports only what the parser needs:
a command says what it does first, then imports the simulator, the planner and the dataset
reader (seconds)."""

import time
from pathlib import Path

from ..io._files import check_output_dir, output_lock


def cmd_simulate(args) -> int:
    """`jaxcal simulate`: a rendered camera dataset."""
    args.robot = args.robot or "ur5e"
    if args.robot == "upper_body":
        return _simulate_head_camera(args)
    robot_file = [args.robot] if Path(args.robot).exists() else []
    check_output_dir(args.out, inputs=robot_file, overwrite=args.overwrite, kind="dataset", what="--out")
    if not args.quiet:
        print(f"simulating a perturbed {args.robot} into {args.out}: building the scene ...", flush=True)
    from ..io._truth import small_markers
    from ..io.dataset import load_dataset, true_poses
    from ..sim.simulate import SimConfig, simulate

    config = SimConfig(
        robot=args.robot,
        seed=args.seed,
        resolution=args.resolution,
        frames_per_joint=args.frames_per_joint,
        range_deg=args.sweep_deg,
        range_mm=args.sweep_mm,
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
        camera=args.camera_model,
        arm=args.arm,
    )
    trajectory = None
    if args.random_motion is not None:
        from ..sim.motion import random_motion
        from ..sim.simulate import nominal_robot

        names = nominal_robot(args.robot)[0].joint_names
        trajectory = random_motion(names, args.random_motion, args.motion_amplitude_deg, seed=args.seed)
    start = time.perf_counter()
    with output_lock(args.out, what="--out"):
        out = simulate(
            config, args.out, trajectory=trajectory, overwrite=args.overwrite, progress=not args.quiet
        )

    ds = load_dataset(out)
    truth = true_poses(ds.truth)
    visible = sum(all(v.values()) for v in truth.visible)
    print(
        f"wrote {out}: {len(ds.frames.file)} images from {len(ds.cameras)} camera(s), "
        f"{len(truth.dropped_frames)} dropped, targets fully in view in {visible} "
        f"({time.perf_counter() - start:.1f} s)"
    )
    for warning in small_markers(truth, ds.cameras, ds.targets):
        print(f"warning: {warning}")
    return 0


# --------------------------------------------------------------------------- capture planning


def cmd_plan(args) -> int:
    """`jaxcal plan` (docs/plan.md), with MuJoCo's contact and line-of-sight checks."""
    if not args.quiet:  # before the planner, the robot, the scene and MuJoCo's checker: seconds
        doing = (
            f"evaluating plan {args.evaluate}"
            if args.evaluate
            else f"choosing {args.budget} poses for a drift check of {args.check}"
            if args.check
            else f"planning {args.frames} stop-and-shoot poses of {args.robot} into {args.out}"
        )
        print(f"{doing} ...", flush=True)
    from rich.console import Console

    from ..planning._cli import run_plan
    from ..sim.plan import MujocoChecker

    return run_plan(args, Console(width=max(Console().width, 120)), MujocoChecker, capture_models)


def capture_models(camera: str | None, arm: str | None):
    """`jaxcal plan --camera-model / --arm`: the presets' figures for the prediction
    (`jaxcal.records_capture`), or None for an option not given."""
    from ..sim.arm import arm_model
    from ..sim.camera import camera_model

    return (
        None if camera is None else camera_model(camera).noise_record(),
        None if arm is None else arm_model(arm).figures(),
    )


def cmd_simulate_plan(args) -> int:
    """`jaxcal simulate-plan PLAN --out DIR`: render exactly the plan (options the plan fixes are
    refused by the command line, `jaxcal.cli._refusal`)."""
    check_output_dir(args.out, inputs=[args.plan], overwrite=args.overwrite, kind="dataset", what="--out")
    if not args.quiet:  # before MuJoCo's import and the plan's scene: seconds
        print(
            f"simulating plan {args.plan} into {args.out}: loading the plan and building its scene ...",
            flush=True,
        )
    from ..io.dataset import load_dataset, true_poses
    from ..planning import load_plan, plan_robot
    from ..sim.plan import render_plan

    p = load_plan(args.plan)
    plan_robot(p, args.plan)  # its joints and limits, the error naming the file
    start = time.perf_counter()
    with output_lock(args.out, what="--out"):
        out = render_plan(
            p,
            args.out,
            seed=args.seed,
            overwrite=args.overwrite,
            progress=not args.quiet,
            grayscale=args.grayscale,
            camera=args.camera_model,
            arm=args.arm,
        )
    ds = load_dataset(out)
    visible = sum(all(v.values()) for v in true_poses(ds.truth).visible)
    print(
        f"wrote {out}: {len(ds.frames.file)} images of plan {args.plan} ({p.frames} frames), targets fully in "
        f"view in {visible} ({time.perf_counter() - start:.1f} s)"
    )
    return 0


def cmd_simulate_tracker(args) -> int:
    """`jaxcal simulate-tracker`: laser-tracker sweeps of a perturbed arm (no rendering)."""
    robot = args.robot or "ur3"
    inputs = [robot] if Path(robot).exists() else []
    check_output_dir(args.out, inputs=inputs, overwrite=args.overwrite, kind="dataset", what="--out")
    if robot == "upper_body":
        _refuse_other_options(args, UPPER_BODY_TRACKER_OPTIONS, "the upper body's tracker capture")
        return _simulate_upper_body(args)
    if not args.quiet:
        kind = f"{args.random_poses} stop-and-shoot poses" if args.random_poses else "sweeps"
        print(f"simulating {robot}'s tracker {kind} into {args.out} ...", flush=True)
    from ..io.dataset import load_dataset, true_poses
    from ..sim.tracker import TrackerSimConfig, simulate_tracker

    given = {
        "home_deg": args.home_deg,
        "range_deg": args.sweep_deg,
    }
    config = TrackerSimConfig(
        robot=robot,
        seed=args.seed,
        samples_per_joint=args.samples_per_joint,
        poses=args.random_poses,
        noise_um=args.noise_um,
        bad_fraction=args.bad_fraction,
        device_is_base=args.device_is_base,
        orientation=args.orientation,
        **{k: v for k, v in given.items() if v is not None},
    )
    start = time.perf_counter()
    with output_lock(args.out, what="--out"):
        out = simulate_tracker(config, args.out, overwrite=args.overwrite)
    ds = load_dataset(out)
    what = (
        f"{args.random_poses} stop-and-shoot poses"
        if args.random_poses
        else f"{len(ds.joint_names)} joint sweeps"
    )
    print(
        f"wrote {out}: {len(ds.samples.sample)} tracker samples of {what}, "
        f"{len(true_poses(ds.truth).bad_samples)} bad ({time.perf_counter() - start:.1f} s)"
    )
    return 0


def _simulate_upper_body(args) -> int:
    """`jaxcal simulate-tracker --robot upper_body`: a tree dataset of the synthetic humanoid."""
    poses = args.random_poses or 500
    if not args.quiet:
        print(
            f"simulating the upper body's tracker: both hands at {poses} stop-and-shoot poses into {args.out} ..."
        )
    from ..sim.humanoid import simulate_upper_body

    start = time.perf_counter()
    with output_lock(args.out, what="--out"):
        out = simulate_upper_body(
            args.out, poses=poses, noise_mm=1e-3 * args.noise_um, seed=args.seed, overwrite=args.overwrite
        )
    print(
        f"wrote {out}: a tree dataset (tree.json, robot.urdf, samples.csv, truth.json; {time.perf_counter() - start:.1f} s)"
    )
    return 0


#: What `jaxcal simulate --robot upper_body` takes (its capture is the head camera's, fixed), and
#: what `simulate-tracker --robot upper_body` takes (both hands measured at random poses).
HEAD_CAMERA_OPTIONS = ("robot", "out", "overwrite", "seed", "quiet")
UPPER_BODY_TRACKER_OPTIONS = (*HEAD_CAMERA_OPTIONS, "noise_um", "random_poses")


def _refuse_other_options(args, allowed, what: str) -> None:
    """Refuse, naming them, the options (flags or configuration keys) given values other than
    their defaults that `what` does not take."""
    from . import build_parser

    defaults = vars(build_parser(args.command).parse_args([args.command, "--out", "-"]))
    other = [
        "--" + k.replace("_", "-")
        for k, v in vars(args).items()
        if k in defaults
        and k not in allowed
        and k not in ("func", "foreign", "command", "config")
        and v != defaults[k]
    ]
    if other:
        raise ValueError(
            f"{', '.join(other)}: not options of {what} (it takes {', '.join('--' + a.replace('_', '-') for a in allowed)})"
        )


def _simulate_head_camera(args) -> int:
    """`jaxcal simulate --robot upper_body`: the synthetic humanoid's head camera filming plates on
    both hands (`jaxcal.sim.head_camera`), written as a tree dataset with each point's covariance."""
    _refuse_other_options(
        args,
        HEAD_CAMERA_OPTIONS,
        "the upper body's head-camera capture (640x480, plates on both hands, 200 poses and 50 held out)",
    )
    check_output_dir(args.out, inputs=[], overwrite=args.overwrite, kind="dataset", what="--out")
    if not args.quiet:
        print(f"simulating the upper body's head camera filming both hands into {args.out} ...", flush=True)
    from ..sim.head_camera import simulate_head_camera

    start = time.perf_counter()
    with output_lock(args.out, what="--out"):
        out = simulate_head_camera(
            args.out, seed=args.seed, overwrite=args.overwrite, show_progress=not args.quiet
        )
    print(
        f"wrote {out}: a tree dataset of the head camera's PnP points with their covariances (tree.json, "
        f"robot.urdf, samples.csv, truth.json; {time.perf_counter() - start:.1f} s)"
    )
    return 0
