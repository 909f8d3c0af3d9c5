"""JAX's persistent compilation cache for jaxcal's entry points.

The solvers take a minute to compile on a small CPU and a second to run, so
`jaxcal calibrate`, `jaxcal demo` and `jaxcal.calibrate` keep compiled
programs in `$XDG_CACHE_HOME/jaxcal/xla` (default `~/.cache/jaxcal/xla`):
a second run on data of the same shapes starts at once. A cache directory
the user configured (`JAX_COMPILATION_CACHE_DIR` or
`jax.config.update("jax_compilation_cache_dir", ...)`) is left alone, and
`JAXCAL_NO_CACHE=1` in the environment turns the cache off (nothing is
written to disk).
"""

import os
from pathlib import Path


def enable_compilation_cache() -> None:
    """Point JAX's persistent compilation cache at jaxcal's directory, unless opted out or already set."""
    import jax

    if os.environ.get("JAXCAL_NO_CACHE", "").strip() not in ("", "0"):
        return
    if os.environ.get("JAX_COMPILATION_CACHE_DIR") or jax.config.jax_compilation_cache_dir:
        return
    cache = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "jaxcal" / "xla"
    jax.config.update("jax_compilation_cache_dir", str(cache))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
