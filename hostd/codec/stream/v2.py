"""The .vtx stream, version 2: compact header, integer geometry, range-coded indices.

Specified in docs/stream-format.md ("Version 2"); this module is its reference implementation.
All three methods (shaped, quant, cut) code their integer indices with the adaptive range
coder of hostd/codec/rangecoder.py. Decoding validates every field before it allocates and
raises StreamError with a one-line message for any malformed input.
"""

from __future__ import annotations

import binascii
import functools
import math
import struct
import zlib
from dataclasses import dataclass

import numpy as np

from hostd.codec import rangecoder, transform
from hostd.codec.methods import (
    G_UNIT_DB,
    MAX_LEVELS,
    check_g_db,
    finite_coeffs,
    quantize,
    shaped_quantize,
    shaped_values,
    threshold_cut,
)
from hostd.codec.stream.common import NO_LIMITS, Limits, Stream
from hostd.codec.stream.common import varint as _varint
from hostd.codec.stream.common import zigzag_varint as _zigzag
from hostd.errors import CodecError, StreamError
from hostd.perception import guard, indices
from hostd.perception import thresholds as th

VERSION = 2
MAGIC0 = 0x56  # "V"; byte 1 is (layout << 4) | flags (a v1 stream has "T" = 0x54 there)
# Byte 1's high nibble: 3 when an explicit geometry is stored as 4N + 2 bits (v_ref and f_max
# only where they differ from the paper's), 2 otherwise. Streams of the first v2 layout (nibble
# 2 with an explicit geometry of 4 varints, written until 2026-11-22) still decode.
LAYOUT_FIRST = 2
LAYOUT_COMPACT_GEOMETRY = 3
METHODS = {0: "shaped", 1: "quant", 2: "cut"}
METHOD_IDS = {v: k for k, v in METHODS.items()}
FLAG_CURVE_EMBEDDED = 0x04
FLAG_EXPLICIT_GEOMETRY = 0x08
SHORT_ID_BYTES = 2
SHIPPED_MAX_AGE_S = 1.0  # decode: the shipped curves are re-checked on disk at most once a second
CRC16_LIMIT = 4096  # streams shorter than this end in a CRC-16, longer ones in a CRC-32
CUT_VALUE_BITS = (8, 16, 32)
B0_UNIT_DB = 0.25
REF_SIG_BITS = 17  # reference sums: 17 significant bits (relative error <= 2^-17)
MAX_STREAM_BYTES = 64 + 2 + 16 * th.MAX_POINTS + 12 * (1 << 22) + 4


@dataclass(frozen=True)
class IntGeometry:
    """Geometry in integers with explicit units, as v2 stores it."""

    n: int
    spacing_pm: int
    speed_um_s: int
    fmax_mhz: int

    @property
    def length_mm(self) -> float:
        return self.n * self.spacing_pm / 1e9

    @property
    def speed_mm_s(self) -> float:
        return self.speed_um_s / 1000.0

    @property
    def fmax_hz(self) -> float:
        return self.fmax_mhz / 1000.0

    @property
    def n_keep(self) -> int:
        """N' = floor(2 L fmax / v), exactly, in integers: pm * mHz / (µm/s) = 1e-9."""
        return (2 * self.n * self.spacing_pm * self.fmax_mhz) // (self.speed_um_s * 10**9)

    def geometry(self) -> transform.Geometry:
        return transform.Geometry(self.n, self.length_mm, self.speed_mm_s, self.fmax_hz)

    def frequencies_hz(self) -> np.ndarray:
        return transform.frequencies_hz(np.arange(1, self.n_keep + 1), self.length_mm,
                                        self.speed_mm_s)


def thresholds_at(curve: th.ThresholdCurve, ig: IntGeometry) -> np.ndarray:
    """b(f_k) for k = 1..N' of this geometry (read-only). Memoized per (curve, geometry) for
    N' <= 2^16 (16 entries, <= 8 MiB): a daemon decodes many streams of the same geometry
    and shipped curve (curves are immutable; an embedded one is a new object per stream)."""
    if ig.n_keep > 1 << 16:
        return curve(ig.frequencies_hz())
    return _thresholds_memo(curve, ig)


@functools.lru_cache(maxsize=16)
def _thresholds_memo(curve: th.ThresholdCurve, ig: IntGeometry) -> np.ndarray:
    b = curve(ig.frequencies_hz())
    b.setflags(write=False)
    return b


PAPER_GEOMETRY = IntGeometry(n=20000, spacing_pm=500_000, speed_um_s=50_000, fmax_mhz=400_000)


def sniff(data: bytes) -> bool:
    """Whether these bytes claim to be a version-2 stream: "V" then (layout << 4 | flags), layout
    2 or 3 (version 1 starts "VTX")."""
    return len(data) >= 2 and data[0] == MAGIC0 and data[1] >> 4 in (LAYOUT_FIRST, LAYOUT_COMPACT_GEOMETRY)


def int_geometry(geometry: transform.Geometry) -> IntGeometry:
    """The v2 geometry of a float one: spacing in pm, speed in µm/s, fmax in mHz (rounded)."""
    geometry.n_keep  # noqa: B018 - refuses N' outside 1..N-1 with the option to change
    g = IntGeometry(geometry.n, round(geometry.spacing_um * 1e6), round(geometry.speed_mm_s * 1e3),
                    round(geometry.fmax_hz * 1e3))
    if g.spacing_pm < 1 or g.speed_um_s < 1 or g.fmax_mhz < 1:
        raise CodecError("stream v2 stores spacing in pm, speed in µm/s and fmax in mHz: this "
                         "geometry rounds to zero; use --format v1")
    if not 1 <= g.n_keep < g.n:
        raise CodecError(f"this geometry gives N' = {g.n_keep}, outside 1..N-1: change --fmax-hz or "
                         "--ref-speed-mm-s")
    return g


coding_geometry = int_geometry  # the geometry as this format codes it


# ---------------------------------------------------------------- small codings


class _Reader:
    def __init__(self, data: bytes, end: int) -> None:
        self.data = data
        self.pos = 0
        self.end = end

    def take(self, n: int, what: str) -> bytes:
        if self.pos + n > self.end:
            raise StreamError(f"stream truncated in its {what}")
        b = self.data[self.pos : self.pos + n]
        self.pos += n
        return b

    def varint(self, what: str, limit: int = 1 << 63) -> int:
        u = 0
        for i in range(10):
            (b,) = self.take(1, what)
            u |= (b & 0x7F) << (7 * i)
            if not b & 0x80:
                if u > limit:
                    raise StreamError(f"header field {what} = {u} exceeds {limit}")
                return u
        raise StreamError(f"header field {what} is longer than 10 bytes")

    def zigzag(self, what: str, limit: int = 1 << 62) -> int:
        u = self.varint(what, 2 * limit)
        return (u >> 1) ^ -(u & 1)

    def f64(self, what: str) -> float:
        (v,) = struct.unpack("<d", self.take(8, what))
        return v


def pack_ref(x: float) -> bytes:
    """A reference sum (finite, >= 0) in 3 bytes: exponent byte E, 16-bit fraction.

    E = 0: the value 0. 1 <= E <= 254: (1 + F/2^16) 2^(E - 128), F rounded half-to-even from
    the exact value (17 significant bits). E = 255: a raw little-endian float64 follows (for
    sums outside 2^-127..2^126).
    """
    if not (math.isfinite(x) and x >= 0):
        raise CodecError(f"reference sum must be finite and >= 0, got {x}")
    if x == 0:
        return b"\x00"
    m, e = math.frexp(x)  # x = m 2^e, 0.5 <= m < 1, exact
    s = round(math.ldexp(m, REF_SIG_BITS))  # 2^16 <= s <= 2^17, exact scaling, half-to-even
    if s == 1 << REF_SIG_BITS:
        s >>= 1
        e += 1
    ee = e - 1 + 128  # x ~ (s / 2^16) 2^(e - 1)
    if not 1 <= ee <= 254:
        return b"\xff" + struct.pack("<d", x)
    return bytes([ee]) + struct.pack("<H", s - (1 << 16))


def unpack_ref(r: _Reader, what: str) -> float:
    (ee,) = r.take(1, what)
    if ee == 0:
        return 0.0
    if ee == 255:
        v = r.f64(what)
        if not (math.isfinite(v) and v >= 0):
            raise StreamError(f"header field {what} must be finite and >= 0, got {v!r}")
        return v
    (f,) = struct.unpack("<H", r.take(2, what))
    return math.ldexp((1 << 16) + f, ee - 128 - 16)


def rounded_ref(x: float) -> float:
    """The value a receiver reads back for reference sum x."""
    b = pack_ref(x)
    return unpack_ref(_Reader(b, len(b)), "ref")


def _crc(body: bytes) -> bytes:
    if len(body) + 2 < CRC16_LIMIT:
        return struct.pack("<H", binascii.crc_hqx(body, 0xFFFF))
    return struct.pack("<I", zlib.crc32(body))


# ---------------------------------------------------------------- encode


def _short_id(curve: th.ThresholdCurve) -> bytes:
    return curve.id_bytes[:SHORT_ID_BYTES]


def quarter_units(db: float, name: str, unit: float) -> int:
    u = round(db / unit)
    if not math.isfinite(db) or u * unit != db:
        raise CodecError(f"stream v2 stores {name} in {unit} dB steps, got {db}: round it or "
                         "use --format v1")
    return u


def encode_coefficients(
    coeffs_um: np.ndarray,
    geometry: transform.Geometry | IntGeometry,
    curve: th.ThresholdCurve,
    *,
    method: str,
    g_db: float | None = None,
    levels: int | None = None,
    b0_db: float | None = None,
    value_bits: int = 16,
    embed_curve: bool | None = None,
) -> bytes:
    """Compress C_1..C_N' (for the v2 geometry of `geometry`) into a version-2 stream."""
    ig = geometry if isinstance(geometry, IntGeometry) else int_geometry(geometry)
    n_keep = ig.n_keep
    c = np.asarray(coeffs_um, dtype=np.float64)
    if c.shape != (n_keep,):
        raise CodecError(f"expected {n_keep} coefficients for this geometry, got {c.shape}")
    finite_coeffs(c)
    b_k = thresholds_at(curve, ig)
    P, A = indices.weighted_sums(c, b_k)
    if method not in METHOD_IDS:
        raise CodecError(f"unknown method {method!r}: use shaped, quant or cut")
    if method == "shaped":
        if g_db is None:
            raise CodecError("--method shaped needs --g-db DB (step relative to the threshold)")
        g_db = check_g_db(float(g_db))
        params = _zigzag(round(g_db / G_UNIT_DB))
        q = shaped_quantize(c, b_k, g_db)
        decoded = shaped_values(q, b_k, g_db)
    elif method == "quant":
        if levels is None:
            raise CodecError("--method quant needs --levels L")
        qz = quantize(c, levels)
        if np.any(np.abs(qz.q) > rangecoder.MAX_ABS_INDEX):
            raise CodecError("quantization indices beyond 2^40: use --format v1")
        params = _varint(qz.levels) + struct.pack("<d", qz.step_um)
        q = qz.q
        decoded = q.astype(np.float64) * qz.step_um
    else:
        if b0_db is None:
            raise CodecError("--method cut needs --b0-db DB")
        if value_bits not in CUT_VALUE_BITS:
            raise CodecError("stream v2 stores cut survivors on an 8, 16 or 32-bit grid "
                             "(--value-bits 8|16|32); exact float64 survivors need --format v1")
        b0u = quarter_units(float(b0_db), "b0", B0_UNIT_DB)
        keep = threshold_cut(c, b_k, float(b0_db))
        surv = c[keep]
        top = (1 << (value_bits - 1)) - 1
        step = float(np.max(np.abs(surv))) / top if surv.size else 1.0
        if not (step > 0 and math.isfinite(step)):
            step = 1.0
        q = np.where(keep, np.rint(np.divide(c, step)), 0.0).astype(np.int64)
        params = _zigzag(b0u) + bytes([value_bits]) + struct.pack("<d", step)
        decoded = q.astype(np.float64) * step
    embed = embed_curve if embed_curve is not None else curve.id_bytes not in th.shipped_curves()
    flags = METHOD_IDS[method] | (FLAG_CURVE_EMBEDDED if embed else 0)
    geo = b""
    layout = LAYOUT_FIRST  # the paper's geometry: no geometry bytes, the same in both layouts
    if ig != PAPER_GEOMETRY:
        layout = LAYOUT_COMPACT_GEOMETRY
        flags |= FLAG_EXPLICIT_GEOMETRY
        spacing = ig.spacing_pm // 1000 * 2 if ig.spacing_pm % 1000 == 0 else ig.spacing_pm * 2 + 1
        # v_ref and f_max are stored only where they differ from the paper's 50 mm/s and 400 Hz
        own_speed = ig.speed_um_s != PAPER_GEOMETRY.speed_um_s
        own_fmax = ig.fmax_mhz != PAPER_GEOMETRY.fmax_mhz
        geo = _varint(4 * ig.n + 2 * own_speed + own_fmax) + _varint(spacing)
        if own_speed:
            geo += _varint(ig.speed_um_s)
        if own_fmax:
            geo += _varint(ig.fmax_mhz)
    body = bytearray([MAGIC0, layout << 4 | flags]) + geo + _short_id(curve)
    body += pack_ref(float(P)) + pack_ref(float(A)) + b"\x00"  # guard byte, filled in below
    guard_at = len(body) - 1
    body += (params
             + (curve.to_bytes() if embed else b"") + rangecoder.encode_indices(q))
    # The guard byte records the wSNR of what the receiver decodes (the decoder's formulas).
    body[guard_at] = guard.header_code(guard.weighted_snr_db(c, decoded, b_k))
    return bytes(body) + _crc(bytes(body))


def encode_profile(y_um: np.ndarray, geometry: transform.Geometry, curve: th.ThresholdCurve,
                   **kw) -> bytes:
    """Analyze a profile of geometry.n heights (µm) and compress it as a v2 stream."""
    y = np.asarray(y_um, dtype=np.float64)
    if y.size != geometry.n:
        raise CodecError(f"profile has {y.size} samples, geometry says {geometry.n}")
    ig = int_geometry(geometry)
    return encode_coefficients(transform.analyze(y, ig.n_keep), ig, curve, **kw)


# ---------------------------------------------------------------- decode


def decode(data: bytes, limits: Limits = NO_LIMITS) -> Stream:
    """Parse and validate a version-2 stream; every malformed input raises StreamError."""
    data = bytes(data)
    size = len(data)
    if size > MAX_STREAM_BYTES:
        raise StreamError(f"stream of {size} bytes exceeds the {MAX_STREAM_BYTES}-byte limit")
    if size < 2 or data[0] != MAGIC0 or data[1] >> 4 not in (LAYOUT_FIRST, LAYOUT_COMPACT_GEOMETRY):
        raise StreamError("not a version-2 .vtx stream")
    crc_len = 2 if size < CRC16_LIMIT else 4
    if size < 2 + crc_len:
        raise StreamError(f"stream truncated: {size} bytes")
    body = data[: size - crc_len]
    if _crc(body) != data[size - crc_len :] or (crc_len == 4) != (len(body) + 2 >= CRC16_LIMIT):
        raise StreamError("stream CRC mismatch: the file is truncated or corrupt; fetch or re-encode it")
    flags = data[1] & 0x0F
    method_id = flags & 0x03
    if method_id not in METHODS:
        raise StreamError(f"unknown method id {method_id}")
    method = METHODS[method_id]
    r = _Reader(body, len(body))
    r.pos = 2
    if flags & FLAG_EXPLICIT_GEOMETRY:
        if data[1] >> 4 == LAYOUT_COMPACT_GEOMETRY:
            n4 = r.varint("N", 1 << 63)  # 4·N + 2·(v_ref stored) + (f_max stored)
            n, stored = n4 >> 2, n4 & 3
            if n > transform.MAX_SAMPLES:
                raise StreamError(f"header field N = {n} exceeds {transform.MAX_SAMPLES}")
        else:  # the first v2 layout: N, and v_ref and f_max always stored
            n, stored = r.varint("N", transform.MAX_SAMPLES), 3
        sp = r.varint("spacing", 1 << 50)
        spacing_pm = sp >> 1 if sp & 1 else (sp >> 1) * 1000
        # otherwise the paper's reference speed and f_max
        speed = r.varint("speed_um_s", 1 << 40) if stored & 2 else PAPER_GEOMETRY.speed_um_s
        fmax = r.varint("fmax_mhz", 1 << 40) if stored & 1 else PAPER_GEOMETRY.fmax_mhz
        if n < 2 or spacing_pm < 1 or speed < 1 or fmax < 1:
            raise StreamError("header geometry has a zero or too small field (N >= 2, others >= 1)")
        ig = IntGeometry(n, spacing_pm, speed, fmax)
    else:
        ig = PAPER_GEOMETRY
    n_keep = ig.n_keep
    if not 1 <= n_keep < ig.n:
        raise StreamError(f"header geometry gives N' = {n_keep}, outside 1..N-1 (N = {ig.n})")
    limits.check_size(ig.n, n_keep)  # before anything of size N' is decoded or allocated
    short_id = r.take(SHORT_ID_BYTES, "curve id")
    ref_P = unpack_ref(r, "ref_P")
    ref_A = unpack_ref(r, "ref_A")
    (guard_code,) = r.take(1, "guard")
    g_db = levels = step = b0_db = value_bits = None
    if method == "shaped":
        g_db = r.zigzag("g", 1 << 20) * G_UNIT_DB
        try:
            check_g_db(g_db)
        except CodecError as exc:
            raise StreamError(f"header field {exc}") from None
    elif method == "quant":
        levels = r.varint("levels", MAX_LEVELS)
        if levels < 2:
            raise StreamError(f"quantization levels {levels} outside 2..{MAX_LEVELS}")
        step = r.f64("step")
        if not (math.isfinite(step) and step > 0):
            raise StreamError("quantization step must be a finite number > 0")
    else:
        b0_db = r.zigzag("b0", 1 << 20) * B0_UNIT_DB
        (value_bits,) = r.take(1, "value_bits")
        if value_bits not in CUT_VALUE_BITS:
            raise StreamError(f"survivor bits {value_bits} not one of {CUT_VALUE_BITS}")
        step = r.f64("survivor step")
        if not (math.isfinite(step) and step > 0):
            raise StreamError("cut survivor step must be a finite number > 0")
    curve = None
    if flags & FLAG_CURVE_EMBEDDED:
        start = r.pos
        (count,) = struct.unpack("<H", r.take(2, "threshold table"))
        if not 1 <= count <= th.MAX_POINTS:
            raise StreamError(f"embedded threshold table has {count} points")
        r.take(16 * count, "threshold table")
        try:
            curve = th.from_bytes(body[start : r.pos])
        except Exception as exc:  # ThresholdError from a table the CRC vouched for
            raise StreamError(f"embedded threshold table invalid: {exc}") from None
        if curve.id_bytes[:SHORT_ID_BYTES] != short_id:
            raise StreamError("embedded threshold table does not match the header's curve id")
    payload = body[r.pos :]
    q = rangecoder.decode_indices(payload, n_keep)
    shipped = th.shipped_curves(SHIPPED_MAX_AGE_S) if curve is None else {}
    if method == "shaped":
        if curve is None:
            curve = _shipped_by_short_id(short_id, shipped)
        coeffs = shaped_values(q, thresholds_at(curve, ig), g_db)
    elif method == "quant":
        if np.any(np.abs(q) >= 1 << 53):
            raise StreamError("quantization index out of range")
        coeffs = q.astype(np.float64) * step
    else:
        top = (1 << (value_bits - 1)) - 1
        if np.any(np.abs(q) > top):
            raise StreamError(f"cut survivor index beyond {value_bits} bits")
        coeffs = q.astype(np.float64) * step
    if not np.all(np.isfinite(coeffs)):
        raise StreamError("decoded coefficients are not finite")
    tid = curve.id_bytes if curve is not None else _full_id(short_id, shipped)
    return Stream(
        method=method, coder="range", n=ig.n, n_keep=n_keep, length_mm=ig.length_mm,
        speed_mm_s=ig.speed_mm_s, fmax_hz=ig.fmax_hz, threshold_id=tid, ref_P=ref_P, ref_A=ref_A,
        levels=levels, step_um=step if method == "quant" else None, b0_db=b0_db,
        value_bits=value_bits, curve=curve if flags & FLAG_CURVE_EMBEDDED else None,
        coefficients=coeffs, nbytes=size, payload_bytes=len(payload), version=VERSION, g_db=g_db,
        guard_wsnr_db=guard.from_header(guard_code),
    )


def _shipped_by_short_id(short_id: bytes, shipped: dict) -> th.ThresholdCurve:
    found = [c for k, c in shipped.items() if k[:SHORT_ID_BYTES] == short_id]
    if len(found) != 1:  # look again, on disk: the curve may have been installed just now
        found = [c for k, c in th.shipped_curves().items() if k[:SHORT_ID_BYTES] == short_id]
    if len(found) != 1:
        raise StreamError(
            f"threshold curve {short_id.hex()} is not embedded and "
            + ("not shipped" if not found else "ambiguous among the shipped curves")
            + ": the shaped stream cannot be decoded without it; re-encode with the curve embedded"
        )
    return found[0]


def _full_id(short_id: bytes, shipped: dict) -> bytes:
    """The 8-byte id of the shipped curve with this short id, or the short id zero-padded."""
    found = [k for k in shipped if k[:SHORT_ID_BYTES] == short_id]
    if len(found) != 1:  # look again, on disk (as _shipped_by_short_id)
        found = [k for k in th.shipped_curves() if k[:SHORT_ID_BYTES] == short_id]
    return found[0] if len(found) == 1 else short_id + bytes(8 - SHORT_ID_BYTES)
