"""hostd's own streams (v1, v2) as codecs of the corpus protocol (hostd.corpus.codecs).

A setting is {"method": "shaped", "g_db": ..} (v2), {"method": "quant", "levels": ..},
{"method": "cut", "b0_db": ..} or {"target_iobj": .., ["method": ..]} (rate control, which also
verifies SPQI >= 0.9 on its own bytes: hostd.codec.ratecontrol). One rate-quality curve per
method ("target" for rate control). The reconstruction is the stream's band-limited series
(Stream.reconstruct()), exactly what the display plays.
"""

from __future__ import annotations

from typing import Any

import numpy as np

import hostd
from hostd.codec import transform

SHAPED_G_DB = (-18.0, -12.0, -6.0, 0.0, 6.0, 12.0, 18.0)
QUANT_LEVELS = (4, 6, 8, 12, 16, 24, 32, 48, 64, 96, 128)
CUT_B0_DB = (-18.0, -12.0, -6.0, 0.0, 6.0, 12.0)
KNOB = {"shaped": "g_db", "quant": "levels", "cut": "b0_db"}


def default_settings(fmt: str) -> list[dict]:
    grid = {"shaped": SHAPED_G_DB, "quant": QUANT_LEVELS, "cut": CUT_B0_DB}
    from hostd.codec import formats

    return [{"method": m, KNOB[m]: v} for m in formats.get(fmt).methods for v in grid[m]]


class HostdStream:
    """hostd's stream format `fmt` ("v1" or "v2") through the corpus protocol."""

    def __init__(self, fmt: str) -> None:
        self.fmt = fmt
        self.name = f"hostd-{fmt}"
        self.version = f"{hostd.__version__}/stream-{fmt}"
        self.settings = default_settings(fmt)

    def curve(self, setting: dict) -> str:
        return "target" if "target_iobj" in setting else str(setting.get("method", ""))

    def encode(self, heights_um: np.ndarray, spacing_um: float, *, speed_mm_s: float = 50.0,
               fmax_hz: float = 400.0, method: str | None = None, target_iobj: float | None = None,
               g_db: float | None = None, levels: int | None = None, b0_db: float | None = None,
               value_bits: int | None = None, spqi_min: float | None = 0.9, **unknown: Any) -> bytes:
        from hostd.codec import formats, ratecontrol, stream
        from hostd.errors import CodecError
        from hostd.perception import thresholds as th

        if unknown:
            raise CodecError(f"{self.name} has no setting {', '.join(sorted(unknown))}: use method, "
                             "g_db, levels, b0_db, value_bits or target_iobj")
        y = np.asarray(heights_um, dtype=np.float64)
        length_mm = y.size * spacing_um / 1000.0
        curve = th.default_curve()
        geom = transform.Geometry(y.size, length_mm, speed_mm_s, fmax_hz)
        if target_iobj is not None:
            res = ratecontrol.search(y, geom, curve, float(target_iobj), method=method, fmt=self.fmt,
                                     spqi_min=spqi_min)
            return res.best.data
        if method is None:
            raise CodecError(f"{self.name}: a setting needs method (shaped, quant, cut) or target_iobj")
        fm = formats.get(self.fmt)
        if method not in fm.methods:
            raise CodecError(f"{self.name} has no method {method} (it has {', '.join(fm.methods)})")
        knobs = {"g_db": g_db} if "shaped" in fm.methods else {}
        return stream.encode_profile(y, geom, curve, format=self.fmt, method=method, levels=levels,
                                     b0_db=b0_db, **knobs,
                                     value_bits=fm.value_bits if value_bits is None else value_bits)

    def decode(self, data: bytes, n: int, spacing_um: float, **_: Any) -> np.ndarray:
        from hostd.codec import stream

        s = stream.decode(data)
        return s.reconstruct()
