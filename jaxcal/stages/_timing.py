"""The capture's timing against its motion, for the verdict (`stages._verdict`): an encoder log
too slow for the sweeps' accelerations, and camera stamps that jitter. Each is an error of the
target's positions the model cannot hold, compared with the frames' own scatter (the arcs'
position RMS); `c` is the verdict's checks (`_verdict._Checks`)."""

import numpy as np

from ._setup import Setup
from ._synchronise import Sync
from ._two_stage import TwoStage
from .limits import Limits


def timing_checks(c, setup: Setup, sync: Sync, two: TwoStage, limits: Limits) -> None:
    """The encoder log's rate and the camera stamps' jitter against the sweeps (see the module)."""
    if sync.log_q is None or len(sync.log_q[0]) < 3 or two.arcs is None:
        return
    _encoder_log(c, setup, sync, two, limits)
    _stamp_jitter(c, setup, sync, two, limits)


def _radius(two: TwoStage, j: int) -> float:
    """The farthest of joint `j`'s markers from its measured axis (m)."""
    point, d = np.asarray(two.arcs.point[j]), np.asarray(two.arcs.direction[j])
    markers = np.asarray(two.arcs.T_cam_marker0[j])[..., :3, 3] - point
    return float(np.max(np.linalg.norm(markers - np.outer(markers @ d, d), axis=1)))


def interpolation_error(t: np.ndarray, q: np.ndarray, at: np.ndarray) -> np.ndarray:
    """How far linear interpolation of a log `q` (T,) sampled at `t` misses a smooth motion at the
    times `at` (the interpolated less the true): $\\ddot q\\,h^2 s(1 - s)/2$ at the fraction $s$ of
    its interval $h$, with $\\ddot q$ the mean of the log's second divided differences at the
    interval's ends (exact on a parabola)."""
    h0, h1 = np.diff(t)[:-1], np.diff(t)[1:]
    acc = 2.0 * (np.diff(q)[1:] / h1 - np.diff(q)[:-1] / h0) / (h0 + h1)
    acc = np.r_[acc[0], acc, acc[-1]]  # the log's ends: their neighbours' (the first and last intervals)
    k = np.clip(np.searchsorted(t, at) - 1, 0, t.size - 2)
    h = t[k + 1] - t[k]
    s = np.clip((at - t[k]) / h, 0.0, 1.0)
    return 0.5 * (acc[k] + acc[k + 1]) * h**2 * s * (1.0 - s) / 2.0


def _encoder_log(c, setup: Setup, sync: Sync, two: TwoStage, limits: Limits) -> None:
    """The encoder log's sampling against the sweeps' accelerations: each frame's joint angle is
    interpolated linearly between two samples, which misses where the joint speeds up or slows
    down (`interpolation_error`). What of it is affine in the angle the arc's zero and ratio
    absorb; the rest, at the target's distance from the joint's measured axis, is an error of the
    target's positions the model cannot hold, against their noise (the arc's position RMS); the
    largest ratio over the joints."""
    t, q = (np.asarray(a, np.float64) for a in sync.log_q)
    rows_of = {r.joint: r for r in two.arc_rows}
    worst = (0.0, 0.0, 0.0, "")
    for j, name in enumerate(setup.dataset.joint_names):
        rows = (np.asarray(sync.joint) == j) & np.asarray(sync.inside)
        arc = rows_of.get(name)
        if (
            rows.sum() < 3
            or not np.all(np.isfinite(two.arcs.point[j]))
            or arc is None
            or not arc.position_rms_mm > 0
        ):
            continue
        radius = _radius(two, j)
        e = interpolation_error(t, q[:, j], np.asarray(sync.t_ctrl)[rows])
        X = np.stack([np.ones(e.size), np.asarray(sync.q)[rows, j]], axis=1)
        rest = e - X @ np.linalg.lstsq(X, e, rcond=None)[0]
        mm = 1e3 * radius * float(np.sqrt(np.mean(rest**2)))
        if mm / arc.position_rms_mm > worst[0]:
            worst = (mm / arc.position_rms_mm, mm, arc.position_rms_mm, name)
    ratio, mm, noise, joint = worst
    dt = float(np.median(np.diff(t)))
    c.add(
        "encoder_interpolation",
        ratio,
        limits.encoder_interpolation,
        f"the encoder log samples every {1e3 * dt:.0f} ms ({1 / dt:.0f} Hz): between samples a joint's angle is "
        f"interpolated linearly, which misses the sweeps' accelerations by {mm:.2f} mm RMS at the target over "
        f"{joint!r}'s frames beyond what its zero and ratio absorb, {ratio:.2f} times the frames' own scatter "
        f"({noise:.2f} mm; limit {limits.encoder_interpolation:g}); log the joint states faster (100 Hz or more), or "
        "sweep with gentler accelerations",
        cause="timing",
    )


def stamp_jitter_s(t: np.ndarray) -> float:
    """The jitter (s, one standard deviation) of stamps `t` of a camera filming at a steady rate,
    from their second differences ($\\Delta^2 t$ of independent jitter $\\sigma$ has variance
    $6\\sigma^2$) between intervals within half the median interval of it (none across a dropped
    frame or a pause), robustly."""
    dt = np.diff(np.sort(np.asarray(t, np.float64)))
    if dt.size < 9:
        return 0.0
    steady = np.abs(dt / np.median(dt) - 1.0) < 0.5  # not across a dropped frame or a pause
    d2 = np.diff(dt)[steady[:-1] & steady[1:]]
    if d2.size < 8:
        return 0.0
    return float(1.4826 * np.median(np.abs(d2 - np.median(d2))) / np.sqrt(6.0))


def _stamp_jitter(c, setup: Setup, sync: Sync, two: TwoStage, limits: Limits) -> None:
    """The camera's stamps against a steady frame rate: a stamp off by its jitter puts the joint's
    angle off by the sweep's speed times it, at the target's distance from the axis an error of
    its position the model cannot hold (independent from frame to frame), against the frames' own
    scatter (the arc's position RMS, which it inflates); the largest ratio over the joints."""
    jitter = stamp_jitter_s(sync.t_ctrl[np.asarray(sync.inside)])
    if jitter <= 0.0:
        return
    rows_of = {r.joint: r for r in two.arc_rows}
    worst = (0.0, 0.0, 0.0, "")
    for j, name in enumerate(setup.dataset.joint_names):
        rows = np.flatnonzero((np.asarray(sync.joint) == j) & np.asarray(sync.inside))
        arc = rows_of.get(name)
        if (
            rows.size < 3
            or not np.all(np.isfinite(two.arcs.point[j]))
            or arc is None
            or not arc.position_rms_mm > 0
        ):
            continue
        speed = float(np.median(np.abs(np.diff(sync.q[rows, j]) / np.diff(sync.t_ctrl[rows]))))
        mm = 1e3 * _radius(two, j) * speed * jitter
        if mm / arc.position_rms_mm > worst[0]:
            worst = (mm / arc.position_rms_mm, mm, arc.position_rms_mm, name)
    ratio, mm, noise, joint = worst
    c.add(
        "stamp_jitter",
        ratio,
        limits.stamp_jitter,
        f"camera {setup.camera.name!r}'s stamps jitter by {1e3 * jitter:.1f} ms around a steady frame rate: at "
        f"{joint!r}'s sweep speed that moves the target {mm:.2f} mm, {ratio:.2f} times the frames' own scatter "
        f"({noise:.2f} mm; limit {limits.stamp_jitter:g}); stamp the frames at exposure (the camera's or driver's "
        "hardware stamps, not their arrival), or sweep slower",
        cause="timing",
    )
