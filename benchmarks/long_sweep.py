"""Benchmark: long sweeps without encoders, `fit_arc` by blocks against SciPy's sparse least squares.

What is measured, per sweep length (one marker, positions only and no
encoder, like tracker data; one row with orientations; robust rows; six
sweeps of different lengths stacked), each in a fresh Python process so that
its peak memory is its own:

- `compile_s`: `jax.jit(fit_arc).lower(data).compile()`;
- `fit_s`: the median of `--repeats` calls of the compiled fit (closed-form
  start, Levenberg-Marquardt by blocks, covariance and summary);
- `peak_rss_mb`: the process's peak resident memory (`resource.getrusage`
  `ru_maxrss`) after the compile and the fits, before SciPy runs;
  `base_rss_mb` the same just before compiling (Python, JAX and the data);
- `scipy_s`: `scipy.optimize.least_squares(method="trf")` on the same
  residuals (a NumPy transcription of `arc_residuals`, checked against it:
  `residual_model_max_diff`), from the same closed-form start (computed
  outside SciPy's clock), with `jac_sparsity` (SciPy's grouped finite
  differences; TRF then solves each step with LSMR); `scipy_jac_s`: the same
  with the exact sparse Jacobian (jaxcal's closed form, jitted, assembled as
  CSR; call overhead included);
- `max_abs_diff`: the largest difference between jaxcal's and SciPy's
  (sparsity) solutions over the axis direction, the axis point (m) and the
  per-frame angles (rad); each part is also reported. SciPy stops at its
  default tolerances (1e-8) with LSMR's inexact steps, short of the optimum
  (`cost_scipy` above `cost_jaxcal`): `max_abs_diff_tight` compares with
  SciPy run to tolerances of 1e-14, LSMR's included, with the exact
  Jacobian (`scipy_tight_s`), `cost_scipy_tight` its cost.

How to run (from the repository root; it starts one process per row)::

    .venv/bin/python benchmarks/long_sweep.py --json results/long_sweep.json
    .venv/bin/python benchmarks/long_sweep.py --quick          # smoke run
    .venv/bin/python benchmarks/long_sweep.py --smoke          # smallest run, one process (the tests)

The JSON holds `rows` (one dict per row, the fields above plus `samples`,
`frames`, `orientations`, `loss`, `num_steps`, ratios `speedup_vs_scipy`
and `speedup_vs_scipy_jac`), `device`, `versions` and `notes`.
"""

import argparse
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import scipy
import scipy.sparse as sp
from arcfit import skew_np, so3_exp_np, so3_log_np, write_json
from scipy.optimize import least_squares

import jaxcal
from jaxcal._arcdata import stack_sweeps
from jaxcal._arcfit import _arc_blocks, _to_blocks, fit_arc
from jaxcal._arcmodel import initialise_arc

SIGMA_P = 1e-4  # m
SIGMA_R = 1e-3  # rad
SIZES = (100, 370, 1000, 3000, 10000)


def make_sweep(frames: int, *, orientations: bool, seed: int = 0, span: float = 1.2):
    """One random single-marker sweep (as `tests/helpers.arc_problem`), noisy, no encoder: truth and `ArcData`."""
    rng = np.random.default_rng(seed)
    V = rng.normal(size=3)
    V /= np.linalg.norm(V)
    Q = 0.3 * rng.normal(size=3) + np.array([0.0, 0.0, 1.0])
    p0 = Q + 0.2 * rng.normal(size=3)
    O0 = so3_exp_np(rng.normal(size=3))
    phi = np.linspace(-span / 2, span / 2, frames)
    R = so3_exp_np(V * phi[:, None])
    P = Q + np.einsum("fab,b->fa", R, p0 - Q) + SIGMA_P * rng.normal(size=(frames, 3))
    O = so3_exp_np(SIGMA_R * rng.normal(size=(frames, 3))) @ R @ O0
    data = jaxcal.make_arc_data(
        P, O if orientations else None, None, sigma_position=SIGMA_P, sigma_rotation=SIGMA_R
    )
    return dict(V=V, Q=Q), data


# --------------------------------------------------------------------------- the same residuals in NumPy


def residuals_np(x, P, O, R_ref, c, O_ref, w, gauge_frame):
    """`arc_residuals` without encoders (one marker) in NumPy, flattened.

    `x` = `(line (4), p0 (3)[, r0 (3)], angles of every frame but the gauge frame)`;
    `w` the diagonal whitening `(k,)`.
    """
    F = P.shape[0]
    has_rot = O is not None
    n_g = 10 if has_rot else 7
    line, p0 = x[:4], x[4:7]
    phi = np.insert(x[n_g:], gauge_frame, 0.0)
    V = R_ref @ np.array([line[0], line[1], 1.0])
    V = V / np.sqrt(V @ V)
    Q = c + R_ref[:, :2] @ line[2:]
    s, c1 = np.sin(phi)[:, None], (1.0 - np.cos(phi))[:, None]
    K = skew_np(V)
    d = p0 - Q
    a = K @ d
    b = K @ a
    e = Q + d + s * a + c1 * b - P  # (F, 3)
    if has_rot:
        O0 = O_ref @ so3_exp_np(x[7:10])
        G1 = K @ O0
        G2 = K @ G1
        O_pred = O0 + s[..., None] * G1 + c1[..., None] * G2
        e = np.concatenate([e, so3_log_np(O @ np.swapaxes(O_pred, -1, -2))], axis=-1)
    assert e.shape[0] == F
    return (e * w).reshape(-1)


def sparsity(F: int, k: int, n_g: int, gauge_frame: int) -> sp.csr_matrix:
    """Which residuals see which unknowns: every residual the globals, frame t's its own angle."""
    rows = np.arange(F * k)
    frame = rows // k
    col = n_g + frame - (frame > gauge_frame)
    keep = frame != gauge_frame
    pattern = sp.lil_matrix((F * k, n_g + F - 1), dtype=np.int8)
    pattern[:, :n_g] = 1
    pattern[rows[keep], col[keep]] = 1
    return pattern.tocsr()


# --------------------------------------------------------------------------- one row (child process)


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # KiB on Linux


def _axis(x, R_ref, c, P):
    V = R_ref @ np.array([x[0], x[1], 1.0])
    V /= np.linalg.norm(V)
    Q = c + R_ref[:, :2] @ x[2:4]
    centroid = P.mean(0)
    return V, Q + np.dot(centroid - Q, V) * V


def run_row(
    frames: int, orientations: bool, loss: str | None, repeats: int, scipy_max: int, six: bool
) -> dict:
    """Measure one row (in this process)."""
    if six:
        lengths = [237, 262, 301, 330, 355, 370]
        datas = [make_sweep(n, orientations=orientations, seed=i)[1] for i, n in enumerate(lengths)]
        data = stack_sweeps(datas)
        fn = jax.jit(
            jax.vmap(lambda d: fit_arc(d, robust=None if loss is None else jaxcal.RobustOptions(loss)))
        )
        samples = sum(lengths)
    else:
        truth, data = make_sweep(frames, orientations=orientations)
        fn = jax.jit(lambda d: fit_arc(d, robust=None if loss is None else jaxcal.RobustOptions(loss)))
        samples = frames
    jax.block_until_ready(data)
    base = _rss_mb()
    t0 = time.perf_counter()
    compiled = fn.lower(data).compile()
    compile_s = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(compiled(data))
        times.append(time.perf_counter() - t0)
    peak = _rss_mb()
    row = dict(
        samples=samples,
        frames=int(data.mask.shape[-1]),
        orientations=orientations,
        loss=loss,
        sweeps=6 if six else 1,
        compile_s=compile_s,
        fit_s=statistics.median(times),
        fit_s_all=times,
        base_rss_mb=base,
        peak_rss_mb=peak,
        num_steps=np.asarray(out.num_steps).tolist(),
        successful=bool(np.all(np.asarray(out.result == jaxcal._arcfit.optx.RESULTS.successful))),
    )
    if six or loss is not None or frames > scipy_max:
        return row

    # SciPy on the same residuals, from the same closed-form start (outside its clock).
    params0, ref = jax.jit(initialise_arc)(data)
    g0, l0 = _to_blocks(params0, data)
    gauge_frame = int(np.argmin(np.asarray(ref.gauge)))
    x0 = np.concatenate([np.asarray(g0), np.delete(np.asarray(l0[:, 0]), gauge_frame)])
    P = np.asarray(data.positions[0])
    O = None if data.orientations is None else np.asarray(data.orientations[0])
    k = data.sqrt_info.shape[-1]
    w = np.diagonal(np.asarray(data.sqrt_info[0, 0]))
    args = (P, O, np.asarray(ref.R_ref), np.asarray(ref.c), np.asarray(ref.O_ref[0]), w, gauge_frame)
    n_g = g0.shape[0]
    blocks = jax.jit(lambda g, l: _arc_blocks(g, l, (ref, data, jnp.ones(data.mask.shape))))
    r_jax = np.asarray(blocks(g0, l0)[0]).reshape(-1)
    model_diff = float(np.max(np.abs(residuals_np(x0, *args) - r_jax)))

    rows_idx = np.arange(frames * k)
    frame = rows_idx // k
    keep = frame != gauge_frame

    def exact_jac(x, *_):
        g = jnp.asarray(x[:n_g])
        l = jnp.asarray(np.insert(x[n_g:], gauge_frame, 0.0))[:, None]
        _, Jg, Jl = blocks(g, l)
        Jg = np.asarray(Jg).reshape(-1, n_g)
        Jl = np.asarray(Jl).reshape(-1)
        local = sp.csr_matrix(
            (Jl[keep], (rows_idx[keep], frame[keep] - (frame[keep] > gauge_frame))),
            shape=(frames * k, frames - 1),
        )
        return sp.hstack([sp.csr_matrix(Jg), local], format="csr")

    exact_jac(x0)  # compile the jitted blocks outside the clock
    pattern = sparsity(frames, k, n_g, gauge_frame)
    t0 = time.perf_counter()
    sol = least_squares(residuals_np, x0, jac_sparsity=pattern, method="trf", args=args)
    scipy_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    sol_jac = least_squares(residuals_np, x0, jac=exact_jac, method="trf", args=args)
    scipy_jac_s = time.perf_counter() - t0

    # SciPy to its tightest tolerances (LSMR's too): the optimum both should reach.
    t0 = time.perf_counter()
    sol_tight = least_squares(
        residuals_np,
        x0,
        jac=exact_jac,
        method="trf",
        args=args,
        ftol=1e-14,
        xtol=1e-14,
        gtol=1e-14,
        max_nfev=100,
        tr_options=dict(atol=1e-14, btol=1e-14),  # LSMR's own tolerances (default 1e-6)
    )
    scipy_tight_s = time.perf_counter() - t0

    V, Q = np.asarray(out.direction), np.asarray(out.point)
    phi = np.asarray(out.angles)

    def differences(x):
        V_s, Q_s = _axis(x, args[2], args[3], P)
        phi_s = np.insert(x[n_g:], gauge_frame, 0.0)
        return dict(
            direction=float(np.max(np.abs(V - V_s))),
            point_m=float(np.max(np.abs(Q - Q_s))),
            angles_rad=float(np.max(np.abs(phi - phi_s))),
        )

    diffs = differences(sol.x)
    diffs_tight = differences(sol_tight.x)
    ang_err = float(np.arccos(min(1.0, abs(float(V @ truth["V"])))))
    # jaxcal's solution in SciPy's variables (`meas` is (line, p0[, r0])), its cost in SciPy's residuals.
    x_jax = np.concatenate([np.asarray(out.meas), np.delete(phi, gauge_frame)])
    cost_jaxcal = float(0.5 * np.sum(residuals_np(x_jax, *args) ** 2))
    row.update(
        scipy_s=scipy_s,
        scipy_jac_s=scipy_jac_s,
        speedup_vs_scipy=scipy_s / row["fit_s"],
        speedup_vs_scipy_jac=scipy_jac_s / row["fit_s"],
        max_abs_diff=max(diffs.values()),
        max_abs_diff_parts=diffs,
        scipy_tight_s=scipy_tight_s,
        speedup_vs_scipy_tight=scipy_tight_s / row["fit_s"],
        max_abs_diff_tight=max(diffs_tight.values()),
        max_abs_diff_tight_parts=diffs_tight,
        cost_scipy_tight=float(sol_tight.cost),
        scipy_nfev=int(sol.nfev),
        scipy_jac_nfev=int(sol_jac.nfev),
        scipy_status=int(sol.status),
        cost_jaxcal=cost_jaxcal,
        cost_scipy=float(sol.cost),
        residual_model_max_diff=model_diff,
        direction_error_vs_truth_rad=ang_err,
    )
    return row


# --------------------------------------------------------------------------- driver


def _child(spec: dict, timeout: float) -> dict:
    cmd = [sys.executable, __file__, "--row", json.dumps(spec)]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, cwd=Path(__file__).parent)
    if out.returncode != 0:
        return dict(spec=spec, error=out.stderr[-2000:])
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", type=int, nargs="*", default=list(SIZES), help="samples per sweep")
    parser.add_argument("--repeats", type=int, default=5, help="timed fits per row (the median is kept)")
    parser.add_argument("--scipy-max", type=int, default=10000, help="largest sweep SciPy is timed on")
    parser.add_argument("--quick", action="store_true", help="a small smoke run")
    parser.add_argument(
        "--smoke",
        action="store_true",
        help="the smallest run (the tests'): one row of 50 samples, one process",
    )
    parser.add_argument("--json", metavar="OUT", help="also write the JSON here")
    parser.add_argument("--row", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.row:
        spec = json.loads(args.row)
        print(json.dumps(run_row(**spec)))
        return
    sizes = [100, 370] if args.quick else args.sizes
    repeats = 1 if args.quick else args.repeats
    specs = [dict(frames=n, orientations=False, loss=None) for n in sizes]
    specs += [dict(frames=370, orientations=True, loss=None)]
    if args.smoke:
        specs, repeats, args.scipy_max = [dict(frames=50, orientations=False, loss=None)], 1, 50
    elif not args.quick:
        specs += [dict(frames=n, orientations=False, loss="cauchy") for n in (370, max(sizes))]
        specs += [dict(frames=0, orientations=False, loss=None, six=True)]
    rows = []
    for spec in specs:
        spec = dict(six=False, repeats=repeats, scipy_max=args.scipy_max) | spec
        row = run_row(**spec) if args.smoke else _child(spec, timeout=3600)
        print(json.dumps(row), file=sys.stderr)
        rows.append(row)
    result = dict(
        rows=rows,
        device=jax.devices()[0].platform,
        cpu_count=os.cpu_count(),
        versions=dict(
            jax=jax.__version__,
            scipy=scipy.__version__,
            numpy=np.__version__,
            python=platform.python_version(),
        ),
        notes=[
            "Each row runs in its own process: peak_rss_mb is that process's high-water mark (Python, "
            "JAX, XLA's compile and the fits; base_rss_mb before compiling).",
            "fit_s is the full fit_arc (closed-form start, LM by blocks, covariance, summary) after "
            "compilation, the median of `repeats`; SciPy computes no covariance.",
            "scipy_s: least_squares(method='trf') with jac_sparsity (grouped 2-point finite differences, "
            "LSMR steps); scipy_jac_s: the exact sparse Jacobian from jaxcal's closed form (jitted, CSR). "
            "Both from jaxcal's closed-form start, SciPy's default tolerances (1e-8); jaxcal stops at "
            "rtol=1e-8, atol=0.03 noise sigmas, so max_abs_diff reflects the two stopping rules.",
            "Robust rows (loss='cauchy') run three IRLS rounds and an inlier solve, each with leverages "
            "by blocks; SciPy has no equivalent scheme and is not timed there.",
            "The six-sweep row is jit(vmap(fit_arc)) on stack_sweeps of 237-370 frames (padded to 384).",
        ],
    )
    if args.json:
        write_json(result, args.json)
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
