"""Rate control: the smallest stream whose Iobj does not exceed a target, with a waveform guard.

`search` (what `hostd encode --target-iobj` uses) bisects each method's knob, which is
monotone in quality: the shaped quantizer's g (0.25 dB steps), the number of levels L of
linear quantization, the cut's b0 (0.25 dB in v2, 0.5 dB in v1). A candidate passes when
its Iobj (scored as a receiver would: against the reference sums in its header) is <= the
target AND it passes the waveform guard (hostd.perception.guard: wSNR >= 25 dB and sSNR >=
27 dB by default), so a stream whose sums match but whose spectrum does not is never
returned. Each probe is encoded and decoded for real. Because Iobj is not strictly
monotone in a knob, the search also probes a few steps past the boundary it found.

`candidates` / `smallest_within` keep the exhaustive v1 search (every L and every b0 of a
grid), used as the reference the bisection is tested against.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import numpy as np

from hostd.codec import methods as qmethods
from hostd.codec import stream as vtx
from hostd.codec import stream2, transform
from hostd.codec.methods import db_to_ratio
from hostd.errors import CodecError
from hostd.perception import guard, indices
from hostd.perception.thresholds import ThresholdCurve

MAX_L = 256
B0_GRID_DB = np.arange(-40.0, 40.0 + 1e-9, 0.5)


@dataclass(frozen=True)
class Candidate:
    method: str
    levels: int | None
    b0_db: float | None
    value_bits: int
    data: bytes
    Ip: float
    Ia: float
    Iobj: float

    @property
    def nbytes(self) -> int:
        return len(self.data)

    def describe(self) -> str:
        par = (f"L={self.levels}" if self.method == "quant"
               else f"b0={self.b0_db:+.1f} dB, survivors {self.value_bits or 'float64'}"
               + ("" if not self.value_bits else "-bit"))
        return f"{self.method} ({par}): {self.nbytes} bytes, Iobj={self.Iobj:.4f}"


def _settings(coeffs: np.ndarray, b_k: np.ndarray) -> Iterator[dict]:
    for levels in range(2, MAX_L + 1):
        yield {"method": "quant", "levels": levels}
    nz = np.abs(coeffs) > 0
    b0s = list(B0_GRID_DB)
    if np.any(nz):  # a shift low enough to keep every nonzero coefficient
        b0s.append(keep_all_b0_db(coeffs[nz], b_k[nz]))
    for vb in vtx.VALUE_BITS:
        for b0 in b0s:
            yield {"method": "cut", "b0_db": float(b0), "value_bits": vb}


def keep_all_b0_db(coeffs: np.ndarray, b_k: np.ndarray) -> float:
    """A whole-dB shift 1 dB below the lowest |C_k| / b_k, settled with exact comparisons.

    The logarithm only gives a first guess; the result is fixed by comparing against
    methods.db_to_ratio, so it is the same on every CPU (libm's log10 is not).
    """
    r = float(np.min(np.abs(coeffs) / b_k))
    d = math.floor(20.0 * math.log10(r))
    while db_to_ratio(d + 1.0) <= r:
        d += 1
    while db_to_ratio(float(d)) > r:
        d -= 1
    return float(d) - 1.0


def candidates(y_um: np.ndarray, geometry: transform.Geometry, curve: ThresholdCurve,
               ab: tuple[float, float] = indices.DEFAULT_AB) -> list[Candidate]:
    c = transform.analyze(y_um, geometry.n_keep)
    b_k = curve(geometry.frequencies_hz())
    P, A = indices.weighted_sums(c, b_k)
    out = []
    for s in _settings(c, b_k):
        data = vtx.encode_coefficients(c, geometry, curve, **s)
        dec = vtx.decode(data)
        Pp, Ap = indices.weighted_sums(dec.coefficients, b_k)
        sc = indices.scores_from_sums(P, A, Pp, Ap, *ab)
        out.append(Candidate(s["method"], s.get("levels"), s.get("b0_db"),
                             s.get("value_bits", 0), data,
                             float(sc.Ip), float(sc.Ia), float(sc.Iobj)))
    return out


def smallest_within(y_um: np.ndarray, geometry: transform.Geometry, curve: ThresholdCurve,
                    target_iobj: float,
                    ab: tuple[float, float] = indices.DEFAULT_AB) -> Candidate:
    """The smallest stream with Iobj <= target (ties: the lower Iobj)."""
    if not (math.isfinite(target_iobj) and target_iobj >= 0):
        raise CodecError(f"--target-iobj must be a finite number >= 0, got {target_iobj}")
    ok = [c for c in candidates(y_um, geometry, curve, ab) if c.Iobj <= target_iobj]
    if not ok:
        raise CodecError(f"no stream reaches Iobj <= {target_iobj}: raise the target")
    return min(ok, key=lambda c: (c.nbytes, c.Iobj))


# ---------------------------------------------------------------- knob search (bisection)

FORMATS = ("v2", "v1")
METHODS_BY_FORMAT = {"v2": ("shaped", "quant", "cut"), "v1": ("quant", "cut")}
LOOKAHEAD = 3  # probes past the found boundary (Iobj is not strictly monotone in a knob)


@dataclass(frozen=True)
class Probe:
    method: str
    setting: dict
    data: bytes
    Iobj: float
    wsnr_db: float
    ssnr_db: float
    guard_ok: bool

    @property
    def nbytes(self) -> int:
        return len(self.data)

    def describe(self) -> str:
        par = ", ".join(f"{k}={v}" for k, v in self.setting.items() if k != "method")
        return (f"{self.method} ({par}): {self.nbytes} bytes, Iobj={self.Iobj:.4f}, "
                f"wSNR={self.wsnr_db:.1f} dB, sSNR={self.ssnr_db:.1f} dB")


@dataclass
class SearchResult:
    best: Probe
    encodes: int
    seconds: float
    notes: list[str] = field(default_factory=list)


@dataclass
class _Knob:
    """An integer knob u in lo..hi; quality falls as u grows (`coarse` is the high end)."""

    method: str
    lo: int
    hi: int
    setting: Callable[[int], dict]


def max_iobj(ab: tuple[float, float]) -> float:
    """The largest Iobj any stream can have: both relative errors at their maximum, 2."""
    return 2.0 * (abs(ab[0]) + abs(ab[1]))


def _knobs(fmt: str, method: str, c: np.ndarray, b_k: np.ndarray) -> list[_Knob]:
    peak = float(np.max(np.abs(c) / b_k)) if c.size else 0.0
    top_db = 20.0 * math.log10(peak) if peak > 0 else 0.0
    if method == "shaped":
        u_hi = min(int(qmethods.G_MAX_DB * 4), math.ceil((top_db + 7.0) * 4))  # all indices 0
        u_lo = max(int(qmethods.G_MIN_DB * 4), u_hi - 4 * 80)
        return [_Knob("shaped", u_lo, u_hi, lambda u: {"method": "shaped", "g_db": u / 4})]
    if method == "quant":
        # u = MAX_L - L: larger u, fewer levels, lower quality
        return [_Knob("quant", 0, MAX_L - 2, lambda u: {"method": "quant", "levels": MAX_L - u})]
    unit = 4 if fmt == "v2" else 2  # steps per dB
    u_hi = math.ceil((top_db + 1.0) * unit)  # everything cut
    u_lo = u_hi - 80 * unit
    bits = (16,) if fmt == "v2" else (0, 16)
    return [_Knob("cut", u_lo, u_hi, lambda u, vb=vb: {"method": "cut", "b0_db": u / unit,
                                                         "value_bits": vb}) for vb in bits]


def search(y_um: np.ndarray, geometry: transform.Geometry, curve: ThresholdCurve,
           target_iobj: float, *, method: str | None = None, fmt: str = "v2",
           guard_db: float | None = guard.DEFAULT_GUARD_DB,
           ssnr_db: float | None = guard.DEFAULT_SSNR_DB,
           ab: tuple[float, float] = indices.DEFAULT_AB) -> SearchResult:
    """The smallest stream with Iobj <= target, wSNR >= guard_db and sSNR >= ssnr_db (None:
    that part of the guard is off)."""
    t0 = time.process_time()
    if not (math.isfinite(target_iobj) and target_iobj >= 0):
        raise CodecError(f"--target-iobj must be a finite number >= 0, got {target_iobj}")
    if fmt not in FORMATS:
        raise CodecError(f"unknown stream format {fmt!r}: use v2 or v1")
    allowed = METHODS_BY_FORMAT[fmt]
    if method is not None and method not in allowed:
        raise CodecError(f"method {method} is not available in stream {fmt}: use one of "
                         f"{', '.join(allowed)}")
    notes = []
    if target_iobj >= max_iobj(ab):
        notes.append(f"--target-iobj {target_iobj:g} is degenerate: no stream can score above "
                     f"{max_iobj(ab):g} (a Ip + b Ia with Ip, Ia <= 2), so only the guard "
                     "limits the choice")
    if fmt == "v2":
        ig = stream2.int_geometry(geometry)
        c = transform.analyze(y_um, ig.n_keep)
        f_k = ig.frequencies_hz()
        b_k = curve(f_k)

        def encode(s: dict) -> bytes:
            return stream2.encode_coefficients(c, ig, curve, **s)
    else:
        c = transform.analyze(y_um, geometry.n_keep)
        f_k = geometry.frequencies_hz()
        b_k = curve(f_k)

        def encode(s: dict) -> bytes:
            return vtx.encode_coefficients(c, geometry, curve, **s)

    cache: dict[tuple, Probe] = {}

    def probe(knob: _Knob, u: int) -> Probe:
        s = knob.setting(u)
        key = tuple(sorted(s.items()))
        if key not in cache:
            data = encode(s)
            dec = vtx.decode(data)
            Pp, Ap = indices.weighted_sums(dec.coefficients, b_k)
            sc = indices.scores_from_sums(dec.ref_P, dec.ref_A, Pp, Ap, *ab)
            v = guard.check(c, dec.coefficients, b_k, f_k, guard_db, ssnr_db)
            cache[key] = Probe(s["method"], s, data, float(sc.Iobj), v.wsnr_db, v.ssnr_db,
                               v.passed)
        return cache[key]

    def ok(p: Probe) -> bool:
        return p.Iobj <= target_iobj and p.guard_ok

    passing: list[Probe] = []
    for m in ((method,) if method else allowed):
        for knob in _knobs(fmt, m, c, b_k):
            if not ok(probe(knob, knob.lo)):
                continue
            lo, hi = knob.lo, knob.hi  # ok(lo); find the largest passing u
            if ok(probe(knob, hi)):
                lo = hi
            else:
                while hi - lo > 1:
                    mid = (lo + hi) // 2
                    if ok(probe(knob, mid)):
                        lo = mid
                    else:
                        hi = mid
                for u in range(lo + 2, min(knob.hi, lo + 1 + LOOKAHEAD) + 1):
                    if ok(probe(knob, u)):
                        lo = u
            passing.append(probe(knob, lo))
    encodes = len(cache)
    seconds = time.process_time() - t0
    if not passing:
        which = f"no {method} stream" if method else "no stream"
        parts = ([f"wSNR >= {guard_db:g} dB"] if guard_db is not None else []) + (
            [f"sSNR >= {ssnr_db:g} dB"] if ssnr_db is not None else [])
        g = f" and {' and '.join(parts)} (the waveform guard)" if parts else ""
        raise CodecError(f"{which} reaches Iobj <= {target_iobj:g}{g}: raise --target-iobj"
                         + (", lower --guard-db / --guard-ssnr-db" if parts else "")
                         + (" or try another --method" if method else ""))
    best = min(passing, key=lambda p: (p.nbytes, p.Iobj))
    return SearchResult(best, encodes, seconds, notes)
