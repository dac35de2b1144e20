"""The paper's two lossy methods on the amplitude spectrum C_1..C_N'.

Linear quantization (eq. 5, 6):  L_k = round(C_k / D) D,  D = (max C - min C) / (L - 1)
Threshold-cut (eq. 7):           T_k = 0 if |C_k| < b(f_k) 10^(b0/20) else C_k
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from hostd.errors import CodecError
from hostd.render import exactmath

MAX_LEVELS = 65535
# |q| beyond 2^53 would no longer be an exact integer in float64.
_MAX_INDEX = float(1 << 53)


@dataclass(frozen=True)
class Quantized:
    """Integer indices q_k and step D, such that L_k = q_k * D."""

    q: np.ndarray  # int64, shape (N',)
    step_um: float
    levels: int

    def values(self) -> np.ndarray:
        return self.q.astype(np.float64) * self.step_um


def finite_coeffs(coeffs_um) -> np.ndarray:
    """The coefficients as float64; NaN or Inf is refused (one message for every encoder)."""
    c = np.asarray(coeffs_um, dtype=np.float64)
    if not np.all(np.isfinite(c)):
        raise CodecError("coefficients contain NaN or Inf")
    return c


def check_levels(levels: int) -> int:
    if isinstance(levels, bool) or int(levels) != levels:
        raise CodecError(f"--levels must be a whole number, got {levels!r}")
    levels = int(levels)
    if levels < 2:
        raise CodecError(f"--levels must be >= 2 (eq. 6 divides by L - 1), got {levels}")
    if levels > MAX_LEVELS:
        raise CodecError(f"--levels must be <= {MAX_LEVELS}, got {levels}")
    return levels


def quantize(coeffs_um: np.ndarray, levels: int) -> Quantized:
    """Linear quantization with L levels spanning min..max of the coefficients.

    Rounding is half-to-even (numpy.rint, C's nearbyint). When every coefficient is equal
    (max == min) the span is zero; D is then |c| (or 1 for all zeros) so the texture is
    represented exactly instead of dividing by zero.
    """
    levels = check_levels(levels)
    c = np.asarray(coeffs_um, dtype=np.float64)
    if c.ndim != 1 or c.size < 1:
        raise CodecError("quantize needs a 1-D array of coefficients")
    finite_coeffs(c)
    lo, hi = float(c.min()), float(c.max())
    step = (hi - lo) / (levels - 1)
    if not (step > 0 and math.isfinite(step)):
        # Constant spectrum (or a span that underflows to 0): exact representation.
        step = abs(hi) if hi != 0 else 1.0
    ratio = c / step
    if np.any(np.abs(ratio) >= _MAX_INDEX):
        raise CodecError("coefficient range too narrow for its magnitude to quantize exactly")
    q = np.rint(ratio).astype(np.int64)
    return Quantized(q=q, step_um=step, levels=levels)


@functools.lru_cache(maxsize=4096)
def db_to_ratio(db: float) -> float:
    """10^(db/20), the same bits on every CPU.

    libm's pow has CPU-specific variants (glibc picks an FMA build at run time) that may differ
    in the last bit; this factor reaches stream bytes (cut decisions, shaped steps), so it is
    computed in decimal arithmetic (libmpdec, integers only) at 40 digits and rounded once.
    """
    if not math.isfinite(db):
        raise CodecError(f"a level in dB must be finite, got {db}")
    r = exactmath.db_ratio(db)
    if not (r > 0 and math.isfinite(r)):
        raise CodecError(f"{db} dB is out of range (10^(dB/20) must be a finite number > 0)")
    return r


def cut_level_um(threshold_um: np.ndarray, b0_db: float) -> np.ndarray:
    """b(f_k) 10^(b0/20): the shifted threshold below which amplitudes are removed."""
    if not math.isfinite(b0_db):
        raise CodecError(f"--b0-db must be a finite number of dB, got {b0_db}")
    return np.asarray(threshold_um, dtype=np.float64) * db_to_ratio(float(b0_db))


def threshold_cut(coeffs_um: np.ndarray, threshold_um: np.ndarray, b0_db: float) -> np.ndarray:
    """Boolean mask of the coefficients kept by eq. 7 (|C_k| >= shifted threshold).

    Compared on a linear scale: log10|C| < log10 b + b0/20  <=>  |C| < b 10^(b0/20),
    which needs no logarithm of zero.
    """
    c = finite_coeffs(coeffs_um)
    level = cut_level_um(threshold_um, b0_db)
    if level.shape != c.shape:
        raise CodecError("one threshold per coefficient is needed")
    return np.abs(c) >= level


def apply_cut(coeffs_um: np.ndarray, keep: np.ndarray) -> np.ndarray:
    return np.where(keep, np.asarray(coeffs_um, dtype=np.float64), 0.0)


# ---------------------------------------------------------------- threshold-shaped quantizer
# Delta_k = G b(f_k), G = 10^(g/20): the error of every component is shaped along the detection
# threshold, as an audio codec shapes its noise under the masking curve. Components far below
# the threshold quantize to 0 on their own. Dead zone and reconstruction points (chosen by
# measurement, docs/stream-format.md "Threshold-shaped quantizer"):
#   q_k  = sign(C_k) floor(|C_k| / Delta_k + SHAPED_RHO)
#   C'_k = sign(q_k) (|q_k| - SHAPED_DELTA) Delta_k      (0 when q_k = 0)
SHAPED_RHO = 0.5
SHAPED_DELTA = 0.0
G_UNIT_DB = 0.25  # the knob g is stored in quarter-dB steps
G_MIN_DB = -200.0  # nm-scale profiles (opdx-3: largest |C_k| / b_k = -56 dB) need g far below 0
G_MAX_DB = 120.0


def check_g_db(g_db: float) -> float:
    """g must be finite, within G_MIN_DB..G_MAX_DB and a multiple of 0.25 dB."""
    if isinstance(g_db, bool) or not math.isfinite(g_db):
        raise CodecError(f"--g-db must be a finite number of dB, got {g_db!r}")
    units = round(g_db / G_UNIT_DB)
    if units * G_UNIT_DB != g_db:
        raise CodecError(f"--g-db must be a multiple of {G_UNIT_DB} dB, got {g_db}")
    if not G_MIN_DB <= g_db <= G_MAX_DB:
        raise CodecError(f"--g-db must be within {G_MIN_DB:g}..{G_MAX_DB:g} dB, got {g_db}")
    return float(g_db)


def shaped_steps(threshold_um: np.ndarray, g_db: float) -> np.ndarray:
    """Delta_k = 10^(g/20) b(f_k), µm."""
    return np.multiply(np.asarray(threshold_um, dtype=np.float64), db_to_ratio(check_g_db(g_db)))


def shaped_quantize(coeffs_um: np.ndarray, threshold_um: np.ndarray, g_db: float) -> np.ndarray:
    """Integer indices q_k of the threshold-shaped quantizer (int64)."""
    c = finite_coeffs(coeffs_um)
    step = shaped_steps(threshold_um, g_db)
    if step.shape != c.shape:
        raise CodecError("one threshold per coefficient is needed")
    mag = np.floor(np.add(np.divide(np.abs(c), step), SHAPED_RHO))
    if np.any(mag >= float(1 << 40)):
        raise CodecError(f"g = {g_db} dB is too fine for these amplitudes: raise --g-db")
    q = mag.astype(np.int64)
    return np.where(c < 0, -q, q)


def shaped_values(q: np.ndarray, threshold_um: np.ndarray, g_db: float) -> np.ndarray:
    """C'_k from indices: sign(q) (|q| - SHAPED_DELTA) Delta_k."""
    q = np.asarray(q, dtype=np.int64)
    step = shaped_steps(threshold_um, g_db)
    mag = np.multiply(np.subtract(np.abs(q).astype(np.float64), SHAPED_DELTA), step)
    return np.where(q < 0, -mag, np.where(q == 0, 0.0, mag))
