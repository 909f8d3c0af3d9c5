"""Synthetic sweeps and vmapped Monte Carlo sensitivity studies.

A trial draws a "true" arm from the nominal one (`perturb_model`) and a true
camera pose, synthesises the marker poses of joint-by-joint sweeps
analytically (forward kinematics, no rendering), adds noise, runs the arc
fits (vmapped over joints) and the axis fit, and scores the result against
the truth. `monte_carlo` runs N trials in one jitted call (vmapped chunks); a
failed trial is flagged through optimistix's result codes and never stops
the batch.

Gauge: the camera only sees lines, so the robot's base frame is defined by
joint 1's nominal frame (its origin and zero offset are held at nominal by
the identifiability analysis). Truths are drawn with joint 1's frame at
nominal accordingly (`anchor_base`), so that $T_{cam,base}$ errors compare
like with like.
"""

import functools
import os
import sys
from dataclasses import replace

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P
from jaxtyping import Array, Bool, Float, PRNGKeyArray

from ._arcdata import ArcData, make_arc_data
from ._arcfit import ARC_OPTIONS, ArcFitResult, fit_arc, fit_joint_sweeps
from ._arcmodel import line_to_params
from ._axisfit import AXIS_OPTIONS, fit_axes
from ._geometry import make_pose, matmul, se3_exp, so3_exp, so3_log
from ._kinematics import (
    REVOLUTE,
    KinematicModel,
    PerturbationScales,
    anchor_base,
    forward_kinematics,
    joint_axes,
    perturb_model,
)
from ._lsq import LMOptions
from ._processes import current
from ._progress import working
from ._scoring import score as score  # re-exported

_MM = 1e-3
_DEG = jnp.pi / 180.0


class SweepPlan(eqx.Module):
    """Joint-by-joint sweeps: each joint turns through `range_deg` (centred on
    its zero) in `frames` camera frames while the others stay at zero."""

    range_deg: float = 60.0
    frames: int = eqx.field(static=True, default=40)


class NoiseModel(eqx.Module):
    """Measurement noise (standard deviations): marker position (mm),
    orientation (deg) and encoder angle (deg of joint motion)."""

    position_mm: float = 0.1
    orientation_deg: float = 0.05
    encoder_deg: float = 0.0


def sweep_commands(
    model: KinematicModel, plan: SweepPlan, home: Float[Array, "joints joints"] | None = None
) -> Float[Array, "joints frames joints"]:
    """Commanded joint positions of every sweep: joint j moves, the others at 0
    (or at row j of `home`, whose entry j is zero)."""
    n = model.num_joints
    half = 0.5 * plan.range_deg * _DEG
    ramp = jnp.linspace(-half, half, plan.frames)
    q = jnp.eye(n)[:, None, :] * ramp[None, :, None]
    return q if home is None else q + home[:, None, :]


def synthesize_sweeps(
    true: KinematicModel,
    T_cam_base: Float[Array, "4 4"],
    T_flange_marker: Float[Array, "markers 4 4"],
    plan: SweepPlan,
    noise: NoiseModel,
    key: PRNGKeyArray,
    *,
    nominal_ratio: Float[Array, " joints"],
    use_encoders: bool = True,
    use_orientations: bool = True,
    home: Float[Array, "joints joints"] | None = None,
) -> ArcData:
    """Noisy marker poses of every joint sweep, stacked over joints.

    The controller commands motor angles $m = q\\,\\rho_{nom}$; the joint really
    turns by $m / \\rho_{true}$; the encoder reports $\\alpha = m/\\rho_{nom}$ plus
    noise (so the arc rate is $\\rho_{nom}/\\rho_{true}$).
    """
    q_nom = sweep_commands(true, plan, home)  # (J, F, J): what the controller intended
    motor = q_nom * nominal_ratio
    q_true = motor / true.reduction_ratio
    k_p, k_r, k_e = jax.random.split(key, 3)
    n, F, M = true.num_joints, plan.frames, T_flange_marker.shape[0]
    T_base_flange = jax.vmap(jax.vmap(lambda q: forward_kinematics(true, q)[-1]))(q_true)  # (J, F, 4, 4)
    T = jnp.einsum("ab,jfbc,mcd->jmfad", T_cam_base, T_base_flange, T_flange_marker)
    pos = T[..., :3, 3] + noise.position_mm * _MM * jax.random.normal(k_p, (n, M, F, 3))
    dR = jax.vmap(so3_exp)(noise.orientation_deg * _DEG * jax.random.normal(k_r, (n * M * F, 3)))
    rot = matmul(dR.reshape(n, M, F, 3, 3), T[..., :3, :3])
    alpha = jnp.einsum("jfj->jf", q_nom) + noise.encoder_deg * _DEG * jax.random.normal(k_e, (n, F))
    sig_p = jnp.maximum(noise.position_mm * _MM, 1e-7)
    sig_r = jnp.maximum(noise.orientation_deg * _DEG, 1e-7)
    return jax.vmap(
        lambda P, O, a: make_arc_data(
            P,
            O if use_orientations else None,
            a if use_encoders else None,
            sigma_position=sig_p,
            sigma_rotation=sig_r,
        )
    )(pos, rot, alpha)


#: `fit_sweeps`' solver settings, the arc fits' and the axis fit's alike: their tolerances
#: (`ARC_OPTIONS`, `AXIS_OPTIONS`: whitened residuals) with up to 100 steps each.
SWEEP_OPTIONS = replace(AXIS_OPTIONS, max_steps=100)


def fit_sweeps(
    nominal: KinematicModel, data: ArcData, *, free=None, options: LMOptions = SWEEP_OPTIONS, **axis_kwargs
) -> tuple:
    """Arc fits of every joint (vmapped; a prismatic joint's sweep by its line
    fit, `jaxcal._arcfit.fit_joint_sweeps`) followed by the axis fit, each solve with
    `options`; `axis_kwargs` go to `fit_axes`."""
    arcs = fit_joint_sweeps(data, nominal.joint_types, scale_covariance=False, options=options)
    return arcs, fit_axes(nominal, arcs, free=free, options=options, **axis_kwargs)


class TrialResult(eqx.Module):
    """Errors of one trial against its truth (a leading trial axis in batches).

    - `ee_rms_mm`, `ee_max_mm`: marker (tool point) position error in the camera
      frame over random validation configurations, calibrated vs true.
    - `ee_rms_mm_nominal`: the same for the nominal model with the calibrated
      camera pose (what the arm would do uncalibrated).
    - Without encoders the sweeps do not fix the last joint's zero nor the
      marker mount (both held at nominal), so every error is taken against the
      same fit on noise-free sweeps: the truth in that gauge.
    - `cam_rot_deg`, `cam_trans_mm`: $T_{cam,base}$ error against the truth in
      the estimator's gauge (the same fit on noise-free sweeps).
    - `axis_dir_deg`, `axis_pos_mm`: per joint, the angle and the distance
      between the estimated and true axis lines at the zero configuration.
    - `ratio_err_percent`: per joint reduction-ratio error (NaN without encoders).
    - `arc_result` (per joint), `axis_result`: optimistix result codes;
      `success`: all of them succeeded and the result is finite.
    """

    ee_rms_mm: Float[Array, ""]
    ee_max_mm: Float[Array, ""]
    ee_rms_mm_nominal: Float[Array, ""]
    cam_rot_deg: Float[Array, ""]
    cam_trans_mm: Float[Array, ""]
    axis_dir_deg: Float[Array, " joints"]
    axis_pos_mm: Float[Array, " joints"]
    ratio_err_percent: Float[Array, " joints"]
    arc_result: optx.RESULTS
    axis_result: optx.RESULTS
    success: Bool[Array, ""]


class MonteCarloSetup(eqx.Module):
    """Fixed inputs of a Monte Carlo study."""

    nominal: KinematicModel
    T_cam_base: Float[Array, "4 4"]
    T_flange_marker: Float[Array, "markers 4 4"]
    scales: PerturbationScales
    noise: NoiseModel
    plan: SweepPlan
    camera_sigma_mm: float = 20.0
    camera_sigma_deg: float = 2.0
    mount_sigma_mm: float = 2.0
    mount_sigma_deg: float = 1.0
    n_validation: int = eqx.field(static=True, default=100)
    use_encoders: bool = eqx.field(static=True, default=True)
    use_orientations: bool = eqx.field(static=True, default=True)
    max_steps: int = eqx.field(static=True, default=100)


def draw_trial_truth(setup: MonteCarloSetup, key: PRNGKeyArray):
    k_model, k_cam, k_mount = jax.random.split(key, 3)
    true = anchor_base(perturb_model(setup.nominal, k_model, setup.scales), setup.nominal)
    kc1, kc2 = jax.random.split(k_cam)
    cam_twist = jnp.concatenate(
        [
            setup.camera_sigma_mm * _MM * jax.random.normal(kc1, (3,)),
            setup.camera_sigma_deg * _DEG * jax.random.normal(kc2, (3,)),
        ]
    )
    T_cam_base = setup.T_cam_base @ se3_exp(cam_twist)
    M = setup.T_flange_marker.shape[0]
    km1, km2 = jax.random.split(k_mount)
    mount_twist = jnp.concatenate(
        [
            setup.mount_sigma_mm * _MM * jax.random.normal(km1, (M, 3)),
            setup.mount_sigma_deg * _DEG * jax.random.normal(km2, (M, 3)),
        ],
        axis=-1,
    )
    T_flange_marker = matmul(setup.T_flange_marker, jax.vmap(se3_exp)(mount_twist))
    return true, T_cam_base, T_flange_marker


def trial_sweeps(
    setup: MonteCarloSetup,
    true: KinematicModel,
    T_cam_base: Float[Array, "4 4"],
    T_flange_marker: Float[Array, "markers 4 4"],
    key: PRNGKeyArray,
    noise: NoiseModel | None = None,
) -> ArcData:
    """`synthesize_sweeps` with the setup's plan, noise (unless given) and options."""
    return synthesize_sweeps(
        true,
        T_cam_base,
        T_flange_marker,
        setup.plan,
        setup.noise if noise is None else noise,
        key,
        nominal_ratio=setup.nominal.reduction_ratio,
        use_encoders=setup.use_encoders,
        use_orientations=setup.use_orientations,
    )


def exact_arcs(
    arcs: ArcFitResult,
    true: KinematicModel,
    T_cam_base: Float[Array, "4 4"],
    T_flange_marker: Float[Array, "markers 4 4"],
    nominal_ratio: Float[Array, " joints"],
) -> ArcFitResult:
    """What the arc fits of noise-free sweeps (with encoders) return, from the truth.

    The true axes and marker zero poses, expressed in the line coordinates of
    the given (noisy) fits' references (`R_ref`, `c`, `O_ref`) and carrying
    their covariances, so an axis fit on them solves the noise-free problem
    with realistic whitening (its optimum is exact: the residuals vanish).
    Noise-free arc fits recover the same numbers to ~1e-9 (`tests/test_arcfit.py`),
    at the cost of six more LM solves per trial.
    """
    q0 = jnp.zeros(true.num_joints)
    points, dirs = joint_axes(true, q0)
    points = points @ T_cam_base[:3, :3].T + T_cam_base[:3, 3]
    dirs = dirs @ T_cam_base[:3, :3].T
    T0 = T_cam_base @ forward_kinematics(true, q0)[-1] @ T_flange_marker  # (M, 4, 4)
    lines = jax.vmap(line_to_params)(points, dirs, arcs.R_ref, arcs.c)
    n, M = points.shape[0], T0.shape[0]
    parts = [lines, jnp.broadcast_to(T0[:, :3, 3].reshape(-1), (n, 3 * M))]
    if arcs.meas.shape[-1] > 4 + 3 * M:  # orientations were measured
        r0 = so3_log(jnp.einsum("jmba,mbc->jmac", arcs.O_ref, T0[:, :3, :3]))  # (J, M, 3)
        parts.append(r0.reshape(n, 3 * M))
    # The reported axis point is the one closest to the markers' centroid: project the fit's.
    point = points + jnp.sum((arcs.point - points) * dirs, -1, keepdims=True) * dirs
    return eqx.tree_at(
        lambda a: (a.direction, a.point, a.rate, a.T_cam_marker0, a.meas),
        arcs,
        (
            dirs,
            point,
            nominal_ratio / true.reduction_ratio,
            jnp.broadcast_to(T0, arcs.T_cam_marker0.shape),
            jnp.concatenate(parts, axis=-1),
        ),
    )


def check_revolute(model: KinematicModel, what: str) -> None:
    """Raise a `ValueError` naming `model`'s prismatic joints: a study's sweeps
    (`SweepPlan.range_deg`), exact arcs and validation configurations are angles."""
    prismatic = [n for n, k in zip(model.joint_names, model.joint_types) if k != REVOLUTE]
    if prismatic:
        raise ValueError(
            f"{what}: Monte Carlo studies sweep and score revolute joints only; "
            f"prismatic joints {prismatic} are not supported"
        )


def run_trial(
    setup: MonteCarloSetup, key: PRNGKeyArray, free: Bool[Array, " n"] | None = None
) -> TrialResult:
    """One Monte Carlo trial (pure; vmap over `key`). Revolute arms only."""
    check_revolute(setup.nominal, "run_trial")
    k_truth, k_noise, k_val = jax.random.split(key, 3)
    true, T_cam_base, T_flange_marker = draw_trial_truth(setup, k_truth)
    data = trial_sweeps(setup, true, T_cam_base, T_flange_marker, k_noise)
    # The truth expressed in the estimator's gauge: the same axis fit on exact
    # measurements, whose T_cam_base is what a perfect calibration returns. Both
    # axis fits run as one vmap (one trace, one compile).
    if setup.use_encoders:
        arcs = jax.vmap(
            lambda d: fit_arc(
                d, scale_covariance=False, options=replace(ARC_OPTIONS, max_steps=setup.max_steps)
            )
        )(data)
        exact = exact_arcs(arcs, true, T_cam_base, T_flange_marker, setup.nominal.reduction_ratio)
        both = jax.tree.map(lambda a, b: jnp.stack([a, b]), arcs, exact)
        fit2 = jax.vmap(
            lambda a: fit_axes(
                setup.nominal, a, free=free, options=replace(AXIS_OPTIONS, max_steps=setup.max_steps)
            )
        )(both)
    else:
        # Without encoders the zero poses are not at q = 0: fit noise-free sweeps instead.
        exact = trial_sweeps(setup, true, T_cam_base, T_flange_marker, k_noise, NoiseModel(0.0, 0.0, 0.0))
        both = jax.tree.map(lambda a, b: jnp.stack([a, b]), data, exact)
        arcs2, fit2 = jax.vmap(
            lambda d: fit_sweeps(
                setup.nominal, d, free=free, options=replace(SWEEP_OPTIONS, max_steps=setup.max_steps)
            )
        )(both)
        arcs = jax.tree.map(lambda x: x[0], arcs2)
    fit, fit_exact = jax.tree.map(lambda x: x[0], fit2), jax.tree.map(lambda x: x[1], fit2)
    q_val = jax.random.uniform(
        k_val, (setup.n_validation, setup.nominal.num_joints), minval=-jnp.pi, maxval=jnp.pi
    )
    if setup.use_encoders:
        s = score(fit, true, T_cam_base, T_flange_marker, setup.nominal, q_val, fit_exact.T_cam_base)
    else:
        # Without encoders the sweeps leave the last joint's zero and the marker mount to
        # the gauge (held at nominal): the truth in that gauge is the exact fit. The
        # ratios are not estimated (NaN).
        s = score(fit, fit_exact.model, fit_exact.T_cam_base, fit_exact.T_flange_marker, setup.nominal, q_val)
        s = s._replace(ratio_err_percent=jnp.full_like(s.ratio_err_percent, jnp.nan))
    success = (
        jnp.all(arcs.result == optx.RESULTS.successful)
        & (fit.result == optx.RESULTS.successful)
        & jnp.all(jnp.isfinite(fit.T_cam_base))
        & jnp.isfinite(s.ee_rms_mm)
    )
    return TrialResult(**s._asdict(), arc_result=arcs.result, axis_result=fit.result, success=success)


def nominal_free_mask(setup: MonteCarloSetup) -> Bool[Array, " n"]:
    """The identifiable parameters at the nominal geometry (noise-free sweeps),
    used for every trial so all trials estimate the same parameters."""
    data = trial_sweeps(
        setup,
        setup.nominal,
        setup.T_cam_base,
        setup.T_flange_marker,
        jax.random.key(0),
        NoiseModel(0.0, 0.0, 0.0),
    )
    _, fit = fit_sweeps(setup.nominal, data)
    return fit.free


def default_setup(
    nominal: KinematicModel,
    *,
    noise: NoiseModel | None = None,
    plan: SweepPlan | None = None,
    scales: PerturbationScales | None = None,
) -> MonteCarloSetup:
    """A camera 1.5 m from the base looking at the arm, a marker 5 cm off the flange."""
    T_cam_base = make_pose(jnp.array([[0.0, 1, 0], [0, 0, -1], [-1, 0, 0]]), jnp.array([0.0, 0.3, 1.5]))
    T_flange_marker = make_pose(jnp.eye(3), jnp.array([0.0, 0.05, 0.02]))[None]
    return MonteCarloSetup(
        nominal=nominal,
        T_cam_base=T_cam_base,
        T_flange_marker=T_flange_marker,
        scales=PerturbationScales() if scales is None else scales,
        noise=NoiseModel() if noise is None else noise,
        plan=SweepPlan() if plan is None else plan,
    )


def dynamic_setup(setup: MonteCarloSetup) -> MonteCarloSetup:
    """Numbers as arrays, so a new noise level or scale reuses the compiled trial."""
    return jax.tree.map(lambda x: jnp.asarray(x, jnp.float64) if isinstance(x, float | int) else x, setup)


#: Default trials per vmapped chunk on the CPU. Under `vmap` every solver
#: loop runs as many steps as the slowest problem of its batch, so one
#: straggler costs the whole batch its steps; chunks bound that cost (one batch
#: of 1000 UR5e trials took over twice as long: docs/performance.md, Monte Carlo).
CPU_CHUNK = 250
#: ... and on an accelerator at most this many (a device's share of the trials at once when
#: fewer): the chunk sets the memory (a trial's sweeps, fits and Jacobians), and 10,000 at once
#: ran no faster than chunks of 1000 on an H100 (docs/performance.md, Monte Carlo).
ACCELERATOR_CHUNK = 10_000
#: Most trials one `monte_carlo` call runs (the results are held in memory, about 300 bytes a
#: trial) and most frames per joint sweep (a trial's memory grows with them).
MAX_TRIALS = 1_000_000
MAX_FRAMES = 2000


#: The name of `trial_mesh`'s one axis: trials are split over it.
TRIALS_AXIS = "trials"


def default_devices() -> list:
    """The devices `monte_carlo` shards over by default: `jax.devices()` (every
    device of every process), except on the CPU, where each process keeps at
    most half its intra-op thread pool's size.

    Why the CPU limit: XLA runs each CPU device's program on a thread of one
    shared pool of $\\max(\\text{cores}, \\text{devices})$ threads, and jaxlib's
    batched LAPACK kernels block their thread until chunks they schedule on the
    same pool are done (`jaxcal._linalg`). When every pool thread runs a device
    program waiting in such a kernel, nothing runs the chunks: with
    `--xla_force_host_platform_device_count=4` on a two-core machine (a pool of
    four), the four-device trial hangs. Half the pool always leaves threads free.
    """
    devices = jax.devices()
    if devices[0].platform != "cpu":
        return devices
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    keep = max(1, max(cores, jax.local_device_count()) // 2)
    taken: dict[int, int] = {}
    out = []
    for d in devices:
        taken[d.process_index] = taken.get(d.process_index, 0) + 1
        if taken[d.process_index] <= keep:
            out.append(d)
    return out


def trial_mesh(devices=None) -> Mesh:
    """A one-dimensional device mesh over the axis `TRIALS_AXIS` (default devices:
    `default_devices()`)."""
    devices = default_devices() if devices is None else list(devices)
    if not devices:
        raise ValueError("trial_mesh: no devices")
    return Mesh(np.asarray(devices), (TRIALS_AXIS,))


def monte_carlo(
    setup: MonteCarloSetup,
    key: PRNGKeyArray,
    trials: int,
    *,
    chunk: int | None = None,
    devices=None,
    progress: bool = False,
) -> TrialResult:
    """Run `trials` seeded trials in one jitted call, sharded over devices; `progress`: say so, and
    that it is still working every few seconds while it compiles and runs (on stderr; the call
    then returns with the results computed).

    **Layout** (`map_over_devices`). With $D$ devices (`devices`, default
    `default_devices()`: every GPU of every host, or part of the CPU's), the trial
    keys `split(key, trials)` are padded to $D\\lceil N/D\\rceil$ by repeating the
    first ones, reshaped to $(D, \\lceil N/D\\rceil)$ and laid along a
    one-dimensional mesh (`trial_mesh`, axis `"trials"`): device $d$ runs its
    row as `vmap(run_trial)` over chunks of at most `chunk` trials, the chunks
    one after another (`lax.map`). The padded trials are dropped before the
    results are gathered (replicated on every device, so every process of a
    multi-host run can read them): summaries never see them.

    **Communication.** None between trials, except that every solver loop is one
    `while` over the whole batch: each iteration all-reduces its "any trial left?"
    flag (a scalar), so the devices step together until the slowest trial of
    any device is done, as the trials of one chunk already do. (`jax.shard_map`
    would drop even that, but lineax 0.1's structure checks reject the manual
    axes' shardings inside it.)

    **Reproducibility.** Trial `i` uses key `split(key, trials)[i]` whatever the
    devices and the chunk, so one CPU, four GPUs or a pod return the same trials
    to round-off (vector widths differ; `tests/test_montecarlo.py` checks four
    CPU devices against one to 1e-12).

    `chunk` defaults to `CPU_CHUNK` on the CPU and to each device's share (at most
    `ACCELERATOR_CHUNK`) on an accelerator. `trials` and the sweeps' frames are bounded
    (`MAX_TRIALS`, `MAX_FRAMES`): the memory a call takes grows with both.

    **Several processes or hosts** (`jaxcal.distributed`). Start the same script in every
    process, with the environment of a distributed run, and join it before anything else touches
    JAX; `jax.devices()` then lists every process's devices and the one call shards over all of
    them, compiled first and run once every process has compiled it (`Processes.meet`):

    ```python
    import jax

    import jaxcal
    from jaxcal._montecarlo import default_setup, summarize

    processes = jaxcal.distributed.join()  # JAX_COORDINATOR_ADDRESS, JAX_NUM_PROCESSES, JAX_PROCESS_ID; or srun
    setup = default_setup(jaxcal.robots.load_robot("ur5e"))
    result = jaxcal.monte_carlo(setup, jax.random.key(0), 100_000)  # every process's devices
    if processes.first:
        print(summarize(result))
    ```

    Every process must pass the same `setup`, `key` and `trials`.

    **Returns:** a `TrialResult` with a leading `(trials,)` axis. Trials whose
    solvers failed have `success == False` (and their codes in
    `arc_result` / `axis_result`); they never raise.
    """
    if not 1 <= trials <= MAX_TRIALS:
        raise ValueError(f"monte_carlo: trials must be from 1 to {MAX_TRIALS:,} (MAX_TRIALS), got {trials}")
    if not setup.plan.frames <= MAX_FRAMES:
        raise ValueError(
            f"monte_carlo: at most {MAX_FRAMES} frames per sweep (MAX_FRAMES), got {setup.plan.frames}"
        )
    check_revolute(setup.nominal, "monte_carlo")
    mesh = trial_mesh(devices)
    per_device = -(-trials // mesh.size)
    if chunk is None:
        cpu = mesh.devices.flat[0].platform == "cpu"
        chunk = CPU_CHUNK if cpu else min(per_device, ACCELERATOR_CHUNK)
    if chunk < 1:
        raise ValueError(f"monte_carlo: chunk must be at least 1, got {chunk}")
    setup = dynamic_setup(setup)
    # A host value (uncommitted): jit places it on the mesh, on every process.
    free = np.asarray(_free_mask_jit(setup))
    static = {"trials": trials, "chunk": min(chunk, per_device), "mesh": mesh}
    if not progress:
        return _run_trials(setup, key, free, static)
    what = f"Monte Carlo: {trials:,} trials in one compiled call (compiling it first, the first run only)"
    print(f"{what} ...", file=sys.stderr, flush=True)
    with working(True, "Monte Carlo", stream=sys.stderr):
        return jax.block_until_ready(_run_trials(setup, key, free, static))


def _run_trials(setup, key, free, static: dict) -> TrialResult:
    """`_sharded_trials`; over several processes compiled first, and run once every process has
    compiled it (`jaxcal.distributed.Processes.meet`)."""
    processes = current()
    if processes.count == 1:
        return _sharded_trials(setup, key, free, **static)
    compiled = _sharded_trials.lower(setup, key, free, **static).compile()
    processes.meet("monte_carlo")
    return compiled(setup, key, free)


_free_mask_jit = jax.jit(nominal_free_mask)


@functools.partial(jax.jit, static_argnames=("trials", "chunk", "mesh"))
def _sharded_trials(setup, key, free, *, trials: int, chunk: int, mesh: Mesh):
    keys = jax.random.split(key, trials)
    return map_over_devices(lambda k: run_trial(setup, k, free), keys, mesh, chunk)


def map_over_devices(fn, xs, mesh: Mesh, chunk: int):
    """`vmap(fn)(xs)` with the leading axis of `xs` split over `mesh`'s devices
    (under `jit`).

    The $n$ entries are padded to $D\\lceil n/D\\rceil$ with copies of the first
    ones, reshaped to $(D, \\lceil n/D\\rceil)$ and constrained to the sharding
    `P(TRIALS_AXIS)`, so XLA's partitioner gives device $d$ row $d$; each row
    runs `map_in_chunks(fn, row, chunk)`. The results drop the padding and are
    constrained to be replicated (gathered on every device).
    """
    n = jax.tree.leaves(xs)[0].shape[0]
    rows = mesh.size
    per = -(-n // rows)
    idx = jnp.arange(rows * per) % n
    xs = jax.tree.map(lambda x: x[idx].reshape((rows, per) + x.shape[1:]), xs)
    xs = jax.lax.with_sharding_constraint(xs, NamedSharding(mesh, P(TRIALS_AXIS)))
    out = jax.vmap(lambda row: map_in_chunks(fn, row, chunk))(xs)
    everywhere = NamedSharding(mesh, P())
    return jax.tree.map(
        lambda y: jax.lax.with_sharding_constraint(y.reshape((rows * per,) + y.shape[2:])[:n], everywhere),
        out,
    )


def map_in_chunks(fn, xs, chunk: int):
    """`vmap(fn)(xs)` computed as `lax.map` over chunks of at most `chunk`
    leading entries of `xs` (equal chunks; the last is padded with copies of
    the first entries, whose results are dropped)."""
    n = jax.tree.leaves(xs)[0].shape[0]
    n_chunks = -(-n // chunk)
    size = -(-n // n_chunks)
    pad = n_chunks * size - n
    xs = jax.tree.map(lambda x: jnp.concatenate([x, x[:pad]]) if pad else x, xs)
    xs = jax.tree.map(lambda x: x.reshape((n_chunks, size) + x.shape[1:]), xs)
    out = jax.lax.map(jax.vmap(fn), xs)
    return jax.tree.map(lambda y: y.reshape((n_chunks * size,) + y.shape[2:])[:n], out)


def summarize(result: TrialResult) -> dict[str, float]:
    """Plain-number summary of a batch of trials (medians and 95th percentiles)."""
    ok = np.asarray(result.success)
    out = {"trials": int(ok.size), "success_rate": float(ok.mean())}
    for name in ("ee_rms_mm", "ee_max_mm", "ee_rms_mm_nominal", "cam_rot_deg", "cam_trans_mm"):
        v = np.asarray(getattr(result, name))[ok]
        out[f"{name}_median"] = float(np.median(v)) if v.size else float("nan")
        out[f"{name}_p95"] = float(np.percentile(v, 95)) if v.size else float("nan")
    for name in ("axis_dir_deg", "axis_pos_mm", "ratio_err_percent"):
        v = np.abs(np.asarray(getattr(result, name))[ok])
        out[f"{name}_max_median"] = float(np.median(v.max(axis=-1))) if v.size else float("nan")
    return out
