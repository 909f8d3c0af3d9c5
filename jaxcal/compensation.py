"""`jaxcal.compensate`: the commanded joints that put the tool where the calibrated rigid model says.

A calibration that kept non-geometric terms (`result.terms`: gravity sag, lost
motion, harmonics; `jaxcal._terms`) knows that the arm stands off the rigid
model `calibrated.urdf` describes. A robot program that plans with that model
(inverse kinematics, a taught pose) commands the joints `compensate` returns
instead of the planned ones, and the tool lands where the plan put it.
"""

from pathlib import Path

import numpy as np

from ._terms import compensate as _compensate
from .io.compensation import COMPENSATION_FILE, Compensation, read_compensation


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
    - `result`: a `CalibrationResult`, a `compensation.json`, or a result directory holding one.
    - `joints`: target joint positions of the rigid model (rad; m for prismatic joints),
      one pose `(joints,)` or a path `(N, joints)` in the order the robot visits them.
    - `approach`: the flank each joint comes from, `+1` (from smaller angles), `-1`
      (from larger) or `0` (unknown), shaped as `joints` or `(joints,)`; default: along
      the path's rows (`jaxcal._terms.approach`), unknown for one pose.

    **Returns:** the commanded joints, shaped as `joints`; `joints` itself when the
    calibration kept no term. Raises `jaxcal.errors.DatasetError` naming a file that is not
    a compensation file, `ValueError` for joints of another arm.
    """
    if isinstance(result, (str, Path)):
        path = Path(result)
        comp = read_compensation(path / COMPENSATION_FILE if path.is_dir() else path)
    else:
        comp = compensation_of(result)
    q = np.asarray(joints, np.float64)
    if comp is None:
        return q.copy()
    n = comp.nominal.num_joints
    if q.shape[-1:] != (n,) or q.ndim > 2:
        raise ValueError(
            f"compensate: joints of shape {q.shape}; this arm has {n} joints (one pose or (N, {n}))"
        )
    return _compensate(comp.terms, comp.x, comp.nominal, comp.masses, comp.coms, q, approach, comp.rate)
