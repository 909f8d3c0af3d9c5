"""Why a capture's measured EE error differs from its predicted one: the detector's true errors, propagated.

`jaxcal plan --evaluate` and the refinement's own standard deviations predict
the end-effector (EE) error from the Jacobian of the reprojection residuals
and i.i.d. Gaussian corner noise. On a rendered dataset the truth gives
each detected corner's true error $\\varepsilon$ (detected minus the corner
projected at the rendered target pose, `truth.json`), so the prediction can
be checked in two separate parts:

1. **The propagation.** To first order the refinement's error is
   $\\delta = (J^T J)^{-1} J^T \\varepsilon$ over the inlier corners and the EE
   error at configuration $c$ is $G_c \\delta$ (`G` over the validation's 1000
   configurations). `linearised_ee_mm` should equal the validation's
   measured `ee_rms_mm_after`: when it does, the Jacobians, the gauge and the
   EE point are right, and any gap to the prediction is the noise itself.
2. **The noise model.** With the true $|\\varepsilon|$ but random signs per
   corner (a wild bootstrap: independent errors of the measured sizes) the
   same map gives a distribution of EE errors; `wild_percentile` is where the
   true $\\varepsilon$ falls in it, and `gaussian_ee_mm` the i.i.d. Gaussian
   figure at the residual sigma (the refinement's own propagated 1-sigma).
   Percentiles near 0 or 1 over several captures of one design mean the
   detector's errors are structured in a way i.i.d. noise is not.

Single fixed camera or camera on the flange, one target kind per dataset,
the first camera's frames. Usage:

    python benchmarks/prediction_check.py DATASET [DATASET ...] --json OUT

Beside OUT it keeps each dataset's true errors (`OUT-stem_NAME_errors.npz`) and
reports `seed_correlation`: how alike the errors of two seeds of one design are
(`view_wild_percentile` flips one sign per view instead of per corner).

`benchmarks/plan.py` leaves its rendered captures in `plan-bench/` (e.g.
`plan-bench/demo_seed0`).
"""

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np


def true_errors(ds: Path, setup, problem, inlier: np.ndarray) -> np.ndarray:
    """Detected minus true pixel of every inlier corner `(views, corners, 2)` (zero elsewhere),
    projecting the board points at `truth.json`'s per-frame `T_cam_target`."""
    import cv2

    truth = json.loads((ds / "truth.json").read_text())
    cam = setup.camera.name
    meta = next(c for c in json.loads((ds / "metadata.json").read_text())["cameras"] if c["name"] == cam)
    K = np.asarray(meta["K"], np.float64)
    dist = np.asarray(meta.get("distortion") or np.zeros(5), np.float64)
    frames = {f["frame"]: f for f in truth["frames"] if f.get("camera", cam) == cam}
    names = [t.name for t in setup.targets]
    P, U = np.asarray(problem.data.points), np.asarray(problem.data.pixels)
    frame, target = np.asarray(problem.data.frame), np.asarray(problem.data.target)
    eps = np.zeros_like(U)
    for v in np.flatnonzero(inlier.any(axis=1)):
        poses = frames[int(frame[v])]["T_cam_target"]
        # Eye-in-hand the refinement's "target" is the camera on the flange; the truth names the board.
        T = np.asarray(
            poses[names[int(target[v])]] if len(poses) > 1 else next(iter(poses.values())), np.float64
        )
        uv, _ = cv2.projectPoints(P[v], cv2.Rodrigues(T[:3, :3])[0], T[:3, 3], K, dist)
        eps[v] = np.where(inlier[v, :, None], U[v] - uv[:, 0], 0.0)
    return eps


def check(ds: Path, flips: int, seed: int, errors_out: Path | None = None) -> dict:
    import jax
    import jax.numpy as jnp
    from jax.flatten_util import ravel_pytree

    from jaxcal import stages
    from jaxcal._reprojection import reprojection_residuals
    from jaxcal._uncertainty import joint_travel, on_travel, random_configurations, tool_points

    t0 = time.perf_counter()
    options = stages.Options(progress=False, limits=stages.Limits())
    setup = stages.setup(ds, options)
    obs = stages.observe(setup, options)
    sync = stages.synchronise(setup, obs, options)
    two = stages.two_stage(setup, obs, sync, options)
    refined = stages.refine(setup, obs, sync, two, options)
    if refined.fit is None:
        raise SystemExit(f"{ds}: the refinement did not run: {refined.warnings}")
    validation = stages.validate(setup, sync, two, refined, options)
    if validation is None:
        raise SystemExit(f"{ds}: no truth.json to check against")
    res, problem, n_axis = refined.fit, refined.problem, refined.layout.axis_size

    flat, unravel = ravel_pytree(res.params)
    idx = np.flatnonzero(np.asarray(res.free))
    inlier = np.asarray(res.inlier)
    weights = jnp.asarray(inlier, jnp.float64)

    def residuals(x):
        return reprojection_residuals(unravel(flat.at[idx].set(x)), problem, weights).reshape(-1)

    rows = np.repeat(inlier.reshape(-1), 2)
    J = np.asarray(jax.jit(jax.jacfwd(residuals))(flat[idx]))[rows]
    A = np.linalg.inv(J.T @ J)
    r = np.asarray(residuals(flat[idx]))[rows]
    sigma2 = r @ r / (J.shape[0] - J.shape[1])

    # The validation's configurations and EE point (`jaxcal.stages._validate`).
    nominal = setup.nominal
    q = on_travel(
        nominal,
        random_configurations(jax.random.key(0), 1000, nominal.num_joints),
        joint_travel(nominal, setup.dataset.joint_limits),
    )
    prefix, unravel_prefix = ravel_pytree((res.params.cam, res.params.correction))
    G = np.asarray(
        jax.jacfwd(
            lambda x: tool_points(
                nominal, problem.T_cam_base0, problem.T_flange_marker0, *unravel_prefix(x), q
            )
        )(prefix)
    )
    Gf = np.zeros(G.shape[:2] + (idx.size,))
    on_axis = idx < n_axis
    Gf[:, :, on_axis] = G[:, :, idx[on_axis]]

    eps = true_errors(ds, setup, problem, inlier)

    def ee_rms_mm(e: np.ndarray) -> float:
        delta = A @ (J.T @ e.reshape(-1)[rows])
        return float(1e3 * np.sqrt(np.mean(np.sum((Gf @ delta) ** 2, axis=-1))))

    rng = np.random.default_rng(seed)
    wild = np.array(
        [ee_rms_mm(eps * rng.choice([-1.0, 1.0], size=eps.shape[:2] + (1,))) for _ in range(flips)]
    )
    # One sign per view: each view's own error pattern kept, the views made independent.
    view_wild = np.array(
        [ee_rms_mm(eps * rng.choice([-1.0, 1.0], size=(eps.shape[0], 1, 1))) for _ in range(flips)]
    )
    linearised = ee_rms_mm(eps)
    gaussian = float(1e3 * np.sqrt(sigma2 * np.mean(np.einsum("cia,ab,cib->c", Gf, A, Gf))))
    e_in = eps[inlier]
    if errors_out is not None:
        np.savez_compressed(errors_out, eps=eps, inlier=inlier, frame=np.asarray(problem.data.frame))
    return {
        "dataset": str(ds),
        "measured_ee_mm": validation.report["ee_rms_mm_after"],
        "linearised_ee_mm": linearised,
        "linearised_over_measured": linearised / validation.report["ee_rms_mm_after"],
        "gaussian_ee_mm": gaussian,
        "measured_over_gaussian": validation.report["ee_rms_mm_after"] / gaussian,
        "wild_ee_mm_rms": float(np.sqrt(np.mean(wild**2))),
        "wild_ee_mm_5_50_95": [float(x) for x in np.percentile(wild, [5, 50, 95])],
        "wild_percentile": float(np.mean(wild <= linearised)),
        "view_wild_ee_mm_5_50_95": [float(x) for x in np.percentile(view_wild, [5, 50, 95])],
        "view_wild_percentile": float(np.mean(view_wild <= linearised)),
        "true_noise_rms_px": float(np.sqrt(np.mean(e_in**2))),
        "residual_sigma_px": float(np.sqrt(sigma2)),
        "corners": int(inlier.sum()),
        "free_parameters": int(idx.size),
        "seconds": time.perf_counter() - t0,
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("datasets", nargs="+", type=Path, help="rendered datasets with truth.json")
    parser.add_argument("--json", required=True, type=Path, help="write the figures here")
    parser.add_argument("--flips", type=int, default=200, help="wild-bootstrap draws per dataset")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)

    import jaxcal  # noqa: F401  (x64, the compilation cache)
    from jaxcal.io._files import write_text_atomic

    out = {
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, CPU only",
        "flips": args.flips,
        "datasets": [],
    }
    errors = {}
    for ds in args.datasets:
        errors[ds] = args.json.parent / f"{args.json.stem}_{ds.name}_errors.npz"
        row = check(ds, args.flips, args.seed, errors[ds])
        out["datasets"].append(row)
        print(
            f"{ds.name}: measured {row['measured_ee_mm']:.4f} mm, linearised {row['linearised_ee_mm']:.4f}, "
            f"gaussian {row['gaussian_ee_mm']:.4f}, wild percentile {row['wild_percentile']:.2f}, "
            f"view-wild percentile {row['view_wild_percentile']:.2f}",
            flush=True,
        )
        out["seed_correlation"] = seed_correlation(errors)
        write_text_atomic(args.json, json.dumps(out, indent=2))
    return 0


def seed_correlation(errors: dict) -> dict:
    """Per design (a dataset's name less `_seedN`), the correlation of the true corner errors of
    every pair of its seeds, over the corners both kept: near 0 when the seeds' noise is drawn
    afresh, near 1 when rendering the same design repeats the same detector errors."""
    groups = {}
    for ds, path in errors.items():
        groups.setdefault(ds.name.rsplit("_seed", 1)[0], []).append((ds.name, np.load(path)))
    out = {}
    for runs in groups.values():
        for i, (na, a) in enumerate(runs):
            for nb, b in runs[i + 1 :]:
                if a["eps"].shape != b["eps"].shape or not np.array_equal(a["frame"], b["frame"]):
                    continue
                both = a["inlier"] & b["inlier"]
                ea, eb = a["eps"][both], b["eps"][both]
                out[f"{na} {nb}"] = float(np.sum(ea * eb) / np.sqrt(np.sum(ea**2) * np.sum(eb**2)))
    return out


if __name__ == "__main__":
    sys.exit(main())
