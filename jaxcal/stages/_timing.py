"""The capture's timing against its motion, for the verdict (`stages._verdict`): an encoder log
too slow for the sweeps' accelerations, and camera stamps that jitter. Each is an error of the
target's positions the model cannot hold, compared with the frames' own scatter about their arc
(its position RMS): where it is half of it or more, it shapes the arc. (The scatter grows with the
error, so the ratio saturates near 1: the millimetres say how large it is.) `c` is the verdict's
checks (`_verdict._Checks`)."""

import numpy as np

from ._setup import Setup
from ._synchronise import Sync
from ._two_stage import TwoStage
from .limits import Limits


def timing_checks(c, setup: Setup, sync: Sync, two: TwoStage, limits: Limits) -> None:
    """The encoder log's rate and the camera stamps' jitter against the sweeps (see the module)."""
    if sync.log_q is None or len(sync.log_q[0]) < 3 or two.arcs is None:
        return
    t, q = (np.asarray(a, np.float64) for a in sync.log_q)
    dt = float(np.median(np.diff(t)))

    def interpolation_m(j, rows):  # what of the interpolation error the zero and ratio cannot absorb
        e = interpolation_error(t, q[:, j], np.asarray(sync.t_ctrl)[rows])
        X = np.stack([np.ones(e.size), np.asarray(sync.q)[rows, j]], axis=1)
        return float(np.sqrt(np.mean((e - X @ np.linalg.lstsq(X, e, rcond=None)[0]) ** 2)))

    _check(
        c,
        setup,
        sync,
        two,
        "encoder_interpolation",
        limits.encoder_interpolation,
        interpolation_m,
        f"the encoder log samples every {1e3 * dt:.0f} ms ({1 / dt:.0f} Hz): between samples a joint's angle is "
        "interpolated linearly, which misses the sweeps' accelerations, beyond what a joint's zero and ratio "
        "absorb, by {mm}; log the joint states faster (100 Hz or more), or sweep with gentler accelerations",
    )
    jitter = stamp_jitter_s(np.asarray(sync.t_ctrl)[np.asarray(sync.inside)])
    if jitter > 0.0:

        def jitter_m(j, rows):  # the sweep's speed times the jitter
            return jitter * float(np.median(np.abs(np.diff(sync.q[rows, j]) / np.diff(sync.t_ctrl[rows]))))

        _check(
            c,
            setup,
            sync,
            two,
            "stamp_jitter",
            limits.stamp_jitter,
            jitter_m,
            f"camera {setup.camera.name!r}'s stamps jitter by {1e3 * jitter:.1f} ms around a steady frame rate, which "
            "at the sweeps' speeds moves the target by {mm}; stamp the frames at exposure (the camera's or driver's "
            "hardware stamps, not their arrival), or sweep slower",
        )


def _check(c, setup: Setup, sync: Sync, two: TwoStage, name: str, limit: float, error_rad, says: str) -> None:
    """One timing check: per swept joint, `error_rad(j, rows)` (rad, RMS over its frames `rows`) at
    the target's distance from its measured axis, against its arc's position RMS; the largest
    ratio is the check's value, and `says` (its `{mm}`: the joints' largest millimetres and that
    ratio) the reason."""
    rows_of = {r.joint: r for r in two.arc_rows}
    rows_all = np.asarray(sync.joint)
    found = []  # (ratio, mm, scatter mm, joint)
    for j, joint in enumerate(setup.dataset.joint_names):
        rows = np.flatnonzero((rows_all == j) & np.asarray(sync.inside))
        arc = rows_of.get(joint)
        if (
            rows.size < 3
            or arc is None
            or not arc.position_rms_mm > 0
            or not np.all(np.isfinite(two.arcs.point[j]))
        ):
            continue
        mm = 1e3 * _radius(two, j) * error_rad(j, rows)
        found.append((mm / arc.position_rms_mm, mm, arc.position_rms_mm, joint))
    if not found:
        return
    ratio, _, scatter, worst = max(found)
    _, mm, _, largest = max(found, key=lambda f: f[1])
    c.add(
        name,
        ratio,
        limit,
        says.format(
            mm=f"up to {mm:.2f} mm RMS ({largest!r}'s frames): on {worst!r}'s, {ratio:.2f} times the frames' scatter "
            f"about its arc ({scatter:.2f} mm; limit {limit:g})"
        ),
        cause="timing",
    )


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


def stamp_jitter_s(t: np.ndarray) -> float:
    """The jitter (s, one standard deviation) of stamps `t` of a camera filming at a steady rate,
    from their second differences ($\\Delta^2 t$ of independent jitter $\\sigma$ has variance
    $6\\sigma^2$) between intervals within 3/4 of the median interval of it (none across a dropped
    frame or a pause), robustly."""
    dt = np.diff(np.sort(np.asarray(t, np.float64)))
    if dt.size < 9:
        return 0.0
    steady = np.abs(dt / np.median(dt) - 1.0) < 0.75  # not across a dropped frame (+1) or a pause
    d2 = np.diff(dt)[steady[:-1] & steady[1:]]
    if d2.size < 8:
        return 0.0
    return float(1.4826 * np.median(np.abs(d2 - np.median(d2))) / np.sqrt(6.0))
