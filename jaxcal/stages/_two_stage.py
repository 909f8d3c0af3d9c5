"""Stage 4, two-stage fit: an arc per joint (the first error function), then
the axes to the kinematic parameters and the camera pose (the second).

With single-joint sweeps every joint's arc is fitted at once (vmapped); with
markers on every link, joint after joint by the seed's sequential procedure
(`jaxcal._links`).
"""

import time
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .._arcdata import MIN_SWEEP_DEG
from .._arcfit import ArcFitResult, arc_outliers, sweep_span_deg, validate_arc_data
from .._axisfit import AxisFitParams, AxisFitResult, register_lines
from .._buckets import bucket
from .._correction import Estimate, ParameterLayout, physical_parameters, zero_correction
from .._device import flat_on_device, result_is, to_device
from .._geometry import pose_inverse
from .._handeye import check_motion_diversity, solve_axzb
from .._kinematics import PRISMATIC, forward_kinematics
from .._links import average_pose, sequential_sweeps
from .._selection import CV_GAIN, MIN_Z
from ..errors import CalibrationError
from ..records import (
    ArcOutlier,
    ArcRow,
    Named,
    ParameterRow,
    SolveOutcome,
    SolverInfo,
    parameter_rows,
)
from . import _programs
from ._blur import blur_notes, lost_to_blur
from ._observe import Observations
from ._points import PointFit, axis_result, fit_point_samples, parameters_of
from ._setup import Options, Setup
from ._synchronise import Sweeps, Sync


@dataclass(frozen=True, eq=False)
class TwoStage:
    """The two-stage result.

    - `sweeps`, `counts`: the sweeps the arcs were fitted on, and frames per
      joint (a pose-based capture: None, and the poses used).
    - `arcs`: the `ArcFitResult`s stacked over joints; `fit`: the `AxisFitResult`
      (its `T_cam_base0`, `T_flange_marker0` are the references of the
      corrections: the start of the refinement).
    - `layout`: the axis fit's `ParameterLayout`; `parameters`: the physical
      parameter table; `frozen`: names held at nominal.
    - `arc_rows`: per-joint summaries for reports; `solver`: success flags.
    - `link_rows`: markers on every link, the two-stage camera's rows inside
      the encoder log with a pose (the refinement's start mounts use them).
    - `estimate`: the axis fit's vector with its covariance and references
      (`jaxcal.parameters_to_model`, `jaxcal.physical_table`).
    - `points`: stop-and-shoot tracker data, the `PointFit` (`fit` is then its
      geometric part; its terms, cross-validation and held parameters are here).
    - `arc_loss`: the robust loss the arcs were fitted with (`Options.arc_loss`: the
      verdict's arm check refits them at another clock offset).
    """

    sweeps: Sweeps | None
    #: Per joint the frames its arc fit used (`poses` for a pose-based capture).
    counts: tuple[Named, ...]
    arcs: ArcFitResult | None
    fit: AxisFitResult
    layout: ParameterLayout
    parameters: tuple[ParameterRow, ...]
    frozen: tuple[str, ...]
    arc_rows: tuple[ArcRow, ...]
    solver: SolverInfo
    notes: tuple[str, ...]
    link_rows: np.ndarray | None
    #: Seconds per step (`arc_fit_s`, `axis_fit_s`, ...): free-form.
    timings: dict[str, float]
    estimate: Estimate | None = None
    points: PointFit | None = None
    arc_loss: str | None = "cauchy"


def _sequential(setup: Setup, obs: Observations, sync: Sync, loss: str | None):
    """Markers on every link: the sweeps and arcs of the sequential procedure."""
    p = obs.primary
    sel = np.flatnonzero(sync.inside & p.found)
    n = setup.nominal.num_joints
    F = bucket(sel.size)
    Ps, Os, Cs, mk, arc_list = sequential_sweeps(
        p.rows[sel],
        [p.poses[i] for i in sel],
        setup.targets,
        setup.per_joint,
        sync.q[sel],
        p.t_cam[sel],
        _programs.arc_fit(loss),
        frames=F,
    )
    pad = F - sel.size
    rows = np.concatenate([p.rows[sel], np.full(pad, -1)])
    t_cam = np.concatenate([p.t_cam[sel], np.full(pad, p.t_cam[sel][-1])])
    q = np.concatenate([sync.q[sel], np.zeros((pad, n))])
    sweeps = Sweeps(
        np.where(mk[:, 0], rows[None], -1), Ps, Os, Cs, mk, np.broadcast_to(t_cam, (n, F)).copy(), q.T.copy()
    )
    counts = tuple(Named(name, int(mk[j, 0].sum())) for j, name in enumerate(setup.dataset.joint_names))
    return sweeps, counts, jax.tree.map(lambda *a: jnp.stack(a), *arc_list), sel


def _pose_start(setup: Setup, obs: Observations, sync: Sync):
    """A pose-based capture's start: the nominal robot, and the camera pose and
    mounts from the closed-form hand-eye solution $A = X B Y$ (Shah) of the PnP
    poses $A$ against the nominal flange poses $B$ at the encoder positions
    (`jaxcal.solve_axzb`): $X = T_{cam,base}$, $Y = T_{flange,target}$."""
    ds, nominal, p = setup.dataset, setup.nominal, obs.primary
    sel = [i for i in np.flatnonzero(sync.inside & p.found)]
    first = setup.targets[0].name
    frames = [i for i in sel if first in p.poses[i]]
    if len(frames) < 3:
        raise CalibrationError(
            f"{ds.root}: a pose-based capture needs at least 3 images showing {first!r} inside the encoder log, "
            f"camera {setup.camera.name!r} has {len(frames)}"
        )
    B = _programs.chains(np.eye(4), nominal, sync.q[frames])[:, -1]
    try:
        check_motion_diversity(B, f"{ds.root}: the poses of camera {setup.camera.name!r}")
    except ValueError as e:
        raise CalibrationError(str(e)) from None
    A = np.stack([p.poses[i][first].T_cam_target for i in frames])
    X, Y = (
        np.asarray(a) for a in solve_axzb(jnp.asarray(A)[None], jnp.asarray(B), jnp.ones((1, len(frames))))
    )
    T_cam_base = X[0]
    mounts = [Y]
    for t in setup.targets[1:]:
        est = [
            np.linalg.inv(T_cam_base @ B[k]) @ p.poses[i][t.name].T_cam_target
            for k, i in enumerate(frames)
            if t.name in p.poses[i]
        ]
        mounts.append(average_pose(np.stack(est)) if est else Y)
    n, M = nominal.num_joints, len(setup.targets)
    mounts0 = jnp.asarray(np.stack(mounts))
    k = ParameterLayout.of(nominal, M).axis_size
    fit = AxisFitResult(
        model=nominal,
        T_flange_marker=mounts0,
        T_cam_base=jnp.asarray(T_cam_base),
        params=AxisFitParams(cam=jnp.zeros(6), correction=zero_correction(n, M)),
        std=jnp.zeros(k),
        cov=jnp.zeros((k, k)),
        free=jnp.zeros(k, bool),
        independence=jnp.full(k, jnp.nan),
        result=optx.RESULTS.successful,
        num_steps=jnp.asarray(0),
        residual_rms=jnp.asarray(jnp.nan),
        singular_values=jnp.zeros(k),
        T_cam_base0=jnp.asarray(T_cam_base),
        T_flange_marker0=mounts0,
    )
    return fit, len(frames)


def _check_sweeps(setup: Setup, sweeps: Sweeps, counts: tuple[Named, ...], data, obs=None, sync=None) -> None:
    """Every joint's sweep can make an arc; a `CalibrationError` names the joint (and motion
    blur when the sweep lost its fast frames: `_blur.lost_to_blur`, given `obs` and `sync`)."""
    ds = setup.dataset
    data = jax.device_get(data)  # host arrays: slicing them per joint compiles nothing
    used = {r.name: r.value for r in counts}
    for j, name in enumerate(ds.joint_names):
        if used[name] == 0:
            none = f"no frame of camera {setup.camera.name!r} shows a target while this joint sweeps alone"
            cause = _outside_log(ds, name) or ("" if obs is None else lost_to_blur(setup, obs, sync, j))
            raise CalibrationError(f"{ds.root}: joint {name!r}: " + (f"{cause} ({none})" if cause else none))
        data_j = jax.tree.map(lambda x, j=j: x[j], data)
        try:
            validate_arc_data(data_j, name, setup.nominal.joint_types[j])
        except ValueError as e:
            cause = _outside_log(ds, name) or ("" if obs is None else lost_to_blur(setup, obs, sync, j))
            if cause:  # the cause first, what it did after
                e = f"joint {name!r}: {cause} ({str(e).removeprefix(f'joint {name!r}: ')})"
            elif _radians_read_as_degrees(ds, data_j, setup.nominal.joint_types[j]):
                e = (
                    f"{e}; encoders.unit is 'deg', but read as radians the log would sweep "
                    f"{np.degrees(sweep_span_deg(data_j)):.0f} degrees: is the log in radians?"
                )
            raise CalibrationError(f"{ds.root}: {e}") from None


def _outside_log(ds, joint: str) -> str:
    """Why `joint`'s sweep has no frames, in words, where the motion says: the capture has no sweep
    of it, or its sweep (its motion segments) reaches beyond the encoder log; else ""."""
    swept = [name for name, _, _ in ds.segments if name is not None]
    if swept and joint not in swept:
        return (
            f"the capture has no sweep of it (metadata.json's motion sweeps {list(dict.fromkeys(swept))} alone): "
            "a capture or bag that ends before its sweep?"
        )
    if ds.encoder_t is None or not len(ds.encoder_t):
        return ""
    t0, t1 = float(ds.encoder_t[0]), float(ds.encoder_t[-1])
    for name, start, end in ds.segments:
        if name == joint and (start < t0 or end > t1):
            part = "" if end < t0 or start > t1 else "partly "
            return (
                f"its sweep [{start:g}, {end:g}] s (metadata.json motion) lies {part}outside the encoder log "
                f"[{t0:g}, {t1:g}] s: the log cut short, or the two stamped on different clocks"
            )
    return ""


def _radians_read_as_degrees(ds, data_j, joint_type: str) -> bool:
    """A revolute sweep too short in the log's `deg` that would be a sweep in radians."""
    if ds.encoder_unit != "deg" or joint_type != "revolute" or data_j.encoder is None:
        return False
    span = sweep_span_deg(data_j)
    return bool(span < MIN_SWEEP_DEG <= np.degrees(span) <= 720.0)


def _start_mounts(setup: Setup, arcs, homes):
    """The fit targets' nominal mounts; where one is unknown, every mount from
    the measured zero pose and the registered camera pose (the identity when
    the fixed frame is the base frame)."""
    mounts0 = [t.T_link_target for t in setup.fit_targets]
    if all(m is not None for m in mounts0):
        return to_device(np.stack(mounts0))
    nominal = setup.nominal
    home = None if homes is None else to_device(homes)
    T0 = register_lines(nominal, arcs, home) if setup.kind.fixed_frame_free else jnp.eye(4)
    T_cf = T0 @ forward_kinematics(nominal, jnp.zeros(nominal.num_joints) if home is None else home[0])[-1]
    return jnp.einsum("ab,mbc->mac", pose_inverse(T_cf), arcs.T_cam_marker0[0])


def arc_outlier_rows(setup: Setup, sweeps: Sweeps, arcs, j: int) -> tuple[ArcOutlier, ...]:
    """The samples joint `j`'s robust arc fit rejected: target, frame and camera time
    (`arcs` as host arrays, as `arc_rows` passes them)."""
    frames = setup.dataset.frames
    rows = []
    for m, f in arc_outliers(jax.tree.map(lambda x: x[j], arcs), sweeps.mask[j]):
        row = int(sweeps.rows[j, f])
        rows.append(
            ArcOutlier(
                target=setup.targets[m].name if m < len(setup.targets) else str(m),
                frame=int(frames.frame[row]),
                timestamp_s=float(frames.timestamp[row]),
                residual=float(arcs.sample_residuals[j, m, f]),
                sample=None if setup.kind.images else int(frames.frame[row]),
                line=None if setup.kind.images else frames.file[row],
            )
        )
    return tuple(rows)


def listed(items: list[str], shown: int = 8) -> str:
    """The first `shown` of `items`, and how many more."""
    return ", ".join(items[:shown]) + (f" and {len(items) - shown} more" if len(items) > shown else "")


def _outlier_notes(rows: tuple[ArcRow, ...]) -> tuple[str, ...]:
    """One note per joint whose robust arc fit rejected samples, naming their frames."""
    notes = []
    for a in rows:
        frames = sorted({o.frame for o in a.outliers})
        if frames:
            shown = listed(list(map(str, frames)))
            what = "sample" if a.outliers[0].sample is not None else "frame"
            notes.append(f"joint {a.joint!r}: the robust arc fit rejected {len(frames)} {what}(s): {shown}")
    return tuple(notes)


def arc_rows(setup: Setup, arcs, sweeps: Sweeps) -> tuple[ArcRow, ...]:
    """Per-joint arc summaries (frames, RMS, axis, ratio with its std, solver,
    the samples a robust fit rejected and the noise scale it saw)."""
    arcs = jax.device_get(arcs)  # host arrays: per-joint indexing compiles nothing
    nominal_ratio = np.asarray(setup.nominal.reduction_ratio)
    ok = result_is(arcs.result)
    has = bool(arcs.has_encoder)
    rows = []
    for j, name in enumerate(setup.dataset.joint_names):
        rate = float(arcs.rate[j])
        prismatic = setup.nominal.joint_types[j] == PRISMATIC
        var = max(float(arcs.rate_var[j]), 0.0)
        rows.append(
            ArcRow(
                joint=name,
                type=setup.nominal.joint_types[j],
                frames=int(arcs.num_frames[j]),
                position_rms_mm=float(arcs.position_rms[j]) * 1e3,
                rotation_rms_deg=float(np.degrees(arcs.rotation_rms[j]))
                if np.isfinite(arcs.rotation_rms[j])
                else None,  # points measured without an orientation
                residual_rms=float(arcs.residual_rms[j]),
                direction_cam=tuple(np.asarray(arcs.direction[j]).tolist()),
                # A translation has no axis position (`fit_line`).
                point_cam_m=None if prismatic else tuple(np.asarray(arcs.point[j]).tolist()),
                ratio_nominal=float(nominal_ratio[j]),
                ratio=float(nominal_ratio[j] / rate) if has else None,
                ratio_std=float(nominal_ratio[j] * np.sqrt(var) / rate**2) if has else None,
                ratio_identifiable=has,
                # Prismatic: the ratio is motor rad per m; the scale is the true travel per
                # commanded travel (nominal ratio / true ratio), 1 for a datasheet screw.
                ratio_unit="rad/m" if prismatic else None,
                scale=rate if prismatic else None,
                scale_std=float(np.sqrt(var)) if prismatic else None,
                travel_mm=float(1e3 * np.ptp(np.asarray(arcs.angles[j])[np.asarray(sweeps.mask[j]).any(0)]))
                if prismatic
                else None,
                solver=SolveOutcome("successful" if ok[j] else "failed", int(arcs.num_steps[j])),
                robust_scale=float(arcs.robust_scale[j]),
                outliers=arc_outlier_rows(setup, sweeps, arcs, j),
            )
        )
    return rows


def two_stage(setup: Setup, obs: Observations, sync: Sync, options: Options) -> TwoStage:
    """Arc fits, then the axis fit (see `TwoStage`); for a pose-based capture,
    the nominal robot and a closed-form hand-eye start."""
    nominal, kind = setup.nominal, setup.kind
    if kind.fits_points:
        return _points(setup, obs, sync, options)
    if not kind.has_arcs:
        return _poses(setup, obs, sync, options)
    timings = {}
    t0 = time.perf_counter()
    link_rows = None
    if kind.sequential:
        prismatic = [n for n, t in zip(nominal.joint_names, nominal.joint_types) if t == PRISMATIC]
        if prismatic:
            raise CalibrationError(
                f"{setup.dataset.root}: markers on every link are calibrated joint by joint with arcs; "
                f"prismatic joints {prismatic} need single-joint sweeps"
            )
        options.say(
            f"sequential arc fits of {nominal.num_joints} joints (markers on every link, earlier joints undone)"
        )
        sweeps, counts, arcs, link_rows = _sequential(setup, obs, sync, options.arc_loss)
        _check_sweeps(setup, sweeps, counts, sweeps.arc_data())
    else:
        sweeps, counts = sync.sweeps, sync.counts
        data = sweeps.arc_data()
        _check_sweeps(setup, sweeps, counts, data, obs.primary, sync)
        options.say(f"arc fits of {nominal.num_joints} joints (one vmapped solve)")
        _programs.wait_ahead()
        arcs = _programs.arc_fits(options.arc_loss, nominal.joint_types)(data)
    jax.block_until_ready(arcs)
    timings["arc_fit_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    options.say(f"axis fit: kinematic parameters and {kind.fixed_frame}")
    mounts0 = _start_mounts(setup, arcs, sync.homes)
    home = None if sync.homes is None else jnp.asarray(sync.homes)
    fit = _programs.axis_fit(kind.axis_fit_uses_poses)(
        nominal, arcs, mounts0, None, home, kind.fixed_frame_free
    )
    jax.block_until_ready(fit)
    timings["axis_fit_s"] = time.perf_counter() - t0

    layout = kind.layout(nominal, len(setup.fit_targets))
    names = layout.names(refine=False)
    free = np.asarray(fit.free)
    parameters = _parameters(layout, nominal, fit, free, setup.fit_targets)
    ok_arc = result_is(arcs.result)
    rows = arc_rows(setup, arcs, sweeps)
    notes = (
        ()
        if arcs.has_encoder
        else ("no encoder log: reduction ratios are not identifiable (images alone give the axes)",)
    ) + _outlier_notes(rows)
    if not setup.kind.sequential:
        notes += blur_notes(setup, obs.primary, sync)
    return TwoStage(
        sweeps=sweeps,
        counts=counts,
        arcs=arcs,
        fit=fit,
        layout=layout,
        parameters=parameter_rows(parameters),
        frozen=tuple(n for n, f in zip(names, free) if not f),
        arc_rows=rows,
        solver=SolverInfo(
            success=bool(ok_arc.all() and result_is(fit.result)),
            arc_fits_ok=tuple(ok_arc.tolist()),
            axis_fit=result_name(fit.result),
            axis_fit_steps=int(fit.num_steps),
            axis_fit_residual_rms=float(fit.residual_rms),
        ),
        notes=notes,
        link_rows=link_rows,
        timings=timings,
        estimate=fit_estimate(layout, setup, fit, [t.name for t in setup.fit_targets]),
        arc_loss=options.arc_loss,
    )


def _parameters(layout, nominal, fit, free, targets) -> list[dict]:
    """The axis fit `fit`'s parameters in physical units (`physical_parameters`)."""
    cam, correction, names = fit.params.cam, fit.params.correction, [t.name for t in targets]
    return physical_parameters(
        layout, nominal, fit.T_flange_marker0, fit.T_cam_base0, cam, correction, fit.cov, free, names
    )


def _poses(setup: Setup, obs: Observations, sync: Sync, options: Options) -> TwoStage:
    """The two-stage record of a pose-based capture: no arcs, no axis fit."""
    t0 = time.perf_counter()
    options.say("pose-based capture: closed-form hand-eye start (camera and mount) from the nominal robot")
    fit, poses = _pose_start(setup, obs, sync)
    layout = setup.kind.layout(setup.nominal, len(setup.targets))
    parameters = _parameters(layout, setup.nominal, fit, np.asarray(fit.free), setup.targets)
    return TwoStage(
        sweeps=None,
        counts=(Named("poses", poses),),
        arcs=None,
        fit=fit,
        layout=layout,
        parameters=parameter_rows(parameters),
        frozen=(),
        arc_rows=(),
        solver=SolverInfo(success=True, arc_fits_ok=(), axis_fit="not run (pose-based capture)"),
        notes=(),
        link_rows=None,
        timings={"hand_eye_start_s": time.perf_counter() - t0},
        estimate=fit_estimate(layout, setup, fit, [t.name for t in setup.targets]),
    )


def term_note(model, models) -> str | None:
    """Why a model with a non-geometric term was not kept, against the model it was tried
    against (the one without its last term): no better, better by no more than `CV_GAIN`, or by
    fewer than `MIN_Z` standard errors of the paired held-out distances (`jaxcal._selection`);
    None for a model that was kept and then extended by a later term (the table shows it)."""
    base = next(m for m in models if m.terms == model.terms[:-1])
    name = "+".join(base.terms) or "geometric model"
    head = f"the model with {'+'.join(model.terms)}: cross-validation {model.cv_mean_mm:.4f} mm mean"
    if model.cv_mean_mm >= base.cv_mean_mm:
        return f"{head}, not better than the {name}'s {base.cv_mean_mm:.4f} mm: not kept"
    gain = 1.0 - model.cv_mean_mm / base.cv_mean_mm
    better = f"{head}, better than the {name}'s {base.cv_mean_mm:.4f} mm by {100 * gain:.2f} %"
    if gain <= CV_GAIN:
        return f"{better}, less than the {100 * CV_GAIN:g} % a term must gain: not kept"
    if model.cv_gain_z is not None and model.cv_gain_z < MIN_Z:
        return (
            f"{better}, {model.cv_gain_z:.2f} standard errors of the samples' paired differences, fewer than "
            f"the {MIN_Z:g} a term's gain must stand out by: not kept"
        )
    return None


def _points(setup: Setup, obs: Observations, sync: Sync, options: Options) -> TwoStage:
    """The two-stage record of stop-and-shoot tracker data: the point fit (`stages._points`)."""
    pf = fit_point_samples(setup, obs, sync, options)
    fit = axis_result(pf, setup.nominal)
    layout = pf.layout.base
    kept = [m for m in pf.models if m.kept][0]
    notes = [
        f"point fit on {int(pf.used.sum())} poses: {int(np.sum(pf.fit.free))} parameters free"
        + (f", non-geometric terms {list(pf.layout.terms)}" if pf.layout.terms else "")
        + f"; fitted residual {pf.residual_mm.rms:.4f} mm RMS"
        + ("" if pf.residual_deg is None else f", {pf.residual_deg.rms:.4f} deg RMS")
        + (f", {pf.folds}-fold cross-validation {kept.cv_mean_mm:.4f} mm mean" if pf.folds else "")
        + (f", {kept.cv_mean_deg:.4f} deg mean" if pf.folds and kept.cv_mean_deg is not None else "")
    ]
    if pf.repeats:
        notes.append(
            f"{len(pf.repeats)} sample(s) repeat an earlier sample's joint positions, merged into its pose (the mean "
            "of their points) and weighted as one pose: "
            + listed([f"sample {r.sample} (= sample {r.of_sample})" for r in pf.repeats])
        )
    notes += [n for m in pf.models if m.terms and not m.kept and (n := term_note(m, pf.models))]
    return TwoStage(
        sweeps=None,
        counts=(Named("poses", int(pf.used.sum())),),
        arcs=None,
        fit=fit,
        layout=layout,
        parameters=parameter_rows(parameters_of(pf, setup, fit)),
        frozen=tuple(pf.held),
        arc_rows=(),
        solver=SolverInfo(
            success=bool(result_is(fit.result)),
            arc_fits_ok=(),
            axis_fit="not run (stop-and-shoot samples: point fit)",
            point_fit=result_name(fit.result),
            point_fit_steps=int(fit.num_steps),
        ),
        notes=tuple(notes),
        link_rows=None,
        timings=pf.timings,
        estimate=fit_estimate(layout, setup, fit, [setup.targets[0].name]),
        points=pf,
    )


def fit_estimate(layout: ParameterLayout, setup: Setup, fit, mount_names: list[str]) -> Estimate:
    """The axis fit's (or the pose-based start's) `Estimate`."""
    return Estimate(
        x=flat_on_device(fit.params),
        cov=to_device(fit.cov),
        free=to_device(fit.free),
        nominal=setup.nominal,
        T_flange_marker0=to_device(fit.T_flange_marker0),
        T_cam_base0=to_device(fit.T_cam_base0),
        reduction_ratio=to_device(fit.model.reduction_ratio),
        layout=layout,
        mount_names=tuple(mount_names),
    )


def result_name(result) -> str:
    """`"successful"` or `"failed"` for an optimistix result code."""
    return "successful" if result_is(result) else "failed"
