"""Stage 3, synchronise: the camera-controller clock offset (estimated when
unknown), the encoder log at every frame, and which joint sweeps in which
frame; for single-joint sweeps, the padded per-joint sweeps the arc fits take.

The clock relation lives in `jaxcal._clocksync.controller_time`.
"""

import dataclasses
import time
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from .._arcdata import make_arc_data
from .._buckets import bucket, pad_log
from .._clocksync import LINEAR_UP_TO_S, controller_time, interpolate_encoders
from .._device import result_is, to_device
from .._kinematics import PRISMATIC
from .._links import link_poses
from .._progress import working
from ..errors import CalibrationError
from ..io.dataset import Dataset
from ..records import Clock, Named
from . import _programs
from ._observe import CameraObservations, Observations
from ._setup import Options, Setup
from .kinds import AT_ZERO_DEG, MOVING_DEG

_DEG = np.pi / 180.0


@dataclass(frozen=True, eq=False)
class Sweeps:
    """The marker poses of every joint sweep, ready for the arc fits (NumPy).

    - `rows`: per joint, the dataset's frame-table rows used, `(joints, frames)`
      padded with -1.
    - `positions` (m), `orientations` (None for measured points), `covariances`
      (of position and camera-frame rotation vector; position only without
      orientations), `mask` `(joints, markers, frames, ...)`.
    - `t_cam`: camera-clock stamps `(joints, frames)`; `encoder`: commanded joint
      positions interpolated at them (rad) or None.
    """

    rows: np.ndarray
    positions: np.ndarray
    orientations: np.ndarray | None
    covariances: np.ndarray
    mask: np.ndarray
    t_cam: np.ndarray
    encoder: np.ndarray | None

    def arc_data(self):
        """Stacked `ArcData` (joints leading) for `jax.vmap(fit_arc)`: one compiled program
        (`_programs.arc_data`), built once per `Sweeps`."""
        data = self.__dict__.get("_arc_data")
        if data is None:
            data = _programs.arc_data(
                self.positions, self.orientations, self.covariances, self.mask, self.encoder
            )
            object.__setattr__(self, "_arc_data", data)
        return data


@dataclass(frozen=True, eq=False)
class Sync:
    """The clock and the frames placed on the controller's time line.

    - `clock`: the offset used, its std, whether it was estimated, the drift and the
      metadata's offset when the estimate replaced it (`Clock`, no two-stage figures yet).
    - `log_q`: the encoder log as commanded joint positions `(t (T,), q (T, joints))`, or None.
    - `t_ctrl`, `q`, `inside`: per row of the two-stage camera, the controller
      time, the interpolated commanded positions (None without a log) and
      whether it lies inside the log and outside every encoder glitch
      (`glitched`: the rows dropped for a glitch, see `Dataset.encoder_glitches`).
    - `joint`: per row, the joint sweeping alone (-1: none; all -1 with free motion).
    - `sweeps`, `counts`: the per-joint sweeps and frames used per joint
      (single-joint sweeps; None with free motion, whose sweeps come from the
      sequential procedure).
    - `homes`: per joint sweep, the commanded configuration the other joints
      held (its own entry zero), `(joints, joints)`; None when every sweep
      started from zero.
    """

    clock: Clock
    log_q: tuple[np.ndarray, np.ndarray] | None
    t_ctrl: np.ndarray
    q: np.ndarray | None
    inside: np.ndarray
    glitched: np.ndarray
    joint: np.ndarray
    sweeps: Sweeps | None
    #: Per joint the frames of its sweep.
    counts: tuple[Named, ...] | None
    homes: np.ndarray | None
    notes: tuple[str, ...]
    #: Seconds per step (`sync_s`): free-form.
    timings: dict[str, float]


def commanded_positions(ds: Dataset, nominal) -> tuple[np.ndarray, np.ndarray] | None:
    """The encoder log as commanded joint positions `motor / nominal ratio`: `(t (T,), q (T, joints))`."""
    if ds.encoder_t is None:
        return None
    ratio = np.asarray(nominal.reduction_ratio, np.float64)
    return ds.encoder_t, ds.encoder_motor / ratio


def interpolate(t, enc_t, enc_q) -> np.ndarray:
    """The log `enc_q (T, joints)` interpolated at controller times `t` as the clock fit and
    the refinement read it (`jaxcal._clocksync.interpolate_encoders`), `t.shape + (joints,)`."""
    t, enc_t, enc_q = (np.asarray(x, np.float64) for x in (t, enc_t, enc_q))
    q = np.stack([np.interp(t, enc_t, enc_q[:, j]) for j in range(enc_q.shape[1])], axis=-1)
    if enc_t.size < 2:
        return q
    i = np.clip(np.searchsorted(enc_t, t, side="right") - 1, 0, enc_t.size - 2)
    long = np.diff(enc_t)[i] > LINEAR_UP_TO_S
    if np.any(long):  # a slow log's long segments: the cubic
        cubic = jax.vmap(interpolate_encoders, in_axes=(None, None, 1), out_axes=-1)(t, enc_t, enc_q)
        q = np.where(long[..., None], np.asarray(cubic), q)
    return q


def assign_frames(ds: Dataset, t_ctrl: np.ndarray, q: np.ndarray | None, num_joints: int) -> np.ndarray:
    """Which joint sweeps in each frame (index, or -1 for none).

    From a tracker table's `joint` column when it names joints; else from the
    metadata's motion segments when present; otherwise from the encoder log
    (or the table's joint positions): the one joint more than `MOVING_DEG`
    from zero while every other stays within `AT_ZERO_DEG`.
    """
    if ds.samples is not None and ds.samples.has_joint:
        return ds.samples.joint.copy()
    index = {name: j for j, name in enumerate(ds.joint_names)}
    joint = np.full(len(t_ctrl), -1)
    if ds.segments:
        for name, start, end in ds.segments:
            if name is None:
                continue
            joint[(t_ctrl >= start) & (t_ctrl <= end)] = index[name]
        return joint
    if q is None:
        raise CalibrationError(
            f"{ds.root / 'metadata.json'}: cannot tell which joint moves in which frame: the metadata has "
            "no 'motion' segments and there is no encoder log"
        )
    away = np.abs(q) > MOVING_DEG * _DEG
    still = np.abs(q) < AT_ZERO_DEG * _DEG
    for j in range(num_joints):
        others = np.delete(np.arange(num_joints), j)
        joint[away[:, j] & np.all(still[:, others], axis=1)] = j
    return joint


def build_sweeps(ds: Dataset, obs: CameraObservations, targets, joint_of_row, q_at_row, num_joints):
    """Group the per-frame poses into padded per-joint sweeps; also the per-joint frame counts."""
    rows, poses, t_cam = obs.rows, obs.poses, obs.t_cam
    M = len(targets)
    found = obs.found
    per_joint = [np.flatnonzero((joint_of_row == j) & found) for j in range(num_joints)]
    F = bucket(max(len(k) for k in per_joint))  # similar captures share the compiled fits
    J = num_joints
    k = 6 if obs.has_orientation else 3
    R = np.full((J, F), -1)
    P = np.zeros((J, M, F, 3))
    O = np.broadcast_to(np.eye(3), (J, M, F, 3, 3)).copy()
    C = np.broadcast_to(np.eye(k), (J, M, F, k, k)).copy()
    mask = np.zeros((J, M, F), bool)
    T = np.zeros((J, F))
    E = None if q_at_row is None else np.zeros((J, F))
    for j, idx in enumerate(per_joint):
        R[j, : len(idx)] = rows[idx]
        T[j, : len(idx)] = t_cam[idx]
        T[j, len(idx) :] = t_cam[idx[-1]] if len(idx) else 0.0
        if E is not None:
            E[j, : len(idx)] = q_at_row[idx, j]
        for f, i in enumerate(idx):
            for m, t in enumerate(targets):
                est = poses[i].get(t.name)
                if est is None:
                    continue
                P[j, m, f] = est.T_cam_target[:3, 3]
                O[j, m, f] = est.T_cam_target[:3, :3]
                C[j, m, f] = est.cov[:k, :k]
                mask[j, m, f] = True
    counts = tuple(Named(ds.joint_names[j], int(len(idx))) for j, idx in enumerate(per_joint))
    return Sweeps(R, P, O if obs.has_orientation else None, C, mask, T, E), counts


def usable(ds: Dataset, t_ctrl: np.ndarray, log_q) -> tuple[np.ndarray, np.ndarray]:
    """`(inside, glitched)`: frames at controller times `t_ctrl` inside the
    encoder log and outside every glitch's interval, and those in a glitch."""
    glitched = ds.in_encoder_glitch(t_ctrl)
    if log_q is None:
        return ~glitched, glitched
    enc_t = log_q[0]
    return (t_ctrl >= enc_t[0]) & (t_ctrl <= enc_t[-1]) & ~glitched, glitched


class _Timeline:
    """The two-stage camera's frames placed on the controller clock at a given offset: their
    joint positions from `log_q`, which joint sweeps from `commanded` (the encoder log as
    logged; `log_q` itself when None)."""

    def __init__(self, setup: Setup, obs: CameraObservations, log_q, commanded=None):
        self.setup, self.obs, self.log_q = setup, obs, log_q
        self.commanded = log_q if commanded is None else commanded

    def at(self, offset_s: float):
        """`(t_ctrl, q, inside)` of every row at `offset_s`."""
        ds, obs = self.setup.dataset, self.obs
        t_ctrl = controller_time(obs.t_cam, offset_s, ds.clock_drift_ppm)
        if ds.samples is not None and ds.samples.q is not None:  # a tracker table with joint positions
            return t_ctrl, ds.samples.q[obs.rows], np.ones(len(t_ctrl), bool)
        if self.log_q is None:
            return t_ctrl, None, np.ones(len(t_ctrl), bool)
        enc_t, enc_q = self.log_q
        inside, _ = usable(ds, t_ctrl, self.log_q)
        if not inside.any():
            raise CalibrationError(
                f"{ds.root}: no overlap between the image timestamps of camera {obs.camera.name!r} "
                f"([{obs.t_cam.min():.3f}, {obs.t_cam.max():.3f}] s camera clock, offset {offset_s * 1e3:.1f} ms) "
                f"and the encoder log ([{enc_t[0]:.3f}, {enc_t[-1]:.3f}] s, {ds.root / 'encoders.csv'})"
            )
        return t_ctrl, interpolate(t_ctrl, enc_t, enc_q), inside

    def sweeps(self, offset_s: float):
        """`(sweeps, counts, joint, t_ctrl, q, inside)` at `offset_s` (single-joint sweeps)."""
        n = self.setup.nominal.num_joints
        t_ctrl, q, inside = self.at(offset_s)
        q_cmd = q if self.commanded is self.log_q or q is None else interpolate(t_ctrl, *self.commanded)
        joint = np.where(inside, assign_frames(self.setup.dataset, t_ctrl, q_cmd, n), -1)
        sw, counts = build_sweeps(self.setup.dataset, self.obs, self.setup.targets, joint, q, n)
        return sw, counts, joint, t_ctrl, q, inside


#: The coarse clock search's acceptance: the share of the camera's speed variance the log's
#: speeds explain at the best offset, and the share of the moving frames inside the log there.
COARSE_MIN_MATCH = 0.6
COARSE_MIN_INSIDE = 0.5


def coarse_offset(obs: CameraObservations, log_q, drift_ppm: float = 0.0) -> tuple[float, float] | None:
    """`(offset_s, match)`: the camera-minus-controller clock offset at which the speed the
    camera sees a target turn at (rad/s, between consecutive frames that show it) best matches
    the arm's joint speed in the encoder log, over every offset that leaves at least
    `COARSE_MIN_INSIDE` of those frames inside the log. `match` is the share of the camera
    speeds' variance the log's explain (1 - SSE / SST), weighted in the search by the share
    inside, since sweeps repeat one speed profile; `None` where it stays below
    `COARSE_MIN_MATCH` (too few moving frames, or positions only). A start for the
    clock fit, which converges only within a fraction of a sweep's length: a clock seconds
    off (another epoch, a camera's own time base) is found here, not there."""
    if log_q is None or not obs.has_orientation:
        return None
    enc_t, enc_q = (np.asarray(a, np.float64) for a in log_q)
    t_mid, speed = [], []
    rows = np.flatnonzero(obs.found)
    gap = 3.0 * np.median(np.diff(obs.t_cam[rows])) if len(rows) > 2 else 0.0
    for a, b in zip(rows[:-1], rows[1:]):
        dt = obs.t_cam[b] - obs.t_cam[a]
        common = [n for n in obs.poses[a] if n in obs.poses[b]]
        if not common or not 0.0 < dt <= gap:
            continue
        R = obs.poses[a][common[0]].T_cam_target[:3, :3].T @ obs.poses[b][common[0]].T_cam_target[:3, :3]
        t_mid.append(0.5 * (obs.t_cam[a] + obs.t_cam[b]))
        speed.append(np.arccos(np.clip(0.5 * (np.trace(R) - 1.0), -1.0, 1.0)) / dt)
    t_mid, speed = np.asarray(t_mid), np.asarray(speed)
    if len(t_mid) < 10 or np.ptp(speed) == 0.0:
        return None
    rate = np.linalg.norm(np.diff(enc_q, axis=0), axis=1) / np.diff(enc_t)
    t_rate = 0.5 * (enc_t[1:] + enc_t[:-1])
    step = 0.5 * float(np.median(np.diff(t_mid)))
    lo, hi = t_mid.min() - enc_t[-1], t_mid.max() - enc_t[0]
    best = None
    for offset in np.arange(lo, hi + step, step):
        t = controller_time(t_mid, offset, drift_ppm)
        inside = (t >= t_rate[0]) & (t <= t_rate[-1])
        if inside.mean() < COARSE_MIN_INSIDE:
            continue
        x, y = speed[inside], np.interp(t[inside], t_rate, rate)
        # The share of the camera's speed variance the log's speeds explain, in absolute terms
        # (both in rad/s): a correlation alone would take a sweep run at half the speed for it.
        match = 1.0 - float(np.sum((x - y) ** 2) / np.sum((x - x.mean()) ** 2))
        score = match * inside.mean()  # a sweep's speed profile repeats: the offset that explains every frame
        if best is None or score > best[2]:
            best = (float(offset), match, score)
    return best[:2] if best is not None and best[1] >= COARSE_MIN_MATCH else None


#: Below this share of the found frames inside the encoder log at the start offset, the
#: clock fit starts from `coarse_offset` instead.
COARSE_BELOW_INSIDE = 0.9
#: Above this share of the frames assigned to another sweep (or in or out of the log) at the
#: fitted offset than at the fit's start, the clock is fitted once more from the fitted offset.
REASSIGNED_REFIT = 0.1


def _share_inside(setup: Setup, obs: CameraObservations, log_q, offset_s: float) -> float:
    """The share of `obs`'s frames with a target that fall inside the encoder log at `offset_s`."""
    found = obs.found
    if log_q is None or not found.any():
        return 1.0
    t = controller_time(obs.t_cam[found], offset_s, setup.dataset.clock_drift_ppm)
    return float(usable(setup.dataset, t, log_q)[0].mean())


def _clock_failure(setup: Setup, obs: CameraObservations, log_q, offset0: float, coarse) -> str:
    """Why the clock fit failed, in the words a user can act on: how the frames and the log
    overlap, and what the motion-matching search found."""
    enc_t = log_q[0]
    t = obs.t_cam[obs.found]
    where = (
        f"the clock-offset fit did not converge: the frames with a target span [{t.min():.3f}, {t.max():.3f}] s "
        f"(camera clock) and the encoder log [{enc_t[0]:.3f}, {enc_t[-1]:.3f}] s; at the start offset "
        f"{offset0:.3f} s, {100 * _share_inside(setup, obs, log_q, offset0):.0f} % of them fall inside the log"
    )
    if coarse is None:
        found = "no offset at which the camera's view of the motion matches the log's speeds was found"
    else:
        found = f"the motion matches best at {coarse[0]:.3f} s (match {coarse[1]:.2f}), and the fit failed there too"
    return (
        f"{where}; {found}. Check that frames.csv and encoders.csv are stamped in seconds of clocks that run "
        "together (the same epoch, or a known clock.offset_s in metadata.json), and that the log is of this capture"
    )


def _clock_from_sweeps(
    sweeps: Sweeps, log_q, offset0: float, drift_ppm: float, loss: str | None, joint_types=None
):
    """All revolute joints' arc fits with one shared offset (a prismatic joint's
    sweep is no arc: it is left out)."""
    enc_t, enc_q = pad_log(*log_q, bucket(len(log_q[0])))
    data, t_cam = sweeps.arc_data(), np.asarray(sweeps.t_cam)
    if joint_types is not None and PRISMATIC in joint_types:
        rev = np.asarray([j for j, t in enumerate(joint_types) if t != PRISMATIC], dtype=int)
        if rev.size == 0:
            raise CalibrationError(
                "the clock offset is fitted on the revolute joints' arcs, and every joint is prismatic: "
                "give the offset (clock.offset_s in metadata.json)"
            )
        data = jax.tree.map(lambda x: x[rev], data)
        t_cam, enc_q = t_cam[rev], np.asarray(enc_q)[:, rev]
    return _programs.clock_fit(loss)(
        data,
        to_device(t_cam),
        to_device(enc_t),
        to_device(enc_q),
        offset0,
        drift_ppm,
    )


def _clock_from_first_link(
    setup: Setup, obs: CameraObservations, sel, log_q, offset0: float, loss: str | None
):
    """The first joint's child-link plate moves with that joint alone: its arc,
    against the encoder log, gives the offset (before anything is undone)."""
    ds = setup.dataset
    if setup.nominal.joint_types[0] == PRISMATIC:
        raise CalibrationError(
            f"{ds.root}: joint {ds.joint_names[0]!r} is prismatic: the clock offset from the first link's "
            "plate needs an arc; give the offset (clock.offset_s in metadata.json)"
        )
    try:
        P1, O1, C1, k1 = link_poses([obs.poses[i] for i in sel], setup.targets, setup.per_joint[0])
    except ValueError as e:
        raise CalibrationError(f"{ds.root}: joint {ds.joint_names[0]!r}: {e}") from None
    F, k = bucket(len(k1)), len(k1)
    pad = lambda x, fill: np.concatenate([x, np.broadcast_to(fill, (F - k,) + x.shape[1:])])  # noqa: E731
    mask = np.arange(F) < k
    d1 = make_arc_data(pad(P1, 0.0), pad(O1, np.eye(3)), None, mask, covariances=pad(C1, np.eye(6)))
    t1 = pad(obs.t_cam[sel][k1], obs.t_cam[sel][k1][-1])
    enc_t, enc_q = pad_log(log_q[0], log_q[1][:, :1], bucket(len(log_q[0])))
    return _programs.clock_fit(loss)(
        jax.tree.map(lambda x: x[None], d1),
        jnp.asarray(t1)[None],
        jnp.asarray(enc_t),
        jnp.asarray(enc_q),
        offset0,
        ds.clock_drift_ppm,
    )


#: The other joints must stand this still while one sweeps (deg).
STILL_DEG = 0.5


def sweep_homes(
    ds: Dataset, joint: np.ndarray, q: np.ndarray | None, inside: np.ndarray, exact: bool = False
) -> np.ndarray | None:
    """Per joint sweep, the configuration the other joints held: the median of
    the encoder log over the sweep's frames (a `CalibrationError` names a joint
    that moved), else the metadata's `home` of the joint's segment, else zero.
    None when every home is within `AT_ZERO_DEG` of zero (the zero configuration),
    unless `exact` (a log corrected by non-geometric terms: their sub-millidegree
    offsets are the point)."""
    n = len(ds.joint_names)
    homes = np.zeros((n, n))
    for j in range(n):
        if q is not None:
            rows = np.flatnonzero((joint == j) & inside)
            if rows.size == 0:
                continue
            others = np.delete(np.arange(n), j)
            h = np.median(q[rows], axis=0)
            spread = np.degrees(np.abs(q[np.ix_(rows, others)] - h[others]).max(axis=0))
            if spread.max() > STILL_DEG:
                k = others[int(np.argmax(spread))]
                raise CalibrationError(
                    f"{ds.root / 'encoders.csv'}: joint {ds.joint_names[k]!r} moved by {spread.max():.2f} deg while "
                    f"{ds.joint_names[j]!r} swept (at most {STILL_DEG:g} deg): the arc of a sweep needs the other "
                    "joints standing still"
                )
            homes[j] = h
        else:
            given = [
                hm for (name, _, _), hm in zip(ds.segments, ds.segment_homes) if name == ds.joint_names[j]
            ]
            if given and given[0] is not None:
                homes[j] = given[0]
        homes[j, j] = 0.0
    return None if np.degrees(np.abs(homes).max()) < AT_ZERO_DEG and not exact else homes


#: A given clock offset disagrees with the estimate beyond this many of its std (and 0.5 ms).
CLOCK_SIGMAS = 5.0


def _compare_clock(ds: Dataset, given: float, clock: Clock) -> list[str]:
    """A warning when the metadata's offset is not what the sweeps say."""
    diff = given - clock.offset_s
    if abs(diff) <= max(CLOCK_SIGMAS * clock.std_s, 0.5e-3):
        return []
    return [
        f"{ds.root / 'metadata.json'}: clock.offset_s is {1e3 * given:.3f} ms but the sweeps say "
        f"{1e3 * clock.offset_s:.3f} +- {1e3 * clock.std_s:.3f} ms ({1e3 * diff:+.3f} ms apart); "
        "using the estimate (--config clock=given uses the metadata's)"
    ]


def _compile_ahead(setup: Setup, options: Options, sweeps: Sweeps, joint, q, inside) -> None:
    """The two-stage fit's programs for these sweeps, compiled while the clock fit runs
    (`_programs.compile_two_stage_ahead`; its shapes at the start offset)."""
    try:
        home = sweep_homes(setup.dataset, joint, q, inside) is not None
    except CalibrationError:  # at the start offset: the fitted one decides
        home = False
    _programs.compile_two_stage_ahead(
        options.arc_loss,
        setup.nominal,
        sweeps.arc_data(),
        len(setup.fit_targets),
        setup.kind.axis_fit_uses_poses,
        setup.kind.fixed_frame_free,
        home,
    )


def _placed(
    setup: Setup, obs: CameraObservations, options: Options, line: "_Timeline", log_q, start: float, fit=False
):
    """`((sweeps, counts, joint, t_ctrl, q, inside), cf)`: the frames placed on the controller
    clock at offset `start`, and with `fit` the clock fit started there (`cf`, else `None`)."""
    ds = setup.dataset
    if not setup.kind.single_joint_sweeps:
        t_ctrl, q, inside = line.at(start)
        cf = None
        if fit:
            options.say(
                "estimating the camera-controller clock offset (the first joint's arc, its link's plate)"
            )
            sel = np.flatnonzero(inside & obs.found)
            with working(options.log is not None, "clock offset", say=options.say):
                cf = _clock_from_first_link(setup, obs, sel, log_q, start, options.arc_loss)
        return (None, None, np.full(len(t_ctrl), -1), t_ctrl, q, inside), cf
    sweeps, counts, joint, t_ctrl, q, inside = line.sweeps(start)
    cf = None
    if fit:
        options.say(
            "estimating the camera-controller clock offset (arc fits of all joints with a shared offset)"
        )
        _compile_ahead(setup, options, sweeps, joint, q, inside)
        with working(options.log is not None, "clock offset", say=options.say):
            cf = _clock_from_sweeps(
                sweeps, log_q, start, ds.clock_drift_ppm, options.arc_loss, setup.nominal.joint_types
            )
    return (sweeps, counts, joint, t_ctrl, q, inside), cf


def _fit_clock(
    setup: Setup, obs: CameraObservations, options: Options, line: "_Timeline", log_q, offset0, offset
):
    """`(placed, cf, note)`: the clock fit from `offset0` (the given offset `offset`, or zero),
    or from `coarse_offset` where too few frames fall inside the log there or the fit fails
    (`note` then says so), and the frames placed at the fitted offset (`_placed`). A fit that
    fails from both is a `CalibrationError` saying how the frames and the log overlap."""
    ds = setup.dataset

    def failed(cf) -> bool:
        return not result_is(cf.result) or not np.isfinite(float(cf.offset_s))

    start, coarse = offset0, None
    if _share_inside(setup, obs, log_q, offset0) < COARSE_BELOW_INSIDE:
        coarse = coarse_offset(obs, log_q, ds.clock_drift_ppm)
        start = offset0 if coarse is None else coarse[0]
    placed, cf = _placed(setup, obs, options, line, log_q, start, fit=True)
    if failed(cf) and coarse is None:
        coarse = coarse_offset(obs, log_q, ds.clock_drift_ppm)
        if coarse is not None and coarse[0] != start:
            start = coarse[0]
            placed, cf = _placed(setup, obs, options, line, log_q, start, fit=True)
    if failed(cf):
        raise CalibrationError(f"{ds.root}: {_clock_failure(setup, obs, log_q, offset0, coarse)}")
    # The fit's frames were assigned to sweeps (and to the log) at its start: where the fitted
    # offset assigns over `REASSIGNED_REFIT` of them otherwise, fit once more from there (image
    # stamps 0.3 s late sent 60 of data/ur5e_sweeps' 144 frames to other sweeps and left the
    # two-stage EE error at 2.3 mm, against 0.77 mm refitted; the 40 ms the demo's clock starts
    # off moves 6 frames, and the fit stays as it was).
    fitted, _ = _placed(setup, obs, options, line, log_q, float(cf.offset_s))
    moved = np.mean((fitted[2] != placed[2]) | (fitted[5] != placed[5]))
    if moved > REASSIGNED_REFIT:
        _, cf_2 = _placed(setup, obs, options, line, log_q, float(cf.offset_s), fit=True)
        if not failed(cf_2):
            cf = cf_2
            fitted, _ = _placed(setup, obs, options, line, log_q, float(cf.offset_s))
    note = None
    if coarse is not None and start == coarse[0]:
        note = (
            f"clock offset: from {'the given' if offset is not None else 'a zero'} offset ({offset0:.3f} s) "
            f"{100 * _share_inside(setup, obs, log_q, offset0):.0f} % of the frames fall inside the encoder log; "
            f"the clock fit started from {coarse[0]:.3f} s, where the camera's view of the motion matches the "
            f"log's (match {coarse[1]:.2f})"
        )
    return fitted, cf, note


def synchronise(setup: Setup, obs: Observations, options: Options, terms=None) -> Sync:
    """Place the frames on the controller clock (see `Sync`), estimating the
    clock offset whenever there is an encoder log (a given offset that
    disagrees is a warning; `options.clock`: `"estimate"` always, `"given"` keeps the given one).

    `terms`: non-geometric terms the refinement kept (`stages._terms.TermFit`): the
    encoder log's joint positions are then corrected by them (`TermFit.log_correction`:
    where the joints stood, not where the motors were), so that the clock fit, the arcs
    (a sweep under a changing gravity torque is then a circle at the joint's rate) and
    the sweeps' homes see the arm the terms describe; which joint sweeps when is still
    read from the log as logged."""
    t0 = time.perf_counter()
    ds, nominal = setup.dataset, setup.nominal
    commanded = log_q = commanded_positions(ds, nominal)
    if terms is not None and terms.kept and log_q is not None:
        log_q = (log_q[0], log_q[1] + terms.log_correction(nominal, *log_q))
    offset = ds.clock_offset_s
    estimate = True if options.clock == "estimate" else None
    if estimate and not setup.kind.has_arcs:
        raise CalibrationError(
            f"{ds.root}: the clock offset of a pose-based capture cannot be estimated (it comes from the arcs of "
            "moving joints); give it in metadata.json, or film the poses standing still"
        )
    if estimate is None and not setup.kind.has_arcs:
        estimate = False
    if estimate is None:
        # The estimate is cheap and accurate to microseconds: made whenever an encoder
        # log exists, and used unless the caller trusts the metadata's offset.
        estimate = log_q is not None and (offset is None or options.clock != "given")
    if estimate and log_q is None:
        raise CalibrationError(f"{ds.root}: the clock offset cannot be estimated without an encoder log")
    offset0 = 0.0 if offset is None else offset
    clock = Clock(offset_s=offset0, std_s=None, estimated=False, drift_ppm=ds.clock_drift_ppm)
    notes = list(ds.notes)
    per_sample_q = ds.samples is not None and ds.samples.q is not None  # no clock relation needed
    if offset is None and not estimate and not per_sample_q:
        notes.append(
            "clock offset unknown and not estimated: 0 assumed"
            + ("" if setup.kind.has_arcs else " (harmless when the arm stands still in every image)")
        )
    line = _Timeline(setup, obs.primary, log_q, commanded)
    if not estimate:
        (sweeps, counts, joint, t_ctrl, q, inside), _ = _placed(
            setup, obs.primary, options, line, log_q, offset0
        )
    else:
        (sweeps, counts, joint, t_ctrl, q, inside), cf, note = _fit_clock(
            setup, obs.primary, options, line, log_q, offset0, offset
        )
        notes += [note] if note else []
        clock = dataclasses.replace(
            clock, offset_s=float(cf.offset_s), std_s=float(cf.std_s), estimated=True, given_s=offset
        )
        if offset is not None:
            notes += _compare_clock(ds, offset, clock)
    corrected = log_q is not commanded
    homes = sweep_homes(ds, joint, q, inside, corrected) if setup.kind.single_joint_sweeps else None
    # A home off zero as the encoders logged it: not the terms' sag and lost motion (`corrected`).
    moved = 0.0 if not corrected else float(np.abs(log_q[1] - commanded[1]).max())
    if homes is not None and np.degrees(np.abs(homes).max() - moved) >= AT_ZERO_DEG:
        notes.append(
            "sweeps from a home configuration other than zero: "
            + "; ".join(
                f"{name} with the others at {np.round(np.degrees(h), 1).tolist()} deg"
                for name, h in zip(ds.joint_names, homes)
            )
        )
    return Sync(
        homes=homes,
        clock=clock,
        glitched=setup.dataset.in_encoder_glitch(t_ctrl),
        log_q=log_q,
        t_ctrl=t_ctrl,
        q=q,
        inside=inside,
        joint=joint,
        sweeps=sweeps,
        counts=counts,
        notes=tuple(notes),
        timings={"sync_s": time.perf_counter() - t0},
    )
