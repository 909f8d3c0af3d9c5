"""The camera YAML both products write (`jaxcal calibrate`'s `camera_<name>.yaml` and
`jaxcal handeye`'s): an OpenCV FileStorage file of a camera's pose with its standard
deviation, its camera matrix and distortion, and the product's labels.

One writer, one convention for the values: strings and integers as they are, matrices as
float64 matrices, vectors (distortion coefficients, a pose's 1-sigma twist `tx ty tz` (m),
`rx ry rz` (rad) of `T = T0 @ exp(xi)`) as one row. Each product names its keys: the
calibration's (`camera_matrix`, `distortion_coefficients`, `T_cam_base`, ...) and hand-eye's
(`K`, `distortion`, `T_robot_cam`, ...) are the files users already read.
"""

from collections.abc import Sequence
from pathlib import Path

import numpy as np


def yaml_value(value):
    """`value` as FileStorage writes it: a str, int or float as is, a vector as a (1, n) float64
    row, any other array as a float64 matrix."""
    if isinstance(value, str):
        return value
    if isinstance(value, int | np.integer) and not isinstance(value, bool):
        return int(value)
    if isinstance(value, float):
        return value
    a = np.asarray(value, np.float64)
    return a.reshape(1, -1) if a.ndim == 1 else a


def pose_fields(
    name: str, T, std=None, *, inverse: str | None = None, std_key: str | None = None
) -> list[tuple[str, object]]:
    """A pose's fields: `name` (4x4), its inverse under `inverse` when named, and its 1-sigma
    twist (6) under `std_key` (default `<name>_std`) when given."""
    T = np.asarray(T, np.float64)
    out = [(name, T)]
    if inverse is not None:
        out.append((inverse, np.linalg.inv(T)))
    if std is not None:
        out.append((std_key or f"{name}_std", np.asarray(std, np.float64).ravel()))
    return out


def intrinsics_fields(K, distortion, *, keys=("camera_matrix", "distortion_coefficients")) -> list:
    """The camera matrix (3, 3) px and the OpenCV distortion coefficients, under `keys`."""
    return [(keys[0], np.asarray(K, np.float64)), (keys[1], np.asarray(distortion, np.float64).ravel())]


def write_camera_yaml(path: Path, fields: Sequence[tuple[str, object]]) -> None:
    """Write `fields` (`(key, value)` in order, values as `yaml_value` makes them) as an OpenCV
    FileStorage YAML file at `path`."""
    import cv2  # OpenCV only when a file is written (the package imports without it)

    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    try:
        for key, value in fields:
            fs.write(key, yaml_value(value))
    finally:
        fs.release()
