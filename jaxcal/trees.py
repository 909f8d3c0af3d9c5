"""Calibrating robots that are trees: a humanoid's torso and two arms, a dual-arm cell.

    tree = load_urdf_tree("robot.urdf", tips=["left_hand", "right_hand"])
    samples = read_tree_samples("poses.csv", tree)
    result = calibrate_tree(tree, samples, noise_mm=0.05)
    save_tree_calibration(result, "out/", source_urdf="robot.urdf")

A tracker (or motion capture) measures a point on several tips at once, at stop-and-shoot poses;
the torso's errors are then seen through both arms and separated from each arm's. The fit
(`jaxcal._treefit`) recovers every joint origin, zero offset and coupled joint's multiplier the
data determine, the measured points on the tips, the device's pose, and the gravity-driven
elasticity of joints and links that cross-validation keeps. What the data cannot see is held at
its robot-file value and named by branch (`held`: `shared` for joints on several tips' paths, a
tip's name for its own branch, and each tip no sample measures).
"""

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._dh import dh_table
from ._npgeom import kabsch
from ._progress import working
from ._tree import KinematicTree, branch, held_by_branch, tip_poses
from ._treefit import (
    FAMILIES,
    Elastic,
    TreeFit,
    TreeSamples,
    body_of,
    cross_validate_terms,
    fit_tree,
    linearised,
    predict,
    predicted_covariance,
    problem_of,
)
from ._treelayout import TreeLayout, tree_layout
from .io._files import atomic_directory
from .io.dh_tables import dh_table_json
from .io.tree_dataset import covariance_noise_mm, read_tree_samples
from .io.urdf_tree import save_urdf_tree

__all__ = [
    "TreeCalibration",
    "TreeSamples",
    "calibrate_tree",
    "read_tree_samples",
    "save_tree_calibration",
]

#: The estimated noise may exceed the stated one by this factor before the result is suspect.
NOISE_FACTOR = 2.0
#: A compliance this many standard deviations below zero is a negative stiffness: suspect.
NEGATIVE_SIGMAS = 3.0
#: A measured point this many sigmas from the fit (its whitened residual's norm; sigma: the
#: stated noise, or the residuals' own robust scale where larger) is left out as a bad sample
#: (a misread marker); more than `OUTLIER_SHARE` of the points left out makes the result suspect.
OUTLIER_SIGMAS, OUTLIER_SHARE = 6.0, 0.05
#: Where every residual is large, a point this many of their robust sigmas from the fit is
#: still a bad sample (the few that pulled the fit), not the model's misfit.
FAR_BEYOND = 10.0
#: The residuals' noise below the stated one by this factor: the noise is overstated (which
#: frees too little and claims too much): suspect.
OVERSTATED = 3.0


@dataclass(frozen=True)
class TreeCalibration:
    """A calibrated tree: `tree` (geometry: origins, zero offsets, couplings), the device's
    pose `T_device_root`, the measured `points` on the tips (tip frames, m), the `elastic`
    compliances with the loads' `mass` corrections, and `harmonic` angle errors (zero where not
    kept), the fit itself, what was
    `held` by branch, and a `status` (`ok`, or `suspect` with `notes` saying why)."""

    tree: KinematicTree
    nominal: KinematicTree
    T_device_root: np.ndarray
    points: np.ndarray
    elastic: Elastic
    harmonic: np.ndarray
    fit: TreeFit
    layout: TreeLayout
    held: dict
    status: str
    notes: tuple[str, ...]
    _problem: object
    device_on: str | None = None

    def parameters(self) -> dict[str, tuple[float, float]]:
        """Every freed parameter's correction from the robot file and its standard deviation,
        in its own unit (m, rad, rad/(N m), or relative for a multiplier)."""
        values = self.fit.values(self.layout)
        return {
            n: (values[n], float(self.fit.std[i]))
            for i, n in enumerate(self.layout.names)
            if self.fit.free[i]
        }

    def _poses(self, q) -> np.ndarray:
        q = np.asarray(q, np.float64)
        if q.ndim != 2 or q.shape[1] != self.tree.num_actuated:
            raise ValueError(
                f"q must be (poses, {self.tree.num_actuated}): one row per pose of the actuated joints "
                f"{self.tree.actuated_names}; got shape {q.shape}"
            )
        return q

    def predict(self, q) -> np.ndarray:
        """The measured points predicted at commanded positions `q` `(n, actuated)`, device frame."""
        return np.asarray(predict(jnp.asarray(self.fit.u), self._problem, jnp.asarray(self._poses(q))))

    def predict_covariance(self, q) -> np.ndarray:
        """The covariance `(n, tips, 3, 3)` (m^2, device frame) of `predict(q)`: what the fit's
        uncertainty leaves in the predicted points."""
        q = self._poses(q)
        if not len(q):
            return np.zeros((0, len(self.tree.tip_names), 3, 3))
        return predicted_covariance(self.fit.u, self.fit.cov, self._problem, q)


def initial_device_pose(tree: KinematicTree, samples: TreeSamples, points: np.ndarray) -> np.ndarray:
    """The device's pose from the robot file's predictions of the measured points and the
    measurements (a rigid fit over every measured tip), for the least squares to start from."""
    tips = np.asarray(jnp.stack([tip_poses(tree, jnp.asarray(q)) for q in samples.q]))
    model = np.einsum("ntab,tb->nta", tips[..., :3, :3], points) + tips[..., :3, 3]
    return kabsch(model[samples.measured], samples.points[samples.measured])


def checked_samples(
    tree: KinematicTree, samples: TreeSamples, noise_mm: float, limits, points
) -> TreeSamples:
    """`samples` as float and bool arrays, refused naming the sample (0-based), joint or tip when
    they cannot be the tree's: shapes, non-finite numbers, poses outside the limits (a
    continuous joint has none), too few measurements for what is fitted."""
    try:
        q, pts = np.asarray(samples.q, np.float64), np.asarray(samples.points, np.float64)
        measured = np.asarray(samples.measured)
    except (TypeError, ValueError) as e:
        raise ValueError(f"samples must hold numbers: {e}") from None
    n, a, tips = len(q), tree.num_actuated, len(tree.tip_names)
    if q.shape != (n, a) or n == 0:
        raise ValueError(
            f"samples.q has shape {q.shape}; expected (poses, {a}) for the actuated joints {tree.actuated_names}"
        )
    if pts.shape != (n, tips, 3) or measured.shape != (n, tips) or measured.dtype != bool:
        raise ValueError(
            f"samples.points must be ({n}, {tips}, 3) and samples.measured a ({n}, {tips}) bool array for the tips "
            f"{tree.tip_names}; got {pts.shape} and {measured.shape} {measured.dtype}"
        )
    if points is not None and np.shape(points) != (tips, 3):
        raise ValueError(
            f"points must be ({tips}, 3): one [x, y, z] per tip of {tree.tip_names}; got {np.shape(points)}"
        )
    if not np.all(np.isfinite(q)):
        row, col = np.argwhere(~np.isfinite(q))[0]
        raise ValueError(f"sample {row}: joint {tree.actuated_names[col]!r} is not a number")
    bad = measured & ~np.all(np.isfinite(pts), axis=-1)
    if bad.any():
        row, t = np.argwhere(bad)[0]
        raise ValueError(
            f"sample {row}: tip {tree.tip_names[t]!r} is marked measured but its point is not finite"
        )
    if not measured.any():
        raise ValueError("no sample measures any tip")
    if not noise_mm > 0:
        raise ValueError(f"noise_mm must be positive, got {noise_mm}")
    cov = samples.covariance
    if cov is not None:
        cov = np.asarray(cov, np.float64)
        if cov.shape != (n, tips, 3, 3):
            raise ValueError(f"samples.covariance must be ({n}, {tips}, 3, 3), got {cov.shape}")
        sym = 0.5 * (cov + np.swapaxes(cov, -1, -2))
        finite = np.all(np.isfinite(sym), axis=(-1, -2))
        smallest = np.linalg.eigvalsh(np.where(finite[..., None, None], sym, np.eye(3))).min(axis=-1)
        ok = finite & (smallest > 0)
        if (measured & ~ok).any():
            row, t = np.argwhere(measured & ~ok)[0]
            raise ValueError(
                f"sample {row}: the covariance of tip {tree.tip_names[t]!r} is not finite and positive definite"
            )
        cov = sym
    if limits is not None:
        limits = np.asarray(limits, np.float64)
        if limits.shape != (a, 2):
            raise ValueError(
                f"limits must be ({a}, 2): lower and upper of each actuated joint; got {limits.shape}"
            )
        out = (q < limits[:, 0] - 1e-9) | (q > limits[:, 1] + 1e-9)
        if out.any():
            row, col = np.argwhere(out)[0]
            raise ValueError(
                f"sample {row}: joint {tree.actuated_names[col]!r} at {q[row, col]:.6g} is outside its limits "
                f"[{limits[col, 0]:.6g}, {limits[col, 1]:.6g}] (radians or metres: a file in degrees?)"
            )
    return TreeSamples(q, pts, measured, samples.truth, cov)


def _verdict(
    fit: TreeFit, layout: TreeLayout, noise_mm: float, samples: TreeSamples, tree, device_on=None
) -> tuple[str, tuple[str, ...]]:
    notes = []
    coordinates, freed = 3 * int(samples.measured.sum()), int(fit.free.sum())
    if coordinates - freed < freed:
        notes.append(
            f"{coordinates} measured coordinates for {freed} freed parameters: too few to check the fit against "
            "(fewer than two per parameter); measure more poses"
        )
    if fit.noise_mm > NOISE_FACTOR * noise_mm:
        notes.append(
            f"the residuals' noise {fit.noise_mm:.3g} mm is over {NOISE_FACTOR:g}x the stated {noise_mm:.3g} mm: "
            "the model does not explain the data (a bad sample, a loose mount, a term missing) or the noise is understated"
            + (
                "; a thousandfold gap means wrong units (joints in radians or metres, points in metres)"
                if fit.noise_mm > 1e3 * noise_mm
                else ""
            )
            + (
                "; with compliance kept, the robot file's centres of mass (family `mass`), or on a very soft body "
                "where along its joint's axis a link bends, which the rigid geometry cannot place (docs/trees.md)"
                if {"joint", "lateral"} & set(fit.families)
                else ""
            )
        )
    if fit.noise_mm < noise_mm / OVERSTATED:
        notes.append(
            f"the residuals' noise {fit.noise_mm:.3g} mm is under 1/{OVERSTATED:g} of the stated {noise_mm:.3g} mm: "
            "the stated noise (or the samples' covariances) is overstated, so the fit frees too little and its "
            "claims are too wide"
            + (
                "; a thousandfold gap means wrong units (mm or mm^2 given for m or m^2)"
                if fit.noise_mm < 1e-3 * noise_mm
                else "; covariances in mm^2 where m^2 is meant?"
                if samples.covariance is not None and fit.noise_mm < 0.1 * noise_mm
                else ""
            )
        )
    values = fit.u * layout.scales
    compliance = layout.family("joint", "lateral") & fit.free
    negative = compliance & (values < -NEGATIVE_SIGMAS * np.where(fit.std > 0, fit.std, np.inf))
    if negative.any():
        notes.append(
            "negative compliance (a stiffness below zero) for "
            + ", ".join(layout.names[i] for i in np.flatnonzero(negative))
            + ": gravity's load is not what the robot file's masses say"
        )
    unseen = [
        t for t, seen in zip(tree.tip_names, samples.measured.any(axis=0)) if not seen and t != device_on
    ]
    if unseen:
        notes.append(f"tips {unseen} were never measured: their branches keep the robot file's values")
    return ("suspect" if notes[: len(notes) - bool(unseen)] else "ok"), tuple(notes)


def _leave_out_outliers(problem, layout, samples: TreeSamples, fit: TreeFit):
    """Refit without the points `OUTLIER_SIGMAS` from the fit, the grossest first (a round
    leaves out those within a tenth of the worst's squared distance), until none is left:
    the problem, samples and fit, and the points left out as (sample, tip, sigmas). Where the
    residuals' robust scale is over `NOISE_FACTOR` times the noise and no point lies
    `FAR_BEYOND` of it from the fit, the model misfits them all: nothing is left out, and the
    verdict says so."""
    left = []
    for _ in range(8):
        r = linearised(jnp.asarray(fit.u), jnp.asarray(fit.free, jnp.float64), problem)[0]
        z2 = (np.asarray(r).reshape(*samples.measured.shape, 3) ** 2).sum(axis=-1)
        scale2 = max(1.0, float(np.median(z2[samples.measured])) / 2.366)  # chi-square(3)'s median
        bad = z2 > max(OUTLIER_SIGMAS**2 * scale2, 0.1 * z2.max())
        # Residuals all large and none far beyond the rest: the model misfits (the verdict's
        # case); a few far beyond a large bulk: they are what inflates it.
        if not bad.any() or (scale2 > NOISE_FACTOR**2 and z2.max() < FAR_BEYOND**2 * scale2):
            break
        left += [(int(i), int(t), float(np.sqrt(z2[i, t] / scale2))) for i, t in np.argwhere(bad)]
        samples = dataclasses.replace(samples, measured=samples.measured & ~bad)
        problem = dataclasses.replace(problem, weight=jnp.asarray(samples.measured, jnp.float64))
        fit = dataclasses.replace(fit_tree(problem, layout, fit.families), cv_mm=fit.cv_mm)
    return problem, samples, fit, left


def _terms_fit(problem, layout, families, show_progress: bool) -> TreeFit:
    """The fit with the term `families`, or (None) with those cross-validation keeps."""
    if families is None:
        # A minute on a 2-core CPU (the first solve compiles): a line every few seconds in a pipe.
        with working(show_progress, "tree calibration: cross-validating the terms"):
            return cross_validate_terms(problem, layout)
    unknown = set(families) - set(FAMILIES)
    if unknown:
        raise ValueError(f"unknown term families {sorted(unknown)}; known: {FAMILIES}")
    return fit_tree(problem, layout, tuple(families))


def _left_out_note(left, measured: int, tips) -> str:
    """The verdict's note on the points `_leave_out_outliers` left out of `measured`."""
    many = len(left) > OUTLIER_SHARE * measured
    why = (
        "from the fit: too many to trust the rest, check the device and the mounts"
        if many
        else "from the fit"
    )
    return (
        f"{len(left)} of {measured} measured points left out as bad samples (over {OUTLIER_SIGMAS:g} sigma {why}): "
        + ", ".join(f"sample {i} tip {tips[t]!r} ({z:.0f} sigma)" for i, t, z in left[:10])
        + (" ..." if len(left) > 10 else "")
    )


def calibrate_tree(
    tree: KinematicTree,
    samples: TreeSamples,
    *,
    noise_mm: float | None = None,
    families=None,
    points=None,
    T_device_root=None,
    device_on: str | None = None,
    limits=None,
    show_progress: bool = True,
) -> TreeCalibration:
    """Calibrate `tree` from points measured on its tips.

    **Arguments:**
    - `tree`: the robot file's tree (`jaxcal.io.urdf_tree.load_urdf_tree`), its tips those the
      samples measure.
    - `samples`: the poses and measured points (`read_tree_samples`).
    - `noise_mm`: the device's noise (1-sigma per axis, default 0.1 mm), which weighs the
      samples and judges what the data determine; samples with their own `covariance` (a
      camera's PnP) are weighed by it instead, and their stated noise is its RMS per axis.
    - `families`: the non-geometric terms to fit (of `jaxcal._treefit.FAMILIES`); default
      `None` lets K-fold cross-validation choose.
    - `points`: the measured points' nominal positions on the tips `(tips, 3)` (m, tip frame;
      default the tips' origins); `T_device_root`: the device's pose (default: a rigid fit).
    - `device_on`: the tip the device rides on (a head camera seeing the hands); the points are
      then in its frame, `T_device_root` is its pose in that tip's frame (default: the tip's
      frame itself), and joints that move both it and a measured tip are not seen (held).
    - `limits`: `(actuated, 2)` joint limits to check the poses against
      (`jaxcal.io.urdf_tree.actuated_limits`).

    Raises `ValueError` naming the sample and joint or tip for malformed input.
    """
    if isinstance(families, str):
        raise ValueError(
            f"families must be a list of {list(FAMILIES)} (or None), got the string {families!r}"
        )
    if samples.covariance is not None and noise_mm is not None:
        raise ValueError("the samples carry their own covariance: noise_mm is not used with them")
    samples = checked_samples(tree, samples, 0.1 if noise_mm is None else noise_mm, limits, points)
    if samples.covariance is not None:  # the stated noise: their RMS per axis
        noise_mm = covariance_noise_mm(samples)
    noise_mm = 0.1 if noise_mm is None else noise_mm
    device_tip = -1
    if device_on is not None:
        if device_on not in tree.tip_names:
            raise ValueError(f"device_on {device_on!r} is not one of the tips {tree.tip_names}")
        device_tip = tree.tip_names.index(device_on)
        if samples.measured[:, device_tip].any():
            raise ValueError(f"the device rides on tip {device_on!r}: no sample may measure that tip's point")
    layout = tree_layout(tree)
    points = np.zeros((len(tree.tip_names), 3)) if points is None else np.asarray(points, np.float64)
    if T_device_root is None:
        T_device_root = initial_device_pose(tree, samples, points) if device_tip < 0 else np.eye(4)
    problem = problem_of(tree, layout, samples, T_device_root, points, noise_mm, device_tip)
    fit = _terms_fit(problem, layout, families, show_progress)
    measured = int(samples.measured.sum())
    problem, samples, fit, left = _leave_out_outliers(problem, layout, samples, fit)
    if left and families is None:  # the bad points swayed the terms' choice: chosen again without them
        fit = _terms_fit(problem, layout, None, show_progress)
        problem, samples, fit, more = _leave_out_outliers(problem, layout, samples, fit)
        left += more
    calibrated, T_dev, pts, elastic, harmonic = body_of(jnp.asarray(fit.u), problem)
    candidates = ~layout.family(*FAMILIES) | layout.family(*fit.families)
    status, notes = _verdict(fit, layout, noise_mm, samples, tree, device_on)
    if left:
        status = "suspect" if len(left) > OUTLIER_SHARE * measured else status
        notes += (_left_out_note(left, measured, tree.tip_names),)
    return TreeCalibration(
        tree=calibrated,
        nominal=tree,
        T_device_root=np.asarray(T_dev),
        points=np.asarray(pts),
        elastic=Elastic(
            *(np.asarray(a) for a in (elastic.joint, elastic.lateral, elastic.moments, elastic.tilt))
        ),
        harmonic=np.asarray(harmonic),
        fit=fit,
        layout=layout,
        held=held_by_branch(tree, layout, fit.free, candidates),
        status=status,
        notes=notes,
        _problem=problem,
        device_on=device_on,
    )


#: What `save_tree_calibration` writes the result into, and the freed parameters' covariance.
RESULT_FILE = "tree_result.json"
COVARIANCE_FILE = "tree_covariance.json"


def _json(result: TreeCalibration) -> dict:
    tree = result.tree
    return {
        "status": result.status,
        "notes": list(result.notes),
        "noise_mm": result.fit.noise_mm,
        "stated_noise_mm": 1e3 * float(result._problem.sigma),
        "point_covariances": result._problem.whiten is not None,
        "terms_kept": list(result.fit.families),
        "cross_validation_mm": result.fit.cv_mm,
        "parameters": {n: {"value": v, "std": s} for n, (v, s) in result.parameters().items()},
        "held": result.held,
        # A fixed device's T_device_root, or with device_on its pose in that tip's frame.
        "device_on": result.device_on,
        "T_device": np.asarray(result.T_device_root).tolist(),
        "tip_points_m": {t: p.tolist() for t, p in zip(tree.tip_names, result.points)},
        "base_link": tree.link_names[0],
        # calibrated.urdf turns these into its origins; a harmonic's phase needs them back.
        "zero_offsets_rad": dict(zip(tree.joint_names, np.asarray(tree.zero_offset).tolist())),
        "coupling": {
            tree.joint_names[j]: {
                tree.actuated_names[a]: float(tree.coupling[j, a])
                for a in np.flatnonzero(np.asarray(tree.coupling)[j])
            }
            for j in tree.coupled
        },
    }


def _covariance_json(result: TreeCalibration) -> dict:
    """What `certify` needs beside the result: the freed parameters' covariance in their own units
    (`tree_result.json`'s), by name, and the configurations fitted (the calibrated workspace)."""
    free = np.flatnonzero(result.fit.free)
    s = result.layout.scales[free]
    return {
        "parameters": [result.layout.names[i] for i in free],
        "matrix": (np.asarray(result.fit.cov)[np.ix_(free, free)] * np.outer(s, s)).tolist(),
        "configurations": np.asarray(result._problem.q).tolist(),
    }


def save_tree_calibration(
    result: TreeCalibration, folder, *, source_urdf, overwrite: bool = False, inputs=(), checked=None
) -> Path:
    """Write `calibrated.urdf` (a copy of `source_urdf` with the calibrated geometry and the
    mimic laws kept), `tree_result.json` (every parameter with its standard deviation, the
    terms kept, what was held by branch, the verdict), `tree_covariance.json` (the freed
    parameters' covariance, for `certify` and `verify`) and each tip's branch as a modified-DH
    table (`TIP_mdh.json`, `branch_table`) into `folder`, atomically: an existing
    result folder is replaced only with `overwrite`, and never one that holds the robot file or
    `inputs` (`checked`: `check_output_dir`'s answer when the run began)."""
    folder = Path(folder)
    with atomic_directory(
        folder, overwrite=overwrite, inputs=(Path(source_urdf), *inputs), checked=checked
    ) as tmp:
        save_urdf_tree(result.tree, tmp / "calibrated.urdf", source=source_urdf)
        (tmp / RESULT_FILE).write_text(json.dumps(_json(result), indent=2) + "\n")
        (tmp / COVARIANCE_FILE).write_text(json.dumps(_covariance_json(result)) + "\n")
        for tip in result.tree.tip_names:
            doc = branch_table(result, tip)
            if doc is not None:
                (tmp / f"{tip}_mdh.json").write_text(json.dumps(doc, indent=2) + "\n")
    return folder


def _table_jacobian(u, problem, tip: str, reference):
    """The derivatives of a branch's MDH columns (theta, d, a, alpha, beta) by the fit's `u`
    (not compiled: the robot file's axes stay concrete, which `make_model` checks)."""

    def columns(u):
        table = dh_table(branch(body_of(u, problem)[0], tip)[0], "mdh", reference=reference)
        return jnp.stack([table.theta, table.d, table.a, table.alpha, table.beta])

    return jax.jacfwd(columns)(u)


def _table_std(result: TreeCalibration, tip: str, reference):
    """The standard deviations of the branch's MDH table (a `DHTable` of them), propagated from
    the fit's covariance."""
    J = np.asarray(_table_jacobian(jnp.asarray(result.fit.u), result._problem, tip, reference))
    std = np.sqrt(np.maximum(np.einsum("knp,pq,knq->kn", J, result.fit.cov, J), 0.0))
    return eqx.tree_at(lambda t: (t.theta, t.d, t.a, t.alpha, t.beta), reference, tuple(jnp.asarray(std)))


def branch_table(result: TreeCalibration, tip: str) -> dict | None:
    """The modified-DH table (a table file's JSON, `jaxcal.io.dh_tables`) of the calibrated
    chain from the root to `tip`, its rows matched to the robot file's; `coupled` names each
    row whose joint follows others (its $q$ is the law's, not a command). None where the branch
    holds a prismatic joint (no DH table here). Parameters of the branch's own joints held at
    the robot file's values are listed under `held`; a tip never measured is `measured: false`,
    with a `note`."""
    chain, C = branch(result.tree, tip)
    nominal, _ = branch(result.nominal, tip)
    if any(kind != "revolute" for kind in chain.joint_types):
        return None
    reference = dh_table(nominal, "mdh")
    doc = dh_table_json(
        dh_table(chain, "mdh", reference=reference),
        robot=f"{result.tree.link_names[0]} to {tip}",
        base_link=result.tree.link_names[0],
        flange_link=tip,
        std=None if result.fit.cov is None else _table_std(result, tip, reference),
        nominal=reference,
        source="jaxcal calibrate_tree (std propagated from the fit's covariance)",
    )
    tree = result.tree
    doc["coupled"] = {
        name: {tree.actuated_names[a]: float(C[i, a]) for a in np.flatnonzero(C[i])}
        for i, name in enumerate(chain.joint_names)
        if name not in tree.actuated_names
    }
    held = result.held.get(tip, [])
    if held:
        doc["held"] = list(held)
    if tip in unmeasured_tips(result):
        doc["measured"] = False
        doc["note"] = (
            "this tip was never measured: where the parameters in 'held' enter, the table is the robot file's, "
            "and their std 0 means held, not exact"
        )
    return doc


def unmeasured_tips(result: TreeCalibration) -> list[str]:
    """The tips no sample measured (their points held at the robot file's values; a measured
    tip's point is always seen), the device's own tip apart."""
    return [
        t
        for t in result.tree.tip_names
        if t != result.device_on and any(n.startswith(f"{t}.point.") for n in result.held.get(t, []))
    ]
