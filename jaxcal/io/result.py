"""`result.json`: a calibration result as plain JSON (schema `jaxcal.result`, version 1).

The only module that knows the file's keys: `result_to_json` writes a
`CalibrationResult`'s typed records (`jaxcal.records`; a block's keys are its
record's field names), `read_result` reads them back as a `ResultFile`.
"""

import json
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from .._correction import Estimate, ParameterLayout
from .._npgeom import matrix_to_quaternion
from ..errors import DatasetError
from ..records import (
    ArcRow,
    Clock,
    FrameCounts,
    Intrinsics,
    ParameterRow,
    PoseFigures,
    RatioRow,
    RefinementSummary,
    ResultFile,
    SolverInfo,
    TermsSummary,
    ValidationReport,
    from_plain,
    plain,
)
from ._schema import loads
from .model_json import model_from_json, model_to_json


def pose_figures(T, std) -> PoseFigures:
    """A pose with its 1-sigma twist `(tx, ty, tz, rx, ry, rz)` (m, rad) as `result.json` gives it."""
    T, std = np.asarray(T, np.float64), np.asarray(std, np.float64)
    return PoseFigures(
        matrix=T,
        xyz_m=T[:3, 3],
        quaternion_xyzw=np.asarray(matrix_to_quaternion(T[:3, :3])),
        std_xyz_mm=1e3 * std[:3],
        std_rot_deg=np.degrees(std[3:]),
    )


def pose_json(T, std) -> dict:
    """A pose with its 1-sigma twist `(tx, ty, tz, rx, ry, rz)` (m, rad) as JSON."""
    return plain(pose_figures(T, std))


#: `result.json`'s `covariance_model`: which covariance the parameters' std, `estimate.npz`
#: (and so `jaxcal certify`) carry.
COVARIANCE_MODELS = {
    "view_robust": "the refinement's: the model's sigma^2 (J^T J)^+ (corner errors independent), "
    "replaced along the directions where the per-view cluster (sandwich, CR1) covariance is larger "
    "by more than its sampling spread 2 sqrt(2/G) (jaxcal._refine, jaxcal._lsq.larger_covariance)",
    "kernel": "the refinement's view_robust covariance, replaced along the directions where the kernel "
    "(HAC) sandwich of the poses along the capture is larger by more than its sampling spread: the residuals' "
    "errors repeat from frame to frame (refinement.error_correlation; jaxcal.stages._residual_tests)",
    "model": "the point fit's sigma^2 (J^T J)^+, sigma^2 its residual variance factor "
    "(tracker samples independent)",
    "two_stage": "the two-stage fit's (no refinement ran)",
}


def covariance_model(result) -> str:
    """The `COVARIANCE_MODELS` key of a `CalibrationResult`'s covariance."""
    if result.refinement is not None:
        correlation = result.refinement.error_correlation
        return "view_robust" if correlation is None or correlation.kernel_lags is None else "kernel"
    return "model" if result.point_fit is not None else "two_stage"


def result_to_json(result) -> dict:
    """The `result.json` payload of a `CalibrationResult` (plain Python types)."""
    fixed = pose_json(result.T_cam_base, result.std_cam)
    if result.eye_in_hand:
        poses = {
            "board": result.board,
            "T_board_base": fixed,
            "T_flange_cam": result.T_flange_target[0].tolist(),
        }
    elif not result.kind.images:
        poses = {
            "device": result.camera,
            "device_is_base": not result.kind.fixed_frame_free,
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
        "targets": list(result.targets),
        "ok": result.ok,
        "status": result.status,
        "reasons": list(result.reasons),
        "notes": [] if result.verdict is None else list(result.verdict.notes),
        **poses,
        "reduction_ratios": {
            r.joint: {k: v for k, v in plain(r).items() if k != "joint"} for r in result.ratios
        },
        "parameters": plain(result.parameters),
        "identifiability": {
            "estimated": sum(p.free for p in result.parameters if p.group == "correction"),
            "frozen": list(result.frozen),
            "note": f"frozen parameters cannot be seen by a {result.kind.sensor} "
            f"watching joint axes (they trade off against others or against {result.kind.fixed_frame}); "
            "they are held at nominal",
        },
        "arcs": plain(result.arcs),
        "frames": plain(result.frames),
        "clock": plain(result.clock),
        "intrinsics": plain(result.intrinsics),
        "solver": plain(result.solver),
        "timings_s": dict(result.timings),
        "refinement": plain(result.refinement),
        "covariance_model": covariance_model(result),
        "other_cameras": [
            {
                "camera": c.camera,
                "views": c.views,
                "T_cam_base": pose_json(c.T_cam_base, c.std_cam),
                "T_cam_base_start": np.asarray(c.T_cam_base_start).tolist(),
            }
            for c in result.other_cameras
        ],
        "validation": plain(result.validation),
        "warnings": list(result.warnings),
        "checks": [] if result.verdict is None else plain(result.verdict.checks),
        "model": model_to_json(result.model),
        **({"point_fit": point_fit_json(result.point_fit)} if result.point_fit is not None else {}),
        **({"terms": plain(result.terms)} if result.terms is not None else {}),
    }


def result_from_json(payload: dict) -> ResultFile:
    """The typed blocks of a `result.json` payload (`result_to_json`'s inverse for them)."""
    block = lambda cls, key: None if payload.get(key) is None else from_plain(cls, payload[key])  # noqa: E731
    return ResultFile(
        status=payload["status"],
        reasons=tuple(payload["reasons"]),
        ratios=tuple(from_plain(RatioRow, {"joint": j, **r}) for j, r in payload["reduction_ratios"].items()),
        parameters=tuple(from_plain(ParameterRow, p) for p in payload["parameters"]),
        frozen=tuple(payload["identifiability"]["frozen"]),
        arcs=tuple(from_plain(ArcRow, a) for a in payload["arcs"]),
        frames=block(FrameCounts, "frames"),
        clock=block(Clock, "clock"),
        intrinsics=block(Intrinsics, "intrinsics"),
        solver=block(SolverInfo, "solver"),
        refinement=block(RefinementSummary, "refinement"),
        validation=block(ValidationReport, "validation"),
        warnings=tuple(payload["warnings"]),
        timings=dict(payload["timings_s"]),
        terms=block(TermsSummary, "terms"),
    )


def read_result(path) -> ResultFile:
    """The typed blocks of the `result.json` at `path`, or in the result folder `path` (raises
    `DatasetError` naming the file when it is missing or not one jaxcal wrote)."""
    path = Path(path) / "result.json" if Path(path).is_dir() else path
    try:
        with open(path) as f:
            payload = loads(f.read())
        if payload.get("schema") != "jaxcal.result":
            raise ValueError("no jaxcal.result schema")
        return result_from_json(payload)
    except FileNotFoundError:
        raise DatasetError(f"{path}: no such file") from None
    except (KeyError, TypeError, ValueError) as e:
        raise DatasetError(f"{path}: not a result.json jaxcal wrote ({e})") from None


def point_fit_json(pf) -> dict:
    """The `point_fit` block: what `jaxcal verify` needs to predict any pose's point with
    the calibrated model (the nominal model, the references, the parameter vector with its
    covariance and the non-geometric terms), and the models cross-validation compared; with
    measured orientations also `orientation`, their median noise `sigma_rad` and `residual_deg`;
    `mount_given`: whether the metadata gave the point's nominal mount."""
    fit, prob = pf.fit, pf.problem
    return {
        "terms": list(pf.layout.terms),
        "term_rows": plain(pf.term_rows),
        "models": plain(pf.models),
        "cv_folds": pf.folds,
        "residual_mm": plain(pf.residual_mm),
        "samples": int(np.sum(pf.used)),
        "poses": pf.poses,
        "repeats": plain(pf.repeats),
        "outliers": plain(pf.outliers),
        "robust_scale": pf.robust_scale,
        "held": list(pf.held),
        "unseen": list(pf.unseen),
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
        "mount_given": bool(pf.mount_given),
        **({"prior": plain(pf.prior)} if pf.prior is not None else {}),
        **(
            {
                "orientation": True,
                "sigma_rad": float(np.median(np.asarray(prob.data.sigma_rad)[pf.used])),
                "residual_deg": plain(pf.residual_deg),
            }
            if pf.layout.orientation
            else {}
        ),
    }


#: The file beside `result.json` holding the final solve's `Estimate` (vector, covariance, references).
ESTIMATE_FILE = "estimate.npz"


def write_estimate(path, estimate) -> None:
    """Write an `Estimate` (`jaxcal._correction`) as an uncompressed `.npz` of plain
    arrays (no pickles): the vector, its covariance and free mask, the references the
    corrections are relative to, the nominal model as JSON and the layout's fields.
    `jaxcal certify` and `jaxcal check` read it back with `read_estimate`."""
    lay = estimate.layout
    with open(path, "wb") as f:
        np.savez(
            f,
            x=np.asarray(estimate.x),
            cov=np.asarray(estimate.cov),
            free=np.asarray(estimate.free, bool),
            names=np.asarray(lay.names(refine=len(estimate.x) == lay.size), str),
            T_flange_marker0=np.asarray(estimate.T_flange_marker0),
            T_cam_base0=np.asarray(estimate.T_cam_base0),
            reduction_ratio=np.asarray(estimate.reduction_ratio),
            nominal_model=np.asarray(json.dumps(model_to_json(estimate.nominal))),
            joints=np.asarray(lay.joints, str),
            num_markers=np.asarray(lay.num_markers),
            other_cameras=np.asarray(lay.other_cameras, str),
            angles=np.asarray(lay.angles, str),
            line_delays=np.asarray(lay.line_delays, str),
            terms=np.asarray(lay.terms, str),
            eye_in_hand=np.asarray(lay.eye_in_hand),
            fixed_name=np.asarray("" if lay.fixed_name is None else lay.fixed_name),
            mount_names=np.asarray(estimate.mount_names, str),
        )


def read_estimate(path) -> Estimate:
    """The `Estimate` `write_estimate` wrote (raises `DatasetError` naming the file when it is not one)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            d = {k: z[k] for k in z.files}
        layout = ParameterLayout(
            tuple(str(s) for s in d["joints"]),
            int(d["num_markers"]),
            other_cameras=tuple(str(s) for s in d["other_cameras"]),
            angles=tuple(str(s) for s in d["angles"]),
            line_delays=tuple(str(s) for s in d.get("line_delays", ())),  # absent before rolling shutters
            terms=tuple(str(s) for s in d.get("terms", ())),  # absent before the non-geometric terms
            eye_in_hand=bool(d["eye_in_hand"]),
            fixed_name=str(d["fixed_name"]) or None,
        )
        return Estimate(
            x=jnp.asarray(d["x"], jnp.float64),
            cov=jnp.asarray(d["cov"], jnp.float64),
            free=jnp.asarray(d["free"], bool),
            nominal=model_from_json(loads(str(d["nominal_model"]))),
            T_flange_marker0=jnp.asarray(d["T_flange_marker0"], jnp.float64),
            T_cam_base0=jnp.asarray(d["T_cam_base0"], jnp.float64),
            reduction_ratio=jnp.asarray(d["reduction_ratio"], jnp.float64),
            layout=layout,
            mount_names=tuple(str(s) for s in d["mount_names"]),
        )
    except FileNotFoundError:
        raise DatasetError(f"{path}: no such file") from None
    except (KeyError, ValueError, OSError) as e:
        raise DatasetError(f"{path}: not an estimate jaxcal wrote ({e})") from None
