"""`jaxcal verify RESULT DATASET`: a calibration against measurements it was not fitted on.

A stop-and-shoot calibration (`result.json` with a `point_fit` block) predicts
the measured point of any pose: the calibrated model, its device frame, the
point's mount and its non-geometric terms. On a tracker dataset of the same
robot and device, `verify` compares every sample with that prediction and with
the nominal model's, and with what the calibration itself predicts for those
poses: per sample, the parameters' covariance pushed through the prediction
plus the per-sample scatter the fit's residuals showed. It reports the share
of samples inside their predicted 95 % bound and the ratio of the measured to
the predicted RMS (about 1 when the calibration's uncertainty is honest).
`cv=K` runs K-fold cross-validation on the dataset itself (the calibration
data: each sample predicted by a fit that did not see it).
"""

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from ._correction import ParameterLayout
from ._exported import stored_jit
from ._pointfit import PointLayout, cross_validate, fold_masks, predict, prediction_std
from .errors import DatasetError
from .io.checks import read_calibration
from .io.dataset import Dataset, load_dataset
from .records import ResidualStats
from .records_check import CalibrationReference, CrossValidation, Verification, VerificationSummary
from .stages._points import point_problem

#: The 95 % quantile of the distance of an isotropic 3-D Gaussian, in per-axis sigmas ($\sqrt{\chi^2_3(0.95)}$).
CHI3_95 = 2.7954834829151074


def _stats(d: np.ndarray) -> ResidualStats:
    return ResidualStats(mean=float(d.mean()), rms=float(np.sqrt(np.mean(d**2))), max=float(d.max()))


def read_point_result(path) -> CalibrationReference:
    """`result.json` (a result directory or the file) with its point fit, checked."""
    ref = read_calibration(path)
    if ref.point_fit is None:
        raise DatasetError(
            f"{ref.file}: no 'point_fit' block: verify checks results of stop-and-shoot tracker data "
            f"(this one is {ref.capture or 'another kind'!r})"
        )
    return ref


def _problem_for(ref: CalibrationReference, ds: Dataset, used=None):
    pf, file = ref.point_fit, ref.file
    nominal = pf.nominal
    if ds.samples is None:
        raise DatasetError(
            f"{ds.root / 'metadata.json'}: not a tracker dataset (no 'device'): nothing to verify"
        )
    if tuple(ds.joint_names) != tuple(nominal.joint_names):
        raise DatasetError(
            f"{ds.root / 'metadata.json'}: robot.joints {list(ds.joint_names)} differ from the calibrated robot's "
            f"{list(nominal.joint_names)} ({file}): another robot?"
        )
    if ref.device not in (None, ds.device.name):
        raise DatasetError(
            f"{ds.root / 'metadata.json'}: device {ds.device.name!r}, but {file} calibrated device "
            f"{ref.device!r}: its frame is another"
        )
    if ds.samples.q is None:
        raise DatasetError(f"{ds.root / ds.device.file}: verify needs every sample's joint positions")
    fixed = "T_device_base"
    layout = PointLayout(ParameterLayout.of(nominal, 1, fixed_name=fixed), pf.terms)
    if len(pf.x) != layout.size:
        raise DatasetError(f"{file}: point_fit.x has {len(pf.x)} entries, its layout {layout.size}")
    s = ds.samples
    used = np.ones(len(s.sample), bool) if used is None else used
    problem = point_problem(
        nominal, layout, s.q, s.position, s.sigma_m, used,
        pf.T_device_base0, pf.T_flange_point0, (pf.masses, pf.coms),
    )  # fmt: skip
    return problem, layout, nominal


def _predictions(x, cov, problem):
    """The points predicted by the calibrated and the nominal model, and the calibrated ones' std."""
    return predict(x, problem), predict(jnp.zeros_like(x), problem), prediction_std(x, cov, problem)


#: `verify`'s model algebra, one stored program (a later `jaxcal verify` reloads it).
_PREDICTIONS = stored_jit(_predictions, "verify_predictions")


def verify(result, dataset, *, cv: int = 0) -> Verification:
    """Check the stop-and-shoot calibration `result` (a directory or its
    `result.json`) against the tracker `dataset` (a path or a loaded `Dataset`);
    `cv`: also run K-fold cross-validation on `dataset` (see the module docstring).
    Raises `DatasetError` naming the file when the two do not belong together."""
    ref = read_point_result(result)
    ds = dataset if isinstance(dataset, Dataset) else load_dataset(dataset)
    problem, layout, _ = _problem_for(ref, ds)
    pf = ref.point_fit
    x = jnp.asarray(pf.x, jnp.float64)
    cov = jnp.asarray(pf.covariance, jnp.float64)
    y = np.asarray(ds.samples.position)
    calibrated, at_nominal, param = (np.asarray(a) for a in _PREDICTIONS(x, cov, problem))
    err = 1e3 * np.linalg.norm(calibrated - y, axis=1)
    nominal = 1e3 * np.linalg.norm(at_nominal - y, axis=1)  # param: per-axis RMS, m
    scatter2 = pf.residual_variance_factor * np.asarray(ds.samples.sigma_m) ** 2
    per_axis = np.sqrt(param**2 + scatter2)
    predicted = 1e3 * np.sqrt(3.0) * per_axis
    inside = err <= 1e3 * CHI3_95 * per_axis
    meas_rms = float(np.sqrt(np.mean(err**2)))
    pred_rms = float(np.sqrt(np.mean(predicted**2)))
    summary = VerificationSummary(
        samples=int(len(err)),
        calibrated_mm=_stats(err),
        nominal_mm=_stats(nominal),
        predicted_rms_mm=pred_rms,
        measured_over_predicted=meas_rms / pred_rms,
        inside_95_bound=float(np.mean(inside)),
        parameter_part_rms_mm=float(1e3 * np.sqrt(3 * np.mean(param**2))),
    )
    notes = []
    if summary.inside_95_bound < 0.9:
        notes.append(
            f"only {100 * summary.inside_95_bound:.0f} % of the samples lie inside their predicted 95 % bound: "
            "the calibration is worse here than it claims (poses outside the calibrated workspace, a changed "
            "set-up, or drift since)"
        )
    cv_block = None
    if cv:
        cv_problem, _, _ = _problem_for(ref, ds)
        free = jnp.asarray(pf.free, bool)
        train = jnp.asarray(fold_masks(len(y), cv))
        dist, test = jax.jit(cross_validate)(cv_problem, free, free, train)
        d = 1e3 * np.asarray(dist)[np.asarray(test)]
        s = _stats(d)
        cv_block = CrossValidation(folds=int(cv), mean=s.mean, rms=s.rms, max=s.max)
    return Verification(
        result=str(ref.file),
        dataset=str(ds.root),
        samples=np.asarray(ds.samples.sample),
        errors_mm=err,
        nominal_mm=nominal,
        predicted_mm=predicted,
        summary=summary,
        cv=cv_block,
        notes=tuple(notes),
    )


def plot_verification(v: Verification, path) -> None:
    """Error per sample (calibrated, nominal, the predicted 95 % bound) and a histogram, as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4), gridspec_kw={"width_ratios": [2, 1]})
    k = np.arange(len(v.errors_mm))
    a.plot(
        k,
        v.nominal_mm,
        "o",
        ms=3,
        color="0.6",
        label=f"nominal (mean {v.summary.nominal_mm.mean:.3f} mm)",
    )
    a.plot(
        k,
        v.errors_mm,
        "o",
        ms=3,
        color="C0",
        label=f"calibrated (mean {v.summary.calibrated_mm.mean:.3f} mm)",
    )
    a.plot(k, CHI3_95 / np.sqrt(3.0) * v.predicted_mm, "_", color="C3", label="predicted 95 % bound")
    a.set_yscale("log")
    a.set_xlabel("sample")
    a.set_ylabel("distance from measured point (mm)")
    a.legend(fontsize=8)
    b.hist(v.errors_mm, bins=max(5, len(v.errors_mm) // 5), color="C0")
    b.set_xlabel("calibrated error (mm)")
    b.set_ylabel("samples")
    fig.suptitle(f"jaxcal verify: {Path(v.dataset).name}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
