"""Height under the finger at any real position, band-limited for the current hand speed.

The exact evaluator is the series  h(x) = Σ_k g_k(v) C'_k cos(π k (2x/dx + 1) / (2N)),  which is
already the mirror-even, 2L-periodic extension of the patch (a hand moving past the patch
sees a continuous texture). Faster evaluators read a precomputed table of that series (one
period, oversampled `table_oversample` times over its highest component, built by one
inverse real FFT per speed bucket) with linear or cubic interpolation, or the nearest sample.

Speed-aware band limit: at hand speed v component k sounds at f_k = k |v| / (2L). Gains g_k are
1 up to f_pass = pass_band_hz (the codec's f_max, 400 Hz: at the reference speed every kept
component sounds at or below f_max, so a hand at v_ref feels every kept component at full
amplitude) and fade to 0 with a raised cosine between f_pass and f_stop, so fast strokes do
not alias and speed changes do not click. f_stop is `stop_band_hz`, 1000 Hz by default: a
compromise, measured (docs/rendering.md), between fidelity at fast strokes (more of the texture
plays the further the fade reaches) and the slew the equalized piezo needs (the equalizer's
gain is 10 at 800 Hz, 18 at 1000 Hz and 34 at 1200 Hz; with the fade to 1200 Hz the wood
texture reaches the 60 mm/s slew limit at the metronome's 93 mm/s peak, with 1000 Hz it
uses 88 % of it). It is never above nyquist_fraction * fs/2 (1200 Hz at 3 kHz: the aliasing
limit of the output, with a 20 % guard; `stop_band_hz = None` means that) and never below f_pass.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from hostd.cyclestate import record
from hostd.render.series import evaluate as series_evaluate
from hostd.render.series import phase_rad as series_phase

METHODS = ("series", "table-cubic", "table-linear", "nearest")
REST_BUCKET = -(1 << 30)  # the speed bucket of a hand at rest


@dataclass
class BandLimitConfig:
    pass_band_hz: float = 400.0  # full amplitude up to here: the codec's f_max at v_ref
    sample_rate_hz: float = 3000.0
    nyquist_fraction: float = 0.8  # the fade ends at this fraction of fs/2 (aliasing limit)
    stop_band_hz: float | None = 1000.0  # end of the fade (None: the aliasing limit)
    speed_bucket: float = 0.02  # relative speed step between cached gains / tables


def band_edges_hz(cfg: BandLimitConfig) -> tuple[float, float]:
    """(f_pass, f_stop) in Hz: gains are 1 below f_pass, 0 from f_stop, a raised cosine between."""
    f_alias = cfg.nyquist_fraction * cfg.sample_rate_hz / 2.0
    f_stop = f_alias if cfg.stop_band_hz is None else min(cfg.stop_band_hz, f_alias)
    if not (0 < cfg.pass_band_hz < f_stop):
        raise ValueError(f"the pass band ({cfg.pass_band_hz} Hz) must be > 0 and below the end of "
                         f"the fade ({f_stop} Hz: stop_band_hz or {cfg.nyquist_fraction} x fs/2)")
    return float(cfg.pass_band_hz), float(f_stop)


def band_gains(k: np.ndarray, speed_mm_s, length_mm: float, cfg: BandLimitConfig) -> np.ndarray:
    """Gains of components k at speed(s) v: shape k.shape, or v.shape + k.shape for arrays."""
    f_pass, f_stop = band_edges_hz(cfg)
    f = np.multiply.outer(np.abs(speed_mm_s), k) / (2.0 * length_mm)
    g = np.ones_like(f)
    fade = (f > f_pass) & (f < f_stop)
    g[fade] = 0.5 * (1.0 + np.cos(np.pi * (f[fade] - f_pass) / (f_stop - f_pass)))
    g[f >= f_stop] = 0.0
    return g


class HeightEvaluator(record("height")):
    """Evaluate band-limited heights (µm) at positions x (mm) for a given hand speed."""

    def __init__(self, coeffs_um: np.ndarray, n: int, length_mm: float, method: str = "series",
                 band: BandLimitConfig | None = None, dtype: type = np.float64,
                 cache_tables: int = 16, table_oversample: int = 16) -> None:
        if method not in METHODS:
            raise ValueError(f"height method must be one of {METHODS}")
        c = np.asarray(coeffs_um, dtype=np.float64)
        if not np.all(np.isfinite(c)):
            raise ValueError("coefficients must be finite")
        self.c = c
        self.n = int(n)
        self.length_mm = float(length_mm)
        self.dx_mm = self.length_mm / self.n
        self.method = method
        self.band = band or BandLimitConfig()
        self._speed_bucket = self.band.speed_bucket
        self.dtype = dtype
        self.k = np.arange(1, c.size + 1, dtype=np.float64)
        self._w_bucket: int | None = None
        self._w = self.c.astype(dtype)
        self._w_cache: dict[int, np.ndarray] = {}
        self._tables: OrderedDict[int, np.ndarray] = OrderedDict()
        self._cache = cache_tables
        if not 2 <= table_oversample <= 1024:
            raise ValueError("table_oversample must be 2..1024")
        self.m = 1 << max(4, math.ceil(math.log2(table_oversample * 2 * (c.size + 1))))
        self._idx_per_sample = self.m / (2.0 * self.n)  # table index per sample spacing
        # Up to this speed every non-zero component sounds at or below f_pass: every gain is 1 and
        # the weights are those of a hand at rest, so those speeds share the rest bucket instead
        # of one bucket per 2 % of speed (a reversal sweeps through hundreds of them, each a first
        # visit the compiled cycle hands to the reference). A hair below the edge, so that no
        # rounding of k v / 2L puts a component past f_pass.
        nz = np.flatnonzero(c)
        f_pass, _f_stop = band_edges_hz(self.band)
        self._v_full_mm_s = (f_pass * 2.0 * self.length_mm / float(nz[-1] + 1) * (1.0 - 1e-9)
                             if nz.size else math.inf)

    def gains(self, speed_mm_s: float) -> np.ndarray:
        return band_gains(self.k, speed_mm_s, self.length_mm, self.band)

    WEIGHT_CACHE_BYTES = 4 << 20

    def weights(self, speed_mm_s: float) -> np.ndarray:
        """C'_k g_k(v), cached per speed bucket (the gains change smoothly with |v|). A stroke
        sweeps a few hundred buckets back and forth, so the weights of every bucket seen are
        kept (up to WEIGHT_CACHE_BYTES, oldest first out), not only the last one: recomputing
        the gains of a bucket (every third 1 ms cycle under the metronome) costs ~15 µs."""
        b = self._bucket(speed_mm_s)
        if b != self._w_bucket:
            w = self._w_cache.get(b)
            if w is None:
                w = (self.c * self.gains(self._bucket_speed(b))).astype(self.dtype)
                w.flags.writeable = False
                self._w_cache[b] = w
                if len(self._w_cache) * w.nbytes > self.WEIGHT_CACHE_BYTES and len(self._w_cache) > 2:
                    self._w_cache.pop(next(iter(self._w_cache)))
            self._w = w
            self._w_bucket = b
        return self._w

    def series(self, x_mm: np.ndarray, speed_mm_s: float, exact_gains: bool = False) -> np.ndarray:
        """The band-limited series. With exact_gains the gains are those of the exact speed
        (the reference of every other method); otherwise of the speed's bucket."""
        # Reduce x to one period (2L) in float64 first: a hand that travels far in one
        # direction (a mouse, an hour at 50 mm/s = 180 m) keeps full phase precision in float32.
        u = series_phase(x_mm, self.n, self.length_mm).astype(self.dtype)
        w = ((self.c * self.gains(speed_mm_s)).astype(self.dtype) if exact_gains
             else self.weights(speed_mm_s))
        return series_evaluate(w, u)

    def _bucket(self, speed_mm_s: float) -> int:
        s = abs(speed_mm_s)
        if s < 1e-9 or s <= self._v_full_mm_s:
            return REST_BUCKET
        return math.floor(math.log(s) / math.log1p(self.band.speed_bucket))

    def _bucket_speed(self, b: int) -> float:
        """The speed a bucket's gains are computed for: its geometric centre."""
        return 0.0 if b == REST_BUCKET else math.exp((b + 0.5) * math.log1p(self.band.speed_bucket))

    def table(self, speed_mm_s: float) -> np.ndarray:
        """One period of the series, band-limited for the speed's bucket, sampled at M points
        (M = a power of two >= oversample x 2 x components; +3 samples for the cubic's wrap)."""
        b = self._bucket(speed_mm_s)
        tab = self._tables.get(b)
        if tab is None:
            v = self._bucket_speed(b)
            spec = np.zeros(self.m // 2 + 1)
            spec[1 : self.c.size + 1] = self.c * self.gains(v) * (self.m / 2)
            import scipy.fft

            y = scipy.fft.irfft(spec, self.m)  # y_j = sum_k w_k cos(2 pi k j / M)
            tab = np.concatenate([y, y[:3]]).astype(self.dtype)
            self._tables[b] = tab
            if len(self._tables) > self._cache:
                self._tables.popitem(last=False)
        else:
            self._tables.move_to_end(b)
        return tab

    def __call__(self, x_mm: np.ndarray, speed_mm_s: float) -> np.ndarray:
        if self.method == "series":
            return self.series(x_mm, speed_mm_s)
        tab = self.table(speed_mm_s)
        period = self.m
        u = np.mod((np.asarray(x_mm, dtype=np.float64) / self.dx_mm + 0.5) * self._idx_per_sample, period)
        if self.method == "nearest":
            return tab[np.rint(u).astype(np.int64) % period]
        i = np.floor(u).astype(np.int64)
        t = (u - i).astype(self.dtype)
        if self.method == "table-linear":
            return tab[i] + t * (tab[i + 1] - tab[i])
        # Catmull-Rom cubic through i-1, i, i+1, i+2 (i-1 wraps to the period's end).
        p0 = tab[(i - 1) % period]
        p1, p2, p3 = tab[i], tab[i + 1], tab[i + 2]
        return p1 + 0.5 * t * (p2 - p0 + t * (2 * p0 - 5 * p1 + 4 * p2 - p3 + t * (3 * (p1 - p2) + p3 - p0)))
