"""A tree calibration read back from its folder, and checked against samples it was not fitted on
(`jaxcal verify RESULT DATASET` with a tree calibration; docs/trees.md).

`load_tree_calibration` rebuilds what `jaxcal.trees.save_tree_calibration` wrote (the calibrated
URDF and `tree_result.json`) into a model whose `predict(q)` is the calibration's: the sag, the
mass corrections and a harmonic's phase included. Every field is checked against the robot file it
names (a parameter of a joint or link that is not there, a pose that is not 4x4, a value that is
not a finite number are refused by name), so a damaged file is never taken for a changed robot.
`verify_tree` compares the model's predictions with new samples, per tip.
"""

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ._kinematics import joint_motion
from ._npgeom import se3_exp as np_se3_exp
from ._tree import KinematicTree
from ._treefit import (
    FAMILIES,
    Elastic,
    TreeSamples,
    deflected_tips,
    local_twists,
    prediction_jacobian,
    problem_of,
)
from ._treelayout import tree_layout
from .certification import Predictor
from .drift import fit_drift, verdict, whitening
from .io._files import shown
from .io.tree_dataset import TreeDataset, read_json_object
from .io.urdf_tree import actuated_limits, load_urdf_tree
from .records_check import DriftCheck
from .trees import (
    COVARIANCE_FILE,
    FAR_BEYOND,
    NOISE_FACTOR,
    OUTLIER_SHARE,
    OUTLIER_SIGMAS,
    RESULT_FILE,
    checked_samples,
)

__all__ = ["CalibratedTree", "check_tree", "load_tree_calibration", "tip_predictors", "verify_tree"]

#: A tree calibration holds on new samples while their residuals' RMS per axis stays within this
#: factor of what the fit expects: its own residual noise and its parameters' uncertainty there.
HOLDS_FACTOR = 1.5


@dataclass(frozen=True)
class CalibratedTree:
    """A tree calibration read back from the folder `save_tree_calibration` wrote: the calibrated
    tree, its loads and terms, the device and the measured points, and the fit's verdict and
    residual noise (mm per axis); the freed parameters' `values`, and from `tree_covariance.json`
    their `covariance` (names, matrix, the configurations fitted) and the noise the fit was
    given (`stated_noise_mm`; None in a folder written before they were kept), and whether the
    points were weighed by their own covariances (`point_covariances`)."""

    tree: KinematicTree
    elastic: Elastic
    harmonic: np.ndarray
    points: np.ndarray
    T_device_root: np.ndarray
    device_on: str | None
    noise_mm: float
    status: str
    values: dict = field(default_factory=dict)
    covariance: tuple | None = None
    stated_noise_mm: float | None = None
    point_covariances: bool = False

    def prediction_jacobian(self, q) -> tuple[np.ndarray, np.ndarray]:
        """`(G, cov)`: the derivatives `(n, tips, 3, k)` (device frame) of `predict(q)` by the freed
        parameters of `tree_covariance.json` (in their own units), to first order about the
        calibrated body, and those parameters' covariance `(k, k)`."""
        if self.covariance is None:
            raise ValueError(f"the tree calibration has no {COVARIANCE_FILE} (written before jaxcal kept it)")
        names, cov, _ = self.covariance
        layout = tree_layout(self.tree)
        index = [layout.names.index(n) for n in names]
        tips, a = len(self.tree.tip_names), self.tree.num_actuated
        # The geometry is the calibrated tree's own: only the terms' values lie in the vector.
        terms = layout.family(*FAMILIES)
        x = np.array([self.values.get(n, 0.0) if t else 0.0 for n, t in zip(layout.names, terms)])
        one = TreeSamples(np.zeros((1, a)), np.zeros((1, tips, 3)), np.ones((1, tips), bool))
        device_tip = self.tree.tip_names.index(self.device_on) if self.device_on else -1
        problem = problem_of(
            self.tree, layout, one, self.T_device_root, self.points, self.noise_mm, device_tip
        )
        J = prediction_jacobian(x / layout.scales, problem, np.asarray(q, np.float64)) / layout.scales
        # ... and by the fit's own parameters (the covariance's), whose twists were about the nominal body.
        fitted = np.array([self.values.get(n, 0.0) for n in layout.names])
        return (J @ local_twists(layout, fitted))[..., index], cov

    def predict_covariance(self, q) -> np.ndarray:
        """The covariance `(n, tips, 3, 3)` (m^2, device frame) of `predict(q)` from the fit's
        (`tree_covariance.json`): to first order about the calibrated body, as the calibration's
        own `predict_covariance` gives it."""
        G, cov = self.prediction_jacobian(q)
        return np.einsum("ntak,kl,ntbl->ntab", G, cov, G)

    def predict(self, q) -> np.ndarray:
        """The measured points predicted at commanded positions `q` `(n, actuated)`, device frame."""
        tip = self.tree.tip_names.index(self.device_on) if self.device_on else -1
        return np.asarray(
            deflected_tips(
                self.tree,
                self.elastic,
                jnp.asarray(q, jnp.float64),
                self.points,
                self.T_device_root,
                jnp.asarray(self.harmonic),
                tip,
            )
        )


def _numbers(value, shape: tuple, path: Path, field: str) -> np.ndarray:
    """`value` as finite float64 numbers of `shape`, or a `ValueError` naming the file and field."""
    try:
        a = np.asarray(value, np.float64)
    except (TypeError, ValueError):
        a = None
    if a is None or a.shape != shape or not np.all(np.isfinite(a)) or isinstance(value, bool):
        want = "a number" if shape == () else f"finite numbers of shape {list(shape)}"
        got = repr(value)
        got = got if len(got) <= 80 else f"{got[:60]} ... ({len(got):,} characters)"
        raise ValueError(f"tree calibration {shown(path)!r}: field {field} must be {want}, got {got}")
    return a


def _object(doc, name: str, path: Path) -> dict:
    if not isinstance(doc.get(name), dict):
        raise ValueError(
            f"tree calibration {shown(path)!r}: field {name!r} must be an object, got {doc.get(name)!r}"
        )
    return doc[name]


def _covariance(path: Path, tree: KinematicTree, std: dict) -> tuple | None:
    """`tree_covariance.json`'s parameter names, matrix and configurations fitted (None where the
    folder has none), checked against `tree_result.json`'s standard deviations (`std`)."""
    if not path.is_file():
        return None
    doc = read_json_object(path, "tree calibration's covariance")
    names = doc.get("parameters")
    if not isinstance(names, list) or set(names) - set(tree_layout(tree).names):
        raise ValueError(
            f"{shown(path)!r}: field 'parameters' must name parameters of calibrated.urdf's tree"
        )
    cov = _numbers(doc.get("matrix"), (len(names), len(names)), path, "'matrix'")
    q = doc.get("configurations")
    rows = len(q) if isinstance(q, list) else -1
    q = _numbers(q, (rows, tree.num_actuated), path, "'configurations'")
    if (
        not np.allclose(cov, cov.T, rtol=1e-9, atol=0.0)
        or np.linalg.eigvalsh(cov).min() < -1e-9 * abs(cov).max()
    ):
        raise ValueError(
            f"{shown(path)!r}: field 'matrix' is not a symmetric positive semi-definite covariance"
        )
    stated = np.array([std.get(n, np.nan) for n in names], np.float64)
    if not np.allclose(np.sqrt(np.diag(cov)), stated, rtol=1e-6, atol=1e-300):
        k = int(np.argmax(~np.isclose(np.sqrt(np.diag(cov)), stated, rtol=1e-6, atol=1e-300)))
        raise ValueError(
            f"{shown(path)!r}: the standard deviation of {names[k]!r} is {np.sqrt(cov[k, k]):.6g} there, "
            f"{stated[k]:.6g} in {RESULT_FILE}: the two files are not one calibration's"
        )
    return tuple(names), cov, q


def load_tree_calibration(folder) -> CalibratedTree:
    """Read a tree calibration's folder (`calibrated.urdf` and `tree_result.json`, or that file's
    path) back into a model that predicts what the calibration predicted. Raises `ValueError`
    naming the file and field of what is missing or malformed."""
    folder = Path(folder)
    folder = folder.parent if folder.name == RESULT_FILE else folder
    path = folder / RESULT_FILE
    doc = read_json_object(path, "tree calibration")
    points, zero = _object(doc, "tip_points_m", path), _object(doc, "zero_offsets_rad", path)
    base = doc.get("base_link")
    if not isinstance(base, str):
        raise ValueError(
            f"tree calibration {shown(path)!r}: field 'base_link' must be a link's name, got {base!r}"
        )
    tree = load_urdf_tree(folder / "calibrated.urdf", base_link=base, tips=list(points))
    unknown = sorted(set(zero) - set(tree.joint_names))
    if unknown:
        raise ValueError(
            f"tree calibration {shown(path)!r}: zero_offsets_rad names joints {unknown} that calibrated.urdf lacks"
        )
    # calibrated.urdf holds each actuated joint's zero offset in its origin: turned back into the
    # offset, so that a harmonic's phase is the fit's.
    offsets = np.array(
        [
            0.0
            if j in tree.coupled
            else float(_numbers(zero.get(n, 0.0), (), path, f"zero_offsets_rad[{n!r}]"))
            for j, n in enumerate(tree.joint_names)
        ]
    )
    T = np.stack(
        [
            np.asarray(T0) @ np.asarray(joint_motion(kind, a, -z))
            for T0, kind, a, z in zip(
                np.asarray(tree.T_parent_joint), tree.joint_types, np.asarray(tree.axis), offsets
            )
        ]
    )
    tree = eqx.tree_at(
        lambda t: (t.T_parent_joint, t.zero_offset), tree, (jnp.asarray(T), jnp.asarray(offsets))
    )
    parameters = _object(doc, "parameters", path)
    unknown = sorted(set(parameters) - set(tree_layout(tree).names))
    if unknown:
        raise ValueError(
            f"tree calibration {shown(path)!r}: parameters {unknown[:5]} are not parameters of calibrated.urdf's tree"
        )
    values = {
        name: float(
            _numbers(v.get("value") if isinstance(v, dict) else v, (), path, f"parameters[{name!r}].value")
        )
        for name, v in parameters.items()
    }
    n = tree.num_joints

    def of(names) -> np.ndarray:
        return np.array([values.get(name, 0.0) for name in names], np.float64)

    elastic = Elastic(
        of(f"{j}.compliance" for j in tree.joint_names),
        of(f"{j}.lateral_compliance.{k}" for j in tree.joint_names for k in "12").reshape(n, 2),
        of(f"{link}.moment.{a}" for link in tree.link_names for a in "xyz").reshape(n + 1, 3),
        of(f"gravity.tilt.{a}" for a in "xy"),
        of(f"{link}.mass" for link in tree.link_names),
    )
    device_on = doc.get("device_on")
    if device_on is not None and device_on not in tree.tip_names:
        raise ValueError(
            f"tree calibration {shown(path)!r}: device_on {device_on!r} is not one of the tips {list(points)}"
        )
    noise = _numbers(doc.get("noise_mm"), (), path, "'noise_mm'")
    if not noise > 0:
        raise ValueError(f"tree calibration {shown(path)!r}: field 'noise_mm' must be positive, got {noise}")
    stated = doc.get("stated_noise_mm")
    return CalibratedTree(
        values=values,
        covariance=_covariance(
            folder / COVARIANCE_FILE,
            tree,
            {n: v.get("std") for n, v in parameters.items() if isinstance(v, dict)},
        ),
        stated_noise_mm=None if stated is None else float(_numbers(stated, (), path, "'stated_noise_mm'")),
        point_covariances=doc.get("point_covariances") is True,
        tree=tree,
        elastic=elastic,
        harmonic=of(f"{j}.harmonic.{k}" for j in tree.joint_names for k in ("cos", "sin")).reshape(n, 2),
        points=np.stack([_numbers(p, (3,), path, f"tip_points_m[{t!r}]") for t, p in points.items()]),
        T_device_root=_numbers(doc.get("T_device"), (4, 4), path, "'T_device'"),
        device_on=device_on,
        noise_mm=float(noise),
        status=str(doc.get("status")),
    )


def _aligned(model: CalibratedTree, folder, dataset: TreeDataset):
    """`dataset`'s samples checked against the calibration's robot and device, and its measured
    mask, points and covariances (None: none) in the calibration's tip order (a tip it does not
    measure: never seen)."""
    if dataset.device_on != model.device_on:
        raise ValueError(
            f"dataset {shown(dataset.folder)!r} is measured by a device on {dataset.device_on or 'no tip (fixed)'}; "
            f"the calibration {shown(folder)!r} by one on {model.device_on or 'no tip (fixed)'}: give samples of "
            "the device the calibration was fitted to"
        )
    if dataset.tree.actuated_names != model.tree.actuated_names:
        raise ValueError(
            f"dataset {shown(dataset.folder)!r} has the joints {list(dataset.tree.actuated_names)}; the "
            f"calibration {shown(folder)!r} has {list(model.tree.actuated_names)}"
        )
    if set(dataset.tree.tip_names) - set(model.tree.tip_names):
        raise ValueError(
            f"dataset {shown(dataset.folder)!r} measures tips {sorted(set(dataset.tree.tip_names) - set(model.tree.tip_names))} "
            f"that the calibration {shown(folder)!r} did not calibrate (its tips: {list(model.tree.tip_names)})"
        )
    samples = checked_samples(dataset.tree, dataset.samples, dataset.noise_mm, dataset.limits, None)
    # The dataset's tips, in the calibration's order (a tip it does not measure: never seen).
    order = [
        dataset.tree.tip_names.index(t) if t in dataset.tree.tip_names else -1 for t in model.tree.tip_names
    ]
    measured = np.stack(
        [samples.measured[:, k] if k >= 0 else np.zeros(len(samples.q), bool) for k in order], 1
    )
    points = np.stack([samples.points[:, max(k, 0)] for k in order], 1)
    cov = None
    if samples.covariance is not None:
        cov = np.stack([samples.covariance[:, max(k, 0)] for k in order], 1)
    return samples, measured, points, cov


#: A tip whose prediction the calibration knows only to this many times its residual noise is
#: named: a verification that holds says little of it.
LOOSE_TIP = 5.0


def _per_tip(model, measured, residual, var, points, **predicted) -> dict:
    """Each measured tip's figures: its samples, RMS per axis against its own expectation (the
    fit's noise and its parameters' `var` there) and whether it holds, and per prediction in
    `predicted` the mean, RMS and largest distance (mm) from the measured `points`."""
    tips = {}
    for t, name in enumerate(model.tree.tip_names):
        seen = measured[:, t]
        if not seen.any():
            continue
        # Each tip against its own expectation too: a branch the calibration never measured (held
        # at the robot file's values) must not pass under the other branches' figures.
        rms_t = 1e3 * float(np.sqrt(np.mean(residual[seen, t] ** 2)))
        expected_t = float(np.hypot(model.noise_mm, 1e3 * np.sqrt(var[seen, t].mean())))
        tips[name] = {
            "samples": int(seen.sum()),
            "rms_per_axis_mm": rms_t,
            "expected_mm": expected_t,
            "holds": bool(rms_t <= HOLDS_FACTOR * expected_t),
        }
        for kind, p in predicted.items():
            d = 1e3 * np.linalg.norm(p[seen, t] - points[seen, t], axis=-1)
            tips[name] |= {
                f"{kind}_mean_mm": float(d.mean()),
                f"{kind}_rms_mm": float(np.sqrt(np.mean(d**2))),
            }
            tips[name][f"{kind}_max_mm"] = float(d.max())
    return tips


def verify_tree(folder, dataset: TreeDataset) -> dict:
    """A tree calibration (`folder`) against samples it was not fitted on (`dataset`, of the same
    robot and device): per tip, the measured points' distance (mm) from the calibration's
    predictions and from the robot file's (rigid, in the calibrated device frame), and whether it
    holds: the residuals' RMS per axis (points that carry covariances weighed by them, as the fit
    weighed its own) within `HOLDS_FACTOR` of what the fit expects there, its residual noise and
    its parameters' uncertainty at these poses (`expected_mm`). The samples are checked as `calibrate_tree` checks them (joint limits,
    with a hint where they look like degrees)."""
    model = load_tree_calibration(folder)
    samples, measured, points, cov = _aligned(model, folder, dataset)
    rigid = Elastic(np.zeros_like(model.elastic.joint), np.zeros_like(model.elastic.lateral))
    device_tip = model.tree.tip_names.index(model.device_on) if model.device_on else -1
    nominal_tree = load_urdf_tree(
        dataset.urdf, base_link=model.tree.link_names[0], tips=list(model.tree.tip_names)
    )
    nominal = np.asarray(
        deflected_tips(
            nominal_tree, rigid, jnp.asarray(samples.q), model.points, model.T_device_root, None, device_tip
        )
    )
    calibrated = model.predict(samples.q)
    residual = calibrated - points
    if cov is not None:  # each point in units of its own noise, scaled to the dataset's
        L = np.linalg.cholesky(np.where(measured[..., None, None], cov, np.eye(3)))
        residual = 1e-3 * dataset.noise_mm * np.linalg.solve(L, residual[..., None])[..., 0]
    # What the fit's own uncertainty adds at these poses (per axis, RMS over the measured points).
    param_mm, var = 0.0, np.zeros(measured.shape)
    if model.covariance is not None:
        var = np.trace(model.predict_covariance(samples.q), axis1=-2, axis2=-1) / 3.0
        param_mm = 1e3 * float(np.sqrt(var[measured].mean()))
    expected = float(np.hypot(model.noise_mm, param_mm))
    where = np.argwhere(measured)
    far = _far_points(
        residual[measured],
        np.tile((1e-3 * expected) ** 2 * np.eye(3), (len(where), 1, 1)),
        np.ones(len(where), bool),
    )
    left = [(int(where[k][0]), int(where[k][1]), z) for k, z in far]
    notes = []
    if len(left) > OUTLIER_SHARE * measured.sum():
        notes.append(
            f"{len(left)} points lie over {OUTLIER_SIGMAS:g} sigma from the calibration: too many to be bad samples"
        )
        left = []
    elif left:
        notes.append(
            f"{len(left)} of {int(measured.sum())} points left out as bad samples (over {OUTLIER_SIGMAS:g} sigma): "
            + ", ".join(
                f"sample {i} tip {model.tree.tip_names[t]!r} ({z:.0f} sigma)" for i, t, z in left[:10]
            )
        )
    for i, t, _ in left:
        measured[i, t] = False
    rms_axis = 1e3 * float(np.sqrt(np.mean(residual[measured] ** 2)))
    tips = _per_tip(model, measured, residual, var, points, calibrated=calibrated, nominal=nominal)
    if model.status != "ok":
        notes.append(f"the calibration itself was {model.status}")
    if model.covariance is None:
        notes.append(f"the calibration has no {COVARIANCE_FILE}: its parameters' uncertainty is not weighed")
    if rms_axis > NOISE_FACTOR * dataset.noise_mm and rms_axis <= HOLDS_FACTOR * expected:
        notes.append(
            f"the residuals are over {NOISE_FACTOR:g}x the dataset's stated noise {dataset.noise_mm:g} mm"
        )
    loose = [n for n, v in tips.items() if v["expected_mm"] > LOOSE_TIP * model.noise_mm]
    if loose:
        notes.append(
            f"tip(s) {loose}: the calibration predicts them only to "
            + ", ".join(f"{tips[n]['expected_mm']:.3g} mm" for n in loose)
            + " per axis (their branches barely measured, or never: held at the robot file's values), so "
            "holding says little there; calibrate with samples of them"
        )
    worse = [n for n, v in tips.items() if v["calibrated_mean_mm"] > v["nominal_mean_mm"]]
    if worse and len(worse) == len(tips):
        notes.append(
            "the calibration predicts these samples worse than the robot file does: they are of another robot "
            "of this model, or the device moved since (`jaxcal check RESULT DATASET` tells a moved device)"
        )
    failing = [n for n, v in tips.items() if not v["holds"]]
    if failing and rms_axis <= HOLDS_FACTOR * expected:
        notes.append(
            f"tip(s) {failing} do not hold on their own (RMS per axis "
            + ", ".join(
                f"{tips[n]['rms_per_axis_mm']:.3g} mm against {tips[n]['expected_mm']:.3g}" for n in failing
            )
            + "): a branch the calibration did not measure, or one that changed since"
        )
    return {
        "tips": tips,
        "rms_per_axis_mm": rms_axis,
        "weighted_by_covariances": samples.covariance is not None,
        "fit_noise_mm": model.noise_mm,
        "parameters_mm": param_mm if model.covariance is not None else None,
        "expected_mm": expected,
        "ratio": rms_axis / expected,
        "holds": bool(rms_axis <= HOLDS_FACTOR * expected) and not failing,
        "calibration_status": model.status,
        "left_out": [{"sample": i, "tip": model.tree.tip_names[t], "sigmas": z} for i, t, z in left],
        "notes": notes,
    }


def tip_predictors(folder) -> dict[str, Predictor]:
    """A `jaxcal.certification.Predictor` per measured tip of a tree calibration's folder, for
    `certify`: each tip's point and its covariance from the fit's (`tree_covariance.json`), the
    fit's residual noise beyond the stated one as the unexplained scatter, over the robot file's
    joint limits. Only the device's frame (`frame="fixed"`)."""
    folder = Path(folder)
    folder = folder.parent if folder.name == RESULT_FILE else folder
    model = load_tree_calibration(folder)
    if model.covariance is None:
        raise ValueError(
            f"{shown(folder)!r}: no {COVARIANCE_FILE}: calibrate again with this jaxcal to certify it"
        )
    if model.status == "failed":
        raise ValueError(f"{shown(folder)!r}: the calibration failed: there is nothing to certify")
    notes = (
        [] if model.status == "ok" else [f"the calibration is {model.status}: these figures take it as right"]
    )
    stated = model.stated_noise_mm or model.noise_mm
    excess = max(model.noise_mm**2 - stated**2, 0.0)
    if model.stated_noise_mm is None:
        notes.append("the result does not state the device's noise: the residuals' scatter is not counted")
    elif model.point_covariances and excess > 0:
        # The points' own covariances (a camera's PnP) understated, not the model: that is in the
        # parameters' covariance already (scaled by the residuals), and adds nothing isotropic.
        notes.append(
            f"the residuals are {model.noise_mm / stated:.2f}x what the points' covariances say: taken as "
            "those covariances understated (the parameters' covariance is scaled by it)"
        )
        excess = 0.0
    travel = actuated_limits(folder / "calibrated.urdf", model.tree)
    out = {}
    for t, tip in enumerate(model.tree.tip_names):
        if tip == model.device_on:
            continue

        def covariances(q, frame="fixed", t=t):
            if frame != "fixed":
                raise ValueError("a tree calibration is certified in its device's frame only (frame 'fixed')")
            return model.predict_covariance(q)[:, t]

        def base_points(q, t=t):
            root = dataclasses.replace(model, T_device_root=np.eye(4), device_on=None)
            return root.predict(q)[:, t]

        out[tip] = Predictor(
            kind=f"tree tip {tip!r}",
            result=str(folder / RESULT_FILE),
            joint_names=tuple(model.tree.actuated_names),
            covariances=covariances,
            base_points=base_points,
            scatter_var=1e-6 * excess,
            model=None,
            travel=travel,
            workspace=model.covariance[2],
            notes=tuple(notes),
        )
    return out


def check_tree(folder, dataset: TreeDataset) -> DriftCheck:
    """`jaxcal check` of a tree calibration (`folder`) on a short later capture (`dataset`): has its
    device moved since? `jaxcal.drift`'s test: the device's pose fitted as a twist against the
    calibrated predictions, the residuals whitened by the points' scatter (the fit's residual
    variance times the stated noise, or the points' own covariances) and the calibration's own
    uncertainty at these poses (`prediction_jacobian`), and its chi-square against what a device
    that stayed would give. A device on a tip (a head camera) moves on that tip's mount."""
    model = load_tree_calibration(folder)
    if model.covariance is None:
        raise ValueError(
            f"{shown(folder)!r}: no {COVARIANCE_FILE}: calibrate again with this jaxcal to check it"
        )
    samples, measured, points, cov = _aligned(model, folder, dataset)
    S = int(measured.sum())
    if 3 * S <= 6:
        raise ValueError(
            f"{shown(dataset.folder)!r}: a check of the device's pose needs 3 measured points, got {S}"
        )
    G, Sigma = model.prediction_jacobian(samples.q)
    G = G[measured]
    factor2 = (model.noise_mm / (model.stated_noise_mm or model.noise_mm)) ** 2
    blocks = (
        factor2 * cov[measured]
        if cov is not None
        else np.tile((1e-3 * model.noise_mm) ** 2 * np.eye(3), (S, 1, 1))
    )
    y, y_hat, where = points[measured], model.predict(samples.q)[measured], np.argwhere(measured)
    keep, left = np.ones(S, bool), []
    for rounds in range(4):  # bad samples (a misread plate) left out as `verify` leaves them out
        theta, C, T, rss = _fit_device(y[keep], y_hat[keep], G[keep], Sigma, blocks[keep])
        bad = _far_points(y - _moved(theta, y_hat), blocks + np.einsum("sak,kl,sbl->sab", G, Sigma, G), keep)
        if rounds == 3 or not bad or len(left) + len(bad) > OUTLIER_SHARE * S or keep.sum() - len(bad) < 3:
            break
        left += bad
        keep[[k for k, _ in bad]] = False
    move = np_se3_exp(theta[:6])
    T_now = model.T_device_root @ move if model.device_on else np.linalg.inv(move) @ model.T_device_root
    names, what = (str(folder), str(dataset.folder)), "camera" if model.device_on else "device"
    samples_seen = int(measured.any(axis=1).sum())
    c = verdict(
        theta,
        C,
        float(T),
        float(rss),
        3 * int(keep.sum()) - 6,
        samples=samples_seen,
        joint_names=model.tree.actuated_names,
        T_now=T_now,
        names=names,
        what=what,
        frame="T_device",
    )
    notes = []
    if left:
        notes.append(
            f"{len(left)} of {S} points left out as bad samples (over {OUTLIER_SIGMAS:g} sigma): "
            + ", ".join(
                f"sample {where[k][0]} tip {model.tree.tip_names[where[k][1]]!r} ({z:.0f} sigma)"
                for k, z in left
            )
        )
    if model.status != "ok":
        notes.append(f"the calibration itself was {model.status}: what it misfits may read as a move")
    advice = c.advice
    if not c.residual.fits_rigidly:
        advice = (
            "check that the capture is of the same robot, device and points (reflectors, plates); if it is, "
            "something else changed (the robot, a mount): calibrate again"
        )
    return dataclasses.replace(c, message="; ".join([c.message, *notes]), advice=advice)


def _far_points(e: np.ndarray, B: np.ndarray, keep: np.ndarray) -> list[tuple[int, float]]:
    """The kept points whose residuals `e` `(S, 3)` lie `OUTLIER_SIGMAS` beyond their covariances
    `B` (scaled by the residuals' robust scale where that is larger), as (point, sigmas); none
    where every residual is large and none lies `FAR_BEYOND` of the rest."""
    z2 = np.einsum("sa,sa->s", e, np.linalg.solve(B, e[..., None])[..., 0])
    scale2 = max(1.0, float(np.median(z2[keep])) / 2.366)  # chi-square(3)'s median
    if scale2 > NOISE_FACTOR**2 and z2[keep].max() < FAR_BEYOND**2 * scale2:
        return []
    return [
        (int(k), float(np.sqrt(z2[k] / scale2)))
        for k in np.flatnonzero(keep & (z2 > OUTLIER_SIGMAS**2 * scale2))
    ]


def _moved(theta, y_hat):
    """The points `y_hat` seen from the device moved by the twist `theta[:6]` (`jaxcal.drift`'s model)."""
    T = np.linalg.inv(np_se3_exp(theta[:6]))
    return y_hat @ T[:3, :3].T + T[:3, 3]


def _fit_device(y, y_hat, G, Sigma, blocks):
    """`jaxcal.drift.fit_drift` of the device's twist, the residuals' covariance `R` being the
    points' `blocks` and the calibration's uncertainty `G Sigma G^T` (`G` `(S, 3, k)`)."""
    S = len(y)
    G = G.reshape(3 * S, -1)
    R = G @ Sigma @ G.T
    for i in range(S):
        R[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] += blocks[i]
    out = fit_drift(y, y_hat, np.zeros((S, 3, 0)), whitening(R), offsets=False)
    return tuple(np.asarray(a) for a in out)
