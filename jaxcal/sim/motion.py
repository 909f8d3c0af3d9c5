"""Joint motions, the motor encoder stream and the camera clock (NumPy, no rendering).

Time base: the robot controller's clock (the encoder timestamps) is the
reference, $t$. A camera frame taken at $t$ is stamped
$t_{cam} = \\text{offset} + (1 + \\text{drift}) t + \\text{jitter}$.

Reduction ratios follow the core's convention: the controller commands the
motor angle $m = q \\rho_{nom}$; the joint really turns to
$\\theta = m / \\rho_{true} + \\delta_{true}$; the encoder reports $m$
(quantised, noisy).
"""

import math
from dataclasses import dataclass, fields

import numpy as np


def check_finite(config, what: str) -> None:
    """Refuse (`ValueError` naming the field) a number of the dataclass `config` that is not
    finite, alone or in a tuple: a simulation checks its numbers before it writes anything."""
    for f in fields(config):
        value = getattr(config, f.name)
        values = value if isinstance(value, tuple) else (value,)
        for v in values:
            if isinstance(v, int | float) and not isinstance(v, bool) and not math.isfinite(v):
                raise ValueError(f"{what}: {f.name} must be finite, got {value!r}")


@dataclass(frozen=True)
class Segment:
    """A stretch of the motion, `start`..`end` on the controller clock (s).
    `joint` names the one joint that moves (a joint-by-joint sweep) or is `None`."""

    joint: str | None
    start: float
    end: float
    home: tuple[float, ...] | None = None


class Trajectory:
    """Commanded joint positions through waypoints, each leg a smooth step
    $q_i + (q_{i+1} - q_i)(1 - \\cos \\pi s)/2$ (zero velocity at every waypoint).

    **Arguments:** `times` (K,) increasing, s; `q` (K, joints) rad or m;
    `segments`: the stretches the camera records.
    """

    def __init__(self, times, q, segments):
        self.times = np.asarray(times, np.float64)
        self.q = np.asarray(q, np.float64)
        if self.times.ndim != 1 or self.q.shape[0] != len(self.times) or self.q.ndim != 2:
            raise ValueError(f"waypoints: times {self.times.shape} and q {self.q.shape} do not match")
        if np.any(np.diff(self.times) <= 0):
            raise ValueError("waypoint times must increase strictly")
        self.segments = tuple(segments)

    @property
    def duration(self) -> float:
        return float(self.times[-1])

    def __call__(self, t) -> np.ndarray:
        t = np.clip(np.asarray(t, np.float64), self.times[0], self.times[-1])
        i = np.clip(np.searchsorted(self.times, t, side="right") - 1, 0, len(self.times) - 2)
        s = (t - self.times[i]) / (self.times[i + 1] - self.times[i])
        w = 0.5 * (1.0 - np.cos(np.pi * s))
        return self.q[i] + (self.q[i + 1] - self.q[i]) * w[..., None]

    def velocity(self, t) -> np.ndarray:
        """The commanded velocity at `t` (rad/s or m/s; zero outside the waypoints' span)."""
        t = np.asarray(t, np.float64)
        i = np.clip(np.searchsorted(self.times, t, side="right") - 1, 0, len(self.times) - 2)
        h = self.times[i + 1] - self.times[i]
        s = (t - self.times[i]) / h
        inside = (t >= self.times[0]) & (t <= self.times[-1])
        rate = np.where(inside, 0.5 * np.pi * np.sin(np.pi * np.clip(s, 0.0, 1.0)) / h, 0.0)
        return (self.q[i + 1] - self.q[i]) * rate[..., None]


def joint_sweeps(
    joint_names,
    range_deg=40.0,
    sweep_s: float = 1.5,
    move_s: float = 0.8,
    joints=None,
    home=None,
    back_s: float | None = None,
) -> Trajectory:
    """Joint-by-joint sweeps about the zero configuration (or `home`, rad).

    Each joint in turn goes 0 -> -range/2 (`move_s`), sweeps to +range/2
    (`sweep_s`, recorded), and returns to 0 (`move_s`); the others stay at 0
    (with `home`, every position is relative to it: the arm starts and rests
    there, and each segment records it). With `back_s`, each joint also sweeps
    back to -range/2 in `back_s` (recorded too) before it returns: a second speed,
    which separates a compliant joint's lag under its inertial torques (the
    speed squared) from its reduction ratio (none).
    `range_deg`: one angle for every joint, or one per joint (e.g. a wide
    sweep of the last joint of an eye-in-hand arm, which spins the camera
    about its own axis and keeps the board in view). `joints` (indices)
    selects which joints sweep (default all).
    """
    n = len(joint_names)
    joints = range(n) if joints is None else joints
    ranges = np.broadcast_to(np.asarray(range_deg, np.float64), (n,)) if np.ndim(range_deg) == 0 else None
    if ranges is None:
        ranges = np.asarray(range_deg, np.float64)
        if ranges.shape != (n,):
            raise ValueError(f"range_deg has {ranges.size} angles for {n} joints {list(joint_names)}")
    halves = 0.5 * np.deg2rad(ranges)
    h = np.zeros(n) if home is None else np.asarray(home, np.float64)
    if h.shape != (n,):
        raise ValueError(f"home has {h.size} positions for {n} joints {list(joint_names)}")
    times, q, segments = [0.0], [h], []
    for j in joints:
        half = halves[j]
        e = np.eye(n)[j]
        t = times[-1]
        seg_home = None if home is None else tuple(float(x) for x in h * (1.0 - e))
        times += [t + move_s, t + move_s + sweep_s]
        q += [h - half * e, h + half * e]
        segments.append(Segment(joint_names[j], t + move_s, t + move_s + sweep_s, seg_home))
        if back_s:
            times.append(times[-1] + back_s)
            q.append(h - half * e)
            segments.append(Segment(joint_names[j], times[-2], times[-1], seg_home))
        times.append(times[-1] + move_s)
        q.append(h)
    return Trajectory(times, q, segments)


def random_motion(
    joint_names, seconds: float = 8.0, amplitude_deg=25.0, waypoints: int = 8, seed: int = 0
) -> Trajectory:
    """Every joint at once through random waypoints (uniform within
    +-`amplitude_deg` about zero, one value or one per joint), from and back to
    the zero configuration, recorded throughout: the arbitrary motion of the
    markers-on-every-link method."""
    n = len(joint_names)
    rng = np.random.default_rng(seed)
    amp = np.deg2rad(np.broadcast_to(np.asarray(amplitude_deg, np.float64), (n,)))
    q = np.concatenate([np.zeros((1, n)), rng.uniform(-1.0, 1.0, (waypoints, n)) * amp, np.zeros((1, n))])
    return free_motion(np.linspace(0.0, seconds, waypoints + 2), q)


def free_motion(times, q) -> Trajectory:
    """An arbitrary trajectory through waypoints, recorded from start to end."""
    times = np.asarray(times, np.float64)
    return Trajectory(times, q, [Segment(None, float(times[0]), float(times[-1]))])


@dataclass(frozen=True)
class EncoderModel:
    """Motor encoders: sampling rate (Hz), counts per motor revolution, noise (counts), and
    latency (s: each reading stamped that much after the instant it measures)."""

    rate_hz: float = 500.0
    counts_per_rev: int = 2**17
    noise_counts: float = 0.5
    latency_s: float = 0.0


@dataclass(frozen=True)
class ClockModel:
    """The camera's clock against the controller's, and its frame delivery.

    `offset_ms`: $t_{cam} - t$ at $t = 0$; `drift_ppm`: rate error;
    `jitter_ms`: standard deviation of each stamp; `fps`: frame rate;
    `drop_rate`: probability that a frame never arrives.
    """

    fps: float = 30.0
    offset_ms: float = 0.0
    drift_ppm: float = 0.0
    jitter_ms: float = 0.0
    drop_rate: float = 0.0

    def stamp(self, t, rng: np.random.Generator) -> np.ndarray:
        t = np.asarray(t, np.float64)
        jitter = self.jitter_ms * 1e-3 * rng.standard_normal(t.shape) if self.jitter_ms > 0 else 0.0
        return self.offset_ms * 1e-3 + (1.0 + 1e-6 * self.drift_ppm) * t + jitter


def encoder_stream(
    trajectory: Trajectory, nominal_ratio, encoder: EncoderModel, rng: np.random.Generator, motor_at=None
) -> tuple[np.ndarray, np.ndarray]:
    """Motor encoder log: timestamps (T,) on the controller clock and motor angles (T, joints), rad
    (the reading stamped $t$ measures the motor at $t$ - `encoder.latency_s`). `motor_at(t)`: the
    motor angles at controller times `t`, by default the command's, $q(t)\\,\\rho_{nom}$ (a motor
    that follows its command exactly)."""
    t = np.arange(0.0, trajectory.duration + 0.5 / encoder.rate_hz, 1.0 / encoder.rate_hz)
    if motor_at is None:
        motor = trajectory(t - encoder.latency_s) * np.asarray(nominal_ratio, np.float64)
    else:
        motor = np.asarray(motor_at(t - encoder.latency_s), np.float64)
    step = 2.0 * np.pi / encoder.counts_per_rev
    counts = motor / step + encoder.noise_counts * rng.standard_normal(motor.shape)
    return t, np.round(counts) * step


def true_angles(trajectory: Trajectory, t, nominal_ratio, true_ratio, true_zero_offset) -> np.ndarray:
    """Where the joints really stand at controller times `t`: $\\theta = q\\,\\rho_{nom}/\\rho_{true} + \\delta$."""
    ratio = np.asarray(nominal_ratio, np.float64) / np.asarray(true_ratio, np.float64)
    return trajectory(t) * ratio + np.asarray(true_zero_offset, np.float64)


def frame_times(trajectory: Trajectory, frames_per_segment: int | None, clock: ClockModel) -> list:
    """Controller times of the camera frames, per recorded segment.

    With `frames_per_segment`, that many frames evenly over each segment
    (the segment's own length sets the spacing, centred); otherwise one
    every `1/clock.fps` seconds.
    """
    out = []
    for seg in trajectory.segments:
        if frames_per_segment is not None:
            dt = (seg.end - seg.start) / frames_per_segment
            out.append(seg.start + dt * (np.arange(frames_per_segment) + 0.5))
        else:
            out.append(np.arange(seg.start + 0.5 / clock.fps, seg.end, 1.0 / clock.fps))
    return out
