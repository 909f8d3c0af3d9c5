"""Stage 4 for stop-and-shoot tracker data: the point fit (`jaxcal._pointfit`).

Samples where every joint stands still and a device measures a point on the
flange have no arcs: the kinematic corrections, the device frame (unless it is
the base) and the point's mount are fitted to every sample at once. Only the
directions the samples determine are freed (the identifiability search of the
kind's tolerance); the rest are held at nominal and named.

The samples are judged as poses: rows whose joint positions repeat an earlier
row's are merged into its pose (the mean of their points, weighted once) and named,
so copies neither shrink the standard deviations nor count towards the minimum,
and cross-validation folds hold whole poses; a row whose point disagrees with its
pose's others (`REPEAT_SIGMAS`) is fitted apart, for the robust fit to judge. The fit is robust (`POINT_ROBUST`):
after least squares, a sample whose deletion residual lies beyond the rejection
radius starts the arc fits' reweighted rounds (`jaxcal._pointfit.fit_points_robust`),
and the samples they reject are left out of everything after (the models with
terms, the cross-validation) and named with their distance from the calibrated
model. A parameter the data cannot see (alone it would be known no better than a
third of its plausible correction, `Limits`) is held and named, not freed.

Non-geometric terms (`Options.terms`: joint compliance under gravity,
transmission harmonics) are tried one after another and each is kept only
when K-fold cross-validation on the samples improves, by `jaxcal._selection`'s
rule (the one the hand-eye robot-noise model is chosen by): the fit reports the
geometric model's cross-validation beside every model tried.

The record is the two-stage one (`TwoStage`, with `points`): its axis-fit
result holds the point fit's geometric part, so the verdict, the tables and
the outputs are those of every other kind.
"""

import dataclasses
import time
from dataclasses import dataclass, field
from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._axisfit import AxisFitResult
from .._correction import ParameterLayout, apply_correction, physical_parameters
from .._device import result_is, to_device
from .._exported import stored_jit
from .._geometry import se3_exp
from .._kinematics import PRISMATIC, KinematicModel, forward_kinematics
from .._npgeom import fit_sandwich, kabsch, nearest_rotation
from .._options import RobustOptions
from .._pointfit import (
    TERMS,
    PointData,
    PointFitResult,
    PointLayout,
    PointPrior,
    PointProblem,
    cross_validate,
    fit_points,
    fit_points_robust,
    fold_masks,
    predict,
    rotation_errors,
    sample_radii,
    term_basis,
)
from .._rowshift import describe, misread_points, shifted_points
from .._selection import improves_on_samples, paired_z
from .._terms import approach, signs
from ..errors import CalibrationError, DatasetError
from ..records import ModelRow, PointOutlier, PriorUse, RepeatedPose, ResidualStats, TermRow
from ._observe import Observations
from ._prior import prior_rows_of, prior_use
from ._programs import compile_ahead
from ._setup import Options, Setup
from ._synchronise import Sync
from ._terms import TERM_FLOOR as TERM_FLOOR
from ._terms import TERM_STD_RAD as TERM_STD_RAD
from ._terms import inertials, resolve
from .limits import Limits

#: The robust point fit (`jaxcal._pointfit.fit_points_robust`): Cauchy rounds, then the inliers
#: within 6 robust sigmas (as a 2-D radius), the arc fits' threshold (`_programs.ARC_REJECT`).
#: A tracker's residuals are the arm's unmodelled errors more than the instrument's noise, with
#: heavier tails than a normal law's: on the real UR5's 1000 grid poses (`data/ur5_tracker`) the
#: largest clean sample lies at 4.0 robust sigmas, so 3.7 would reject four real poses, while a
#: joint cell off by 2 degrees moves the point by millimetres, hundreds of sigmas.
POINT_ROBUST = RobustOptions("cauchy", reject=6.0)
#: Joint positions within this of another row's in every joint (rad, or m) are that pose repeated
#: (a controller logging one stop twice, a table holding a row twice): far under any pose
#: difference a capture plans, far over a text file's rounding.
SAME_POSE = 1e-6
#: Rows of one pose whose points lie farther than this many of their stated 3-D noise from the pose's
#: median point are not merged: each is fitted alone, so the robust fit rejects the wrong one and keeps
#: the others (a mean would carry the error into the good measurement, and both would be lost).
REPEAT_SIGMAS = 10.0
#: A term's gain in standard errors (`ModelRow.cv_gain_z`) is recorded up to this (a gain without
#: spread is infinitely many).
Z_SHOWN = 1e3


@dataclass(frozen=True, eq=False)
class PointFit:
    """The point fit of a stop-and-shoot capture.

    - `problem`, `fit`: the `PointProblem` solved (all samples used) and its
      `PointFitResult`; `layout`: its `PointLayout` (the terms kept).
    - `candidates`: the parameters the search could free.
    - `held`: names of the parameters held at nominal (the data do not see them).
    - `models`: per model tried, `{"terms", "free", "cv_mean_mm", "cv_rms_mm", "kept"}`,
      the geometric one first.
    - `folds`: the number of cross-validation folds (0: not run).
    - `residual_mm`: mean, RMS and max distance of the fitted samples (mm);
      `residual_deg`: with orientations, their angles from the fitted ones (deg).
    - `used`: the samples in the fit (mask over the table's rows): one per distinct
      pose, the robust fit's inliers.
    - `mount_given`: the metadata gives the point's nominal mount (else the fit measures it).
    - `poses`: the distinct poses (used and rejected).
    - `repeats`: the samples merged into an earlier sample's pose (`RepeatedPose`).
    - `outliers`: the samples the robust fit rejected (`PointOutlier`), farthest first.
    - `robust_scale`: the residuals' robust scale over the noise model's (the
      deletion residuals' median over its value for clean samples of that noise).
    - `unseen`: parameters held because the data cannot see them (alone, a third of
      their plausible correction or more: `PointFitResult.std_alone`).
    """

    problem: PointProblem
    fit: PointFitResult
    layout: PointLayout
    candidates: np.ndarray
    held: tuple[str, ...]
    models: tuple[ModelRow, ...]
    folds: int
    residual_mm: ResidualStats
    used: np.ndarray
    poses: int
    repeats: tuple[RepeatedPose, ...]
    outliers: tuple[PointOutlier, ...]
    robust_scale: float
    unseen: tuple[str, ...]
    residual_deg: ResidualStats | None = None
    mount_given: bool = True
    #: With a fleet's prior, how much of each parameter it gave.
    prior: PriorUse | None = None
    #: Seconds per step (`point_fit_s`): free-form.
    timings: dict[str, float] = field(default_factory=dict)

    @property
    def term_rows(self) -> tuple[TermRow, ...]:
        """The non-geometric coefficients: `name`, `estimate`, `std`, `free`."""
        k = self.layout.base.axis_size
        x, std, free = (np.asarray(a) for a in (self.fit.x, self.fit.std, self.fit.free))
        return tuple(
            TermRow(name=n, estimate=float(x[i]), std=float(std[i]), free=bool(free[i]))
            for i, n in enumerate(self.layout.term_names(), start=k)
        )


def point_problem(
    nominal: KinematicModel,
    layout: PointLayout,
    q: np.ndarray,
    y: np.ndarray,
    sigma: np.ndarray,
    used: np.ndarray,
    T_dev_base0: np.ndarray,
    T_flange_point0: np.ndarray,
    inertials: tuple[np.ndarray, np.ndarray] | None = None,
    R: np.ndarray | None = None,
    sigma_rad: np.ndarray | None = None,
    prior: tuple[np.ndarray, np.ndarray] | None = None,
) -> PointProblem:
    """A `PointProblem` from NumPy arrays (`inertials`: masses and centres of mass, for
    compliance and backlash's preload, the payload lumped in; `R`, `sigma_rad`: measured
    orientations, when `layout.orientation`; `prior`: a `PointPrior`'s root and mean). With a
    `backlash` term every joint's approach flank follows the samples' order
    (`jaxcal._terms.approach`)."""
    n = nominal.num_joints
    S = len(q)
    masses, coms = (np.zeros(n), np.zeros((n, 3))) if inertials is None else inertials
    if layout.orientation and (R is None or sigma_rad is None):
        raise ValueError("a layout with orientations needs R and sigma_rad")
    f64 = lambda a: to_device(a, np.float64)  # noqa: E731 - moved, not a program per array
    data = PointData(
        q=f64(q),
        y=f64(y),
        sigma=f64(sigma),
        mask=to_device(used, bool),
        weight=f64(np.ones(S)),
        masses=f64(masses),
        coms=f64(coms),
        R=f64(np.broadcast_to(np.eye(3), (S, 3, 3)) if R is None else R),
        sigma_rad=f64(np.ones(S) if sigma_rad is None else sigma_rad),
        approach=f64(approach(q)) if "backlash" in layout.terms else None,
    )
    gauss = None if prior is None else PointPrior(*(f64(a) for a in prior))
    return PointProblem(nominal, f64(T_dev_base0), f64(T_flange_point0), data, layout, gauss)


def candidates(layout: PointLayout, *, fixed_frame_free: bool, orientation: bool = False) -> np.ndarray:
    """What the search may free: all but the fixed frame when it is the base, and
    the mount's rotation, which a measured point never shows."""
    cand = np.ones(layout.size, bool)
    base = layout.base
    if not fixed_frame_free:
        cand[base.index("cam")] = False
    if not orientation:
        cand[base.index("tool")[3:6]] = False
    return cand


# The stage's programs are stored (`jaxcal._exported`): a second process neither traces nor
# compiles them. The fit (what `benchmarks/real_tracker.py` times against SciPy) and the
# cross-validation run several times per calibration and keep XLA's optimisations
# (`compiler_options=None`); the others run once or twice and compile quickly.
def _fit_program(problem: PointProblem, cand, tol, scale=None):
    return fit_points(problem, cand, tol=tol, scale=scale)


def _radii_program(problem: PointProblem, fit: PointFitResult):
    return sample_radii(fit.x, fit.free, problem)


def _robust_program(problem: PointProblem, fit: PointFitResult):
    return fit_points_robust(problem, fit, POINT_ROBUST)


def _refit_program(problem: PointProblem, cand, free):
    return fit_points(problem, cand, tol=0.0, free=free)


def _cv_program(problem: PointProblem, cand, free, train):
    return cross_validate(problem, cand, free, train)


def _basis_rms_program(problem: PointProblem):
    """The RMS of the term basis over the used samples, `(joints, k)`."""
    d = problem.data
    b = term_basis(problem.layout.terms, problem.nominal, d.q, d.masses, d.coms, d.approach)
    w = d.mask.astype(b.dtype)[:, None, None]
    return jnp.sqrt(jnp.sum(w * b**2, axis=0) / jnp.sum(w))


def _residuals_program(problem: PointProblem, x):
    """The fitted points' distances from the measured ones (m) and, with orientations, their
    angles (rad; zeros without)."""
    dist = jnp.linalg.norm(predict(x, problem) - problem.data.y, axis=1)
    angle = rotation_errors(x, problem) if problem.layout.orientation else jnp.zeros_like(dist)
    return dist, angle


_fit = stored_jit(_fit_program, "point_fit", compiler_options=None)
_radii = stored_jit(_radii_program, "point_radii")
_robust = stored_jit(_robust_program, "point_robust", (POINT_ROBUST,))
_refit = stored_jit(_refit_program, "point_refit")
_cv = stored_jit(_cv_program, "point_cv", compiler_options=None)
_residuals = stored_jit(_residuals_program, "point_residuals")
_basis_rms = stored_jit(_basis_rms_program, "point_basis_rms")


def _compile_ahead(problem: PointProblem, cand, tol, scale, folds: int) -> None:
    """Compile, on background threads while the model's fit compiles and runs, the programs the
    stage calls after it on the same samples (`_programs.compile_ahead`): on a first run their
    compiles share the cores instead of following one another. The geometric model's are its
    screening, cross-validation, residuals and record; a model with terms', its cross-validation
    and the refit that holds the coefficients the data do not pin."""
    fit = _fit.out_info(problem, cand, tol, scale)
    if folds:
        train = jax.ShapeDtypeStruct((folds, problem.data.q.shape[0]), jnp.bool_)
        compile_ahead(_cv, problem, cand, fit.free, train)
    if problem.layout.terms:
        compile_ahead(_refit, problem, cand, fit.free)
        return
    compile_ahead(_radii, problem, fit)
    compile_ahead(_residuals, problem, fit.x)
    compile_ahead(_axis_result, problem, fit, problem.nominal)


def term_scale(problem: PointProblem) -> np.ndarray:
    """Per non-geometric coefficient (`PointLayout` order), the RMS of its basis over the fitted samples."""
    layout = problem.layout
    if not layout.terms:
        return np.zeros(0)
    rms = np.asarray(_basis_rms(problem))  # (joints, k): family-major below
    cols, start = [], 0
    for t in layout.terms:
        m = TERMS[t]
        cols.append(rms[:, start : start + m].reshape(-1))
        start += m
    return np.concatenate(cols) if cols else np.zeros(0)


def term_effect_std(problem: PointProblem, fit: PointFitResult) -> np.ndarray:
    """Per non-geometric coefficient, its std times the RMS of its basis over the
    fitted samples: how well the data pin its effect on the joint angle (rad)."""
    return np.asarray(fit.std)[problem.layout.base.axis_size :] * term_scale(problem)


def _hold_implausible_terms(problem: PointProblem, cand, fit: PointFitResult) -> PointFitResult:
    """Hold at zero, and refit without, the non-geometric coefficients the data do not
    pin (`TERM_STD_RAD`) and those whose sign no real arm has (`jaxcal._terms.SIGNS`: a
    joint does not yield against gravity, nor its link lead its motor; such a term is
    absorbing something else), one round at a time."""
    layout = problem.layout
    k = layout.base.axis_size
    sign = signs(layout.terms, len(layout.base.joints))
    for _ in range(len(layout.term_names())):
        free = np.asarray(fit.free).copy()
        terms_free = free[k:]
        loose = terms_free & (term_effect_std(problem, fit) > TERM_STD_RAD)
        negative = terms_free & (sign * np.asarray(fit.x)[k:] < 0)
        if not (loose | negative).any():
            break
        free[k:] &= ~(loose | negative)
        fit = jax.device_get(_refit(problem, jnp.asarray(cand), jnp.asarray(free)))
    return fit


def fold_train(used: np.ndarray, folds: int) -> np.ndarray:
    """The training masks `(folds, samples)` of the point fit's K-fold cross-validation over the
    samples `used`: `jaxcal verify --cv` forms the same."""
    used = np.asarray(used, bool)
    train = np.zeros((folds, len(used)), bool)
    train[:, np.flatnonzero(used)] = fold_masks(int(used.sum()), folds)
    return train


def _stats(d: np.ndarray) -> ResidualStats:
    return ResidualStats(mean=float(d.mean()), rms=float(np.sqrt(np.mean(d**2))), max=float(d.max()))


def _held_out(problem, cand, free, train) -> tuple[ResidualStats, ResidualStats | None, np.ndarray]:
    """The held-out distances (mm) and, with orientations, angles (deg) of K-fold
    cross-validation with the free parameters `free` over the training masks `train`, and each
    held-out sample's distance (mm) in sample order."""
    dist, test, angle = (np.asarray(a) for a in _cv(problem, cand, free, to_device(train)))
    deg = _stats(np.degrees(angle[test])) if problem.layout.orientation else None
    per_sample = 1e3 * np.sum(np.where(test, dist, 0.0), axis=0)[test.any(0)]
    return _stats(1e3 * dist[test]), deg, per_sample


def cross_validation(problem, cand, free, train) -> tuple[ResidualStats, ResidualStats | None]:
    """`_held_out`'s summaries: what `jaxcal verify --cv` reports."""
    return _held_out(problem, cand, free, train)[:2]


def _cv_row(problem, cand, fit, train) -> tuple[dict, np.ndarray]:
    """The cross-validated summary of a model's row and each held-out sample's distance (mm)."""
    mm, deg, per_sample = _held_out(problem, cand, fit.free, train)
    row = {"cv_mean_mm": mm.mean, "cv_rms_mm": mm.rms, "cv_max_mm": mm.max}
    if deg is not None:
        row |= {"cv_mean_deg": deg.mean, "cv_rms_deg": deg.rms, "cv_max_deg": deg.max}
    return row, per_sample


def flange_frames(nominal: KinematicModel, q: np.ndarray) -> np.ndarray:
    """The nominal robot's flange frames `(samples, 4, 4)` at the joint positions `q` (NumPy)."""
    return np.asarray(jax.vmap(lambda qq: forward_kinematics(nominal, qq)[-1])(jnp.asarray(q)))


def start_frame(F: np.ndarray, y: np.ndarray, T_flange_point0: np.ndarray) -> np.ndarray:
    """A start for $T_{dev,base}$: the rigid registration of the nominal model's points (on its
    flange frames `F`) onto the measured ones (Kabsch)."""
    p = np.einsum("nab,b->na", F, np.asarray(T_flange_point0)[:, 3])[:, :3]
    return kabsch(p, y)


def _orient_start(F, y, R, T0, Tp0, *, frame_free: bool, mount_known: bool):
    """With measured orientations $R_i \\approx R_{db} F_i R_{mount}$ (`F`: the nominal flange's), the
    starts of the device frame's rotation (when free) and of the mount's (when the metadata gives
    none) fitted to them (`fit_sandwich`), the device frame's translation then re-fitted to the
    points `y`. **Returns:** `(T0, Tp0)`."""
    A, B = T0[:3, :3], Tp0[:3, :3]
    if frame_free:
        A, B, _ = fit_sandwich(R, F[:, :3, :3], A, B if mount_known else None)
    elif not mount_known:
        B = nearest_rotation(np.einsum("nba,nbc->ac", A @ F[:, :3, :3], R))
    T, Tp = T0.copy(), Tp0.copy()
    T[:3, :3], Tp[:3, :3] = A, B
    if frame_free:
        p = np.einsum("nab,b->na", F, Tp[:, 3])[:, :3]
        T[:3, 3] = np.mean(y - p @ A.T, axis=0)
    return T, Tp


def plausible_scale(layout: PointLayout, nominal: KinematicModel, limits: Limits) -> np.ndarray:
    """Per parameter (`PointLayout` order) a third of its plausible correction (m, rad), the
    verdict's measure of a parameter barely determined (`Limits`): a joint origin's, a zero
    offset's, the point mount's; `inf` for the device frame and the terms (any value)."""
    base = layout.base
    scale = np.full(layout.size, np.inf)
    mm, deg = 1e-3 * limits.origin_mm / 3, np.radians(limits.origin_deg / 3)
    scale[base.index("origin")] = np.tile([mm] * 3 + [deg] * 3, len(base.joints))
    scale[base.index("zero")] = [
        mm if t == PRISMATIC else np.radians(limits.zero_offset_deg / 3) for t in nominal.joint_types
    ]
    scale[base.index("tool")] = [1e-3 * limits.mount_mm / 3] * 3 + [np.radians(limits.mount_deg / 3)] * 3
    return scale


def repeated_poses(q: np.ndarray, used: np.ndarray) -> np.ndarray:
    """Per row of `q` `(samples, joints)` the first used row with the same joint positions
    (within `SAME_POSE` in every joint; itself for the first), -1 where not `used`."""
    idx = np.flatnonzero(used)
    key = np.round(q[idx] / SAME_POSE).astype(np.int64)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    rep = np.full(len(q), -1)
    rep[idx] = idx[first[inverse.reshape(-1)]]
    return rep


def _merged(rep: np.ndarray, y: np.ndarray, R: np.ndarray | None):
    """Each pose's measurement: the mean point of its samples (and the rotation nearest their
    mean), at the first sample's row."""
    y = y.copy()
    R = None if R is None else R.copy()
    for first in np.unique(rep[rep >= 0]):
        rows = np.flatnonzero(rep == first)
        if len(rows) > 1:
            y[first] = y[rows].mean(axis=0)
            if R is not None:
                U, _, Vt = np.linalg.svd(R[rows].sum(axis=0))
                R[first] = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    return y, R


def _check_pairing(ds, nominal, q, F: np.ndarray, y: np.ndarray, valid: np.ndarray) -> None:
    """Refuse (`DatasetError`) points `y` that fit the nominal robot (its flange frames `F` at `q`)
    only with the rows shifted against the joint positions (`jaxcal._rowshift.shifted_points`),
    naming the shift and where it starts, or only read otherwise (`misread_points`: a joint's sign,
    two joints' columns, mirrored coordinates)."""
    rows = np.flatnonzero(valid)
    found = shifted_points(F[rows], np.asarray(y, np.float64)[rows])
    if found is None:
        at = (q[rows], np.asarray(y)[rows], nominal.joint_names, F[rows])
        read = misread_points(lambda qq: flange_frames(nominal, qq), *at)
        if read is not None:
            raise DatasetError(
                f"{ds.device.file}: the measured points fit no pose of the nominal robot as read; {read}"
            )
    if found is not None:
        s = ds.samples
        name = lambda k: f"{int(s.sample[rows[k]])} (line {int(s.lines[rows[k]])})"  # noqa: E731
        raise DatasetError(
            f"{ds.device.file}: measured points fit no pose of the nominal robot at their row's joint "
            f"positions, but they do with the rows shifted: {describe(found, name, 'sample', 'robot pose')}. "
            "Pair each point with the joint positions the robot held when it was measured"
        )


def _row_name(ds, i: int) -> tuple[int, str]:
    """A sample's index (the table's `sample` column) and its line in the samples file."""
    s = ds.samples
    return int(s.sample[i]), f"{ds.device.file} line {int(s.lines[i])}"


def _outliers(ds, dist: np.ndarray, radius: np.ndarray, rejected: np.ndarray) -> tuple[PointOutlier, ...]:
    """The `rejected` samples (mask) named, with their distance from the calibrated model (mm,
    `dist`) and their robust radius, farthest first."""
    rows = (
        PointOutlier(*_row_name(ds, i), distance_mm=float(dist[i]), radius=float(radius[i]))
        for i in np.flatnonzero(rejected)
    )
    return tuple(sorted(rows, key=lambda o: -o.distance_mm))


def _inliers(problem: PointProblem, fit: PointFitResult) -> tuple[np.ndarray, np.ndarray, float]:
    """The samples the fit keeps: all, when no deletion residual of the least-squares `fit`
    lies beyond `POINT_ROBUST.reject`; else the robust fit's inliers. Returns them (mask over
    the rows), every sample's radius in robust sigmas (that fit's) and the scale."""
    mask = np.asarray(problem.data.mask)
    z, scale = jax.device_get(_radii(problem, fit))
    if np.all(z <= POINT_ROBUST.reject):
        return mask, np.asarray(z), float(scale)
    robust = jax.device_get(_robust(problem, fit))
    return mask & (np.asarray(robust.weights) > 0), np.asarray(robust.radius), float(robust.robust_scale)


def fit_point_samples(setup: Setup, obs: Observations, sync: Sync, options: Options) -> PointFit:
    """The point fit of a stop-and-shoot capture (see the module docstring)."""
    t0 = time.perf_counter()
    ds, nominal, kind = setup.dataset, setup.nominal, setup.kind
    s = ds.samples
    n = nominal.num_joints
    q, y = np.asarray(sync.q, np.float64), np.asarray(s.position, np.float64)
    valid = np.asarray(sync.inside, bool) & np.all(np.isfinite(q), axis=1)
    rep, first, n_poses, copies = _distinct_poses(ds, q, valid, n, y, options.say)
    y, orient = _merged(rep, y, s.orientation)
    repeats = tuple(
        RepeatedPose(*_row_name(ds, i), of_sample=_row_name(ds, rep[i])[0])
        for i in np.flatnonzero(valid & ~first)
    )
    point = setup.targets[0]
    Tp0 = np.eye(4) if point.T_link_target is None else np.asarray(point.T_link_target, np.float64)
    F = flange_frames(nominal, q) if kind.fixed_frame_free or orient is not None else None
    if kind.fixed_frame_free:
        _check_pairing(ds, nominal, q, F, s.position, valid)
    T0 = np.eye(4) if not kind.fixed_frame_free else start_frame(F[first], y[first], Tp0)
    if orient is not None:
        T0, Tp0 = _orient_start(
            F[first],
            y[first],
            orient[first],
            T0,
            Tp0,
            frame_free=kind.fixed_frame_free,
            mount_known=point.T_link_target is not None,
        )
    base = ParameterLayout.of(nominal, 1, fixed_name=kind.fixed_frame)
    terms = resolve(setup, options)
    masses = inertials(setup) if {"compliance", "backlash"} & set(terms) else None
    tol = setup.identifiability_tol
    folds = options.cv_folds
    orientation = orient is not None

    def fitted(terms, used):
        layout = PointLayout(base, terms, orientation)
        prior = prior_rows_of(options, layout, nominal, kind.fixed_frame_free)
        problem = point_problem(
            nominal, layout, q, y, s.sigma_m, used, T0, Tp0, masses, orient, s.sigma_rad, prior
        )
        cand = candidates(layout, fixed_frame_free=kind.fixed_frame_free, orientation=orientation)
        cand[base.axis_size :] &= term_scale(problem) >= TERM_FLOOR
        scale = plausible_scale(layout, nominal, options.limits)
        cand_d, scale_d = to_device(cand), to_device(scale, np.float64)  # moved, not compiled
        _compile_ahead(problem, cand_d, tol, scale_d, folds)
        fit = jax.device_get(_fit(problem, cand_d, tol, scale_d))
        return layout, problem, cand, np.asarray(scale, np.float64), fit

    options.say(
        f"point fit: {n_poses} stop-and-shoot poses"
        + (f" ({copies} repeated samples merged)" if copies else "")
        + ", forward kinematics of every sample"
    )
    geometric = fitted((), first)
    used, radius, robust_scale = _inliers(geometric[1], geometric[4])
    if not np.array_equal(used, first):
        options.say(f"point fit: {n_poses - int(used.sum())} samples rejected; fitted again without them")
        geometric = fitted((), used)
    train = fold_train(used, folds) if folds else None

    def attempt(terms):
        layout, problem, cand, scale, fit = geometric if not terms else fitted(terms, used)
        # The search's: the refits below take its mask of free parameters as given.
        unseen = tuple(nm for nm, c, a, sc in zip(layout.names(), cand, fit.std_alone, scale) if c and a > sc)
        fit = _hold_implausible_terms(problem, cand, fit)
        row, held = ModelRow(terms=tuple(terms), free=int(np.sum(fit.free))), None
        if train is not None:
            summary, held = _cv_row(problem, cand, fit, train)
            row = dataclasses.replace(row, **summary)
        return layout, problem, cand, unseen, fit, row, held

    best = attempt(())
    models, kept = [best[5]], 0
    for term in terms:
        if train is None:
            raise CalibrationError(
                "non-geometric terms are kept only when cross-validation improves: cv_folds >= 2"
            )
        options.say(f"point fit: trying {term} (kept only if {folds}-fold cross-validation improves)")
        trial = attempt((*best[0].terms, term))
        z = min(paired_z(best[6], trial[6]), Z_SHOWN)
        trial = (*trial[:5], dataclasses.replace(trial[5], cv_gain_z=z), trial[6])
        models.append(trial[5])
        # `jaxcal._selection`'s rule: a gain over CV_GAIN, by two standard errors of the paired distances.
        if improves_on_samples(best[6], trial[6], best[5].cv_mean_mm, trial[5].cv_mean_mm):
            best, kept = trial, len(models) - 1
    layout, problem, cand, unseen, fit, *_ = best
    if not result_is(fit.result):
        options.say("point fit: the solver did not converge")
    dist, angle = (np.asarray(a) for a in _residuals(problem, fit.x))
    dist, angle = 1e3 * dist, np.degrees(angle)[used] if orientation else None
    names = layout.names()
    free = np.asarray(fit.free)
    held = tuple(nm for nm, f, c in zip(names, free, cand) if not f and c)
    return PointFit(
        problem=problem,
        fit=fit,
        layout=layout,
        candidates=cand,
        held=held,
        models=tuple(dataclasses.replace(m, kept=k == kept) for k, m in enumerate(models)),
        folds=folds,
        residual_mm=_stats(dist[used]),
        used=used,
        residual_deg=None if angle is None else _stats(angle),
        mount_given=point.T_link_target is not None,
        poses=n_poses,
        repeats=repeats,
        outliers=_outliers(ds, dist, radius, first & ~used),
        robust_scale=robust_scale,
        unseen=unseen,
        prior=prior_use(
            options, problem, fit, names, partial(_data_alone, problem, cand, tol, layout, options)
        ),
        timings={"point_fit_s": time.perf_counter() - t0},
    )


def _data_alone(
    problem: PointProblem, cand, tol: float, layout: PointLayout, options: Options
) -> PointFitResult:
    """`problem`'s fit without its prior: the same candidates, identifiability search and samples."""
    scale = plausible_scale(layout, problem.nominal, options.limits)
    return _fit(dataclasses.replace(problem, prior=None), to_device(cand), tol, to_device(scale, np.float64))


def _apart(ds, rep: np.ndarray, y: np.ndarray, say) -> np.ndarray:
    """`rep` with every row of a repeated pose whose point lies over `REPEAT_SIGMAS` of its noise
    from the pose's median point made a pose of its own (named through `say`)."""
    rep, sigma = rep.copy(), np.sqrt(3.0) * np.asarray(ds.samples.sigma_m, np.float64)
    for head in np.unique(rep[rep >= 0]):
        rows = np.flatnonzero(rep == head)
        if len(rows) < 2:
            continue
        d = np.linalg.norm(y[rows] - np.median(y[rows], axis=0), axis=1)
        far = rows[d > REPEAT_SIGMAS * sigma[rows]]
        if len(far):
            rep[far] = far
            lines = ", ".join(_row_name(ds, i)[1] for i in rows)
            spread = np.max(np.linalg.norm(y[rows, None] - y[None, rows], axis=-1))
            say(
                f"point fit: {lines} repeat one pose but their points differ by up to {1e3 * spread:.3g} mm; "
                "fitted apart, not averaged (the robust fit judges each)"
            )
    return rep


def _distinct_poses(
    ds, q: np.ndarray, valid: np.ndarray, n: int, y: np.ndarray, say
) -> tuple[np.ndarray, np.ndarray, int, int]:
    """Per sample the first sample of its pose (`repeated_poses`; rows that disagree with their
    pose's point apart, `_apart`), the mask of those firsts, the distinct poses and the copies;
    too few poses for an `n`-joint arm are refused."""
    rep = _apart(ds, repeated_poses(q, valid), y, say)
    first = valid & (rep == np.arange(len(q)))
    n_poses = int(first.sum())
    copies = int(valid.sum()) - n_poses
    if n_poses < 4 * n:
        samples = (
            f" ({int(valid.sum())} samples, {copies} repeating another's joint positions)" if copies else ""
        )
        raise CalibrationError(
            f"{ds.root / ds.device.file}: {n_poses} distinct stop-and-shoot poses{samples}; a {n}-joint arm "
            f"needs at least {4 * n} (and several times that for a trustworthy result)"
        )
    return rep, first, n_poses, copies


def axis_result(pf: PointFit, nominal: KinematicModel) -> AxisFitResult:
    """The point fit's geometric part as an `AxisFitResult` (the record every kind's verdict and outputs read)."""
    return _axis_result(pf.problem, pf.fit, nominal)


def _axis_result_program(
    problem: PointProblem, fit: PointFitResult, nominal: KinematicModel
) -> AxisFitResult:
    layout = problem.layout
    k = layout.base.axis_size
    params, _ = layout.split(fit.x)
    model, mounts = apply_correction(nominal, problem.T_flange_point0[None], params.correction)
    return AxisFitResult(
        model=eqx.tree_at(lambda m: m.T_flange_tool, model, mounts[0]),
        T_flange_marker=mounts,
        T_cam_base=problem.T_dev_base0 @ se3_exp(params.cam),
        params=params,
        std=fit.std[:k],
        cov=fit.cov[:k, :k],
        free=fit.free[:k],
        independence=fit.independence[:k],
        result=fit.result,
        num_steps=jnp.asarray(fit.num_steps),
        residual_rms=jnp.sqrt(fit.sigma2),
        singular_values=jnp.zeros(k),
        T_cam_base0=problem.T_dev_base0,
        T_flange_marker0=problem.T_flange_point0[None],
    )


_axis_result = stored_jit(_axis_result_program, "point_axis_result")


def parameters_of(pf: PointFit, setup: Setup, fit: AxisFitResult) -> list:
    """The physical parameter table of the point fit's geometric part."""
    return physical_parameters(
        pf.layout.base,
        setup.nominal,
        fit.T_flange_marker0,
        fit.T_cam_base0,
        fit.params.cam,
        fit.params.correction,
        fit.cov,
        np.asarray(fit.free),
        [setup.targets[0].name],
    )
