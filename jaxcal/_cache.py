"""JAX's persistent compilation cache, on for every jaxcal user.

The solvers take a minute to compile on a small CPU and a second to run, so
importing jaxcal keeps compiled programs in `$XDG_CACHE_HOME/jaxcal/xla`
(default `~/.cache/jaxcal/xla`): a second run on data of the same shapes
(and, with jaxcal's size buckets, of similar shapes) starts at once, from the
command line and the Python API alike.

- A cache directory the user configured (`JAX_COMPILATION_CACHE_DIR`, or
  `jax.config.update("jax_compilation_cache_dir", ...)` before importing
  jaxcal) is left alone.
- `JAXCAL_NO_CACHE=1` in the environment turns it off (nothing is written).
"""

import os
from pathlib import Path

import jax


def enable_compilation_cache() -> None:
    """Point JAX's persistent cache at jaxcal's directory, unless the user chose
    one or set `JAXCAL_NO_CACHE`."""
    if os.environ.get("JAXCAL_NO_CACHE", "").strip() not in ("", "0"):
        return
    if os.environ.get("JAX_COMPILATION_CACHE_DIR") or jax.config.jax_compilation_cache_dir:
        return
    cache = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "jaxcal" / "xla"
    jax.config.update("jax_compilation_cache_dir", str(cache))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
