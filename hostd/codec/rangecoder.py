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
            (0..4; q_0 = q_-1 = 0); not coded for k = n_sig (known nonzero);
    sign    bypass bit (1 = negative);
    gt1     adaptive bit "|q_k| > 1", context c;
    rest    |q_k| - 2 when gt1, Exp-Golomb with adaptive prefix bits (contexts EG_MAG)
            and bypass suffix bits.
"""

from __future__ import annotations

import numpy as np

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


class Encoder:
    def __init__(self) -> None:
        self.low = 0
        self.range = MASK32
        self.cache = 0
        self.cache_size = 1
        self.out = bytearray()

    def _shift_low(self) -> None:
        low = self.low
        if low < 0xFF000000 or low > MASK32:
            carry = low >> 32
            temp = self.cache
            while True:
                self.out.append((temp + carry) & 0xFF)
                temp = 0xFF
                self.cache_size -= 1
                if not self.cache_size:
                    break
            self.cache = (low >> 24) & 0xFF
        self.cache_size += 1
        self.low = (low & 0x00FFFFFF) << 8

    def bit(self, probs: list[int], i: int, b: int) -> None:
        p = probs[i]
        bound = (self.range >> PROB_BITS) * p
        if b:
            self.low += bound
            self.range -= bound
            probs[i] = p - (p >> ADAPT_SHIFT)
        else:
            self.range = bound
            probs[i] = p + ((PROB_ONE - p) >> ADAPT_SHIFT)
        while self.range < TOP:
            self.range <<= 8
            self._shift_low()

    def bypass(self, b: int) -> None:
        self.range >>= 1
        if b:
            self.low += self.range
        while self.range < TOP:
            self.range <<= 8
            self._shift_low()

    def finish(self) -> bytes:
        # Any value in [low, low + range) decodes the same; take the one with the most
        # trailing zero bits so that the dropped zero bytes cost nothing.
        hi = self.low + self.range - 1
        for shift in (32, 24, 16, 8, 0):
            v = ((self.low + (1 << shift) - 1) >> shift) << shift
            if v <= hi:
                self.low = v
                break
        for _ in range(5):
            self._shift_low()
        out = bytes(self.out)
        if out[0] != 0:  # pragma: no cover - the LZMA coder's first byte is always 0
            raise AssertionError("range coder invariant broken: first byte not 0")
        return out[1:].rstrip(b"\x00")


class Decoder:
    def __init__(self, data: bytes) -> None:
        self.data = data
        self.pos = 4
        padded = data[:4] + bytes(max(0, 4 - len(data)))
        self.code = int.from_bytes(padded, "big")
        self.range = MASK32

    def _next(self) -> int:
        p = self.pos
        self.pos = p + 1
        return self.data[p] if p < len(self.data) else 0

    def bit(self, probs: list[int], i: int) -> int:
        p = probs[i]
        bound = (self.range >> PROB_BITS) * p
        if self.code < bound:
            self.range = bound
            probs[i] = p + ((PROB_ONE - p) >> ADAPT_SHIFT)
            b = 0
        else:
            self.code -= bound
            self.range -= bound
            probs[i] = p - (p >> ADAPT_SHIFT)
            b = 1
        while self.range < TOP:
            self.range <<= 8
            self.code = ((self.code << 8) | self._next()) & MASK32
        return b

    def bypass(self) -> int:
        self.range >>= 1
        if self.code >= self.range:
            self.code -= self.range
            b = 1
        else:
            b = 0
        while self.range < TOP:
            self.range <<= 8
            self.code = ((self.code << 8) | self._next()) & MASK32
        return b


def _eg_encode(enc: Encoder, probs: list[int], v: int) -> None:
    """Exp-Golomb order 0 of v >= 0: n = bit_length(v+1)-1 prefix ones (adaptive, one
    context per position, capped at the last), a zero, then n suffix bits (bypass, MSB first)."""
    v1 = v + 1
    n = v1.bit_length() - 1
    last = len(probs) - 1
    for i in range(n):
        enc.bit(probs, min(i, last), 1)
    enc.bit(probs, min(n, last), 0)
    for i in range(n - 1, -1, -1):
        enc.bypass((v1 >> i) & 1)


def _eg_decode(dec: Decoder, probs: list[int]) -> int:
    n = 0
    last = len(probs) - 1
    while dec.bit(probs, min(n, last)):
        n += 1
        if n > EG_MAX_PREFIX:
            raise StreamError("entropy-coded number too long")
    v1 = 1
    for _ in range(n):
        v1 = (v1 << 1) | dec.bypass()
    return v1 - 1


def encode_indices(q: np.ndarray) -> bytes:
    """Range-code signed integer indices q_1..q_N' with the context model above."""
    vals = [int(v) for v in np.asarray(q).tolist()]
    if any(abs(v) > MAX_ABS_INDEX for v in vals):
        raise ValueError("index magnitude beyond 2^40")
    enc = Encoder()
    p_zero = [PROB_INIT] * N_CTX
    p_gt1 = [PROB_INIT] * N_CTX
    p_sig = [PROB_INIT] * 16
    p_mag = [PROB_INIT] * 16
    n_sig = 0
    for i, v in enumerate(vals):
        if v:
            n_sig = i + 1
    _eg_encode(enc, p_sig, n_sig)
    a1 = a2 = 0
    for i in range(n_sig):
        v = vals[i]
        a = abs(v)
        ctx = min(2, a1) + min(2, a2)
        if i != n_sig - 1:
            enc.bit(p_zero, ctx, 1 if a else 0)
        if a:
            enc.bypass(1 if v < 0 else 0)
            enc.bit(p_gt1, ctx, 1 if a > 1 else 0)
            if a > 1:
                _eg_encode(enc, p_mag, a - 2)
        a2, a1 = a1, a
    return enc.finish()


def decode_indices(data: bytes, n_keep: int) -> np.ndarray:
    """Inverse of encode_indices for N' = n_keep; malformed data raises StreamError."""
    dec = Decoder(data)
    p_zero = [PROB_INIT] * N_CTX
    p_gt1 = [PROB_INIT] * N_CTX
    p_sig = [PROB_INIT] * 16
    p_mag = [PROB_INIT] * 16
    n_sig = _eg_decode(dec, p_sig)
    if n_sig > n_keep:
        raise StreamError(f"entropy-coded payload claims {n_sig} significant components, N' = {n_keep}")
    out = [0] * n_keep
    a1 = a2 = 0
    for i in range(n_sig):
        ctx = min(2, a1) + min(2, a2)
        nz = 1 if i == n_sig - 1 else dec.bit(p_zero, ctx)
        a = 0
        if nz:
            neg = dec.bypass()
            a = 1
            if dec.bit(p_gt1, ctx):
                a = 2 + _eg_decode(dec, p_mag)
                if a > MAX_ABS_INDEX:
                    raise StreamError("entropy-coded index out of range")
            out[i] = -a if neg else a
        a2, a1 = a1, a
    return np.array(out, dtype=np.int64)
