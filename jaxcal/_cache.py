"""Compilation: JAX's persistent cache, on for every jaxcal user, and the
XLA options of the programs that run once per calibration.

The solvers take a minute to compile on a small CPU and a second to run, so
importing jaxcal keeps compiled programs in `$XDG_CACHE_HOME/jaxcal/xla`
(default `~/.cache/jaxcal/xla`): a second run on data of the same shapes
(and, with jaxcal's size buckets, of similar shapes) starts at once, from the
command line and the Python API alike.

- A cache directory the user configured (`JAX_COMPILATION_CACHE_DIR`, or
  `jax.config.update("jax_compilation_cache_dir", ...)` before importing
  jaxcal) is left alone.
- `JAXCAL_NO_CACHE=1` in the environment turns it off (nothing is written).

`quick_jit` compiles with XLA's optimisation passes off (what
`JAX_DISABLE_MOST_OPTIMIZATIONS` does, per program): a calibration runs each
stage program once or a few times, so the passes cost more than they save.
"""

import os
from pathlib import Path

import jax

#: `jax.jit`'s `compiler_options` for `quick_jit`: LLVM at -O0 and without its
#: expensive passes. On `data/ur5e_sweeps` (`benchmarks/compile.py`, 2 cores)
#: XLA's compile time fell from 56 to 30 s and the cold `calibrate` from 81 to
#: 56 s, while the warm run went from 1.75 to 1.95 s and the result moved by
#: round-off (EE error equal to 5e-12 relative). The Monte Carlo trial and the
#: hand-eye solver, which run many times, keep XLA's defaults.
QUICK_COMPILE = {"xla_backend_optimization_level": 0, "xla_llvm_disable_expensive_passes": True}


def quick_jit(fun, **kwargs):
    """`jax.jit(fun, **kwargs)` compiled with `QUICK_COMPILE`: for programs that run
    a few times per process, where compile time dominates run time. Top-level
    programs only: JAX refuses `compiler_options` on a jit called inside a trace."""
    return jax.jit(fun, compiler_options=QUICK_COMPILE, **kwargs)


def enable_compilation_cache() -> None:
    """Point JAX's persistent cache at jaxcal's directory, unless the user chose
    one or set `JAXCAL_NO_CACHE`."""
    if os.environ.get("JAXCAL_NO_CACHE", "").strip() not in ("", "0"):
        return
    if os.environ.get("JAX_COMPILATION_CACHE_DIR") or jax.config.jax_compilation_cache_dir:
        return
    cache = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "jaxcal" / "xla"
    jax.config.update("jax_compilation_cache_dir", str(cache))
    # Every program, however quick to compile: a warm run otherwise compiles its ~100
    # small eager operations again in every process.
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
