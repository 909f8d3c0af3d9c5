"""`jaxcal verify RESULT DATASET`: a calibration against measurements it was not fitted on.

A stop-and-shoot calibration (`result.json` with a `point_fit` block) predicts
the measured point of any pose (and, when it fitted orientations, the point
frame's orientation): the calibrated model, its device frame, the point's mount
and its non-geometric terms. On a tracker dataset of the same robot and device,
`verify` compares every sample with that prediction and with the nominal
robot's, and with what the calibration itself predicts for those poses: per
sample, the parameters' covariance pushed through the prediction plus the
per-sample scatter the fit's residuals showed. It reports the share of samples
inside their predicted 95 % bound and the ratio of the measured to the
predicted RMS (about 1 when the calibration's uncertainty is honest), of the
positions (mm) and of the orientations (deg). `cv=K` runs K-fold
cross-validation on the dataset itself with the calibration's own observations
and folds (`stages._points.fold_train`, `cross_validation`): on the calibration's
dataset its figures are `jaxcal calibrate`'s.

**Nominal.** The `nominal` row is the nominal robot (no kinematic correction,
no non-geometric term) in the calibration's fitted device frame, with the
point's nominal mount (its fitted one when the calibration's dataset gave
none): the same whether the device frame was fitted or is the base
(`--device-is-base`), where it is the base.

**The test (the exit status).** Under the calibration's own model the errors
of the $N$ samples ($k$ = 3 components each, 6 with orientations) are jointly
Gaussian, $e \\sim N(0, \\Sigma)$, $\\Sigma = D + G C G^T$: $D$ the scatter the fit
showed per component ($\\hat\\sigma^2 \\sigma_i^2$), $G$ the prediction's Jacobian and
$C$ the parameters' covariance (their error is common to every sample). Whitened
by the symmetric root, $z = \\Sigma^{-1/2} e$ (`whiten`: the SVD of
$D^{-1/2} G C^{1/2}$, linear in $N$), the samples' blocks $z_i$ are independent
and standard normal, so that

- $T = \\|z\\|^2$ has $T / (kN) \\sim F(kN, \\nu)$, $\\nu$ the fit's residual degrees
  of freedom on which $\\hat\\sigma^2$ was estimated ($\\chi^2_{kN}$ for a result without
  them): the whitened measured / predicted RMS $\\sqrt{T / kN}$ is about 1, and
  too large beyond the $1 - \\alpha$ quantile;
- the samples with $\\|z_i\\|^2 \\le k F_{k, \\nu}(0.95)$ (inside their 95 % bound) are
  Binomial$(N, 0.95)$: too few when the binomial's lower tail at their count is
  below $\\alpha$.

Each at $\\alpha$ = `ALPHA` = 0.001: a calibration that is what it claims is
rejected in at most 0.2 % of verifications, while a result verified on another
set-up or 10 times worse than it claims fails both from a handful of samples.
`verify` (`Verification.exit_code`) exits 3 when either rejects; a dataset of
another robot is refused (exit 2): its nominal model's flange, at the dataset's
joint positions and after the best rigid alignment, lies more than
`ROBOT_GAP_M` from the result's nominal and calibrated models' (compared by
kinematics, whatever the joints are called).
"""

import functools
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from . import _distributions as distributions
from ._correction import ParameterLayout, apply_correction
from ._device import to_device
from ._exported import stored_jit
from ._geometry import so3_log
from ._kinematics import KinematicModel, forward_kinematics
from ._npgeom import kabsch
from ._pointfit import (
    PointLayout,
    point_jacobian,
    predict,
    predict_rotation,
    prediction_std,
    rotation_jacobian,
)
from .errors import DatasetError
from .fleet_prior import gaussian_rows
from .io.checks import read_calibration
from .io.dataset import Dataset, load_dataset
from .records import ResidualStats
from .records_check import (
    CalibrationReference,
    CrossValidation,
    PredictionTest,
    Verification,
    VerificationSummary,
)
from .stages._points import cross_validation, fold_train, point_problem

#: The 95 % quantile of the distance of an isotropic 3-D Gaussian, in per-axis sigmas ($\\sqrt{\\chi^2_3(0.95)}$).
CHI3_95 = 2.7954834829151074
#: Each test's false-alarm probability (see the module docstring).
ALPHA = 1e-3
#: A dataset whose nominal robot puts the flange this far (m) from the result's robots (its nominal
#: and its calibrated model, after the best rigid alignment) is of another robot (`jaxcal check`'s
#: `ROBOT_TOLERANCE_M`, there between joint origins): a real arm is millimetres off its datasheet.
ROBOT_GAP_M = 0.01
#: ... and one within it whose flange differs from the result's nominal one by more than this (m)
#: is named in a note: the same robot, another robot file.
ROBOT_SAME_M = 1e-6
#: The robots are compared at up to this many of the dataset's configurations.
ROBOT_POSES = 1000


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


def _flange_points(model: KinematicModel, q) -> jax.Array:
    return jax.vmap(lambda qq: forward_kinematics(model, qq)[-1, :3, 3])(q)


def _gap(pa: np.ndarray, pb: np.ndarray) -> float:
    """The largest distance between two sets of flange origins `(S, 3)` after the best rigid
    alignment of one onto the other (m)."""
    T = kabsch(pb, pa)
    return float(np.max(np.linalg.norm(pb @ T[:3, :3].T + T[:3, 3] - pa, axis=1)))


@functools.cache
def _robot_points(layout: PointLayout):
    """One stored program (`jaxcal._exported`): the flange origins at `q` of the dataset's robot,
    the result's nominal one and its calibrated one (the point fit's `x` applied)."""

    def robot_points(mine, nominal, x, T_flange_point0, q):
        params, _ = layout.split(x)
        calibrated, _ = apply_correction(nominal, T_flange_point0[None], params.correction)
        return tuple(_flange_points(m, q) for m in (mine, nominal, calibrated))

    return stored_jit(robot_points, "verify_robot_points", (layout,))


def _same_robot(ref: CalibrationReference, ds: Dataset) -> tuple[str, ...]:
    """Refuse (`DatasetError`, exit 2) a dataset whose nominal robot is not the result's, by
    kinematics (`_gap` against the result's nominal and calibrated models); a note when its robot
    file differs from the calibrated one within that, and when the joints' names differ."""
    pf, meta = ref.point_fit, ds.root / "metadata.json"
    nominal, mine = pf.nominal, ds.load_model()
    if mine.num_joints != nominal.num_joints or tuple(mine.joint_types) != tuple(nominal.joint_types):
        raise DatasetError(
            f"{meta}: its robot has joints {list(zip(mine.joint_names, mine.joint_types))}, the robot {ref.file} "
            f"calibrated {list(zip(nominal.joint_names, nominal.joint_types))}: another robot"
        )
    q = np.asarray(ds.samples.q, np.float64)
    q = q[:: max(1, len(q) // ROBOT_POSES)]
    layout = PointLayout(ParameterLayout.of(nominal, 1, fixed_name="T_device_base"), pf.terms)
    x, mount = (np.asarray(v, np.float64) for v in (pf.x, pf.T_flange_point0))
    p_mine, p_nominal, p_calibrated = (
        np.asarray(p) for p in _robot_points(layout)(mine, nominal, x, mount, q)
    )
    gap = min(_gap(p_mine, p_nominal), _gap(p_mine, p_calibrated))
    if gap > ROBOT_GAP_M:
        raise DatasetError(
            f"{ds.robot_urdf}: at the dataset's joint positions its flange lies up to {1e3 * gap:.1f} mm from the "
            f"robot {ref.file} calibrated (after the best rigid alignment; tolerance {1e3 * ROBOT_GAP_M:g} mm): "
            "another robot; verify a result on data of its own robot"
        )
    notes = []
    if (differ := _gap(p_mine, p_nominal)) > ROBOT_SAME_M:
        notes.append(
            f"{ds.robot_urdf} is not the robot file of {ref.file}: at the dataset's joint positions "
            f"their flanges differ by up to {1e3 * differ:.3g} mm (after the best rigid alignment), within "
            f"{1e3 * ROBOT_GAP_M:g} mm: taken for the same robot, verified with the result's nominal model "
            "(if the robot file was updated, calibrate again with it)"
        )
    if tuple(ds.joint_names) != tuple(nominal.joint_names):
        notes.append(
            f"the dataset's joints {list(ds.joint_names)} are named otherwise than the calibrated robot's "
            f"{list(nominal.joint_names)}; the kinematics agree (within {1e3 * gap:.2g} mm): matched in order"
        )
    return tuple(notes)


def _problem_for(ref: CalibrationReference, ds: Dataset):
    """The `PointProblem` of the dataset's samples with the result's references, its layout (with
    orientations when the result fitted them and the dataset has them) and notes."""
    pf, file = ref.point_fit, ref.file
    nominal = pf.nominal
    if ds.samples is None:
        raise DatasetError(
            f"{ds.root / 'metadata.json'}: not a tracker dataset (no 'device'): nothing to verify"
        )
    if ref.device not in (None, ds.device.name):
        raise DatasetError(
            f"{ds.root / 'metadata.json'}: device {ds.device.name!r}, but {file} calibrated device "
            f"{ref.device!r}: its frame is another"
        )
    if ds.samples.q is None:
        raise DatasetError(f"{ds.root / ds.device.file}: verify needs every sample's joint positions")
    notes = list(_same_robot(ref, ds))
    s = ds.samples
    orientation = pf.orientation and s.orientation is not None
    if pf.orientation and not orientation:
        notes.append(
            f"{file} fitted orientations, the dataset has none: positions only (its cross-validation differs "
            "from the calibration's)"
        )
    layout = PointLayout(ParameterLayout.of(nominal, 1, fixed_name="T_device_base"), pf.terms, orientation)
    if len(pf.x) != layout.size:
        raise DatasetError(f"{file}: point_fit.x has {len(pf.x)} entries, its layout {layout.size}")
    used = np.all(np.isfinite(s.q), axis=1)
    problem = point_problem(
        nominal,
        layout,
        s.q,
        s.position,
        s.sigma_m,
        used,
        pf.T_device_base0,
        pf.T_flange_point0,
        (pf.masses, pf.coms),
        s.orientation if orientation else None,
        s.sigma_rad if orientation else None,
        None
        if pf.prior is None
        else gaussian_rows(pf.prior.names, pf.prior.mean, pf.prior.covariance, layout.names()),
    )
    return problem, layout, tuple(notes)


def set_up_only(x, layout: PointLayout, mount: bool):
    """`x` with only the device frame kept (and with `mount` the point's mount): the nominal robot."""
    keep = np.zeros(layout.size, bool)
    keep[layout.base.index("cam")] = True
    keep[layout.base.index("tool")] = mount
    return to_device(np.where(keep, np.asarray(x, np.float64), 0.0))


def _rotation_error(x, problem):
    """Per sample $\\log(\\hat R_i^T R_i)$: the measured orientation in the predicted one's frame (rad)."""
    R_hat = predict_rotation(x, problem)
    return jax.vmap(so3_log)(jnp.einsum("sba,sbc->sac", R_hat, problem.data.R))


def _predictions(x, x_nom, cov, problem):
    """The points predicted by the calibrated model (`x`) and the nominal robot (`x_nom`), the
    calibrated ones' std and Jacobian, and (with orientations) the same of the orientations."""
    out = {
        "y": predict(x, problem),
        "y_nominal": predict(x_nom, problem),
        "std": prediction_std(x, cov, problem),
        "G": point_jacobian(x, problem),
    }
    if problem.layout.orientation:
        Gr = rotation_jacobian(x, problem)
        out |= {
            "rot": _rotation_error(x, problem),
            "rot_nominal": _rotation_error(x_nom, problem),
            "std_rot": jnp.sqrt(jnp.maximum(jnp.einsum("sai,ij,saj->s", Gr, cov, Gr), 0.0) / 3.0),
            "Gr": Gr,
        }
    return out


#: `verify`'s model algebra, one stored program (a later `jaxcal verify` reloads it).
_PREDICTIONS = stored_jit(_predictions, "verify_predictions")


def whiten(e: np.ndarray, G: np.ndarray, cov: np.ndarray, var: np.ndarray) -> np.ndarray:
    """The errors `e` `(N, k)` whitened by their joint covariance $\\Sigma = D + G C G^T$ ($D$ the
    per-component variances `var` `(N, k)`, `G` `(N, k, n)` the prediction's Jacobian, `C` =
    `cov` `(n, n)`), with the symmetric root: $z = (I + U U^T)^{-1/2} D^{-1/2} e$, $U = D^{-1/2} G L$,
    $C = L L^T$; by the SVD $U = Q S W^T$, $(I + UU^T)^{-1/2} = I - Q (I - (I + S^2)^{-1/2}) Q^T$.
    **Returns:** $z$ `(N, k)`, standard normal when the prediction is right."""
    N, k = e.shape
    d = np.sqrt(var.reshape(-1))
    w = e.reshape(-1) / d
    lam, V = np.linalg.eigh(cov)
    keep = lam > max(lam.max(), 0.0) * 1e-14
    U = (G.reshape(N * k, -1) / d[:, None]) @ (V[:, keep] * np.sqrt(lam[keep]))
    Q, S, _ = np.linalg.svd(U, full_matrices=False)
    z = w - Q @ ((1.0 - 1.0 / np.sqrt(1.0 + S**2)) * (Q.T @ w))
    return z.reshape(N, k)


#: Samples whose whitened error lies beyond this many sigmas (the norm over their components), at
#: most `OUTLIER_SHARE` of them, are bad measurements: left out of the prediction test, named.
OUTLIER_SIGMAS, OUTLIER_SHARE = 6.0, 0.1


def _bad_samples(z: np.ndarray) -> np.ndarray:
    """The rows of `z` `(N, k)` beyond `OUTLIER_SIGMAS` (none when more than `OUTLIER_SHARE` are:
    then it is the calibration or the set-up, not a few measurements)."""
    far = np.flatnonzero(np.sqrt(np.sum(z**2, axis=1)) > OUTLIER_SIGMAS)
    return far if far.size <= OUTLIER_SHARE * len(z) else far[:0]


def prediction_test(z: np.ndarray, dof_noise: int | None, alpha: float = ALPHA) -> PredictionTest:
    """The two tests of whitened errors `z` `(N, k)` (see the module docstring)."""
    N, k = z.shape
    T, dof = float(np.sum(z**2)), N * k
    if dof_noise is None:
        p, limit, bound = (
            distributions.chi2_sf(T, dof),
            distributions.chi2_ppf(1 - alpha, dof) / dof,
            distributions.chi2_ppf(0.95, k),
        )
    else:
        p = distributions.f_sf(T / dof, dof, dof_noise)
        limit, bound = (
            distributions.f_ppf(1 - alpha, dof, dof_noise),
            k * distributions.f_ppf(0.95, k, dof_noise),
        )
    inside = int(np.sum(np.sum(z**2, axis=1) <= bound))
    p_inside = float(distributions.binom_cdf(inside, N, 0.95))
    return PredictionTest(
        samples=N,
        components=k,
        statistic=T,
        dof=dof,
        dof_noise=dof_noise,
        ratio=float(np.sqrt(T / dof)),
        ratio_limit=float(np.sqrt(limit)),
        p_value=float(p),
        inside=inside / N,
        inside_limit=float(distributions.binom_ppf(alpha, N, 0.95)) / N,
        p_inside=p_inside,
        alpha=alpha,
        holds=bool(p >= alpha and p_inside >= alpha),
    )


def _tested(z: np.ndarray, dof: int, s, notes: list) -> PredictionTest:
    """The prediction test of the whitened errors `z` (one row per sample of `s`), the bad samples
    left out where the rest then hold; what it found is appended to `notes`."""
    test = prediction_test(z, dof)
    far = _bad_samples(z)
    if not test.holds and far.size:  # bad measurements, which calibrate's robust fit leaves out too
        kept = np.ones(len(z), bool)
        kept[far] = False
        test = prediction_test(z[kept], dof)
        sigmas = np.sqrt(np.sum(z[far] ** 2, axis=1))
        notes.append(
            f"{far.size} of {len(z)} samples left out of the test as bad measurements (over {OUTLIER_SIGMAS:g} "
            "whitened sigmas, as calibrate's robust fit rejects them): "
            + ", ".join(
                f"sample {int(s.sample[i])} (line {int(s.lines[i])}, {v:.0f} sigma)"
                for i, v in zip(far, sigmas)
            )
            + f"; the rest {'hold' if test.holds else 'do not hold either'}"
        )
    if not test.holds:
        worst = np.argsort(-np.sum(z**2, axis=1))[:3]
        notes.append(
            f"the errors are not what the calibration predicts: whitened measured / predicted RMS {test.ratio:.2f} "
            f"(limit {test.ratio_limit:.2f}), {100 * test.inside:.0f} % of the samples inside their 95 % bound "
            f"(at least {100 * test.inside_limit:.0f} %); worst samples {[int(s.sample[i]) for i in worst]} "
            "(poses outside the calibrated workspace, a changed set-up, drift since, or bad measurements)"
        )
    return test


def verify(result, dataset, *, cv: int = 0) -> Verification:
    """Check the stop-and-shoot calibration `result` (a directory or its
    `result.json`) against the tracker `dataset` (a path or a loaded `Dataset`);
    `cv`: also run K-fold cross-validation on `dataset` (see the module docstring).
    Raises `DatasetError` naming the file when the two do not belong together
    (another robot, by kinematics; another device)."""
    ref = read_point_result(result)
    ds = dataset if isinstance(dataset, Dataset) else load_dataset(dataset)
    problem, layout, notes = _problem_for(ref, ds)
    notes = list(notes)
    if ref.status in (
        "failed",
        "suspect",
    ):  # measured all the same: what a suspect result does is worth knowing
        notes.insert(0, f"the calibration is {ref.status} ({ref.reason or 'see result.json reasons'})")
    pf = ref.point_fit
    x = to_device(pf.x, np.float64)
    cov = np.asarray(pf.covariance, np.float64)
    s = ds.samples
    y = np.asarray(s.position)
    x_nom = set_up_only(x, layout, not pf.mount_given)
    out = {k: np.asarray(v) for k, v in _PREDICTIONS(x, x_nom, to_device(cov), problem).items()}
    e = y - out["y"]
    err = 1e3 * np.linalg.norm(e, axis=1)
    nominal = 1e3 * np.linalg.norm(y - out["y_nominal"], axis=1)
    param = out["std"]  # per-axis RMS, m
    scatter2 = pf.residual_variance_factor * np.asarray(s.sigma_m) ** 2
    per_axis = np.sqrt(param**2 + scatter2)
    predicted = 1e3 * np.sqrt(3.0) * per_axis
    inside = err <= 1e3 * CHI3_95 * per_axis
    meas_rms = float(np.sqrt(np.mean(err**2)))
    pred_rms = float(np.sqrt(np.mean(predicted**2)))
    errors, G, var = [e], [out["G"]], [np.repeat(scatter2[:, None], 3, axis=1)]
    angles = None
    if layout.orientation:
        scatter_r = pf.residual_variance_factor * np.asarray(s.sigma_rad) ** 2
        per_axis_r = np.sqrt(out["std_rot"] ** 2 + scatter_r)
        angles = (
            np.degrees(np.linalg.norm(out["rot"], axis=1)),
            np.degrees(np.linalg.norm(out["rot_nominal"], axis=1)),
            np.degrees(np.sqrt(3.0) * per_axis_r),
        )
        inside_r = angles[0] <= np.degrees(CHI3_95 * per_axis_r)
        errors, G, var = (
            errors + [out["rot"]],
            G + [out["Gr"]],
            var + [np.repeat(scatter_r[:, None], 3, axis=1)],
        )
    summary = VerificationSummary(
        samples=int(len(err)),
        calibrated_mm=_stats(err),
        nominal_mm=_stats(nominal),
        predicted_rms_mm=pred_rms,
        measured_over_predicted=meas_rms / pred_rms,
        inside_95_bound=float(np.mean(inside)),
        parameter_part_rms_mm=float(1e3 * np.sqrt(3 * np.mean(param**2))),
        **(
            {}
            if angles is None
            else {
                "calibrated_deg": _stats(angles[0]),
                "nominal_deg": _stats(angles[1]),
                "predicted_rms_deg": float(np.sqrt(np.mean(angles[2] ** 2))),
                "measured_over_predicted_deg": float(
                    np.sqrt(np.mean(angles[0] ** 2) / np.mean(angles[2] ** 2))
                ),
                "inside_95_bound_deg": float(np.mean(inside_r)),
            }
        ),
    )
    z = whiten(np.concatenate(errors, axis=1), np.concatenate(G, axis=1), cov, np.concatenate(var, axis=1))
    test = _tested(z, pf.dof, s, notes)
    cv_block = None
    if cv:
        cand = np.asarray(pf.free, bool)
        mm, deg = cross_validation(problem, cand, cand, fold_train(np.asarray(problem.data.mask), cv))
        extra = {} if deg is None else {"mean_deg": deg.mean, "rms_deg": deg.rms, "max_deg": deg.max}
        cv_block = CrossValidation(folds=int(cv), mean=mm.mean, rms=mm.rms, max=mm.max, **extra)
    return Verification(
        result=str(ref.file),
        dataset=str(ds.root),
        samples=np.asarray(s.sample),
        errors_mm=err,
        nominal_mm=nominal,
        predicted_mm=predicted,
        summary=summary,
        cv=cv_block,
        notes=tuple(notes),
        test=test,
        **({} if angles is None else dict(zip(("errors_deg", "nominal_deg", "predicted_deg"), angles))),
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
