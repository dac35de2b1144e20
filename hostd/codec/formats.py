"""The stream formats, declared once: each .vtx version's name, module, methods and knobs.

The CLI's --format choices, the API's checks, rate control's knob grid, the corpus codecs
(hostd-v1, hostd-v2) and the format-neutral encode/decode of hostd.codec.stream all read this
table, so a stream format v3 is its module under hostd/codec/stream/ plus one entry here. It
imports no numpy (the command-line parser reads it); the module is imported when it is used.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass


@dataclass(frozen=True)
class Format:
    name: str                      # "v2": what --format and the corpus codec hostd-v2 say
    module: str                    # its encoder and decoder (encode_profile, encode_coefficients,
                                   #   decode, coding_geometry, sniff)
    methods: tuple[str, ...]       # the coding methods it carries
    value_bits: int                # the default width of cut survivors (0 = exact float64)
    cut_steps_per_db: int          # the b0 grid rate control searches
    options: tuple[str, ...] = ()  # encoder options only this format takes (CLI spelling)
    summary: str = ""

    def load(self):
        return importlib.import_module(self.module)


FORMATS: dict[str, Format] = {f.name: f for f in (  # newest first
    Format("v2", "hostd.codec.stream.v2", ("shaped", "quant", "cut"), value_bits=16, cut_steps_per_db=4,
           summary="compact header, range-coded indices, threshold-shaped steps"),
    Format("v1", "hostd.codec.stream.v1", ("quant", "cut"), value_bits=0, cut_steps_per_db=2,
           options=("--coder",), summary="the original 84-byte header, deflate"),
)}
DEFAULT = "v2"


def get(name: str) -> Format:
    """The format called `name`; CodecError naming the formats when there is none."""
    try:
        return FORMATS[name]
    except KeyError:
        from hostd.errors import CodecError

        raise CodecError(f"unknown stream format {name!r}: use --format "
                         + " or ".join(FORMATS)) from None
