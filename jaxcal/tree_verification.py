"""A tree calibration read back from its folder, and checked against samples it was not fitted on
(`jaxcal verify RESULT DATASET` with a tree calibration; docs/trees.md).

`load_tree_calibration` rebuilds what `jaxcal.trees.save_tree_calibration` wrote (the calibrated
URDF and `tree_result.json`) into a model whose `predict(q)` is the calibration's: the sag, the
mass corrections and a harmonic's phase included. Every field is checked against the robot file it
names (a parameter of a joint or link that is not there, a pose that is not 4x4, a value that is
not a finite number are refused by name), so a damaged file is never taken for a changed robot.
`verify_tree` compares the model's predictions with new samples, per tip.
"""

from dataclasses import dataclass
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ._kinematics import joint_motion
from ._tree import KinematicTree
from ._treefit import Elastic, deflected_tips, tree_layout
from .io._files import shown
from .io.tree_dataset import TreeDataset, read_json_object
from .io.urdf_tree import load_urdf_tree
from .trees import NOISE_FACTOR, RESULT_FILE, checked_samples

__all__ = ["CalibratedTree", "load_tree_calibration", "verify_tree"]

#: A tree calibration holds on new samples while their residuals' RMS per axis stays within this
#: factor of the fit's own residual noise (the parameters' uncertainty adds a few percent).
HOLDS_FACTOR = 1.5


@dataclass(frozen=True)
class CalibratedTree:
    """A tree calibration read back from the folder `save_tree_calibration` wrote: the calibrated
    tree, its loads and terms, the device and the measured points, and the fit's verdict and
    residual noise (mm per axis)."""

    tree: KinematicTree
    elastic: Elastic
    harmonic: np.ndarray
    points: np.ndarray
    T_device_root: np.ndarray
    device_on: str | None
    noise_mm: float
    status: str

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
        raise ValueError(f"tree calibration {shown(path)!r}: field {field} must be {want}, got {value!r}")
    return a


def _object(doc, name: str, path: Path) -> dict:
    if not isinstance(doc.get(name), dict):
        raise ValueError(
            f"tree calibration {shown(path)!r}: field {name!r} must be an object, got {doc.get(name)!r}"
        )
    return doc[name]


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
    return CalibratedTree(
        tree=tree,
        elastic=elastic,
        harmonic=of(f"{j}.harmonic.{k}" for j in tree.joint_names for k in ("cos", "sin")).reshape(n, 2),
        points=np.stack([_numbers(p, (3,), path, f"tip_points_m[{t!r}]") for t, p in points.items()]),
        T_device_root=_numbers(doc.get("T_device"), (4, 4), path, "'T_device'"),
        device_on=device_on,
        noise_mm=float(noise),
        status=str(doc.get("status")),
    )


def verify_tree(folder, dataset: TreeDataset) -> dict:
    """A tree calibration (`folder`) against samples it was not fitted on (`dataset`, of the same
    robot and device): per tip, the measured points' distance (mm) from the calibration's
    predictions and from the robot file's (rigid, in the calibrated device frame), and whether it
    holds (`HOLDS_FACTOR`; points that carry covariances weighed by them, as the fit weighed
    its own). The samples are checked as `calibrate_tree` checks them (joint limits,
    with a hint where they look like degrees)."""
    model = load_tree_calibration(folder)
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
    tips = {}
    for t, name in enumerate(model.tree.tip_names):
        seen = measured[:, t]
        if not seen.any():
            continue
        tips[name] = {"samples": int(seen.sum())}
        for kind, p in (("calibrated", calibrated), ("nominal", nominal)):
            d = 1e3 * np.linalg.norm(p[seen, t] - points[seen, t], axis=-1)
            tips[name] |= {
                f"{kind}_mean_mm": float(d.mean()),
                f"{kind}_rms_mm": float(np.sqrt(np.mean(d**2))),
            }
            tips[name][f"{kind}_max_mm"] = float(d.max())
    residual = calibrated - points
    if samples.covariance is not None:  # each point in units of its own noise, scaled to the dataset's
        cov = np.stack([samples.covariance[:, max(k, 0)] for k in order], 1)
        L = np.linalg.cholesky(np.where(measured[..., None, None], cov, np.eye(3)))
        residual = 1e-3 * dataset.noise_mm * np.linalg.solve(L, residual[..., None])[..., 0]
    rms_axis = 1e3 * float(np.sqrt(np.mean(residual[measured] ** 2)))
    notes = []
    if model.status != "ok":
        notes.append(f"the calibration itself was {model.status}")
    if rms_axis > NOISE_FACTOR * dataset.noise_mm and rms_axis <= HOLDS_FACTOR * model.noise_mm:
        notes.append(
            f"the residuals are over {NOISE_FACTOR:g}x the dataset's stated noise {dataset.noise_mm:g} mm"
        )
    return {
        "tips": tips,
        "rms_per_axis_mm": rms_axis,
        "fit_noise_mm": model.noise_mm,
        "ratio": rms_axis / model.noise_mm,
        "holds": bool(rms_axis <= HOLDS_FACTOR * model.noise_mm),
        "calibration_status": model.status,
        "notes": notes,
    }
