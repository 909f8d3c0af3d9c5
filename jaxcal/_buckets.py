"""Array sizes rounded up to a few buckets, so datasets of similar size share compiled programs.

Every jitted solver compiles once per input shape. The number of frames in a
sweep, of views in a refinement or of samples in an encoder log differs from
one capture to the next, so the stages pad them (with a mask, or, for a log,
with samples past its end) to the next size of a short geometric ladder
(ratio at most 1.5): at most a third of the work is padding, and a second
capture of about the same size starts without compiling.
"""

import numpy as np

#: The smallest bucket.
SMALLEST = 8


def bucket(n: int) -> int:
    """The smallest size of the ladder 8, 12, 16, 24, 32, 48, 64, 96, ... that holds `n`."""
    n = int(n)
    if n < 0:
        raise ValueError(f"bucket: a size cannot be negative, got {n}")
    size = SMALLEST
    while size < n:
        size = size * 3 // 2 if (size & (size - 1)) == 0 else size * 4 // 3
    return size


def pad_log(t: np.ndarray, values: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """A time series `(t (T,), values (T, ...))` extended to `size` samples past
    its end: times 1 s apart after the last, values held at the last. Linear
    interpolation inside the original span, and its clamping outside it, are
    unchanged."""
    t = np.asarray(t, np.float64)
    extra = size - t.shape[0]
    if extra < 0:
        raise ValueError(f"pad_log: {t.shape[0]} samples do not fit in {size}")
    if extra == 0:
        return t, np.asarray(values)
    t_pad = t[-1] + np.arange(1, extra + 1, dtype=np.float64)
    v_pad = np.broadcast_to(values[-1:], (extra,) + values.shape[1:])
    return np.concatenate([t, t_pad]), np.concatenate([values, v_pad])
