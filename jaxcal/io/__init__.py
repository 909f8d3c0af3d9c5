"""File formats (impure edge: never jitted)."""


def __getattr__(name: str):
    # `load_urdf`/`save_urdf` on first use: importing `jaxcal.io.<format>` (what every command
    # does for its files) does not import the URDF reader and JAX's model code with it.
    if name in ("load_urdf", "save_urdf"):
        from . import urdf

        return getattr(urdf, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["load_urdf", "save_urdf"]
