"""`jaxcal.compensate`: the commanded joints that put the tool where the calibrated rigid model says.

A calibration that kept non-geometric terms (`result.terms`: gravity sag, lost
motion, harmonics; `jaxcal._terms`) knows that the arm stands off the rigid
model `calibrated.urdf` describes. A robot program that plans with that model
(inverse kinematics, a taught pose) commands the joints `compensate` returns
instead of the planned ones, and the tool lands where the plan put it.
"""

from pathlib import Path

import numpy as np

from ._kinematics import REVOLUTE
from ._terms import compensate as _compensate
from .errors import DatasetError
from .io.compensation import COMPENSATION_FILE, Compensation, read_compensation
from .io.result import read_result
from .records import ResultFile


def compensation_of(result) -> Compensation | None:
    """The `Compensation` of a `CalibrationResult` (None when it kept no term)."""
    fit = getattr(result, "term_fit", None)
    if fit is None or not fit.kept:
        return None
    est = result.estimate
    idx = est.layout.index("terms")
    std = np.sqrt(np.maximum(np.diag(np.asarray(est.cov))[idx], 0.0)) if len(idx) else np.zeros(len(fit.x))
    if len(idx) != len(fit.x):  # a point fit's coefficients (its own layout): their rows carry the std
        std = np.array([r.std for r in result.terms.coefficients])
    rate = np.asarray(result.nominal.reduction_ratio) / np.asarray(result.model.reduction_ratio)
    return Compensation(fit.terms, np.asarray(fit.x), std, result.nominal, fit.masses, fit.coms, rate)


def compensate(result, joints, approach=None) -> np.ndarray:
    """The commanded joints that put each joint, and so the tool, where the calibrated
    rigid model (`calibrated.urdf`) puts it at `joints`.

    **Arguments:**
    - `result`: a `CalibrationResult`, a `compensation.json`, or a result directory holding
      `compensation.json` (or only `result.json`, when the calibration kept no term).
    - `joints`: target joint positions of the rigid model (rad; m for prismatic joints),
      one pose `(joints,)` or a path `(N, joints)` in the order the robot visits them.
    - `approach`: the flank each joint comes from, `+1` (from smaller angles), `-1`
      (from larger) or `0` (unknown), or between (within the lost motion), shaped as `joints`
      or `(joints,)`; default: along the path's rows (`jaxcal._terms.approach`), unknown for
      one pose.

    **Returns:** the commanded joints, shaped as `joints`; a copy of `joints` when the
    calibration kept no term. Raises `jaxcal.errors.DatasetError` naming a file that is not
    a compensation file, `ValueError` naming what is wrong with `joints` or `approach` (another
    arm's count, a value that is not finite, degrees for radians), `TypeError` for a `result` of
    none of these kinds.
    """
    comp, where = _compensation(result)
    q = np.array(joints, np.float64)
    n = None if comp is None else comp.nominal.num_joints
    if q.ndim not in (1, 2) or (n is not None and q.shape[-1] != n):
        arm = "" if n is None else f"; this arm has {n} joints"
        raise ValueError(f"compensate: joints of shape {q.shape}{arm} (one pose or (N, joints))")
    _finite("joints", q)
    if comp is None:
        return q
    revolute = np.array([kind == REVOLUTE for kind in comp.nominal.joint_types])
    far = np.abs(q) > MAX_TURN_RAD
    if (far & revolute).any():
        k = tuple(int(i) for i in np.argwhere(far & revolute)[0])
        raise ValueError(
            f"compensate: joints{list(k)} = {q[k]:.6g} rad ({comp.nominal.joint_names[k[-1]]}), more than two "
            f"turns: joints are radians (metres for prismatic joints), not degrees ({where})"
        )
    if approach is not None:
        a = np.asarray(approach, np.float64)
        try:
            np.broadcast_to(a, q.shape)
        except ValueError:
            raise ValueError(
                f"compensate: approach of shape {a.shape} for joints of shape {q.shape}"
            ) from None
        _finite("approach", a)
        if (np.abs(a) > 1.0).any():
            raise ValueError(
                f"compensate: approach {a.min():.6g} to {a.max():.6g}; the flank is from -1 to +1"
            )
    return _compensate(comp.terms, comp.x, comp.nominal, comp.masses, comp.coms, q, approach, comp.rate)


#: The largest revolute target `compensate` takes (rad): two turns; more is degrees given for radians.
MAX_TURN_RAD = 4 * np.pi


def _finite(what: str, x: np.ndarray) -> None:
    if not np.isfinite(x).all():
        k = tuple(int(i) for i in np.argwhere(~np.isfinite(x))[0])
        raise ValueError(f"compensate: {what}{list(k)} is {x[k]}: every value must be finite")


def _compensation(result) -> tuple[Compensation | None, str]:
    """What `compensate` applies (None: no term kept) and where it was read."""
    if isinstance(result, (str, Path)):
        path = Path(result)
        if not path.is_dir():
            return read_compensation(path), str(path)
        if (path / COMPENSATION_FILE).exists() or not (path / "result.json").exists():
            return read_compensation(path / COMPENSATION_FILE), str(path / COMPENSATION_FILE)
        kept = _kept(read_result(path / "result.json"))
        if kept:
            raise DatasetError(
                f"{path / COMPENSATION_FILE}: no such file, though the calibration kept {kept}"
            )
        return None, str(path / "result.json")
    if hasattr(result, "term_fit"):  # a CalibrationResult
        return compensation_of(result), "the result"
    if isinstance(result, ResultFile):
        if kept := _kept(result):
            raise ValueError(
                f"compensate: a result read back from result.json holds the terms {kept} but not what their "
                f"basis is evaluated on (the nominal model, the links' masses): give its folder or its "
                f"{COMPENSATION_FILE}"
            )
        return None, "result.json"
    raise TypeError(
        f"compensate: result is a {type(result).__name__}; give a CalibrationResult, a {COMPENSATION_FILE} "
        "or a result folder"
    )


def _kept(result: ResultFile) -> list[str]:
    return [] if result.terms is None else list(result.terms.kept)
