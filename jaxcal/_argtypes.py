"""The command line's number types, shared by `jaxcal.cli` and `jaxcal.planning` (argparse, no JAX).

Every number an option takes is checked by its type before any work: a float is finite
(`finite`: `nan` or `inf` never reaches a computation or a file), and a count that sizes
work or memory lies within a documented bound (`count`), each refused by argparse naming
the option. `tests/test_escapes.py` holds every option of every command to them.
"""

import argparse
import math


def finite(text: str) -> float:
    """An argparse type: a finite number (not `nan`, `inf`)."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return v


def positive(text: str) -> float:
    """An argparse type: a finite number above zero (a distance, a size)."""
    v = finite(text)
    if v <= 0.0:
        raise argparse.ArgumentTypeError(f"expected a number above zero, got {text!r}")
    return v


def non_negative(text: str) -> float:
    """An argparse type: a finite number, zero or above (a noise's standard deviation)."""
    v = finite(text)
    if v < 0.0:
        raise argparse.ArgumentTypeError(f"expected a number of zero or more, got {text!r}")
    return v


def count(lo: int, hi: int):
    """An argparse type: an integer from `lo` to `hi` (the bound of an option that sizes work
    or memory, documented in its help)."""

    words = {0: "a non-negative integer", 1: "a positive integer"}.get(lo, f"an integer >= {lo}")

    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            v = None
        if v is None or v < lo:
            raise argparse.ArgumentTypeError(f"expected {words}, got {text!r}")
        if v > hi:
            raise argparse.ArgumentTypeError(f"expected {words} of at most {hi:,}, got {text!r}")
        return v

    return parse


def resolution(max_side: int, max_pixels: int):
    """The type of a `WxH` option: each side from 1 to `max_side` pixels and at most `max_pixels`
    in all (what the dataset reader takes: `jaxcal.io._images`)."""

    def parse(text: str) -> tuple[int, int]:
        try:
            w, h = (int(v) for v in text.lower().split("x"))
        except ValueError:
            raise argparse.ArgumentTypeError(f"resolution must look like 640x480, got {text!r}") from None
        if not (1 <= w <= max_side and 1 <= h <= max_side and w * h <= max_pixels):
            raise argparse.ArgumentTypeError(
                f"resolution {text!r}: each side from 1 to {max_side} pixels, at most {max_pixels / 1e6:g} megapixels"
            )
        return w, h

    return parse
