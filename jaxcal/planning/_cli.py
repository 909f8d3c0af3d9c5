"""`jaxcal plan`: its run and its tables (`jaxcal.cli` adds the MuJoCo checker, and its
arguments: `jaxcal.cli._plan`).

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

import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

from .._progress import working
from ..errors import OutputError, PlanError, PlanFileError
from ..io._files import check_output_file, resolved, write_text_atomic
from ..io.plan_inputs import parse_pose, parse_region, read_camera, read_target
from ._api import Robot, evaluate_plan, plan, scene_of, views, workspace
from ._check import plan_check, write_poses
from ._evaluate import PlanEvaluation
from ._plan import load_plan, save_plan
from ._report import parameter_rows, plot_evaluation
from ._scene import FeasibilityLimits


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
    if ev.frames_infeasible:
        t.add_row("frames left out", ev.infeasible_note)
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
        if ev.terms_unpinned:
            t.add_row(
                "terms the frames cannot pin",
                f"{', '.join(ev.terms_unpinned)}: held at zero, as the calibration will hold them "
                "(their effect on the joint known to no better than 1 mrad)",
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
    with working(not args.quiet, f"evaluating {args.evaluate}", say=console.print):
        ev = evaluate_plan(
            args.evaluate,
            region=region,
            sigma_px=args.sigma_px,
            camera_model=camera,
            arm=arm,
            terms=args.terms,
        )
    where = "over the region" if region is not None else "over the workspace"
    evaluation_table(
        console, ev, f"{args.evaluate}: pre-evaluation ({len(views(p)[0])} planned frames, EE {where})"
    )
    _write_evaluation(console, ev, p, region, plot, out_json)
    if 2 * ev.frames_infeasible > ev.frames + ev.frames_infeasible:  # the figures are another capture's
        console.print(
            f"[bold]most of the plan's frames fail the feasibility checks[/bold] ({ev.frames_infeasible} of "
            f"{ev.frames + ev.frames_infeasible}): the figures are those of the {ev.frames} left, not of the "
            "capture the plan describes (exit 3)"
        )
        return 3
    return 0


def run_check_plan(args, console: Console) -> int:
    """`jaxcal plan --check RESULT`: the poses of a sensitive drift check (`jaxcal.planning._check`)."""
    out = _free(args.out, args.overwrite, "--out", [args.check]) if args.out else None
    out_json = _free(args.json, args.overwrite, "--json", [args.check]) if args.json else None
    with working(not args.quiet, f"choosing {args.budget} poses", say=console.print):
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
