"""Full poses in a CSV (`jaxcal.io.csv_import`): orientation columns in a stated format and
direction, read into rotations and checked against the nominal robot.

- `orientations`: the columns as rotations, each checked to be one (a unit quaternion, a
  rotation vector within a turn, an orthonormal matrix of determinant +1), the line and the
  column(s) named;
- `directed`: a device-in-point pose (PnP's board in the camera) inverted into the point's pose
  in the device frame;
- `check_orientations`: the rotations of the device frame and of the mount fitted to all rows
  (`_npgeom.fit_sandwich`); each row, the device frame and the mount checked against them;
- `other_readings`: after a refusal, the other readings of the columns, for the importer to
  name the one that fits.
"""

import math
from pathlib import Path

import numpy as np

from .._npgeom import fit_sandwich, quaternion_to_matrix, rotation_angle, rotvec_to_matrix, so3_log
from ..errors import CsvImportError
from ._tracker import QUATERNION_TOL

#: `joint_unit` choices, to rad; `length_unit` choices, units per metre (a division keeps
#: 0.432471963 from 432.471963 mm, where a product by 1e-3 adds round-off digits).
ANGLE_UNITS = {"rad": 1.0, "deg": math.pi / 180.0}
LENGTH_UNITS = {"m": 1.0, "mm": 1000.0}

#: Largest angle between a measured orientation and the nominal robot's after the best device-frame
#: and mount rotations (deg). A real arm's joint errors turn the flange by a few degrees (the
#: simulator's Panda at 0.5 deg zero offsets and 0.2 deg origins: up to 5.1 deg); a quaternion in
#: the wrong order, an inverted rotation or degrees read as radians by tens of degrees.
ANGLE_TOL_DEG = 10.0
#: `orientation_format` choices and their column counts: a unit quaternion (scalar last or
#: first), a rotation vector (rad or deg), or a rotation matrix row by row (r11, r12, ..., r33).
ORIENTATION_FORMATS = {"quat-xyzw": 4, "quat-wxyz": 4, "rotvec-rad": 3, "rotvec-deg": 3, "matrix": 9}
#: `pose_direction` choices: a row is the point's pose in the device frame (a 6-DoF probe, a
#: motion-capture body, a flange camera's pose in a fixed board's frame), or the device frame's
#: pose in the point's (PnP's pose of the board in the camera's frame), inverted on import.
POSE_DIRECTIONS = ("point-in-device", "device-in-point")
#: A rotation matrix may be off orthonormal by this much (the largest entry of $R R^T - I$); it
#: is then projected onto the nearest rotation.
MATRIX_TOL = 1e-3
#: A rotation vector longer than this (rad) is degrees declared as radians.
MAX_ROTVEC_RAD = 2.0 * math.pi
#: The mount's rotation the orientations imply may differ from the stated one (the identity when
#: none is given) by this much (deg): the verdict's `stages.Limits.mount_deg`, beyond which the
#: calibration would be called suspect.
MOUNT_TOL_DEG = 10.0
#: Rounds of the alternating fit of the device frame's and the mount's rotations.
ORIENT_ROUNDS = 20


def rotations(raw: np.ndarray, fmt: str) -> np.ndarray:
    """The rotations `(N, 3, 3)` of orientation columns `raw` `(N, k)` read as `fmt`, unchecked
    (quaternions normalised, matrices as given)."""
    if fmt.startswith("quat"):
        xyzw = raw if fmt == "quat-xyzw" else raw[:, [1, 2, 3, 0]]
        return quaternion_to_matrix(xyzw / np.linalg.norm(xyzw, axis=1, keepdims=True))
    if fmt.startswith("rotvec"):
        return rotvec_to_matrix(raw * (math.pi / 180.0 if fmt == "rotvec-deg" else 1.0))
    return raw.reshape(-1, 3, 3)


def orientations(path: Path, raw: np.ndarray, fmt: str, cols: list[str], lines) -> np.ndarray:
    """Orientation columns `raw` `(N, k)` in format `fmt` (`ORIENTATION_FORMATS`) -> rotations
    `(N, 3, 3)`, each checked to be one: a refusal names the line and the column(s)."""
    where = f"(--orientation, --orientation-format {fmt})"
    if fmt.startswith("quat"):
        norm = np.linalg.norm(raw, axis=1)
        bad = np.flatnonzero(np.abs(norm - 1.0) > QUATERNION_TOL)
        if bad.size:
            raise CsvImportError(
                f"{path} line {lines[bad[0]]} columns {cols} {where}: norm {norm[bad[0]]:.6g}; expected a unit "
                f"quaternion (within {QUATERNION_TOL:g}); {bad.size} of {len(raw)} rows"
            )
    elif fmt.startswith("rotvec"):
        angle = np.linalg.norm(raw, axis=1) * (math.pi / 180.0 if fmt == "rotvec-deg" else 1.0)
        bad = np.flatnonzero(angle > MAX_ROTVEC_RAD)
        if bad.size:
            hint = "; degrees? (--orientation-format rotvec-deg)" if fmt == "rotvec-rad" else ""
            raise CsvImportError(
                f"{path} line {lines[bad[0]]} columns {cols} {where}: a rotation vector of {angle[bad[0]]:.4g} rad, "
                f"more than a turn{hint}"
            )
    else:
        M = raw.reshape(-1, 3, 3)
        off = np.abs(M @ np.swapaxes(M, 1, 2) - np.eye(3))  # (N, row, row)
        det = np.linalg.det(M)
        bad = np.flatnonzero((off.max(axis=(1, 2)) > MATRIX_TOL) | (det < 0))
        if bad.size:
            k = bad[0]
            a = int(np.argmax(off[k].max(axis=1)))
            if det[k] < 0:
                where, what = cols, f"its determinant is {det[k]:.4g}: a reflection, not a rotation"
            else:
                where = f"{cols[3 * a : 3 * a + 3]} (matrix row {a + 1} of --orientation {','.join(cols)}, row by row)"
                what = f"not orthonormal: R R^T - I reaches {off[k].max():.3g} (tolerance {MATRIX_TOL:g})"
            raise CsvImportError(
                f"{path} line {lines[k]} columns {where}: {what}; {bad.size} of {len(raw)} rows"
            )
        U, _, Vt = np.linalg.svd(M)
        return U @ Vt  # the nearest rotation (the determinants are positive)
    return rotations(raw, fmt)


def directed(P: np.ndarray, R: np.ndarray, direction: str) -> tuple[np.ndarray, np.ndarray]:
    """The point's position and orientation in the device frame from rows in `direction`
    (`POSE_DIRECTIONS`): a device-in-point pose $(R, t)$ inverted, $(R^T, -R^T t)$."""
    if direction == "point-in-device":
        return P, R
    Rt = np.swapaxes(R, 1, 2)
    return -np.einsum("nab,nb->na", Rt, P), Rt


def check_orientations(
    path: Path, R: np.ndarray, lines, F: np.ndarray, A0: np.ndarray, mount, spec
) -> np.ndarray:
    """The measured orientations `R` `(N, 3, 3)` (the point's in the device frame; `lines`: their
    lines in the CSV) against the nominal robot's link rotations `F` `(N, 3, 3)`: each within
    `ANGLE_TOL_DEG` after the best device-frame and mount rotations (`_npgeom.fit_sandwich`, from
    `A0`, the points' alignment), the device frame within `ANGLE_TOL_DEG` of `A0` (when the
    point's mount is given; its offset otherwise blurs the points' alignment), and the mount's
    rotation within `MOUNT_TOL_DEG` of `mount` (None: the mount is not given, the fit measures it).
    `spec`: `(columns, orientation_format, pose_direction)`. **Returns:** the mount's rotation."""
    cols, fmt, direction = spec
    where = f"columns {list(cols)} (--orientation-format {fmt}, --pose-direction {direction})"
    A, B, angle = fit_sandwich(R, F, A0, rounds=ORIENT_ROUNDS)
    tol = math.radians(ANGLE_TOL_DEG)
    bad = np.flatnonzero(angle > tol)
    if bad.size:
        k = bad[np.argmax(angle[bad])]
        raise CsvImportError(
            f"{path} line {lines[k]} {where}: the orientation lies {math.degrees(angle[k]):.3g} deg from the "
            f"nominal robot's after the best rotations of the device frame and of the mount fitted to all rows "
            f"(tolerance {ANGLE_TOL_DEG:g} deg); {bad.size} of {len(angle)} rows; check that row's cells, the "
            "columns' order and the format"
        )
    turn = float(rotation_angle(A0.T @ A))
    if mount is not None and turn > tol:
        raise CsvImportError(
            f"{path} {where}: the orientations put the device frame {math.degrees(turn):.3g} deg from where the "
            f"points put it (tolerance {ANGLE_TOL_DEG:g} deg): are the orientations in the positions' frame?"
        )
    if mount is not None and rotation_angle(mount.T @ B) > math.radians(MOUNT_TOL_DEG):
        w, w0 = (",".join(f"{round(v, 2) + 0.0:g}" for v in np.degrees(so3_log(M))) for M in (B, mount))
        stated = f"point-rotvec-deg {w0}" if rotation_angle(mount) > 0 else "none given: not turned"
        raise CsvImportError(
            f"{path} {where}: the orientations turn the point's frame {math.degrees(rotation_angle(B)):.3g} deg on "
            f"its link (rotation vector {w} deg), {math.degrees(rotation_angle(mount.T @ B)):.3g} deg from the "
            f"stated mount ({stated}; tolerance {MOUNT_TOL_DEG:g} deg, beyond which the calibration is "
            f"suspect): give the mount's rotation, --config point-rotvec-deg={w}"
        )
    return B


def other_readings(raw: np.ndarray, P: np.ndarray, R: np.ndarray, spec):
    """After a refusal: the other readings of orientation columns `raw` (the quaternion's order,
    the rotation vector's unit, the matrix's order, the pose's direction) of a table read as
    `spec` `(columns, format, direction)` into positions `P` and orientations `R`: per reading
    `(P, R, spec, what to tell)`, for the caller to check."""
    cols, fmt, direction = spec
    xyz = directed(P, R, direction)[0]  # the positions as read
    other = {"quat-xyzw": "quat-wxyz", "quat-wxyz": "quat-xyzw", "rotvec-rad": "rotvec-deg"}
    other |= {"rotvec-deg": "rotvec-rad", "matrix": "matrix"}
    flip = dict(zip(POSE_DIRECTIONS, POSE_DIRECTIONS[::-1]))
    tries = [
        (f, d, f"--orientation-format {f} --pose-direction {d}")
        for f in dict.fromkeys([fmt, other[fmt]])
        for d in (direction, flip[direction])
        if (f, d) != (fmt, direction)
    ]
    if fmt == "matrix":
        tries.insert(0, ("matrix-columns", direction, "the matrices column by column (list them row by row)"))
    for f, d, text in tries:
        M = rotations(raw, "matrix").transpose(0, 2, 1) if f == "matrix-columns" else rotations(raw, f)
        yield (*directed(xyz, M, d), (cols, fmt if f == "matrix-columns" else f, d), text)


def check_orientation_arguments(orientation, orientation_format, pose_direction, sigma_rad, point, rotvec):
    """An orientation's columns, format, direction and noise; the mount's rotation (3, 3) or None."""
    if orientation is None:
        if orientation_format is not None or pose_direction is not None:
            raise ValueError(
                "orientation_format and pose_direction describe orientation columns: none are given"
            )
    else:
        if orientation_format not in ORIENTATION_FORMATS:
            raise ValueError(
                f"orientation_format must be one of {sorted(ORIENTATION_FORMATS)} (no default: state the "
                f"convention), got {orientation_format!r}"
            )
        k = ORIENTATION_FORMATS[orientation_format]
        if len(orientation) != k:
            raise ValueError(
                f"orientation names {len(orientation)} columns {list(orientation)}; format {orientation_format} "
                f"has {k}"
            )
        if pose_direction not in POSE_DIRECTIONS:
            raise ValueError(
                f"pose_direction must be one of {POSE_DIRECTIONS} (no default: state which frame each row's pose "
                f"is in), got {pose_direction!r}"
            )
        if not (isinstance(sigma_rad, (int, float)) and 0.0 < sigma_rad <= 1.0):
            raise ValueError(f"an orientation needs sigma_rad (its noise, rad) in (0, 1], got {sigma_rad!r}")
    if rotvec is None:
        return None if point is None else np.eye(3)
    w = np.asarray(rotvec, np.float64)
    if w.shape != (3,) or not np.all(np.isfinite(w)) or np.linalg.norm(w) > MAX_ROTVEC_RAD:
        raise ValueError(f"point_rotvec_rad must be 3 finite numbers within a turn (rad), got {rotvec!r}")
    if point is None:
        raise ValueError(
            "point_rotvec_rad (the mount's rotation) needs point_m (its offset): a mount is given whole"
        )
    return rotvec_to_matrix(w)
