"""The WaveletWave band of MPEG-I Haptics (.hjif), decoded as the reference software decodes it,
so hostd reads the reference Encoder's files without the reference software installed.

A port of the reference software's decoder (MPEGGroup/HapticReferenceSoftware 2de9ff1, BSD:
Spiht/src/ArithDec.cpp, Spiht/src/Spiht_Dec.cpp, FilterBank/src/Wavelet.cpp inv_DWT,
WaveletDecoder/src/WaveletDecoder.cpp transformBand, IOJson.cpp base642bits): each effect is one
block of `block_length` ms at `upper_frequency_limit` samples per second, coded by SPIHT with an
adaptive binary arithmetic coder (7 contexts), then an inverse biorthogonal (9/7) wavelet
transform; tests/test_hjif_rm.py checks it against the reference Synthesizer.

Ported from software under this licence, whose notice a port retains:

Copyright (c) 2010-2022, ISO/IEC. All rights reserved.
Redistribution and use in source and binary forms, with or without modification, are permitted
provided that the following conditions are met: Redistributions of source code must retain the
above copyright notice, this list of conditions and the following disclaimer. Redistributions in
binary form must reproduce the above copyright notice, this list of conditions and the following
disclaimer in the documentation and/or other materials provided with the distribution. Neither the
name of the ISO/IEC nor the names of its contributors may be used to endorse or promote products
derived from this software without specific prior written permission.
THIS SOFTWARE IS PROVIDED BY THE COPYRIGHT HOLDERS AND CONTRIBUTORS "AS IS" AND ANY EXPRESS OR
IMPLIED WARRANTIES, INCLUDING, BUT NOT LIMITED TO, THE IMPLIED WARRANTIES OF MERCHANTABILITY AND
FITNESS FOR A PARTICULAR PURPOSE ARE DISCLAIMED. IN NO EVENT SHALL THE COPYRIGHT HOLDER OR
CONTRIBUTORS BE LIABLE FOR ANY DIRECT, INDIRECT, INCIDENTAL, SPECIAL, EXEMPLARY, OR CONSEQUENTIAL
DAMAGES (INCLUDING, BUT NOT LIMITED TO, PROCUREMENT OF SUBSTITUTE GOODS OR SERVICES; LOSS OF USE,
DATA, OR PROFITS; OR BUSINESS INTERRUPTION) HOWEVER CAUSED AND ON ANY THEORY OF LIABILITY, WHETHER
IN CONTRACT, STRICT LIABILITY, OR TORT (INCLUDING NEGLIGENCE OR OTHERWISE) ARISING IN ANY WAY OUT
OF THE USE OF THIS SOFTWARE, EVEN IF ADVISED OF THE POSSIBILITY OF SUCH DAMAGE.
"""

from __future__ import annotations

import math

import numpy as np

from hostd.errors import ProfileError

RANGE_MAX, HALF, FIRST_QTR, THIRD_QTR = 1024, 512, 256, 768
CONTEXTS = 7
RESET_HALF, RESET_TOTAL = 8, 16
WAVMAX_LENGTH, FRACTION_BITS_0, FRACTION_BITS_1 = 8, 7, 3
MAXALLOCBITS_SIZE = 4
MIN_BLOCK = 16
MAX_BLOCK = 1 << 16  # samples of one block (a hostile block_length would ask for more)
MAX_DECODED = 4_000_000  # samples of one band (8 min at 8 kHz): bounds the decoder's work

LP = (0.852698679009404, 0.377402855612654, -0.110624404418423, -0.023849465019380, 0.037828455506995)
HP = (-0.788485616405665, 0.418092273222212, 0.040689417609559, -0.064538882628938)
# the reconstruction filters of FilterBank/include/Wavelet.h
LPR = np.array([HP[3], -HP[2], HP[1], -HP[0], HP[1], -HP[2], HP[3]])
HPR = np.array([-LP[4], LP[3], -LP[2], LP[1], -LP[0], LP[1], -LP[2], LP[3], -LP[4]])
_B64 = {c: i for i, c in enumerate("ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+")}


def stream_bits(text: str) -> list[int]:
    """The bits of a `wavelet_stream`: 6 per character, most significant first (the RM maps any
    character outside A-Z a-z 0-9 + to 63, as '/'); trailing zeros are as good as none."""
    out: list[int] = []
    for ch in text:
        v = _B64.get(ch, 63)
        out += [(v >> s) & 1 for s in range(5, -1, -1)]
    while out and out[-1] == 0:
        out.pop()
    out += [0] * (-len(out) % 8)
    return out


class _ArithDec:
    def __init__(self, bits: list[int]) -> None:
        self.bits, self.i = bits, 0
        self.leading = 0
        shift = 9
        for _ in range(10):
            if self.i < len(bits):
                self.leading += bits[self.i] << shift
                self.i += 1
                shift -= 1
        self.lower, self.upper, self.diff = 0, RANGE_MAX, RANGE_MAX
        self.count = [RESET_HALF] * CONTEXTS
        self.total = [RESET_TOTAL] * CONTEXTS

    def _next(self) -> int:
        if self.i < len(self.bits):
            self.i += 1
            return self.bits[self.i - 1]
        return 0

    def bit(self, ctx: int) -> int:
        p = math.floor(self.count[ctx] / self.total[ctx] * RANGE_MAX + 0.5)  # C's round (p >= 0)
        compare = int(self.diff * p) // RANGE_MAX
        if compare == 0:
            compare = 1
        elif compare == self.diff:
            compare = self.diff - 1
        s = 0
        if self.leading - self.lower < compare:
            self.upper = self.lower + compare
        else:
            s = 1
            self.lower += compare
        while True:
            if self.upper <= HALF:
                self.lower <<= 1
                self.upper <<= 1
                self.leading = (self.leading << 1) + self._next()
            elif self.lower >= HALF:
                self.lower = (self.lower - HALF) << 1
                self.upper = (self.upper - HALF) << 1
                self.leading = ((self.leading - HALF) << 1) + self._next()
            elif self.lower >= FIRST_QTR and self.upper <= THIRD_QTR:
                self.lower = (self.lower - FIRST_QTR) << 1
                self.upper = (self.upper - FIRST_QTR) << 1
                self.leading = ((self.leading - FIRST_QTR) << 1) + self._next()
            else:
                break
        self.diff = self.upper - self.lower
        if s == 0:
            self.count[ctx] += 1
        self.total[ctx] += 1
        return s

    def number(self, width: int, ctx: int) -> int:
        return sum(self.bit(ctx) << i for i in range(width))


def spiht_decode(bits: list[int], length: int) -> tuple[np.ndarray, float]:
    """(the block's integer wavelet coefficients, their scale) from one effect's bits."""
    dec = _ArithDec(bits)
    n = n_bits = dec.number(MAXALLOCBITS_SIZE, 0)
    mode = dec.bit(0)
    t = dec.number(WAVMAX_LENGTH - 1, 0)
    wavmax = t * 2.0**-FRACTION_BITS_0 if mode == 0 else t * 2.0**-FRACTION_BITS_1 + 1
    out = [0] * length
    bandsize = 8  # 2 << (log2(length) - level), level = log2(length) - 2
    lip = list(range(bandsize))
    lis = [[i, 0] for i in range(bandsize // 2, bandsize)]
    lsp: list[int] = []
    while n >= 0:
        compare = 1 << n
        lsp_count = len(lsp)
        keep = []
        for i in lip:
            if dec.bit(2):
                out[i] = compare if dec.bit(1) else -compare
                lsp.append(i)
            else:
                keep.append(i)
        lip = keep
        k = 0
        while k < len(lis):  # entries appended during the pass are visited in the same pass
            y, kind = lis[k]
            if kind == 0:
                if dec.bit(3):
                    for idx in (2 * y, 2 * y + 1):
                        if dec.bit(4):
                            lsp.append(idx)
                            out[idx] = compare if dec.bit(1) else -compare
                        else:
                            lip.append(idx)
                    if 4 * y + 3 < length:
                        lis.append([y, 1])
                    del lis[k]
                    continue
            elif dec.bit(5):
                lis.append([2 * y, 0])
                lis.append([2 * y + 1, 0])
                del lis[k]
                continue
            k += 1
        for i in lsp[:lsp_count]:
            if dec.bit(6):
                out[i] += compare if out[i] > 0 else -compare if out[i] < 0 else 0
        n -= 1
    return np.array(out, dtype=np.float64), wavmax / 2.0**n_bits


def _symconv(x: np.ndarray, h: np.ndarray, add_offset: int | None) -> np.ndarray:
    lext = h.size // 2
    ext = np.concatenate([x[1 : lext + 1][::-1], x, x[-lext - 1 : -1][::-1]])
    conv = np.convolve(ext, h)
    if add_offset is None:
        return conv[2 * lext : 2 * lext + x.size]
    return conv[add_offset : add_offset + x.size]


def inverse_dwt(coeffs: np.ndarray, levels: int) -> np.ndarray:
    out = coeffs.astype(np.float64).copy()
    for i in range(levels - 1, -1, -1):
        n = coeffs.size >> i
        lo = np.zeros(n)
        hi = np.zeros(n)
        lo[0::2] = out[: n // 2]
        hi[1::2] = out[n // 2 : n]
        y = _symconv(hi, HPR, None)
        y += _symconv(lo, LPR, LPR.size - 1)
        out[:n] = y
    return out


def decode_band(band: dict, timescale: int, where: str, path) -> list[tuple[int, np.ndarray]]:
    """[(effect position in ticks, samples at upper_frequency_limit per second)] of a WaveletWave
    band (its effects are consecutive blocks)."""
    for key in ("upper_frequency_limit", "block_length"):
        v = band.get(key)
        if not (isinstance(v, int) and not isinstance(v, bool) and 0 < v <= 10**6):
            got = "missing" if v is None else f"{str(v)[:40]!r} is not an integer in 1..1000000"
            raise ProfileError(f"{path}: {where}.{key}: {got} (a WaveletWave band needs it; the reference "
                               "software skips such a band)")
    ufl, bl_ms = band["upper_frequency_limit"], band["block_length"]
    bl = int(bl_ms * 0.001 * ufl)
    # SPIHT's first pass reaches coefficient 15 (the children of 4..7): a block has at least 16
    if not MIN_BLOCK <= bl <= MAX_BLOCK or bl & (bl - 1):
        raise ProfileError(f"{path}: {where}.block_length: {bl_ms} ms at {ufl} Hz = {bl} samples a block: "
                           f"not a power of two in {MIN_BLOCK}..{MAX_BLOCK}")
    levels = int(math.log2(bl / 4))
    out = []
    effects = band.get("effects")
    if not isinstance(effects, list):
        raise ProfileError(f"{path}: {where}.effects: must be an array")
    if len(effects) * bl > MAX_DECODED:
        raise ProfileError(f"{path}: {where}.effects: {len(effects)} blocks of {bl} samples, more than the "
                           f"{MAX_DECODED} samples hostd decodes from one band")
    for b, e in enumerate(effects):
        s = e.get("wavelet_stream") if isinstance(e, dict) else None
        if not isinstance(s, str) or len(s) > 8 * MAX_BLOCK:
            raise ProfileError(f"{path}: {where}.effects[{b}].wavelet_stream: missing, not a string or "
                               "too long")
        q, scale = spiht_decode(stream_bits(s), bl)
        out.append((int(b * bl * timescale / ufl), inverse_dwt(q * scale, levels)))
    return out


def render_band(band: dict, timescale: int, rate: int, count: int, where: str, path) -> np.ndarray:
    """The band's samples at `rate` as the reference Synthesizer takes them: for output sample t,
    position p = timescale t / rate ticks, sample floor((p - effect position) ufl / timescale) of
    every effect at or before p (0 past its block)."""
    blocks = decode_band(band, timescale, where, path)  # checks the band's fields first
    ufl = band["upper_frequency_limit"]
    y = np.zeros(count)
    pos = timescale * (np.arange(count, dtype=np.float64) / float(rate))
    for start, samples in blocks:
        idx = np.floor((pos - start) * float(ufl) / float(timescale))
        ok = (pos >= start) & (idx < samples.size)
        y[ok] += samples[idx[ok].astype(np.int64)]
    return y
