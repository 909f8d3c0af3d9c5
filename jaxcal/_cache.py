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

import importlib.abc
import importlib.util
import os
import sys
from pathlib import Path

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
    import jax

    return jax.jit(fun, compiler_options=QUICK_COMPILE, **kwargs)


def _cache_settings() -> dict:
    """JAX's settings for jaxcal's persistent cache: none where the user chose a cache
    directory (`JAX_COMPILATION_CACHE_DIR` or JAX's config) or set `JAXCAL_NO_CACHE`."""
    if os.environ.get("JAXCAL_NO_CACHE", "").strip() not in ("", "0"):
        return {}
    jax = sys.modules.get("jax")
    if os.environ.get("JAX_COMPILATION_CACHE_DIR") or (jax and jax.config.jax_compilation_cache_dir):
        return {}
    cache = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "jaxcal" / "xla"
    # Every program, however quick to compile: a warm run otherwise compiles its ~100
    # small eager operations again in every process.
    return {"jax_compilation_cache_dir": str(cache), "jax_persistent_cache_min_compile_time_secs": 0.0}


class _WhenJaxImports(importlib.abc.MetaPathFinder):
    """Applies `settings` to JAX's config the moment `jax` is first imported (its module run,
    before anything can use it), then leaves `sys.meta_path`: so that `import jaxcal` need not
    import JAX, which takes a second, and leaves the environment, which child processes would
    inherit, as it found it."""

    def __init__(self):
        self.settings: dict = {}

    def find_spec(self, name, path=None, target=None):
        if name != "jax":
            return None
        sys.meta_path.remove(self)
        spec = importlib.util.find_spec(name)  # by the finders after this one
        if spec is not None and spec.loader is not None:
            run, settings = spec.loader.exec_module, self.settings

            def exec_module(module):
                run(module)
                for key, value in settings.items():
                    module.config.update(key, value)

            spec.loader.exec_module = exec_module
        return spec


_PENDING = _WhenJaxImports()


def _apply(settings: dict) -> None:
    """`settings` in JAX's config: now if JAX is imported, else when it is (`_WhenJaxImports`)."""
    jax = sys.modules.get("jax")
    if jax is not None:
        for name, value in settings.items():
            jax.config.update(name, value)
        return
    _PENDING.settings.update(settings)
    if _PENDING not in sys.meta_path:
        sys.meta_path.insert(0, _PENDING)


def enable_compilation_cache() -> None:
    """Point JAX's persistent cache at jaxcal's directory, unless the user chose
    one or set `JAXCAL_NO_CACHE`."""
    _apply(_cache_settings())


def configure_jax() -> None:
    """float64 for the calibration maths and jaxcal's persistent cache, for the whole
    process: in JAX's config if it is imported, else for when it is."""
    _apply({"jax_enable_x64": True} | _cache_settings())
