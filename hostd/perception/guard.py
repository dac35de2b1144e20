"""The waveform guard: per-component distortion measures, proxies of the waveform criterion.

Rate control certifies the waveform with SPQI itself, measured on each candidate's played
signal (hostd.codec.ratecontrol, hostd.perception.spqi): a proxy calibrated on a few textures
was no guarantee on others (issue 23: SPQI < 0.9 at sSNR up to 40 dB on held-out recordings).
The SNRs below are reported with every stream, are extra floors only when asked for
(`--guard-db`, `--guard-ssnr-db`), and are the fallback (with `waveform_verified: false`) only
where SPQI cannot be computed. The history of their calibration follows.

Iobj compares two weighted *sums*, so a stream can match the sums with the wrong spectrum
(issue 14). The guard looks at the error of each component instead, with two SNRs of the
same form, each a weighted power sum of the texture over the same sum of the error:

    wSNR = 10 log10( sum_k (C_k / b_k)^2  /  sum_k ((C_k - C'_k) / b_k)^2 )          [dB]
    sSNR = 10 log10( sum_k w(f_k) C_k^2   /  sum_k w(f_k) (C_k - C'_k)^2 )            [dB]

- wSNR weighs by the project's detection threshold b(f_k) (the weighting of Iobj's P). It is
  recorded in every v2 header and reported by `inspect` and `iobj`.
- sSNR weighs by the vibrotactile threshold curve of the SPQI/ST-SIM model (Hassen &
  Steinbach; as implemented in vibromaf's PerceptualThreshold): w(f) = 10^(-T(f)/10) with
  T(f) = |62 / log10(c)^2 * log10(f/550 + c)^2| - 77 dB, c = 1 - 250/550, capped at 0 dB.
  That curve keeps falling from 0 to 250 Hz (-15 dB at DC, -38 dB at 40 Hz, -77 dB at 250 Hz)
  where b(f) is flat below 40 Hz, so it weighs the small high-frequency components of a
  low-frequency texture about 16 dB more than wSNR does.

Errors add as squares whatever their sign, so neither SNR can be matched by a wrong spectrum.
Why two: on the 32 textures of the calibration (DEVELOPMENT.md, "Waveform guard") the
largest wSNR at which a stream still had SPQI < 0.9 was 35.5 dB (real profile dektak-1 at
25 mm/s; 22-25 dB on most textures), so no wSNR default gave SPQI >= 0.9 everywhere; the
largest such sSNR was at most 24.8 dB on every texture (synthetic, real, 7 to 160 components).
The former defaults wSNR >= 25 dB AND sSNR >= 27 dB (2 dB above the worst case measured) gave
SPQI >= 0.945 on all 32 textures and 12 held-out ones, against 0.489-0.834 on 6 of 32 with
wSNR >= 25 dB alone, but SPQI 0.20-0.86 on 5 of the 25 held-out textures of
hostd/bench/holdout.py (DEVELOPMENT.md); they remain the proxy floors (DEFAULT_*).
The largest per-component error relative to b_k (`nmr_max_db`) is reported, not guarded: a
single component decides it, and it is unreachable for strong textures at low rates.

Decisions are exact comparisons of correctly rounded sums (math.fsum) against factors
computed in decimal arithmetic, so the stream rate control picks is the same on every CPU;
the dB values are for reports.
"""

from __future__ import annotations

import decimal
import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from hostd.errors import QualityError
from hostd.perception.indices import exact_sum, pow2_scale, weights

DEFAULT_GUARD_DB = 25.0  # wSNR (threshold b(f)) proxy floor (rate control's fallback)
DEFAULT_SSNR_DB = 27.0  # sSNR (the SPQI model's threshold curve) proxy floor (fallback)
CAP_DB = 200.0  # a lossless (or float64-exact) stream reports this

# The SPQI model's threshold curve (vibromaf.signal.perception.PerceptualThreshold's defaults)
SPQI_CURVE = {"x_scaler": 62.0, "y_scaler": 1.0 / 550.0, "x_offset": 1.0 - 250.0 / 550.0,
              "y_offset_db": 77.0}


def _threshold_weights(threshold_um: np.ndarray) -> np.ndarray:
    """1/b^2 up to one power of two: computed from b scaled into [0.5, 1) at its largest, so
    thresholds of 1e200 or 5e-324 µm do not underflow or overflow the weights (an SNR is a
    ratio of two sums with the same weights, so the common factor cancels exactly)."""
    b = np.asarray(threshold_um, dtype=np.float64)
    with np.errstate(over="ignore"):  # only its refusal of non-finite or non-positive b is used
        weights(b)
    inv = np.divide(1.0, np.multiply(b, pow2_scale(b)))
    return np.multiply(inv, inv)


def weighted_snr_db(reference_um: np.ndarray, decoded_um: np.ndarray, threshold_um: np.ndarray) -> float:
    """wSNR in dB (capped at CAP_DB; -CAP_DB for a silent reference that was not kept silent)."""
    c = np.asarray(reference_um, dtype=np.float64)
    d = np.asarray(decoded_um, dtype=np.float64)
    return _db(*_power_sums(c, d, _threshold_weights(threshold_um)))


@lru_cache(maxsize=64)
def _spqi_weights(freqs: tuple[float, ...]) -> np.ndarray:
    ctx = decimal.Context(prec=25)  # integer arithmetic (libmpdec): the same on every CPU
    D = decimal.Decimal
    xo = D(SPQI_CURVE["x_offset"])
    scale = ctx.divide(D(SPQI_CURVE["x_scaler"]), ctx.power(ctx.log10(xo), 2))
    ln10 = ctx.ln(D(10))
    out = []
    for f in freqs:
        arg = ctx.add(ctx.multiply(D(SPQI_CURVE["y_scaler"]), D(f)), xo)
        t = ctx.subtract(abs(ctx.multiply(scale, ctx.power(ctx.log10(arg), 2))),
                         D(SPQI_CURVE["y_offset_db"]))
        t = min(t, D(0))  # the curve is held at 0 dB above the frequency where it crosses 0
        out.append(float(ctx.exp(ctx.multiply(ctx.divide(-t, D(10)), ln10))))
    return np.array(out, dtype=np.float64)


def spqi_curve_weights(freqs_hz: np.ndarray) -> np.ndarray:
    """w(f) = 10^(-T(f)/10): power weights of the SPQI model's threshold curve at f (Hz),
    computed in 25-digit decimal arithmetic (the same bits on every CPU)."""
    f = np.asarray(freqs_hz, dtype=np.float64)
    if f.ndim != 1 or not np.all(np.isfinite(f)) or np.any(f < 0):
        raise QualityError("component frequencies must be finite and >= 0 Hz")
    w = _spqi_weights(tuple(f.tolist()))
    w.flags.writeable = False
    return w


def _power_sums(c: np.ndarray, d: np.ndarray, w2: np.ndarray) -> tuple[float, float]:
    """(sum w C^2, sum w (C - C')^2), correctly rounded, both times one common power of two:
    C and C' are first scaled so that the larger peak is in [0.5, 1), w likewise, so the
    squares neither underflow (heights of 1e-300 µm: both sums 0, an SNR of "200 dB" for any
    stream) nor overflow (1e150 µm). Exact scaling: in the normal range the SNR and every
    decision are bit-identical to the unscaled sums'."""
    if c.shape != d.shape:
        raise QualityError(f"{c.size} reference but {d.size} decoded coefficients")
    if not (np.all(np.isfinite(c)) and np.all(np.isfinite(d))):
        raise QualityError("coefficients contain NaN or Inf")
    k = min(pow2_scale(c), pow2_scale(d))
    c, d = np.multiply(c, k), np.multiply(d, k)
    w2 = np.multiply(w2, pow2_scale(w2))
    err = np.subtract(c, d)
    return (float(exact_sum(np.multiply(np.multiply(c, c), w2))),
            float(exact_sum(np.multiply(np.multiply(err, err), w2))))


def _db(sig: float, noise: float) -> float:
    if noise == 0.0:
        return CAP_DB
    if sig == 0.0:
        return -CAP_DB
    return max(-CAP_DB, min(CAP_DB, 10.0 * math.log10(sig / noise)))


def spectral_snr_db(reference_um: np.ndarray, decoded_um: np.ndarray, freqs_hz: np.ndarray) -> float:
    """sSNR in dB: the SNR weighted by the SPQI model's threshold curve (capped at CAP_DB)."""
    c = np.asarray(reference_um, dtype=np.float64)
    d = np.asarray(decoded_um, dtype=np.float64)
    return _db(*_power_sums(c, d, spqi_curve_weights(freqs_hz)))


def _at_least(sig: float, noise: float, floor_db: float) -> bool:
    """10 log10(sig / noise) >= floor_db, decided exactly: noise * 10^(floor/10) <= sig."""
    from hostd.codec.methods import db_to_ratio

    if noise == 0.0:
        return True
    return noise * db_to_ratio(2.0 * floor_db) <= sig


@dataclass(frozen=True)
class Verdict:
    """The guard's measures of one decoded stream and whether it passes."""

    wsnr_db: float
    ssnr_db: float
    passed: bool


def check(reference_um: np.ndarray, decoded_um: np.ndarray, threshold_um: np.ndarray,
          freqs_hz: np.ndarray, wsnr_min_db: float | None = DEFAULT_GUARD_DB,
          ssnr_min_db: float | None = DEFAULT_SSNR_DB) -> Verdict:
    """Both SNRs, and whether wSNR >= wsnr_min_db and sSNR >= ssnr_min_db (None: not required)."""
    c = np.asarray(reference_um, dtype=np.float64)
    d = np.asarray(decoded_um, dtype=np.float64)
    ws, wn = _power_sums(c, d, _threshold_weights(threshold_um))
    ss, sn = _power_sums(c, d, spqi_curve_weights(freqs_hz))
    ok = ((wsnr_min_db is None or _at_least(ws, wn, wsnr_min_db))
          and (ssnr_min_db is None or _at_least(ss, sn, ssnr_min_db)))
    return Verdict(_db(ws, wn), _db(ss, sn), ok)


def check_db(wsnr_db: float, ssnr_db: float, wsnr_min_db: float = DEFAULT_GUARD_DB,
             ssnr_min_db: float = DEFAULT_SSNR_DB) -> bool:
    """The proxy floors on reported dB values: rate control's fallback when SPQI, the
    criterion it certifies, cannot be computed (it then says so: waveform_verified false)."""
    return wsnr_db >= wsnr_min_db and ssnr_db >= ssnr_min_db


def max_nmr_db(reference_um: np.ndarray, decoded_um: np.ndarray, threshold_um: np.ndarray) -> float:
    """20 log10 max_k |C_k - C'_k| / b_k: the worst component's error over its threshold, dB."""
    c = np.asarray(reference_um, dtype=np.float64)
    d = np.asarray(decoded_um, dtype=np.float64)
    _, w1 = weights(threshold_um)
    worst = float(np.max(np.multiply(np.abs(np.subtract(c, d)), w1)))
    if worst == 0.0:
        return -CAP_DB
    return max(-CAP_DB, min(CAP_DB, 20.0 * math.log10(worst)))


def header_code(wsnr_db: float) -> int:
    """The guard byte of a v2 stream: floor(2 wSNR) clamped to 0..255 (a lower bound, 0.5 dB)."""
    return int(max(0, min(255, math.floor(2.0 * wsnr_db))))


def from_header(code: int) -> float:
    return code / 2.0
