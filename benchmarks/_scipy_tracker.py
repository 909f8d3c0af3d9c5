"""Independent SciPy reference: stop-and-shoot UR5 calibration from laser-tracker points.

This module is a deliberately separate implementation (NumPy and
`scipy.optimize.least_squares` only; nothing from jaxcal's fitting code) of
the classic point-based kinematic calibration, written the way a typical SciPy
user would write it. The benchmark compares jaxcal's tracker calibration
against it.

Model (UR5, standard DH, `data/robots/ur5_dh.json` nominal)::

    p = R_b(w) @ (T_1 ... T_6 @ [p_tool; 1])[:3] + t_b
    T_i = Rz(theta_i + dtheta_i + q_i) Tz(d_i + dd_i) Tx(a_i + da_i) Rx(alpha_i + dalpha_i) [Ry(beta_i)]

with Hayati's extra rotation `Ry(beta_i)` on rows 2 and 3 (the parallel joint
pairs 2-3 and 3-4, where the DH `d` is ill-defined), a small base-frame
correction (translation `t_b`, rotation vector `w`) and the tool point
`p_tool` in the flange frame: 6 x 4 + 2 + 6 + 3 = 35 parameters.

The identifiable subset is chosen by a rank-revealing QR with column pivoting
of the column-normalised residual Jacobian at the nominal (columns whose
`|R_kk| / |R_00|` exceed `RANK_TOL`: 25 of 35 on the shipped grid); the
others stay at their nominal values.
The fit is `least_squares(method="lm", x_scale="jac")` on the residuals
predicted minus measured point (m), with SciPy's default finite-difference
Jacobian (`jac="complex"` selects an exact complex-step Jacobian instead).

Run (from the repository root)::

    .venv/bin/python benchmarks/_scipy_tracker.py
"""

from __future__ import annotations

import csv
import json
import time
from pathlib import Path

import numpy as np
import scipy.linalg
from scipy.optimize import least_squares

ROOT = Path(__file__).resolve().parents[1]
GRID = ROOT / "data" / "ur5_tracker" / "grid" / "samples.csv"
TEST = ROOT / "data" / "ur5_tracker" / "test" / "samples.csv"
DH_FILE = ROOT / "data" / "robots" / "ur5_dh.json"

JOINTS = (
    "shoulder_pan_joint",
    "shoulder_lift_joint",
    "elbow_joint",
    "wrist_1_joint",
    "wrist_2_joint",
    "wrist_3_joint",
)

_dh = json.loads(DH_FILE.read_text())
A0 = np.asarray(_dh["a"], float)
ALPHA0 = np.asarray(_dh["alpha"], float)
D0 = np.asarray(_dh["d"], float)
THETA0 = np.asarray(_dh["theta"], float)
TOOL0 = np.array([0.0, 0.00009, 0.031])  # nominal tool point in the flange frame (m)

#: Rows (0-based) that carry Hayati's beta: joints 2 and 3, whose axes are
#: parallel to the next joint's.
BETA_ROWS = (1, 2)

#: Parameter layout: per joint [da, dalpha, dd, dtheta] (24), beta (2), base
#: translation (3), base rotation vector (3), tool point (3).
N_JOINT = 6
I_JOINT = 0
I_BETA = 4 * N_JOINT
I_BASE_T = I_BETA + len(BETA_ROWS)
I_BASE_W = I_BASE_T + 3
I_TOOL = I_BASE_W + 3
N_PARAMS = I_TOOL + 3

#: Relative threshold on the pivoted QR's diagonal for a column to count as identifiable.
#: On the shipped grid the ratios fall from 4.0e-2 (dtheta1, the 25th pivot)
#: to 1.0e-4 (dtheta5) and 1.1e-5 (dalpha5), then to rounding (<1e-15: the
#: eight exact redundancies dd2, dd4, dalpha6, dtheta6, base_tz, base_wz,
#: tool_x, tool_z). dtheta5 and dalpha5 are only weakly observable because the
#: tool point lies 0.09 mm off the wrist-3 axis; a 1e-6 threshold keeps them
#: (27 free), the fit then crawls (about 250 Levenberg-Marquardt iterations
#: instead of 4) to the same test errors within 0.0001 mm. 1e-3 sits in the gap.
RANK_TOL = 1e-3


def param_names() -> list[str]:
    names = [f"{k}{i + 1}" for i in range(N_JOINT) for k in ("da", "dalpha", "dd", "dtheta")]
    names += [f"beta{i + 1}" for i in BETA_ROWS]
    names += ["base_tx", "base_ty", "base_tz", "base_wx", "base_wy", "base_wz"]
    names += ["tool_x", "tool_y", "tool_z"]
    return names


def nominal_params() -> np.ndarray:
    x = np.zeros(N_PARAMS)
    x[I_TOOL : I_TOOL + 3] = TOOL0
    return x


def load_samples(path) -> tuple[np.ndarray, np.ndarray]:
    """Joint angles `q` (N, 6) in rad and tracker points `y` (N, 3) in m from a samples CSV."""
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    q = np.array([[float(r[j]) for j in JOINTS] for r in rows])
    y = np.array([[float(r[c]) for c in ("x", "y", "z")] for r in rows])
    return q, y


def _rotvec_matrix(w: np.ndarray) -> np.ndarray:
    """Rodrigues' formula written through theta^2 only, so it is analytic (complex-step safe) at 0."""
    th2 = w @ w
    K = np.array([[0.0 * w[0], -w[2], w[1]], [w[2], 0.0 * w[0], -w[0]], [-w[1], w[0], 0.0 * w[0]]])
    if abs(th2) < 1e-8:
        s = 1.0 - th2 / 6.0 + th2**2 / 120.0
        c = 0.5 - th2 / 24.0 + th2**2 / 720.0
    else:
        th = np.sqrt(th2)
        s = np.sin(th) / th
        c = (1.0 - np.cos(th)) / th2
    return np.eye(3) + s * K + c * (K @ K)


def forward(x: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Predicted tracker points (N, 3) for parameters `x` (real or complex) at joint angles `q` (N, 6)."""
    dt = np.result_type(x.dtype, float)
    n = q.shape[0]
    # Running transform T = T_1 ... T_i as rotation R (N,3,3) and position p (N,3).
    R = np.broadcast_to(np.eye(3, dtype=dt), (n, 3, 3)).copy()
    p = np.zeros((n, 3), dtype=dt)
    for i in range(N_JOINT):
        da, dal, dd, dth = x[I_JOINT + 4 * i : I_JOINT + 4 * i + 4]
        th = THETA0[i] + dth + q[:, i]
        a = A0[i] + da
        al = ALPHA0[i] + dal
        d = D0[i] + dd
        ct, st = np.cos(th), np.sin(th)
        ca, sa = np.cos(al), np.sin(al)
        z = np.zeros_like(ct)
        o = np.ones_like(ct)
        # Rz(th) Tz(d) Tx(a) Rx(al): rotation Rz(th) Rx(al), translation (a ct, a st, d).
        Ri = np.stack(
            [
                np.stack([ct, -st * ca, st * sa], -1),
                np.stack([st, ct * ca, -ct * sa], -1),
                np.stack([z, sa * o, ca * o], -1),
            ],
            -2,
        )
        ti = np.stack([a * ct, a * st, d * o], -1)
        if i in BETA_ROWS:
            b = x[I_BETA + BETA_ROWS.index(i)]
            cb, sb = np.cos(b), np.sin(b)
            Ry = np.array([[cb, 0.0 * b, sb], [0.0 * b, 1.0 + 0.0 * b, 0.0 * b], [-sb, 0.0 * b, cb]])
            Ri = Ri @ Ry
        p = p + np.einsum("nij,nj->ni", R, ti)
        R = R @ Ri
    tool = x[I_TOOL : I_TOOL + 3]
    pt = p + np.einsum("nij,j->ni", R, tool)
    Rb = _rotvec_matrix(x[I_BASE_W : I_BASE_W + 3])
    return pt @ Rb.T + x[I_BASE_T : I_BASE_T + 3]


def residuals(x: np.ndarray, q: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Predicted minus measured points, flattened (3N,), in m."""
    return (forward(x, q) - y).ravel()


def complex_step_jacobian(x: np.ndarray, q: np.ndarray, y: np.ndarray, h: float = 1e-20) -> np.ndarray:
    """Exact (to rounding) Jacobian of `residuals` by the complex step, one column per parameter."""
    J = np.empty((3 * q.shape[0], x.size))
    for k in range(x.size):
        xc = x.astype(complex)
        xc[k] += 1j * h
        J[:, k] = forward(xc, q).ravel().imag / h
    return J


def select_identifiable(
    q: np.ndarray, y: np.ndarray, tol: float | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Free-parameter mask by pivoted QR of the column-normalised Jacobian at the nominal.

    Returns the mask (N_PARAMS,) and the ratios |R_kk| / |R_00| in pivot order.
    """
    tol = RANK_TOL if tol is None else tol
    J = complex_step_jacobian(nominal_params(), q, y)
    norms = np.linalg.norm(J, axis=0)
    Jn = J / np.where(norms > 0, norms, 1.0)
    _, Rq, piv = scipy.linalg.qr(Jn, mode="economic", pivoting=True)
    ratios = np.abs(np.diag(Rq)) / abs(Rq[0, 0])
    rank = int(np.sum(ratios > tol))
    free = np.zeros(N_PARAMS, bool)
    free[piv[:rank]] = True
    return free, ratios


def fit(
    q: np.ndarray, y: np.ndarray, jac: str = "2-point", method: str = "lm", tol: float | None = None
) -> dict:
    """Calibrate on (q, y); `jac="complex"` uses the complex-step Jacobian instead of finite differences.

    Only the identifiable parameters (`select_identifiable`, threshold `tol`)
    are fitted; `fit_s` times `least_squares` alone, after the selection.
    """
    free, _ = select_identifiable(q, y, tol)
    x0 = nominal_params()

    def full(z):
        x = x0.astype(np.result_type(z.dtype, float))
        x[free] = z
        return x

    def fun(z):
        return residuals(full(z), q, y)

    kw = {}
    if jac == "complex":
        kw["jac"] = lambda z: complex_step_jacobian(full(z), q, y)[:, free]
    else:
        kw["jac"] = jac
    t0 = time.perf_counter()
    sol = least_squares(fun, x0[free], method=method, x_scale="jac", **kw)
    fit_s = time.perf_counter() - t0
    x = full(sol.x)
    return {
        "x": x,
        "free": free,
        "n_free": int(free.sum()),
        "n_params": N_PARAMS,
        "fit_s": fit_s,
        "nfev": int(sol.nfev),
        "status": int(sol.status),
        "predict": lambda qq: forward(x, np.asarray(qq, float)),
    }


def test_errors_mm(result: dict, q: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Per-sample distance (mm) between the fitted model's prediction and the measured point."""
    return 1e3 * np.linalg.norm(result["predict"](q) - y, axis=1)


test_errors_mm.__test__ = False  # not a pytest test


def nominal_errors_mm(q: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Per-sample distance (mm) with the uncalibrated nominal model."""
    return 1e3 * np.linalg.norm(forward(nominal_params(), q) - y, axis=1)


def main() -> None:
    qg, yg = load_samples(GRID)
    qt, yt = load_samples(TEST)
    e0 = nominal_errors_mm(qt, yt)
    results = [fit(qg, yg) for _ in range(5)]
    r = results[0]
    e = test_errors_mm(r, qt, yt)
    names = param_names()
    print(f"parameters: {r['n_params']}, identifiable (free): {r['n_free']}")
    print("fixed:", ", ".join(n for n, f in zip(names, r["free"]) if not f))
    print(
        f"uncalibrated test: mean {e0.mean():.4f} mm, RMS {np.sqrt((e0**2).mean()):.4f} mm, max {e0.max():.4f} mm"
    )
    print(
        f"calibrated test:   mean {e.mean():.4f} mm, RMS {np.sqrt((e**2).mean()):.4f} mm, max {e.max():.4f} mm"
    )
    print(
        f"fit time (least_squares, 2-point FD, median of 5): {np.median([x['fit_s'] for x in results]):.3f} s"
    )
    rc = [fit(qg, yg, jac="complex") for _ in range(5)]
    ec = test_errors_mm(rc[0], qt, yt)
    print(
        f"complex-step Jacobian: test mean {ec.mean():.4f} mm, "
        f"fit time median of 5 {np.median([x['fit_s'] for x in rc]):.3f} s"
    )


if __name__ == "__main__":
    main()
