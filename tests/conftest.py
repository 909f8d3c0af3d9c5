from pathlib import Path

import jax
import pytest

from jaxcal.sim._gl import select_backend

select_backend()  # before anything imports mujoco: headless EGL (or OSMesa) for the rendering tests

jax.config.update("jax_enable_x64", True)
# Compiled programs are cached on disk, so a second run of the suite (and the
# notebook kernels it starts) skips XLA compilation.
CACHE_DIR = Path(__file__).resolve().parents[1] / ".cache" / "jax"
jax.config.update("jax_compilation_cache_dir", str(CACHE_DIR))
jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)


@pytest.fixture
def key():
    return jax.random.key(0)
