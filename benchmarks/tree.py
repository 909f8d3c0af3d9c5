"""Benchmark: a humanoid upper body calibrated from both hands measured at once (issue 51).

What is measured: the simulated upper body of `jaxcal.sim.humanoid` (a 3-DOF torso with a
coupled fourth joint, two 7-DOF arms on tilted shoulder mounts, a 2-DOF head) is perturbed
(joint origins 1 mm / 0.2 deg, zero offsets 0.3 deg, the coupling's multiplier 1 %, the
reflectors' mounts 2 mm) and bent by gravity with drawn joint and lateral compliances
(`elastic_truth`). A tracker measures a reflector on each hand at `--poses` random
stop-and-shoot poses inside the joints' limits (`--noise-mm` per axis); `--test-poses` more
poses are held out. Three fits of the same samples:

- `calibrate_tree` as a user runs it: cross-validation chooses the term families among joint
  compliance, lateral compliance and a once-per-turn harmonic (which the truth lacks);
- the floor: the true elastic structure given (joint and lateral compliance);
- geometry alone.

Each is judged by its held-out tips' mean distance from the noise-free truth (mm). The freed
compliances are compared with the truth in their standard deviations. The calibrated URDF is
written, read back and compared, mimic law included.

Then the seed's method on the same kind of body (`jaxcal.sim.head_camera`): the head camera
(640x480) films a ChArUco plate on each hand at `--camera-poses` poses where both are in view,
rendered by MuJoCo; OpenCV detects the plates and solves their PnP; the tree fit (the body's
joint and lateral compliances) weighs each plate's origin by its PnP covariance. It is judged
per hand on `--camera-test-poses` more frames: the EE RMS against the truth, and the mean of
the errors' squared Mahalanobis distance over 3 under the covariance the fit claims for its
predictions (1 when the claim is right).

How to run (from the repository root)::

    .venv/bin/python benchmarks/tree.py --json results/tree.json

The JSON holds `tree_test_mean_mm`, `tree_floor_mm`, `tree_geometric_mm`, `tree_over_floor`,
`tree_terms_kept`, `elastic_within_3sigma` (share of freed compliances within 3 sigma of the
truth), `elastic_max_abs_z`, `urdf_roundtrip_max_m`, `calibrate_s`, per seed and as means, and
`camera` (per seed): `status`, `ee_rms_mm` and `prediction_z2` per hand, `elastic_within_3sigma`,
`noise_ratio` (the residuals' noise over PnP's), `sigma_px`, `seen` (frames per plate); over
the seeds `camera_ee_rms_mm` and `camera_prediction_z2` (means of the worse hand's), and
`camera_statuses`.
"""

import argparse
import json
import tempfile
import time
from pathlib import Path

import jax.numpy as jnp
import numpy as np

import jaxcal  # noqa: F401  (float64)
from jaxcal._npgeom import rotvec_to_matrix
from jaxcal._tree import tip_poses
from jaxcal.io._files import write_text_atomic
from jaxcal.io.urdf_tree import actuated_limits, load_urdf_tree
from jaxcal.sim.head_camera import CAMERA_TIP, film_upper_body
from jaxcal.sim.humanoid import (
    compliance_z,
    elastic_truth,
    perturb_tree,
    random_poses,
    tree_tracker_samples,
    upper_body_urdf,
)
from jaxcal.trees import calibrate_tree, save_tree_calibration

TIPS = ("left_hand", "right_hand")
#: The reflectors' nominal positions on the hands (m, hand frames).
POINTS = np.array([[0.02, 0.0, -0.01], [0.02, 0.0, -0.01]])


def _held_out_mm(result, test) -> float:
    return 1e3 * float(np.linalg.norm(result.predict(test.q) - test.truth, axis=-1).mean())


def _roundtrip_m(result, urdf: Path, work: Path) -> float:
    """The largest difference (m) between the calibrated tree's tip poses and those of its
    written URDF read back, over random configurations; inf if the structure changed."""
    save_tree_calibration(result, work / "out", source_urdf=urdf)
    back = load_urdf_tree(work / "out" / "calibrated.urdf", tips=list(TIPS))
    tree = result.tree
    if (back.parent, back.joint_names, back.actuated_names) != (
        tree.parent,
        tree.joint_names,
        tree.actuated_names,
    ):
        return float("inf")
    rng = np.random.default_rng(0)
    q = rng.uniform(-1.0, 1.0, (20, tree.num_actuated))
    return max(
        float(
            np.abs(
                np.asarray(tip_poses(back, jnp.asarray(x))) - np.asarray(tip_poses(tree, jnp.asarray(x)))
            ).max()
        )
        for x in q
    )


def run_camera(seed: int, poses: int, test_poses: int) -> dict:
    """The head camera's capture of seed `seed`'s body, calibrated and judged (module docstring)."""
    t0 = time.perf_counter()
    body = film_upper_body(poses + test_poses, seed=seed)
    film_s = time.perf_counter() - t0
    samples = body.capture.samples
    fit, test = samples.subset(slice(0, poses)), samples.subset(slice(poses, None))
    t0 = time.perf_counter()
    result = calibrate_tree(
        body.nominal, fit, points=body.points, device_on=CAMERA_TIP, families=("joint", "lateral"),
        limits=body.limits, show_progress=False,
    )  # fmt: skip
    seconds = time.perf_counter() - t0
    predicted, cov = result.predict(test.q), result.predict_covariance(test.q)
    rms, z2 = {}, {}
    for t, hand in enumerate(TIPS):
        rows = test.measured[:, t]
        e = predicted[rows, t] - test.truth[rows, t]
        rms[hand] = 1e3 * float(np.sqrt((e**2).sum(axis=-1).mean()))
        z2[hand] = float(np.einsum("na,nab,nb->n", e, np.linalg.inv(cov[rows, t]), e).mean() / 3.0)
    stated = 1e3 * np.sqrt(np.trace(fit.covariance[fit.measured], axis1=1, axis2=2).mean() / 3.0)
    z = np.asarray(list(compliance_z(result, body.elastic).values()))
    return {
        "status": result.status,
        "notes": list(result.notes),
        "ee_rms_mm": rms,
        "prediction_z2": z2,
        "elastic_within_3sigma": float(np.mean(np.abs(z) <= 3.0)) if z.size else None,
        "noise_ratio": result.fit.noise_mm / stated,
        "pnp_noise_mm": stated,
        "sigma_px": body.capture.sigma_px,
        "seen": body.capture.seen,
        "held": {k: len(v) for k, v in result.held.items()},
        "film_s": film_s,
        "calibrate_s": seconds,
    }


def run_seed(seed: int, poses: int, test_poses: int, noise_mm: float, work: Path) -> dict:
    urdf = work / "upper_body.urdf"
    urdf.write_text(upper_body_urdf())
    nominal = load_urdf_tree(urdf, tips=list(TIPS))
    limits = actuated_limits(urdf, nominal)
    rng = np.random.default_rng(seed)
    true = perturb_tree(nominal, rng)
    elastic = elastic_truth(nominal, rng)
    T_device = np.eye(4)
    T_device[:3, :3] = rotvec_to_matrix(np.array([0.0, 0.0, np.pi]) + 0.05 * rng.standard_normal(3))
    T_device[:3, 3] = [2.0, 0.1, -0.4]
    points = POINTS + 2e-3 * rng.standard_normal(POINTS.shape)
    q = random_poses(limits, poses + test_poses, rng)
    samples = tree_tracker_samples(true, q, points, T_device, rng, noise_mm=noise_mm, elastic=elastic)
    fit, test = samples.subset(slice(0, poses)), samples.subset(slice(poses, None))
    t0 = time.perf_counter()
    auto = calibrate_tree(nominal, fit, noise_mm=noise_mm, points=POINTS, limits=limits)
    seconds = time.perf_counter() - t0
    floor = calibrate_tree(nominal, fit, noise_mm=noise_mm, points=POINTS, families=("joint", "lateral"))
    geometric = calibrate_tree(nominal, fit, noise_mm=noise_mm, points=POINTS, families=())
    z = np.asarray(list(compliance_z(auto, elastic).values()))
    return {
        "seed": seed,
        "tree_test_mean_mm": _held_out_mm(auto, test),
        "tree_floor_mm": _held_out_mm(floor, test),
        "tree_geometric_mm": _held_out_mm(geometric, test),
        "tree_terms_kept": list(auto.fit.families),
        "cross_validation_mm": auto.fit.cv_mm,
        "elastic_freed": int(z.size),
        "elastic_within_3sigma": float(np.mean(np.abs(z) <= 3.0)) if z.size else None,
        "elastic_max_abs_z": float(np.abs(z).max()) if z.size else None,
        "status": auto.status,
        "notes": list(auto.notes),
        "noise_mm_estimated": auto.fit.noise_mm,
        "held": {k: len(v) for k, v in auto.held.items()},
        "urdf_roundtrip_max_m": _roundtrip_m(auto, urdf, work),
        "calibrate_s": seconds,
    }


def run(seeds, poses: int, test_poses: int, noise_mm: float, camera_poses: int, camera_test: int) -> dict:
    rows = []
    for seed in seeds:
        with tempfile.TemporaryDirectory() as tmp:
            rows.append(run_seed(seed, poses, test_poses, noise_mm, Path(tmp)))
        r = rows[-1]
        print(
            f"seed {seed}: held-out {r['tree_test_mean_mm']:.4f} mm (floor {r['tree_floor_mm']:.4f}, "
            f"geometry alone {r['tree_geometric_mm']:.3f}), terms {r['tree_terms_kept']}, "
            f"elastic within 3 sigma {r['elastic_within_3sigma']}, {r['calibrate_s']:.1f} s",
            flush=True,
        )
        r["camera"] = c = run_camera(seed, camera_poses, camera_test)
        print(
            f"seed {seed}, head camera: {c['status']}, EE RMS {c['ee_rms_mm']} mm, claim ratio "
            f"{c['prediction_z2']}, elastic within 3 sigma {c['elastic_within_3sigma']}",
            flush=True,
        )
    mean = lambda k: float(np.mean([r[k] for r in rows]))  # noqa: E731
    kept = sorted({tuple(r["tree_terms_kept"]) for r in rows})
    return {
        "poses": poses,
        "test_poses": test_poses,
        "noise_mm": noise_mm,
        "tree_test_mean_mm": mean("tree_test_mean_mm"),
        "tree_floor_mm": mean("tree_floor_mm"),
        "tree_geometric_mm": mean("tree_geometric_mm"),
        "tree_over_floor": mean("tree_test_mean_mm") / mean("tree_floor_mm"),
        "tree_terms_kept": [list(k) for k in kept] if len(kept) > 1 else list(kept[0]),
        "elastic_within_3sigma": float(np.mean([r["elastic_within_3sigma"] for r in rows])),
        "elastic_max_abs_z": max(r["elastic_max_abs_z"] for r in rows),
        "urdf_roundtrip_max_m": max(r["urdf_roundtrip_max_m"] for r in rows),
        "calibrate_s": mean("calibrate_s"),
        "camera_ee_rms_mm": float(np.mean([max(r["camera"]["ee_rms_mm"].values()) for r in rows])),
        "camera_prediction_z2": float(np.mean([max(r["camera"]["prediction_z2"].values()) for r in rows])),
        "camera_statuses": [r["camera"]["status"] for r in rows],
        "seeds": rows,
    }


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--poses", type=int, default=500, help="stop-and-shoot poses fitted")
    parser.add_argument("--test-poses", type=int, default=200, help="poses held out")
    parser.add_argument("--noise-mm", type=float, default=0.1, help="tracker noise, 1-sigma per axis")
    parser.add_argument("--camera-poses", type=int, default=200, help="head camera: poses fitted")
    parser.add_argument("--camera-test-poses", type=int, default=50, help="head camera: poses held out")
    parser.add_argument("--seeds", type=int, default=1, help="bodies drawn")
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--json", metavar="OUT", help="also write the JSON here")
    args = parser.parse_args(argv)
    seeds = range(args.first_seed, args.first_seed + args.seeds)
    print(
        f"{args.seeds} upper bodies, {args.poses} poses each (cross-validation: a minute each) ...",
        flush=True,
    )
    result = run(seeds, args.poses, args.test_poses, args.noise_mm, args.camera_poses, args.camera_test_poses)
    if args.json:
        write_text_atomic(Path(args.json), json.dumps(result, indent=2) + "\n")
    print(json.dumps({k: v for k, v in result.items() if k != "seeds"}, indent=2))


if __name__ == "__main__":
    main()
