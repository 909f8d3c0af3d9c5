"""The encoder log's units, plausibility and glitches (NumPy; impure edge, never jitted).

- `to_radians`: `encoders.unit` (`rad`, `deg`, `counts` with `counts_per_rev`) to radians.
- `unit_problem`: commanded joint positions (motor angle / nominal reduction
  ratio) against the URDF joint limits, or against an absurd magnitude for a
  joint without limits; says which unit the values would fit.
- `find_glitches`: isolated jumps of one joint's log, away from its local
  trend faster than the joint's speed limit and back again.
"""

import math
from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

#: The units `encoders.unit` may name.
UNITS = ("rad", "deg", "counts")
#: Speed limit (rad/s, m/s) for a joint whose URDF gives none (or 0).
DEFAULT_VELOCITY = {"revolute": 2.0 * math.pi, "continuous": 2.0 * math.pi, "prismatic": 1.0}
#: Slack beyond the URDF position limits: max(`LIMIT_MARGIN_ABS`, `LIMIT_MARGIN_REL` x range).
#: It leaves room for zero offsets and for captures about a pose outside the
#: limits (simulations), and still catches a unit mistake (a factor of 57 or more).
LIMIT_MARGIN_ABS = {"revolute": 0.5, "prismatic": 0.05}
LIMIT_MARGIN_REL = 0.25
#: Largest plausible |position| of a joint without limits: 100 turns (rad) or 100 m.
ABSURD = {"revolute": 100 * 2.0 * math.pi, "continuous": 100 * 2.0 * math.pi, "prismatic": 100.0}
#: Longest run of samples a glitch may span before it counts as a jump that stays.
GLITCH_MAX_RUN = 10
#: More glitched rows than this fraction of the log (or more than `GLITCH_MAX_COUNT`
#: glitches) means the log is unreliable, not glitchy: an error.
GLITCH_MAX_FRACTION = 0.05
GLITCH_MAX_COUNT = 100
#: A joint whose local speed (the median over 7 steps) exceeds its limit this many
#: times is logged in another unit than `encoders.unit` says (degrees read as
#: radians move 57 times too fast). Generous: `jaxcal simulate`'s shortest
#: sweeps (2 frames for 360 degrees) reach 47 times the UR5e's limit.
SPEED_FACTOR = 50.0
#: Noise floor of the glitch test (rad or m of joint motion).
NOISE_FLOOR = 1e-5


def to_radians(unit: str, counts_per_rev: int | None) -> float:
    """The factor from `unit` to radians (`counts`: $2\\pi$ / `counts_per_rev`)."""
    if unit == "rad":
        return 1.0
    if unit == "deg":
        return math.pi / 180.0
    if unit == "counts":
        return 2.0 * math.pi / counts_per_rev
    raise ValueError(f"unknown unit {unit!r}")


def _kind(joint_type: str) -> str:
    return "prismatic" if joint_type == "prismatic" else "revolute"


def margin(joint_type: str, lower: float, upper: float) -> float:
    """The slack allowed beyond the URDF limits (rad or m)."""
    return max(LIMIT_MARGIN_ABS[_kind(joint_type)], LIMIT_MARGIN_REL * (upper - lower))


#: Values beyond a joint's limits in at most this share of a column's rows (or in one row) are
#: wrong cells, named by line; more are the column's unit. A column in the wrong unit puts every
#: value far from zero out of the limits, a sweep's tenths of them or more; values near zero
#: fit in either unit, so that the other rows fitting says nothing of the unit.
FEW_CELLS = 0.02


def _outside(q: np.ndarray, limits) -> np.ndarray:
    """Per value, whether it lies beyond `limits` and their margin (or absurd without limits)."""
    if limits.lower is None or limits.upper is None:
        return np.abs(q) > ABSURD[limits.joint_type]
    m = margin(limits.joint_type, limits.lower, limits.upper)
    return (q < limits.lower - m) | (q > limits.upper + m)


def _fits(q: np.ndarray, limits) -> bool:
    return not _outside(q, limits).any()


def unit_problem(
    raw: np.ndarray, factor: float, unit: str, counts_per_rev, limits, lines=None, stated: str | None = None
) -> str | None:
    """Why the logged values of one joint do not fit its limits in `unit`, or `None` if they do.

    **Arguments:** `raw` (T,) the logged values in `unit`; `factor`: `unit` to
    radians; `counts_per_rev`: `encoders.counts_per_rev` or `None`; `limits`:
    the joint's `jaxcal.io.urdf.JointLimits`; `lines`: each value's line in its file (then a
    few values out of a column that otherwise fits are named by line, as wrong cells, not as the
    column's unit); `stated`: where the unit is stated (default `encoders.unit is 'UNIT'`).

    **Returns:** a sentence naming the range, the limits and the unit that would fit.
    """
    ratio = limits.reduction_ratio
    q = raw * factor / ratio
    if _fits(q, limits):
        return None
    stated = stated or f"encoders.unit is {unit!r}"
    lin = "m" if limits.joint_type == "prismatic" else "rad"
    if limits.lower is None or limits.upper is None:
        bound = ABSURD[limits.joint_type]
        where = f"beyond {bound:g} {lin} ({'100 turns' if lin == 'rad' else '100 m'}), absurd for any joint"
    else:
        m = margin(limits.joint_type, limits.lower, limits.upper)
        where = (
            f"outside the robot file's limits [{limits.lower:.4g}, {limits.upper:.4g}] {lin} by more than the "
            f"{m:.3g} {lin} margin"
        )
    out = np.flatnonzero(_outside(q, limits))
    # A few wrong cells, not the column's unit.
    if lines is not None and out.size <= max(1, FEW_CELLS * q.size):
        k, named = out[0], ", ".join(str(lines[i]) for i in out[:5]) + (" ..." if out.size > 5 else "")
        hint = ""
        if lin == "rad" and unit != "deg" and not _outside(np.radians(raw[k] * factor) / ratio, limits):
            hint = f"; read as degrees it lies within them: that row in degrees, the others in {unit}?"
        return (
            f"line {lines[k]}: {raw[k]:.6g} (a commanded joint position of {q[k]:.4g} {lin}) lies {where}, "
            f"where the other {q.size - out.size} of {q.size} rows fit: {out.size} row(s) (line {named}) hold a "
            f"wrong value{hint}"
        )
    span = f"[{q.min():.4g}, {q.max():.4g}] {lin}"
    what = (
        f"the commanded joint positions (logged value x {factor:.6g} / reduction ratio {ratio:g}) span {span}"
    )
    guesses = []
    for other in UNITS:
        if other == unit or (other == "counts" and not counts_per_rev):
            continue
        if _fits(raw * to_radians(other, counts_per_rev) / ratio, limits):
            guesses.append("degrees" if other == "deg" else "radians" if other == "rad" else "encoder counts")
    if guesses:
        hint = f"{stated} but the values look like {' or '.join(guesses)}"
    elif np.all(raw == np.round(raw)) and np.abs(raw).max() > 1000:
        hint = (
            f"{stated} but the values are whole numbers: encoder counts? (set unit 'counts' "
            "and counts_per_rev)"
        )
    else:
        hint = f"no unit fits; check the unit ({stated}) and the joint's reduction ratio in the robot file"
    return f"{what}, {where}; {hint}"


def _one_sided(rate: np.ndarray, k: int, half: int) -> float:
    """The trend of `rate` at step `k` from the steps within `half` of it, where the window is not
    centred on `k` (a log's first and last steps): each step's rate carried to `k` along the
    window's median pairwise slope (Theil-Sen), then their median. A plain median lags a rate
    that changes (a fast sweep's end reads as a jump); this one does not, and a glitch's one or
    two steps move neither median."""
    lo, hi = max(0, k - half), min(len(rate), k + half + 1)
    idx, r = np.arange(lo, hi), rate[lo:hi]
    if len(r) < 3:
        return float(np.median(r))
    i, j = np.triu_indices(len(r), 1)
    slope = np.median((r[j] - r[i]) / (idx[j] - idx[i]))
    return float(np.median(r + slope * (k - idx)))


def local_rate(t: np.ndarray, x: np.ndarray, half: int = 3) -> np.ndarray:
    """The local trend of `x`'s rate of change: the median of the step rates over
    `2 half + 1` steps (at the ends, where fewer lie on one side, `_one_sided`), (T - 1,)."""
    rate = np.diff(x) / np.diff(t)
    m, width = len(rate), 2 * half + 1
    if m < width:
        return np.array([_one_sided(rate, k, half) for k in range(m)])
    out = np.empty(m)
    out[half : m - half] = np.median(sliding_window_view(rate, width), axis=1)
    for k in (*range(half), *range(m - half, m)):
        out[k] = _one_sided(rate, k, half)
    return out


@dataclass(frozen=True)
class Jump:
    """A step of the log that leaves the local trend faster than the speed limit and
    is not undone within `GLITCH_MAX_RUN` samples: into sample `index`, by `size`."""

    index: int
    size: float


def find_glitches(
    t: np.ndarray,
    x: np.ndarray,
    max_speed: float,
    *,
    max_run: int = GLITCH_MAX_RUN,
    noise: float = NOISE_FLOOR,
) -> tuple[list[tuple[int, int]], list[Jump]]:
    """Isolated glitches of one joint's log: runs of samples that jump away from the
    signal's local trend faster than `max_speed` allows and come back.

    A step $k \\to k+1$ is a jump when it departs from the local trend (the
    median step rate over 7 steps, which a glitch of a few samples cannot move)
    by more than $v_{max} \\Delta t_k + $ `noise`. A jump followed, within
    `max_run` samples, by jumps that bring the cumulative departure back within
    that bound is a glitch; the samples between are glitched. A jump near the
    start (end) of the log that is not undone makes the samples before (after)
    it the glitch. Smooth motion, however fast, never jumps (a unit mistake is
    caught by `unit_problem` and the speed check instead).

    **Arguments:** `t` (T,) strictly increasing, s; `x` (T,) positions (rad or
    m); `max_speed` (rad/s or m/s); `max_run`: longest glitch, samples; `noise`:
    the floor of the jump test (rad or m).

    **Returns:** `(glitches, jumps)`: `(first, last)` sample indices (inclusive)
    of each glitch, and the `Jump`s that are not undone (a reset or a unit
    change mid-log: not an isolated glitch).
    """
    t = np.asarray(t, np.float64)
    x = np.asarray(x, np.float64)
    n = len(x)
    if n < 3:
        return [], []
    dt = np.diff(t)
    excess = np.diff(x) - local_rate(t, x) * dt
    bound = max_speed * dt + noise
    steps = np.flatnonzero(np.abs(excess) > bound)
    glitches, jumps = [], []
    i = 0
    while i < len(steps):
        k = int(steps[i])
        back = None
        for i2 in range(i + 1, len(steps)):
            k2 = int(steps[i2])
            if k2 - k > max_run:
                break
            if abs(excess[k : k2 + 1].sum()) <= bound[k2]:
                back = i2
                break
        if back is not None:
            glitches.append((k + 1, int(steps[back])))
            i = back + 1
        elif not glitches and not jumps and k + 1 <= max_run:
            glitches.append((0, k))  # the log starts with a glitch; step k is its end
            i += 1
        elif n - 1 - k <= max_run:
            glitches.append((k + 1, n - 1))  # the log ends with a glitch
            break
        else:
            jumps.append(Jump(k + 1, float(excess[k])))
            i += 1
    return glitches, jumps
