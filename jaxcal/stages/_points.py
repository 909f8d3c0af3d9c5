"""Stage 4 for stop-and-shoot tracker data: the point fit (`jaxcal._pointfit`).

Samples where every joint stands still and a device measures a point on the
flange have no arcs: the kinematic corrections, the device frame (unless it is
the base) and the point's mount are fitted to every sample at once. Only the
directions the samples determine are freed (the identifiability search of the
kind's tolerance); the rest are held at nominal and named.

Non-geometric terms (`Options.terms`: joint compliance under gravity,
transmission harmonics) are tried one after another and each is kept only
when K-fold cross-validation on the samples improves: the fit reports the
geometric model's cross-validation beside every model tried.

The record is the two-stage one (`TwoStage`, with `points`): its axis-fit
result holds the point fit's geometric part, so the verdict, the tables and
the outputs are those of every other kind.
"""

import dataclasses
import time
from dataclasses import dataclass, field

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .._axisfit import AxisFitResult
from .._correction import ParameterLayout, apply_correction, physical_parameters
from .._geometry import se3_exp
from .._kinematics import KinematicModel, forward_kinematics
from .._pointfit import (
    TERMS,
    PointData,
    PointFitResult,
    PointLayout,
    PointProblem,
    cross_validate,
    fit_points,
    fold_masks,
    predict,
    start_frame,
    term_basis,
)
from .._terms import approach, signs
from ..errors import CalibrationError
from ..records import ModelRow, ResidualStats, TermRow
from ._observe import Observations
from ._setup import Options, Setup
from ._synchronise import Sync
from ._terms import CV_GAIN as CV_GAIN  # the rule every capture's terms are kept by
from ._terms import TERM_FLOOR as TERM_FLOOR
from ._terms import TERM_STD_RAD as TERM_STD_RAD
from ._terms import inertials, resolve


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
    - `residual_mm`: mean, RMS and max distance of the fitted samples (mm).
    - `used`: the samples in the fit (mask over the table's rows).
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
) -> PointProblem:
    """A `PointProblem` from NumPy arrays (`inertials`: masses and centres of mass, for
    compliance and backlash's preload, the payload lumped in; `R`, `sigma_rad`: measured
    orientations, when `layout.orientation`). With a `backlash` term every joint's
    approach flank follows the samples' order (`jaxcal._terms.approach`)."""
    n = nominal.num_joints
    S = len(q)
    masses, coms = (np.zeros(n), np.zeros((n, 3))) if inertials is None else inertials
    if layout.orientation and (R is None or sigma_rad is None):
        raise ValueError("a layout with orientations needs R and sigma_rad")
    data = PointData(
        q=jnp.asarray(q, jnp.float64),
        y=jnp.asarray(y, jnp.float64),
        sigma=jnp.asarray(sigma, jnp.float64),
        mask=jnp.asarray(used, bool),
        masses=jnp.asarray(masses, jnp.float64),
        coms=jnp.asarray(coms, jnp.float64),
        R=jnp.asarray(np.broadcast_to(np.eye(3), (S, 3, 3)) if R is None else R, jnp.float64),
        sigma_rad=jnp.asarray(np.ones(S) if sigma_rad is None else sigma_rad, jnp.float64),
        approach=jnp.asarray(approach(q), jnp.float64) if "backlash" in layout.terms else None,
    )
    return PointProblem(nominal, jnp.asarray(T_dev_base0), jnp.asarray(T_flange_point0), data, layout)


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


@jax.jit
def _fit(problem: PointProblem, cand, tol):
    return fit_points(problem, cand, tol=tol)


@jax.jit
def _refit(problem: PointProblem, cand, free):
    return fit_points(problem, cand, tol=0.0, free=free)


def term_scale(problem: PointProblem) -> np.ndarray:
    """Per non-geometric coefficient (`PointLayout` order), the RMS of its basis over the fitted samples."""
    layout, d = problem.layout, problem.data
    b = np.asarray(term_basis(layout.terms, problem.nominal, d.q, d.masses, d.coms, d.approach))
    b = b[np.asarray(d.mask)]
    rms = np.sqrt(np.mean(b**2, axis=0))  # (joints, k): family-major below
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


@jax.jit
def _cv(problem: PointProblem, cand, free, train):
    return cross_validate(problem, cand, free, train)


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


def _cv_row(problem, cand, fit, train) -> dict:
    dist, test = (np.asarray(a) for a in _cv(problem, cand, fit.free, jnp.asarray(train)))
    d = 1e3 * dist[test]
    return {
        "cv_mean_mm": float(d.mean()),
        "cv_rms_mm": float(np.sqrt(np.mean(d**2))),
        "cv_max_mm": float(d.max()),
    }


def _orient_start(nominal, q, R, Tp0, T0) -> np.ndarray:
    """With measured orientations, the start's rotation from them (the mean of
    $R_i (R_{flange,i} R_{mount})^T$), its translation re-fitted to the points."""
    F = np.asarray(jax.vmap(lambda qq: forward_kinematics(nominal, qq)[-1])(jnp.asarray(q)))
    M = np.einsum("sab,sbc->sac", R, np.swapaxes(F[:, :3, :3] @ Tp0[:3, :3], 1, 2)).sum(0)
    U, _, Vt = np.linalg.svd(M)
    Rdb = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    T = T0.copy()
    T[:3, :3] = Rdb
    return T


def fit_point_samples(setup: Setup, obs: Observations, sync: Sync, options: Options) -> PointFit:
    """The point fit of a stop-and-shoot capture (see the module docstring)."""
    t0 = time.perf_counter()
    ds, nominal, kind = setup.dataset, setup.nominal, setup.kind
    s = ds.samples
    used = np.asarray(sync.inside, bool) & np.all(np.isfinite(sync.q), axis=1)
    n_used = int(used.sum())
    n = nominal.num_joints
    if n_used < 4 * n:
        raise CalibrationError(
            f"{ds.root / ds.device.file}: {n_used} stop-and-shoot samples; a {n}-joint arm needs at least "
            f"{4 * n} (and several times that for a trustworthy result)"
        )
    point = setup.targets[0]
    Tp0 = np.eye(4) if point.T_link_target is None else np.asarray(point.T_link_target, np.float64)
    q, y = np.asarray(sync.q, np.float64), np.asarray(s.position, np.float64)
    T0 = np.eye(4) if not kind.fixed_frame_free else start_frame(nominal, q[used], y[used], Tp0)
    if s.orientation is not None and kind.fixed_frame_free:
        T0 = _orient_start(nominal, q[used], s.orientation[used], Tp0, T0)
    base = ParameterLayout.of(nominal, 1, fixed_name=kind.fixed_frame)
    terms = resolve(setup, options)
    masses = inertials(setup) if {"compliance", "backlash"} & set(terms) else None
    tol = kind.identifiability_tol
    folds = options.cv_folds
    train = fold_masks(len(used), folds) if folds else None

    orientation = s.orientation is not None

    def attempt(terms):
        layout = PointLayout(base, terms, orientation)
        problem = point_problem(
            nominal, layout, q, y, s.sigma_m, used, T0, Tp0, masses, s.orientation, s.sigma_rad
        )
        cand = candidates(layout, fixed_frame_free=kind.fixed_frame_free, orientation=orientation)
        cand[base.axis_size :] &= term_scale(problem) >= TERM_FLOOR
        fit = jax.device_get(_fit(problem, jnp.asarray(cand), tol))
        fit = _hold_implausible_terms(problem, cand, fit)
        row = ModelRow(terms=tuple(terms), free=int(np.sum(fit.free)))
        if train is not None:
            row = dataclasses.replace(row, **_cv_row(problem, cand, fit, train & used[None]))
        return layout, problem, cand, fit, row

    options.say(f"point fit: {n_used} stop-and-shoot samples, forward kinematics of every sample")
    best = attempt(())
    models, kept = [best[4]], 0
    for term in terms:
        if train is None:
            raise CalibrationError(
                "non-geometric terms are kept only when cross-validation improves: cv_folds >= 2"
            )
        options.say(f"point fit: trying {term} (kept only if {folds}-fold cross-validation improves)")
        trial = attempt((*best[0].terms, term))
        models.append(trial[4])
        if trial[4].cv_mean_mm < (1.0 - CV_GAIN) * best[4].cv_mean_mm:
            best, kept = trial, len(models) - 1
    layout, problem, cand, fit, _ = best
    if not bool(fit.result == optx.RESULTS.successful):
        options.say("point fit: the solver did not converge")
    dist = 1e3 * np.linalg.norm(np.asarray(predict(fit.x, problem)) - y, axis=1)[used]
    names = layout.names()
    held = tuple(nm for nm, f, c in zip(names, np.asarray(fit.free), cand) if not f and c)
    return PointFit(
        problem=problem,
        fit=fit,
        layout=layout,
        candidates=cand,
        held=held,
        models=tuple(dataclasses.replace(m, kept=k == kept) for k, m in enumerate(models)),
        folds=folds,
        residual_mm=ResidualStats(
            mean=float(dist.mean()), rms=float(np.sqrt(np.mean(dist**2))), max=float(dist.max())
        ),
        used=used,
        timings={"point_fit_s": time.perf_counter() - t0},
    )


def axis_result(pf: PointFit, nominal: KinematicModel) -> AxisFitResult:
    """The point fit's geometric part as an `AxisFitResult` (the record every kind's verdict and outputs read)."""
    layout, fit, problem = pf.layout, pf.fit, pf.problem
    k = layout.base.axis_size
    params, _ = layout.split(jnp.asarray(fit.x))
    model, mounts = apply_correction(nominal, problem.T_flange_point0[None], params.correction)
    cov = jnp.asarray(fit.cov)[:k, :k]
    return AxisFitResult(
        model=eqx.tree_at(lambda m: m.T_flange_tool, model, mounts[0]),
        T_flange_marker=mounts,
        T_cam_base=problem.T_dev_base0 @ se3_exp(params.cam),
        params=params,
        std=jnp.asarray(fit.std)[:k],
        cov=cov,
        free=jnp.asarray(fit.free)[:k],
        independence=jnp.asarray(fit.independence)[:k],
        result=fit.result,
        num_steps=jnp.asarray(fit.num_steps),
        residual_rms=jnp.sqrt(jnp.asarray(fit.sigma2)),
        singular_values=jnp.zeros(k),
        T_cam_base0=problem.T_dev_base0,
        T_flange_marker0=problem.T_flange_point0[None],
    )


def parameters_of(pf: PointFit, setup: Setup, fit: AxisFitResult) -> list:
    """The physical parameter table of the point fit's geometric part."""
    return physical_parameters(
        pf.layout.base, setup.nominal, fit.T_flange_marker0, fit.T_cam_base0, fit.params.cam,
        fit.params.correction, fit.cov, np.asarray(fit.free), [setup.targets[0].name],
    )  # fmt: skip
