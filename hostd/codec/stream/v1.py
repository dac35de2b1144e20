"""The .vtx stream, version 1: fixed 80-byte header, float64 geometry, deflate payloads.

The byte layout is specified in docs/stream-format.md; this module is its reference
implementation. Decoding validates every size before it allocates, checks the CRC and the
version, refuses non-finite numbers, and raises StreamError with a one-line message for
any malformed input.
"""

from __future__ import annotations

import math
import struct
import zlib

import numpy as np

from hostd.codec import transform
from hostd.codec.methods import MAX_LEVELS, apply_cut, finite_coeffs, quantize, threshold_cut
from hostd.codec.stream.common import NO_LIMITS, Limits, Stream, zigzag_varint
from hostd.errors import CodecError, StreamError
from hostd.perception import indices
from hostd.perception import thresholds as th

MAGIC = b"VTX"
VERSION = 1
HEADER = struct.Struct("<3sBBBBBIIddd8sdddII")
HEADER_SIZE = HEADER.size  # 80
CRC_SIZE = 4
METHODS = {1: "quant", 2: "cut"}
METHOD_IDS = {v: k for k, v in METHODS.items()}
CODERS = {0: "none", 1: "deflate"}
CODER_IDS = {v: k for k, v in CODERS.items()}
FLAG_CURVE_EMBEDDED = 0x01
VALUE_BITS = (0, 8, 16, 32)  # cut survivors: 0 = exact float64, else signed integers on a grid
MAX_STREAM_BYTES = HEADER_SIZE + 2 + 16 * th.MAX_POINTS + 16 + 9 * (1 << 22) + CRC_SIZE

assert HEADER_SIZE == 80


# ---------------------------------------------------------------- small codings


def _read_zigzag_varint(buf: bytes, pos: int) -> tuple[int, int]:
    u = 0
    for i in range(10):
        if pos + i >= len(buf):
            raise StreamError("payload truncated inside a number")
        b = buf[pos + i]
        u |= (b & 0x7F) << (7 * i)
        if not b & 0x80:
            if u >= 1 << 64:
                raise StreamError("payload number out of range")
            return (u >> 1) ^ -(u & 1), pos + i + 1
    raise StreamError("payload number longer than 10 bytes")


_DEFLATE_STRATEGIES = (
    zlib.Z_DEFAULT_STRATEGY, zlib.Z_FILTERED, zlib.Z_HUFFMAN_ONLY, zlib.Z_RLE, zlib.Z_FIXED,
)


def _entropy_encode(raw: bytes, coder: str) -> tuple[int, bytes]:
    if coder == "auto":
        candidates = [_entropy_encode(raw, c) for c in ("none", "deflate")]
        return min(candidates, key=lambda t: (len(t[1]), t[0]))
    if coder == "none":
        return CODER_IDS["none"], raw
    if coder == "deflate":
        # Every strategy yields plain raw deflate; keep the smallest (small payloads often
        # favour Huffman-only or fixed codes over the default LZ77 search).
        outs = []
        for strategy in _DEFLATE_STRATEGIES:
            co = zlib.compressobj(9, zlib.DEFLATED, -15, 9, strategy)
            outs.append(co.compress(raw) + co.flush())
        return CODER_IDS["deflate"], min(outs, key=len)
    raise CodecError(f"unknown entropy coder {coder!r}: use none, deflate or auto")


def _entropy_decode(coder_id: int, data: bytes, bound: int) -> bytes:
    if coder_id == 0:
        if len(data) > bound:
            raise StreamError("payload larger than its header allows")
        return data
    try:
        d = zlib.decompressobj(-15)
        out = d.decompress(data, bound + 1)
    except zlib.error as exc:
        raise StreamError(f"payload does not inflate: {exc}") from None
    if len(out) > bound or d.unconsumed_tail:
        raise StreamError("payload inflates past the size its header allows")
    if not d.eof or d.unused_data:
        raise StreamError("payload's deflate data is truncated or has trailing bytes")
    return out


# ---------------------------------------------------------------- payloads


def _quant_payload(q: np.ndarray) -> bytes:
    qmin = int(q.min())
    span = int(q.max()) - qmin
    width = 1 if span < 1 << 8 else 2 if span < 1 << 16 else 4
    if span >= 1 << 32:
        raise CodecError("quantization indices span more than 32 bits")
    dt = {1: "<u1", 2: "<u2", 4: "<u4"}[width]
    return zigzag_varint(qmin) + bytes([width]) + (q - qmin).astype(dt).tobytes()


def _parse_quant(raw: bytes, n_keep: int) -> np.ndarray:
    qmin, pos = _read_zigzag_varint(raw, 0)
    if not -(1 << 53) < qmin < 1 << 53:  # before any int64 arithmetic (-2**63 defeats np.abs)
        raise StreamError("quantization index out of range")
    if pos >= len(raw):
        raise StreamError("quantization payload truncated")
    width = raw[pos]
    pos += 1
    if width not in (1, 2, 4):
        raise StreamError(f"quantization index width {width} is not 1, 2 or 4")
    if len(raw) - pos != width * n_keep:
        raise StreamError("quantization payload size does not match N'")
    dt = {1: "<u1", 2: "<u2", 4: "<u4"}[width]
    q = np.frombuffer(raw, dtype=dt, offset=pos, count=n_keep).astype(np.int64) + qmin
    if np.any(np.abs(q) >= 1 << 53):
        raise StreamError("quantization index out of range")
    return q


def _cut_payload(values: np.ndarray, keep: np.ndarray, value_bits: int) -> bytes:
    bitmap = np.packbits(keep, bitorder="little").tobytes()
    surv = values[keep]
    if surv.size == 0:
        return bitmap
    if value_bits == 0:
        planes = surv.astype("<f8").view(np.uint8).reshape(surv.size, 8).T
        return bitmap + planes.tobytes()
    top = (1 << (value_bits - 1)) - 1
    step = float(np.max(np.abs(surv))) / top
    ints = np.rint(surv / step).astype({8: "<i1", 16: "<i2", 32: "<i4"}[value_bits])
    return bitmap + struct.pack("<d", step) + ints.tobytes()


def _parse_cut(raw: bytes, n_keep: int, value_bits: int) -> np.ndarray:
    nb = (n_keep + 7) // 8
    if len(raw) < nb:
        raise StreamError("cut payload truncated in its bitmap")
    keep = np.unpackbits(np.frombuffer(raw, dtype=np.uint8, count=nb), bitorder="little")
    if np.any(keep[n_keep:]):
        raise StreamError("cut bitmap has bits set past N'")
    keep = keep[:n_keep].astype(bool)
    count = int(np.count_nonzero(keep))
    rest = raw[nb:]
    out = np.zeros(n_keep, dtype=np.float64)
    if count == 0:
        if rest:
            raise StreamError("cut payload has bytes after an empty bitmap")
        return out
    if value_bits == 0:
        if len(rest) != 8 * count:
            raise StreamError("cut payload size does not match its bitmap")
        vals = np.frombuffer(rest, dtype=np.uint8).reshape(8, count).T.copy().view("<f8")[:, 0]
    else:
        width = value_bits // 8
        if len(rest) != 8 + width * count:
            raise StreamError("cut payload size does not match its bitmap")
        (step,) = struct.unpack_from("<d", rest)
        if not (math.isfinite(step) and step > 0):
            raise StreamError("cut survivor step must be a finite number > 0")
        dt = {1: "<i1", 2: "<i2", 4: "<i4"}[width]
        vals = np.frombuffer(rest, dtype=dt, offset=8, count=count).astype(np.float64) * step
    if not np.all(np.isfinite(vals)):
        raise StreamError("cut payload holds NaN or Inf coefficients")
    out[keep] = vals
    return out


def _payload_bound(method_id: int, n_keep: int) -> int:
    if method_id == 1:
        return 10 + 1 + 4 * n_keep
    return (n_keep + 7) // 8 + 8 + 8 * n_keep


# ---------------------------------------------------------------- encode


def _want_embed(curve: th.ThresholdCurve, embed_curve: bool | None) -> bool:
    if embed_curve is not None:
        return embed_curve
    return curve.id_bytes not in th.shipped_curves()


def _assemble(
    *,
    method: str,
    geometry: transform.Geometry,
    n_keep: int,
    curve: th.ThresholdCurve,
    ref_coeffs: np.ndarray,
    param: float,
    levels: int,
    value_bits: int,
    raw_payload: bytes,
    coder: str,
    embed_curve: bool | None,
) -> bytes:
    b_k = curve(geometry.frequencies_hz(n_keep))
    P, A = indices.weighted_sums(ref_coeffs, b_k)
    coder_id, payload = _entropy_encode(raw_payload, coder)
    embed = _want_embed(curve, embed_curve)
    head = HEADER.pack(
        MAGIC,
        VERSION,
        METHOD_IDS[method],
        coder_id,
        FLAG_CURVE_EMBEDDED if embed else 0,
        value_bits,
        geometry.n,
        n_keep,
        geometry.length_mm,
        geometry.speed_mm_s,
        geometry.fmax_hz,
        curve.id_bytes,
        float(P),
        float(A),
        param,
        levels,
        len(payload),
    )
    body = head + (curve.to_bytes() if embed else b"") + payload
    return body + struct.pack("<I", zlib.crc32(body))


def sniff(data: bytes) -> bool:
    """Whether these bytes claim to be a version-1 stream (its magic)."""
    return data[:3] == MAGIC


def coding_geometry(geometry: transform.Geometry) -> transform.Geometry:
    """The geometry as this format codes it (v1 stores the float geometry as it is)."""
    return geometry


def encode_coefficients(
    coeffs_um: np.ndarray,
    geometry: transform.Geometry,
    curve: th.ThresholdCurve,
    *,
    method: str,
    levels: int | None = None,
    b0_db: float | None = None,
    value_bits: int = 0,
    coder: str = "auto",
    embed_curve: bool | None = None,
) -> bytes:
    """Compress the uncompressed amplitudes C_1..C_N' into a .vtx stream."""
    c = np.asarray(coeffs_um, dtype=np.float64)
    n_keep = geometry.n_keep
    if c.shape != (n_keep,):
        raise CodecError(f"expected {n_keep} coefficients for this geometry, got {c.shape}")
    finite_coeffs(c)
    common = dict(
        geometry=geometry, n_keep=n_keep, curve=curve, ref_coeffs=c, coder=coder,
        embed_curve=embed_curve,
    )
    if method == "quant":
        if levels is None:
            raise CodecError("--method quant needs --levels L")
        qz = quantize(c, levels)
        return _assemble(
            method="quant", param=qz.step_um, levels=qz.levels, value_bits=0,
            raw_payload=_quant_payload(qz.q), **common,
        )
    if method == "cut":
        if b0_db is None:
            raise CodecError("--method cut needs --b0-db DB")
        if value_bits not in VALUE_BITS:
            raise CodecError(f"survivor bits must be one of {VALUE_BITS} (0 = exact float64)")
        keep = threshold_cut(c, curve(geometry.frequencies_hz(n_keep)), b0_db)
        return _assemble(
            method="cut", param=float(b0_db), levels=0, value_bits=value_bits,
            raw_payload=_cut_payload(c, keep, value_bits), **common,
        )
    raise CodecError(f"unknown method {method!r}: use quant or cut")


def encode_profile(
    y_um: np.ndarray, geometry: transform.Geometry, curve: th.ThresholdCurve, **kw
) -> bytes:
    """Analyze a profile of geometry.n heights (µm) and compress it."""
    y = np.asarray(y_um, dtype=np.float64)
    if y.size != geometry.n:
        raise CodecError(f"profile has {y.size} samples, geometry says {geometry.n}")
    return encode_coefficients(transform.analyze(y, geometry.n_keep), geometry, curve, **kw)


def expected_coefficients(
    coeffs_um: np.ndarray,
    geometry: transform.Geometry,
    curve: th.ThresholdCurve,
    *,
    method: str,
    levels: int | None = None,
    b0_db: float | None = None,
) -> np.ndarray:
    """C'_k straight from eq. 5-7 (no stream): what an exact decoder must return."""
    c = np.asarray(coeffs_um, dtype=np.float64)
    if method == "quant":
        return quantize(c, levels).values()  # type: ignore[arg-type]
    keep = threshold_cut(c, curve(geometry.frequencies_hz(c.size)), b0_db)  # type: ignore[arg-type]
    return apply_cut(c, keep)


# ---------------------------------------------------------------- decode


def _finite_pos(name: str, v: float) -> None:
    if not (math.isfinite(v) and v > 0):
        raise StreamError(f"header field {name} must be a finite number > 0, got {v!r}")


def decode(data: bytes, limits: Limits = NO_LIMITS) -> Stream:
    """Parse and validate a version-1 stream; every malformed input raises StreamError."""
    data = bytes(data)
    size = len(data)
    if size > MAX_STREAM_BYTES:
        raise StreamError(f"stream of {size} bytes exceeds the {MAX_STREAM_BYTES}-byte limit")
    if size < 3 or data[:3] != MAGIC:
        raise StreamError("not a .vtx stream (bad magic): was this file made by 'hostd encode'?")
    if size < HEADER_SIZE + CRC_SIZE:
        raise StreamError(f"stream truncated: {size} bytes, the header alone needs {HEADER_SIZE + 4}")
    (
        _magic, version, method_id, coder_id, flags, value_bits, n, n_keep, length_mm,
        speed_mm_s, fmax_hz, tid, ref_P, ref_A, param, levels, payload_len,
    ) = HEADER.unpack_from(data)
    if version != VERSION:
        raise StreamError(
            f"stream version {version} is not supported (this hostd reads version {VERSION}): "
            "re-encode it or upgrade hostd"
        )
    curve_len = 0
    if flags & ~FLAG_CURVE_EMBEDDED:
        raise StreamError(f"unknown header flags 0x{flags:02x}")
    if flags & FLAG_CURVE_EMBEDDED:
        if size < HEADER_SIZE + 2:
            raise StreamError("stream truncated in its threshold table")
        (count,) = struct.unpack_from("<H", data, HEADER_SIZE)
        if not 1 <= count <= th.MAX_POINTS:
            raise StreamError(f"embedded threshold table has {count} points")
        curve_len = 2 + 16 * count
    expected = HEADER_SIZE + curve_len + payload_len + CRC_SIZE
    if size != expected:
        what = "truncated" if size < expected else "has trailing bytes"
        raise StreamError(f"stream {what}: header promises {expected} bytes, got {size}")
    (crc,) = struct.unpack_from("<I", data, size - CRC_SIZE)
    if zlib.crc32(data[: size - CRC_SIZE]) != crc:
        raise StreamError("stream CRC mismatch: the file is corrupt; fetch or re-encode it")
    # The CRC matched: the remaining checks catch encoders that wrote nonsense.
    if method_id not in METHODS:
        raise StreamError(f"unknown method id {method_id}")
    if coder_id not in CODERS:
        raise StreamError(f"unknown entropy coder id {coder_id}")
    if not 2 <= n <= transform.MAX_SAMPLES:
        raise StreamError(f"N = {n} is outside 2..{transform.MAX_SAMPLES}")
    if not 1 <= n_keep < n:
        raise StreamError(f"N' = {n_keep} must be in 1..N-1 (N = {n})")
    limits.check_size(n, n_keep)  # before the payload is inflated to N' values
    _finite_pos("length_mm", length_mm)
    _finite_pos("speed_mm_s", speed_mm_s)
    _finite_pos("fmax_hz", fmax_hz)
    for name, v in (("ref_P", ref_P), ("ref_A", ref_A)):
        if not (math.isfinite(v) and v >= 0):
            raise StreamError(f"header field {name} must be finite and >= 0, got {v!r}")
    if not math.isfinite(param):
        raise StreamError("header method parameter is not finite")
    method = METHODS[method_id]
    if method == "quant":
        if not 2 <= levels <= MAX_LEVELS:
            raise StreamError(f"quantization levels {levels} outside 2..{MAX_LEVELS}")
        if not param > 0:
            raise StreamError("quantization step must be > 0")
        if value_bits != 0:
            raise StreamError("quantization streams must have value_bits 0")
    else:
        if levels != 0:
            raise StreamError("cut streams must have levels 0")
        if value_bits not in VALUE_BITS:
            raise StreamError(f"survivor bits {value_bits} not one of {VALUE_BITS}")
    curve = None
    if curve_len:
        try:
            curve = th.from_bytes(data[HEADER_SIZE : HEADER_SIZE + curve_len])
        except Exception as exc:  # ThresholdError from a table the CRC vouched for
            raise StreamError(f"embedded threshold table invalid: {exc}") from None
        if curve.id_bytes != tid:
            raise StreamError("embedded threshold table does not match the header's curve id")
    bound = _payload_bound(method_id, n_keep)
    start = HEADER_SIZE + curve_len
    raw = _entropy_decode(coder_id, data[start : start + payload_len], bound)
    if method == "quant":
        coeffs = _parse_quant(raw, n_keep).astype(np.float64) * param
    else:
        coeffs = _parse_cut(raw, n_keep, value_bits)
    if not np.all(np.isfinite(coeffs)):
        raise StreamError("decoded coefficients are not finite")
    return Stream(
        method=method,
        coder=CODERS[coder_id],
        n=n,
        n_keep=n_keep,
        length_mm=length_mm,
        speed_mm_s=speed_mm_s,
        fmax_hz=fmax_hz,
        threshold_id=tid,
        ref_P=ref_P,
        ref_A=ref_A,
        levels=levels if method == "quant" else None,
        step_um=param if method == "quant" else None,
        b0_db=param if method == "cut" else None,
        value_bits=value_bits if method == "cut" else None,
        curve=curve,
        coefficients=coeffs,
        nbytes=size,
        payload_bytes=payload_len,
    )
