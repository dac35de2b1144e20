"""The .vtx stream: a compressed DCT texture with its geometry and quality reference.

The formats are declared in hostd.codec.formats (v2, the default: compact header, range-coded
indices; v1: the original fixed header, deflate), specified in docs/stream-format.md, each a
module here. `encode_profile` and `encode_coefficients` write the format asked for (default
v2, as the CLI and the API); `decode` reads any, told apart by their magic. What the formats
share is in `common`.
"""

from __future__ import annotations

from hostd.codec import formats
from hostd.codec.stream import v1, v2
from hostd.codec.stream.common import NO_LIMITS, Limits, Stream, curve_for, varint, zigzag_varint
from hostd.codec.stream.v1 import (  # the v1 layout's constants, kept at their old import path
    CRC_SIZE,
    HEADER,
    HEADER_SIZE,
    MAGIC,
    MAX_STREAM_BYTES,
    VALUE_BITS,
    VERSION,
    expected_coefficients,
)

__all__ = ["CRC_SIZE", "HEADER", "HEADER_SIZE", "MAGIC", "MAX_STREAM_BYTES", "NO_LIMITS", "VALUE_BITS",
           "VERSION", "Limits", "Stream", "curve_for", "decode", "encode_coefficients", "encode_profile",
           "expected_coefficients", "format_of", "is_v2", "v1", "v2", "varint", "zigzag_varint"]


def encode_profile(y_um, geometry, curve, *, format: str = formats.DEFAULT, **kw) -> bytes:
    """Analyze a profile of geometry.n heights (µm) and compress it in stream `format`."""
    return formats.get(format).load().encode_profile(y_um, geometry, curve, **kw)


def encode_coefficients(coeffs_um, geometry, curve, *, format: str = formats.DEFAULT, **kw) -> bytes:
    """Compress C_1..C_N' (N' of the format's coding geometry of `geometry`) in stream `format`."""
    return formats.get(format).load().encode_coefficients(coeffs_um, geometry, curve, **kw)


def format_of(data: bytes) -> str | None:
    """The name of the format these bytes claim to be (by its magic), or None."""
    for f in formats.FORMATS.values():
        if f.load().sniff(data):
            return f.name
    return None


def is_v2(data: bytes) -> bool:
    return format_of(data) == "v2"


def decode(data: bytes, limits: Limits = NO_LIMITS) -> Stream:
    """Parse and validate a .vtx stream of any format; every malformed input raises
    StreamError. limits: the caller's caps, N and N' checked from the header before allocating."""
    data = bytes(data)
    name = format_of(data) or "v1"  # v1's decoder says what a stream must start with
    s = formats.get(name).load().decode(data, limits)
    limits.check_values(s.coefficients)
    return s
