"""hostd: vibrotactile texture codec, perceptual quality index, renderer and device daemon."""

__version__ = "0.1.0"
