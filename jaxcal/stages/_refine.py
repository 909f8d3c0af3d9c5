"""Stage 5, refinement: the reprojection error of every detected corner,
minimised over every parameter from the two-stage start (`jaxcal._refine`).

Every frame inside the encoder log with a detected target contributes all
its corners (sweep or not), from every camera observed. The axis fit's
frozen parameters stay frozen where the capture kind keeps the two-stage
gauge; rates are free with encoders, the clock offset when it was
estimated. Without an encoder log each sweep view's joint angle is one more
unknown; with markers on every link every target's corners go through its
own link's chain and the corners decide what is identifiable.

With an encoder log the non-geometric terms (`Options.terms`, by default the
kind's: joint compliance under gravity and lost motion) are then tried on the
rigid solution and kept only where held-out views say so (`stages._terms`);
with one kept, the refinement runs again with its coefficients free.
"""

import dataclasses
import time
from dataclasses import dataclass, field

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._buckets import bucket, pad_log
from .._clocksync import controller_time
from .._correction import INTRINSIC_NAMES, Estimate, ParameterLayout, physical_parameters
from .._device import flat_on_device, result_is, to_device
from .._links import average_pose, start_mounts
from .._npgeom import so3_log
from .._progress import working
from .._refine import (
    OtherCameras,
    RefineParams,
    RefineProblem,
    RefineResult,
    make_corner_data,
    summarize_refinement,
)
from ..records import (
    ClockEstimate,
    ErrorCorrelation,
    IntrinsicsTest,
    JointAngles,
    LensTest,
    LineDelay,
    Named,
    OtherCamera,
    ParameterRow,
    RefinedIntrinsics,
    RefinementSummary,
    ShutterTest,
    TwoStageStart,
    ViewAngle,
    from_plain,
    parameter_rows,
)
from . import _programs
from ._observe import CameraObservations, Observations
from ._residual_tests import error_correlation, score_tests
from ._setup import Options, Setup
from ._synchronise import Sync, interpolate, usable
from ._terms import TermFit, not_tried, resolve, with_terms
from ._two_stage import TwoStage

#: Names of the per-view angles of padding views (never free, never reported).
PADDING = "(padding)"
LOSS = "cauchy IRLS (3 rounds), then least squares on the inliers (3.7 robust sigmas)"


@dataclass(frozen=True, eq=False)
class Refined:
    """The refinement's outcome.

    - `fit`: the `RefineResult`, or None when the refinement could not run
      (`warnings` say why; the two-stage result stands).
    - `layout`, `names`: the refinement's parameter layout and names.
    - `summary`: the `refinement` block of `result.json`.
    - `parameters`, `frozen`: the physical parameter table and the held
      parameters, at the refined estimate.
    - `ratios`: per joint `(ratio, std)` (None without encoders); `clock`: the
      refined offset and std (None when the clock was not estimated).
    - `references`: `(T_cam_base0, T_flange_marker0)`, what the correction is relative to.
    - `intrinsics`: the first camera's refined `K`, `distortion`, their std
      and the coefficients held (None when the intrinsics were held fixed).
    - `other_cameras`: per further camera its refined pose, std, views, start and intrinsics.
    - `estimate`: the refinement's whole vector with its covariance and references.
    - `problem`: the `RefineProblem` solved (its corners, encoder log and
      references), for analyses at the solution (`reprojection_residuals`).
    - `line_delays`: with a rolling shutter, per camera its line delay (s per
      row), std (None when given), whether it was estimated, and the readout
      (the delay times the image height, s).
    - `shutter_test`: without one, per camera the rolling shutter its residuals
      point to (`score_tests`); None when not tested. `lens_test`, `intrinsics_test`: the
      radial distortion, focal lengths and principal point they point to beyond the first
      camera's given ones.
    - `error_correlation`: the test of errors that repeat along the capture and
      between the views of one pose (`error_correlation`), and where it passed,
      `cov_views`, the covariance its kernel sandwich replaced.
    - `terms`: the non-geometric terms tried (`stages._terms.TermFit`: the kept
      families and coefficients, and the result's `TermsSummary`); None when none was.
    """

    fit: RefineResult | None = None
    layout: ParameterLayout | None = None
    names: tuple[str, ...] = ()
    summary: RefinementSummary | None = None
    parameters: tuple[ParameterRow, ...] | None = None
    frozen: tuple[str, ...] | None = None
    #: Per joint `(ratio, std)`.
    ratios: tuple[tuple[float, float], ...] | None = None
    clock: ClockEstimate | None = None
    intrinsics: RefinedIntrinsics | None = None
    #: `(T_cam_base0, T_flange_marker0)`.
    references: tuple[np.ndarray, np.ndarray] | None = None
    other_cameras: tuple[OtherCamera, ...] = ()
    warnings: tuple[str, ...] = ()
    #: Seconds per step (`refine_s`, `shutter_test_s`): free-form.
    timings: dict[str, float] = field(default_factory=dict)
    estimate: Estimate | None = None
    problem: RefineProblem | None = None
    line_delays: tuple[LineDelay, ...] = ()
    shutter_test: tuple[ShutterTest, ...] | None = None
    terms: TermFit | None = None
    lens_test: LensTest | None = None
    intrinsics_test: IntrinsicsTest | None = None
    #: How the solution (flattened) moves were the first camera's held focal lengths 0.1 % longer.
    focal_shift: np.ndarray | None = None
    error_correlation: ErrorCorrelation | None = None
    #: Where the residuals' errors are correlated, the covariance of the free parameters
    #: the kernel sandwich replaced (the views' sandwich or the model's).
    cov_views: np.ndarray | None = None
    #: What the covariance counts beside the noise (`_considered`; flat): None where nothing.
    considered: np.ndarray | None = None


def dist5(dist) -> np.ndarray | None:
    """OpenCV's first five distortion coefficients; `None` if more are non-zero."""
    d = np.zeros(5) if dist is None else np.asarray(dist, np.float64).ravel()
    if d.size > 5 and np.any(d[5:] != 0):
        return None
    out = np.zeros(5)
    out[: min(5, d.size)] = d[:5]
    return out


def _start_pose(views: CameraObservations, t_ctrl, inside, log_q, rate, model, mounts, targets):
    """A further camera's `T_cam_base` from its PnP poses and the two-stage
    robot: per view $T_{cam,target} (T_{base,flange}(q) T_{flange,target})^{-1}$,
    averaged (`average_pose`)."""
    idx = [i for i in range(len(views.rows)) if inside[i] and views.poses[i]]
    if not idx:
        return None
    q = interpolate(t_ctrl[idx], *log_q) * np.asarray(rate)
    T_bf = _programs.chains(np.eye(4), model, q)[:, -1]
    est = []
    for k, i in enumerate(idx):
        for m, t in enumerate(targets):
            pose = views.poses[i].get(t.name)
            if pose is not None:
                est.append(pose.T_cam_target @ np.linalg.inv(T_bf[k] @ np.asarray(mounts[m])))
    return average_pose(np.stack(est))


def sweep_angles(R_pnp, target, joint, model, T_cam_base, mounts, homes=None) -> np.ndarray:
    """Start angles of the sweeping joint in every view without encoders, from
    its PnP orientation and the two-stage model: with the others at their
    sweep's home the joint turns the target about its axis $w_j$ (camera
    frame), $R(a) = \\exp(a[w_j]_\\times) R(0)$, so $a$ is the rotation of
    $R_{PnP} R(0)^T$ about $w_j$.

    **Arguments:** per view the PnP rotation `R_pnp` `(V, 3, 3)`, the target
    index and the sweeping joint `(V,)`; the two-stage model, `T_cam_base` and
    mounts `(targets, 4, 4)`; `homes` `(joints, joints)` per sweep (None: zero).
    """
    n = model.num_joints
    home = np.zeros((n, n)) if homes is None else np.asarray(homes)
    # Per joint: at its home, then with the joint at 1 rad.
    q = np.concatenate([home, home + np.eye(n)])
    T = _programs.chains(T_cam_base, model, q)[:, -1]
    R_home, R_turned = T[:n, :3, :3], T[n:, :3, :3]
    w = so3_log(np.einsum("nab,ncb->nac", np.asarray(R_turned), np.asarray(R_home)))  # (n, 3)
    joint, target = np.asarray(joint), np.asarray(target)
    R0 = np.einsum("vab,vbc->vac", R_home[joint], np.asarray(mounts)[target][:, :3, :3])  # (V, 3, 3)
    M = np.einsum("vab,vcb->vac", np.asarray(R_pnp), R0)
    vee = 0.5 * np.stack([M[:, 2, 1] - M[:, 1, 2], M[:, 0, 2] - M[:, 2, 0], M[:, 1, 0] - M[:, 0, 1]], -1)
    cos = 0.5 * (np.trace(M, axis1=1, axis2=2) - 1.0)
    return np.arctan2(np.einsum("va,va->v", w[joint], vee), cos)


@dataclass
class _Corners:
    """Per view (one target in one frame of one camera) the corners and their bookkeeping."""

    points: list = field(default_factory=list)
    pixels: list = field(default_factory=list)
    target: list = field(default_factory=list)
    frame: list = field(default_factory=list)
    t_cam: list = field(default_factory=list)
    row: list = field(default_factory=list)  # each corner's image row (px)
    ids: list = field(default_factory=list)  # each corner's id on its target
    pose: list = field(default_factory=list)  # each view's capture index (frames.csv's `frame`)
    camera: list = field(default_factory=list)
    sweep: list = field(default_factory=list)
    pnp: list = field(default_factory=list)
    others: list = field(default_factory=list)  # (T_cam_base0, K, dist5) per further camera used
    used: list = field(default_factory=list)  # the CameraObservations used, the primary first
    warnings: list = field(default_factory=list)


def _collect(setup: Setup, obs: Observations, sync: Sync, two: TwoStage) -> _Corners:
    ds, kind = setup.dataset, setup.kind
    no_encoders = kind.per_view_angles
    offset = sync.clock.offset_s
    rate0 = to_device(
        two.arcs.rate if kind.rates_from_arcs else np.ones(setup.nominal.num_joints), np.float64
    )
    pts = {t.name: np.asarray(t.spec.points(), np.float64) for t in setup.targets}
    rolling = any(rolling_shutter(v.camera) for v in (obs.primary, *obs.others))
    out = _Corners(used=[obs.primary])
    for v in (obs.primary, *obs.others):
        t_ctrl = controller_time(v.t_cam, offset, ds.clock_drift_ppm)
        if no_encoders:
            inside = np.asarray(sync.joint) >= 0
        else:
            inside, _ = usable(ds, t_ctrl, sync.log_q)
        if v is not obs.primary:
            d5 = dist5(v.dist)
            fit = two.fit
            T0 = _start_pose(
                v, t_ctrl, inside, sync.log_q, rate0, fit.model, fit.T_flange_marker, setup.targets
            )
            if d5 is None or T0 is None:
                out.warnings.append(
                    f"camera {v.camera.name!r}: "
                    + ("unmodelled distortion" if d5 is None else "no target pose inside the encoder log")
                    + "; left out of the refinement"
                )
                continue
            out.others.append((T0, np.asarray(v.K, np.float64), d5))
            out.used.append(v)
        c = len(out.used) - 1
        for i, det in enumerate(v.detections):
            if not inside[i]:
                continue
            for m, t in enumerate(setup.targets):
                dt = det.get(t.name)
                if dt is None or len(dt.ids) < 4:
                    continue
                if no_encoders:
                    pose = v.poses[i].get(t.name)
                    if pose is None:
                        continue
                    out.sweep.append(int(sync.joint[i]))
                    out.pnp.append(pose.T_cam_target[:3, :3])
                out.points.append(pts[t.name][dt.ids])
                out.pixels.append(dt.pixels)
                out.target.append(m)
                out.frame.append(int(v.rows[i]))
                out.t_cam.append(float(v.frame_times[i]) if rolling else float(v.t_cam[i]))
                out.row.append(dt.pixels[:, 1])
                out.ids.append(np.asarray(dt.ids, int))
                out.pose.append(int(ds.frames.frame[int(v.rows[i])]))
                out.camera.append(c)
    return out


def rolling_shutter(camera) -> bool:
    """The camera reads its rows out one after the other, with its line delay given
    (above zero) or to be estimated (`line_delay_s: "estimate"` in the metadata)."""
    return bool(getattr(camera, "line_delay_s", None)) or bool(getattr(camera, "estimate_line_delay", False))


def _line_delays(corners: _Corners) -> tuple[np.ndarray, np.ndarray] | None:
    """Every used camera's start line delay (s per row; 0 when estimated or a global
    shutter) and which are estimated; `None` when no camera has a rolling shutter."""
    cams = [v.camera for v in corners.used]
    if not any(rolling_shutter(c) for c in cams):
        return None
    start = np.array([float(getattr(c, "line_delay_s", None) or 0.0) for c in cams])
    return start, np.array([bool(getattr(c, "estimate_line_delay", False)) for c in cams])


def _link_mounts(setup: Setup, obs: Observations, sync: Sync, two: TwoStage) -> np.ndarray:
    """Start mounts of every arm target on its link (`jaxcal._links.start_mounts`)
    from the two-stage robot at the rows' encoder positions."""
    fit, sel = two.fit, two.link_rows
    T = _programs.chains(fit.T_cam_base, fit.model, sync.q[sel])
    return start_mounts(T, [obs.primary.poses[i] for i in sel], setup.targets, setup.target_link)


def frees_intrinsics(obs: Observations, options: Options) -> bool:
    """The first camera's intrinsics join the refinement when they were
    self-calibrated (the sweep images alone fix them poorly, and held fixed
    they bias the robot) or when the caller asks (`refine_intrinsics`)."""
    if options.refine_intrinsics is not None:
        return bool(options.refine_intrinsics)
    return obs.primary.intrinsics.source != "metadata"


def _problem(setup: Setup, obs: Observations, sync: Sync, two: TwoStage, corners: _Corners, K, d5, options):
    """The `RefineProblem`, its start, the layout and the candidate mask."""
    kind, nominal, fit = setup.kind, setup.nominal, two.fit
    n, M = nominal.num_joints, len(setup.targets)
    if not kind.per_view_angles:
        log_q = pad_log(*sync.log_q, bucket(len(sync.log_q[0])))
    else:
        log_q = (np.array([-np.inf, np.inf]), np.zeros((2, n)))  # not read: each view's angle is an unknown
    V = len(corners.points)
    delays = _line_delays(corners)
    data = make_corner_data(
        corners.points,
        corners.pixels,
        np.array(corners.target),
        np.array(corners.frame),
        np.array(corners.t_cam),
        *log_q,
        setup.dataset.clock_drift_ppm,
        camera=np.array(corners.camera) if corners.others else None,
        sweep_joint=np.array(corners.sweep) if kind.per_view_angles else None,
        views=bucket(V),
        sweep_home=np.asarray(sync.homes)[corners.sweep]
        if kind.per_view_angles and sync.homes is not None
        else None,
        row=None if delays is None else corners.row,
    )
    correction, mounts0 = fit.params.correction, fit.T_flange_marker0
    if kind.sequential:
        mounts0 = _link_mounts(setup, obs, sync, two)
        correction = eqx.tree_at(lambda c: c.tool, correction, jnp.zeros((M, 6)))
    problem = RefineProblem(
        nominal=nominal,
        T_flange_marker0=to_device(mounts0),
        T_cam_base0=to_device(fit.T_cam_base0),
        K0=to_device(K, np.float64),
        dist0=to_device(d5),
        offset0_s=to_device(np.float64(sync.clock.offset_s)),
        data=data,
        other_cameras=OtherCameras(*(to_device(np.stack(a)) for a in zip(*corners.others)))
        if corners.others
        else None,
        eye_in_hand=kind.inverts_poses,
        target_link=to_device(setup.target_link) if kind.sequential else None,
        line_delay0_s=None if delays is None else to_device(delays[0], np.float64),
    )
    params0 = RefineParams(
        cam=fit.params.cam,
        correction=correction,
        rate=to_device(two.arcs.rate if kind.rates_from_arcs else np.ones(n), np.float64),
        clock_ms=to_device(np.zeros(())),
        intrinsics=to_device(np.zeros(9)),
        other_cams=to_device(np.zeros((len(corners.others), 6))) if corners.others else None,
        angles=None,
        line_delay_us=None if delays is None else to_device(np.zeros(len(delays[0]))),
    )
    angle_names = []
    if kind.per_view_angles:
        a0 = sweep_angles(
            np.stack(corners.pnp),
            corners.target,
            corners.sweep,
            fit.model,
            to_device(fit.T_cam_base),
            fit.T_flange_marker,
            sync.homes,
        )
        a0 = np.concatenate([a0, np.zeros(bucket(V) - V)])  # padded views: zero columns, never free
        params0 = eqx.tree_at(
            lambda p: p.angles, params0, to_device(a0, np.float64), is_leaf=lambda x: x is None
        )
        angle_names = [f"frame{f}.{nominal.joint_names[j]}" for f, j in zip(corners.frame, corners.sweep)]
        angle_names += [f"{PADDING}{k}" for k in range(bucket(V) - V)]
    layout = kind.layout(
        nominal,
        M,
        other_cameras=tuple(v.camera.name for v in corners.used[1:]),
        angles=tuple(angle_names),
        line_delays=() if delays is None else tuple(v.camera.name for v in corners.used),
    )
    cand = layout.candidates(
        rates=kind.fits_rates,
        clock=bool(sync.clock.estimated),
        intrinsics=frees_intrinsics(obs, options),
        line_delay=False if delays is None else delays[1],
    )
    if kind.keeps_two_stage_gauge:
        cand[: layout.axis_size] &= np.asarray(fit.free)
    return problem, params0, layout, cand


def _outcome(setup: Setup, sync: Sync, two: TwoStage, corners, problem, res, layout, cand, free) -> Refined:
    """The refined figures (the two-stage ones stay beside them in `summary`)."""
    nominal, kind = setup.nominal, setup.kind
    names = layout.names()
    summary = summarize_refinement(res, names, problem.data)
    std = np.asarray(res.std)
    n_ax = layout.axis_size
    mount_names = [t.name for t in setup.targets]
    parameters = physical_parameters(
        layout,
        nominal,
        problem.T_flange_marker0,
        problem.T_cam_base0,
        res.params.cam,
        res.params.correction,
        np.asarray(res.cov)[:n_ax, :n_ax],
        free[:n_ax],
        mount_names,
    )
    ratios = None
    if kind.fits_rates:
        rate, nominal_ratio = np.asarray(res.params.rate), np.asarray(nominal.reduction_ratio)
        i_rate = layout.index("rate")
        ratios = tuple(
            (float(nominal_ratio[j] / rate[j]), float(nominal_ratio[j] * std[i_rate[j]] / rate[j] ** 2))
            for j in range(nominal.num_joints)
        )
    intrinsics = None
    i_intr = layout.index("intr")
    if free[i_intr].any():
        intrinsics = RefinedIntrinsics(
            K=np.asarray(res.K),
            distortion=np.asarray(res.dist),
            std=tuple(Named(n, float(std[i])) for n, i in zip(INTRINSIC_NAMES, i_intr) if free[i]),
            held=tuple(n for n, i in zip(INTRINSIC_NAMES, i_intr) if not free[i]),
        )
    clock = None
    if sync.clock.estimated:
        clock = ClockEstimate(float(res.offset_s), float(1e-3 * std[layout.index("clock")[0]]))
    frame = corners.frame
    free_std = {nm: float(std[i]) for i, nm in enumerate(names) if free[i]}
    angles = None
    if kind.per_view_angles:
        angles = _joint_angles(nominal, corners, res, layout, std)
        free_std = {nm: sd for nm, sd in free_std.items() if nm not in set(layout.angles)}
    cams_v = np.zeros(len(frame), int) if not corners.others else np.array(corners.camera)
    views = {v.camera.name: int((cams_v == c).sum()) for c, v in enumerate(corners.used)}
    summary = summary_record(
        {
            **summary,
            "views": len(frame),
            "frames": len(set(frame)),
            "free_parameters": int(free.sum()),
            "held_at_start": [nm for nm, f in zip(names, free) if not f and not nm.startswith(PADDING)],
            "frozen_beyond_two_stage": [
                nm for nm, c, f in zip(names, cand, free) if c and not f and not nm.startswith(PADDING)
            ],
            "std": free_std,
            "loss": LOSS,
            "views_per_camera": views,
        },
        two_stage=TwoStageStart(
            T_cam_base=np.asarray(two.fit.T_cam_base, np.float64),
            std_cam=np.asarray(two.fit.std, np.float64)[:6],
            T_flange_target=np.asarray(two.fit.T_flange_marker, np.float64),
            clock_offset_s=sync.clock.offset_s,
            ratios=tuple(Named(a.joint, a.ratio) for a in two.arc_rows),
        ),
        joint_angles=angles,
    )
    others = _other_cameras(corners, res, layout, std, views)
    warnings = list(corners.warnings)
    if summary.outlier_frames:
        warnings.append(
            f"refinement: {len(summary.outlier_frames)} frame(s) whose corners stay outliers: "
            f"{list(summary.outlier_frames[:20])}"
        )
    return Refined(
        fit=jax.device_get(res),
        layout=layout,
        names=tuple(names),
        summary=summary,
        parameters=parameter_rows(parameters),
        frozen=tuple(nm for nm, f in zip(names[:n_ax], free[:n_ax]) if not f),
        ratios=ratios,
        clock=clock,
        intrinsics=intrinsics,
        references=(np.asarray(problem.T_cam_base0), np.asarray(problem.T_flange_marker0)),
        other_cameras=tuple(others),
        warnings=tuple(warnings),
        estimate=Estimate(
            x=flat_on_device(res.params),
            cov=to_device(res.cov),
            free=to_device(free),
            nominal=nominal,
            T_flange_marker0=to_device(problem.T_flange_marker0),
            T_cam_base0=to_device(problem.T_cam_base0),
            reduction_ratio=to_device(res.model.reduction_ratio),
            layout=layout,
            mount_names=tuple(mount_names),
        ),
    )


def _joint_angles(nominal, corners: _Corners, res, layout: ParameterLayout, std) -> JointAngles:
    """Without an encoder log: every sweep frame's joint angle estimated from the images."""
    g0 = layout.index("angles")[0]
    a = np.asarray(res.params.angles)
    return JointAngles(
        note="no encoder log: each sweep frame's joint angle was estimated from the images "
        "(commanded coordinates; the other joints at zero); reduction ratios are not identifiable",
        views=tuple(
            ViewAngle(
                frame=int(f),
                joint=nominal.joint_names[j],
                angle_deg=float(np.degrees(a[k])),
                std_deg=float(np.degrees(std[g0 + k])),
            )
            for k, (f, j) in enumerate(zip(corners.frame, corners.sweep))
        ),
    )


def _other_cameras(corners: _Corners, res, layout: ParameterLayout, std, views: dict) -> list[OtherCamera]:
    """Every fixed camera the refinement added beside the first: its pose, std and start."""
    T_all = np.asarray(res.T_cam_bases)
    others = []
    for c, v in enumerate(corners.used[1:], start=1):
        k = layout.index("others")[6 * (c - 1)]
        T0, K, d5 = corners.others[c - 1]
        others.append(
            OtherCamera(
                camera=v.camera.name,
                T_cam_base=T_all[c],
                std_cam=std[k : k + 6],
                views=views[v.camera.name],
                T_cam_base_start=np.asarray(T0),
                K=np.asarray(K),
                distortion=np.asarray(d5),
            )
        )
    return others


def _delay_rows(corners: _Corners, res, layout: ParameterLayout, free) -> tuple[LineDelay, ...]:
    """Per used camera with a rolling-shutter model, its line delay (s per row), std,
    whether it was estimated and its readout (s): the `line_delay` rows of the summary."""
    if res.line_delay_s is None:
        return ()
    std, idx = np.asarray(res.std), layout.index("line_delay")
    rows = []
    for c, v in enumerate(corners.used):
        delay = float(res.line_delay_s[c])
        est = bool(free[idx[c]])
        rows.append(
            LineDelay(
                camera=v.camera.name,
                line_delay_s=delay,
                std_s=float(1e-6 * std[idx[c]]) if est else None,
                estimated=est,
                readout_s=delay * v.camera.height,
            )
        )
    return tuple(rows)


def refine(setup: Setup, obs: Observations, sync: Sync, two: TwoStage, options: Options) -> Refined:
    """Refine the two-stage result on every corner (see the module docstring)."""
    t0 = time.perf_counter()
    cam = setup.camera
    d5 = dist5(obs.primary.dist)
    if d5 is None:
        return Refined(
            warnings=(
                f"camera {cam.name!r}: distortion beyond (k1, k2, p1, p2, k3) is not modelled by the refinement; "
                "stopped at two-stage",
            )
        )
    corners = _collect(setup, obs, sync, two)
    if not corners.points:
        return Refined(
            warnings=(
                *corners.warnings,
                "refinement: no detected corners inside the encoder log; stopped at two-stage",
            )
        )
    n_cams = len(corners.used)
    options.say(
        "refinement: reprojection error of every corner over all parameters (robust, Cauchy)"
        + (f", {n_cams} cameras" if n_cams > 1 else "")
    )
    problem, params0, layout, cand = _problem(setup, obs, sync, two, corners, obs.primary.K, d5, options)
    with working(options.log is not None, "refinement", say=options.say):
        free, _ = _programs.identifiable()(problem, params0, cand, tol=setup.identifiability_tol)
        free = np.asarray(free)
        terms = resolve(setup, options)
        tried = terms if setup.kind.terms_in == "refinement" else ()
        res = _programs.refinement(free, jacobian=bool(tried))(problem, params0)
    fit_terms = None
    if tried:
        problem, res, layout, cand, free, fit_terms = with_terms(
            setup, sync, problem, res, layout, cand, free, tried, options
        )
    elif terms:
        fit_terms = TermFit((), np.zeros(0), None, None, not_tried(terms, "the capture has no encoder log"))
    # The shutter's, the lens's and the intrinsics' score tests, in the `Future` the verdict reads (`run_ahead`
    # runs it inline).
    pending = _programs.run_ahead("score tests", score_tests, setup, corners, problem, res, layout, free)
    jax.block_until_ready(res)
    correlation, cov_free, cov_views = error_correlation(
        corners, res, options.limits, lambda: _programs.view_information(free)(problem, res)
    )
    cov = np.array(res.cov, np.float64)
    if cov_free is not None:  # the kernel sandwich's covariance, where larger than the views'
        cov[np.ix_(*2 * [np.flatnonzero(np.asarray(free))])] = cov_free
    timings = {"refine_s": time.perf_counter() - t0}
    t0 = time.perf_counter()
    test, lens, pinhole, sensitivity = pending.result()
    if test is not None:
        timings["shutter_test_s"] = time.perf_counter() - t0  # the wait for them, past the refinement
    focal_shift = None if sensitivity is None else sensitivity[:, :2] @ (1e-3 * np.diag(problem.K0)[:2])
    considered = _considered(cov.shape, setup, sensitivity, fit_terms)
    if considered is not None:  # what the model takes as exact, counted
        cov += considered
    if cov_free is not None or considered is not None:
        res = eqx.tree_at(lambda r: (r.cov, r.std), res, (cov, np.sqrt(np.maximum(np.diag(cov), 0.0))))
    out = _outcome(setup, sync, two, corners, problem, res, layout, cand, free)
    if considered is not None and out.clock is not None:  # the clock's std in the noise (the arm test's)
        i = layout.index("clock")[0]
        noise = 1e-3 * np.sqrt(max(cov[i, i] - considered[i, i], 0.0))
        out = dataclasses.replace(out, clock=dataclasses.replace(out.clock, std_s=float(noise)))
    delays = _delay_rows(corners, res, layout, free)
    summary = dataclasses.replace(
        out.summary,
        line_delay=delays or None,
        rolling_shutter_test=test,
        lens_test=lens,
        intrinsics_test=pinhole,
        error_correlation=correlation,
    )
    return dataclasses.replace(
        out,
        summary=summary,
        problem=problem,
        line_delays=delays,
        shutter_test=test,
        lens_test=lens,
        intrinsics_test=pinhole,
        focal_shift=focal_shift,
        error_correlation=correlation,
        cov_views=cov_views,
        considered=considered,
        timings=timings,
        terms=fit_terms,
    )


def _considered(shape, setup: Setup, sensitivity, fit_terms: TermFit | None) -> np.ndarray | None:
    """The covariance of what the refinement holds but may be wrong (a consider covariance, in the
    flat parameters, `shape`), or None: the held `K`'s own uncertainty (`cameras[].K_std`, through
    the score tests' `sensitivity`) and the geometry's shifts that what the non-geometric terms
    cannot tell from it would make (`stages._terms.unresolved`)."""
    out, counted = np.zeros(shape), False
    if sensitivity is not None and setup.camera.K_std is not None:
        out += sensitivity @ np.diag(np.square(setup.camera.K_std)) @ sensitivity.T
        counted = True
    if fit_terms is not None and fit_terms.shift is not None:
        out[np.ix_(*2 * [fit_terms.shift_at])] += fit_terms.shift @ fit_terms.shift.T
        counted = True
    return out if counted else None


def summary_record(figures: dict, **typed) -> RefinementSummary:
    """The refinement's summary as its typed record: `figures`, the plain figures of
    `jaxcal._refine.summarize_refinement` and the stage's (decoded by `records.from_plain`),
    and the fields already typed (`two_stage`, `joint_angles`)."""
    extra = set(figures) - {f.name for f in dataclasses.fields(RefinementSummary)}
    if extra:  # a figure the summary gained must become a field, not vanish from result.json
        raise ValueError(f"refinement summary keys without a RefinementSummary field: {sorted(extra)}")
    return dataclasses.replace(from_plain(RefinementSummary, figures), **typed)


def succeeded(refined: Refined) -> bool:
    """The refinement ran, its final solve succeeded and the pose is finite."""
    res = refined.fit
    if res is None:
        return False
    return bool(result_is(res.result)) and bool(np.all(np.isfinite(np.asarray(res.T_cam_base))))
