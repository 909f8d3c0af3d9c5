"""Pick MuJoCo's headless OpenGL backend before `mujoco` is imported.

MuJoCo reads `MUJOCO_GL` once, when `mujoco` is first imported. jaxcal uses
EGL (Mesa's software rasteriser on CPU-only machines, the GPU driver where
there is one) and falls back to OSMesa. A user's own `MUJOCO_GL` is kept.
"""

import ctypes.util
import os
import sys

PACKAGES = "libegl1 libgl1-mesa-dri (EGL, preferred) or libosmesa6 (OSMesa)"


def _available(lib: str) -> bool:
    return ctypes.util.find_library(lib) is not None


def select_backend() -> str:
    """Set `MUJOCO_GL` (if unset) to the first headless backend whose library is present."""
    chosen = os.environ.get("MUJOCO_GL")
    if chosen:
        return chosen
    if "mujoco" in sys.modules:  # too late to choose; MuJoCo picked its default
        return ""
    for backend, lib in (("egl", "EGL"), ("osmesa", "OSMesa")):
        if _available(lib):
            os.environ["MUJOCO_GL"] = backend
            return backend
    return ""


def no_backend_error(cause: BaseException | None = None) -> RuntimeError:
    backend = os.environ.get("MUJOCO_GL", "<unset>")
    detail = f" ({type(cause).__name__}: {cause})" if cause is not None else ""
    return RuntimeError(
        f"MuJoCo could not create an OpenGL context with MUJOCO_GL={backend}{detail}. "
        f"Rendering needs a headless GL library: install the Debian packages {PACKAGES} "
        "(`sudo apt-get install libegl1 libgl1-mesa-dri`), or set MUJOCO_GL to a backend that works here."
    )
