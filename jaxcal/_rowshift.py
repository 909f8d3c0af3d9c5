"""Measurements paired with the wrong robot rows (a table's rows shifted against the robot's), or
read otherwise than written.

A logger that writes each pose one frame late, a row lost and the rows after it renumbered, an
extra row: from some row on, measurement `i` belongs to robot row `i - shift`. The checks that see
such data fail (hand-eye: relative rotation angles; stop-and-shoot points: the nominal robot's
points) say which shift and from where makes them pass, instead of only that they fail.

- `pairings(n)`: every shifted pairing of `n` rows, up to `MAX_ROW_SHIFT` rows either way, from
  any row on.
- `shifted_points`: the stop-and-shoot check (NumPy): the nominal robot's flange frames against
  measured points, through one rigid device frame and one point on the flange.
- `describe`: the finding in words, with the rows' names.
- `misread_points`: a stop-and-shoot table that fits the nominal robot only with a joint's
  positions negated, two joints' columns swapped, or the device's coordinates mirrored.
"""

from collections.abc import Iterator

import numpy as np

from ._npgeom import kabsch

#: Rows shifted by up to this many rows either way are tried.
MAX_ROW_SHIFT = 3
#: A shifted pairing must pair at least this share of the rows.
MIN_PAIRED = 0.75


def pairings(n: int) -> Iterator[tuple[int, int, np.ndarray]]:
    """`(first, shift, rows)` for every shift up to `MAX_ROW_SHIFT` either way and every `first`:
    `rows[i]` the robot row of measurement `i` (`i - shift` from `first` on, `i` before it), -1
    where none (`shift` > 0: the `shift` rows before `first` were lost; past the table's end)."""
    for shift in (s for k in range(1, MAX_ROW_SHIFT + 1) for s in (-k, k)):
        for first in range(max(shift, 0), n):
            rows = np.arange(n)
            rows[first:] -= shift
            rows[first - max(shift, 0) : first] = -1
            rows[rows >= n] = -1
            if np.sum(rows >= 0) >= max(3, MIN_PAIRED * n):
                yield first, shift, rows


def describe(found: tuple[int, int, float], name, what: str, robot: str) -> str:
    """`found` (`first`, `shift`, the share of pairs that still disagree) in words: from `what`
    `name(first)` on, each one's `robot` is written `|shift|` rows earlier or later."""
    first, shift, bad = found
    rows = f"{abs(shift)} row{'s' if abs(shift) > 1 else ''}"
    if shift > 0:
        how = (
            f"from {what} {name(first)} on, each {what}'s {robot} is written {rows} earlier ({what} "
            f"{name(first)}'s in the row of {what} {name(first - shift)}): the {robot} row of {what} "
            f"{', '.join(name(f) for f in range(first - shift, first))} is missing and the rows after it were "
            "renumbered, or the measurements lag"
        )
    else:
        how = (
            f"from {what} {name(first)} on, each {what}'s {robot} is written {rows} later ({what} "
            f"{name(first)}'s in the row of {what} {name(first - shift)}): "
            + (f"the {robot}s were logged late, or " if first == 0 else "")
            + f"an extra {robot} row comes before {what} {name(first - shift)}"
        )
    return f"{how} ({100 * bad:.0f}% of them still disagree that way)"


#: Stop-and-shoot points: the nominal robot's point within this (m), or this many times the
#: median of every row's best fit, fits.
POINT_TOL_M = 0.01
POINT_TOL_MEDIANS = 4.0
#: ... the table as read may be shifted when this many of its rows misfit (fewer: bad samples the
#: robust fit leaves out, or two rows swapped) ...
AS_READ_MISFITS = 3
#: ... and is when a shifted pairing leaves at most this share of its rows unfitted, and at most
#: this share of the rows that misfit as read.
SHIFT_MISFITS = 0.05
SHIFT_GAIN = 0.25


def _align(F: np.ndarray, y: np.ndarray, keep: float, rounds: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """The device frame `T` `(4, 4)` and the flange point `t` `(3,)` best fitting `y_i = T F_i t`
    on the `keep` share of rows that fit best (trimmed alternation: Kabsch for the frame's
    rotation, linear least squares for the two translations)."""
    n = len(y)
    t = np.zeros(3)
    use = np.ones(n, bool)
    T = np.eye(4)
    for _ in range(rounds):
        p = np.einsum("nab,b->na", F[:, :3, :3], t) + F[:, :3, 3]
        T = kabsch(p[use], y[use])
        R = T[:3, :3]
        # y_i - R o_i = R R_i t + t_dev: linear in (t, t_dev).
        A = np.concatenate(
            [np.einsum("ab,nbc->nac", R, F[:, :3, :3]), np.broadcast_to(np.eye(3), (n, 3, 3))], -1
        )
        b = y - F[:, :3, 3] @ R.T
        sol = np.linalg.lstsq(A[use].reshape(-1, 6), b[use].reshape(-1), rcond=None)[0]
        t, T[:3, 3] = sol[:3], sol[3:]
        err = np.linalg.norm(np.einsum("nab,b->na", A, sol) - b, axis=1)
        use = err <= np.quantile(err, keep)
    return T, t


def _predicted(F: np.ndarray, T: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The flange point `t` on the frames `F`, seen from the device frame `T`: `(n, 3)`."""
    return (np.einsum("nab,b->na", F[:, :3, :3], t) + F[:, :3, 3]) @ T[:3, :3].T + T[:3, 3]


def shifted_points(F: np.ndarray, y: np.ndarray) -> tuple[int, int, float] | None:
    """Stop-and-shoot points shifted against the robot's rows: `(first, shift, misfit share)` or
    None. `F` `(n, 4, 4)`: the nominal robot's flange frames, row by row; `y` `(n, 3)` the points
    measured (m). When `AS_READ_MISFITS` rows or more misfit the nominal robot as paired, and a
    pairing of `pairings` fits all but `SHIFT_MISFITS` of its rows and `SHIFT_GAIN` of those, the
    best such pairing."""
    F, y = np.asarray(F, np.float64), np.asarray(y, np.float64)
    n = len(y)
    if n < 8:
        return None
    shifts = np.arange(-MAX_ROW_SHIFT, MAX_ROW_SHIFT + 1)

    def errors(T, t):  # (n, shifts): point i against the robot row i - s
        p = _predicted(F, T, t)
        E = np.full((n, len(shifts)), np.inf)
        for k, s in enumerate(shifts):
            i = np.arange(max(s, 0), n + min(s, 0))
            E[i, k] = np.linalg.norm(y[i] - p[i - s], axis=1)
        return E

    def aligned(s):  # the frame and point fitted to the pairing shifted by `s` from the first row
        i = np.arange(max(s, 0), n + min(s, 0))
        T, t = _align(F[i - s], y[i], 0.5)
        E = errors(T, t)
        return float(np.median(E[i, MAX_ROW_SHIFT + s])), E

    # The frame from the shift whose rows fit it best (from the first row: a pairing shifted from a
    # later row is fitted best by one of its two halves' shifts).
    E = min((aligned(s) for s in shifts), key=lambda m: m[0])[1]
    tol = max(POINT_TOL_M, POINT_TOL_MEDIANS * float(np.median(E.min(1))))
    fit = E <= tol
    misfits = int(np.sum(~fit[:, MAX_ROW_SHIFT]))
    if misfits < AS_READ_MISFITS:
        return None
    found = None
    for first, shift, rows in pairings(n):
        k = np.where(np.arange(n) < first, MAX_ROW_SHIFT, MAX_ROW_SHIFT + shift)
        paired = rows >= 0
        wrong = ~fit[np.flatnonzero(paired), k[paired]]
        bad = float(np.mean(wrong))
        if bad <= SHIFT_MISFITS and wrong.sum() <= SHIFT_GAIN * misfits and (found is None or bad < found[2]):
            found = (first, shift, bad)
    return found


#: A reading of the table explains it when at most this share of its rows lie farther than
#: `MISREAD_TOL_M` from the nominal robot, where at least `MISREAD_AS_READ` did as read (a real arm
#: is millimetres off its datasheet).
MISREAD_FITS, MISREAD_AS_READ, MISREAD_TOL_M = 0.05, 0.5, 0.02


def misfit_share(F: np.ndarray, y: np.ndarray) -> float:
    """The share of rows farther than `MISREAD_TOL_M` from the nominal robot (one device frame
    and flange point, fitted to the better half)."""
    return float(np.mean(np.linalg.norm(y - _predicted(F, *_align(F, y, 0.5)), axis=1) > MISREAD_TOL_M))


def misread_points(frames, q: np.ndarray, y: np.ndarray, joints: tuple[str, ...], F=None) -> str | None:
    """What fixes a stop-and-shoot table whose points fit the nominal robot only read otherwise
    (`frames(q)`: its flange frames `(n, 4, 4)` at joint positions `q`, `F` those of `q` when known;
    `y` the points, m), or None:
    one or two joints' positions negated (their direction opposite the robot file's axis), two
    joints' columns swapped, the device's coordinates mirrored (left-handed). Tried only when at least
    `MISREAD_AS_READ` of the rows misfit as read; a reading must fit all but `MISREAD_FITS`."""
    q, y = np.asarray(q, np.float64), np.asarray(y, np.float64)
    F = frames(q) if F is None else F  # as read
    if len(y) < 8 or misfit_share(F, y) < MISREAD_AS_READ:
        return None
    if misfit_share(F, y * np.array([-1.0, 1.0, 1.0])) <= MISREAD_FITS:
        return (
            "the points fit the nominal robot mirrored: the device's coordinates are left-handed (one axis "
            "reversed, or two swapped); write them in its right-handed frame"
        )
    n = q.shape[1]
    for flip in [(j,) for j in range(n)] + [(i, j) for i in range(n) for j in range(i + 1, n)]:
        flipped = q.copy()
        flipped[:, list(flip)] *= -1.0
        if misfit_share(frames(flipped), y) <= MISREAD_FITS:
            which = (
                f"joint {joints[flip[0]]!r}'s positions"
                if len(flip) == 1
                else f"the positions of joints {joints[flip[0]]!r} and {joints[flip[1]]!r}"
            )
            return (
                f"the points fit the nominal robot with {which} negated: the log turns "
                f"{'it' if len(flip) == 1 else 'them'} the other way than the robot file's axis (negate "
                f"{'that column' if len(flip) == 1 else 'those columns'}, or the robot file's axes)"
            )
    for i in range(n):
        for j in range(i + 1, n):
            swapped = q.copy()
            swapped[:, [i, j]] = q[:, [j, i]]
            if misfit_share(frames(swapped), y) <= MISREAD_FITS:
                return (
                    f"the points fit the nominal robot with the columns of {joints[i]!r} and {joints[j]!r} "
                    "swapped: the header names them the other way round"
                )
    return None
