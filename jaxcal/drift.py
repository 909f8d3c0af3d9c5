"""`jaxcal check RESULT CAPTURE`: has the set-up drifted since the calibration?

A short capture taken later (a few tracker samples at known configurations
$q_i$) is fitted against the calibrated model $\\hat x$ with only what can
drift free: the measuring device's pose, as a twist $\\varepsilon = (v, \\omega)$
with $T_{base,dev}' = T_{base,dev} \\exp(\\varepsilon)$ (the device moved by $v$,
in its own frame, and turned by $\\omega$), and optionally the joints' zero
offsets $\\delta q$:

$$ y_i = \\exp(-\\varepsilon)\\, \\big(\\hat y_i + Z_i\\, \\delta q\\big) + n_i, $$

$\\hat y_i$ the calibrated prediction, $Z_i = \\partial y_i / \\partial q$. Without drift
the residuals $y_i - \\hat y_i$ are the capture's noise plus the calibration's own
error, jointly Gaussian with covariance

$$ R = \\mathrm{diag}(s_i^2 I_3) + J \\Sigma J^T, $$

$s_i^2 = \\hat\\sigma^2 \\sigma_i^2$ the per-sample scatter the fit showed (as `jaxcal
verify` uses it), $J = \\partial \\hat y / \\partial x$ and $\\Sigma$ the calibration's
covariance. The drift $\\theta = (\\varepsilon, \\delta q)$ is estimated by
Levenberg-Marquardt on the residuals whitened by $R$, so that $\\hat\\theta \\sim N(\\theta,
C)$, $C = (A^T R^{-1} A)^{-1}$, $A = \\partial y / \\partial \\theta$, and the test is

$$ T = \\hat\\theta^T C^{-1} \\hat\\theta \\sim \\chi^2_k \\text{ without drift}, \\qquad
   \\text{drift detected when } T > \\chi^2_{k}(1 - \\alpha). $$

Against a drift $\\theta$ its power is $P(\\chi'^2_k(\\lambda) > \\chi^2_k(1-\\alpha))$,
$\\lambda = \\theta^T C^{-1} \\theta$ (non-central chi-square). The smallest device
translation detected with 95 % power along the worst direction is
$\\sqrt{\\lambda^* / \\mu_{min}}$, $\\mu_{min}$ the least eigenvalue of the translation
block of $C^{-1}$ and $\\lambda^*$ the non-centrality of 95 % power; likewise the
rotation. After the drift fit the whitened residuals' sum of squares is
$\\chi^2_{3S-k}$ when a rigid motion (and the offsets) explain the change: a large
value says something else changed (the robot, the point's mount).
Measured orientations join the rigid-fit check: `jaxcal._drift_orientation`.
"""

import importlib
import json
from collections.abc import Mapping
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from ._buckets import bucket, pad_log
from ._correction import ParameterLayout
from ._device import to_device
from ._drift_camera import CameraReference, camera_reference, drift_least_squares, pad_corners
from ._drift_camera import fit as fit_camera
from ._drift_orientation import orientation_residuals
from ._exported import stored_jit
from ._geometry import se3_exp
from ._lsq import normal_inverse
from ._npgeom import se3_exp as np_se3_exp
from ._pointfit import PointLayout, point_jacobian, predict, predict_rotation, rotation_jacobian
from ._reprojection import make_corner_data
from .errors import DatasetError
from .handeye_check import HandEyeCheckFit, fit_hand_eye_check
from .io.checks import calibration_reference, drift_check_json, read_calibration, read_hand_eye_reference
from .io.dataset import Dataset, load_dataset
from .io.handeye import HandEyeCapture
from .io.result import ESTIMATE_FILE, read_estimate
from .records_check import EXIT_DRIFT as EXIT_DRIFT
from .records_check import (
    CalibrationReference,
    Detectable,
    DriftCheck,
    DriftResidual,
    HandEyeReference,
    JointOffset,
)
from .stages._points import point_problem
from .vision import detect_frames


def _stats():
    """`scipy.stats`, imported when a test first needs it: `jaxcal plan` and `jaxcal
    calibrate` import this module and should not pay a second for it."""
    return importlib.import_module("scipy.stats")


#: The test's false-alarm probability, and the power the detectable change is quoted at.
ALPHA, POWER = 0.05, 0.95


@dataclass(frozen=True, eq=False)
class DriftReference:
    """What a calibration predicts for a check capture's configurations (device frame, m).

    - `y_hat` `(S, 3)`: the calibrated prediction; `Z` `(S, 3, joints)`: its derivative
      with respect to the joint angles; `R` `(3S, 3S)`: the residuals' covariance
      without drift (the capture's scatter plus the calibration's error).
    - with orientations, `R_hat` `(S, 3, 3)` the predicted ones, `Gz` `(S, 3, joints)` their
      turn per zero offset (point frame) and `rot_cov` `(S, 3, 3)` their error's covariance;
      None otherwise.
    """

    y_hat: np.ndarray
    Z: np.ndarray
    R: np.ndarray
    joint_names: tuple[str, ...]
    T_device_base: np.ndarray
    R_hat: np.ndarray | None = None
    Gz: np.ndarray | None = None
    rot_cov: np.ndarray | None = None


def as_reference(result, file="result.json") -> CalibrationReference:
    """`result` as a `CalibrationReference`: one already, or a `result.json` payload read from `file`."""
    return calibration_reference(result, file) if isinstance(result, Mapping) else result


def reference(
    result, q: np.ndarray, sigma: np.ndarray, sigma_rad: np.ndarray | None = None
) -> DriftReference:
    """The `DriftReference` of a stop-and-shoot result's point fit (a `CalibrationReference`, or
    its `result.json` payload) at configurations `q` `(S, joints)` measured with per-axis noise
    `sigma` `(S,)` (m) and, for orientations when the calibration fitted them, `sigma_rad` (rad)."""
    pf = as_reference(result).point_fit
    layout = PointLayout(ParameterLayout.of(pf.nominal, 1, fixed_name="T_device_base"), pf.terms)
    x = to_device(pf.x, np.float64)
    S = len(q)
    problem = point_problem(
        pf.nominal, layout, np.asarray(q, np.float64), np.zeros((S, 3)), np.ones(S), np.ones(S, bool),
        pf.T_device_base0, pf.T_flange_point0, (pf.masses, pf.coms),
    )  # fmt: skip
    J, y_hat = (np.asarray(a) for a in _REFERENCE(x, problem))  # (S, 3, n), (S, 3)
    Z = J[:, :, layout.base.index("zero")]
    Jf = J.reshape(3 * S, -1)
    scatter = pf.residual_variance_factor * np.repeat(np.asarray(sigma, np.float64) ** 2, 3)
    R = np.diag(scatter) + Jf @ pf.covariance @ Jf.T
    T_db = np.asarray(pf.T_device_base0) @ np_se3_exp(np.asarray(pf.x)[layout.base.index("cam")])
    ref = DriftReference(y_hat, Z, R, tuple(pf.nominal.joint_names), T_db)
    if not pf.orientation or sigma_rad is None:
        return ref
    R_hat, Gr = (np.asarray(a) for a in _ROTATIONS(x, problem))
    var = pf.residual_variance_factor * np.asarray(sigma_rad, np.float64) ** 2
    rot_cov = np.einsum("sai,ij,sbj->sab", Gr, pf.covariance, Gr) + var[:, None, None] * np.eye(3)
    return replace(ref, R_hat=R_hat, Gz=Gr[:, :, layout.base.index("zero")], rot_cov=rot_cov)


def _reference_arrays(x, problem):
    return point_jacobian(x, problem), predict(x, problem)


def _rotation_arrays(x, problem):
    return predict_rotation(x, problem), rotation_jacobian(x, problem)


#: `reference`'s model algebra, stored programs (a later `jaxcal check` reloads them).
_REFERENCE = stored_jit(_reference_arrays, "drift_reference")
_ROTATIONS = stored_jit(_rotation_arrays, "drift_rotations")


def _model(theta, y_hat, Z):
    y = y_hat + jnp.einsum("saj,j->sa", Z, theta[6:])
    T = jnp.linalg.inv(se3_exp(theta[:6]))
    return y @ T[:3, :3].T + T[:3, 3]


def fit_drift(y, y_hat, Z, W, *, offsets: bool):
    """Levenberg-Marquardt (`jaxcal._drift_camera.drift_least_squares`) on the whitened residuals $W (y - f(\\theta))$ ($W^T W = R^{-1}$).

    **Returns:** `(theta, C, T, rss)`: the drift (6, or 6 + joints with `offsets`),
    its covariance, the test statistic and the whitened residual sum of squares after it."""
    return _FIT_DRIFT[bool(offsets)](y, y_hat, Z, W)


def _fit_drift(y, y_hat, Z, W, *, offsets: bool):
    k = 6 + (Z.shape[2] if offsets else 0)
    Zk = Z if offsets else Z[:, :, :0]

    def res(theta):
        return W @ (y - _model(theta, y_hat, Zk)).reshape(-1)

    theta, info, r = drift_least_squares(res, k)
    C = normal_inverse(info)
    return theta, C, theta @ info @ theta, r @ r


#: `fit_drift`'s two programs (with and without the joint offsets), stored.
_FIT_DRIFT = {
    offsets: stored_jit(partial(_fit_drift, offsets=offsets), "fit_drift", static=(offsets,))
    for offsets in (False, True)
}


def whitening(R: np.ndarray) -> np.ndarray:
    """$W = L^{-1}$ with $R = L L^T$."""
    L = np.linalg.cholesky(R)
    return np.linalg.solve(L, np.eye(len(R)))


def power(lam, dof: int, alpha: float = ALPHA, dof_noise: int | None = None):
    """The test's power against a drift of non-centrality `lam`: non-central chi-square, or
    with `dof_noise` (the noise scale estimated on that many degrees of freedom) non-central F."""
    stats = _stats()
    if dof_noise is None:
        return stats.ncx2.sf(stats.chi2.ppf(1 - alpha, dof), dof, lam)
    x = stats.f.ppf(1 - alpha, dof, dof_noise)
    # SciPy's non-central F is wrong at a non-centrality of exactly zero: the central F there.
    return np.where(
        np.asarray(lam) > 0,
        stats.ncf.sf(x, dof, dof_noise, np.maximum(lam, 1e-300)),
        stats.f.sf(x, dof, dof_noise),
    )


def threshold(dof: int, alpha: float = ALPHA, dof_noise: int | None = None) -> float:
    """The level-`alpha` threshold of $T$: $\\chi^2_{k}(1 - \\alpha)$, or $k F_{k, n}(1 - \\alpha)$."""
    stats = _stats()
    if dof_noise is None:
        return float(stats.chi2.ppf(1 - alpha, dof))
    return float(dof * stats.f.ppf(1 - alpha, dof, dof_noise))


def p_value(T: float, dof: int, dof_noise: int | None = None) -> float:
    stats = _stats()
    return float(stats.chi2.sf(T, dof) if dof_noise is None else stats.f.sf(T / dof, dof, dof_noise))


def noncentrality_for_power(
    dof: int, p: float = POWER, alpha: float = ALPHA, dof_noise: int | None = None
) -> float:
    """$\\lambda^*$ with `power(lambda*) = p`."""
    return float(
        importlib.import_module("scipy.optimize").brentq(
            lambda lam: power(lam, dof, alpha, dof_noise) - p, 1e-9, 1e4
        )
    )


def detectable(
    C: np.ndarray, alpha: float = ALPHA, p: float = POWER, dof_noise: int | None = None
) -> Detectable:
    """The smallest translation (mm) and rotation (deg) detected with power `p` along
    their worst and best directions (see the module docstring)."""
    k = len(C)
    lam = noncentrality_for_power(k, p, alpha, dof_noise)
    P = np.linalg.inv(C)
    mu_t = np.linalg.eigvalsh(P[:3, :3])
    mu_r = np.linalg.eigvalsh(P[3:6, 3:6])
    return Detectable(
        noncentrality=lam,
        translation_mm_worst=float(1e3 * np.sqrt(lam / mu_t[0])),
        translation_mm_best=float(1e3 * np.sqrt(lam / mu_t[-1])),
        rotation_deg_worst=float(np.degrees(np.sqrt(lam / mu_r[0]))),
        rotation_deg_best=float(np.degrees(np.sqrt(lam / mu_r[-1]))),
    )


def _size_and_std(v: np.ndarray, C: np.ndarray) -> tuple[float, float]:
    """$|v|$ and its standard deviation along $v$ (first order; the largest std at $v = 0$)."""
    n = float(np.linalg.norm(v))
    if n == 0:
        return 0.0, float(np.sqrt(np.linalg.eigvalsh(C)[-1]))
    u = v / n
    return n, float(np.sqrt(u @ C @ u))


def check_samples(
    ref: DriftReference, y: np.ndarray, *, joint_offsets: bool = False, names=("", ""), R=None
) -> DriftCheck:
    """The drift check of measured points `y` `(S, 3)` (device frame, m) against `ref`, and of
    the measured orientations `R` `(S, 3, 3)` when given and `ref` predicts them."""
    S = len(y)
    k = 6 + (len(ref.joint_names) if joint_offsets else 0)
    if 3 * S <= k:
        raise ValueError(f"a check of {k} drift unknowns needs more than {k // 3} samples, got {S}")
    W = whitening(ref.R)
    theta, C, T, rss = (
        np.asarray(a)
        for a in fit_drift(
            to_device(y, np.float64), ref.y_hat, ref.Z, to_device(W, np.float64), offsets=joint_offsets
        )
    )
    T_base_dev = np.linalg.inv(ref.T_device_base) @ np_se3_exp(theta[:6])
    c = verdict(
        theta, C, float(T), float(rss), 3 * S - k, samples=S, joint_names=ref.joint_names,
        T_now=np.linalg.inv(T_base_dev), names=names,
    )  # fmt: skip
    return c if R is None or ref.R_hat is None else _with_orientations(c, ref, np.asarray(R, np.float64))


def _with_orientations(c: DriftCheck, ref: DriftReference, R: np.ndarray) -> DriftCheck:
    """`c` with the orientations' residuals (see the module docstring)."""
    angles, rss = orientation_residuals(ref.R_hat, ref.Gz, ref.rot_cov, np.asarray(c.theta), R)
    dof, p = 3 * len(R), float(_stats().chi2.sf(rss, 3 * len(R)))
    residual = replace(c.residual, rotation_sum_of_squares=rss, rotation_dof=dof, rotation_p_value=p)
    c = replace(c, residual=residual, rotation_residual_deg=angles)
    if residual.fits_rigidly or not c.message.startswith(("no drift", f"the {c.what} moved")):
        return c
    return replace(
        c,
        message=f"{c.message}; but the orientations do not fit it (chi2 {rss:.0f} on {dof} dof, p = {p:.2g}; "
        f"{angles.mean:.3f} deg mean): the point's mount turned, or the orientations are of another frame",
        advice="check the point's mount on its link and the orientations' frame; if the mount changed, calibrate again",
    )


def verdict(
    theta: np.ndarray,
    C: np.ndarray,
    T: float,
    rss: float,
    dof_r: int,
    *,
    samples: int,
    joint_names,
    T_now: np.ndarray,
    names=("", ""),
    what: str = "device",
    frame: str = "T_device_base",
    dof_noise: int | None = None,
) -> DriftCheck:
    """The test of a fitted drift `theta` `(6[+joints])` with covariance `C`, statistic
    `T` and whitened residual sum of squares `rss` on `dof_r` degrees of freedom: the
    `DriftCheck` (`what` moved: its `frame` now is `T_now`). Shared by the tracker and the
    camera checks; `dof_noise`: the degrees of freedom the noise scale was estimated on
    (the test then uses Fisher's F, see `jaxcal._drift_camera`), None when it is known."""
    k = len(theta)
    joint_offsets = k > 6
    thr = threshold(k, ALPHA, dof_noise)
    detected = T > thr
    tr, rot = _size_and_std(theta[:3], C[:3, :3]), _size_and_std(theta[3:6], C[3:6, 3:6])
    tr_mm, rot_deg = (1e3 * tr[0], 1e3 * tr[1]), (float(np.degrees(rot[0])), float(np.degrees(rot[1])))
    offs = None
    if joint_offsets:
        sd = np.sqrt(np.diag(C)[6:])
        offs = tuple(
            JointOffset(j, float(np.degrees(e)), float(np.degrees(s)))
            for j, e, s in zip(joint_names, theta[6:], sd)
        )
    det = detectable(C, dof_noise=dof_noise)
    residual = DriftResidual(sum_of_squares=rss, dof=dof_r, p_value=float(_stats().chi2.sf(rss, dof_r)))
    law = f"chi2 on {k} dof" if dof_noise is None else f"{k} F({k}, {dof_noise})"
    stat = f"T {T:.1f}, threshold {thr:.1f} ({law}), p = {p_value(T, k, dof_noise):.3g}"
    if detected:
        message = f"the {what} moved by {tr_mm[0]:.3f} +- {tr_mm[1]:.3f} mm, {rot_deg[0]:.4f} +- {rot_deg[1]:.4f} deg ({stat})"
        if offs:
            big = [o for o in offs if abs(o.estimate_deg) > 2 * o.std_deg]
            if big:
                message += "; joint offsets changed: " + ", ".join(
                    f"{o.joint} {o.estimate_deg:+.4f} +- {o.std_deg:.4f} deg" for o in big
                )
        advice = (
            f"re-register the {what} (the JSON's {frame}_now is the calibrated pose moved by the drift) "
            "or calibrate again; if the robot itself changed (joint offsets, a crash), calibrate again"
        )
    else:
        message = (
            f"no drift detected ({stat}); a change of {det.translation_mm_worst:.3f} mm (worst direction; "
            f"{det.translation_mm_best:.3f} mm best) or {det.rotation_deg_worst:.4f} deg would have been "
            f"detected with {100 * POWER:.0f} % power at {100 * ALPHA:.0f} % false alarms"
        )
        advice = "nothing to do; for a finer check, measure more poses spread over the workspace"
    if not residual.fits_rigidly:
        # The headline is the mismatch: a "move" fitted to data no rigid move explains is no
        # move of the device (a clock or timestamps off, another robot or mount, a bumped arm).
        mount = "point" if what == "device" else "target"
        message = (
            f"the capture does not fit the calibration with the {what} moved rigidly (chi2 {rss:.0f} on "
            f"{dof_r} dof, p = {residual.p_value:.2g}): more than the {what}'s pose changed, or the capture "
            f"does not match the calibration; the best rigid move would be {tr_mm[0]:.3f} mm, "
            f"{rot_deg[0]:.4f} deg ({stat})"
        )
        advice = (
            f"check that the capture matches the calibration: the same robot and {mount} mount, and (with "
            "moving joints) its timestamps against the encoder log (`jaxcal inspect CAPTURE` shows the clocks' "
            "overlap); if it does, something else changed (the robot, the mount, the noise): calibrate again"
        )
    return DriftCheck(
        result=names[0], capture=names[1], samples=samples, theta=theta, cov=C, statistic=T, dof=k, threshold=thr,
        p_value=p_value(T, k, dof_noise), detected=bool(detected), translation_mm=tr_mm, rotation_deg=rot_deg,
        joint_offsets_deg=offs, detectable=det, residual=residual, T_device_base=np.asarray(T_now),
        message=message, advice=advice, alpha=ALPHA, what=what, frame=frame, dof_noise=dof_noise,
    )  # fmt: skip


def _matching_capture(ref: CalibrationReference, ds: Dataset) -> None:
    """Refuse a capture of another robot, device or measured point, naming the file."""
    meta, file = ds.root / "metadata.json", ref.file
    if ds.samples is None:
        raise DatasetError(
            f"{meta}: a camera capture, but {file} calibrated {ref.device or 'a device'!r} from "
            "tracker samples: check it with samples of the same device"
        )
    names = list(ref.point_fit.nominal.joint_names)
    if tuple(ds.joint_names) != tuple(names):
        raise DatasetError(
            f"{meta}: robot.joints {list(ds.joint_names)} differ from the calibrated robot's {names} ({file}): "
            "another robot?"
        )
    if ref.device not in (None, ds.device.name):
        raise DatasetError(
            f"{meta}: device {ds.device.name!r}, but {file} calibrated device {ref.device!r}: another device"
        )
    if ref.targets and ds.device.point not in ref.targets:
        raise DatasetError(
            f"{meta}: measured point {ds.device.point!r}, but {file} calibrated {list(ref.targets)}: another target"
        )
    if ds.samples.q is None:
        raise DatasetError(f"{ds.root / ds.device.file}: a check needs every sample's joint positions")


#: A capture's nominal joint origins this far (m) from the calibrated robot's: another robot.
ROBOT_TOLERANCE_M = 0.01


def _robot_gap(a, b) -> float:
    """The largest distance between two models' joint origins (m); inf for other joint types."""
    if tuple(a.joint_types) != tuple(b.joint_types):
        return float("inf")
    d = np.asarray(a.T_parent_joint)[:, :3, 3] - np.asarray(b.T_parent_joint)[:, :3, 3]
    return float(np.max(np.linalg.norm(d, axis=1)))


def _matching_camera(ref: CalibrationReference, ds: Dataset, est) -> tuple:
    """Refuse a capture of another robot, camera or target, naming the file. **Returns:**
    `(camera, targets)`: the capture's `CameraInfo` and the `TargetInfo`s the result calibrated."""
    meta, file = ds.root / "metadata.json", ref.file
    if ds.samples is not None:
        raise DatasetError(
            f"{meta}: tracker samples, but {file} calibrated camera {ref.camera!r}: check it with images"
        )
    names = tuple(est.nominal.joint_names)
    if tuple(ds.joint_names) != names:
        raise DatasetError(
            f"{meta}: robot.joints {list(ds.joint_names)} differ from the calibrated robot's {list(names)} "
            f"({file}): another robot?"
        )
    gap = _robot_gap(ds.load_model(), est.nominal)
    if gap > ROBOT_TOLERANCE_M:
        raise DatasetError(
            f"{ds.robot_urdf}: its joint origins are up to {1e3 * gap:.0f} mm from those of the robot {file} "
            "calibrated: another robot?"
        )
    try:
        camera = ds.camera(ref.camera)
    except KeyError:
        raise DatasetError(
            f"{meta}: no camera {ref.camera!r} ({file} calibrated it; the capture has "
            f"{[c.name for c in ds.cameras]}): another camera"
        ) from None
    K_cal = np.asarray(result_intrinsics(ref)[0])
    if camera.K is not None and not np.allclose(camera.K, K_cal, rtol=1e-3, atol=0.05):
        raise DatasetError(
            f"{meta}: camera {camera.name!r} intrinsics K differ from those {file} calibrated with: another camera"
        )
    cal = _calibration_dataset(ref)
    sizes = {} if cal is None else {c.name: (c.width, c.height) for c in cal.cameras}
    size = sizes.get(camera.name)
    cx, cy = K_cal[0, 2], K_cal[1, 2]
    off_centre = (
        abs(cx - (camera.width - 1) / 2) > 0.25 * camera.width
        or abs(cy - (camera.height - 1) / 2) > 0.25 * camera.height
    )
    if (size is not None and size != (camera.width, camera.height)) or off_centre:
        raise DatasetError(
            f"{meta}: camera {camera.name!r} is {camera.width}x{camera.height}, but {file} calibrated "
            f"{'x'.join(map(str, size)) if size else f'one with its principal point at ({cx:.1f}, {cy:.1f})'}: "
            "another camera (or resolution)"
        )
    wanted = [ref.board] if est.layout.eye_in_hand else list(ref.targets)
    by_name = {t.name: t for t in ds.targets}
    missing = [t for t in wanted if t not in by_name]
    if missing or not wanted:
        raise DatasetError(
            f"{meta}: targets {sorted(by_name)}, but {file} calibrated {wanted}: another target"
        )
    specs = {} if cal is None else {t.name: t.spec.to_dict() for t in cal.targets}
    for t in wanted:
        if t in specs and by_name[t].spec.to_dict() != specs[t]:
            raise DatasetError(f"{meta}: target {t!r} is not the one {file} calibrated (its pattern differs)")
    if ds.encoder_t is None:
        raise DatasetError(f"{meta}: a camera check needs the encoder log (every image's joint positions)")
    return camera, [by_name[t] for t in wanted]


def _calibration_dataset(ref: CalibrationReference) -> Dataset | None:
    """The calibration's dataset (its cameras' sizes, its targets' patterns), or None when it cannot be read."""
    if ref.dataset is None:
        return None
    try:
        return load_dataset(ref.dataset)
    except (DatasetError, OSError, KeyError, ValueError):
        return None


def result_intrinsics(result) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """`(K, dist, K0, dist0)` of a camera result (a `CalibrationReference`, or its `result.json`
    payload): the calibrated intrinsics and the start the refinement's increments are relative to."""
    ref = as_reference(result)
    i = ref.intrinsics
    if i is None or i.K is None or i.distortion is None:
        raise DatasetError(f"{ref.file}: no camera intrinsics (K, distortion)")
    K, d = np.asarray(i.K, np.float64), np.zeros(5)
    dist = np.asarray(i.distortion, np.float64).ravel()
    d[: min(5, len(dist))] = dist[:5]
    K0, d0 = np.asarray(i.K if i.K_start is None else i.K_start, np.float64), np.zeros(5)
    ds = np.asarray(i.distortion if i.distortion_start is None else i.distortion_start, np.float64).ravel()
    d0[: min(5, len(ds))] = ds[:5]
    return K, d, K0, d0


def camera_corners(ds: Dataset, camera, targets, mount_index, K, dist, *, workers=None):
    """Detect `targets` in `camera`'s images of `ds`: the `CornerData` (joint positions
    from the encoder log at the images' stamps) and the number of corners; `mount_index`:
    target name -> its mount in the estimate."""
    rows = np.flatnonzero(ds.frames.camera == camera.name)
    if rows.size == 0:
        raise DatasetError(f"{ds.root / 'frames.csv'}: no images of camera {camera.name!r}")
    paths = [ds.image_path(int(i)) for i in rows]
    dets = detect_frames(paths, [t.spec for t in targets], K=K, dist=dist, workers=workers, progress=False)
    pts, pix, tgt, frm, tc = [], [], [], [], []
    for i, det in zip(rows, dets):
        for t in targets:
            d = det.get(t.name)
            if d is None or len(d.ids) < 4:
                continue
            pts.append(np.asarray(t.spec.points(), np.float64)[d.ids])
            pix.append(d.pixels)
            tgt.append(mount_index[t.name])
            frm.append(int(i))
            tc.append(float(ds.frames.timestamp[i]))
    if len(pts) < 2:
        raise DatasetError(f"{ds.root}: the targets were found in {len(pts)} image(s): a check needs a few")
    return pts, pix, np.array(tgt), np.array(frm), np.array(tc)


@dataclass(frozen=True, eq=False)
class CameraCapture:
    """A camera check capture read against a camera result: the result (`reference`, its
    `file`, its `Estimate`), the capture `ds` and its detected corners: per view the
    target points `(n, 3)`, pixels `(n, 2)`, and `(views,)` mount index, dataset row, stamp;
    `max_points`: the most corners a view can have (the targets' patterns)."""

    reference: CalibrationReference
    file: Path
    est: object
    ds: Dataset
    points: list
    pixels: list
    target: np.ndarray
    row: np.ndarray
    t_cam: np.ndarray
    max_points: int


def camera_capture(result, file: Path, ds: Dataset, *, workers=None) -> CameraCapture:
    """Check that `ds` matches the camera result (a `CalibrationReference`, or the `result.json`
    payload read from `file`) and detect its corners."""
    ref = as_reference(result, file)
    path = file.parent / ESTIMATE_FILE
    if not path.is_file():
        raise DatasetError(
            f"{path}: missing: the check of a camera calibration needs the covariance jaxcal calibrate "
            "writes there (since this version): calibrate the dataset again"
        )
    est = read_estimate(path)
    if est.layout.angles or ref.sigma_px is None:
        raise DatasetError(f"{file}: the check needs a refined calibration with an encoder log")
    camera, targets = _matching_camera(ref, ds, est)
    K, dist, _, _ = result_intrinsics(ref)
    mounts = {t.name: (0 if est.layout.eye_in_hand else est.mount_names.index(t.name)) for t in targets}
    corners = camera_corners(ds, camera, targets, mounts, K, dist, workers=workers)
    return CameraCapture(ref, file, est, ds, *corners, max(len(t.spec.points()) for t in targets))


def camera_check_reference(cap: CameraCapture, pixels: list | None = None) -> tuple[CameraReference, int]:
    """The `CameraReference` of a `CameraCapture` (its views inside the encoder log, padded so
    that check captures share the compiled fit) and the number of views kept; `pixels`: per
    view other detections in place of the capture's (a benchmark's shifted copies)."""
    ref, est, ds = cap.reference, cap.est, cap.ds
    pts, tgt, frm, tc = cap.points, cap.target, cap.row, cap.t_cam
    pix = cap.pixels if pixels is None else pixels
    _, _, K0, dist0 = result_intrinsics(ref)
    enc_q = np.asarray(ds.encoder_motor, np.float64) / np.asarray(est.nominal.reduction_ratio)
    offset = ds.clock_offset_s if ds.clock_offset_s is not None else ref.clock_offset_s
    t_ctrl = (tc - offset) / (1.0 + 1e-6 * ds.clock_drift_ppm)
    inside = (t_ctrl >= ds.encoder_t[0]) & (t_ctrl <= ds.encoder_t[-1]) & ~ds.in_encoder_glitch(t_ctrl)
    keep = np.flatnonzero(inside)
    if len(keep) < 2:
        raise DatasetError(f"{ds.root}: {len(keep)} image(s) inside the encoder log: a check needs a few")
    data = make_corner_data(
        [pts[i] for i in keep], [pix[i] for i in keep], tgt[keep], frm[keep], tc[keep],
        *pad_log(ds.encoder_t, enc_q, bucket(len(ds.encoder_t))), ds.clock_drift_ppm, views=bucket(len(keep)),
    )  # fmt: skip
    data = pad_corners(data, cap.max_points)
    corners = int(sum(len(pts[i]) for i in keep))
    sigma = ref.sigma_px
    return camera_reference(est, data, K0, dist0, offset, sigma, corners), len(keep)


def check_camera(
    cap: CameraCapture, *, joint_offsets: bool = False, pixels: list | None = None
) -> DriftCheck:
    """The drift check of a `CameraCapture` (`jaxcal._drift_camera`); `pixels`: per view
    other detections in place of the capture's (a benchmark's shifted copies)."""
    est, ds = cap.est, cap.ds
    ref, views = camera_check_reference(cap, pixels)
    corners = ref.corners
    theta, C, T, rss, nu = fit_camera(ref, joint_offsets=joint_offsets)
    dof_r = 2 * corners - len(theta)
    eps = np_se3_exp(theta[:6])
    if est.layout.eye_in_hand:
        T_now, frame = ref.T_fixed @ eps, "T_flange_cam"
    else:
        T_now, frame = np.linalg.inv(eps) @ ref.T_fixed, "T_cam_base"
    c = verdict(
        theta, C, T, rss, dof_r, samples=views, joint_names=ref.joint_names,
        T_now=T_now, names=(str(cap.file), str(ds.root)), what="camera", frame=frame, dof_noise=dof_r,
    )  # fmt: skip
    if others := [
        cam.name for cam in ds.cameras if cam.name != cap.reference.camera
    ]:  # said, not skipped unsaid
        c = replace(c, message=f"{c.message}; camera {cap.reference.camera!r} only: {others} not tested")
    return _noise_note(c, nu, ref.factor)


#: A check's corner noise variance this many times the calibration's: something other than a move changed.
NOISE_ALARM = 4.0


def _noise_note(c: DriftCheck, nu: float, factor: float) -> DriftCheck:
    """`c` with the check's estimated noise variance factor in its residual block (and advice when large)."""
    c = replace(
        c, residual=replace(c.residual, noise_variance_factor=nu, calibration_covariance_factor=factor)
    )
    if nu > NOISE_ALARM:
        return replace(
            c,
            advice=(c.advice if c.detected else "no move seen, but it may hide one")
            + f"; the check images' corners scatter {np.sqrt(nu):.1f}x the calibration's noise: "
            "something else changed (focus, light, the target, the robot): look at the images, or calibrate again",
        )
    return c


def hand_eye_verdict(f: HandEyeCheckFit, names=("", "")) -> DriftCheck:
    """The test of a hand-eye drift fit (`jaxcal.handeye_check`; its noise and per-view
    components estimated: Fisher's F on `f.dof_noise` degrees of freedom)."""
    c = verdict(
        f.theta, f.C, f.T, f.rss, f.dof, samples=f.views, joint_names=(), T_now=f.T_now, names=names,
        what="camera", frame=f.frame, dof_noise=f.dof_noise,
    )  # fmt: skip
    view = replace(
        c.residual, view_sigma_mm=1e3 * f.view_sigma[0], view_sigma_deg=float(np.degrees(f.view_sigma[1]))
    )
    return _noise_note(replace(c, residual=view), f.nu, 1.0)


def check_hand_eye(ref: HandEyeReference, capture, *, workers=None) -> DriftCheck:
    """The drift check of a `jaxcal handeye` result (`jaxcal.io.checks.read_hand_eye_reference`)
    against a later capture of the same kind (`jaxcal.handeye_check`): the camera's pose the only unknown."""
    root = capture.root if isinstance(capture, HandEyeCapture) else capture  # a Path's `.root` is "/"
    return hand_eye_verdict(fit_hand_eye_check(ref, capture, workers=workers), (str(ref.file), str(root)))


def check(result, capture, *, joint_offsets: bool = False, workers=None) -> DriftCheck:
    """Check the calibration `result` (a directory or its `result.json`) against a later
    `capture` (a path or a loaded `Dataset`): tracker samples against a stop-and-shoot
    tracker result, images against a camera result (its `estimate.npz`), a hand-eye capture
    against a `jaxcal handeye` result (`jaxcal.handeye_check`); `joint_offsets`: also free the
    joints' zero offsets (not for hand-eye results: the robot's poses are given); `workers`:
    the image detection's threads. Raises `DatasetError` naming the file when the capture is
    not one of the calibrated robot, device or camera and target."""
    hand_eye = read_hand_eye_reference(result)
    if hand_eye is not None:
        if joint_offsets:
            raise DatasetError(
                f"{hand_eye.file}: a hand-eye result has no joint offsets to free (--joint-offsets)"
            )
        return check_hand_eye(hand_eye, capture, workers=workers)
    cal = read_calibration(result)
    file = cal.file
    ds = capture if isinstance(capture, Dataset) else load_dataset(capture)
    if cal.point_fit is None:
        if cal.tracker:
            raise DatasetError(
                f"{file}: jaxcal check handles stop-and-shoot tracker results ('point_fit') and camera results; "
                f"this one is {cal.capture or 'another kind'!r}"
            )
        return check_camera(camera_capture(cal, file, ds, workers=workers), joint_offsets=joint_offsets)
    _matching_capture(cal, ds)
    s = ds.samples
    ref = reference(cal, s.q, s.sigma_m, s.sigma_rad)
    return check_samples(
        ref, np.asarray(s.position, np.float64), joint_offsets=joint_offsets, names=(str(file), str(ds.root)),
        R=s.orientation,
    )  # fmt: skip


def drift_json(c: DriftCheck) -> str:
    """The `jaxcal check --json` file's text (`jaxcal.io.checks.drift_check_json`)."""
    return json.dumps(drift_check_json(c), indent=1)
