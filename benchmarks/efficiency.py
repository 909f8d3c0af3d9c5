"""Benchmark: statistical efficiency of the refinement against the Cramer-Rao bound.

What is measured: a UR5e (nominal model with known corrections on its
identifiable parameters, a camera 1.5 m away, 1000 px focal length, a
4x3-corner grid 40 mm apart on the flange) makes joint-by-joint sweeps
(`--frames` frames through `--range-deg` per joint). Every corner is projected
analytically (no rendering) and i.i.d. Gaussian pixel noise `--sigma-px` is
added, `--trials` times (seeded, one `jit(vmap(...))` call). Each trial runs

- the two-stage method: per-view PnP (Gauss-Newton on the corners, with the
  pose covariance $\\sigma^2 (J^T J)^{-1}$), arc fits of every joint and the
  axis fit, with the same frozen parameters;
- the refinement from that start: robust (Cauchy IRLS, then least squares on
  the inliers; the pipeline's default) and plain least squares.

The Cramer-Rao bound of every free parameter is the diagonal of
$\\sigma^2 (J^T J)^{-1}$ with $J$ the reprojection Jacobian at the truth
(`jaxcal._refine.fisher_std`). For each estimator, the empirical RMSE of every
free parameter over the trials is divided by its bound; an efficient
estimator has ratios near 1 (a Monte Carlo of N trials estimates each ratio
within about $1/\\sqrt{2N}$).

How to run (from the repository root)::

    .venv/bin/python benchmarks/efficiency.py --json results/efficiency.json
    .venv/bin/python benchmarks/efficiency.py --quick

The JSON holds `trials`, `sigma_px`, `max_ratio_to_crlb` and
`median_ratio_to_crlb` (the refinement as the pipeline runs it, robust),
`plain_max_ratio_to_crlb` / `plain_median_ratio_to_crlb` (least squares),
`two_stage_max_ratio_to_crlb` / `two_stage_median_ratio_to_crlb`, per
parameter ratios, success rates, and compile / run times.
"""

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jax.flatten_util import ravel_pytree

import jaxcal  # noqa: F401  (float64)
from jaxcal import RobustOptions
from jaxcal._arcdata import make_arc_data
from jaxcal._arcfit import fit_arc
from jaxcal._axisfit import fit_axes
from jaxcal._correction import ParameterLayout
from jaxcal._geometry import make_pose, se3_log, so3_exp
from jaxcal._montecarlo import default_setup
from jaxcal._refine import (
    RefineParams,
    RefineProblem,
    default_free,
    fisher_std,
    grid_points,
    identifiable_mask,
    project,
    projected_corners,
    refine,
    refine_parameter_names,
    sweep_corner_data,
    target_poses,
    zero_params,
)
from jaxcal.robots import load_robot


def _truth(flat0: np.ndarray, free: np.ndarray, n: int, seed: int) -> np.ndarray:
    g = ParameterLayout.sized(n, 1).indices()
    scale = np.zeros(flat0.size)
    scale[g["cam"]] = [5e-3] * 3 + [5e-3] * 3
    scale[g["origin"]] = np.tile([1e-3] * 3 + [2e-3] * 3, n)
    scale[g["zero"]] = 3e-3
    scale[g["tool"]] = [1e-3] * 3 + [5e-3] * 3
    scale[g["rate"]] = 0.01
    return flat0 + scale * np.random.default_rng(seed).standard_normal(flat0.size) * free


def _pnp(points, pixels, T0, K, dist, sigma, iterations=6):
    """Gauss-Newton PnP of one view from `T0`, with the $(p, w)$ covariance of `jaxcal.vision`."""

    def proj(x):
        R = so3_exp(x[3:]) @ T0[:3, :3]
        return project(K, dist, points @ R.T + T0[:3, 3] + x[:3]).reshape(-1)

    x = jnp.zeros(6)
    for _ in range(iterations):
        J = jax.jacfwd(proj)(x)
        x = x - jnp.linalg.solve(J.T @ J, J.T @ (proj(x) - pixels.reshape(-1)))
    J = jax.jacfwd(proj)(x)
    T = make_pose(so3_exp(x[3:]) @ T0[:3, :3], T0[:3, 3] + x[:3])
    return T, sigma**2 * jnp.linalg.inv(J.T @ J)


def run(trials: int, sigma: float, frames: int, range_deg: float, seed: int) -> dict:
    nominal = load_robot("ur5e")
    setup = default_setup(nominal)
    n = nominal.num_joints
    problem = RefineProblem(
        nominal=nominal,
        T_flange_marker0=setup.T_flange_marker,
        T_cam_base0=setup.T_cam_base,
        K0=jnp.array([[1000.0, 0, 640], [0, 1000, 480], [0, 0, 1]]),
        dist0=jnp.zeros(5),
        offset0_s=jnp.zeros(()),
        data=sweep_corner_data(grid_points(), n, frames, range_deg),
    )
    p0 = zero_params(n, 1)
    flat0, unravel = ravel_pytree(p0)
    flat0 = np.asarray(flat0)
    free = np.asarray(jax.jit(identifiable_mask)(problem, p0, default_free(n, 1))[0])
    n_ax = flat0.size - n - 1 - 9
    x_true = jnp.asarray(_truth(flat0, free, n, seed))
    p_true = unravel(x_true)
    clean = projected_corners(p_true, problem)
    poses_true = target_poses(p_true, problem)
    crlb = np.asarray(fisher_std(eqx.tree_at(lambda p: p.data.pixels, problem, clean), p_true, free, sigma))
    ramp = jnp.linspace(-0.5, 0.5, frames) * np.radians(range_deg)
    ax_free = jnp.asarray(free[:n_ax])

    def trial(key, c, reject):
        pixels = clean + sigma * jax.random.normal(key, clean.shape)
        prob = eqx.tree_at(lambda p: p.data.pixels, problem, pixels)
        # Two-stage: PnP per view -> arc fits -> axis fit.
        T, C = jax.vmap(lambda u, T0: _pnp(problem.data.points[0], u, T0, problem.K0, problem.dist0, sigma))(
            pixels, poses_true
        )
        T = T.reshape(n, 1, frames, 4, 4)
        C = C.reshape(n, 1, frames, 6, 6)
        data = jax.vmap(lambda P, O, Cj: make_arc_data(P, O, ramp, covariances=Cj))(
            T[..., :3, 3], T[..., :3, :3], C
        )
        arcs = jax.vmap(lambda d: fit_arc(d, scale_covariance=False))(data)
        fit = fit_axes(nominal, arcs, T_flange_marker=setup.T_flange_marker, free=ax_free)
        start = RefineParams(
            cam=se3_log(jnp.linalg.inv(problem.T_cam_base0) @ fit.T_cam_base),
            correction=fit.params.correction,
            rate=arcs.rate,
            clock_ms=jnp.zeros(()),
            intrinsics=jnp.zeros(9),
        )
        res = refine(prob, start, free, robust=RobustOptions(c=c, reject=reject))
        ok2 = jnp.all(arcs.result == optx.RESULTS.successful) & (fit.result == optx.RESULTS.successful)
        return ravel_pytree(start)[0], ok2, ravel_pytree(res.params)[0], res.result == optx.RESULTS.successful

    batched = jax.jit(jax.vmap(trial, in_axes=(0, None, None)))
    keys = jax.random.split(jax.random.key(seed + 1), trials)
    t0 = time.perf_counter()
    compiled = batched.lower(keys, 3.0, 3.7).compile()
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    x2, ok2, xr, okr = jax.block_until_ready(compiled(keys, 3.0, 3.7))
    robust_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    _, _, xp, okp = jax.block_until_ready(compiled(keys, np.inf, np.inf))
    plain_s = time.perf_counter() - t0

    names = refine_parameter_names(nominal, 1)
    idx = np.flatnonzero(free)
    x_true = np.asarray(x_true)

    def ratios(x, ok):
        x, ok = np.asarray(x), np.asarray(ok)
        rmse = np.sqrt(np.mean((x[ok][:, idx] - x_true[idx]) ** 2, axis=0))
        return rmse / crlb[idx], float(ok.mean())

    r_rob, s_rob = ratios(xr, okr)
    r_pl, s_pl = ratios(xp, okp)
    # The two-stage method has no clock or intrinsics; its rates come from the arc fits.
    r_two, s_two = ratios(x2, ok2)
    return {
        "benchmark": "efficiency",
        "trials": trials,
        "sigma_px": sigma,
        "frames_per_joint": frames,
        "range_deg": range_deg,
        "corners": int(np.asarray(problem.data.mask).sum()),
        "free_parameters": int(free.sum()),
        "max_ratio_to_crlb": float(r_rob.max()),
        "median_ratio_to_crlb": float(np.median(r_rob)),
        "plain_max_ratio_to_crlb": float(r_pl.max()),
        "plain_median_ratio_to_crlb": float(np.median(r_pl)),
        "two_stage_max_ratio_to_crlb": float(r_two.max()),
        "two_stage_median_ratio_to_crlb": float(np.median(r_two)),
        "monte_carlo_ratio_resolution": float(1.0 / np.sqrt(2 * trials)),
        "success_rate": {"refined": s_rob, "plain": s_pl, "two_stage": s_two},
        "per_parameter": {
            names[i]: {
                "crlb": float(crlb[i]),
                "refined": float(r_rob[k]),
                "plain": float(r_pl[k]),
                "two_stage": float(r_two[k]),
            }
            for k, i in enumerate(idx)
        },
        "compile_s": compile_s,
        "run_s": {"robust": robust_s, "plain": plain_s},
        "device": f"{jax.devices()[0].device_kind} ({platform.machine()}, {os.cpu_count()} CPUs)",
        "notes": "RMSE over trials of each free parameter divided by its Cramer-Rao bound at the truth; "
        "the refinement starts from each trial's two-stage result",
    }


def write_json(result: dict, path: str) -> None:
    """Write `result` to `path` atomically (a temporary file in the same folder, then a rename)."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.NamedTemporaryFile("w", dir=target.parent, suffix=".tmp", delete=False) as f:
        json.dump(result, f, indent=2)
        f.write("\n")
    os.replace(f.name, target)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--trials", type=int, default=200)
    parser.add_argument("--sigma-px", type=float, default=0.5, help="pixel noise per coordinate (px)")
    parser.add_argument("--frames", type=int, default=10, help="frames per joint sweep")
    parser.add_argument("--range-deg", type=float, default=60.0, help="sweep range per joint (deg)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--quick", action="store_true", help="a small smoke run (20 trials)")
    parser.add_argument("--json", metavar="OUT", help="also write the JSON here")
    args = parser.parse_args(argv)
    if args.quick:
        args.trials = 20
    result = run(args.trials, args.sigma_px, args.frames, args.range_deg, args.seed)
    text = json.dumps(result, indent=2)
    if args.json:
        write_json(result, args.json)
    print(text)


if __name__ == "__main__":
    main()
