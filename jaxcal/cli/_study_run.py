"""`jaxcal montecarlo`'s work (its options: `._study`): the vmapped sensitivity study and its tables."""

import io
import json
import sys
import time

import jax
import numpy as np
from rich.console import Console
from rich.table import Table

from .. import _montecarlo as mc
from .. import distributed
from .._axisfit import parameter_names
from .._device import result_is
from .._progress import working
from ..io._files import check_output_file, write_text_atomic
from ..robots import load_robot_file


def _setup(args):
    noise = mc.NoiseModel(
        position_mm=args.noise_mm, orientation_deg=args.noise_deg, encoder_deg=args.encoder_noise_deg
    )
    if isinstance(args.sweep_deg, tuple):
        raise ValueError("montecarlo --sweep-deg: one angle, every joint sweeps it (got one per joint)")
    plan = mc.SweepPlan(range_deg=args.sweep_deg, frames=args.frames_per_joint)
    return mc.default_setup(load_robot_file(args.robot), noise=noise, plan=plan)


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
    arc_ok = result_is(arcs.result)
    for j, name in enumerate(setup.nominal.joint_names):
        code = "ok" if arc_ok[j] else "FAILED"
        t.add_row(
            name,
            str(int(arcs.num_frames[j])),
            f"{1e3 * float(arcs.position_rms[j]):.3f}",
            f"{np.degrees(float(arcs.rotation_rms[j])):.4f}",
            f"{float(true.reduction_ratio[j]):.3f}",
            f"{float(fit.model.reduction_ratio[j]):.3f}",
            f"{float(s.axis_dir_deg[j]):.4f}",
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
    t.add_row("EE RMS mm", f"{float(s.ee_rms_mm_nominal):.3f}", f"{float(s.ee_rms_mm):.4f}")
    t.add_row("EE max mm", "", f"{float(s.ee_max_mm):.4f}")
    console.print(t)
    T = np.asarray(fit.T_cam_base)
    sd = np.asarray(fit.std[:6])
    console.print(
        f"T_cam_base: t = {np.round(T[:3, 3] * 1e3, 2).tolist()} mm "
        f"(std {np.round(sd[:3] * 1e3, 3).tolist()} mm, {np.round(np.degrees(sd[3:]), 4).tolist()} deg)"
    )
    ok = bool(result_is(fit.result)) and bool(arc_ok.all())
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


def run_montecarlo(args) -> int:
    check_output_file(args.json, overwrite=True, what="--json")
    setup = _setup(args)
    ok, first = True, distributed.current().first  # a distributed run: the first process reports
    if args.detail and first:
        console = Console(width=max(Console().width, 132))
        console.rule("[bold]One trial in detail: UR5e, joint-by-joint sweeps, analytic marker poses")
        t0 = time.perf_counter()
        ok = _single_trial_report(console, setup, args.seed)
        console.print(f"(single trial incl. compilation: {time.perf_counter() - t0:.1f} s)")
    else:
        console = Console(stderr=True) if first else Console(file=io.StringIO())
    console.print(
        f"Monte Carlo: {args.trials} trials of {setup.plan.frames} frames per sweep in one compiled call "
        "(compiling it comes first, the first run only: most of a minute on a few cores) ...",
        highlight=False,
        soft_wrap=True,
    )
    t0 = time.perf_counter()
    with working(first, f"Monte Carlo: {args.trials} trials", stream=sys.stderr):
        result = mc.monte_carlo(setup, jax.random.key(args.seed), args.trials, chunk=args.chunk)
        jax.block_until_ready(result)
    summary = mc.summarize(result) | {"seconds": time.perf_counter() - t0}
    _summary_table(
        console,
        summary,
        f"Monte Carlo: {args.trials} trials in one jit call ('seconds' includes compiling it, unless cached)",
    )
    if args.json and first:
        write_text_atomic(args.json, json.dumps(summary, indent=2))
    rate = float(np.asarray(result.success).mean())  # summary's success_rate
    ok = ok and rate == 1.0 if args.detail else rate > 0
    return 0 if ok else 1
