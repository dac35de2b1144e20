"""The texture codec: DCT-II amplitudes, quantize / threshold-cut, entropy stage, .vtx streams.

The names below load on first use (PEP 562), so that hostd.codec.formats, the stream formats'
table, can be read without numpy (the command-line parser does)."""

import importlib

_LAZY = {"Stream": "hostd.codec.stream", "decode": "hostd.codec.stream",
         "encode_coefficients": "hostd.codec.stream", "encode_profile": "hostd.codec.stream",
         "Geometry": "hostd.codec.transform", "analyze": "hostd.codec.transform",
         "synthesize": "hostd.codec.transform"}

__all__ = sorted(_LAZY)


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'hostd.codec' has no attribute {name!r}")
