"""The measured points of a CSV against the nominal robot's (`jaxcal.io.csv_import`), in NumPy.

- `rigid_alignment`: the nominal points moved rigidly onto the measured ones, robust to a few
  wild rows;
- `reread_hint`: why a far row lies far where its joints read in the other angle unit explain it
  (a row typed in radians in a table of degrees);
- `far_rows`: the warning for rows much further from the nominal robot than the others.
"""

from pathlib import Path

import numpy as np

#: A row further from the nominal robot (after the rigid alignment) than this many times the median
#: row, and than `FAR_MIN_M`, is warned of: one wrong joint cell puts a point tens of mm off.
FAR_FACTOR, FAR_MIN_M = 5.0, 0.01


def rigid_alignment(P: np.ndarray, Q: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The nominal points `Q` moved rigidly onto the measured `P` (Kabsch, least squares), and per row
    the distance between them; fitted again twice on the rows within max(tol, 3 x median) so that a
    few wild rows cannot skew it. **Returns:** `(Q moved (N, 3), distances (N,), rotation R)`, the
    move being `(Q - mean) @ R.T + mean'`."""
    keep = np.ones(len(P), bool)
    for _ in range(3):
        mp, mq = P[keep].mean(0), Q[keep].mean(0)
        U, _, Vt = np.linalg.svd((Q[keep] - mq).T @ (P[keep] - mp))
        R = Vt.T @ np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))]) @ U.T
        moved = (Q - mq) @ R.T + mp
        r = np.linalg.norm(P - moved, axis=1)
        keep = r <= max(tol, 3.0 * np.median(r))
    return moved, r, R


def reread_hint(k: int, P: np.ndarray, aligned: tuple, reread, limit: float) -> str:
    """Why row `k` may lie far from the nominal robot: `reread(k)` is the row's nominal point with
    its angles read in the other unit (None: no revolute joint); where that point lies within
    `limit` of the measured one (after the alignment `aligned = (nominal, moved, R)`) and ten
    times closer than as read, the row's joints are in that unit (where every row is far, the
    limit is, and a point a metre off as read and as re-read says nothing of the unit)."""
    alt = None if reread is None else reread(k)
    if alt is None:
        return ""
    nominal, moved, R = aligned
    point, other, stated = alt
    d = float(np.linalg.norm(P[k] - (moved[k] + (point - nominal[k]) @ R.T)))
    if d > limit or d > 0.1 * float(np.linalg.norm(P[k] - moved[k])):
        return ""
    return (
        f"; read as {other}, its joints put the point {1e3 * d:.3g} mm from where it was measured: that row's "
        f"joints are most likely in {other}, the others' in {stated} (--joint-unit)"
    )


def far_rows(path: Path, lines: np.ndarray, r: np.ndarray, hint) -> list[str]:
    """A warning for the rows much further from the nominal robot than the others (after the rigid
    alignment): `FAR_FACTOR` x the median row and at least `FAR_MIN_M`, the worst five named, each
    with `hint(k)` (`reread_hint`); `lines`: each row's line in the file."""
    limit = max(FAR_MIN_M, FAR_FACTOR * float(np.median(r)))
    far = np.flatnonzero(r > limit)
    if not far.size:
        return []
    worst = far[np.argsort(-r[far])][:5]
    rows = ", ".join(f"line {lines[k]} ({1e3 * r[k]:.1f} mm{hint(k)})" for k in worst)
    more = f" and {far.size - len(worst)} more" if far.size > len(worst) else ""
    return [
        f"{path}: {far.size} row(s) lie far from where the nominal robot puts them after the best rigid "
        f"alignment: {rows}{more}, against {1e3 * np.median(r):.2g} mm for the median row. A real arm is "
        "0.5-5 mm off its datasheet, so such a row most likely holds a wrong cell (a joint mistyped or "
        "from another pose, a swapped column): check it, and remove or correct it before calibrating"
    ]
