"""File formats (impure edge: never jitted)."""

from .urdf import load_urdf as load_urdf
from .urdf import save_urdf as save_urdf
