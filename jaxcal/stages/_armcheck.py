"""The verdict's check for an arm that is not rigid: the joint axes move with the gravity torques.

The camera calibration models a rigid arm whose joints stand where the
encoders say. A real one sags under gravity (each joint yields by its
compliance $c_k$ times the gravity torque $\\tau_k$ of the links it carries)
and has lost motion. Between single-joint sweeps both move the joint axes
the camera measures: during the sweep of joint $j$ the resting joint $k$
stands $10^{-3} c_k \\bar\\tau_{jk}$ off, $\\bar\\tau_{jk}$ its mean gravity torque
(N m) over that sweep's frames (`jaxcal._pointfit.gravity_torques` at the
frames' commanded positions, from the robot file's masses). The part of that
which is the same in every sweep is a zero offset; the rest makes the
sweeps' axes disagree with any rigid arm.

`gravity_score` is a score test of those compliances in the axis fit: the
whitened axis residuals $r$ at the fit, their Jacobian $J_p$ in the free
parameters and $J_c$ in the compliances (the derivative with respect to each
sweep's home configuration times $10^{-3}\\bar\\tau$); with $P$ the projection
off the span of $J_p$ and $A = P J_c$ (its directions below `1e-2` of the
largest singular value dropped, rank $m$), the compliances that best explain
the residuals are $\\hat c = -A^+ r$, and
$F = (\\|A \\hat c\\|^2 / m) / (\\|P r + A\\hat c\\|^2 / (N - p - m))$ is
F-distributed with $(m, N - p - m)$ degrees of freedom for a rigid arm, when
the residuals' noise is what the arc fits' covariances say.

It is not, unless the clock is accounted for. The arcs are fitted with the
encoder log read at the frames' times through the estimated clock offset,
and that offset's error ($\\delta t$, the clock fit's standard deviation
$\\sigma_t$, about 26 us on `data/ur5e_sweeps`' design) is shared by every
sweep and in none of the arcs' covariances: it moves the long sweeps' axes
(the shoulder's, the elbow's) by many of their own sigmas, in just the
directions a sag moves them. On analytic corners of that design (a rigid arm,
independent pixel noise; `docs/performance.md`) the uncorrected statistic had
a median of 11 (the F law's: 0.7) and exceeded the former fixed limit of 20 in
a quarter of the seeds; with the clock given exactly it follows the F law. So
the residuals $r$ are taken at the best clock offset there is, the
refinement's when it estimated one (its $\\sigma_t$ about 4 us: every corner
against one rigid model), the arcs fitted again there; and the offset's own
uncertainty enters the noise, $\\Sigma = I + \\sigma_t^2 a a^T$ with
$a = \\partial r / \\partial t$ (central differences over the arcs' own clock
sigma, two more fits of the arcs), by whitening $r$, $J_p$ and $J_c$ with
$\\Sigma^{-1/2}$. The terms at the arcs' own offset need only the two-stage fit
(`start_arm_score`); the arcs' three fits again follow the refinement
(`finish_arm_score`). The limit is
then the F law's quantile at `Limits.arm_false_alarm`, applied where $\\hat c$ at the joint
whose sag it moves the most is one of a real arm (a sag, at least
`Limits.arm_compliance_rad_per_kNm`; a rigid arm's axis misfit can correlate
with the torques too, with no sign or size of its own).

What the former statistic saw in a sagging arm was mostly the clock: a joint
yielding to a gravity torque that changes along its own sweep departs from its
encoder along the sweep, part of which the arcs' clock fit takes for a time
offset; the refinement, every corner against one model,
absorbs the sag into the geometry instead and keeps the clock. So the second
row compares the two clocks: $z = (t_{arcs} - t_{ref}) / \\sqrt{\\sigma_{arcs}^2 -
\\sigma_{ref}^2}$ (the variance of an estimate's difference from an efficient
one) is standard normal for a rigid arm, and $|z|$ beyond its quantile at
`Limits.arm_false_alarm` (two-sided) names gravity sag or backlash (lost motion
lags the motor: a delay, whichever way the joint turns).
"""

import dataclasses
import math
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass
from statistics import NormalDist

import numpy as np

from .._buckets import bucket
from .._clocksync import controller_time
from ..robots import link_inertials
from . import _programs
from ._synchronise import interpolate

#: The least clock offset step (s) of the residuals' derivative `a` (central differences over
#: the offset's own standard deviation, at least this).
CLOCK_STEP_S = 1e-6


@dataclass(frozen=True)
class ArmScore:
    """`gravity_score`'s figures (see the module docstring).

    - `F` on `(m, dof)` degrees of freedom; `c_hat`: the compliances the axes fit (rad per kN m,
      per joint); `tau`: row `j`, each joint's mean gravity torque (N m) over joint `j`'s sweep.
    - `clock`: the clock offset the arcs' residuals were taken at (`"refined"`, `"arcs"`:
      the clock fit's, `"given"`: not estimated) and `clock_std_s`, its uncertainty in the noise.
    - `clock_z`: the arcs' clock against the refinement's in sigmas of their difference,
      `clock_gap_s` and `clock_gap_std_s` (None without a refined clock).
    """

    F: float
    m: int
    dof: int
    c_hat: np.ndarray
    tau: np.ndarray
    clock: str
    clock_std_s: float
    clock_z: float | None = None
    clock_gap_s: float | None = None
    clock_gap_std_s: float | None = None


def _sweep_weights(setup, sync) -> tuple[np.ndarray, np.ndarray] | None:
    """The frames' commanded positions `q` padded to a bucket, and `weights` whose column `j`
    averages over joint `j`'s sweep (`_programs.arm_score`); None without the frames'
    positions or with a sweep that has none."""
    if sync.q is None or sync.sweeps is None:
        return None
    q, joint = np.asarray(sync.q, np.float64), np.asarray(sync.joint)
    inside = np.asarray(sync.inside, bool) & np.all(np.isfinite(q), axis=1) & (joint >= 0)
    n = setup.nominal.num_joints
    counts = np.array([np.sum(inside & (joint == j)) for j in range(n)])
    if np.any(counts == 0):
        return None
    size = bucket(int(inside.sum()))
    padded, weights = np.zeros((size, n)), np.zeros((size, n))
    padded[: inside.sum()] = q[inside]
    weights[np.arange(inside.sum()), joint[inside]] = 1.0 / counts[joint[inside]]
    return padded, weights


def arcs_at(setup, sync, two, offset_s: float):
    """The arcs of `two` fitted again with the encoder log read at the sweeps' frames through
    the clock offset `offset_s` (the same frames, poses and loss)."""
    sweeps, (enc_t, enc_q) = sync.sweeps, sync.log_q
    t = controller_time(np.asarray(sweeps.t_cam), offset_s, sync.clock.drift_ppm)
    q = np.stack([interpolate(t[j], enc_t, enc_q)[:, j] for j in range(setup.nominal.num_joints)])
    encoder = np.where(np.asarray(sweeps.rows) >= 0, q, sweeps.encoder)
    data = dataclasses.replace(sweeps, encoder=encoder).arc_data()
    return _programs.arc_fits(two.arc_loss, setup.nominal.joint_types)(data)


@dataclass(frozen=True, eq=False)
class ScoreTerms:
    """What the test needs of the two-stage fit alone (`score_terms`, run ahead of the
    refinement): the whitened axis residuals `r`, their Jacobians `J` (free parameters) and
    `Jc` (compliances) and the torques `tau`, at the arcs' own clock offset `t_arcs` (its std
    `s_arcs`; None when the offset was not estimated); `refit(t)`: the residuals at another
    offset, the arcs fitted again (`gravity_score` calls it, never beside another program:
    see `finish_arm_score`)."""

    r: np.ndarray
    J: np.ndarray
    Jc: np.ndarray
    tau: np.ndarray
    t_arcs: float | None
    s_arcs: float
    refit: Callable[[float], np.ndarray]


def _program_args(setup, sync, two) -> Callable | None:
    """`args(arcs)`: the arm score program's arguments (`_programs.arm_score`) with the arcs
    `arcs`, or None where the test does not apply (no sweeps with encoders, no masses)."""
    fit = two.fit
    sweeps = _sweep_weights(setup, sync)
    if sweeps is None or not bool(two.arcs.has_encoder):
        return None
    try:
        masses, coms = link_inertials(setup.dataset.robot_urdf)
    except (ValueError, KeyError, OSError):
        return None
    n = setup.nominal.num_joints
    home = np.zeros((n, n)) if sync.homes is None else np.asarray(sync.homes, np.float64)

    def args(arcs):
        return (
            setup.nominal,
            arcs,
            fit.T_flange_marker0,
            fit.T_cam_base0,
            home,
            fit.params,
            *sweeps,
            masses,
            coms,
        )

    return args


def score_terms(setup, sync, two) -> ScoreTerms | None:
    """The test's terms at the arcs' clock (see `ScoreTerms`), or None where it does not apply
    (no sweeps with encoders, no masses)."""
    arcs, fit = two.arcs, two.fit
    args = _program_args(setup, sync, two)
    if args is None:
        return None

    def terms(arcs):
        return [np.asarray(a) for a in _programs.arm_score(True)(*args(arcs))]

    def refit(offset_s: float) -> np.ndarray:
        return terms(arcs_at(setup, sync, two, offset_s))[0]

    r, J, Jc, tau = terms(arcs)
    t_arcs, s_arcs = (
        (float(sync.clock.offset_s), float(sync.clock.std_s)) if sync.clock.estimated else (None, 0.0)
    )
    return ScoreTerms(r, J[:, np.asarray(fit.free)], Jc, tau, t_arcs, s_arcs, refit)


def gravity_score(setup, sync, two, refined=None, terms: ScoreTerms | None = None) -> ArmScore | None:
    """The module docstring's test (`refined`: the refinement's record, whose clock the
    residuals are taken at when it estimated one; `terms`: `score_terms(setup, sync, two)`
    if it ran ahead), or None where it does not apply (no sweeps with encoders, no masses, no
    gravity torque that varies)."""
    terms = score_terms(setup, sync, two) if terms is None else terms
    if terms is None:
        return None
    r, J, Jc, t_arcs = terms.r, terms.J, terms.Jc, terms.t_arcs
    clock, sigma, z, norm = "given", 0.0, (None, None, None), 0.0
    if t_arcs is not None:
        own = getattr(refined, "clock", None)
        clock, sigma = ("refined", own.std_s) if own else ("arcs", terms.s_arcs)
        if own and own.offset_s != t_arcs:
            r = terms.refit(own.offset_s)  # the arcs at the refinement's clock
        if own and terms.s_arcs > own.std_s:
            gap_std = math.sqrt(terms.s_arcs**2 - own.std_s**2)
            z = ((t_arcs - own.offset_s) / gap_std, t_arcs - own.offset_s, gap_std)
        # The residuals' slope in the offset over the arcs' uncertainty of it (central
        # differences: their robust fits are smooth over tens of microseconds, not milliseconds).
        h = max(terms.s_arcs, CLOCK_STEP_S)
        a = (terms.refit(t_arcs + h) - terms.refit(t_arcs - h)) / (2.0 * h)
        norm = float(np.linalg.norm(a))
    if norm > 0.0 and sigma > 0.0:
        u = a / norm
        k = 1.0 - 1.0 / math.sqrt(1.0 + (sigma * norm) ** 2)  # (I + s^2 a a^T)^(-1/2) = I - k u u^T
        r, J, Jc = r - k * u * (u @ r), J - k * np.outer(u, u @ J), Jc - k * np.outer(u, u @ Jc)
    Q = np.linalg.qr(J)[0]
    A, rp = Jc - Q @ (Q.T @ Jc), r - Q @ (Q.T @ r)
    U, s, Vt = np.linalg.svd(A, full_matrices=False)
    keep = s > 1e-2 * s.max() if s.size and s.max() > 0 else np.zeros(len(s), bool)
    m, dof = int(keep.sum()), len(r) - J.shape[1] - int(keep.sum())
    if m == 0 or dof <= 0:
        return None
    proj = U[:, keep].T @ rp
    drop = float(proj @ proj)
    F = (drop / m) / max(float(rp @ rp) - drop, 1e-300) * dof
    c_hat = -(Vt[keep].T @ (proj / s[keep]))
    return ArmScore(F, m, dof, c_hat, terms.tau, clock, sigma, *z)


def start_arm_score(setup, sync, two) -> Future:
    """`score_terms(setup, sync, two)` as a `Future` to hand to `finish_arm_score`: they need
    only the two-stage fit. Their program compiles now on a background thread
    (`_programs.compile_ahead`), beside the refinement's on this one, and runs when the
    `Future` is first asked for its result, after the refinement: never beside another."""
    args = _program_args(setup, sync, two)
    if args is not None:
        _programs.compile_ahead(_programs.arm_score(True), *args(two.arcs))
    return _programs.Deferred(score_terms, setup, sync, two)


def comparable(refined):
    """`refined` when its clock is the arcs' to compare with (it ran; no rolling shutter, whose
    rows it timed and the arcs' poses could not), else None."""
    ran = refined is not None and refined.fit is not None
    return refined if ran and not refined.line_delays else None


def _score(setup, sync, two, refined, terms: ScoreTerms | None) -> ArmScore | None:
    return None if terms is None else gravity_score(setup, sync, two, comparable(refined), terms)


def finish_arm_score(setup, sync, two, refined, pending: Future | None = None) -> Future:
    """The test (`gravity_score`, the refinement's clock if comparable) on the terms
    `start_arm_score` started (`pending`; computed here without), as a done `Future` that
    `verdict(..., arm_score=...)` takes. Call it after the refinement and before anything runs
    beside the verdict: its fits of the arcs must not run beside another program. (Two XLA:CPU
    programs with batched LAPACK calls, as the arc fits' QR, can each hold one of a 2-core
    machine's two pool threads while waiting for their batch's tasks on that pool: a hang of
    `jaxcal.calibrate`, seen when the arcs were fitted again beside the validation.)"""
    done: Future = Future()
    done.set_result(
        _score(
            setup, sync, two, refined, score_terms(setup, sync, two) if pending is None else pending.result()
        )
    )
    return done


def f_quantile(alpha: float, m: int, dof: int) -> float:
    """The F law's upper `alpha` quantile on `(m, dof)` degrees of freedom (bisection on
    `f_survival`; no SciPy at calibration time)."""
    lo, hi = 0.0, 1.0
    while f_survival(hi, m, dof) > alpha:
        lo, hi = hi, 2.0 * hi
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if f_survival(mid, m, dof) > alpha else (lo, mid)
        if hi - lo <= 1e-12 * hi:
            break
    return 0.5 * (lo + hi)


def f_survival(x: float, m: int, dof: int) -> float:
    """$P(F > x)$ for $F$ on `(m, dof)` degrees of freedom: $I_{d/(d + m x)}(d/2, m/2)$."""
    if x <= 0.0:
        return 1.0
    return _beta_regularized(dof / (dof + m * x), 0.5 * dof, 0.5 * m)


def _beta_regularized(x: float, a: float, b: float) -> float:
    """The regularised incomplete beta function $I_x(a, b)$ (Lentz's continued fraction)."""
    if x <= 0.0:
        return 0.0
    if x >= 1.0:
        return 1.0
    if x > (a + 1.0) / (a + b + 2.0):
        return 1.0 - _beta_regularized(1.0 - x, b, a)
    front = (
        math.exp(math.lgamma(a + b) - math.lgamma(a) - math.lgamma(b) + a * math.log(x) + b * math.log1p(-x))
        / a
    )
    tiny = 1e-300
    c, d = 1.0, 1.0 - (a + b) * x / (a + 1.0)
    d = 1.0 / (d if abs(d) > tiny else tiny)
    f = d
    for i in range(1, 500):
        for num in (
            i * (b - i) * x / ((a + 2 * i - 1) * (a + 2 * i)),
            -(a + i) * (a + b + i) * x / ((a + 2 * i) * (a + 2 * i + 1)),
        ):
            d = 1.0 + num * d
            d = 1.0 / (d if abs(d) > tiny else tiny)
            c = 1.0 + num / c
            c = c if abs(c) > tiny else tiny
            f *= c * d
        if abs(c * d - 1.0) < 1e-15:
            break
    return front * f


#: What to change when the arm is not rigid (both rows' reasons end with it).
TO_CHANGE = (
    "The non-geometric terms the calibration kept (result.json 'terms') do not account for it. To change: "
    "calibrate with `--terms compliance,backlash` on a capture planned for them (`jaxcal plan --terms ...`: "
    "gravity torques that vary, sweeps approached from both sides), calibrate the compliance with stop-and-shoot "
    "poses (a laser tracker's point fit with `compliance` terms), sweep about a home pose where the gravity "
    "torques change less, or trust the result only near the capture's poses"
)


def arm_check(c, setup, sync, two, refined, limits, score: ArmScore | Future | None = None) -> None:
    """Add the `arm_gravity_F` and `arm_clock_z` checks to the verdict's checks `c` (see the
    module docstring); `refined`: the refinement's record, or None; `score`: the test's figures
    (`finish_arm_score`'s Future, whose None is "does not apply"), or its terms started ahead
    (`start_arm_score`), or None (computed here)."""
    if score is None:
        got = _score(setup, sync, two, refined, score_terms(setup, sync, two))
    else:
        got = score.result() if isinstance(score, Future) else score
        got = _score(setup, sync, two, refined, got) if isinstance(got, ScoreTerms) else got
    if got is None:
        return
    alpha = limits.arm_false_alarm
    span = got.tau.max(axis=0) - got.tau.min(axis=0)
    j = int(np.argmax(np.abs(got.c_hat) * span))
    joint = setup.nominal.joint_names[j]
    physical = got.c_hat[j] >= limits.arm_compliance_rad_per_kNm
    limit = f_quantile(alpha, got.m, got.dof)
    clock = {
        "refined": f"at the refinement's clock offset, its {got.clock_std_s * 1e6:.2g} us in the noise",
        "arcs": f"at the arcs' clock offset, its {got.clock_std_s * 1e6:.2g} us in the noise",
        "given": "at the given clock offset",
    }[got.clock]
    c.add(
        "arm_gravity_F",
        got.F,
        limit if physical else float("inf"),
        f"the joint axes moved between the sweeps as the gravity torques did (F = {got.F:.3g} on ({got.m}, "
        f"{got.dof}) degrees of freedom, limit {limit:.3g}, which a rigid arm exceeds with probability {alpha:g}; "
        f"the axes {clock}; axis fit residual RMS {float(two.fit.residual_rms):.3g}): the arm is not rigid. "
        f"Gravity sag moves them so: {joint}'s torque changes by {span[j]:.0f} N m between sweeps (from "
        f"{setup.dataset.robot_urdf.name}'s masses) and the axes fit an apparent compliance of {got.c_hat[j]:.3g} "
        "rad/kN m there (a UR5's shoulder: 0.031); backlash does too (a resting joint stands where its last move "
        "left it within its lost motion), and so do camera stamps that jump between sweeps (each sweep then at a "
        "clock of its own: see frames.csv where the arc fits below do not fit). " + TO_CHANGE,
        cause="arm",
    )
    if got.clock_z is None:
        return
    z_limit = NormalDist().inv_cdf(1.0 - 0.5 * alpha)
    c.add(
        "arm_clock_z",
        abs(got.clock_z),
        z_limit,
        f"the arcs put the camera clock {got.clock_gap_s * 1e6:+.3g} us from the refinement's ({got.clock_z:+.3g} "
        f"sigmas of their difference, {got.clock_gap_std_s * 1e6:.2g} us; limit {z_limit:.3g}, which a rigid arm "
        f"exceeds with probability {alpha:g}): the joints' angles along their own sweeps depart from the encoders "
        "with the sweeps' speed, as they do when a joint yields to a gravity torque that changes along its sweep "
        "(gravity sag) or lags its motor (backlash); the arcs take that for a clock offset, the refinement "
        "absorbs it into the geometry, which then holds only near the capture's poses. " + TO_CHANGE,
        cause="arm",
    )
