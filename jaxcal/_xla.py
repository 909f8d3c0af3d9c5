"""XLA's CPU compiler, set for programs like jaxcal's.

jaxcal's solvers are long straight-line programs of small dense algebra
(3x3 rotations, 6x6 blocks, Cholesky of a few dozen unknowns) inside
`while` loops. XLA's newer CPU fusion emitters (on by default since
jaxlib 0.5) spend most of the compile on them for nothing: with
`--xla_cpu_use_fusion_emitters=false` the arc fit compiles in about half the
time and runs no slower, and a cold `jaxcal calibrate data/ur5e_sweeps` takes
a quarter less CPU, to the same digits (`benchmarks/compile.py`; the figures
are in docs/performance.md).

On a machine of a few cores, XLA's split of each program's LLVM module into
32 parts compiled on its thread pool (`--xla_cpu_parallel_codegen_split_count`)
costs more than it returns: jaxcal already compiles its stage programs side by
side, and the split copies the module for each part. With one part a cold
`calibrate` and the test suite's compiles take less CPU and less wall time on
2 cores (docs/performance.md); a machine with more than `FEW_CORES` cores keeps
XLA's split.

XLA aborts the whole process on a flag it does not know, so a flag is
only added when the installed jaxlib carries it (its name is in the shared
library), and only when

- no JAX backend is running yet (XLA reads `XLA_FLAGS` once, when it
  starts),
- `XLA_FLAGS` does not already name it (the user's choice wins), and
- `JAXCAL_XLA_DEFAULTS=0` is not set (the opt-out).
"""

import importlib.util
import mmap
import os
import sys
from pathlib import Path

#: The flags and their values; see the module docstring.
FUSION_EMITTERS_OFF = "--xla_cpu_use_fusion_emitters=false"
ONE_CODEGEN_PART = "--xla_cpu_parallel_codegen_split_count=1"
#: Up to this many usable cores, `ONE_CODEGEN_PART` is added.
FEW_CORES = 4


def _jaxlib_knows(flag_names: list[str]) -> set[str]:
    """Those of `flag_names` that a shared library of the installed jaxlib contains
    (XLA's flags are registered by name in its binary)."""
    spec = importlib.util.find_spec("jaxlib")  # not imported: its extension takes a tenth of a second
    if spec is None or spec.origin is None:
        return set()
    missing, found = set(flag_names), set()
    for path in Path(spec.origin).parent.glob("*.so"):
        try:
            if path.stat().st_size < 1 << 20:  # the thin Python-extension stubs
                continue
            with open(path, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as m:
                found |= {name for name in missing if m.find(name.encode()) >= 0}
        except (OSError, ValueError):
            continue
        missing -= found
        if not missing:
            break
    return found


def _cores() -> int:
    """The cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not Linux
        return os.cpu_count() or 1


def defaults() -> list[str]:
    """jaxcal's XLA flags for this machine (before the checks of `configure_xla`)."""
    return [FUSION_EMITTERS_OFF] + ([ONE_CODEGEN_PART] if _cores() <= FEW_CORES else [])


def configure_xla() -> list[str]:
    """Add jaxcal's XLA defaults to `XLA_FLAGS` where it is safe to; returns
    the flags added."""
    if os.environ.get("JAXCAL_XLA_DEFAULTS", "").strip() == "0":
        return []
    if "jax" in sys.modules:  # else no backend can be running, and JAX is not imported for the check
        from jax._src import xla_bridge

        if xla_bridge.backends_are_initialized():
            return []
    flags = os.environ.get("XLA_FLAGS", "")
    wanted = {flag.split("=")[0].lstrip("-"): flag for flag in defaults()}
    wanted = {name: flag for name, flag in wanted.items() if name not in flags}
    known = _jaxlib_knows(list(wanted)) if wanted else set()
    added = [flag for name, flag in wanted.items() if name in known]
    if added:
        os.environ["XLA_FLAGS"] = " ".join([flags, *added]).strip()
    return added
