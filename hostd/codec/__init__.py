"""The texture codec: DCT-II amplitudes, quantize / threshold-cut, entropy stage, .vtx streams."""

from hostd.codec.stream import Stream, decode, encode_coefficients, encode_profile
from hostd.codec.transform import Geometry, analyze, synthesize

__all__ = ["Geometry", "Stream", "analyze", "decode", "encode_coefficients", "encode_profile",
           "synthesize"]
