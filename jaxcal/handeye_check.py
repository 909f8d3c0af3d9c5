"""`jaxcal check` of a hand-eye result (`jaxcal handeye`): has the camera moved since?

A short later capture of the same kind (the capture format of `jaxcal.io.handeye`: a few
images of the same target at recorded robot poses, same camera) is detected as `jaxcal
handeye` detects it (PnP with the distortion modelled, symmetric targets resolved, the robot
against camera rotation-angle check, corners undistorted) and fitted against the result with
only the camera's pose free (`jaxcal._drift_handeye`): eye-to-hand its pose in the base
frame, eye-in-hand on the flange. `jaxcal.drift.check` turns the fit into the verdict the
other checks give.
"""

from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np

from ._drift_handeye import HandEyeCheckData, covariance_terms, fit_handeye_drift, variance_components
from ._geometry import se3_exp
from ._handeye.assess import MAX_ROBOT_SIGMA_DEG, MAX_ROBOT_SIGMA_M
from ._lsq import larger_covariance_np as larger_covariance
from .errors import DatasetError
from .io.checks import is_hand_eye_result as is_hand_eye_result
from .io.checks import read_hand_eye_reference
from .io.handeye import HandEyeCapture, load_hand_eye_capture
from .records_check import HandEyeCameraReference, HandEyeReference
from .vision import detect_frames, hand_eye_from_detections

#: Intrinsics closer than this to the calibrated ones are the same camera's (K: relative, px).
K_RTOL, K_ATOL = 1e-3, 0.05


@dataclass(frozen=True, eq=False)
class HandEyeCheckFit:
    """The drift fit of a hand-eye check capture: `theta` (6: the camera's twist, m and rad),
    its covariance `C`, the statistic `T`, the whitened residual sum of squares `rss` on
    `dof` degrees of freedom, `views` used; `T_now` the camera's pose moved by the drift,
    named `frame` (`T_base_cam` or `T_ee_cam`); `camera`: its name; `nu`: the check's corner
    noise variance in units of the calibration's, `view_sigma`: each view's coherent pose error
    (m, rad per axis), both estimated (`jaxcal._drift_handeye.variance_components`), on
    `dof_noise` degrees of freedom."""

    theta: np.ndarray
    C: np.ndarray
    T: float
    rss: float
    dof: int
    views: int
    T_now: np.ndarray
    frame: str
    camera: str
    nu: float = 1.0
    view_sigma: tuple[float, float] = (0.0, 0.0)
    dof_noise: int | None = None


def _refuse(cond: bool, message: str) -> None:
    if cond:
        raise DatasetError(message)


def _matching(ref: HandEyeReference, cap: HandEyeCapture) -> HandEyeCameraReference:
    """Refuse a check capture of another arrangement, camera (name, size, intrinsics) or target,
    naming the field. **Returns:** the calibrated camera."""
    meta, file = cap.root / "handeye.json", ref.file
    _refuse(
        cap.arrangement != ref.arrangement,
        f"{meta}: arrangement {cap.arrangement!r}, but {file} calibrated {ref.arrangement!r}",
    )
    names = [c.name for c in cap.cameras]
    _refuse(
        len(cap.cameras) != 1,
        f"{meta}: cameras {names}: a check fits one camera at a time (give a capture of one of "
        f"{sorted(ref.camera_names)})",
    )
    cam = cap.cameras[0]
    entry = ref.camera(cam.name)
    _refuse(
        entry is None,
        f"{meta}: camera {cam.name!r}, but {file} calibrated {sorted(ref.camera_names)}: another camera",
    )
    _refuse(
        entry.covariance is None,
        f"{file}: written before jaxcal check could read hand-eye results (no cameras.{cam.name}.check): "
        "run jaxcal handeye on the calibration capture again",
    )
    size = (entry.width, entry.height)
    _refuse(
        (cam.width, cam.height) != size,
        f"{meta}: cameras[0] ({cam.name!r}) is {cam.width}x{cam.height}, but {file} calibrated it at "
        f"{size[0]}x{size[1]}: another camera (or resolution)",
    )
    if cam.K is not None:
        _refuse(
            not np.allclose(cam.K, entry.K, rtol=K_RTOL, atol=K_ATOL),
            f"{meta}: cameras[0].K of {cam.name!r} differs from the K {file} calibrated with: another camera",
        )
        d_cal = np.zeros(14)
        d_cal[: len(entry.distortion)] = entry.distortion
        d = np.zeros(14)
        d[: len(cam.dist)] = np.asarray(cam.dist, np.float64).ravel()
        _refuse(
            not np.allclose(d, d_cal, rtol=1e-3, atol=1e-6),
            f"{meta}: cameras[0].distortion of {cam.name!r} differs from the one {file} calibrated with: another "
            "camera (or lens)",
        )
    calibrated = ref.target.to_dict()
    _refuse(
        cap.target.to_dict() != calibrated,
        f"{meta}: target {cap.target.to_dict()} differs from the {calibrated} {file} calibrated: another target",
    )
    return entry


def check_data(
    ref: HandEyeReference, capture, *, workers=None
) -> tuple[HandEyeCheckData, HandEyeCameraReference, int]:
    """Read and detect a hand-eye check capture against the result `ref`: the `HandEyeCheckData`,
    the calibrated camera, and the number of views that showed the target."""
    cap = capture if isinstance(capture, HandEyeCapture) else load_hand_eye_capture(capture)
    entry = _matching(ref, cap)
    name, K, dist = entry.name, entry.K, entry.distortion
    dets = detect_frames(
        list(cap.images[0]), [cap.target], K=K, dist=dist, workers=workers, progress=False, pool="thread"
    )
    seen = [d for d in dets if cap.target.name in d]
    _refuse(
        len(seen) < 2,
        f"{cap.root}: the target was found in {len(seen)} image(s) of camera {name!r}: a check needs a few",
    )
    obs = hand_eye_from_detections(
        dets,
        cap.target,
        cap.T_base_ee,
        K,
        dist,
        eye_in_hand=cap.eye_in_hand,
        sigma_px=1.0,
        frame_names=cap.frames,
        pad=False,
    )
    d = obs.data
    data = HandEyeCheckData(
        T_base_ee=jnp.asarray(d.T_base_ee),
        pixels=jnp.nan_to_num(jnp.asarray(d.pixels[0])),
        mask=jnp.asarray(d.mask[0]),
        K=jnp.asarray(K),
        board_points=jnp.asarray(d.board_points),
        eye_in_hand=jnp.asarray(cap.eye_in_hand),
    )
    return data, entry, len(seen)


def robot_sigma(ref: HandEyeReference) -> np.ndarray:
    """The robot pose noise the calibration used (or estimated), `(6,)` m and rad; zero for exact poses."""
    if ref.robot_noise is None:
        return np.zeros(6)
    mm, deg = ref.robot_noise
    return np.r_[np.full(3, 1e-3 * mm), np.full(3, np.radians(deg))]


def fit_check(
    data: HandEyeCheckData,
    X,
    Y,
    cov,
    robot_sigma,
    sigma_px: float,
    *,
    eye_in_hand: bool,
    camera: str = "",
    views: int | None = None,
) -> HandEyeCheckFit:
    """The drift fit of `data` against the calibrated `X` ($T_{cam,robot}$) and `Y`
    ($T_{robot,target}$) with covariance `cov` `(12, 12)`, robot pose noise `robot_sigma` `(6,)`
    (m, rad) and corner noise `sigma_px` (see `jaxcal._drift_handeye`)."""
    corners = int(np.asarray(data.mask).sum())
    views = int(np.asarray(data.mask).any(-1).sum()) if views is None else views
    X, Y = jnp.asarray(X, jnp.float64), jnp.asarray(Y, jnp.float64)
    terms = covariance_terms(X, Y, jnp.asarray(cov, jnp.float64), jnp.asarray(robot_sigma, jnp.float64), data)
    R, s = variance_components(terms, sigma_px)
    theta, C, T, rss = (np.asarray(a) for a in fit_handeye_drift(X, Y, R, data))
    nu, view = float(s[0]) / sigma_px**2, (float(np.sqrt(s[1])), float(np.sqrt(s[2])))
    T_now = np.linalg.inv(np.asarray(X)) @ np.asarray(se3_exp(jnp.asarray(theta)))
    frame = "T_ee_cam" if eye_in_hand else "T_base_cam"
    # The per-view components rest on the views' 6 (views - 1) redundant pose coordinates: the F
    # test's denominator degrees of freedom (the corners' 2 m - 6 are many more).
    return HandEyeCheckFit(
        theta,
        C,
        float(T),
        float(rss),
        2 * corners - 6,
        views,
        np.asarray(T_now),
        frame,
        camera,
        nu,
        view,
        6 * (views - 1),
    )


def fit_hand_eye_check(ref: HandEyeReference, capture, *, workers=None) -> HandEyeCheckFit:
    """The drift fit of a hand-eye check `capture` (a directory or a `HandEyeCapture`) against the
    result `ref` (`read_hand_eye_result`); raises `DatasetError` naming the field when they do not match."""
    data, entry, views = check_data(ref, capture, workers=workers)
    fit = fit_check(
        data,
        entry.T_cam_robot,
        ref.T_robot_target,
        larger_covariance(entry.covariance, entry.covariance_frames),
        robot_sigma(ref),
        ref.sigma_px,
        eye_in_hand=ref.eye_in_hand,
        camera=entry.name,
        views=views,
    )
    root = capture.root if isinstance(capture, HandEyeCapture) else capture
    return _judgeable(fit, root)


#: What the poses should have been checked for when a check capture fits no robot's poses (as
#: `jaxcal handeye` says it of a calibration capture).
MISREAD = (
    "the poses are not these images' as read: check the arrangement, that the poses are the flange in "
    "the base frame and not inverted, the quaternion component order, the rotation and translation "
    "units (`jaxcal handeye` on this capture names a misreading that fits)"
)


def _judgeable(fit: HandEyeCheckFit, root) -> HandEyeCheckFit:
    """`fit`, or a `DatasetError` naming the capture where no drift can be judged from it: the fit
    did not converge, or each view's pose error it needs is beyond any robot's (a misread pose
    file, whose "move" of the camera would be a confident wrong answer)."""
    if not (np.isfinite(fit.theta).all() and np.isfinite(fit.C).all() and np.isfinite(fit.T)):
        raise DatasetError(f"{root}: the camera's drift could not be fitted to this capture: {MISREAD}")
    mm, deg = 1e3 * fit.view_sigma[0], float(np.degrees(fit.view_sigma[1]))
    if mm > 1e3 * MAX_ROBOT_SIGMA_M or deg > MAX_ROBOT_SIGMA_DEG:
        raise DatasetError(
            f"{root}: its robot poses and images fit the calibration only with each view's pose {mm:.3g} mm / "
            f"{deg:.3g} deg off (limits {1e3 * MAX_ROBOT_SIGMA_M:g} mm, {MAX_ROBOT_SIGMA_DEG:g} deg, any robot's): "
            + MISREAD
        )
    return fit


def read_hand_eye_result(path) -> HandEyeReference | None:
    """The `HandEyeReference` when `path` (a result directory or its `result.json`) is a `jaxcal
    handeye` result, else None (a calibration result, or nothing readable: `jaxcal.io.checks.read_calibration`
    says why)."""
    return read_hand_eye_reference(path)
