"""Rate control: the smallest stream that verifiably meets Iobj <= target and SPQI >= 0.9.

`search` (what `hostd encode --target-iobj` and `hostd.api.encode(target_iobj=...)` use)
bisects each method's knob, which is monotone in quality: the shaped quantizer's g (0.25 dB
steps), the number of levels L of linear quantization, the cut's b0 (0.25 dB in v2, 0.5 dB
in v1). Every probe is encoded, its bytes decoded, and a candidate passes only on what was
measured on those bytes:
- Iobj <= target, scored exactly as `hostd iobj STREAM` does (hostd.quality.score_stream:
  the decoded coefficients against the reference sums in the stream's header), and
- the waveform criterion, measured, not predicted: SPQI >= `spqi_min` (default 0.9) of the
  signal played from the decoded stream against the original's, exactly as
  `hostd iobj REF STREAM --json` reports it (hostd.perception.peer.played_spqi; SPQI is
  hostd's own implementation, so it is always available).
A stream is returned only after both were checked on it. The waveform guard's SNRs
(hostd.perception.guard: wSNR, sSNR) are proxies: they are reported, and are extra floors
only when asked for (`guard_db`, `ssnr_db`); SPQI itself costs about a millisecond per
candidate, so every candidate whose Iobj passes is measured instead of predicted. Because
neither criterion is strictly monotone in a knob, the search also probes a few steps past
the boundary it found, and it keeps going finer (the bisection moves toward the fine end)
until both hold. A method that cannot code the input at some setting (an exception from the
coder) is skipped there; rate control fails only when no method yields a verified stream.

`candidates` / `smallest_within` keep the exhaustive v1 search (every L and every b0 of a
grid), used as the reference the bisection is tested against.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import numpy as np

from hostd.codec import formats, transform
from hostd.codec import methods as qmethods
from hostd.codec import stream as vtx
from hostd.codec.methods import db_to_ratio
from hostd.errors import CodecError, HostdError, QualityError
from hostd.perception import guard, indices, spqi
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
        data = vtx.v1.encode_coefficients(c, geometry, curve, **s)
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

LOOKAHEAD = 3  # probes past the found boundary (Iobj is not strictly monotone in a knob)
DEFAULT_SPQI_MIN = spqi.CRITERION

@dataclass(frozen=True)
class Probe:
    method: str
    setting: dict
    data: bytes
    Iobj: float
    wsnr_db: float
    ssnr_db: float
    guard_ok: bool  # the explicit SNR floors (True when none was asked for)
    spqi: float | None = None  # measured on the played signal; None: not measured or not computable

    @property
    def nbytes(self) -> int:
        return len(self.data)

    def describe(self) -> str:
        par = ", ".join(f"{k}={v}" for k, v in self.setting.items() if k != "method")
        sp = "" if self.spqi is None else f", SPQI={self.spqi:.4f}"
        return (f"{self.method} ({par}): {self.nbytes} bytes, Iobj={self.Iobj:.4f}{sp}, "
                f"wSNR={self.wsnr_db:.1f} dB, sSNR={self.ssnr_db:.1f} dB")


@dataclass
class SearchResult:
    best: Probe
    encodes: int
    seconds: float
    notes: list[str] = field(default_factory=list)
    spqi_min: float | None = DEFAULT_SPQI_MIN
    # True: SPQI >= spqi_min was measured on best; False: it could not be computed (see notes);
    # None: no waveform criterion was asked for (spqi_min=None, Iobj alone)
    waveform_verified: bool | None = True
    # "Iobj" or "waveform": which criterion stopped a smaller stream (a smaller candidate met
    # Iobj but failed the waveform criterion -> "waveform")
    size_set_by: str = "Iobj"


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


def peak_db(c: np.ndarray, b_k: np.ndarray) -> float:
    """20 log10 max_k |C_k| / b_k, computed as a difference of logarithms so that it stays
    finite where the ratio itself over- or underflows (thresholds of 5e-324 µm, heights of
    1e150 µm); 0 for a silent texture."""
    nz = np.abs(c) > 0
    if not np.any(nz):
        return 0.0
    with np.errstate(divide="ignore"):
        return float(np.max(20.0 * (np.log10(np.abs(c[nz])) - np.log10(b_k[nz]))))


def _knobs(fmt: str, method: str, c: np.ndarray, b_k: np.ndarray) -> list[_Knob]:
    top_db = peak_db(c, b_k)
    if method == "shaped":
        g_lo, g_hi = int(qmethods.G_MIN_DB * 4), int(qmethods.G_MAX_DB * 4)
        u_hi = max(g_lo, min(g_hi, math.ceil((top_db + 7.0) * 4)))  # all indices 0
        u_lo = max(g_lo, u_hi - 4 * 80)
        return [_Knob("shaped", u_lo, u_hi, lambda u: {"method": "shaped", "g_db": u / 4})]
    if method == "quant":
        # u = MAX_L - L: larger u, fewer levels, lower quality
        return [_Knob("quant", 0, MAX_L - 2, lambda u: {"method": "quant", "levels": MAX_L - u})]
    unit = formats.get(fmt).cut_steps_per_db
    top_db = max(-1000.0, min(1000.0, top_db))  # b0 = 10^(b0/20) must stay a finite factor
    u_hi = math.ceil((top_db + 1.0) * unit)  # everything cut
    u_lo = u_hi - 80 * unit
    bits = tuple(sorted({formats.get(fmt).value_bits, 16}))  # the format's default, and 16-bit
    return [_Knob("cut", u_lo, u_hi, lambda u, vb=vb: {"method": "cut", "b0_db": u / unit,
                                                         "value_bits": vb}) for vb in bits]


def search(y_um: np.ndarray, geometry: transform.Geometry, curve: ThresholdCurve,
           target_iobj: float, *, method: str | None = None, fmt: str = "v2",
           spqi_min: float | None = DEFAULT_SPQI_MIN,
           guard_db: float | None = None, ssnr_db: float | None = None,
           ab: tuple[float, float] = indices.DEFAULT_AB) -> SearchResult:
    """The smallest stream with Iobj <= target and SPQI >= spqi_min, both measured on the
    returned bytes (spqi_min=None: Iobj alone), and, when given, wSNR >= guard_db and
    sSNR >= ssnr_db. Messages name the CLI's options; hostd.api renames them for Python."""
    from hostd.perception import peer
    from hostd.quality import score_stream

    peer.played_signal(np.ones(1), 2, 1.0, 1.0, duration_s=0.001)  # load scipy.signal before timing
    t0 = time.thread_time()
    if not (math.isfinite(target_iobj) and target_iobj >= 0):
        raise CodecError(f"--target-iobj must be a finite number >= 0, got {target_iobj}")
    if spqi_min is not None and not (math.isfinite(spqi_min) and 0.0 <= spqi_min <= 1.0):
        raise CodecError(f"--spqi-min must be a number in 0..1, got {spqi_min}")
    fm = formats.get(fmt)
    allowed = fm.methods
    if method is not None and method not in allowed:
        raise CodecError(f"method {method} is not available in stream {fmt}: use one of "
                         f"{', '.join(allowed)}")
    notes = []
    if target_iobj >= max_iobj(ab):
        notes.append(f"--target-iobj {target_iobj:g} is degenerate: no stream can score "
                     f"above {max_iobj(ab):g} (a Ip + b Ia with Ip, Ia <= 2), so only the waveform "
                     "criterion limits the choice")
    module = fm.load()
    cg = module.coding_geometry(geometry)  # the geometry as the format stores it
    c = transform.analyze(y_um, cg.n_keep)
    f_k = cg.frequencies_hz()
    b_k = curve(f_k)

    def encode(s: dict) -> bytes:
        return module.encode_coefficients(c, cg, curve, **s)

    cache: dict[tuple, Probe | None] = {}
    refused: set[str] = set()  # methods whose coder refused some setting
    unmeasurable: list[str] = []  # why SPQI could not be computed (then the proxies decide)

    def probe(knob: _Knob, u: int) -> Probe | None:
        """The measured candidate at knob setting u, or None when the coder refuses it."""
        s = knob.setting(u)
        key = tuple(sorted(s.items()))
        if key not in cache:
            try:
                data = encode(s)
                dec = vtx.decode(data)
                sc = score_stream(dec, curve=curve, a=ab[0], b=ab[1])  # as `hostd iobj STREAM`
                v = guard.check(c, dec.coefficients, b_k, f_k, guard_db, ssnr_db)
            except (CodecError, QualityError):  # this setting cannot code the input
                refused.add(knob.method)
                cache[key] = None
                return None
            sp = None
            if spqi_min is not None and float(sc.Iobj) <= target_iobj and v.passed:
                try:  # the waveform criterion, measured as `hostd iobj REF STREAM` does
                    sp = peer.played_spqi(c, dec.coefficients, dec.n, dec.length_mm, dec.speed_mm_s)
                except (HostdError, ValueError, FloatingPointError) as exc:
                    unmeasurable.append(str(exc))
            cache[key] = Probe(s["method"], s, data, float(sc.Iobj), v.wsnr_db, v.ssnr_db,
                               v.passed, sp)
        return cache[key]

    def meets_iobj(p: Probe | None) -> bool:
        return p is not None and p.Iobj <= target_iobj and p.guard_ok

    def ok(p: Probe | None) -> bool:
        if not meets_iobj(p):
            return False
        if spqi_min is None:
            return True
        if p.spqi is None:  # not computable: fall back to the proxy guard's calibrated floors
            return guard.check_db(p.wsnr_db, p.ssnr_db)
        return p.spqi >= spqi_min

    passing: list[Probe] = []
    for m in ((method,) if method else allowed):
        for knob in _knobs(fmt, m, c, b_k):
            lo, hi = knob.lo, knob.hi
            if probe(knob, lo) is None:  # the finest setting cannot be coded: find the finest that can
                if probe(knob, hi) is None:
                    continue
                while hi - lo > 1:
                    mid = (lo + hi) // 2
                    if probe(knob, mid) is None:
                        lo = mid
                    else:
                        hi = mid
                lo, hi = hi, knob.hi
            if not ok(probe(knob, lo)):
                continue
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
    if not passing:
        raise CodecError(_no_stream_message(method, fmt, target_iobj, spqi_min, guard_db, ssnr_db,
                                            cache, peak_db(c, b_k)))
    best = min(passing, key=lambda p: (p.nbytes, p.Iobj))
    for m in refused:
        if not any(p is not None and p.method == m for p in cache.values()):
            notes.append(f"method {m} skipped: it cannot code this input at any setting")
    verified: bool | None = None
    if spqi_min is not None:
        verified = best.spqi is not None
        if not verified:
            notes.append(f"the waveform criterion SPQI >= {spqi_min:g} could not be computed "
                         f"({unmeasurable[0]}); the stream meets the proxy guard wSNR >= "
                         f"{guard.DEFAULT_GUARD_DB:g} dB and sSNR >= {guard.DEFAULT_SSNR_DB:g} dB "
                         "instead, which does not guarantee it")
    smaller_failed = any(p is not None and meets_iobj(p) and not ok(p) and p.nbytes < best.nbytes
                         for p in cache.values())
    return SearchResult(best, encodes, time.thread_time() - t0, notes, spqi_min, verified,
                        "waveform" if smaller_failed else "Iobj")


def _no_stream_message(method, fmt, target_iobj, spqi_min, guard_db, ssnr_db, cache, top_db) -> str:
    """One line: why no stream was returned, and what the user can change."""
    if cache and all(p is None for p in cache.values()):
        which = f"method {method} cannot" if method else "no method can"
        return (f"{which} code this texture at any setting (largest |C_k| / b(f_k) is "
                f"{top_db:.0f} dB): check the heights' unit (--y-unit) and the threshold curve "
                f"(--thresholds)" + (", or use --format v1" if fmt == "v2" else "")
                + (", or try another --method" if method else ""))
    parts = ([f"SPQI >= {spqi_min:g}"] if spqi_min is not None else []) + (
        [f"wSNR >= {guard_db:g} dB"] if guard_db is not None else []) + (
        [f"sSNR >= {ssnr_db:g} dB"] if ssnr_db is not None else [])
    g = f" and {' and '.join(parts)} (the waveform criterion)" if parts else ""
    lower = ["--spqi-min"] if spqi_min is not None else []
    lower += ["--guard-db"] if guard_db is not None else []
    lower += ["--guard-ssnr-db"] if ssnr_db is not None else []
    return (f"{'no ' + method + ' stream' if method else 'no stream'} reaches Iobj <= "
            f"{target_iobj:g}{g}: raise --target-iobj"
            + (f", lower {' / '.join(lower)}" if lower else "")
            + (" or try another --method" if method else ""))
