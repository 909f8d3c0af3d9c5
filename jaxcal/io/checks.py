"""The after-calibration products' files: what `jaxcal certify`, `check` and `verify` read and write.

The only module that knows their JSON keys (`jaxcal.records_check` holds the records):

- reading a calibration's `result.json` (`read_calibration` -> `CalibrationReference`) and a
  `jaxcal handeye` result (`read_hand_eye_reference` -> `HandEyeReference`);
- writing the certificate (`certificate_json`, schema `jaxcal.certificate`), the drift check
  (`drift_check_json`, `jaxcal.drift_check`) and the verification (`verification_json`,
  `jaxcal.verification`), each with its inverse (`*_from_json`): a file read back and written
  again is the same JSON.
"""

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from ..errors import DatasetError
from ..markers import TargetSpec
from ..records import Intrinsics, PriorUse, ResidualStats, from_plain, plain
from ..records_check import (
    CalibrationReference,
    Certificate,
    CertificateRotation,
    CertificateSummary,
    CrossValidation,
    Detectable,
    DriftCheck,
    DriftResidual,
    Extrapolation,
    HandEyeCameraReference,
    HandEyeReference,
    JointOffset,
    PointFitModel,
    PredictionTest,
    Region,
    Verification,
    VerificationSummary,
)
from ._files import resolved
from ._schema import loads
from .handeye_results import HANDEYE_RESULT_SCHEMA
from .model_json import model_from_json

RESULT_SCHEMA = "jaxcal.result"
CERTIFICATE_SCHEMA, DRIFT_CHECK_SCHEMA, VERIFICATION_SCHEMA = (
    "jaxcal.certificate",
    "jaxcal.drift_check",
    "jaxcal.verification",
)


# --------------------------------------------------------------------------- a calibration's result.json


def read_result_json(path) -> tuple[dict, Path]:
    """`result.json` (a result directory or the file) as plain JSON, checked to be a jaxcal result."""
    p = Path(path)
    file = p / "result.json" if p.is_dir() else p
    resolved(file)  # a loop of symbolic links is named as one
    try:
        doc = loads(file.read_text())
    except FileNotFoundError:
        raise DatasetError(
            f"{file}: no such result (give a directory jaxcal calibrate wrote, or its result.json)"
        ) from None
    except (ValueError, UnicodeDecodeError) as e:
        raise DatasetError(f"{file}: not JSON ({e})") from None
    schema = doc.get("schema") if isinstance(doc, dict) else None
    if schema != RESULT_SCHEMA:
        raise DatasetError(f"{file}: schema is {schema!r}, expected {RESULT_SCHEMA!r}")
    return doc, file


def point_fit_model(pf: Mapping) -> PointFitModel:
    """The `PointFitModel` of a `point_fit` block (`jaxcal.io.result.point_fit_json`)."""
    return PointFitModel(
        nominal=model_from_json(pf["nominal_model"]),
        terms=tuple(pf["terms"]),
        x=np.asarray(pf["x"], np.float64),
        free=np.asarray(pf["free"], bool),
        covariance=np.asarray(pf["covariance"], np.float64),
        residual_variance_factor=float(pf["residual_variance_factor"]),
        sigma_m=float(pf["sigma_m"]),
        T_device_base0=np.asarray(pf["T_device_base0"]),
        T_flange_point0=np.asarray(pf["T_flange_point0"]),
        masses=np.asarray(pf["masses"]),
        coms=np.asarray(pf["coms"]),
        orientation=bool(pf.get("orientation", False)),
        sigma_rad=None if pf.get("sigma_rad") is None else float(pf["sigma_rad"]),
        samples=None if pf.get("samples") is None else int(pf["samples"]),
        mount_given=bool(pf.get("mount_given", True)),
        prior=from_plain(PriorUse, pf["prior"]) if pf.get("prior") else None,
    )


def calibration_reference(doc: Mapping, file) -> CalibrationReference:
    """The `CalibrationReference` of a `result.json` payload `doc` read from `file` (raises
    `DatasetError` naming the file when a block it has is not one jaxcal wrote)."""
    try:
        refinement, clock = doc.get("refinement") or {}, doc.get("clock")
        return CalibrationReference(
            file=Path(file),
            dataset=doc.get("dataset"),
            setup=doc.get("setup", ""),
            capture=doc.get("capture"),
            camera=doc.get("camera"),
            device=doc.get("device"),
            targets=tuple(doc.get("targets") or ()),
            board=doc.get("board"),
            device_frame="T_device_base" in doc,
            joint_names=tuple(doc["model"]["joint_names"]) if "model" in doc else None,
            intrinsics=from_plain(Intrinsics, doc["intrinsics"]) if doc.get("intrinsics") else None,
            clock_offset_s=None if clock is None else float(clock["offset_s"]),
            sigma_px=None if "sigma_px" not in refinement else float(refinement["sigma_px"]),
            point_fit=point_fit_model(doc["point_fit"]) if "point_fit" in doc else None,
            covariance_model=doc.get("covariance_model"),
            status=doc.get("status"),
            reason=str((doc.get("reasons") or [""])[0]),
        )
    except (KeyError, TypeError, ValueError) as e:
        raise DatasetError(f"{file}: not a result.json jaxcal wrote ({type(e).__name__}: {e})") from None


def read_calibration(path) -> CalibrationReference:
    """The `CalibrationReference` of a result directory or its `result.json`."""
    return calibration_reference(*read_result_json(path))


# --------------------------------------------------------------------------- a jaxcal handeye result


def is_hand_eye_result(doc: Mapping) -> bool:
    """A `jaxcal handeye` `result.json` (new or old: old ones lack the schema and the check block)."""
    return doc.get("schema") == HANDEYE_RESULT_SCHEMA or (
        "schema" not in doc and "arrangement" in doc and "cameras" in doc
    )


def _hand_eye_camera(name: str, e: Mapping) -> HandEyeCameraReference:
    i, chk = e.get("intrinsics") or {}, e.get("check")
    return HandEyeCameraReference(
        name=name,
        width=int(e.get("width", 0)),
        height=int(e.get("height", 0)),
        K=np.asarray(i.get("K", np.eye(3)), np.float64),
        distortion=np.asarray(i.get("distortion", ()), np.float64),
        T_cam_robot=np.asarray(e.get("T_cam_robot", np.eye(4)), np.float64),
        covariance=None if chk is None else np.asarray(chk["covariance"], np.float64),
        covariance_frames=None if chk is None else np.asarray(chk["covariance_frames"], np.float64),
    )


def hand_eye_reference(doc: Mapping, file) -> HandEyeReference:
    """The `HandEyeReference` of a `jaxcal handeye` `result.json` payload `doc` read from `file`."""
    try:
        # Exact robot poses kept by the held-out comparison still have the noise their frames left
        # out read as (at most): a later capture's frames carry it too, which the check must not take
        # for the camera's motion.
        rn, target = (
            doc.get("robot_noise") or (doc.get("held_out") or {}).get("robot_noise_level"),
            doc["target"],
        )
        return HandEyeReference(
            file=Path(file),
            arrangement=doc["arrangement"],
            cameras=tuple(_hand_eye_camera(n, e) for n, e in doc["cameras"].items()),
            target=TargetSpec.from_dict(target["spec"], where=f"{file}: target.spec"),
            T_robot_target=np.asarray(target["T_robot_target"]["matrix"], np.float64),
            robot_noise=(float(rn["translation_mm"]), float(rn["rotation_deg"])) if rn else None,
            sigma_px=float(doc["solver"]["sigma_px"]),
        )
    except (KeyError, TypeError, ValueError) as e:
        raise DatasetError(
            f"{file}: not a result.json jaxcal handeye wrote ({type(e).__name__}: {e})"
        ) from None


def read_hand_eye_reference(path) -> HandEyeReference | None:
    """The `HandEyeReference` when `path` (a result directory or its `result.json`) is a `jaxcal
    handeye` result, else None (a calibration result, or nothing readable: `read_result_json` says why)."""
    p = Path(path)
    file = p / "result.json" if p.is_dir() else p
    try:
        doc = loads(file.read_text())
    except (OSError, ValueError):
        return None
    return hand_eye_reference(doc, file) if isinstance(doc, dict) and is_hand_eye_result(doc) else None


# --------------------------------------------------------------------------- jaxcal check --json


def drift_check_json(c: DriftCheck) -> dict:
    """The `jaxcal check --json` payload of a `DriftCheck`."""
    return {
        "schema": DRIFT_CHECK_SCHEMA,
        "schema_version": 1,
        "result": c.result,
        "capture": c.capture,
        "samples": c.samples,
        "detected": c.detected,
        "statistic": c.statistic,
        "dof": c.dof,
        "threshold": c.threshold,
        "p_value": c.p_value,
        "alpha": c.alpha,
        "test": c.test,
        "dof_noise": c.dof_noise,
        "translation_mm": {"size": c.translation_mm[0], "std": c.translation_mm[1]},
        "rotation_deg": {"size": c.rotation_deg[0], "std": c.rotation_deg[1]},
        "device_translation_m": c.theta[:3].tolist(),
        "device_rotation_rad": c.theta[3:6].tolist(),
        "covariance": c.cov.tolist(),
        "joint_offsets_deg": None
        if c.joint_offsets_deg is None
        else {o.joint: [o.estimate_deg, o.std_deg] for o in c.joint_offsets_deg},
        "detectable": plain(c.detectable),
        "residual": plain(c.residual),
        "moved": c.what,
        f"{c.frame}_now": c.T_device_base.tolist(),
        "message": c.message,
        "advice": c.advice,
        **(
            {}
            if c.rotation_residual_deg is None
            else {"rotation_residual_deg": plain(c.rotation_residual_deg)}
        ),
    }


def drift_check_from_json(d: Mapping) -> DriftCheck:
    """The `DriftCheck` a `jaxcal check --json` file holds (`drift_check_json`'s inverse; the
    joint offsets' part of `theta` from their degrees)."""
    offsets = d["joint_offsets_deg"]
    rows = None if offsets is None else tuple(JointOffset(j, e, s) for j, (e, s) in offsets.items())
    theta = np.r_[
        d["device_translation_m"], d["device_rotation_rad"], [np.radians(r.estimate_deg) for r in rows or ()]
    ]
    frame = next(k for k in d if k.endswith("_now"))[: -len("_now")]
    return DriftCheck(
        result=d["result"],
        capture=d["capture"],
        samples=d["samples"],
        theta=theta,
        cov=np.asarray(d["covariance"], np.float64),
        statistic=d["statistic"],
        dof=d["dof"],
        threshold=d["threshold"],
        p_value=d["p_value"],
        detected=d["detected"],
        translation_mm=(d["translation_mm"]["size"], d["translation_mm"]["std"]),
        rotation_deg=(d["rotation_deg"]["size"], d["rotation_deg"]["std"]),
        joint_offsets_deg=rows,
        detectable=from_plain(Detectable, d["detectable"]),
        residual=from_plain(DriftResidual, d["residual"]),
        T_device_base=np.asarray(d[f"{frame}_now"], np.float64),
        message=d["message"],
        advice=d["advice"],
        alpha=d["alpha"],
        what=d["moved"],
        frame=frame,
        dof_noise=d["dof_noise"],
        rotation_residual_deg=None
        if d.get("rotation_residual_deg") is None
        else from_plain(ResidualStats, d["rotation_residual_deg"]),
    )


# --------------------------------------------------------------------------- jaxcal certify --json


def certificate_json(c: Certificate, *, poses: bool = True) -> dict:
    """The `certificate.json` payload of a `Certificate` (`poses`: with every pose's figures)."""
    out = {
        "schema": CERTIFICATE_SCHEMA,
        "schema_version": 1,
        "result": c.result,
        "kind": c.kind,
        "frame": c.frame,
        "covariance_model": c.covariance_model,
        "region": plain(c.region),
        "summary": plain(c.summary),
        "extrapolation": plain(c.extrapolation),
        "caveats": list(c.caveats),
        "notes": list(c.notes),
    }
    if c.rotation is not None:
        out["rotation"] = plain(c.rotation)
    if poses:
        deg = [{}] * len(c.q)
        if c.rms_deg is not None:
            deg = [{"rms_deg": float(r), "bound95_deg": float(b)} for r, b in zip(c.rms_deg, c.bound95_deg)]
        out["joint_names"] = list(c.joint_names)
        out["poses"] = [
            {"q": a.tolist(), "point_m": p.tolist(), "rms_mm": float(r), "bound95_mm": float(b)} | d
            for a, p, r, b, d in zip(c.q, c.points, c.rms_mm, c.bound95_mm, deg)
        ]
    return out


def certificate_from_json(d: Mapping) -> Certificate:
    """The `Certificate` a `certificate.json` holds (`certificate_json`'s inverse; without
    its poses the per-pose arrays are empty)."""
    poses = d.get("poses", [])
    names = tuple(d.get("joint_names", ()))
    column = lambda key, shape: np.asarray([p[key] for p in poses], np.float64).reshape(shape)  # noqa: E731
    deg = bool(poses) and "rms_deg" in poses[0]
    return Certificate(
        result=d["result"],
        kind=d["kind"],
        frame=d["frame"],
        region=from_plain(Region, d["region"]),
        joint_names=names,
        q=column("q", (len(poses), -1) if poses else (0, len(names))),
        points=column("point_m", (len(poses), 3)),
        rms_mm=column("rms_mm", (len(poses),)),
        bound95_mm=column("bound95_mm", (len(poses),)),
        summary=from_plain(CertificateSummary, d["summary"]),
        extrapolation=None if d["extrapolation"] is None else from_plain(Extrapolation, d["extrapolation"]),
        caveats=tuple(d["caveats"]),
        notes=tuple(d["notes"]),
        covariance_model=d.get("covariance_model"),
        rotation=None if d.get("rotation") is None else from_plain(CertificateRotation, d["rotation"]),
        rms_deg=column("rms_deg", (len(poses),)) if deg else None,
        bound95_deg=column("bound95_deg", (len(poses),)) if deg else None,
    )


# --------------------------------------------------------------------------- jaxcal verify --json


def verification_json(v: Verification) -> dict:
    """The `jaxcal verify --json` payload of a `Verification`."""
    return {
        "schema": VERIFICATION_SCHEMA,
        "schema_version": 1,
        "result": v.result,
        "dataset": v.dataset,
        "summary": plain(v.summary),
        "cv": plain(v.cv),
        "test": plain(v.test),
        "exit_code": v.exit_code,
        "notes": list(v.notes),
        "samples": [
            {"sample": int(s), "error_mm": float(e), "nominal_mm": float(n), "predicted_rms_mm": float(p)}
            | ({} if a is None else {"error_deg": a, "nominal_deg": b, "predicted_rms_deg": c})
            for s, e, n, p, (a, b, c) in zip(v.samples, v.errors_mm, v.nominal_mm, v.predicted_mm, _angles(v))
        ],
    }


def _angles(v: Verification) -> list:
    """Per sample `(error, nominal, predicted)` angles (deg), or None without orientations."""
    if v.errors_deg is None:
        return [(None, None, None)] * len(v.samples)
    return [tuple(map(float, t)) for t in zip(v.errors_deg, v.nominal_deg, v.predicted_deg)]


def verification_from_json(d: Mapping) -> Verification:
    """The `Verification` a `jaxcal verify --json` file holds (`verification_json`'s inverse)."""
    rows = d["samples"]
    column = lambda key, dtype=np.float64: np.asarray([r[key] for r in rows], dtype)  # noqa: E731
    angles = bool(rows) and "error_deg" in rows[0]
    deg = lambda key: column(key) if angles else None  # noqa: E731
    return Verification(
        result=d["result"],
        dataset=d["dataset"],
        samples=column("sample", np.int64),
        errors_mm=column("error_mm"),
        nominal_mm=column("nominal_mm"),
        predicted_mm=column("predicted_rms_mm"),
        summary=from_plain(VerificationSummary, d["summary"]),
        cv=None if d["cv"] is None else from_plain(CrossValidation, d["cv"]),
        notes=tuple(d["notes"]),
        test=None if d.get("test") is None else from_plain(PredictionTest, d["test"]),
        errors_deg=deg("error_deg"),
        nominal_deg=deg("nominal_deg"),
        predicted_deg=deg("predicted_rms_deg"),
    )


# --------------------------------------------------------------------------- any of the three


#: Per schema the product's writer and reader.
PRODUCTS = {
    CERTIFICATE_SCHEMA: (Certificate, certificate_json, certificate_from_json),
    DRIFT_CHECK_SCHEMA: (DriftCheck, drift_check_json, drift_check_from_json),
    VERIFICATION_SCHEMA: (Verification, verification_json, verification_from_json),
}


def product_json(record: Certificate | DriftCheck | Verification) -> dict:
    """The JSON payload of a certificate, drift check or verification."""
    return next(write for cls, write, _ in PRODUCTS.values() if isinstance(record, cls))(record)


def read_product(path) -> Certificate | DriftCheck | Verification:
    """The record a `certificate.json`, `jaxcal check --json` or `jaxcal verify --json` file
    holds, by its schema (raises `DatasetError` naming the file when it is none of them)."""
    try:
        d = loads(Path(path).read_text())
        _, _, read = PRODUCTS[d.get("schema")]
        return read(d)
    except FileNotFoundError:
        raise DatasetError(f"{path}: no such file") from None
    except (KeyError, TypeError, ValueError, AttributeError) as e:
        raise DatasetError(
            f"{path}: not a certificate, drift check or verification jaxcal wrote ({type(e).__name__}: {e})"
        ) from None
