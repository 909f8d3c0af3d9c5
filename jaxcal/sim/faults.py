"""Faults injected into a copy of a rendered dataset, for robustness tests and benchmarks.

`shear_copy` copies a dataset and shears some of its images about the plate's
image centre: the plate still decodes, but its corners move by up to ~10 px
(a bent or smeared plate, a rolling-shutter wobble), so each affected frame
gives a confidently wrong marker pose. The source dataset is never modified.
"""

import shutil
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from ..io.dataset import load_dataset, true_poses


def shear_copy(
    src,
    dst,
    *,
    rows: Sequence[int] | None = None,
    fraction: float | None = None,
    shear: float = 0.08,
    seed: int = 0,
) -> list[str]:
    """Copy dataset `src` (with `truth.json`) to `dst` and shear images in place there.

    The sheared images are the `frames.csv` `rows` given, or a random
    `fraction` of them (drawn with `seed`). Each is warped by
    $x' = x + s\\,(y - c_y)$ about the first target's projected origin
    $(c_x, c_y)$ (from the truth), with $s$ = `shear`.

    **Returns:** the sheared images' file names, relative to `dst`, sorted.
    """
    src, dst = Path(src), Path(dst)
    if (rows is None) == (fraction is None):
        raise ValueError("shear_copy: give rows or fraction")
    shutil.copytree(src, dst)
    ds = load_dataset(dst)
    truth = true_poses(ds.truth)
    K = np.asarray(ds.cameras[0].K)
    files = [str(f) for f in ds.frames.file]
    if rows is None:
        rng = np.random.default_rng(seed)
        rows = rng.choice(len(files), size=max(1, int(round(fraction * len(files)))), replace=False)
    for r in sorted(int(r) for r in rows):
        T = np.asarray(next(iter(truth.T_cam_target[r].values())))
        c = K @ T[:3, 3]
        cy = c[1] / c[2]
        image = cv2.imread(str(dst / files[r]), cv2.IMREAD_UNCHANGED)
        A = np.array([[1.0, shear, -shear * cy], [0.0, 1.0, 0.0]])
        if not cv2.imwrite(
            str(dst / files[r]), cv2.warpAffine(image, A, image.shape[1::-1], flags=cv2.INTER_LINEAR)
        ):
            raise OSError(f"could not write {dst / files[r]}")
    return sorted(files[int(r)] for r in rows)
