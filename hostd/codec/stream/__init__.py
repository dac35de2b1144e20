"""The .vtx stream: a compressed DCT texture with its geometry and quality reference.

Two versions, specified in docs/stream-format.md: version 1 (`v1`, fixed header, deflate) and
version 2 (`v2`, compact header, range-coded indices). `decode` reads either; `encode_*` here
write version 1 (`v2.encode_*` write version 2). What both share is in `common`.
"""

from __future__ import annotations

from hostd.codec.stream import v1, v2
from hostd.codec.stream.common import NO_LIMITS, Limits, Stream, curve_for, varint, zigzag_varint
from hostd.codec.stream.v1 import (
    CRC_SIZE,
    HEADER,
    HEADER_SIZE,
    MAGIC,
    MAX_STREAM_BYTES,
    VALUE_BITS,
    VERSION,
    encode_coefficients,
    encode_profile,
    expected_coefficients,
)

__all__ = ["CRC_SIZE", "HEADER", "HEADER_SIZE", "MAGIC", "MAX_STREAM_BYTES", "NO_LIMITS", "VALUE_BITS",
           "VERSION", "Limits", "Stream", "curve_for", "decode", "encode_coefficients", "encode_profile",
           "expected_coefficients", "is_v2", "v1", "v2", "varint", "zigzag_varint"]


def is_v2(data: bytes) -> bool:
    """Version 2 starts "V" then (layout << 4 | flags), layout 2 or 3; version 1 starts "VTX"."""
    return (data[:1] == b"V" and len(data) >= 2
            and data[1] >> 4 in (v2.LAYOUT_FIRST, v2.LAYOUT_COMPACT_GEOMETRY))


def decode(data: bytes, limits: Limits = NO_LIMITS) -> Stream:
    """Parse and validate a .vtx stream of either version; every malformed input raises
    StreamError. limits: the caller's caps, N and N' checked from the header before allocating."""
    data = bytes(data)
    s = v2.decode(data, limits) if is_v2(data) else v1.decode(data, limits)
    limits.check_values(s.coefficients)
    return s
