"""XLA's CPU compiler, set for programs like jaxcal's.

jaxcal's solvers are long straight-line programs of small dense algebra
(3x3 rotations, 6x6 blocks, Cholesky of a few dozen unknowns) inside
`while` loops. XLA's newer CPU fusion emitters (on by default since
jaxlib 0.5) spend most of the compile on them for nothing: with
`--xla_cpu_use_fusion_emitters=false` the arc fit compiles in about half the
time and runs no slower, and a cold `jaxcal calibrate data/ur5e_sweeps` takes
a quarter less CPU, to the same digits (`benchmarks/compile.py`; the figures
are in docs/performance.md).

XLA aborts the whole process on a flag it does not know, so the flag is
only added when the installed jaxlib carries it (its name is in the shared
library), and only when

- no JAX backend is running yet (XLA reads `XLA_FLAGS` once, when it
  starts),
- `XLA_FLAGS` does not already name it (the user's choice wins), and
- `JAXCAL_XLA_DEFAULTS=0` is not set (the opt-out).
"""

import mmap
import os
from pathlib import Path

#: The flag and its value; see the module docstring.
FUSION_EMITTERS_OFF = "--xla_cpu_use_fusion_emitters=false"


def _jaxlib_knows(flag_name: str) -> bool:
    """Whether a shared library of the installed jaxlib contains `flag_name`
    (XLA's flags are registered by name in its binary)."""
    try:
        import jaxlib
    except ImportError:
        return False
    needle = flag_name.encode()
    for path in Path(jaxlib.__file__).parent.glob("*.so"):
        try:
            if path.stat().st_size < 1 << 20:  # the thin Python-extension stubs
                continue
            with open(path, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as m:
                if m.find(needle) >= 0:
                    return True
        except (OSError, ValueError):
            continue
    return False


def configure_xla() -> bool:
    """Add jaxcal's XLA defaults to `XLA_FLAGS` where it is safe to; returns
    whether they were added."""
    if os.environ.get("JAXCAL_XLA_DEFAULTS", "").strip() == "0":
        return False
    flags = os.environ.get("XLA_FLAGS", "")
    name = FUSION_EMITTERS_OFF.split("=")[0].lstrip("-")
    if name in flags:
        return False
    from jax._src import xla_bridge

    if xla_bridge.backends_are_initialized():
        return False
    if not _jaxlib_knows(name):
        return False
    os.environ["XLA_FLAGS"] = f"{flags} {FUSION_EMITTERS_OFF}".strip()
    return True
