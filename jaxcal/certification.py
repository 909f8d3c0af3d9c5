"""`jaxcal certify RESULT`: the tool-point accuracy a calibration supports over the user's task region.

A calibration's covariance $\\Sigma$ (of its correction vector $x$) says how far
its prediction of the tool point $p(q; x)$ can be off at any configuration $q$.
To first order, with $G_q = \\partial p / \\partial x$, the error at $q$ is Gaussian,

$$ e_q \\sim N(0,\\ \\Sigma_q), \\qquad \\Sigma_q = G_q \\Sigma G_q^T + s^2 I_3, $$

with $s^2$ the residual scatter the noise model does not explain (tracker
results: $\\max(\\hat\\sigma^2 - 1, 0)\\,\\sigma_m^2$ per axis, $\\hat\\sigma^2$ the fit's
residual variance factor; camera results: 0, the covariance is already scaled).
Over the region's configurations the certificate reports per pose the RMS
error $\\sqrt{\\mathrm{tr}\\,\\Sigma_q}$ and the 95 % bound $b_q$ with $P(|e_q| \\le b_q)
= 0.95$ (the quantile of $\\sum_k \\lambda_k z_k^2$, $\\lambda = \\mathrm{eig}\\,\\Sigma_q$, read off
fixed draws of $z$), and over the region: the mean and RMS, the 95th percentile
of the error at a random pose of the region (the quantile of the mixture of the
poses' distributions), and the worst pose.

**Orientations.** A tracker result that fitted measured orientations (a 6-DoF
probe, a camera on the flange seeing a fixed board) predicts the point frame's
orientation too: its error, a rotation vector in the point's frame, is
Gaussian the same way, $G^R_q \\Sigma G^{R\\,T}_q + s_R^2 I_3$
($s_R^2 = \\max(\\hat\\sigma^2 - 1, 0)\\,\\sigma_{rad}^2$), and the certificate reports
the same figures of its angle (deg) beside the positions'.

**The point and its frame.** The point is the one the calibration measured:
the tracker's reflector, the target's origin (the camera's origin
eye-in-hand), in the fixed frame (`frame="fixed"`: the device's or camera's,
as `jaxcal verify` and the validation measure it) or in the robot's base frame
(`frame="base"`: the fixed frame's own uncertainty left out).

**The region.** A Cartesian box in the base frame (configurations drawn
uniformly over the joints' travel, kept when the calibrated model puts the
point inside), a box of joint ranges, or a list of configurations.

**Extrapolation.** The calibration saw the configurations of its dataset
(tracker samples; a camera capture's encoder log): each joint's range there,
and the convex hull of the points they put the tool at. The certificate says
how far the region's joints leave those ranges, what share of its poses do,
how far its points leave the hull, and how much larger the predicted error is
there than over the calibration's own configurations.
"""

import importlib
from dataclasses import dataclass, replace
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from ._correction import ParameterLayout, apply_correction, parameters_to_model
from ._device import to_device
from ._exported import stored_jit
from ._geometry import se3_exp
from ._kinematics import KinematicModel, forward_kinematics
from ._pointfit import PointLayout, point_jacobian, predict, rotation_jacobian
from ._uncertainty import joint_travel, tool_points
from .errors import DatasetError
from .io.checks import read_calibration, read_result_json
from .io.dataset import load_dataset
from .io.result import ESTIMATE_FILE, read_estimate
from .records import Named
from .records_check import (
    CalibrationReference,
    Certificate,
    CertificateRotation,
    CertificateSummary,
    Extrapolation,
    Region,
    WorstPose,
)
from .stages._points import point_problem

#: Draws of the 3-D standard normal used for the quantiles of $|e_q|$ (fixed seed: repeatable).
QUANTILE_DRAWS = 4000
#: A region joint beyond the calibrated range by more than this (rad, or m) is extrapolation.
JOINT_TOLERANCE = np.radians(1.0)
#: Cartesian-box sampling: configurations drawn per round and the most drawn in all.
BOX_CHUNK, BOX_MAX_DRAWS = 20_000, 1_000_000
#: Most configurations one certificate takes (`samples`, or the rows of `poses`): its figures
#: settle long before (docs/certify.md), while its time and its file grow with them.
MAX_POSES = 100_000
#: Configurations per chunk of the prediction (covariances, points, quantiles, the hull): the
#: memory a certificate takes is bounded by it, whatever the region's size.
POSE_CHUNK = 5000
#: Values of the region's error distribution kept for its 95th percentile: each pose's first
#: ceil(MIXTURE_VALUES / poses) draws (all `QUANTILE_DRAWS` of them up to 1000 poses).
MIXTURE_VALUES = 4_000_000
#: Covariances whose norm quantiles are drawn at once (`norm_quantiles`).
QUANTILE_CHUNK = 500
#: The caveat of a capture of stop-and-shoot camera views (a planned capture).
COHERENT_VIEWS = (
    "a capture of camera views at stops (e.g. a planned capture): the detector's errors can add up "
    "coherently across its views; the covariance takes in what each view's residuals show of them, "
    "not what the solution absorbs, and on rendered planned captures one seed in ten came out "
    "about 2.2x its prediction (docs/certify.md)"
)
SELF_CALIBRATED = (
    "the intrinsics were self-calibrated from the same images: their errors are in the covariance only "
    "as far as the refinement freed them; a lens model the images cannot pin makes the bound optimistic"
)


@dataclass(frozen=True, eq=False)
class Predictor:
    """What a result predicts at any configuration (see the module docstring).

    - `kind`: `"tracker"` (a `point_fit` block) or `"camera"` (`estimate.npz`).
    - `covariances(q, frame)`: `(C, 3, 3)` the tool point's covariance (m^2).
    - `base_points(q)`: `(C, 3)` the calibrated tool point in the base frame (m).
    - `scatter_var`: the unexplained per-axis residual variance $s^2$ (m^2).
    - `model`: the calibrated model; `travel`: `(joints, 2)` the joints' travel.
    - `workspace`: the calibration's configurations `(S, joints)`, or None.
    - `caveats`, `notes`: what the certificate states beside its figures.
    - `covariance_model`: the result's `covariance_model` (None: written before the key).
    - `rotation_covariances(q, frame)`: `(C, 3, 3)` the point frame's orientation error's
      covariance (rad^2) and `scatter_var_rad` its unexplained part, for a result that fitted
      orientations; None otherwise.
    """

    kind: str
    result: str
    joint_names: tuple[str, ...]
    covariances: object
    base_points: object
    scatter_var: float
    model: KinematicModel
    travel: np.ndarray
    workspace: np.ndarray | None
    caveats: tuple[str, ...] = ()
    notes: tuple[str, ...] = ()
    covariance_model: str | None = None
    rotation_covariances: object = None
    scatter_var_rad: float = 0.0


def read_result(path) -> tuple[dict, Path]:
    """`result.json` (a result directory or the file) as plain JSON, checked to be a jaxcal result
    (`jaxcal.io.checks.read_result_json`; the products read its typed `read_calibration`)."""
    return read_result_json(path)


def _workspace(ref: CalibrationReference, ratio: np.ndarray) -> tuple[np.ndarray | None, str | None, dict]:
    """The calibration dataset's configurations (tracker samples, or the encoder log as
    joint positions), a note when they cannot be read, and its joint limits."""
    try:
        if ref.dataset is None:
            raise KeyError("dataset")
        ds = load_dataset(ref.dataset)
    except (DatasetError, OSError, KeyError, ValueError) as e:
        return None, f"the calibration's dataset could not be read ({e}): extrapolation not assessed", {}
    if ds.samples is not None and ds.samples.q is not None:
        return np.asarray(ds.samples.q, np.float64), None, ds.joint_limits
    if ds.encoder_motor is not None:
        q = np.asarray(ds.encoder_motor, np.float64) / ratio
        return q[:: max(1, len(q) // 5000)], None, ds.joint_limits
    return None, f"{ds.root}: no joint positions: extrapolation not assessed", ds.joint_limits


def _point_covariances(x, cov, problem):
    J = point_jacobian(x, problem)
    return jnp.einsum("sai,ij,sbj->sab", J, cov, J)


def _rotation_covariances(x, cov, problem):
    J = rotation_jacobian(x, problem)
    return jnp.einsum("sai,ij,sbj->sab", J, cov, J)


def _point_model(x, problem):
    """The point fit's calibrated model and device-to-base pose."""
    layout = problem.layout
    params, _ = layout.split(x)
    model, _ = apply_correction(problem.nominal, problem.T_flange_point0[None], params.correction)
    return model, problem.T_dev_base0 @ se3_exp(x[layout.base.index("cam")])


# The tracker predictor's programs, stored (a later `jaxcal certify` reloads them) and with XLA's
# optimisations (they sweep a whole region), as the camera predictor's below.
_point_covariances = stored_jit(_point_covariances, "point_covariances", compiler_options=None)
_tracker_points = stored_jit(predict, "tracker_points", compiler_options=None)
_rotation_covariances = stored_jit(_rotation_covariances, "rotation_covariances", compiler_options=None)
_point_model = stored_jit(_point_model, "point_model")


def tracker_predictor(ref: CalibrationReference) -> Predictor:
    """The `Predictor` of a stop-and-shoot result's point fit."""
    pf, file = ref.point_fit, ref.file
    nominal = pf.nominal
    layout = PointLayout(ParameterLayout.of(nominal, 1, fixed_name="T_device_base"), pf.terms)
    if len(pf.x) != layout.size:
        raise DatasetError(f"{file}: point_fit.x has {len(pf.x)} entries, its layout {layout.size}")
    x = to_device(pf.x, np.float64)
    cov = np.asarray(pf.covariance, np.float64)
    cam = layout.base.index("cam")
    T0, Tp0 = pf.T_device_base0, pf.T_flange_point0
    inertials = (pf.masses, pf.coms)

    def problem(q):
        n = len(q)
        return point_problem(
            nominal, layout, q, np.zeros((n, 3)), np.ones(n), np.ones(n, bool), T0, Tp0, inertials
        )

    def in_frame(frame):
        c = cov.copy()
        if frame == "base":
            c[cam, :] = 0.0
            c[:, cam] = 0.0
        return to_device(c)

    def covariances(q, frame="fixed"):
        return np.asarray(_point_covariances(x, in_frame(frame), problem(np.asarray(q))))

    def rotation_covariances(q, frame="fixed"):
        return np.asarray(_rotation_covariances(x, in_frame(frame), problem(np.asarray(q))))

    def base_points(q):
        y = np.asarray(_tracker_points(x, problem(np.asarray(q))))
        return (y - T_db[:3, 3]) @ T_db[:3, :3]

    model, T_db = _point_model(x, problem(np.zeros((1, nominal.num_joints))))
    T_db = np.asarray(T_db)
    ws, note, limits = _workspace(ref, np.ones(nominal.num_joints))
    excess = max(pf.residual_variance_factor - 1.0, 0.0)
    scatter = excess * pf.sigma_m**2
    return Predictor(
        kind="tracker",
        result=str(file),
        joint_names=tuple(nominal.joint_names),
        covariances=covariances,
        base_points=base_points,
        scatter_var=scatter,
        model=model,
        travel=joint_travel(nominal, limits),
        workspace=ws,
        notes=() if note is None else (note,),
        covariance_model=ref.covariance_model,
        rotation_covariances=rotation_covariances if pf.orientation else None,
        scatter_var_rad=excess * (pf.sigma_rad or 0.0) ** 2,
    )


def _tool_covariances(estimate, x, cov, q):
    k = estimate.layout.axis_size
    prefix, unravel = ravel_pytree(estimate.layout.split(x[:k])[:2])

    def points(v):
        c, corr = unravel(v)
        return tool_points(estimate.nominal, estimate.T_cam_base0, estimate.T_flange_marker0, c, corr, q)

    G = jax.jacfwd(points)(prefix)
    return jnp.einsum("cai,ij,cbj->cab", G, cov, G)


def _base_points(model: KinematicModel, mount, q):
    return jax.vmap(lambda qq: (forward_kinematics(model, qq)[-1] @ mount)[:3, 3])(q)


# Stored programs (`jaxcal._exported`): a second `jaxcal certify` neither traces nor compiles them.
# The two that run over every configuration of a region keep XLA's optimisations (they run
# about three times faster so; compiled once per cache).
_tool_covariances = stored_jit(_tool_covariances, "tool_covariances", compiler_options=None)
_base_points = stored_jit(_base_points, "base_points", compiler_options=None)
_calibrated_model = stored_jit(lambda estimate: parameters_to_model(estimate), "calibrated_model")


def camera_predictor(ref: CalibrationReference) -> Predictor:
    """The `Predictor` of a camera result (its `estimate.npz`, written beside `result.json`)."""
    file = ref.file
    path = file.parent / ESTIMATE_FILE
    if not path.is_file():
        raise DatasetError(
            f"{path}: missing: the certificate of a camera calibration needs the covariance jaxcal "
            "calibrate writes there (since this version): calibrate the dataset again"
        )
    est = read_estimate(path)
    k = est.layout.axis_size
    cov = np.asarray(est.cov, np.float64)[:k, :k]
    cam = est.layout.index("cam")
    calibrated = _calibrated_model(est)

    def covariances(q, frame="fixed"):
        c = cov.copy()
        if frame == "base":
            c[cam, :] = 0.0
            c[:, cam] = 0.0
        return np.asarray(_tool_covariances(est, est.x, to_device(c), to_device(q, np.float64)))

    def base_points(q):
        return np.asarray(_base_points(calibrated.model, calibrated.T_flange_marker[0], to_device(q)))

    ws, note, limits = _workspace(ref, np.asarray(est.reduction_ratio))
    caveats = []
    if ref.intrinsics is not None and ref.intrinsics.source.startswith("self-calibrated"):
        caveats.append(SELF_CALIBRATED)
    if "poses" in (ref.capture or ""):
        caveats.append(COHERENT_VIEWS)
    return Predictor(
        kind="camera",
        result=str(file),
        joint_names=tuple(est.nominal.joint_names),
        covariances=covariances,
        base_points=base_points,
        scatter_var=0.0,
        model=calibrated.model,
        travel=joint_travel(est.nominal, limits),
        workspace=ws,
        caveats=tuple(caveats),
        notes=() if note is None else (note,),
        covariance_model=ref.covariance_model,
    )


def load_predictor(result) -> Predictor:
    """The `Predictor` of a result directory (or its `result.json`): tracker or camera."""
    ref = read_calibration(result)
    if ref.status == "failed":  # a solver that did not converge: its covariance describes nothing
        raise DatasetError(
            f"{ref.file}: the calibration failed (status 'failed': {ref.reason or 'see its reasons'}): there is "
            "nothing to certify; calibrate again"
        )
    if ref.point_fit is None and ref.tracker:
        raise DatasetError(
            f"{ref.file}: a tracker result without a 'point_fit' block (sweeps): not supported yet"
        )
    pred = tracker_predictor(ref) if ref.point_fit is not None else camera_predictor(ref)
    if ref.status == "suspect":
        said = f"the calibration is suspect ({ref.reason or 'see result.json reasons'}): these figures take it as right"
        pred = replace(pred, notes=(said, *pred.notes))
    return pred


def norm_quantiles(
    cov: np.ndarray, p: float = 0.95, draws: int = QUANTILE_DRAWS, keep: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Per `(3, 3)` covariance of `cov` `(C, 3, 3)`, the `p` quantile of the norm of
    $e \\sim N(0, \\Sigma)$, and the norms at the first `keep` (default all) of the fixed
    draws `(C, keep)` (m). Computed `QUANTILE_CHUNK` covariances at a time (16 MB of draws)."""
    lam = np.clip(np.linalg.eigvalsh(cov), 0.0, None)
    z2 = np.random.default_rng(0).standard_normal((draws, 3)) ** 2
    keep = draws if keep is None else keep
    quantiles, kept = np.empty(len(lam)), np.empty((len(lam), keep))
    for s in range(0, len(lam), QUANTILE_CHUNK):
        d = lam[s : s + QUANTILE_CHUNK] @ z2.T
        np.sqrt(d, out=d)
        quantiles[s : s + QUANTILE_CHUNK] = np.quantile(d, p, axis=1)
        kept[s : s + QUANTILE_CHUNK] = d[:, :keep]
    return quantiles, kept


def chunked(fn, q: np.ndarray, chunk: int = POSE_CHUNK) -> np.ndarray:
    """`fn(q)` (one row out per configuration) over chunks of `chunk` configurations, so that
    its memory is bounded; the last chunk is padded with its last row to the chunk's size (one
    compiled program for every chunk). Up to one chunk, `fn(q)` itself."""
    if len(q) <= chunk:
        return np.asarray(fn(q))
    out = []
    for s in range(0, len(q), chunk):
        part = q[s : s + chunk]
        n = len(part)
        padded = np.concatenate([part, np.repeat(part[-1:], chunk - n, axis=0)]) if n < chunk else part
        out.append(np.asarray(fn(padded))[:n])
    return np.concatenate(out)


# --------------------------------------------------------------------------- regions


def box_configurations(pred: Predictor, box, n: int, seed: int = 0) -> tuple[np.ndarray, int]:
    """`n` configurations uniform over the joints' travel whose calibrated tool point lies
    in the Cartesian `box` `(x0, y0, z0, x1, y1, z1)` (m, base frame), and the draws it took."""
    b = np.asarray(box, np.float64).reshape(2, 3)
    lo, hi = np.minimum(b[0], b[1]), np.maximum(b[0], b[1])
    rng = np.random.default_rng(seed)
    kept, drawn = [], 0
    while sum(len(k) for k in kept) < n and drawn < BOX_MAX_DRAWS:
        q = pred.travel[:, 0] + (pred.travel[:, 1] - pred.travel[:, 0]) * rng.uniform(
            size=(BOX_CHUNK, len(pred.travel))
        )
        p = pred.base_points(q)
        kept.append(q[np.all((p >= lo) & (p <= hi), axis=1)])
        drawn += BOX_CHUNK
    q = np.concatenate(kept)[:n]
    if len(q) < min(n, 20):
        raise ValueError(
            f"--region {','.join(f'{v:g}' for v in b.ravel())}: the calibrated tool point reached the box in "
            f"{len(q)} of {drawn} random configurations: give a box the arm reaches (base frame, m)"
        )
    return q, drawn


def joint_box_configurations(pred: Predictor, ranges, n: int, seed: int = 0) -> np.ndarray:
    """`n` configurations uniform in the joint `ranges` `(joints, 2)` (rad, or m)."""
    r = np.asarray(ranges, np.float64)
    if r.shape != (len(pred.joint_names), 2):
        raise ValueError(f"joint box: {r.shape[0]} ranges for the robot's {len(pred.joint_names)} joints")
    return r[:, 0] + (r[:, 1] - r[:, 0]) * np.random.default_rng(seed).uniform(size=(n, len(r)))


def read_poses(path, joint_names, *, degrees: bool = False) -> np.ndarray:
    """A CSV of configurations: a header naming the robot's joints (any order, other
    columns ignored), or rows of one value per joint in order (rad, or m; `degrees`: deg);
    read line by line, at most `MAX_POSES` of them."""
    rows, cols = [], None
    try:
        with open(path, encoding="utf-8-sig") as f:
            for n, line in enumerate(f, start=1):
                if not line.strip():
                    continue
                cells = line.split(",")
                if cols is None:
                    head = [c.strip() for c in cells]
                    cols = list(range(len(joint_names)))
                    if set(joint_names) <= set(head):
                        cols = [head.index(j) for j in joint_names]
                        continue
                if len(rows) == MAX_POSES:
                    raise DatasetError(f"{path}: more than {MAX_POSES:,} configurations (at most MAX_POSES)")
                rows.append(_pose_row(cells, cols, path, n, joint_names))
    except (OSError, UnicodeDecodeError) as e:
        raise DatasetError(f"{path}: cannot read the configurations ({e})") from None
    if not rows:
        raise DatasetError(f"{path}: no configurations")
    q = np.asarray(rows, np.float64)
    return np.radians(q) if degrees else q


def _pose_row(cells: list[str], cols: list[int], path, line: int, joint_names) -> list[float]:
    try:
        row = [float(cells[c]) for c in cols]
    except (ValueError, IndexError):
        raise DatasetError(
            f"{path} line {line}: each row needs one value per joint {list(joint_names)} (or a header naming them)"
        ) from None
    if not all(np.isfinite(row)):
        raise DatasetError(f"{path} line {line}: a value is not finite (NaN or infinite)")
    return row


# --------------------------------------------------------------------------- the certificate


def _scipy_spatial():
    """`scipy.spatial` (Qhull), imported when a certificate first needs its hull: `jaxcal
    calibrate` imports this module for `--region` and should not pay for it otherwise."""
    return importlib.import_module("scipy.spatial")


def extrapolation(
    pred: Predictor, q: np.ndarray, points: np.ndarray, rms_m: np.ndarray, frame: str
) -> Extrapolation | None:
    """How far the region leaves the calibrated workspace (see the module docstring), or None
    when the calibration's configurations are unknown."""
    ws = pred.workspace
    if ws is None:
        return None
    lo, hi = ws.min(0), ws.max(0)
    excess = np.maximum(np.maximum(lo - q, q - hi), 0.0)  # (C, joints)
    per_joint = excess.max(0)
    inside = ws[np.random.default_rng(1).permutation(len(ws))[:1000]]
    # The same prediction as the region's (the parameters' covariance and the unexplained scatter).
    inside_var = np.trace(chunked(lambda c: pred.covariances(c, frame), inside), axis1=1, axis2=2)
    inside_var = inside_var + 3.0 * pred.scatter_var
    inside_rms = float(np.sqrt(np.mean(inside_var)))
    region_rms = float(np.sqrt(np.mean(rms_m**2)))
    ws_points = chunked(pred.base_points, inside)
    spatial = _scipy_spatial()
    try:
        hull = spatial.ConvexHull(ws_points)
        out = chunked(lambda p: np.max(p @ hull.equations[:, :3].T + hull.equations[:, 3], axis=1), points)
    except spatial.QhullError:  # the calibration's points are flat (e.g. one joint swept)
        out = np.full(len(points), np.nan)
    return Extrapolation(
        calibrated_joint_range=tuple((float(a), float(b)) for a, b in zip(lo, hi)),
        joint_excess=tuple(Named(j, float(e)) for j, e in zip(pred.joint_names, per_joint)),
        share_of_poses_outside_joint_ranges=float(np.mean(np.any(excess > JOINT_TOLERANCE, axis=1))),
        max_joint_excess=float(per_joint.max()),
        share_of_points_outside_hull=float(np.mean(out > 0)) if np.all(np.isfinite(out)) else None,
        max_distance_outside_hull_mm=float(1e3 * max(np.nanmax(out), 0.0))
        if np.any(np.isfinite(out))
        else None,
        calibrated_rms_mm=1e3 * inside_rms,
        error_ratio=region_rms / inside_rms if inside_rms > 0 else None,
        extrapolated=bool(per_joint.max() > JOINT_TOLERANCE or np.nanmax(np.r_[out, -1.0]) > 0.01),
    )


def certify(
    result,
    *,
    region=None,
    joint_box=None,
    poses=None,
    samples: int = 1000,
    frame: str = "fixed",
    seed: int = 0,
) -> Certificate:
    """The accuracy certificate of `result` (a directory or its `result.json`, or a
    loaded `Predictor`) over one region (see the module docstring).

    **Arguments:**
    - `region`: a Cartesian box `(x0, y0, z0, x1, y1, z1)` (m, base frame); or
      `joint_box`: `(joints, 2)` ranges (rad, or m); or `poses`: `(C, joints)`
      configurations. None of them: the joints' whole travel.
    - `samples`: configurations drawn for a box; `seed`: their draw.
    - `frame`: `"fixed"` (the device's / camera's frame) or `"base"`.

    **Returns:** a `Certificate`. Raises `DatasetError` naming a file that is not
    a result it can certify, `ValueError` for a region it cannot use.
    """
    if frame not in ("fixed", "base"):
        raise ValueError(f"frame must be 'fixed' or 'base', got {frame!r}")
    if not 1 <= samples <= MAX_POSES:
        raise ValueError(f"samples: from 1 to {MAX_POSES:,} configurations (MAX_POSES), got {samples}")
    if sum(r is not None for r in (region, joint_box, poses)) > 1:
        raise ValueError("give one region: a Cartesian box, a joint box or a list of poses")
    pred = result if isinstance(result, Predictor) else load_predictor(result)
    notes = list(pred.notes)
    if region is not None:
        q, drawn = box_configurations(pred, region, samples, seed)
        desc = Region("cartesian_box", box_m=tuple(np.asarray(region, float).tolist()), drawn=drawn)
        if len(q) < samples:
            notes.append(f"only {len(q)} of {drawn} random configurations put the tool point in the box")
    elif poses is not None:
        q = np.asarray(poses, np.float64)
        if q.ndim != 2 or q.shape[1] != len(pred.joint_names):
            raise ValueError(f"poses: shape {q.shape}, expected (configurations, {len(pred.joint_names)})")
        if len(q) > MAX_POSES:
            raise ValueError(f"poses: {len(q):,} configurations, at most {MAX_POSES:,} (MAX_POSES)")
        desc = Region("poses")
    else:
        box = pred.travel if joint_box is None else joint_box
        q = joint_box_configurations(pred, box, samples, seed)
        desc = Region("joint_box", ranges=tuple(tuple(r) for r in np.asarray(box, float).tolist()))
    cov = chunked(lambda c: pred.covariances(c, frame), q) + pred.scatter_var * np.eye(3)
    b95, draws = norm_quantiles(cov, keep=min(QUANTILE_DRAWS, -(-MIXTURE_VALUES // len(q))))
    rms = np.sqrt(np.trace(cov, axis1=1, axis2=2))
    points = chunked(pred.base_points, q)
    w = int(np.argmax(b95))
    summary = CertificateSummary(
        poses=int(len(q)),
        mean_mm=float(1e3 * rms.mean()),
        rms_mm=float(1e3 * np.sqrt(np.mean(rms**2))),
        p95_mm=float(1e3 * np.quantile(draws, 0.95)),
        max_bound95_mm=float(1e3 * b95[w]),
        unexplained_scatter_mm=float(1e3 * np.sqrt(3 * pred.scatter_var)),
        worst=WorstPose(
            index=w, q=tuple(q[w].tolist()), point_m=tuple(points[w].tolist()), rms_mm=float(1e3 * rms[w])
        ),
    )
    rotation, rms_deg, b95_deg = _rotation_part(pred, q, frame)
    ext = extrapolation(pred, q, points, rms, frame)
    if ext is not None and ext.extrapolated:
        notes.append(
            f"the region leaves the calibrated workspace: joints up to {np.degrees(ext.max_joint_excess):.1f} deg "
            f"beyond the calibrated ranges ({100 * ext.share_of_poses_outside_joint_ranges:.0f} % of its poses), "
            f"predicted error {ext.error_ratio:.2f}x that over the calibrated configurations: extrapolation, "
            "the first-order prediction is all that supports it"
        )
    return Certificate(
        result=pred.result,
        kind=pred.kind,
        frame=frame,
        region=desc,
        joint_names=pred.joint_names,
        q=q,
        points=points,
        rms_mm=1e3 * rms,
        bound95_mm=1e3 * b95,
        summary=summary,
        extrapolation=ext,
        caveats=pred.caveats,
        notes=tuple(notes),
        covariance_model=pred.covariance_model,
        rotation=rotation,
        rms_deg=rms_deg,
        bound95_deg=b95_deg,
    )


def _rotation_part(pred: Predictor, q, frame: str):
    """The certificate's orientation part (`CertificateRotation`, per-pose RMS and 95 % bound,
    deg), or Nones for a result without orientations."""
    if pred.rotation_covariances is None:
        return None, None, None
    cov = pred.rotation_covariances(q, frame) + pred.scatter_var_rad * np.eye(3)
    b95, draws = norm_quantiles(cov)
    rms = np.sqrt(np.trace(cov, axis1=1, axis2=2))
    rotation = CertificateRotation(
        mean_deg=float(np.degrees(rms.mean())),
        rms_deg=float(np.degrees(np.sqrt(np.mean(rms**2)))),
        p95_deg=float(np.degrees(np.quantile(draws, 0.95))),
        max_bound95_deg=float(np.degrees(b95.max())),
        unexplained_scatter_deg=float(np.degrees(np.sqrt(3 * pred.scatter_var_rad))),
    )
    return rotation, np.degrees(rms), np.degrees(b95)


def plot_certificate(c: Certificate, path, workspace_points: np.ndarray | None = None) -> None:
    """The region's tool points seen from above and from the side, coloured by their 95 % bound,
    and the bounds' histogram, as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(14, 4.2), gridspec_kw={"width_ratios": [1, 1, 0.8]})
    vmax = float(np.max(c.bound95_mm))
    for ax, (i, j, lab) in zip(axes[:2], ((0, 1, "top view (x, y)"), (0, 2, "side view (x, z)"))):
        if workspace_points is not None:
            ax.plot(
                workspace_points[:, i], workspace_points[:, j], ".", ms=1, color="0.75", label="calibrated"
            )
        sc = ax.scatter(
            c.points[:, i], c.points[:, j], c=c.bound95_mm, s=6, cmap="viridis", vmin=0, vmax=vmax
        )
        ax.set_xlabel("xyz"[i] + " (m, base)")
        ax.set_ylabel("xyz"[j] + " (m, base)")
        ax.set_title(lab)
        ax.set_aspect("equal", adjustable="datalim")
    fig.colorbar(sc, ax=axes[1], label="95 % bound (mm)")
    axes[2].hist(c.bound95_mm, bins=30, color="C0")
    s = c.summary
    axes[2].axvline(s.p95_mm, color="C3", label=f"region 95th percentile {s.p95_mm:.3f} mm")
    axes[2].set_xlabel("per-pose 95 % bound (mm)")
    axes[2].set_ylabel("poses")
    axes[2].legend(fontsize=8)
    fig.suptitle(
        f"jaxcal certify ({c.kind}, {c.frame} frame): mean {s.mean_mm:.3f} mm, 95 % {s.p95_mm:.3f} mm"
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
