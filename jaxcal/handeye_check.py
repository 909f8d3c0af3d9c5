"""`jaxcal check` of a hand-eye result (`jaxcal handeye`): has the camera moved since?

A short later capture of the same kind (the capture format of `jaxcal.io.handeye`: a few
images of the same target at recorded robot poses, same camera) is detected as `jaxcal
handeye` detects it (PnP with the distortion modelled, symmetric targets resolved, the robot
against camera rotation-angle check, corners undistorted) and fitted against the result with
only the camera's pose free (`jaxcal._drift_handeye`): eye-to-hand its pose in the base
frame, eye-in-hand on the flange. `jaxcal.drift.check` turns the fit into the verdict the
other checks give.
"""

import json
from dataclasses import dataclass
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from ._drift_handeye import HandEyeCheckData, covariance_terms, fit_handeye_drift, variance_components
from ._geometry import se3_exp
from .errors import DatasetError
from .io.handeye import HandEyeCapture, load_hand_eye_capture
from .io.handeye_results import HANDEYE_RESULT_SCHEMA
from .vision import detect_frames, hand_eye_from_detections

#: Intrinsics closer than this to the calibrated ones are the same camera's (K: relative, px).
K_RTOL, K_ATOL = 1e-3, 0.05


def is_hand_eye_result(doc: dict) -> bool:
    """A `jaxcal handeye` `result.json` (new or old: old ones lack the schema and the check block)."""
    return doc.get("schema") == HANDEYE_RESULT_SCHEMA or (
        "schema" not in doc and "arrangement" in doc and "cameras" in doc
    )


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


def larger_covariance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The covariance that is, along every direction of $a$'s generalised eigenvectors, the larger
    of `a` and `b`: $L Q \\max(\\Lambda, 1) Q^T L^T$ with $a = L L^T$, $L^{-1} b L^{-T} = Q \\Lambda Q^T$
    (the model's covariance where the frame-robust one is not larger)."""
    lam, V = np.linalg.eigh(0.5 * (a + a.T))
    keep = lam > lam.max() * 1e-14
    L = V[:, keep] * np.sqrt(lam[keep])
    Li = np.linalg.pinv(L)
    mu, Q = np.linalg.eigh(Li @ (0.5 * (b + b.T)) @ Li.T)
    M = L @ Q
    return M @ np.diag(np.maximum(mu, 1.0)) @ M.T


def _refuse(cond: bool, message: str) -> None:
    if cond:
        raise DatasetError(message)


def _matching(doc: dict, file: Path, cap: HandEyeCapture) -> tuple[str, dict]:
    """Refuse a check capture of another arrangement, camera (name, size, intrinsics) or target,
    naming the field. **Returns:** the camera's name and its entry in `result.json`."""
    meta = cap.root / "handeye.json"
    _refuse(
        cap.arrangement != doc["arrangement"],
        f"{meta}: arrangement {cap.arrangement!r}, but {file} calibrated {doc['arrangement']!r}",
    )
    names = [c.name for c in cap.cameras]
    _refuse(
        len(cap.cameras) != 1,
        f"{meta}: cameras {names}: a check fits one camera at a time (give a capture of one of "
        f"{sorted(doc['cameras'])})",
    )
    cam = cap.cameras[0]
    entry = doc["cameras"].get(cam.name)
    _refuse(
        entry is None,
        f"{meta}: camera {cam.name!r}, but {file} calibrated {sorted(doc['cameras'])}: another camera",
    )
    _refuse(
        "check" not in entry,
        f"{file}: written before jaxcal check could read hand-eye results (no cameras.{cam.name}.check): "
        "run jaxcal handeye on the calibration capture again",
    )
    size = (entry["width"], entry["height"])
    _refuse(
        (cam.width, cam.height) != tuple(size),
        f"{meta}: cameras[0] ({cam.name!r}) is {cam.width}x{cam.height}, but {file} calibrated it at "
        f"{size[0]}x{size[1]}: another camera (or resolution)",
    )
    K_cal = np.asarray(entry["intrinsics"]["K"], np.float64)
    if cam.K is not None:
        _refuse(
            not np.allclose(cam.K, K_cal, rtol=K_RTOL, atol=K_ATOL),
            f"{meta}: cameras[0].K of {cam.name!r} differs from the K {file} calibrated with: another camera",
        )
        d_cal = np.zeros(14)
        d_cal[: len(entry["intrinsics"]["distortion"])] = entry["intrinsics"]["distortion"]
        d = np.zeros(14)
        d[: len(cam.dist)] = np.asarray(cam.dist, np.float64).ravel()
        _refuse(
            not np.allclose(d, d_cal, rtol=1e-3, atol=1e-6),
            f"{meta}: cameras[0].distortion of {cam.name!r} differs from the one {file} calibrated with: another "
            "camera (or lens)",
        )
    calibrated = doc["target"]["spec"]
    _refuse(
        cap.target.to_dict() != calibrated,
        f"{meta}: target {cap.target.to_dict()} differs from the {calibrated} {file} calibrated: another target",
    )
    return cam.name, entry


def check_data(doc: dict, file: Path, capture, *, workers=None) -> tuple[HandEyeCheckData, str, dict, int]:
    """Read and detect a hand-eye check capture against `doc`: the `HandEyeCheckData`, the
    camera's name and `result.json` entry, and the number of views that showed the target."""
    cap = capture if isinstance(capture, HandEyeCapture) else load_hand_eye_capture(capture)
    name, entry = _matching(doc, file, cap)
    K = np.asarray(entry["intrinsics"]["K"], np.float64)
    dist = np.asarray(entry["intrinsics"]["distortion"], np.float64)
    dets = detect_frames(
        list(cap.images[0]), [cap.target], K=K, dist=dist, workers=workers, progress=False, pool="thread"
    )
    seen = [d for d in dets if cap.target.name in d]
    _refuse(
        len(seen) < 2,
        f"{cap.root}: the target was found in {len(seen)} image(s) of camera {name!r}: a check needs a few",
    )
    obs = hand_eye_from_detections(
        dets, cap.target, cap.T_base_ee, K, dist, eye_in_hand=cap.eye_in_hand, sigma_px=1.0,
        frame_names=cap.frames, pad=False,
    )  # fmt: skip
    d = obs.data
    data = HandEyeCheckData(
        T_base_ee=jnp.asarray(d.T_base_ee), pixels=jnp.nan_to_num(jnp.asarray(d.pixels[0])),
        mask=jnp.asarray(d.mask[0]), K=jnp.asarray(K), board_points=jnp.asarray(d.board_points),
        eye_in_hand=jnp.asarray(cap.eye_in_hand),
    )  # fmt: skip
    return data, name, entry, len(seen)


def robot_sigma(doc: dict) -> np.ndarray:
    """The robot pose noise the calibration used (or estimated), `(6,)` m and rad; zero for exact poses."""
    rn = doc.get("robot_noise")
    if not rn:
        return np.zeros(6)
    return np.r_[np.full(3, 1e-3 * rn["translation_mm"]), np.full(3, np.radians(rn["rotation_deg"]))]


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
    R, s = variance_components(*terms, sigma_px)
    theta, C, T, rss = (np.asarray(a) for a in fit_handeye_drift(X, Y, R, data))
    nu, view = float(s[0]) / sigma_px**2, (float(np.sqrt(s[1])), float(np.sqrt(s[2])))
    T_now = np.linalg.inv(np.asarray(X)) @ np.asarray(se3_exp(jnp.asarray(theta)))
    frame = "T_ee_cam" if eye_in_hand else "T_base_cam"
    # The per-view components rest on the views' 6 (views - 1) redundant pose coordinates: the F
    # test's denominator degrees of freedom (the corners' 2 m - 6 are many more).
    return HandEyeCheckFit(
        theta, C, float(T), float(rss), 2 * corners - 6, views, np.asarray(T_now), frame, camera, nu, view,
        6 * (views - 1),
    )  # fmt: skip


def fit_hand_eye_check(doc: dict, file: Path, capture, *, workers=None) -> HandEyeCheckFit:
    """The drift fit of a hand-eye check `capture` (a directory or a `HandEyeCapture`) against the
    result `doc` read from `file`; raises `DatasetError` naming the field when they do not match."""
    data, name, entry, views = check_data(doc, file, capture, workers=workers)
    chk = entry["check"]
    return fit_check(
        data, np.asarray(entry["T_cam_robot"], np.float64), np.asarray(doc["target"]["T_robot_target"]["matrix"]),
        larger_covariance(np.asarray(chk["covariance"]), np.asarray(chk["covariance_frames"])),
        robot_sigma(doc), float(doc["solver"]["sigma_px"]), eye_in_hand=doc["arrangement"] == "eye_in_hand",
        camera=name, views=views,
    )  # fmt: skip


def read_hand_eye_result(path) -> "tuple[dict, Path] | None":
    """`(doc, file)` when `path` (a result directory or its `result.json`) is a `jaxcal handeye`
    result, else None (a calibration result, or nothing readable: `read_result` says why)."""
    p = Path(path)
    file = p / "result.json" if p.is_dir() else p
    try:
        doc = json.loads(file.read_text())
    except (OSError, ValueError):
        return None
    return (doc, file) if isinstance(doc, dict) and is_hand_eye_result(doc) else None
