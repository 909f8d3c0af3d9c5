"""`result.json`: a calibration result as plain JSON (schema `jaxcal.result`, version 1)."""

import cv2
import numpy as np

from .model_json import model_to_json


def quaternion_xyzw(R) -> np.ndarray:
    """The unit quaternion `(x, y, z, w)` of a rotation matrix."""
    rvec = cv2.Rodrigues(np.asarray(R, np.float64))[0].ravel()
    angle = np.linalg.norm(rvec)
    axis = rvec / angle if angle > 0 else np.array([1.0, 0.0, 0.0])
    return np.r_[np.sin(angle / 2) * axis, np.cos(angle / 2)]


def pose_json(T, std) -> dict:
    """A pose with its 1-sigma twist `(tx, ty, tz, rx, ry, rz)` (m, rad) as JSON."""
    T, std = np.asarray(T), np.asarray(std)
    return {
        "matrix": T.tolist(),
        "xyz_m": T[:3, 3].tolist(),
        "quaternion_xyzw": quaternion_xyzw(T[:3, :3]).tolist(),
        "std_xyz_mm": (1e3 * std[:3]).tolist(),
        "std_rot_deg": np.degrees(std[3:]).tolist(),
    }


def result_to_json(result) -> dict:
    """The `result.json` payload of a `CalibrationResult` (plain Python types)."""
    fixed = pose_json(result.T_cam_base, result.std_cam)
    if result.eye_in_hand:
        poses = {
            "board": result.board,
            "T_board_base": fixed,
            "T_flange_cam": result.T_flange_target[0].tolist(),
        }
    elif result.kind.device:
        poses = {
            "device": result.camera,
            "device_is_base": bool(result.kind.device_is_base),
            "T_device_base": fixed,
            "T_flange_point": result.T_flange_target[0].tolist(),
        }
    else:
        poses = {"T_cam_base": fixed, "T_flange_target": result.T_flange_target.tolist()}
    return {
        "schema": "jaxcal.result",
        "schema_version": 1,
        "dataset": str(result.dataset),
        "setup": result.kind.label,
        "capture": result.kind.describe(),
        "camera": result.camera,
        "targets": result.targets,
        "ok": result.ok,
        "status": result.status,
        "reasons": list(result.reasons),
        **poses,
        "reduction_ratios": result.ratios,
        "parameters": result.parameters,
        "identifiability": {
            "estimated": sum(bool(p["free"]) for p in result.parameters if p["group"] == "correction"),
            "frozen": result.frozen,
            "note": f"frozen parameters cannot be seen by a {'device' if result.kind.device else 'camera'} "
            f"watching joint axes (they trade off against others or against {result.kind.fixed_frame}); "
            "they are held at nominal",
        },
        "arcs": result.arcs,
        "frames": result.frames,
        "clock": result.clock,
        "intrinsics": result.intrinsics,
        "solver": result.solver,
        "timings_s": result.timings,
        "refinement": result.refinement,
        "other_cameras": [
            {
                "camera": c["camera"],
                "views": c["views"],
                "T_cam_base": pose_json(c["T_cam_base"], c["std_cam"]),
                "T_cam_base_start": np.asarray(c["T_cam_base_start"]).tolist(),
            }
            for c in result.other_cameras
        ],
        "validation": result.validation,
        "warnings": result.warnings,
        "checks": [] if result.verdict is None else list(result.verdict.checks),
        "model": model_to_json(result.model),
        **({"point_fit": point_fit_json(result.point_fit)} if result.point_fit is not None else {}),
    }


def point_fit_json(pf) -> dict:
    """The `point_fit` block: what `jaxcal verify` needs to predict any pose's point with
    the calibrated model (the nominal model, the references, the parameter vector with its
    covariance and the non-geometric terms), and the models cross-validation compared."""
    fit, prob = pf.fit, pf.problem
    return {
        "terms": list(pf.layout.terms),
        "term_rows": pf.term_rows,
        "models": list(pf.models),
        "cv_folds": pf.folds,
        "residual_mm": pf.residual_mm,
        "samples": int(np.sum(pf.used)),
        "held": list(pf.held),
        "names": pf.layout.names(),
        "x": np.asarray(fit.x).tolist(),
        "free": np.asarray(fit.free).astype(bool).tolist(),
        "covariance": np.asarray(fit.cov).tolist(),
        "residual_variance_factor": float(fit.sigma2),
        "sigma_m": float(np.median(np.asarray(prob.data.sigma)[pf.used])),
        "T_device_base0": np.asarray(prob.T_dev_base0).tolist(),
        "T_flange_point0": np.asarray(prob.T_flange_point0).tolist(),
        "masses": np.asarray(prob.data.masses).tolist(),
        "coms": np.asarray(prob.data.coms).tolist(),
        "nominal_model": model_to_json(prob.nominal),
    }
