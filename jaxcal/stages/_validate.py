"""Stage 6, validate (synthetic datasets): the calibration against `truth.json`.

End-effector error over random configurations (nominal, two-stage and
refined), the camera pose in the estimator's gauge, per-joint axis, ratio
and zero-offset errors, the clock offset and the further cameras' poses.
"""

import dataclasses
import functools
import time
from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._correction import KinematicCorrection, apply_correction
from .._device import to_device
from .._exported import stored_jit
from .._geometry import se3_exp
from .._geometry import so3_log as jax_so3_log
from .._kinematics import REVOLUTE, forward_kinematics
from .._montecarlo import NoiseModel, SweepPlan, synthesize_sweeps
from .._npgeom import pose_inverse, so3_log
from .._scoring import score
from .._uncertainty import joint_travel, on_travel
from ..io.dataset import TruePoses, true_poses
from ..records import CameraPoseError, EEErrors, JointError, OtherCamera, PoseError, ValidationReport
from . import _programs
from ._refine import Refined
from ._setup import Options, Setup
from ._synchronise import Sync
from ._two_stage import TwoStage

#: Random configurations of the end-effector comparison, and their seed.
CONFIGURATIONS = 1000
SEED = 0


@dataclass(frozen=True, eq=False)
class Validation:
    """`report`: the `validation` block of `result.json`; `ee_errors`: per
    configuration the EE error (mm) `before` (nominal model), `two_stage`, `after`."""

    report: ValidationReport
    ee_errors: EEErrors
    #: Seconds per step (`validation_s`): free-form.
    timings: dict[str, float]


def _truth_poses(setup: Setup, truth: TruePoses):
    """The true fixed frame and mounts in the fits' roles, or None when the truth lacks them."""
    cam = setup.camera.name
    if setup.board is not None:
        board = setup.board.name
        if cam not in truth.T_mount_cam or board not in truth.T_link_target:
            return None
        T_cb = np.linalg.inv(truth.T_link_target[board]) @ truth.T_world_base
        return to_device(T_cb, np.float64), to_device(np.asarray(truth.T_mount_cam[cam])[None], np.float64)
    if cam not in truth.T_cam_base:
        return None
    mounts = np.stack([np.asarray(truth.T_link_target[t.name]) for t in setup.targets])
    return to_device(truth.T_cam_base[cam], np.float64), to_device(mounts, np.float64)


#: The pose capture's gauge fit (`_pose_gauge`): configurations, Gauss-Newton steps, and the lever
#: that weighs a rotation against a translation (m per rad).
GAUGE_CONFIGURATIONS = 200
GAUGE_STEPS = 8
GAUGE_LEVER_M = 0.1
#: What a capture without sweeps measures its fixed-frame error against (`_pose_gauge`). The
#: truth's perturbations of the parameters the refinement holds at nominal (a joint origin's offset
#: along joint 1's axis is the base's) move the estimate along the gauge without any tool-point
#: error: against the truth's own pose a planned capture read 0.37 mm where its gauge gives 0.03.
POSE_GAUGE = (
    "the truth seen through the same held parameters (the estimator's parameters fitted to the truth's "
    "marker poses)"
)


def _rot_deg(R) -> float:
    return float(np.degrees(np.linalg.norm(so3_log(R))))


def _pose_error(dT) -> PoseError:
    return PoseError(trans_mm=float(np.linalg.norm(dT[:3, 3]) * 1e3), rot_deg=_rot_deg(dT[:3, :3]))


@functools.cache
def _exact_sweeps(frames: int, use_encoders: bool):
    """The truth's sweeps of 40 degrees, `frames` per sweep, with near-zero noise:
    what the gauge's arc and axis fits see."""

    def exact_sweeps(true, T_cam_base, mounts, nominal_ratio, home):
        plan = SweepPlan(range_deg=40.0, frames=frames)
        tiny = NoiseModel(position_mm=1e-3, orientation_deg=1e-4, encoder_deg=0.0)
        return synthesize_sweeps(
            true,
            T_cam_base,
            mounts,
            plan,
            tiny,
            jax.random.key(1),
            nominal_ratio=nominal_ratio,
            use_encoders=use_encoders,
            home=home,
        )

    return stored_jit(exact_sweeps, "exact_sweeps", (frames, use_encoders))


def _score(fit, true, T_cam_base_true, mounts_true, nominal, travel, fits: dict):
    """At the validation's configurations (`CONFIGURATIONS`, seed `SEED`, within
    each joint's travel): `score`, and per configuration the marker position
    error (mm) of each `(model, T_cam_base, mount)` in `fits`; one compiled call."""
    q = jax.random.uniform(
        jax.random.key(SEED), (CONFIGURATIONS, nominal.num_joints), minval=-np.pi, maxval=np.pi
    )
    q = on_travel(nominal, q, travel)

    def marker(model, T_cb, mount):
        return (T_cb @ jax.vmap(lambda qq: forward_kinematics(model, qq)[-1])(q) @ mount)[:, :3, 3]

    tru = marker(true, T_cam_base_true, mounts_true[0])
    errors = {k: 1e3 * jnp.linalg.norm(marker(*f) - tru, axis=-1) for k, f in fits.items()}
    return errors, score(fit, true, T_cam_base_true, mounts_true, nominal, q)


_score = stored_jit(_score, "validation_score")


def _gauge(setup: Setup, sync: Sync, two: TwoStage, true, T_cb_true, mounts_true, loss):
    """The estimator's gauge: the same axis fit on (nearly) exact sweeps of the truth, with the
    same parameters frozen (its fixed frame and model: the truth as the estimator sees it). The sweeps have
    the dataset's shapes, so the arc and axis fits reuse their compiled code."""
    nominal, fit = setup.nominal, two.fit
    mounts0 = fit.T_flange_marker0
    home = None if sync.homes is None else jnp.asarray(sync.homes)
    exact = _exact_sweeps(two.sweeps.mask.shape[-1], bool(two.arcs.has_encoder))(
        true,
        T_cb_true,
        mounts_true[: mounts0.shape[0]],  # the axis fit's markers (the flange's, first)
        nominal.reduction_ratio,
        home,
    )
    arcs_exact = _programs.arc_fits(loss, nominal.joint_types)(exact)
    return _programs.axis_fit(setup.kind.axis_fit_uses_poses)(
        nominal, arcs_exact, mounts0, fit.free, home, setup.kind.fixed_frame_free
    )


def _pose_gauge(nominal, true, free, T_cb_true, mount_true, travel):
    """The estimator's gauge for a capture without sweeps, `(T_cam_base, zero offsets)`: the
    estimator's own parameters (its fixed frame, the joint origins and zero offsets it freed, the
    first mount) fitted to the truth's marker poses at the validation's configurations, those it
    held at nominal held there too (a joint origin's spin about its axis, held, and the zero offset
    are one direction: the truth's spin comes out in the gauge's zero offset). The truth's perturbations of the held parameters then move the fitted fixed frame
    as they moved the estimate, and nothing else does (Gauss-Newton from the nominal robot at the
    true fixed frame and mount, `GAUGE_STEPS` steps: the fit is exact where only the gauge differs)."""
    n = nominal.num_joints
    q = on_travel(
        nominal,
        jax.random.uniform(jax.random.key(SEED), (GAUGE_CONFIGURATIONS, n), minval=-np.pi, maxval=np.pi),
        travel,
    )
    return _pose_gauge_program(n)(nominal, true, jnp.asarray(free), T_cb_true, mount_true, q)


@functools.cache
def _pose_gauge_program(n: int):
    def fit(nominal, true, free, T_cb_true, mount_true, q):
        def poses(x):
            corr = KinematicCorrection(
                origin=x[6 : 6 + 6 * n].reshape(n, 6),
                zero_offset=x[6 + 6 * n : 7 * n + 6],
                tool=x[None, 7 * n + 6 :],
            )
            model, mounts = apply_correction(nominal, mount_true[None], corr)
            T_cb = T_cb_true @ se3_exp(x[:6])
            return jax.vmap(lambda qq: T_cb @ forward_kinematics(model, qq)[-1] @ mounts[0])(q)

        target = jax.vmap(lambda qq: T_cb_true @ forward_kinematics(true, qq)[-1] @ mount_true)(q)

        def residual(x):
            T = poses(x)
            dR = jnp.einsum("kba,kbc->kac", target[:, :3, :3], T[:, :3, :3])
            rot = jax.vmap(jax_so3_log)(dR)
            return jnp.concatenate([(T[:, :3, 3] - target[:, :3, 3]).ravel(), GAUGE_LEVER_M * rot.ravel()])

        def step(x, _):
            r, J = residual(x), jax.jacfwd(residual)(x)
            J = jnp.where(free[None, :], J, 0.0)  # held parameters stay at nominal
            dx = jnp.linalg.lstsq(J, -r)[0]
            return x + jnp.where(free, dx, 0.0), None

        # From the nominal robot at the true fixed frame and mount (corrections of a few mm and
        # tenths of a degree: Gauss-Newton converges in a few steps).
        x, _ = jax.lax.scan(step, jnp.zeros(7 * n + 12), None, length=GAUGE_STEPS)
        return T_cb_true @ se3_exp(x[:6]), nominal.zero_offset + x[6 + 6 * n : 7 * n + 6]

    return stored_jit(fit, "pose_gauge", (n,))


def other_camera_errors(
    truth: TruePoses, camera: str, T_two_stage, T_refined, others: tuple[OtherCamera, ...]
) -> tuple[CameraPoseError, ...]:
    """Each further camera's pose relative to the first, against the truth
    (gauge-free: the base frame cancels), at the start (relative to the
    two-stage first camera, the gauge it was computed in) and refined."""
    if camera not in truth.T_cam_base:
        return ()
    T0_true = truth.T_cam_base[camera]
    out = []
    for c in others:
        if c.camera not in truth.T_cam_base:
            continue
        rel_true = truth.T_cam_base[c.camera] @ np.linalg.inv(T0_true)
        row = {}
        for key, T, T0 in (
            ("start", c.T_cam_base_start, T_two_stage),
            ("refined", c.T_cam_base, T_refined),
        ):
            D = np.linalg.inv(rel_true) @ (np.asarray(T) @ np.linalg.inv(np.asarray(T0)))
            cos = np.clip((np.trace(D[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
            row[key] = PoseError(
                trans_mm=float(1e3 * np.linalg.norm(D[:3, 3])), rot_deg=float(np.degrees(np.arccos(cos)))
            )
        out.append(CameraPoseError(camera=c.camera, **row))
    return tuple(out)


def _joint_errors(nominal, true, model, s) -> tuple[JointError, ...]:
    """Per joint its axis, ratio and zero-offset errors against the truth (`score`'s figures `s`;
    the zero offsets against `true`'s: the truth in the estimator's gauge, `_gauge` with sweeps,
    `_pose_gauge` without);
    a prismatic joint has a direction (no axis position), the scale's error and mm."""
    ratio_err, dir_deg, pos_mm = (np.asarray(a) for a in (s.ratio_err_percent, s.axis_dir_deg, s.axis_pos_mm))
    rows, zero_err = [], np.asarray(model.zero_offset) - np.asarray(true.zero_offset)
    for k, (j, kind) in enumerate(zip(nominal.joint_names, nominal.joint_types)):
        dz = float(zero_err[k])
        rows.append(
            JointError(
                joint=j,
                axis_direction_deg=float(dir_deg[k]),
                axis_position_mm=float(pos_mm[k]) if kind == REVOLUTE else None,
                ratio_percent=None if not np.isfinite(ratio_err[k]) else float(ratio_err[k]),
                zero_offset_deg=float(np.degrees(dz)) if kind == REVOLUTE else None,
                zero_offset_mm=None if kind == REVOLUTE else 1e3 * dz,
            )
        )
    return tuple(rows)


def validate(
    setup: Setup, sync: Sync, two: TwoStage, refined: Refined | None, options: Options
) -> Validation | None:
    """Errors against `truth.json` (None when the truth lacks the poses to compare)."""
    t0 = time.perf_counter()
    truth = true_poses(setup.dataset.truth)
    poses = _truth_poses(setup, truth)
    if poses is None:
        return None
    options.say(f"validating against truth.json ({CONFIGURATIONS} random configurations)")
    T_cb_true, mounts_true = poses
    nominal, two_fit = setup.nominal, two.fit
    true = truth.model
    res = refined.fit if refined is not None else None
    fit = res if res is not None else two_fit
    first = lambda mounts: to_device(np.asarray(mounts)[0])  # noqa: E731 - on the host: no program
    fits = {
        "before": (nominal, fit.T_cam_base, first(fit.T_flange_marker)),
        "two_stage": (two_fit.model, two_fit.T_cam_base, first(two_fit.T_flange_marker)),
        "after": (fit.model, fit.T_cam_base, first(fit.T_flange_marker)),
    }
    travel = joint_travel(nominal, setup.dataset.joint_limits)
    err, s = _score(fit, true, T_cb_true, mounts_true, nominal, travel, fits)
    ee = EEErrors(**{k: np.asarray(v) for k, v in err.items()})
    # The estimator's gauge: the axis fit's frozen parameters (a pose-based capture has no axis fit,
    # and the refinement holds joint 1's frame at nominal, as the truth does).
    gauge = (
        _gauge(setup, sync, two, true, T_cb_true, mounts_true, options.arc_loss)
        if setup.kind.has_arcs
        else None
    )
    if gauge is not None:
        T_gauge, true_gauge = np.asarray(gauge.T_cam_base), gauge.model
    elif setup.kind.images:  # the truth seen through the parameters the estimator held
        free = np.asarray(fit.free)[: 7 * nominal.num_joints + 12]
        T_gauge, zero = _pose_gauge(nominal, true, free, T_cb_true, mounts_true[0], travel)
        true_gauge = eqx.tree_at(lambda m: m.zero_offset, true, jnp.asarray(zero))
    else:  # a tracker's point has no orientation to fit; its truth is anchored
        T_gauge, true_gauge = T_cb_true, true
    dT = pose_inverse(T_gauge) @ np.asarray(fit.T_cam_base)
    dT_raw = pose_inverse(T_cb_true) @ np.asarray(fit.T_cam_base)
    rms = lambda e: float(np.sqrt(np.mean(e**2)))  # noqa: E731
    offset_s = refined.clock.offset_s if refined is not None and refined.clock else sync.clock.offset_s
    true_offset = truth.clock_offset_s
    out = ValidationReport(
        configurations=CONFIGURATIONS,
        ee_point=setup.kind.ee_point,
        ee_rms_mm_before=rms(ee.before),
        ee_max_mm_before=float(ee.before.max()),
        ee_rms_mm_after=rms(ee.after),
        ee_max_mm_after=float(ee.after.max()),
        ee_rms_mm_two_stage=rms(ee.two_stage),
        ee_max_mm_two_stage=float(ee.two_stage.max()),
        refined=res is not None,
        T_cam_base_error=dataclasses.replace(
            _pose_error(dT),
            gauge="the truth seen through the same frozen parameters (the same fit on exact sweeps)"
            if setup.kind.has_arcs
            else POSE_GAUGE
            if setup.kind.images
            else "the truth's own pose (the simulated device frame absorbs joint 1's)",
            raw_trans_mm=float(np.linalg.norm(dT_raw[:3, 3]) * 1e3),
            raw_rot_deg=_rot_deg(dT_raw[:3, :3]),
        ),
        parameter_errors=_joint_errors(nominal, true_gauge, fit.model, s),
        true_ratios=tuple(np.asarray(true.reduction_ratio).tolist()),
        true_clock_offset_s=true_offset,
        T_cam_base_error_two_stage=None
        if res is None
        else _pose_error(pose_inverse(T_gauge) @ np.asarray(two_fit.T_cam_base)),
        # Encoders stamped `latency_s` late look like a camera clock that much behind: the offset a
        # clock fit should find is the truth's less the simulated arm's latency.
        clock_offset_error_ms=None
        if true_offset is None
        else 1e3 * (offset_s - true_offset + (truth.arm or {}).get("latency_s", 0.0)),
        other_cameras=other_camera_errors(
            truth, setup.camera.name, two_fit.T_cam_base, res.T_cam_base, refined.other_cameras
        )
        if refined is not None and refined.other_cameras
        else None,
    )
    return Validation(out, ee, {"validation_s": time.perf_counter() - t0})
