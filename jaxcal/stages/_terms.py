"""The non-geometric terms of a camera capture, kept only where held-out views say so.

A real arm sags under gravity and loses motion in its gears
(`jaxcal._terms`: every view's joint angles gain $\\Delta_j = \\sum_k e_{j,k} b_{j,k}$,
the basis from the view's commanded pose and approach). Where a joint is filmed at two
speeds (`two_speeds`) the torques of the basis are the transmissions' along the encoder
log, the inertial ones included (`LogTorques`); elsewhere gravity's at the view's pose. The rigid refinement
(`stages.refine`) runs first; its Jacobian at the solution, in the free
parameters and in every joint's angle, gives every term's column (the joint's
angle column times its basis, per view), so the models are compared without
another solve:

1. candidates: a term column is tried where its basis varies over the views
   (`TERM_FLOOR`) and it is independent of the geometry's columns and of the
   terms' before it (the kind's identifiability tolerance; terms last, so a
   term is freed only where the geometry cannot already explain it);
2. the families are tried one after another, as the tracker's point fit does
   (`stages._points`): each model is fitted to the views by one Gauss-Newton
   step from the rigid solution (the terms are milliradians: the model is linear
   there to far below the pixel noise), its coefficients the data do not pin
   (`TERM_STD_RAD`) or whose sign no arm has (`jaxcal._terms.SIGNS`) held at zero;
3. cross-validation on the reprojection error: the views are left out in blocks
   of `BLOCK_FRAMES` consecutive frames of the capture order (so a frame's
   neighbours, whose detector errors and arm state it shares, are not split
   between fit and test), the blocks dealt round the `cv_folds` folds; each fold's
   fit is the same step on the other folds' views, and its held-out corners'
   reprojection errors are scored. A family is kept when it lowers the mean
   held-out error by more than `CV_GAIN` and the per-block gains stand out by
   `MIN_Z_BLOCKS` standard errors (`jaxcal._selection`'s rule, whose `MIN_Z` of 2 is
   too weak a test over the 10-25 blocks of consecutive frames a sweeps capture holds:
   on the realistic arm's analytic corners of `data/ur5e_sweeps`' design it would drop
   the compliance the held-out views prefer by 2.5 %, 1.8 standard errors, and that
   result is 2.0 mm and `suspect`; while a rigid arm's terms that gain 0.7-1.2 % do so
   by 0.7-0.8, and, kept, they cost a rendered SCARA's quill a third of its axis
   accuracy);
4. with a family kept, the refinement runs again with the kept columns free
   (`jaxcal._refine.refine`: the covariance, the summary and every output include
   them); with none, the rigid refinement stands, unchanged.
"""

import dataclasses
from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._device import to_device
from .._selection import CV_GAIN, improves, paired_z
from .._terms import (
    BASIS_FLOOR,
    TERM_STD_RAD,
    TERMS,
    approach_at,
    check_terms,
    column_map,
    correction,
    family_of,
    log_motion,
    names,
    relay,
    signs,
    with_payload,
    with_payload_tensors,
)
from ..errors import CalibrationError
from ..records import ModelRow, TermRow, TermsSummary
from ..robots import link_inertials, link_inertias
from . import _programs
from ._setup import Options, Setup
from ._synchronise import Sync, interpolate

#: A non-geometric coefficient whose basis has an RMS over the samples under this is not a
#: candidate: the joint carries no gravity load (compliance, in kN m), e.g. a vertical axis.
TERM_FLOOR = BASIS_FLOOR
#: The rigid model's held-out error beyond this many times its in-sample one: the folds' fits are not
#: the capture's (a block left out leaves part of the geometry unseen), and no term is judged by them.
CV_SANE = 20.0
#: A family's per-block gain must stand out by this many standard errors (see the module docstring).
MIN_Z_BLOCKS = 1.0
#: A capture sweeps a joint at two speeds when its segments' peak speeds differ by this factor:
#: then the terms' torques include the inertial ones (`two_speeds`).
TWO_SPEEDS = 1.5
#: Consecutive frames of the capture left out together by the cross-validation.
BLOCK_FRAMES = 6
#: A model's held-out fit solves its normal equations on Jacobi-scaled columns, dropping
#: directions below this share of the largest singular value (none on an identifiable set).
RCOND = 1e-10


def resolve(setup: Setup, options: Options) -> tuple[str, ...]:
    """The families to try: `options.terms` (`"auto"`: the kind's `default_terms`; `"none"`; a
    comma-separated string or a sequence of families)."""
    terms = options.terms
    if isinstance(terms, str):
        if terms.strip() == "auto":
            return setup.kind.default_terms
        terms = () if terms.strip() == "none" else tuple(t.strip() for t in terms.split(",") if t.strip())
    try:
        return check_terms(terms)
    except ValueError as e:
        raise CalibrationError(str(e)) from None


def inertials(setup: Setup) -> tuple[np.ndarray, np.ndarray]:
    """The links' masses and centres of mass from the robot file, the metadata's payload
    (`robot.payload`) lumped into the last link (`jaxcal._terms.with_payload`)."""
    ds = setup.dataset
    try:
        masses, coms = link_inertials(ds.robot_urdf)
    except (ValueError, KeyError, OSError) as e:
        raise CalibrationError(
            f"{ds.robot_urdf}: joint compliance and lost motion need every link's mass and centre of mass: {e}"
        ) from None
    p = ds.payload
    return with_payload(
        setup.nominal, masses, coms, 0.0 if p is None else p.mass_kg, (0, 0, 0) if p is None else p.com_m
    )


def speeds(setup: Setup, log_q) -> dict[str, list[float]]:
    """Each joint's peak speed (rad/s or m/s) in every recorded segment where it moves alone
    (`dataset.segments`), from the encoder log `log_q = (t, q)` (commanded positions)."""
    enc_t, enc_q = (np.asarray(a, np.float64) for a in log_q)
    qd = np.gradient(enc_q, enc_t, axis=0) if len(enc_t) > 2 else np.zeros_like(enc_q)
    names = list(setup.nominal.joint_names)
    out: dict[str, list[float]] = {}
    for name, start, end in setup.dataset.segments:
        rows = (enc_t >= start) & (enc_t <= end)
        if name in names and np.count_nonzero(rows) > 2:
            out.setdefault(name, []).append(float(np.abs(qd[rows, names.index(name)]).max()))
    return out


def two_speeds(setup: Setup, log_q) -> str | None:
    """The joint filmed sweeping at two speeds (`TWO_SPEEDS` apart; the first such joint's name), or
    None: then a compliant joint's lag under its inertial torques cannot be told from its reduction
    ratio (on a raised-cosine sweep the acceleration is proportional to the angle swept), and the
    terms' torques are gravity's alone."""
    for name, peaks in speeds(setup, log_q).items():
        if min(peaks) > 0 and max(peaks) / min(peaks) >= TWO_SPEEDS:
            return name
    return None


def inertia_tensors(setup: Setup, masses, coms) -> np.ndarray:
    """The links' inertia tensors about their centres of mass (the inertial torques') from the
    robot file, the metadata's payload lumped in (its own inertia where stated, else a point
    mass; `inertials`' masses and centres of mass are after the lumping)."""
    ds = setup.dataset
    try:
        raw_masses, raw_coms, tensors = link_inertias(ds.robot_urdf)
    except (ValueError, KeyError, OSError) as e:
        raise CalibrationError(
            f"{ds.robot_urdf}: the inertial torques need every link's inertia: {e}"
        ) from None
    p = ds.payload
    if p is None:
        return tensors
    return with_payload_tensors(
        setup.nominal, raw_masses, raw_coms, tensors, p.mass_kg, p.com_m, p.inertia_kgm2
    )


@dataclass(frozen=True)
class LogTorques:
    """The transmissions' torques along an encoder log (`jaxcal._terms.transmission_torques`
    at every row: the log's positions, velocities and accelerations times the joints' rates)
    and the load rule's flank there (`jaxcal._terms.relay`), read at any controller time."""

    t: np.ndarray
    torque: np.ndarray
    flank: np.ndarray

    @classmethod
    def of_log(cls, nominal, enc_t, enc_q, rate, masses, coms, tensors) -> "LogTorques":
        enc_t, enc_q = np.asarray(enc_t, np.float64), np.asarray(enc_q, np.float64)
        r = np.asarray(rate, np.float64)
        qd, qdd = log_motion(enc_t, enc_q, enc_t)
        torque = _programs.motion_torques(nominal, enc_q * r, qd * r, qdd * r, masses, coms, tensors)
        return cls(enc_t, torque, relay(torque))

    def at(self, t) -> tuple[np.ndarray, np.ndarray]:
        """`(torque, flank)` at controller times `t (N,)`: the torque interpolated, the flank of
        the log row at or before (times outside the log: its ends)."""
        t = np.clip(np.asarray(t, np.float64), self.t[0], self.t[-1])
        torque = np.stack(
            [np.interp(t, self.t, self.torque[:, j]) for j in range(self.torque.shape[1])], axis=-1
        )
        i = np.clip(np.searchsorted(self.t, t, side="right") - 1, 0, len(self.t) - 1)
        return torque, self.flank[i]


@dataclass(frozen=True, eq=False)
class TermFit:
    """The terms the refinement kept, with what the encoder log's correction needs.

    - `terms`: the kept families; `x`: their coefficients (`jaxcal._terms.names` order; held
      ones zero); `masses`, `coms`: the inertials of the basis (payload included).
    - `summary`: the result's `TermsSummary` (the models compared and why).
    - `tensors`: the links' inertia tensors (`inertia_tensors`; None: gravity's torques alone).
    """

    terms: tuple[str, ...]
    x: np.ndarray
    masses: np.ndarray
    coms: np.ndarray
    summary: TermsSummary
    tensors: np.ndarray | None = None
    #: The geometry's shifts `(free, r)` that what the model cannot tell from the geometry would
    #: make (`unresolved`), at the flat parameters `shift_at`; their causes `shift_of` (r).
    shift: np.ndarray | None = None
    shift_at: np.ndarray | None = None
    shift_of: tuple[str, ...] = ()

    @property
    def kept(self) -> bool:
        return bool(self.terms)

    def log_correction(self, nominal, enc_t, enc_q) -> np.ndarray:
        """The kept terms' joint-angle correction (rad) at every row of an encoder log
        `(T, joints)` of commanded positions (the approach rule along the log itself)."""
        enc_q = np.asarray(enc_q, np.float64)
        torque, load = None, None
        if self.tensors is not None:
            log = LogTorques.of_log(
                nominal, enc_t, enc_q, np.ones(enc_q.shape[1]), self.masses, self.coms, self.tensors
            )
            torque, load = log.torque, log.flank
        basis = view_basis(
            self.terms, nominal, enc_q, approach_at(enc_t, enc_q, enc_t), self.masses, self.coms, torque, load
        )
        return np.asarray(correction(self.terms, self.x, basis))


def view_basis(terms, nominal, q, a, masses, coms, torque=None, load=None) -> np.ndarray:
    """`jaxcal._terms.term_basis` at commanded positions `q (N, joints)`, approach flanks `a` and,
    along a logged motion, the transmissions' torques and load flanks (`LogTorques.at`; None:
    the arm still), as one compiled program on `q` padded to a size bucket (NumPy out, `(N,
    joints, k)`)."""
    return _programs.term_basis(terms, nominal, q, a, masses, coms, torque, load)


def fold_of_views(frames: np.ndarray, t_cam: np.ndarray, real: np.ndarray, folds: int) -> np.ndarray:
    """Each view's fold (-1 for padding): frames in capture order (their stamps) cut into
    blocks of `BLOCK_FRAMES`, the blocks dealt round the folds."""
    out = np.full(len(frames), -1)
    rows = np.unique(frames[real])
    first = {f: t_cam[real][frames[real] == f].min() for f in rows}
    order = sorted(rows, key=lambda f: (first[f], f))
    block = {f: (i // BLOCK_FRAMES) % folds for i, f in enumerate(order)}
    out[real] = [block[f] for f in frames[real]]
    return out


def block_of_views(frames: np.ndarray, t_cam: np.ndarray, real: np.ndarray) -> np.ndarray:
    """Each view's block of `BLOCK_FRAMES` consecutive frames in capture order (-1 for padding):
    `fold_of_views`' blocks before they are dealt round the folds."""
    return fold_of_views(frames, t_cam, real, np.iinfo(np.int32).max)


@dataclass
class _Linear:
    """The rigid solution's residuals and Jacobian (the geometry's free columns, then every
    term's) for the linearised fits: `A` `(rows, columns)` and `b` `(rows,)` weighted, `scale`
    the columns' norms, `raw_r`, `raw_J` unweighted, `used` the inlier rows, `fold` each
    row's fold, `n_geo` the geometry's columns; per term column its `family`, physical
    `sign` and basis RMS over the views (`b_rms`)."""

    A: np.ndarray
    b: np.ndarray
    scale: np.ndarray
    raw_r: np.ndarray
    raw_J: np.ndarray
    used: np.ndarray
    fold: np.ndarray
    n_geo: int
    family: np.ndarray
    sign: np.ndarray
    b_rms: np.ndarray
    #: Each row's block of consecutive frames (the paired test's unit; None: its fold).
    block: np.ndarray | None = None

    def columns(self, term_cols) -> np.ndarray:
        """The geometry's columns and the term columns `term_cols`."""
        return np.concatenate([np.arange(self.n_geo), self.n_geo + np.asarray(term_cols, int)])

    def fit(self, cols: np.ndarray, train: np.ndarray | None = None) -> np.ndarray:
        """The Gauss-Newton step of columns `cols` on the rows `train` (all: None), in the
        columns' own units."""
        A = self.A[:, cols] if train is None else self.A[train][:, cols]
        b = self.b if train is None else self.b[train]
        s = self.scale[cols]
        return np.linalg.lstsq(A / s, -b, rcond=RCOND)[0] / s

    def in_sample_px(self, term_cols) -> float:
        """The mean reprojection error (px) of the inlier corners after the all-views fit."""
        cols = self.columns(term_cols)
        e = self.raw_r[self.used] + self.raw_J[self.used][:, cols] @ self.fit(cols)
        return float(np.mean(np.sqrt(np.sum(e.reshape(-1, 2) ** 2, axis=1))))

    def held_out(self, term_cols, folds: int, blocks: bool = False):
        """Per held-out inlier corner (every fold), its reprojection error (px) after the fold's
        fit; with `blocks`, also each of those corners' block (`block`)."""
        cols, errs, ids = self.columns(term_cols), [], []
        block = self.fold if self.block is None else self.block
        for f in range(folds):
            test = self.fold == f
            d = self.fit(cols, ~test & self.used)
            sel = test & self.used
            e = self.raw_r[sel] + self.raw_J[sel][:, cols] @ d
            errs.append(np.sqrt(np.sum(e.reshape(-1, 2) ** 2, axis=1)))
            ids.append(block[sel][::2])
        return (np.concatenate(errs), np.concatenate(ids)) if blocks else np.concatenate(errs)

    def estimate(self, term_cols) -> tuple[np.ndarray, np.ndarray]:
        """The term columns' coefficients and std of the all-views fit (the noise from its residuals)."""
        idx = self.columns(term_cols)
        d = self.fit(idx)
        An = self.A[:, idx] / self.scale[idx]
        resid = self.b + An @ (d * self.scale[idx])
        n_obs = int(np.count_nonzero(self.used))
        sigma2 = float(resid @ resid) / max(n_obs - len(idx), 1)
        cov = sigma2 * np.linalg.pinv(An.T @ An, rcond=RCOND, hermitian=True)
        std = np.sqrt(np.maximum(np.diag(cov)[self.n_geo :], 0.0)) / self.scale[idx[self.n_geo :]]
        return d[self.n_geo :], std

    def held(self, term_cols) -> np.ndarray:
        """The term columns left free once those the views do not pin (`TERM_STD_RAD`) and those
        of a sign no arm has (`SIGNS`) are held, one round at a time."""
        cols = np.array(sorted(term_cols), int)
        while len(cols):
            x, std = self.estimate(cols)
            bad = (std * self.b_rms[cols] > TERM_STD_RAD) | (self.sign[cols] * x < 0)
            if not bad.any():
                break
            cols = cols[~bad]
        return cols


def _independent(A: np.ndarray, base: np.ndarray, cand: np.ndarray, tol: float) -> np.ndarray:
    """Which candidate columns `cand` are independent (distance above `tol`, columns
    normalised) of the span of the columns `base` and of the candidates kept before them."""
    norm = np.linalg.norm(A, axis=0)
    An = A / np.where(norm > 0, norm, 1.0)
    Q = np.linalg.qr(An[:, base])[0] if len(base) else np.zeros((A.shape[0], 0))
    keep = []
    for c in cand:
        v = An[:, c] - Q @ (Q.T @ An[:, c])
        dist = float(np.linalg.norm(v))
        if dist > tol:
            keep.append(c)
            Q = np.concatenate([Q, (v / dist)[:, None]], axis=1)
    return np.array(keep, int)


def _linearised(setup: Setup, sync, problem, res, terms, folds: int, masses, coms, tensors=None):
    """`(_Linear, basis (views, joints, k))`: every view's basis at its commanded pose, approach
    and (given the links' inertia `tensors`) the transmissions' torques and load flanks along the
    encoder log (at the refined clock and rates), and the term columns, each joint's angle column
    times its basis."""
    n = setup.nominal.num_joints
    data = problem.data
    real = np.asarray(data.frame) >= 0
    enc_t, enc_q = sync.log_q
    t_ctrl = (np.asarray(data.t_cam) - float(res.offset_s)) / (1.0 + 1e-6 * setup.dataset.clock_drift_ppm)
    rate = np.asarray(res.params.rate)
    q = interpolate(t_ctrl, enc_t, enc_q) * rate
    torque, load = None, None
    if tensors is not None:
        torque, load = LogTorques.of_log(setup.nominal, enc_t, enc_q, rate, masses, coms, tensors).at(t_ctrl)
    basis = view_basis(terms, setup.nominal, q, approach_at(enc_t, enc_q, t_ctrl), masses, coms, torque, load)
    basis[~real] = 0.0
    joint, col = column_map(terms, n)
    V, P = np.asarray(data.mask).shape
    view_of_row = np.repeat(np.arange(V), 2 * P)
    J_terms = np.asarray(res.angle_jacobian)[:, joint] * basis[view_of_row][:, joint, col]
    raw_J = np.concatenate([np.asarray(res.jacobian), J_terms], axis=1)
    raw_r = np.asarray(res.residuals).reshape(-1)
    w = np.repeat(np.asarray(res.weights).reshape(-1), 2)
    used = (w > 0) & np.repeat(np.asarray(data.mask).reshape(-1), 2)
    sw = np.sqrt(np.where(used, w, 0.0))
    A = raw_J * sw[:, None]
    scale = np.linalg.norm(A, axis=0)
    fold = fold_of_views(np.asarray(data.frame), np.asarray(data.t_cam), real, folds)[view_of_row]
    block = block_of_views(np.asarray(data.frame), np.asarray(data.t_cam), real)[view_of_row]
    lin = _Linear(
        A=A,
        b=raw_r * sw,
        scale=np.where(scale > 0, scale, 1.0),
        raw_r=raw_r,
        raw_J=raw_J,
        used=used,
        fold=fold,
        n_geo=int(np.asarray(res.jacobian).shape[1]),
        family=family_of(terms, n),
        sign=signs(terms, n),
        b_rms=np.sqrt(np.mean(basis[real][:, joint, col] ** 2, axis=0)),
        block=block,
    )
    return lin, basis


def _scored(lin: _Linear, term_cols, folds: int) -> tuple[dict, np.ndarray]:
    """A model's held-out figures (px) and its mean held-out error per block of consecutive
    frames (the paired test's samples)."""
    e, block = lin.held_out(term_cols, folds, blocks=True)
    per_block = np.array([e[block == b].mean() for b in np.unique(block)])
    return {
        "cv_mean_px": float(e.mean()),
        "cv_rms_px": float(np.sqrt(np.mean(e**2))),
        "cv_max_px": float(e.max()),
    }, per_block


def _better(current: np.ndarray, candidate: np.ndarray, current_px: float, candidate_px: float) -> bool:
    """`jaxcal._selection`'s gain (`CV_GAIN`), and the per-block gains at least `MIN_Z_BLOCKS`
    standard errors (`paired_z`)."""
    return improves(candidate_px, current_px) and paired_z(current, candidate) >= MIN_Z_BLOCKS


def _gain_words(gain: float, z: float, blocks: int) -> str:
    """The gain and its standard errors, and whether they pass the rule (a gain over `CV_GAIN` by
    `MIN_Z_BLOCKS` standard errors), in words."""
    passed = gain > CV_GAIN and z >= MIN_Z_BLOCKS
    return (
        f"{100 * abs(gain):.1f} % {'lower' if gain >= 0 else 'higher'} with it, {min(z, 999.0):.1f} standard errors "
        f"over {blocks} blocks of frames; {'passes' if passed else 'fails'} the rule (a gain over "
        f"{100 * CV_GAIN:g} % by {MIN_Z_BLOCKS:g} standard error)"
    )


def _compare(lin: _Linear, terms, folds: int, tol: float) -> tuple[list[dict], np.ndarray, list[str]]:
    """The families tried one after another (the module docstring's steps 1-3): `(models,
    the kept term columns, the kept families)`."""
    best_cols = np.zeros(0, int)
    best, best_blocks = _scored(lin, best_cols, folds)
    models = [dict(terms=(), free=lin.n_geo, **best)]
    inside = lin.in_sample_px(best_cols)
    if best["cv_mean_px"] > CV_SANE * inside:  # the folds' fits are not the capture's: nothing to judge by
        why = (
            f"not tried: the views left out are predicted {best['cv_mean_px']:.3g} px off on average against "
            f"{inside:.3g} px in the fit of every view; leaving a block of frames out leaves part of the geometry "
            "unseen, so cross-validation cannot judge a term (longer sweeps, or more frames per sweep, let it)"
        )
        models += [dict(terms=(t,), free=lin.n_geo, why=f"{t}: {why}") for t in terms]
        models[0]["kept"] = True
        return models, best_cols, []
    kept: list[str] = []
    for i, t in enumerate(terms):
        trial = (*kept, t)
        own = np.flatnonzero((lin.family == i) & (lin.b_rms >= TERM_FLOOR))
        cand = _independent(lin.A, lin.columns(best_cols), lin.n_geo + own, tol) - lin.n_geo
        cols = lin.held(np.concatenate([best_cols, cand])) if len(cand) else best_cols
        if not np.any(lin.family[cols] == i):
            why = (
                f"{t}: every coefficient held (not pinned to {TERM_STD_RAD:g} rad by the views, or of a sign no arm "
                "has)"
                if len(cand)
                else f"{t}: no coefficient the views tell apart from the geometry (its basis does not vary over "
                "them, or the geometry explains it)"
            )
            models.append(dict(terms=trial, free=lin.n_geo + len(cols), why=why))
            continue
        row, blocks = _scored(lin, cols, folds)
        gain = 1.0 - row["cv_mean_px"] / best["cv_mean_px"]
        why = (
            f"{t}: held-out reprojection error {row['cv_mean_px']:.4f} px mean against {best['cv_mean_px']:.4f} "
            f"({_gain_words(gain, paired_z(best_blocks, blocks), len(blocks))})"
        )
        models.append(dict(terms=trial, free=lin.n_geo + len(cols), why=why, **row))
        if _better(best_blocks, blocks, best["cv_mean_px"], row["cv_mean_px"]):
            best, best_blocks, best_cols = row, blocks, cols
            kept.append(t)
    best, best_cols, kept = _eliminate(lin, terms, folds, models, (best, best_blocks), best_cols, kept)
    final = next(m for m in reversed(models) if set(m["terms"]) == set(kept) and "cv_mean_px" in m)
    final["kept"] = True  # the model that stands: the last one scored with the kept families
    return models, best_cols, kept


def _eliminate(lin: _Linear, terms, folds: int, models: list[dict], best: tuple, best_cols, kept: list[str]):
    """The backward step after the forward one: a kept family that the model without it does not
    lose to by `_better` is dropped again (a family tried early can take part of a later one's
    pattern: compliance some of a lost motion's), the models' rows updated. `best`: the kept
    model's figures and per-block errors (`_scored`)."""
    best, best_blocks = best
    for t in list(kept) if len(kept) > 1 else ():
        i = terms.index(t)
        cols = lin.held(best_cols[lin.family[best_cols] != i])
        row, blocks = _scored(lin, cols, folds)
        gain = 1.0 - best["cv_mean_px"] / row["cv_mean_px"]
        rest = tuple(u for u in kept if u != t)
        why = (
            f"{t} left out again: held-out reprojection error {row['cv_mean_px']:.4f} px mean against "
            f"{best['cv_mean_px']:.4f} with it ({_gain_words(gain, paired_z(blocks, best_blocks), len(blocks))})"
        )
        models.append(dict(terms=rest, free=lin.n_geo + len(cols), why=why, **row))
        if not _better(blocks, best_blocks, row["cv_mean_px"], best["cv_mean_px"]):
            best, best_blocks, best_cols, kept = row, blocks, cols, [u for u in kept if u != t]
    return best, best_cols, kept


def left_out(lin: _Linear, terms, kept, best_cols, tol: float) -> np.ndarray:
    """The term columns of the families the cross-validation left out that a fit could free (as
    `_compare` frees them: independent of the geometry and the kept columns, pinned by the views, of
    an arm's sign); empty where none."""
    dropped = [i for i, t in enumerate(terms) if t not in kept]
    own = np.flatnonzero(np.isin(lin.family, dropped) & (lin.b_rms >= TERM_FLOOR))
    if not len(own):
        return own
    cand = _independent(lin.A, lin.columns(best_cols), lin.n_geo + own, tol) - lin.n_geo
    return np.setdiff1d(lin.held(np.concatenate([best_cols, cand])), best_cols) if len(cand) else cand


#: The cause `unresolved` names for a compliance's lag under the arm's own acceleration.
LAG = "lag"


def unresolved(lin: _Linear, terms, kept, best_cols, tol: float, lagging=None):
    """What the views cannot tell from the geometry would move it: `(the geometry's shifts (free,
    r), their causes (r))`, or `(None, ())`.

    Each column is the kept model's all-views fit against a fuller one the views cannot reject:
    with the families left out (`left_out`); and, where a compliance is free and sweeps at one speed
    hold the terms to gravity's torques, with the linearisation `lagging()` (the transmissions'
    torques, the inertial ones included; None without the robot's inertias) and the families it
    frees: the compliance's lag while the arm speeds up, which one speed cannot tell from the
    reduction ratios (`two_speeds`), cause `LAG`.

    A family left out because the held-out views cannot tell it from the geometry (a sag the link
    lengths absorb, on a capture of few poses) still moves the geometry, and a claim that takes the
    kept model as exact misses it. Each shift is a random vector of covariance the difference of the
    two fits' covariances where the effect is absent, its bias where it is not; the refinement
    counts their outer products in the covariance (`stages._refine.refine`: a consider covariance,
    the coefficients taken at their own estimates, every model the views cannot reject counted: the
    estimates of a capture that cannot tell them apart are noisy, and one model's may miss what the
    other's catches)."""
    base = lin.fit(lin.columns(best_cols))[: lin.n_geo]  # the geometry's step of the kept model
    shifts, causes = [], []
    extra = left_out(lin, terms, kept, best_cols, tol)
    cols = np.concatenate([best_cols, extra]).astype(int)
    if len(extra):
        shifts.append(lin.fit(lin.columns(cols))[: lin.n_geo] - base)
        causes.append("+".join(terms[i] for i in sorted(set(lin.family[extra]))))
    if (
        lagging is not None
        and "compliance" in terms
        and np.any(lin.family[cols] == terms.index("compliance"))
    ):
        full = lagging()
        if full is not None:  # the columns it frees judged on its own torques, as the kept ones
            cols = np.concatenate([best_cols, left_out(full, terms, kept, best_cols, tol)]).astype(int)
            shifts.append(full.fit(full.columns(cols))[: lin.n_geo] - base)
            causes.append(LAG)
    return (np.stack(shifts, axis=1), tuple(causes)) if shifts else (None, ())


@dataclass(frozen=True, eq=False)
class Selection:
    """`select`'s outcome: the `summary`; the `kept` families, their `basis` (views, joints, k) and
    coefficients' free mask `kept_free`; the basis's inertials `inert` (masses, coms, tensors:
    `tensors` None without two speeds); the geometry's shifts `shift` `(free, r)` that what the
    views cannot tell from the geometry would make, and their causes `shift_of` (`unresolved`)."""

    summary: TermsSummary
    kept: tuple[str, ...] = ()
    basis: np.ndarray | None = None
    kept_free: np.ndarray | None = None
    inert: tuple | None = None
    shift: np.ndarray | None = None
    shift_of: tuple[str, ...] = ()


def select(setup: Setup, sync, problem, res, terms: tuple[str, ...], options: Options) -> Selection:
    """The cross-validation of the module docstring on the rigid refinement `res` (with its
    Jacobians, `refine(..., jacobian=True)`) of `problem`."""
    folds = int(options.cv_folds)
    if folds < 2:
        return Selection(
            not_tried(terms, "they are kept only when cross-validation improves (cv_folds >= 2)")
        )
    masses, coms = inertials(setup)
    moving = two_speeds(setup, sync.log_q) if {"compliance", "backlash"} & set(terms) else None
    tensors = None if moving is None else inertia_tensors(setup, masses, coms)
    lin, basis = _linearised(setup, sync, problem, res, terms, folds, masses, coms, tensors)
    tol = setup.kind.identifiability_tol
    models, best_cols, kept_families = _compare(lin, terms, folds, tol)
    kept = tuple(t for t in terms if t in kept_families)

    def lagging() -> _Linear | None:  # the terms at one speed hold gravity's torques alone: the lag beside
        try:
            full = inertia_tensors(setup, masses, coms)
        except CalibrationError:  # a robot file without inertias: no lag to count
            return None
        return _linearised(setup, sync, problem, res, terms, folds, masses, coms, full)[0]

    swept = moving is None and setup.kind.has_arcs  # frames taken while the arm moves, at one speed
    shift, shift_of = unresolved(lin, terms, kept, best_cols, tol, lagging if swept else None)
    # The kept families' basis columns and coefficient mask, in the kept layout's order.
    keep_mask = np.zeros(len(lin.family), bool)
    keep_mask[best_cols] = True
    first = np.cumsum([0] + [TERMS[t] for t in terms])
    basis_cols = [np.arange(first[terms.index(t)], first[terms.index(t) + 1]) for t in kept]
    kept_free = [keep_mask[lin.family == terms.index(t)] for t in kept]
    payload = setup.dataset.payload
    torques = (
        (f"the transmissions' torques include the links' inertial ones ({moving} is filmed at two speeds)",)
        if moving
        else (
            "the torques are gravity's alone: no joint is filmed at two speeds, so a compliant joint's lag "
            "while the arm speeds up cannot be told from its reduction ratio (film each sweep both ways, "
            "the second at another speed)",
        )
        if {"compliance", "backlash"} & set(kept) and setup.kind.has_arcs
        else ()
    )
    summary = TermsSummary(
        tried=terms,
        kept=kept,
        models=tuple(ModelRow(**m) for m in models),
        coefficients=(),
        folds=folds,
        block_frames=BLOCK_FRAMES,
        payload_kg=None if payload is None else payload.mass_kg,
        notes=torques,
    )
    inert = (masses, coms, tensors)
    if not kept:
        return Selection(summary, inert=inert, shift=shift, shift_of=shift_of)
    return Selection(
        summary,
        kept,
        basis[:, :, np.concatenate(basis_cols)],
        np.concatenate(kept_free),
        inert,
        shift,
        shift_of,
    )


def with_terms(setup: Setup, sync: Sync, problem, res, layout, cand, free, terms, options: Options):
    """The non-geometric `terms` tried on the rigid refinement `res` (`select`)
    and, where a family is kept, the refinement again with its coefficients free: `(problem,
    res, layout, cand, free, TermFit)` of the refinement that stands (the rigid one's when
    nothing is kept, its Jacobians dropped)."""
    options.say(f"refinement: non-geometric terms {list(terms)}, each kept only if held-out views improve")
    jax.block_until_ready(res)
    sel = select(setup, sync, problem, jax.device_get(res), terms, options)
    res = eqx.tree_at(lambda r: (r.jacobian, r.angle_jacobian), res, (None, None))
    left = dict(shift=sel.shift, shift_at=np.flatnonzero(free), shift_of=sel.shift_of)
    if not sel.kept:
        return problem, res, layout, cand, free, TermFit((), np.zeros(0), None, None, sel.summary, **left)
    kept, kept_free = sel.kept, sel.kept_free
    options.say(f"refinement: kept {'+'.join(kept)}; refining again with them")
    problem = dataclasses.replace(
        problem, terms=kept, data=dataclasses.replace(problem.data, term_basis=to_device(sel.basis))
    )
    params = dataclasses.replace(res.params, terms=jnp.zeros(kept_free.size))
    layout = dataclasses.replace(layout, terms=kept)
    free = np.concatenate([free, kept_free])
    cand = np.concatenate([cand, np.ones(kept_free.size, bool)])
    res = _programs.refinement(free)(problem, params)
    idx = layout.index("terms")
    x, std = np.asarray(res.params.terms), np.asarray(res.std)[idx]
    rows = coefficient_rows(kept, setup.nominal.joint_names, x, std, free[idx])
    summary = dataclasses.replace(sel.summary, coefficients=rows)
    masses, coms, tensors = sel.inert
    return problem, res, layout, cand, free, TermFit(kept, x, masses, coms, summary, tensors, **left)


def coefficient_rows(terms, joints, x, std, free) -> tuple[TermRow, ...]:
    """The kept coefficients as the result's rows."""
    return tuple(
        TermRow(name=nm, estimate=float(v), std=float(s), free=bool(f))
        for nm, v, s, f in zip(names(terms, joints), x, std, free)
    )


def not_tried(terms: tuple[str, ...], why: str) -> TermsSummary:
    """A summary of terms asked for but not tried, saying why."""
    return TermsSummary(
        tried=(),
        kept=(),
        models=(),
        coefficients=(),
        folds=0,
        notes=(f"non-geometric terms {list(terms)} not tried: {why}",),
    )
