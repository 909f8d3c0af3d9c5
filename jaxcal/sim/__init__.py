"""MuJoCo synthetic arm: scene, motions, encoder and clock logs, datasets on disk.

Impure (MuJoCo, OpenCV, files); never jitted. Importing it selects MuJoCo's
headless GL backend (EGL, else OSMesa) unless `MUJOCO_GL` is already set.
"""

from .scene import (
    CameraSpec as CameraSpec,
)
from .scene import (
    PlateSpec as PlateSpec,
)
from .scene import (
    Scene as Scene,
)
from .scene import (
    build_scene as build_scene,
)
