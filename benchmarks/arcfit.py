"""Benchmark: batched arc fits, jaxcal's `jit(vmap(fit_arc))` against SciPy's Levenberg-Marquardt.

What is compared: N random single-marker joint sweeps (encoders and
orientations, 0.1 mm / 1 mrad noise, a fixed seed) are fitted

- by jaxcal, as one `jax.jit(jax.vmap(fit_arc))` call (closed-form start,
  optimistix Levenberg-Marquardt, covariance). Compile time (`compile_s`,
  via `.lower(...).compile()`) is reported apart from the best of three runs
  (`jaxcal_s`);
- by `scipy.optimize.least_squares(method="lm")` (MINPACK) in a Python loop,
  on a NumPy residual that is the same model as `jaxcal._arcfit.arc_residuals`
  (same parameterisation, whitening and geodesic rotation error), from the
  same closed-form start, which jaxcal computes for every problem beforehand,
  outside SciPy's clock. SciPy runs twice: with its own finite differences
  (`scipy_s`) and with the exact Jacobian of a jitted `jax.jacfwd` of the
  single-problem residual (`scipy_jac_s`, call overhead included). SciPy is
  timed on a subset (`--scipy-problems`) and scaled to N.

How to run (from the repository root)::

    .venv/bin/python benchmarks/arcfit.py --json results/arcfit.json
    .venv/bin/python benchmarks/arcfit.py --quick          # smoke run

The JSON (printed, and written atomically with `--json`) holds `n_problems`,
`frames`, `jaxcal_s`, `compile_s`, `scipy_s`, `speedup`, `scipy_jac_s`,
`speedup_vs_jac`, `max_abs_diff` (largest difference between the two
solutions' axis direction, axis point and rate), `device`, `notes`, and
details (solver steps, a per-part breakdown of jaxcal's time).
"""

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import scipy
from scipy.optimize import least_squares

import jaxcal
from jaxcal._arcdata import ArcData
from jaxcal._arcfit import fit_arc
from jaxcal._arcmodel import ArcParams, ArcReference, arc_residuals, initialise_arc

SIGMA_P = 1e-4  # m
SIGMA_R = 1e-3  # rad

# --------------------------------------------------------------------------- NumPy geometry


_I, _J = np.array([2, 0, 1]), np.array([1, 2, 0])  # vee(R - R^T) = R[_I, _J] - R[_J, _I]


def skew_np(w: np.ndarray) -> np.ndarray:
    """`[w]_x` for `(..., 3)` vectors."""
    K = np.zeros(w.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2] = -w[..., 2], w[..., 1]
    K[..., 1, 0], K[..., 1, 2] = w[..., 2], -w[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -w[..., 1], w[..., 0]
    return K


def so3_exp_np(w: np.ndarray) -> np.ndarray:
    """Rodrigues' formula for `(..., 3)` rotation vectors, with jaxcal's small-angle branch."""
    theta_sq = np.einsum("...i,...i->...", w, w)
    small = theta_sq < 1e-12
    safe_sq = np.where(small, 1.0, theta_sq)
    theta = np.sqrt(safe_sq)
    a = np.where(small, 1.0 - theta_sq / 6.0, np.sin(theta) / theta)[..., None, None]
    b = np.where(small, 0.5 - theta_sq / 24.0, (1.0 - np.cos(theta)) / safe_sq)[..., None, None]
    K = skew_np(w)
    return np.eye(3) + a * K + b * (K @ K)


def so3_log_np(R: np.ndarray) -> np.ndarray:
    """Rotation vectors of `(..., 3, 3)` rotations: $\\theta = \\mathrm{atan2}(\\|s\\|, c)$ as in jaxcal."""
    s = 0.5 * (R[..., _I, _J] - R[..., _J, _I])
    c = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    sin_theta = np.sqrt(np.einsum("...i,...i->...", s, s))
    theta = np.arctan2(sin_theta, c)
    small = sin_theta < 1e-6
    scale = np.where(small, 1.0 + sin_theta**2 / 6.0, theta / np.where(small, 1.0, sin_theta))
    return scale[..., None] * s


# --------------------------------------------------------------------------- NumPy arc model


def arc_residuals_np(
    x: np.ndarray,
    P: np.ndarray,
    O: np.ndarray,
    enc: np.ndarray,
    R_ref: np.ndarray,
    c: np.ndarray,
    O_ref: np.ndarray,
    w: np.ndarray,
) -> np.ndarray:
    """`jaxcal._arcfit.arc_residuals` in NumPy, flattened (encoders and orientations, all observed).

    **Arguments:**
    - `x`: `(line (4), rate, p0 (markers*3), r0 (markers*3))`, the order of
      `ravel_pytree(ArcParams)`.
    - `P` `(markers, frames, 3)`, `O` `(markers, frames, 3, 3)`, `enc` `(frames,)`:
      the sweep; `R_ref`, `c`, `O_ref` `(markers, 3, 3)`: the reference of the
      parameterisation; `w` `(6,)`: the diagonal whitening `1/sigma`.

    **Returns:** `(markers * frames * 6,)` whitened residuals.
    """
    M = P.shape[0]
    line, rate = x[:4], x[4]
    p0 = x[5 : 5 + 3 * M].reshape(M, 3)
    r0 = x[5 + 3 * M :].reshape(M, 3)
    V = R_ref @ np.array([line[0], line[1], 1.0])
    V = V / np.sqrt(V @ V)
    Q = c + R_ref[:, :2] @ line[2:]
    phi = rate * enc
    s, c1 = np.sin(phi)[:, None], (1.0 - np.cos(phi))[:, None]
    # Rodrigues about the unit axis with the frame-independent parts hoisted, as jaxcal:
    # R_t x = x + s_t V x x + (1 - c_t) V x (V x x), and V x d = K d.
    K = skew_np(V)
    d = p0 - Q
    a = d @ K.T
    b = a @ K.T
    e_pos = (Q + d)[:, None, :] + s * a[:, None, :] + c1 * b[:, None, :] - P  # (M, F, 3)
    O0 = O_ref @ so3_exp_np(r0)  # (M, 3, 3)
    G1 = K @ O0
    G2 = K @ G1
    O_pred = O0[:, None] + s[..., None] * G1[:, None] + c1[..., None] * G2[:, None]  # (M, F, 3, 3)
    e = np.concatenate([e_pos, so3_log_np(O @ np.swapaxes(O_pred, -1, -2))], axis=-1)
    return (e * w).reshape(-1)


def flat_params(params: ArcParams) -> np.ndarray:
    """`(line, rate, p0, r0)` of one problem as a NumPy vector (the order of `ravel_pytree`)."""
    return np.concatenate(
        [np.asarray(params.line), np.asarray(params.rate)[None], np.ravel(params.p0), np.ravel(params.r0)]
    )


def unflatten_params(x, M: int) -> ArcParams:
    """Inverse of `flat_params` for `M` markers (works on NumPy and JAX arrays)."""
    return ArcParams(
        line=x[:4], rate=x[4], p0=x[5 : 5 + 3 * M].reshape(M, 3), r0=x[5 + 3 * M :].reshape(M, 3), angles=None
    )


def _jax_flat_residual(x, P, O, enc, R_ref, c, O_ref, W):
    """jaxcal's own `arc_residuals`, flattened, as a function of the NumPy parameter vector."""
    M, F = P.shape[:2]
    data = ArcData(positions=P, orientations=O, encoder=enc, mask=jnp.ones((M, F), bool), sqrt_info=W)
    ref = ArcReference(R_ref=R_ref, c=c, O_ref=O_ref, gauge=jnp.ones(F))
    return arc_residuals(unflatten_params(x, M), (ref, data)).reshape(-1)


jax_residual = jax.jit(_jax_flat_residual)
jax_jacobian = jax.jit(jax.jacfwd(_jax_flat_residual))


def axis_from_params(x: np.ndarray, R_ref, c, P) -> tuple[np.ndarray, np.ndarray, float]:
    """(V, Q, rate) as `fit_arc` reports them: Q is the axis point closest to the markers' centroid."""
    line = x[:4]
    V = R_ref @ np.array([line[0], line[1], 1.0])
    V = V / np.linalg.norm(V)
    Q = c + R_ref[:, :2] @ line[2:]
    centroid = P.reshape(-1, 3).mean(0)
    return V, Q + np.dot(centroid - Q, V) * V, float(x[4])


# --------------------------------------------------------------------------- problems


def make_problems(n: int, frames: int, *, seed: int = 0, span: float = 1.2) -> tuple[dict, ArcData]:
    """`n` random single-marker sweeps (as `tests/helpers.arc_problem`), noisy, with encoders.

    **Returns:** the truth `(V, Q, rate)` and a batched `ArcData` (leading axis `n`).
    """
    rng = np.random.default_rng(seed)
    V = rng.normal(size=(n, 3))
    V /= np.linalg.norm(V, axis=-1, keepdims=True)
    Q = 0.3 * rng.normal(size=(n, 3)) + np.array([0.0, 0.0, 1.0])
    p0 = Q + 0.2 * rng.normal(size=(n, 3))
    O0 = so3_exp_np(rng.normal(size=(n, 3)))
    rate = 1.0 + 0.01 * rng.normal(size=n)
    alpha = np.linspace(-span / 2, span / 2, frames)
    R = so3_exp_np(V[:, None, :] * (rate[:, None] * alpha)[..., None])  # (n, F, 3, 3)
    P = Q[:, None] + np.einsum("nfab,nb->nfa", R, p0 - Q) + SIGMA_P * rng.normal(size=(n, frames, 3))
    O = so3_exp_np(SIGMA_R * rng.normal(size=(n, frames, 3))) @ (R @ O0[:, None])
    enc = np.broadcast_to(alpha, (n, frames))
    data = jax.vmap(
        lambda P, O, a: jaxcal.make_arc_data(P, O, a, sigma_position=SIGMA_P, sigma_rotation=SIGMA_R)
    )(jnp.asarray(P), jnp.asarray(O), jnp.asarray(enc))
    return dict(V=V, Q=Q, rate=rate), data


# --------------------------------------------------------------------------- timing


def _best_of(fn, repeats: int) -> tuple[float, object]:
    best, out = float("inf"), None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn())
        best = min(best, time.perf_counter() - t0)
    return best, out


def _solve_only(data: ArcData):
    """`fit_arc` without its covariance and summary: the closed-form start and the LM solve."""
    params0, ref = initialise_arc(data)
    solver = optx.LevenbergMarquardt(rtol=1e-8, atol=3e-2)
    return optx.least_squares(arc_residuals, solver, params0, (ref, data), max_steps=50, throw=False).value


def time_jaxcal(data: ArcData, repeats: int) -> dict:
    """Compile once, then the best of `repeats` runs of the full fit and of its parts."""
    t0 = time.perf_counter()
    fit = jax.jit(jax.vmap(fit_arc)).lower(data).compile()
    compile_s = time.perf_counter() - t0
    run_s, out = _best_of(lambda: fit(data), repeats)
    parts = {}
    for name, fn in (("initialise_arc", initialise_arc), ("initialise_and_solve", _solve_only)):
        compiled = jax.jit(jax.vmap(fn)).lower(data).compile()
        parts[name], _ = _best_of(lambda c=compiled: c(data), repeats)
    return dict(compile_s=compile_s, run_s=run_s, out=out, parts=parts)


def time_scipy(problems: list[tuple], x0: list, jac_args: list | None = None) -> tuple[float, list]:
    """Solve every problem with MINPACK LM in a Python loop; the wall time and SciPy's results.

    With `jac_args` (the problems' arrays on the device), the Jacobian is jaxcal's, by `jax_jacobian`.
    """
    results = []
    t0 = time.perf_counter()
    for i, (x_init, args) in enumerate(zip(x0, problems)):
        if jac_args is None:
            results.append(least_squares(arc_residuals_np, x_init, method="lm", args=args))
        else:

            def jac(x, *_, a=jac_args[i]):
                return np.asarray(jax_jacobian(x, *a))

            results.append(least_squares(arc_residuals_np, x_init, jac=jac, method="lm", args=args))
    return time.perf_counter() - t0, results


def _count_calls(problems: list[tuple], x0: list) -> float:
    """Mean number of NumPy residual evaluations per problem, finite differences included."""
    calls = 0

    def counted(x, *args):
        nonlocal calls
        calls += 1
        return arc_residuals_np(x, *args)

    for x_init, args in zip(x0, problems):
        least_squares(counted, x_init, method="lm", args=args)
    return calls / len(problems)


def _device_args(problems):
    """The fixed arguments of JAX's Jacobian, on the device and with the full whitening matrix."""
    out = []
    for P, O, enc, R_ref, c, O_ref, w in problems:
        W = np.broadcast_to(np.diag(w), P.shape[:2] + (6, 6))
        out.append(tuple(jax.device_put(a) for a in (P, O, enc, R_ref, c, O_ref, W)))
    return out


# --------------------------------------------------------------------------- main


def run(n: int, frames: int, n_scipy: int, repeats: int, seed: int) -> dict:
    truth, data = make_problems(n, frames, seed=seed)
    jx = time_jaxcal(data, repeats)
    out = jx["out"]

    # SciPy's inputs: jaxcal's closed-form start for every problem, outside SciPy's clock.
    params0, ref = jax.jit(jax.vmap(initialise_arc))(data)
    n_scipy = min(n_scipy, n)
    Pn, On, En = np.asarray(data.positions), np.asarray(data.orientations), np.asarray(data.encoder)
    Rn, cn, ORn = np.asarray(ref.R_ref), np.asarray(ref.c), np.asarray(ref.O_ref)
    Wn = np.asarray(data.sqrt_info)
    w = np.diagonal(Wn[0, 0, 0])
    if not np.allclose(Wn, np.diag(w)):
        raise ValueError("the NumPy residual assumes one diagonal whitening for every frame")
    problems = [(Pn[i], On[i], En[i], Rn[i], cn[i], ORn[i], w) for i in range(n_scipy)]
    x0 = [flat_params(jax.tree.map(lambda a, i=i: a[i], params0)) for i in range(n_scipy)]

    # The NumPy residual is jaxcal's model: compare at the start.
    dev = _device_args(problems)
    model_diff = max(
        float(np.max(np.abs(arc_residuals_np(x, *p) - np.asarray(jax_residual(x, *d)))))
        for x, p, d in zip(x0[:20], problems[:20], dev[:20])
    )
    # Warm up the jitted Jacobian (its compile is not SciPy's run time).
    jax.block_until_ready(jax_jacobian(x0[0], *dev[0]))

    scipy_t, res_fd = min((time_scipy(problems, x0) for _ in range(repeats)), key=lambda r: r[0])
    scipy_jac_t, res_jac = min(
        (time_scipy(problems, x0, jac_args=dev) for _ in range(repeats)), key=lambda r: r[0]
    )

    # Compare solutions: (V, Q, rate), Q the axis point closest to the centroid, as fit_arc reports.
    diffs, diffs_jac, diffs_truth = [], [], []
    for i in range(n_scipy):
        P, R_ref, c = Pn[i], Rn[i], cn[i]
        ours = np.concatenate([np.asarray(out.direction[i]), np.asarray(out.point[i]), [float(out.rate[i])]])
        for res, acc in ((res_fd[i], diffs), (res_jac[i], diffs_jac)):
            V, Q, r = axis_from_params(res.x, R_ref, c, P)
            acc.append(np.max(np.abs(np.concatenate([V, Q, [r]]) - ours)))
        diffs_truth.append(np.max(np.abs(np.asarray(out.direction[i]) - truth["V"][i])))

    steps = np.asarray(out.num_steps)
    ok = np.asarray(out.result == optx.RESULTS.successful)
    scipy_s = scipy_t / n_scipy * n
    scipy_jac_s = scipy_jac_t / n_scipy * n
    return dict(
        n_problems=n,
        frames=frames,
        jaxcal_s=jx["run_s"],
        compile_s=jx["compile_s"],
        scipy_s=scipy_s,
        speedup=scipy_s / jx["run_s"],
        scipy_jac_s=scipy_jac_s,
        speedup_vs_jac=scipy_jac_s / jx["run_s"],
        max_abs_diff=float(max(diffs)),
        max_abs_diff_jac=float(max(diffs_jac)),
        device=jax.devices()[0].platform,
        scipy_measured_problems=n_scipy,
        scipy_per_problem_ms=1e3 * scipy_t / n_scipy,
        scipy_jac_per_problem_ms=1e3 * scipy_jac_t / n_scipy,
        jaxcal_per_problem_ms=1e3 * jx["run_s"] / n,
        jaxcal_parts_s=jx["parts"],
        jaxcal_success_rate=float(ok.mean()),
        jaxcal_num_steps=dict(mean=float(steps.mean()), max=int(steps.max())),
        scipy_nfev=dict(mean=float(np.mean([r.nfev for r in res_fd])), max=int(max(r.nfev for r in res_fd))),
        scipy_residual_calls_per_problem=_count_calls(problems[:20], x0[:20]),
        scipy_jac_nfev=dict(
            mean=float(np.mean([r.nfev for r in res_jac])), max=int(max(r.nfev for r in res_jac))
        ),
        scipy_jac_njev=dict(
            mean=float(np.mean([r.njev for r in res_jac])), max=int(max(r.njev for r in res_jac))
        ),
        scipy_success_rate=float(np.mean([r.status > 0 for r in res_fd])),
        scipy_jac_success_rate=float(np.mean([r.status > 0 for r in res_jac])),
        residual_model_max_diff=model_diff,
        direction_error_vs_truth_max=float(max(diffs_truth)),
        repeats=repeats,
        seed=seed,
        versions=dict(
            jax=jax.__version__,
            scipy=scipy.__version__,
            numpy=np.__version__,
            python=platform.python_version(),
        ),
        cpu_count=os.cpu_count(),
        notes=[
            "SciPy starts from jaxcal's closed-form initialise_arc, computed for all problems before "
            "SciPy's clock starts; jaxcal_s includes that initialisation (see jaxcal_parts_s), so the "
            "comparison favours SciPy.",
            "jaxcal_s also includes fit_arc's covariance (the closed-form Jacobian and a pinv per problem) and summary; "
            "SciPy computes neither. jaxcal_parts_s.initialise_and_solve is jaxcal without them.",
            "scipy_s: least_squares(method='lm') with its default 2-point finite differences (SciPy "
            "computes them in Python, approx_derivative, and drives MINPACK's lmder) on a vectorised "
            "NumPy residual (the same model as arc_residuals, checked: residual_model_max_diff); "
            "scipy_jac_s: the same with jac = a jitted jax.jacfwd of jaxcal's arc_residuals, called "
            "from NumPy (per-call dispatch included). Both timed on scipy_measured_problems (best of "
            "`repeats` loops, as jaxcal) and scaled to n_problems.",
            "Tolerances differ by design: jaxcal stops at rtol=1e-8, atol=3e-2 (steps below 3% of a "
            "noise standard deviation), SciPy at its defaults ftol=xtol=gtol=1e-8; max_abs_diff "
            "(m for the point, unitless for the direction and rate) reflects that.",
            "vmap runs every problem's LM loop until the slowest converges (jaxcal_num_steps.max).",
            "SciPy's nfev counts residual evaluations outside its finite differences; "
            "scipy_residual_calls_per_problem counts them all (untimed pass over 20 problems).",
        ],
    )


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
    parser.add_argument("--problems", type=int, default=1000, help="arc problems fitted by jaxcal")
    parser.add_argument("--frames", type=int, default=40, help="frames per sweep")
    parser.add_argument("--scipy-problems", type=int, default=200, help="problems timed with SciPy")
    parser.add_argument("--repeats", type=int, default=3, help="timed jaxcal runs (best is kept)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--quick", action="store_true", help="a small smoke run")
    parser.add_argument("--json", metavar="OUT", help="also write the JSON here")
    args = parser.parse_args(argv)
    if args.quick:
        args.problems, args.scipy_problems, args.repeats = 50, 10, 1
    print(
        f"{args.problems} arc fits in one vmapped call ({args.repeats} timed runs), {args.scipy_problems} with "
        "SciPy (compiling first: most of a minute) ...",
        flush=True,
    )
    result = run(args.problems, args.frames, args.scipy_problems, args.repeats, args.seed)
    if args.json:
        write_json(result, args.json)
    print(json.dumps(result, indent=2) if not args.json else f"wrote {args.json}")


if __name__ == "__main__":
    main()
