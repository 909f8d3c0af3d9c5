"""Benchmark: UR5e Monte Carlo trials, jaxcal's one jitted call (vmapped chunks) against SciPy in a loop.

What is compared: full six-joint UR5e calibration trials (a camera 1.5 m
away, one marker 5 cm off the flange, 40-frame sweeps, 0.1 mm / 0.05 deg
noise, encoders and orientations).

- jaxcal: `jaxcal._montecarlo.monte_carlo`, every trial in one jitted
  call (`vmap(run_trial)` over chunks of `CPU_CHUNK` trials). A trial synthesises the sweeps, fits them
  (six arc fits, vmapped, then the axis fit), runs the same axis fit on the
  exact arcs of its truth (`exact_arcs`: what noise-free arc fits return,
  the gauge reference of `score`) and scores the result. The first
  call compiles and runs; `compile_s` is the first call's time minus the
  best later one (`jaxcal_s`).
- SciPy: for each trial, the same sweeps (jaxcal's `synthesize_sweeps` on
  the trial's own keys, outside the clock, with jaxcal's closed-form arc
  starts), then the same residuals solved by
  `scipy.optimize.least_squares(method="lm")`: every joint's arc with the
  NumPy residual of `benchmarks/arcfit.py` (finite differences), jaxcal's
  arc covariance and axis-problem set-up as one jitted call, then the axis
  fit, on jaxcal's own `axis_residuals` jitted and called from NumPy (finite
  differences) with the same identifiability mask (`nominal_free_mask`).
  Like jaxcal's trial, SciPy then solves the axis fit again on the exact arcs.
  It is timed on a subset (`--scipy-trials`), scaled to `--trials`, and
  scored with jaxcal's `score`.

- Devices (`--device-counts 1,4`): the same `monte_carlo` call sharded over
  1, 4, ... devices, each count in a fresh process (JAX reads the device count
  at start). On the CPU the devices are forced
  (`XLA_FLAGS=--xla_force_host_platform_device_count`), twice as many as the
  mesh uses so that jaxlib's LAPACK kernels keep free pool threads (see
  `jaxcal._montecarlo.default_devices`); on a GPU host, the GPUs. Each entry
  of `device_scaling` holds `devices`, `trials_per_s` (best of `--repeats`
  after the compiling call), `compile_s`, and the largest difference of any
  trial's `ee_rms_mm` from the one-device run (`max_abs_diff_ee_rms_mm`).
- Processes (`--processes N`): the same call in N local processes of one distributed
  run (`jaxcal.distributed.run_local`; each process's devices, the mesh over all of
  them) against one process of one device: `process_scaling` holds both entries (as
  `device_scaling`'s), the largest difference of any trial's `ee_rms_mm`
  (`max_abs_diff_ee_rms_mm`) and `wall_ratio`, one process's run time over theirs.

How to run (from the repository root)::

    .venv/bin/python benchmarks/montecarlo.py --trials 200 --scipy-trials 10 --json results/montecarlo.json
    .venv/bin/python benchmarks/montecarlo.py --quick      # smoke run
    .venv/bin/python benchmarks/montecarlo.py --scaling-only --trials 64 --device-counts 1,4
    .venv/bin/python benchmarks/montecarlo.py --scaling-only --trials 64 --device-counts '' --processes 2

The JSON (printed, and written atomically with `--json`) holds `trials`,
`jaxcal_s`, `compile_s`, `scipy_s`, `speedup`, `success_rate`,
`ee_rms_mm_median`, `scipy_ee_rms_mm_median`, `device`, `devices` and
`trials_per_s` (the main run's mesh and rate), `device_scaling`, `notes`, and
details (SciPy's time per stage, solver steps on both sides).
"""

import argparse
import dataclasses
import json
import os
import platform
import subprocess
import sys
import time
from collections.abc import Callable
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import scipy
from arcfit import arc_residuals_np, flat_params, jax_jacobian, unflatten_params, write_json
from jax.flatten_util import ravel_pytree
from scipy.optimize import least_squares

from jaxcal._arcfit import _ARC, _summarise
from jaxcal._arcmodel import free_mask, initialise_arc
from jaxcal._axisfit import (
    AxisFitParams,
    AxisFitProblem,
    KinematicCorrection,
    _meas_dim,
    _whitening,
    apply_correction,
    axis_residuals,
    register_lines,
)
from jaxcal._geometry import pose_inverse, se3_exp
from jaxcal._kinematics import KinematicModel, forward_kinematics
from jaxcal._montecarlo import (
    SWEEP_OPTIONS,
    SweepPlan,
    _free_mask_jit,
    default_setup,
    draw_trial_truth,
    dynamic_setup,
    exact_arcs,
    fit_sweeps,
    monte_carlo,
    score,
    summarize,
    synthesize_sweeps,
    trial_mesh,
)
from jaxcal.distributed import join, run_local
from jaxcal.robots import load_robot

# --------------------------------------------------------------------------- the trials' inputs


def _trial_inputs(setup, key):
    """What `run_trial` draws from `key`: the truth, the noisy sweeps, the
    validation configurations, and jaxcal's closed-form arc starts (SciPy's
    starting point)."""
    k_truth, k_noise, k_val = jax.random.split(key, 3)
    true, T_cam_base, T_flange_marker = draw_trial_truth(setup, k_truth)
    kw = dict(
        nominal_ratio=setup.nominal.reduction_ratio,
        use_encoders=setup.use_encoders,
        use_orientations=setup.use_orientations,
    )
    data = synthesize_sweeps(true, T_cam_base, T_flange_marker, setup.plan, setup.noise, k_noise, **kw)
    params0, ref = jax.vmap(initialise_arc)(data)
    q_val = jax.random.uniform(
        k_val, (setup.n_validation, setup.nominal.num_joints), minval=-jnp.pi, maxval=jnp.pi
    )
    return dict(
        true=true, T_cam_base=T_cam_base, T_flange_marker=T_flange_marker, data=data, params0=params0, ref=ref
    ), q_val


# --------------------------------------------------------------------------- SciPy's pipeline


class Calibrated(eqx.Module):
    """What `score` reads from an `AxisFitResult`."""

    model: KinematicModel
    T_flange_marker: jax.Array
    T_cam_base: jax.Array


class AxisStage(NamedTuple):
    """jaxcal's pieces around SciPy's solves, each jitted once for every trial."""

    setup: Callable  # (x_arcs, ref, data) -> AxisFitProblem
    setup_exact: Callable  # (problem, true, T_cam_base, T_flange_marker) -> AxisFitProblem
    residuals: Callable  # (x_free, problem) -> flat whitened residuals
    jacobian: Callable  # (x_free, problem) -> their Jacobian (jax.jacfwd)
    finish: Callable  # (x_free, problem) -> Calibrated
    n_free: int


def make_axis_stage(nominal: KinematicModel, free: np.ndarray, n_markers: int) -> AxisStage:
    """Jitted closures over the nominal model and the fixed identifiability mask `free`.

    Plain `jax.jit` (not `eqx.filter_jit`, whose per-call filtering doubles the
    dispatch time of these ~100 us calls).
    """
    n = nominal.num_joints
    template = AxisFitParams(
        cam=jnp.zeros(6),
        correction=KinematicCorrection(
            origin=jnp.zeros((n, 6)), zero_offset=jnp.zeros(n), tool=jnp.zeros((n_markers, 6))
        ),
    )
    flat0, unravel = ravel_pytree(template)
    idx = np.flatnonzero(free)

    def params_of(xf):
        return unravel(jnp.zeros_like(flat0).at[idx].set(xf))

    def setup(x_arcs, ref, data):
        """Arc results from SciPy's arc solutions (jaxcal's covariance and summary, as
        `fit_arc(scale_covariance=False)`), then `fit_axes`' set-up of the axis problem."""

        def one(x, ref, data):
            params = unflatten_params(x, data.positions.shape[0])
            mask = free_mask(params, data, ref)
            return _summarise(_ARC, params, ref, data, mask, optx.RESULTS.successful, jnp.asarray(0), False)

        return problem_of(jax.vmap(one)(x_arcs, ref, data))

    def setup_exact(problem, true, T_cam_base, T_flange_marker):
        """The reference fit's problem: `run_trial`'s exact arcs from the noisy ones."""
        return problem_of(
            exact_arcs(problem.arcs, true, T_cam_base, T_flange_marker, nominal.reduction_ratio)
        )

    def problem_of(arcs):
        T_cam_base0 = register_lines(nominal, arcs)
        T_cam_flange = T_cam_base0 @ forward_kinematics(nominal, jnp.zeros(n))[-1]
        T_flange_marker = jnp.einsum("ab,mbc->mac", pose_inverse(T_cam_flange), arcs.T_cam_marker0[0])
        k = _meas_dim(arcs, arcs.has_encoder)
        return AxisFitProblem(
            nominal=nominal,
            T_flange_marker0=T_flange_marker,
            T_cam_base0=T_cam_base0,
            arcs=arcs,
            sqrt_info=jax.vmap(_whitening)(arcs.meas_cov[:, :k, :k]),
            use_poses=arcs.has_encoder,
        )

    def residuals(xf, problem):
        return axis_residuals(params_of(xf), problem).reshape(-1)

    def finish(xf, problem):
        params = params_of(xf)
        model, mounts = apply_correction(nominal, problem.T_flange_marker0, params.correction)
        model = eqx.tree_at(
            lambda m: (m.reduction_ratio, m.T_flange_tool),
            model,
            (nominal.reduction_ratio / problem.arcs.rate, mounts[0]),
        )
        T_cam_base = problem.T_cam_base0 @ se3_exp(params.cam)
        return Calibrated(model=model, T_flange_marker=mounts, T_cam_base=T_cam_base)

    return AxisStage(
        setup=jax.jit(setup),
        setup_exact=jax.jit(setup_exact),
        residuals=jax.jit(residuals),
        jacobian=jax.jit(jax.jacfwd(residuals)),
        finish=jax.jit(finish),
        n_free=int(idx.size),
    )


def scipy_fit(stage: AxisStage, arrays: dict, clock: dict, stats: tuple, *, exact_jac: bool) -> list:
    """One trial through SciPy, as `run_trial`: the six arc fits, jaxcal's set-up,
    the axis fit, then the reference axis fit on the exact arcs (`exact_arcs`).

    With `exact_jac`, every solve gets jaxcal's Jacobian (jitted `jax.jacfwd`)
    instead of finite differences. **Returns:** the two `Calibrated`.
    """
    t0 = time.perf_counter()
    x_arcs = []
    for j in range(arrays["P"].shape[0]):
        args = tuple(arrays[k][j] for k in ("P", "O", "enc", "R_ref", "c", "O_ref")) + (arrays["w"][j],)
        jac = "2-point"
        if exact_jac:

            def jac(x, *_, a=arrays["jac_args"][j]):
                return np.asarray(jax_jacobian(x, *a))

        res = least_squares(arc_residuals_np, arrays["x0"][j], jac=jac, method="lm", args=args)
        x_arcs.append(res.x)
        stats[0]["arc_nfev"].append(res.nfev)
        stats[0]["arc_njev"].append(res.njev)
        stats[0]["ok"].append(res.status > 0)
    t1 = time.perf_counter()
    clock["arc_lm"] += t1 - t0
    problem = jax.block_until_ready(stage.setup(np.stack(x_arcs), arrays["ref"], arrays["data"]))
    clock["jaxcal_glue"] += time.perf_counter() - t1
    cal = _scipy_axes(stage, problem, clock, stats[0], exact_jac=exact_jac)
    t2 = time.perf_counter()
    problem = jax.block_until_ready(stage.setup_exact(problem, *arrays["truth"]))
    clock["jaxcal_glue"] += time.perf_counter() - t2
    return [cal, _scipy_axes(stage, problem, clock, stats[1], exact_jac=exact_jac)]


def _scipy_axes(stage: AxisStage, problem, clock: dict, stats: dict, *, exact_jac: bool) -> Calibrated:
    """The axis fit by SciPy on a set-up problem, then jaxcal's read-out."""
    t0 = time.perf_counter()

    def fun(xf):
        return np.asarray(stage.residuals(xf, problem))

    def axis_jac(xf):
        return np.asarray(stage.jacobian(xf, problem))

    res = least_squares(fun, np.zeros(stage.n_free), jac=axis_jac if exact_jac else "2-point", method="lm")
    stats["axis_nfev"].append(res.nfev)
    stats["axis_njev"].append(res.njev)
    stats["ok"].append(res.status > 0)
    t1 = time.perf_counter()
    cal = jax.block_until_ready(stage.finish(res.x, problem))
    clock["axis_lm"] += t1 - t0
    clock["jaxcal_glue"] += time.perf_counter() - t1
    return cal


def time_scipy(stage: AxisStage, arrays: list, *, exact_jac: bool) -> tuple[float, list, dict, tuple]:
    """Every measured trial's noisy and reference fits, after one untimed warm-up trial.

    **Returns:** the wall time, the `Calibrated` pairs, the time per stage, and
    the solver statistics of the noisy and of the reference fits.
    """
    scipy_fit(
        stage, arrays[0], dict.fromkeys(_STAGES, 0.0), (_new_stats(), _new_stats()), exact_jac=exact_jac
    )
    clock, stats, cals = dict.fromkeys(_STAGES, 0.0), (_new_stats(), _new_stats()), []
    t0 = time.perf_counter()
    for trial in arrays:
        cals.append(scipy_fit(stage, trial, clock, stats, exact_jac=exact_jac))
    return time.perf_counter() - t0, cals, clock, stats


_STAGES = ("arc_lm", "jaxcal_glue", "axis_lm")


def _numpy_arrays(inputs: dict, trial: int) -> dict:
    """NumPy views of one trial's sweeps and their starts, and its truth."""
    data, ref, params0, truth = jax.tree.map(
        lambda a: a[trial],
        (
            inputs["data"],
            inputs["ref"],
            inputs["params0"],
            (inputs["true"], inputs["T_cam_base"], inputs["T_flange_marker"]),
        ),
    )
    W = np.asarray(data.sqrt_info)  # (J, M, F, 6, 6)
    w = np.diagonal(W[:, 0, 0], axis1=-2, axis2=-1)  # (J, 6)
    if not np.allclose(W, w[:, None, None, :, None] * np.eye(6)):
        raise ValueError("the NumPy residual assumes one diagonal whitening per sweep")
    if not np.all(np.asarray(data.mask)):
        raise ValueError("the NumPy residual assumes every frame observed")
    J = W.shape[0]
    return dict(
        P=np.asarray(data.positions),
        O=np.asarray(data.orientations),
        enc=np.asarray(data.encoder),
        R_ref=np.asarray(ref.R_ref),
        c=np.asarray(ref.c),
        O_ref=np.asarray(ref.O_ref),
        w=w,
        x0=[flat_params(jax.tree.map(lambda a, j=j: a[j], params0)) for j in range(J)],
        jac_args=[
            (
                data.positions[j],
                data.orientations[j],
                data.encoder[j],
                ref.R_ref[j],
                ref.c[j],
                ref.O_ref[j],
                W[j],
            )
            for j in range(J)
        ],
        ref=ref,
        data=data,
        truth=truth,
    )


# --------------------------------------------------------------------------- main


def run(trials: int, n_scipy: int, repeats: int, seed: int, frames: int) -> dict:
    setup = default_setup(load_robot("ur5e"), plan=SweepPlan(frames=frames))
    key = jax.random.key(seed)

    # jaxcal: first call = compile + run, then the best of `repeats` runs.
    t0 = time.perf_counter()
    result = jax.block_until_ready(monte_carlo(setup, key, trials))
    first_s = time.perf_counter() - t0
    run_s = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        result = jax.block_until_ready(monte_carlo(setup, key, trials))
        run_s = min(run_s, time.perf_counter() - t0)
    summary = summarize(result)

    # SciPy: the same trials' data (the keys monte_carlo splits), made outside the clock.
    n_scipy = min(n_scipy, trials)
    dyn = dynamic_setup(setup)
    free = np.asarray(_free_mask_jit(dyn))  # what monte_carlo gives its trials (already compiled)
    keys = jax.random.split(key, trials)[:n_scipy]
    inputs, q_val = jax.jit(jax.vmap(_trial_inputs, in_axes=(None, 0)))(dyn, keys)
    stage = make_axis_stage(dyn.nominal, free, setup.T_flange_marker.shape[0])
    arrays = [_numpy_arrays(inputs, i) for i in range(n_scipy)]
    scipy_t, cals, clock, stats = time_scipy(stage, arrays, exact_jac=False)
    scipy_jac_t, _, clock_jac, stats_jac = time_scipy(stage, arrays, exact_jac=True)

    # Score SciPy's calibrations as run_trial scores jaxcal's.
    fit, fit_exact = (jax.tree.map(lambda *a: jnp.stack(a), *[c[k] for c in cals]) for k in (0, 1))
    scores = jax.jit(
        jax.vmap(lambda f, t, T, M, q, g: score(f, t, T, M, dyn.nominal, q, g)),
    )(fit, inputs["true"], inputs["T_cam_base"], inputs["T_flange_marker"], q_val, fit_exact.T_cam_base)
    scipy_ee = np.asarray(scores.ee_rms_mm)
    jax_ee = np.asarray(result.ee_rms_mm)[:n_scipy]

    # jaxcal's own solver steps on the same noisy sweeps (not part of any timing).
    noisy = inputs["data"]
    sweep_options = dataclasses.replace(SWEEP_OPTIONS, max_steps=setup.max_steps)
    arcs, axes = jax.jit(jax.vmap(lambda d: fit_sweeps(dyn.nominal, d, free=free, options=sweep_options)))(
        noisy
    )
    cam_diff_mm = 1e3 * np.max(
        np.abs(np.asarray(axes.T_cam_base)[:, :3, 3] - np.asarray(fit.T_cam_base)[:, :3, 3])
    )

    scipy_s = scipy_t / n_scipy * trials
    scipy_jac_s = scipy_jac_t / n_scipy * trials
    arc_steps, axis_steps = np.asarray(arcs.num_steps), np.asarray(axes.num_steps)
    return dict(
        trials=trials,
        jaxcal_s=run_s,
        compile_s=first_s - run_s,
        scipy_s=scipy_s,
        speedup=scipy_s / run_s,
        scipy_jac_s=scipy_jac_s,
        speedup_vs_jac=scipy_jac_s / run_s,
        success_rate=summary["success_rate"],
        ee_rms_mm_median=summary["ee_rms_mm_median"],
        scipy_ee_rms_mm_median=float(np.median(scipy_ee)),
        device=jax.devices()[0].platform,
        devices=trial_mesh().size,
        trials_per_s=trials / run_s,
        scipy_measured_trials=n_scipy,
        scipy_per_trial_s=scipy_t / n_scipy,
        jaxcal_per_trial_ms=1e3 * run_s / trials,
        jaxcal_first_call_s=first_s,
        scipy_time_per_trial_s={k: v / n_scipy for k, v in clock.items()},
        scipy_jac_per_trial_s=scipy_jac_t / n_scipy,
        scipy_jac_time_per_trial_s={k: v / n_scipy for k, v in clock_jac.items()},
        scipy_success_rate=float(np.mean(stats[0]["ok"] + stats[1]["ok"])),
        scipy_jac_success_rate=float(np.mean(stats_jac[0]["ok"] + stats_jac[1]["ok"])),
        scipy_nfev={
            f"{name}_{which}": _describe(st[name])
            for which, st in zip(("noisy", "reference"), stats)
            for name in ("arc_nfev", "arc_njev", "axis_nfev", "axis_njev")
        },
        scipy_jac_nfev={
            f"{name}_{which}": _describe(st[name])
            for which, st in zip(("noisy", "reference"), stats_jac)
            for name in ("arc_nfev", "arc_njev", "axis_nfev", "axis_njev")
        },
        axis_free_parameters=int(free.sum()),
        jaxcal_arc_num_steps=_describe(arc_steps),
        jaxcal_axis_num_steps=_describe(axis_steps),
        ee_rms_mm_median_same_trials=float(np.median(jax_ee)),
        ee_rms_mm_max_abs_diff_same_trials=float(np.max(np.abs(scipy_ee - jax_ee))),
        cam_translation_max_abs_diff_mm=float(cam_diff_mm),
        jaxcal_summary=summary,
        repeats=repeats,
        seed=seed,
        frames=frames,
        versions=dict(
            jax=jax.__version__,
            scipy=scipy.__version__,
            numpy=np.__version__,
            python=platform.python_version(),
        ),
        cpu_count=os.cpu_count(),
        notes=[
            "jaxcal_s is one monte_carlo call: data synthesis, the noisy fits, the reference axis fit on the exact "
            "arcs (exact_arcs, the gauge of score), and scoring "
            "of every trial (plus the nominal identifiability mask). compile_s = first call - best later "
            "call (it includes compiling that mask's fit).",
            "SciPy's clock covers the fits only (the noisy arc and axis fits and the reference axis fit, as "
            "jaxcal's trial): the data, "
            "jaxcal's closed-form arc starts (initialise_arc) and the scoring are computed beforehand or "
            "after, which favours SciPy. scipy_s = per-trial time x trials, measured on scipy_measured_trials.",
            "Arc fits: least_squares(method='lm') with finite differences on the NumPy residual of "
            "benchmarks/arcfit.py (the same model as jaxcal's arc_residuals).",
            "Axis fit: jaxcal's axis_residuals wrapped by a jitted single-problem function called from NumPy "
            "(not rewritten in NumPy), with finite differences, over the parameters free in "
            "nominal_free_mask (the mask monte_carlo gives jaxcal's fits).",
            "scipy_jac_s: the same SciPy pipeline with exact Jacobians for both solves, from jitted "
            "jax.jacfwd of jaxcal's arc_residuals and axis_residuals called from NumPy (dispatch included).",
            "Between the two solves SciPy's pipeline calls jaxcal (one jitted call per sweep set) for the arc "
            "covariance and the axis-problem set-up (register_lines, whitening), as fit_arc/fit_axes do; "
            "that is scipy_time_per_trial_s.jaxcal_glue. SciPy skips the axis fit's final covariance and SVD.",
            "Tolerances: jaxcal rtol=1e-8, atol=3e-2 (in noise standard deviations), SciPy's defaults "
            "ftol=xtol=gtol=1e-8. jaxcal_*_num_steps are from a separate jit(vmap(fit_sweeps)) on the "
            "SciPy trials' noisy sweeps; under vmap every fit runs as many steps as the slowest in the batch.",
        ],
    )


def scaling_worker(devices: int, trials: int, repeats: int, seed: int, frames: int) -> dict:
    """One device count's timing (run in a process started by `device_scaling`; 0: every
    device of every process, in a distributed run that `process_scaling` starts)."""
    setup = default_setup(load_robot("ur5e"), plan=SweepPlan(frames=frames))
    key, mesh = jax.random.key(seed), jax.devices()[: devices or None]
    t0 = time.perf_counter()
    result = jax.block_until_ready(monte_carlo(setup, key, trials, devices=mesh))
    first_s = time.perf_counter() - t0
    run_s = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        result = jax.block_until_ready(monte_carlo(setup, key, trials, devices=mesh))
        run_s = min(run_s, time.perf_counter() - t0)
    return dict(
        devices=len(mesh),
        platform=mesh[0].platform,
        visible_devices=jax.device_count(),
        trials=trials,
        trials_per_s=trials / run_s,
        run_s=run_s,
        compile_s=first_s - run_s,
        success_rate=float(np.mean(np.asarray(result.success))),
        ee_rms_mm=np.asarray(result.ee_rms_mm).tolist(),
    )


def _worker_args(devices: int, trials: int, repeats: int, seed: int, frames: int) -> list[str]:
    return [
        __file__,
        "--scaling-worker",
        str(devices),
        "--trials",
        str(trials),
        "--repeats",
        str(repeats),
    ] + [
        "--seed",
        str(seed),
        "--frames",
        str(frames),
    ]


def _one_count(n: int, trials: int, repeats: int, seed: int, frames: int) -> dict:
    """`scaling_worker(n, ...)` in a fresh process; on a CPU-only host with forced devices (twice
    the count: spare pool threads; none for one device, so that its program is this process's,
    cached)."""
    env = dict(os.environ)
    if jax.devices()[0].platform == "cpu" and n > 1:
        env["XLA_FLAGS"] = (
            env.get("XLA_FLAGS", "") + f" --xla_force_host_platform_device_count={2 * n}"
        ).strip()
    proc = subprocess.run(
        [sys.executable, *_worker_args(n, trials, repeats, seed, frames)],
        env=env,
        capture_output=True,
        text=True,
        check=True,
    )
    return json.loads(proc.stdout.strip().splitlines()[-1])


def device_scaling(counts: list[int], trials: int, repeats: int, seed: int, frames: int) -> list[dict]:
    """`scaling_worker` for every device count, each in a fresh process (`_one_count`)."""
    out = [_one_count(n, trials, repeats, seed, frames) for n in counts]
    ref = np.asarray(out[0]["ee_rms_mm"])
    for entry in out:
        entry["max_abs_diff_ee_rms_mm"] = float(np.max(np.abs(np.asarray(entry.pop("ee_rms_mm")) - ref)))
    return out


def process_scaling(processes: int, trials: int, repeats: int, seed: int, frames: int) -> dict:
    """`scaling_worker` in one process of one device, then in `processes` local processes of one
    distributed run over every device (`jaxcal.distributed.run_local`, each process its own)."""
    one = _one_count(1, trials, repeats, seed, frames) | {"processes": 1}
    env = dict(os.environ)  # one device a process: no forced device count, the other XLA flags kept
    env["XLA_FLAGS"] = " ".join(f for f in env.get("XLA_FLAGS", "").split() if "force_host_platform" not in f)
    argv = [sys.executable, *_worker_args(0, trials, repeats, seed, frames)]
    runs = run_local(argv, processes, env=env, capture=True)
    if any(r.returncode for r in runs):
        raise RuntimeError(
            "the distributed Monte Carlo failed: " + " | ".join(r.stderr[-1500:] for r in runs)
        )
    many = json.loads(runs[0].stdout.strip().splitlines()[-1]) | {"processes": processes}
    diff = np.max(np.abs(np.asarray(many.pop("ee_rms_mm")) - np.asarray(one.pop("ee_rms_mm"))))
    return {
        "one": one,
        "many": many,
        "max_abs_diff_ee_rms_mm": float(diff),
        "wall_ratio": one["run_s"] / many["run_s"],
    }


def _new_stats() -> dict:
    return dict(arc_nfev=[], arc_njev=[], axis_nfev=[], axis_njev=[], ok=[])


def _describe(x) -> dict | None:
    if not len(x) or any(v is None for v in x):  # SciPy reports no njev for finite differences
        return None
    x = np.asarray(x)
    return dict(mean=float(x.mean()), max=int(x.max()))


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--trials", type=int, default=1000, help="trials run by jaxcal")
    parser.add_argument("--scipy-trials", type=int, default=20, help="trials timed with SciPy")
    parser.add_argument("--frames", type=int, default=40, help="frames per joint sweep")
    parser.add_argument(
        "--repeats", type=int, default=2, help="timed jaxcal runs after the first (best kept)"
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--quick", action="store_true", help="a small smoke run")
    parser.add_argument("--json", metavar="OUT", help="also write the JSON here")
    parser.add_argument(
        "--device-counts", default="1,4", help="devices of device_scaling, comma-separated ('' to skip)"
    )
    parser.add_argument(
        "--scaling-only", action="store_true", help="only device_scaling and process_scaling (no SciPy)"
    )
    parser.add_argument(
        "--processes", type=int, default=1, help="process_scaling over this many local processes (1: not)"
    )
    parser.add_argument("--scaling-worker", type=int, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.scaling_worker is not None:
        processes = join()  # a distributed run where `process_scaling` started this one
        report = scaling_worker(args.scaling_worker, args.trials, args.repeats, args.seed, args.frames)
        if processes.first:
            print(json.dumps(report))
        return
    if args.quick:
        args.trials, args.scipy_trials, args.repeats = 8, 2, 1
    counts = [int(c) for c in args.device_counts.split(",") if c.strip()]
    result = (
        {} if args.scaling_only else run(args.trials, args.scipy_trials, args.repeats, args.seed, args.frames)
    )
    if counts:
        scaling = device_scaling(counts, args.trials, args.repeats, args.seed, args.frames)
        result["device_scaling"] = scaling
        result["device_scaling_note"] = (
            f"{os.cpu_count()} cores; on the CPU each count runs on twice as many forced host devices "
            "(spare intra-op pool threads for jaxlib's LAPACK kernels), in its own process"
        )
    if args.processes > 1:
        result["process_scaling"] = process_scaling(
            args.processes, args.trials, args.repeats, args.seed, args.frames
        )
    if args.json:
        write_json(result, args.json)
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
