"""Adaptive binary range coder and the context model for integer coefficient indices (stream v2).

Integer arithmetic only; the exact algorithm is specified in docs/stream-format.md ("v2
entropy coder") so that an independent decoder can be written from the text. The binary
coder is the LZMA range coder (32-bit range, 11-bit probabilities) with two changes that
save bytes on short streams: the always-zero first byte is not written, and the final
value is chosen inside the last interval so that trailing zero bytes can be dropped (the
decoder reads zeros past the end of the payload).

Context model for q_1..q_N' (signed integers):
  n_sig   = index of the last nonzero q (0 when all are zero), Exp-Golomb with adaptive
            prefix bits (contexts EG_SIG) and bypass suffix bits;
  k = 1..n_sig:
    zero    adaptive bit "q_k != 0", context c = min(2,|q_{k-1}|) + min(2,|q_{k-2}|)
            (0..4
            q_0 = q_-1 = 0)
            not coded for k = n_sig (known nonzero);
    sign    bypass bit (1 = negative);
    gt1     adaptive bit "|q_k| > 1", context c;
    rest    |q_k| - 2 when gt1, Exp-Golomb with adaptive prefix bits (contexts EG_MAG)
            and bypass suffix bits.
"""

from __future__ import annotations

import numpy as np

from hostd.compiled import load as load_compiled
from hostd.errors import StreamError

PROB_BITS = 11
PROB_ONE = 1 << PROB_BITS          # 2048
PROB_INIT = PROB_ONE >> 1          # 1024: p(bit = 0) = 1/2
ADAPT_SHIFT = 4
TOP = 1 << 24
MASK32 = 0xFFFFFFFF
N_CTX = 5
EG_MAX_PREFIX = 40                 # Exp-Golomb prefixes longer than this are malformed
MAX_ABS_INDEX = (1 << 40) - 1      # |q| bound (the encoder refuses larger indices)
C_REVISION = 1                     # _rangecoder.c's REVISION this module is written for

MSG_TOO_LONG = "entropy-coded number too long"
MSG_RANGE = "entropy-coded index out of range"


def msg_n_sig(n_sig: int, n_keep: int) -> str:
    return f"entropy-coded payload claims {n_sig} significant components, N' = {n_keep}"


def _code(decisions: list[tuple[list[int] | None, int, int]]) -> bytes:
    """The binary range encoder (LZMA's) over a list of decisions (probs, index, bit), probs
    None for a bypass bit; state in local variables. At the end it picks, inside the final
    interval [low, low + range), the value with the most trailing zero bits, flushes, drops
    the always-zero first byte and strips trailing zero bytes (the decoder reads zeros)."""
    low = 0
    rng = MASK32
    cache = 0
    cache_size = 1
    out = bytearray()

    def shift_low() -> None:
        nonlocal low, cache, cache_size
        if low < 0xFF000000 or low > MASK32:
            carry = low >> 32
            temp = cache
            while True:
                out.append((temp + carry) & 0xFF)
                temp = 0xFF
                cache_size -= 1
                if not cache_size:
                    break
            cache = (low >> 24) & 0xFF
        cache_size += 1
        low = (low & 0x00FFFFFF) << 8

    for probs, i, b in decisions:
        if probs is None:
            rng >>= 1
            if b:
                low += rng
        else:
            p = probs[i]
            bound = (rng >> 11) * p  # PROB_BITS
            if b:
                low += bound
                rng -= bound
                probs[i] = p - (p >> 4)  # ADAPT_SHIFT
            else:
                rng = bound
                probs[i] = p + ((2048 - p) >> 4)
        while rng < 0x1000000:  # TOP
            rng <<= 8
            shift_low()
    hi = low + rng - 1
    for shift in (32, 24, 16, 8, 0):
        v = ((low + (1 << shift) - 1) >> shift) << shift
        if v <= hi:
            low = v
            break
    for _ in range(5):
        shift_low()
    if out[0] != 0:  # pragma: no cover - the LZMA coder's first byte is always 0
        raise AssertionError("range coder invariant broken: first byte not 0")
    return bytes(out[1:]).rstrip(b"\x00")


def _eg(ops: list, probs: list[int], v: int) -> None:
    """Exp-Golomb order 0 of v >= 0: n = bit_length(v+1)-1 prefix ones (adaptive, one
    context per position, capped at the last), a zero, then n suffix bits (bypass, MSB first)."""
    v1 = v + 1
    n = v1.bit_length() - 1
    last = len(probs) - 1
    for i in range(n):
        ops.append((probs, i if i < last else last, 1))
    ops.append((probs, n if n < last else last, 0))
    for i in range(n - 1, -1, -1):
        ops.append((None, 0, (v1 >> i) & 1))


def encode_indices_py(q: np.ndarray) -> bytes:
    """Range-code signed integer indices q_1..q_N' with the context model above (reference)."""
    vals = [int(v) for v in np.asarray(q).tolist()]
    if any(abs(v) > MAX_ABS_INDEX for v in vals):
        raise ValueError("index magnitude beyond 2^40")
    p_zero = [PROB_INIT] * N_CTX
    p_gt1 = [PROB_INIT] * N_CTX
    p_sig = [PROB_INIT] * 16
    p_mag = [PROB_INIT] * 16
    n_sig = 0
    for i, v in enumerate(vals):
        if v:
            n_sig = i + 1
    ops: list = []
    add = ops.append
    _eg(ops, p_sig, n_sig)
    a1 = a2 = 0
    last = n_sig - 1
    for i in range(n_sig):
        v = vals[i]
        a = -v if v < 0 else v
        ctx = (a1 if a1 < 2 else 2) + (a2 if a2 < 2 else 2)
        if i != last:
            add((p_zero, ctx, 1 if a else 0))
        if a:
            add((None, 0, 1 if v < 0 else 0))
            add((p_gt1, ctx, 1 if a > 1 else 0))
            if a > 1:
                _eg(ops, p_mag, a - 2)
        a2, a1 = a1, a
    return _code(ops)


class _Decoder:
    """The binary range decoder of docs/stream-format.md ("Entropy coder (exact)"): the mirror
    of _code, one decision at a time (reads zeros past the end of the payload)."""

    __slots__ = ("_next", "code", "rng")

    def __init__(self, data: bytes) -> None:
        self.code = int.from_bytes((data[:4] + b"\0\0\0\0")[:4], "big")
        self.rng = MASK32
        self._next = iter(data[4:]).__next__

    def _normalize(self) -> None:
        while self.rng < TOP:
            self.rng <<= 8
            try:
                b = self._next()
            except StopIteration:
                b = 0
            self.code = ((self.code << 8) | b) & MASK32

    def bit(self, probs: list[int], i: int) -> int:
        """An adaptive bit with probability probs[i] (of a 0, in 1/2048), updated by shift 4."""
        p = probs[i]
        bound = (self.rng >> PROB_BITS) * p
        if self.code < bound:
            self.rng = bound
            probs[i] = p + ((PROB_ONE - p) >> ADAPT_SHIFT)
            b = 0
        else:
            self.code -= bound
            self.rng -= bound
            probs[i] = p - (p >> ADAPT_SHIFT)
            b = 1
        self._normalize()
        return b

    def bypass(self) -> int:
        self.rng >>= 1
        b = 1 if self.code >= self.rng else 0
        if b:
            self.code -= self.rng
        self._normalize()
        return b

    def exp_golomb(self, probs: list[int]) -> int:
        """The inverse of _eg."""
        last = len(probs) - 1
        n = 0
        while self.bit(probs, n if n < last else last):
            n += 1
            if n > EG_MAX_PREFIX:
                raise StreamError(MSG_TOO_LONG)
        v1 = 1
        for _ in range(n):
            v1 = (v1 << 1) | self.bypass()
        return v1 - 1


def decode_indices_py(data: bytes, n_keep: int) -> np.ndarray:
    """Inverse of encode_indices for N' = n_keep; malformed data raises StreamError (the
    reference; the compiled coder is the fast path)."""
    d = _Decoder(data)
    p_zero = [PROB_INIT] * N_CTX
    p_gt1 = [PROB_INIT] * N_CTX
    p_sig = [PROB_INIT] * 16
    p_mag = [PROB_INIT] * 16
    n_sig = d.exp_golomb(p_sig)
    if n_sig > n_keep:
        raise StreamError(msg_n_sig(n_sig, n_keep))
    out = [0] * n_keep
    a1 = a2 = 0
    last = n_sig - 1
    for k in range(n_sig):
        ctx = (a1 if a1 < 2 else 2) + (a2 if a2 < 2 else 2)
        if k != last and not d.bit(p_zero, ctx):
            a2, a1 = a1, 0
            continue
        neg = d.bypass()
        a = 2 + d.exp_golomb(p_mag) if d.bit(p_gt1, ctx) else 1
        if a > MAX_ABS_INDEX:
            raise StreamError(MSG_RANGE)
        out[k] = -a if neg else a
        a2, a1 = a1, a
    return np.array(out, dtype=np.int64)


# ---------------------------------------------------------------- the compiled coder


_C = load_compiled("hostd.codec._rangecoder", C_REVISION)


def encode_indices_c(q: np.ndarray) -> bytes:
    """encode_indices_py's bytes, by the compiled coder (1-D integer arrays; anything else
    goes to the reference, which gives the same result or error for it)."""
    a = np.asarray(q)
    if a.ndim != 1 or a.dtype.kind not in "iu":
        return encode_indices_py(q)
    if a.size and max(-int(a.min()), int(a.max())) > MAX_ABS_INDEX:
        raise ValueError("index magnitude beyond 2^40")
    return _C.encode(np.ascontiguousarray(a, dtype=np.int64))


def decode_indices_c(data: bytes, n_keep: int) -> np.ndarray:
    """decode_indices_py's indices or StreamError, by the compiled coder."""
    n_keep = int(n_keep)
    out = np.zeros(max(n_keep, 0), dtype=np.int64)
    status, n_sig = _C.decode(data, out)
    if status == _C.ERR_TOO_LONG:
        raise StreamError(MSG_TOO_LONG)
    if status == _C.ERR_N_SIG or n_sig > n_keep:  # (n_keep < 0: decoded against N' = 0)
        raise StreamError(msg_n_sig(n_sig, n_keep))
    if status:
        raise StreamError(MSG_RANGE)
    return out


if _C is not None:
    IMPLEMENTATION = "c"
    encode_indices = encode_indices_c
    decode_indices = decode_indices_c
else:
    IMPLEMENTATION = "python"
    encode_indices = encode_indices_py
    decode_indices = decode_indices_py
