"""Texture input: instrument profile files and seeded synthetic material-like textures."""

from hostd.texture.load import LoadOptions, Profile, load_profile

__all__ = ["LoadOptions", "Profile", "load_profile"]
