"""The waveform guard: a per-component distortion measure relative to the detection threshold.

Iobj compares two weighted *sums*, so a stream can match the sums with the wrong spectrum
(issue 14). The guard looks at the error of each component instead:

    wSNR = 10 log10( sum_k (C_k / b_k)^2  /  sum_k ((C_k - C'_k) / b_k)^2 )   [dB]

the threshold-weighted signal-to-noise ratio: the paper's power sum P of the texture over the
same sum taken of the error. Errors add as squares whatever their sign, so no choice of
C'_k can match the sums and keep a high wSNR with a wrong spectrum; weighting by 1/b_k makes
an error count in units of "how far above the detection threshold", as Iobj's P does.
We prefer it to the largest per-component error relative to b_k (also reported, `nmr_max_db`),
which a single component decides and which is unreachable for strong textures at low rates;
and to a plain SNR, which ignores the threshold curve.

Default guard: wSNR >= 25 dB. Measured (docs/benchmarks.md, `hostd bench codec
--guard-calibration`): on five of six textures (synthetic wood, sandpaper; real xy-1, xy-4)
SPQI reached 0.9 by wSNR 22.5-24.8 dB; the real 23-component dektak-1 profile needed 30.5 dB.
"""

from __future__ import annotations

import math

import numpy as np

from hostd.errors import QualityError
from hostd.perception.indices import exact_sum, weights

DEFAULT_GUARD_DB = 25.0
CAP_DB = 200.0  # a lossless (or float64-exact) stream reports this


def weighted_snr_db(reference_um: np.ndarray, decoded_um: np.ndarray, threshold_um: np.ndarray) -> float:
    """wSNR in dB (capped at CAP_DB; 0 dB for a silent reference that was not kept silent)."""
    c = np.asarray(reference_um, dtype=np.float64)
    d = np.asarray(decoded_um, dtype=np.float64)
    if c.shape != d.shape:
        raise QualityError(f"{c.size} reference but {d.size} decoded coefficients")
    if not (np.all(np.isfinite(c)) and np.all(np.isfinite(d))):
        raise QualityError("coefficients contain NaN or Inf")
    w2, _ = weights(threshold_um)
    err = np.subtract(c, d)
    sig = float(exact_sum(np.multiply(np.multiply(c, c), w2)))
    noise = float(exact_sum(np.multiply(np.multiply(err, err), w2)))
    if noise == 0.0:
        return CAP_DB
    if sig == 0.0:
        return -CAP_DB
    return max(-CAP_DB, min(CAP_DB, 10.0 * math.log10(sig / noise)))


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
