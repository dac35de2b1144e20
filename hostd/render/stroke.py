"""The texture as a hand moving at constant speed feels it on an ideal display: one function
for `hostd render` and hostd.api.render_stroke, the .hjif export's time-domain perception, the
peer metrics' played signal (hostd.perception.peer) and the corpus's peer codecs.

h(t_m) = sum_k g_k C'_k cos(k theta(x0 + v t_m)), t_m = m / rate, theta(x) = pi (x/dx + 1/2) / N
(the patch's mirror-even series, hostd.render.series), evaluated with one chirp-z transform;
g_k are the renderer's speed-aware band gains at the output rate (hostd.render.height), or 1
for the unfiltered series (band_limited=False: what the peer metrics compare).
"""

from __future__ import annotations

import numpy as np

from hostd.render import series


def at_constant_speed(coeffs_um: np.ndarray, n: int, length_mm: float, speed_mm_s: float,
                      rate_hz: float, count: int, *, x0_mm: float = 0.0,
                      band_limited: bool = True) -> np.ndarray:
    """`count` heights (µm) at `rate_hz` under a hand moving at `speed_mm_s` (negative:
    backwards) from `x0_mm`, over a patch of n samples and length_mm (C'_1..C'_N' given)."""
    c = np.asarray(coeffs_um, dtype=np.float64)
    if band_limited:
        c = with_band_gains(c, length_mm, speed_mm_s, rate_hz)
    theta0 = float(series.phase_rad(x0_mm, n, length_mm))
    dtheta = np.pi * speed_mm_s / (length_mm / n * n * rate_hz)  # phase per sample: v / (N dx rate)
    return series.evaluate_uniform(c, theta0, dtheta, int(count))


def with_band_gains(coeffs_um: np.ndarray, length_mm: float, speed_mm_s: float, rate_hz: float) -> np.ndarray:
    """g_k C'_k: the series as the renderer plays it at speed_mm_s and rate_hz (hostd.render.height)."""
    from hostd.render.height import BandLimitConfig, band_gains

    c = np.asarray(coeffs_um, dtype=np.float64)
    k = np.arange(1, c.size + 1, dtype=np.float64)
    return c * band_gains(k, speed_mm_s, length_mm, BandLimitConfig(sample_rate_hz=rate_hz))


def crossing_count(length_mm: float, speed_mm_s: float, rate_hz: float, minimum: int = 2) -> int:
    """Samples of one crossing of the patch (L / |v| seconds) at rate_hz, at least `minimum`."""
    return max(minimum, round(length_mm / abs(speed_mm_s) * rate_hz))
