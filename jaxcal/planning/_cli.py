"""`jaxcal plan`: its arguments, its run and its tables (`jaxcal.cli` adds the MuJoCo checker).

- `jaxcal plan --robot ur5e [--camera-file CAMERA_YAML] [--target TARGET_JSON] --frames 240 --out plan.json`
  plans a pose-based capture and writes it (nothing is written on any error).
- `jaxcal plan --evaluate plan.json [--region x0,y0,z0,x1,y1,z1] [--plot ee.png] [--json out.json]`
  pre-evaluates a plan: per-parameter standard deviations, what it leaves
  unidentifiable, the predicted EE error over the workspace.
- Both take `--camera-model PRESET` and `--arm PRESET` (`jaxcal simulate`'s
  `--camera-model` and `--arm` presets): the prediction then adds the camera's corner
  noise and the arm's bias (`jaxcal.planning._realism`). The presets' figures
  come from the simulator, which this module may not import: `run_plan`'s
  `capture_models(camera, arm)` gives them (`jaxcal.cli`).
"""

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

from .._argtypes import count, finite, resolution
from .._configkeys import knob
from .._terms import check_terms
from ..errors import OutputError, PlanError, PlanFileError
from ..io._files import check_output_file, resolved, write_text_atomic
from ..io._images import MAX_PIXELS, MAX_SIDE
from ..io.plan_inputs import parse_pose, parse_region, read_camera, read_target
from ._api import Robot, evaluate_plan, plan, scene_of, views, workspace
from ._check import plan_check, write_poses
from ._evaluate import DEFAULT_SIGMA_PX, PlanEvaluation
from ._plan import load_plan, save_plan
from ._report import parameter_rows, plot_evaluation
from ._scene import FeasibilityLimits

#: Bounds of the options that size a plan's work and memory (the candidates' and the frames'
#: Jacobians are held at once): ten to twenty times their defaults.
MAX_FRAMES, MAX_CANDIDATES, MAX_STARTS, MAX_STEPS, MAX_BUDGET = 5000, 50_000, 100, 100_000, 1000


#: `--resolution`: `WxH` pixels, as the dataset reader takes them (`jaxcal.cli`'s type).
_RESOLUTION = resolution(MAX_SIDE, MAX_PIXELS)


def add_plan_parser(sub, func, cameras=("ideal",), arms=("ideal",)) -> None:
    """The `plan` subcommand's arguments (`func` runs it; `cameras`, `arms`: the preset names)."""
    p = sub.add_parser(
        "plan",
        help="plan, check and pre-evaluate a calibration capture before any image is taken (docs/plan.md)",
        description="Plan a pose-based calibration capture, or pre-evaluate a plan (--evaluate). Exit codes: 0 done; "
        "2 refused input (unreachable region, a camera that sees nothing, too small a budget, a malformed plan).",
    )
    p.add_argument("--evaluate", metavar="PLAN", help="pre-evaluate this plan file instead of planning")
    p.add_argument(
        "--check",
        metavar="RESULT",
        help="propose the --budget poses that make jaxcal check of this camera result most sensitive "
        "(--out: a CSV of them; --json: the figures)",
    )
    p.add_argument(
        "--budget",
        type=count(1, MAX_BUDGET),
        default=10,
        help=f"--check: the check capture's poses (at most {MAX_BUDGET})",
    )
    p.add_argument(
        "--robot", default="ur5e", help="shipped robot (ur5e, panda; revolute joints only) or a URDF file"
    )
    p.add_argument(
        "--camera-file",
        help="camera YAML (camera_matrix, image size, T_base_cam or T_flange_cam); default: the demo's camera "
        "at the taught pose",
    )
    p.add_argument(
        "--target", help="target JSON (spec, link, T_link_target); default: the demo's plate (board)"
    )
    p.add_argument(
        "--eye-in-hand", action="store_true", help="default layout: camera on the flange, board in the world"
    )
    knob(p, "--resolution", type=_RESOLUTION, default=(1280, 960), help="WxH pixels of the default camera")
    knob(p, "--distance", type=finite, help="default camera to target distance, m (0.9; eye-in-hand 0.6)")
    knob(p, "--taught", help="taught pose q1,q2,... (rad; default the robot's)")
    p.add_argument(
        "--frames",
        type=count(1, MAX_FRAMES),
        default=240,
        help=f"frames (stop-and-shoot poses), at most {MAX_FRAMES:,}",
    )
    p.add_argument("--out", help="the plan file to write (refused if it exists, unless --overwrite)")
    p.add_argument(
        "--overwrite", action="store_true", help="replace --out, --plot and --json (never an input)"
    )
    p.add_argument("--region", help="x0,y0,z0,x1,y1,z1: box (m, base frame) where EE accuracy matters")
    knob(p, "--sigma-px", type=finite, default=DEFAULT_SIGMA_PX, help="detector corner noise, px")
    p.add_argument(
        "--camera-model",
        choices=cameras,
        help="the camera model, as `jaxcal simulate --camera-model`: its corner noise (sensor noise, JPEG) joins "
        "sigma-px, and frames it would blur are left out (default: sigma-px alone)",
    )
    p.add_argument(
        "--arm",
        choices=arms,
        help="the arm model, as `jaxcal simulate --arm`: the EE bias its gravity sag, backlash and latency "
        "leave in the calibration is predicted beside the noise (default: a rigid arm, no bias; 'physics' is "
        "predicted from its compliance and lost motion, as 'realistic')",
    )
    p.add_argument(
        "--terms",
        type=_terms_arg,
        default=(),
        help="non-geometric joint terms the calibration will fit (as `jaxcal calibrate --terms`: compliance, "
        "backlash, harmonic1, harmonic2; comma-separated): planning, the poses are chosen so that the terms can "
        "be told from the geometry (gravity-torque variety, approaches from both sides); --evaluate, the "
        "prediction counts them and the arm's bias is what they leave, the bias without them beside",
    )
    knob(p, "--method", choices=("gradient", "greedy"), default="gradient")
    knob(p, "--baseline", action="store_true", help="also run the greedy D-optimal baseline")
    knob(p, "--starts", type=count(1, MAX_STARTS), default=3, help=f"gradient starts, at most {MAX_STARTS}")
    knob(p, "--steps", type=count(1, MAX_STEPS), default=150, help=f"gradient steps, at most {MAX_STEPS:,}")
    knob(
        p,
        "--candidates",
        type=count(1, MAX_CANDIDATES),
        default=2000,
        help=f"random poses drawn about the taught pose, at most {MAX_CANDIDATES:,}",
    )
    knob(p, "--amplitude-deg", type=finite, default=60.0, help="candidates within this of the taught pose")
    p.add_argument("--goal-mm", type=finite, help="regenerate wider while the predicted EE RMS is above this")
    knob(p, "--floor-z", type=finite, default=-0.6, help="floor height, m (base frame)")
    knob(p, "--view-angle-deg", type=finite, default=60.0, help="largest plate view angle")
    knob(p, "--no-mujoco", action="store_true", help="skip MuJoCo's contact and line-of-sight checks")
    p.add_argument("--seed", type=count(0, 2**32 - 1), default=0)
    p.add_argument("--plot", help="write the plan's predicted EE sigma plot (PNG) here")
    p.add_argument("--json", help="write the plan's predicted figures (JSON) here")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    p.set_defaults(func=func)


def _terms_arg(text: str) -> tuple[str, ...]:
    """`--terms`: the families the calibration will fit, named as `jaxcal calibrate --terms` names
    them (`auto` chooses from a capture's data, which a plan comes before)."""
    try:
        return check_terms(t.strip() for t in text.split(",") if t.strip())
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def _free(path, overwrite: bool, what: str, inputs=()) -> Path | None:
    """An output path that may be written (`jaxcal.io._files.check_output_file`): not an input or
    inside one (whatever `--overwrite` says), not existing without `--overwrite`, not a
    directory, in a folder that exists."""
    return check_output_file(path, inputs=inputs, overwrite=overwrite, what=what)


def _outputs(args, inputs) -> tuple[Path | None, Path | None]:
    """`--plot` and `--json`, checked (`_free`) and distinct from each other and from `--out`."""
    plot = _free(args.plot, args.overwrite, "--plot", inputs)
    out_json = _free(args.json, args.overwrite, "--json", inputs)
    named = [
        (w, resolved(p, w, error=OutputError))
        for w, p in (("--out", args.out), ("--plot", plot), ("--json", out_json))
        if p
    ]
    for i, (w, p) in enumerate(named):
        for w2, p2 in named[i + 1 :]:
            if p == p2:
                raise OutputError(f"{w} and {w2}: the same file {p}")
    return plot, out_json


def evaluation_table(console: Console, ev: PlanEvaluation, title: str) -> None:
    t = Table(title=title)
    t.add_column("")
    t.add_column("predicted", justify="right")
    t.add_row("frames / corners", f"{ev.frames} / {ev.corners}")
    t.add_row("EE RMS (1-sigma) mm", f"{1e3 * ev.ee_rms:.4f}")
    t.add_row("EE p95 mm", f"{1e3 * ev.ee_p95:.4f}")
    if ev.error_eigenvalues.size and np.isfinite(ev.ee_rms):
        lo, hi = (1e3 * ev.ee_rms * r for r in ev.ratio_interval)
        med = 1e3 * ev.ee_rms * ev.ratio_quantile(0.5)
        t.add_row("one capture's EE RMS mm", f"{med:.4f} median, {lo:.4f} .. {hi:.4f} (90 %)")
    t.add_row("pixel noise px", f"{ev.sigma_px:g}")
    if ev.terms:
        worst = sorted((ev.term_std or {}).items(), key=lambda kv: -kv[1])[:3]
        t.add_row(
            "non-geometric terms",
            f"{'+'.join(ev.terms)} fitted beside the geometry (largest std: "
            + ", ".join(f"{k} {v:.2g}" for k, v in worst)
            + ")",
        )
    for name, text in model_rows(ev):
        t.add_row(name, text)
    unidentifiable = len(ev.unidentifiable)
    t.add_row(
        "free parameters",
        f"{int(ev.free.sum())} ({len(ev.held)} held: {len(ev.held) - unidentifiable} redundant with others"
        + (f", {unidentifiable} unidentifiable)" if unidentifiable else ")"),
    )
    t.add_row("left unidentifiable", ", ".join(ev.unidentifiable) or "nothing")
    if ev.unidentifiable:
        t.add_row("EE RMS with their prior mm", f"{1e3 * ev.ee_rms_with_held:.4f}")
    console.print(t)
    s = Table(title="Largest predicted parameter standard deviations")
    s.add_column("parameter")
    s.add_column("1-sigma", justify="right")
    for name, text in parameter_rows(ev, top=8):
        s.add_row(name, text)
    console.print(s)


def model_rows(ev: PlanEvaluation) -> list[tuple[str, str]]:
    """The table's rows on the camera and arm models (none without them): the noise part is the
    table's EE RMS; the arm's bias and both together follow."""
    if ev.camera_model is None and ev.arm_model is None:
        return []
    rows = []
    if ev.camera_model is not None:
        rows.append(
            ("camera model", f"{ev.camera_model}: corner noise +{ev.added_sigma_px:g} px; {ev.camera_note}")
        )
    parts = ", ".join(f"{k} {1e3 * v:.4f}" for k, v in ev.bias_parts.items())
    rows += [
        ("arm model", ev.arm_model or "rigid (none given)"),
        (
            "EE bias RMS mm (arm)" + (f", with {'+'.join(ev.terms)}" if ev.terms else ""),
            f"{1e3 * ev.ee_bias_rms:.4f}" + (f" ({parts})" if parts else ""),
        ),
    ]
    if ev.terms:
        rigid = ", ".join(f"{k} {1e3 * v:.4f}" for k, v in ev.bias_parts_rigid.items())
        rows.append(
            (
                "EE bias RMS mm without the terms",
                f"{1e3 * ev.ee_bias_rigid_rms:.4f}" + (f" ({rigid})" if rigid else ""),
            )
        )
    lo, hi = ev.total_interval() if ev.error_eigenvalues.size else (np.nan, np.nan)
    rows.append(
        (
            "EE RMS noise + bias mm",
            f"{1e3 * ev.ee_total_rms:.4f} (p95 {1e3 * ev.ee_total_p95:.4f}; one capture "
            f"90 % in {1e3 * lo:.4f} .. {1e3 * hi:.4f})",
        )
    )
    return rows


def _figures_title(ev: PlanEvaluation) -> str:
    """The plot title's figures: sigma, or with the models noise, bias and both."""
    if ev.camera_model is None and ev.arm_model is None:
        return f"sigma {ev.sigma_px:g} px"
    return (
        f"sigma {ev.sigma_px:.4g} px ({ev.camera_model or 'no camera model'}), arm {ev.arm_model or 'rigid'}: "
        f"EE RMS noise {1e3 * ev.ee_rms:.3f}, bias {1e3 * ev.ee_bias_rms:.3f}, combined {1e3 * ev.ee_total_rms:.3f} mm"
    )


def _write_evaluation(console: Console, ev: PlanEvaluation, p, region, plot, out_json) -> None:
    if plot is not None:
        robot = Robot.load(p.robot)
        scene = scene_of(robot, p.camera, p.target, p.floor_z)
        where = (
            "the workspace"
            if region is None
            else f"the region {region[0].tolist()} .. {region[1].tolist()} m"
        )
        title = f"{ev.frames} frames, {_figures_title(ev)}: predicted EE error over {where}"
        plot_evaluation(ev, scene, workspace(robot, scene, region), plot, title)
        console.print(f"wrote {plot}")
    if out_json is not None:
        figures = ev.summary() | {
            "region": None if region is None else [list(map(float, region[0])), list(map(float, region[1]))],
            # SI: m (tx, ty, tz), rad (rx, ry, rz, zero offsets), a fraction (rates); and as the table shows them.
            "std": {n: float(s) for n, s, f in zip(ev.names, ev.std, ev.free) if f},
            "std_text": dict(parameter_rows(ev)),
        }
        write_text_atomic(out_json, json.dumps(figures, indent=1))
        console.print(f"wrote {out_json}")


def _models(args, capture_models):
    """`(CameraNoise | None, ArmFigures | None)` of `--camera-model` and `--arm`."""
    camera, arm = getattr(args, "camera_model", None), getattr(args, "arm", None)
    if camera is None and arm is None:
        return None, None
    if capture_models is None:
        raise PlanError("--camera-model and --arm need the simulator's presets (the jaxcal command line)")
    return capture_models(camera, arm)


def run_evaluate(args, console: Console, capture_models=None) -> int:
    if args.out is not None:
        raise PlanError(
            "jaxcal plan --evaluate: --out writes a new plan; to keep the figures give --json (and --plot)"
        )
    plot, out_json = _outputs(args, [args.evaluate])
    p = load_plan(args.evaluate)
    region = None if args.region is None else parse_region(args.region)
    camera, arm = _models(args, capture_models)
    ev = evaluate_plan(
        args.evaluate, region=region, sigma_px=args.sigma_px, camera_model=camera, arm=arm, terms=args.terms
    )
    where = "over the region" if region is not None else "over the workspace"
    evaluation_table(
        console, ev, f"{args.evaluate}: pre-evaluation ({len(views(p)[0])} planned frames, EE {where})"
    )
    _write_evaluation(console, ev, p, region, plot, out_json)
    return 0


def run_check_plan(args, console: Console) -> int:
    """`jaxcal plan --check RESULT`: the poses of a sensitive drift check (`jaxcal.planning._check`)."""
    out = _free(args.out, args.overwrite, "--out", [args.check]) if args.out else None
    out_json = _free(args.json, args.overwrite, "--json", [args.check]) if args.json else None
    cp = plan_check(args.check, args.budget, candidates=args.candidates, seed=args.seed)
    table = Table(title=f"jaxcal plan --check: {args.budget} poses for a drift check of {cp.result}")
    for col in ("pose", *cp.joint_names, "detectable mm (worst)", "deg (worst)"):
        table.add_column(col, justify="right")
    for k, (q, st) in enumerate(zip(cp.q, cp.steps)):
        table.add_row(
            str(k + 1),
            *(f"{np.degrees(v):.1f}" for v in q),
            f"{st.translation_mm_worst:.3f}",
            f"{st.rotation_deg_worst:.4f}",
        )
    console.print(table)
    last = cp.steps[-1]
    console.print(
        f"with these {args.budget} poses a camera move of {last.translation_mm_worst:.3f} mm (worst direction) or "
        f"{last.rotation_deg_worst:.4f} deg is detected with 95 % power; {args.budget} random poses of the "
        f"calibrated joint ranges showing the target: {cp.random.translation_mm_worst:.3f} mm, "
        f"{cp.random.rotation_deg_worst:.4f} deg (median of 20 draws; {cp.visible} of {cp.candidates} "
        f"candidates show the whole target at {cp.sigma_px:.3f} px corner noise). Joint angles in deg; "
        "no collision check: try the poses slowly"
    )
    if out is not None:
        write_poses(cp, out)
        console.print(f"wrote {out} (rad, a header naming the joints: jaxcal certify --poses reads it)")
    if out_json is not None:
        write_text_atomic(out_json, json.dumps(cp.to_json(), indent=1))
        console.print(f"wrote {out_json}")
    return 0


def run_plan(args, console: Console, checker_factory=None, capture_models=None) -> int:
    """`jaxcal plan`; `checker_factory(plan) -> checker` adds MuJoCo's checks;
    `capture_models(camera, arm)`: the records of `--camera-model` / `--arm` presets."""
    if args.evaluate:
        return run_evaluate(args, console, capture_models)
    if args.check:
        return run_check_plan(args, console)
    if args.out is None:
        raise PlanError("jaxcal plan: give --out PLAN.json (or --evaluate PLAN.json)")
    inputs = [args.camera_file, args.target, args.robot if Path(args.robot).is_file() else None]
    out = _free(args.out, args.overwrite, "--out", inputs)
    plot, out_json = _outputs(args, inputs)
    robot = Robot.load(args.robot)
    flange = robot.model.link_names[-1]
    taught = None if args.taught is None else parse_pose(args.taught, robot.model.num_joints)
    camera = None if args.camera_file is None else read_camera(args.camera_file, flange, args.resolution)
    target = None if args.target is None else read_target(args.target)
    if args.eye_in_hand and camera is not None and camera.mount == "world":
        raise PlanFileError(
            f"--eye-in-hand: camera file {args.camera_file} places a fixed camera (T_base_cam / T_cam_base); "
            "give T_flange_cam for a camera on the flange, or drop --eye-in-hand"
        )
    eye_in_hand = args.eye_in_hand or (camera is not None and camera.mount != "world")
    region = None if args.region is None else parse_region(args.region)
    models = _models(args, capture_models)
    limits = FeasibilityLimits(view_angle_deg=args.view_angle_deg)
    factory = None if args.no_mujoco else checker_factory
    t0 = time.perf_counter()
    res = plan(
        args.robot,
        camera=camera,
        target=target,
        taught=taught,
        frames=args.frames,
        eye_in_hand=eye_in_hand,
        distance=args.distance,
        resolution=args.resolution,
        floor_z=args.floor_z,
        region=region,
        limits=limits,
        sigma_px=args.sigma_px,
        method=args.method,
        starts=args.starts,
        steps=args.steps,
        candidates=args.candidates,
        amplitude_deg=args.amplitude_deg,
        goal_mm=args.goal_mm,
        greedy_baseline=args.baseline,
        seed=args.seed,
        checker_factory=factory,
        log=None if args.quiet else (lambda text: console.print(f"[dim]{text}[/dim]")),
        terms=args.terms,
    )
    if models != (None, None):  # the optimiser minimised the noise part; the prediction adds the models
        ev = evaluate_plan(
            res.plan,
            region=region,
            sigma_px=args.sigma_px,
            camera_model=models[0],
            arm=models[1],
            terms=args.terms,
        )
        res = replace(
            res, plan=replace(res.plan, prediction=res.plan.prediction | ev.summary()), evaluation=ev
        )
    evaluation_table(
        console, res.evaluation, f"Planned: {res.plan.frames} stop-and-shoot poses ({args.method})"
    )
    if res.greedy is not None:
        console.print(
            f"greedy D-optimal baseline at the same budget: EE RMS {1e3 * res.greedy.ee_rms:.4f} mm"
        )
    moved = sum(c.action == "moved" for c in res.plan.corrections)
    dropped = [c for c in res.plan.corrections if c.action == "dropped"]
    fails = dict(res.counts)
    drawn = {k: fails.pop(k, 0) for k in ("passed", "moved", "dropped")}
    console.print(
        f"the plan's poses: {moved} moved toward the taught pose, {len(dropped)} dropped"
        + (f" ({', '.join(sorted({c.reason for c in dropped}))})" if dropped else "")
        + f"; of the {sum(drawn.values())} random candidates it chose from: {drawn['passed']} feasible as "
        f"drawn, {drawn['moved']} moved toward the taught pose, {drawn['dropped']} dropped"
        + (f" (first failing checks: {', '.join(f'{k} {v}' for k, v in fails.items())})" if fails else "")
    )
    save_plan(res.plan, out)
    console.print(f"wrote {out} ({time.perf_counter() - t0:.1f} s)")
    _write_evaluation(console, res.evaluation, res.plan, region, plot, out_json)
    return 0
