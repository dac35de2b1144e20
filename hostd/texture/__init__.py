"""Texture input: instrument profile files and seeded synthetic material-like textures.

The names below load on first use (PEP 562), so that a command's parser can import a module of
this package (the export command's) without loading numpy."""

__all__ = ["LoadOptions", "Profile", "load_profile"]


def __getattr__(name: str):
    if name in __all__:
        from hostd.texture import load

        return getattr(load, name)
    raise AttributeError(f"module 'hostd.texture' has no attribute {name!r}")
