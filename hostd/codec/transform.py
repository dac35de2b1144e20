"""DCT-II amplitude spectrum of a height profile, its frequencies, and the band-limited inverse.

Conventions (see docs/conventions.md):
    C_k  = (2/N) sum_n y_n cos(pi k (2n+1) / (2N))        amplitude of the k-th cosine
    f_k  = k v / (2 L)                                      k half-cycles over the patch length L
    y'_n = sum_{k=1..N'} C'_k cos(pi k (2n+1) / (2N))       C_0 (DC) dropped
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hostd import pocketfft
from hostd.errors import CodecError

MAX_SAMPLES = 1 << 22
# Round-off tolerance (issue 23, docs/conventions.md "Round-off"): an amplitude with
# |C_k| <= 2^-ROUNDOFF_LOG2 * max_n |y_n| is exactly 0. The FFT-based DCT's round-off is of
# order eps log2(N) max|y| (<= 5e-15 max|y| for N <= 2^22; measured <= 2e-16 on constant
# profiles of odd length, where every true C_k, k >= 1, is 0); 2^-43 = 1.1e-13 is 20x above
# that bound, and a component of 1e-13 of the profile's height (0.1 pm on a 1 mm profile) is
# below any display's resolution. Relative, so heights x 1e-300 or x 1e150 behave alike.
ROUNDOFF_LOG2 = 43


@dataclass(frozen=True)
class Geometry:
    """A texture patch: N samples over length_mm, played at speed_mm_s, band-limited at fmax_hz."""

    n: int
    length_mm: float
    speed_mm_s: float = 50.0
    fmax_hz: float = 400.0

    def __post_init__(self) -> None:
        if not (2 <= self.n <= MAX_SAMPLES):
            raise CodecError(f"a patch needs 2 to {MAX_SAMPLES} samples, got {self.n}")
        for name in ("length_mm", "speed_mm_s", "fmax_hz"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise CodecError(f"{name} must be a finite number > 0, got {v}")

    @property
    def spacing_um(self) -> float:
        return self.length_mm * 1000.0 / self.n

    @property
    def n_keep(self) -> int:
        """N': the largest k with f_k <= fmax at the reference speed; must be 1..N-1."""
        k = n_keep_for(self.length_mm, self.speed_mm_s, self.fmax_hz)
        if k < 1:
            raise CodecError(
                f"fmax {self.fmax_hz} Hz is below the first component "
                f"({self.speed_mm_s / (2 * self.length_mm):.4g} Hz at {self.speed_mm_s} mm/s over "
                f"{self.length_mm:.4g} mm): the patch is too short for this speed; check --x-unit (is x "
                f"really in that unit?), lower --ref-speed-mm-s, or raise --length-mm / --fmax-hz"
            )
        if k >= self.n:
            raise CodecError(
                f"fmax {self.fmax_hz:g} Hz asks for N' = {k if k < 10**9 else f'{float(k):.3g}'} "
                f"components at {self.speed_mm_s:g} mm/s but the patch has only N = {self.n} samples "
                f"(N' must be < N; spacing {self.spacing_um:.4g} µm): check --x-unit (is x really in "
                "that unit?), or lower --fmax-hz, raise --ref-speed-mm-s or sample more finely"
            )
        return k

    def frequencies_hz(self, n_keep: int | None = None) -> np.ndarray:
        k = np.arange(1, (self.n_keep if n_keep is None else n_keep) + 1, dtype=np.float64)
        return frequencies_hz(k, self.length_mm, self.speed_mm_s)


def frequencies_hz(k: np.ndarray, length_mm: float, speed_mm_s: float) -> np.ndarray:
    """f_k = k v / (2 L): index k of a DCT-II has k half-cycles over the patch."""
    return np.asarray(k, dtype=np.float64) * (speed_mm_s / (2.0 * length_mm))


def n_keep_for(length_mm: float, speed_mm_s: float, fmax_hz: float) -> int:
    """Largest k with k v / (2L) <= fmax (a relative 1e-12 slack absorbs rounding of exact ratios)."""
    return math.floor(2.0 * length_mm * fmax_hz / speed_mm_s * (1.0 + 1e-12))


def amplitudes(y_um: np.ndarray) -> np.ndarray:
    """All N DCT-II amplitudes C_0..C_{N-1} = (2/N) sum_n y_n cos(pi k (2n+1)/(2N))."""
    y = _checked_profile(y_um)
    return roundoff_to_zero(pocketfft.dct(y, type=2) / y.size, y)


def roundoff_to_zero(c: np.ndarray, y: np.ndarray) -> np.ndarray:
    """c with every |C_k| <= 2^-ROUNDOFF_LOG2 max|y| set to 0 (the DCT's round-off, not signal)."""
    floor_um = math.ldexp(float(np.max(np.abs(y))), -ROUNDOFF_LOG2)  # exact: a power of two
    return np.where(np.abs(c) <= floor_um, 0.0, c)


def _checked_profile(y_um: np.ndarray) -> np.ndarray:
    y = np.asarray(y_um, dtype=np.float64)
    if y.ndim != 1 or y.size < 2:
        raise CodecError("a profile must be a 1-D array of at least 2 heights")
    if not np.all(np.isfinite(y)):
        raise CodecError("the profile contains NaN or Inf heights; clean the input file")
    return y


def analyze(y_um: np.ndarray, n_keep: int) -> np.ndarray:
    """C_1..C_N' of a profile (DC dropped): amplitudes(y)[1 : N' + 1], the same bits, with the
    division by N done on the N' kept values only; round-off-level amplitudes are 0
    (`roundoff_to_zero`)."""
    n = np.asarray(y_um).size
    if not (1 <= n_keep < n):
        raise CodecError(f"N' must be in 1..N-1 = 1..{n - 1}, got {n_keep}")
    y = _checked_profile(y_um)
    return roundoff_to_zero(pocketfft.dct(y, type=2)[1 : n_keep + 1] / n, y)


def synthesize(coeffs_um: np.ndarray, n: int) -> np.ndarray:
    """y'_n = sum_{k=1..N'} C'_k cos(pi k (2n+1)/(2N)), n = 0..N-1, through a DCT-III."""
    c = np.asarray(coeffs_um, dtype=np.float64)
    if c.ndim != 1 or not (1 <= c.size < n):
        raise CodecError(f"need 1..N-1 coefficients for N = {n}, got {c.size}")
    full = np.zeros(n, dtype=np.float64)
    # scipy's unnormalized DCT-III is x_0 + 2 sum_{k>=1} x_k cos(...); x_0 = 0 here. The factor
    # 1/2 is applied to the N' inputs instead of the N outputs (a power of two: the same bits)
    # and the DCT works in place: one N-point array allocated in all.
    np.multiply(c, 0.5, out=full[1 : c.size + 1])
    return pocketfft.dct(full, type=3, overwrite_x=True)


def direct_amplitudes(y_um: np.ndarray, k: np.ndarray) -> np.ndarray:
    """O(N K) reference of C_k, for tests and as executable documentation."""
    y = np.asarray(y_um, dtype=np.float64)
    n = y.size
    idx = 2 * np.arange(n) + 1
    return np.array([2.0 / n * np.sum(y * np.cos(np.pi * kk * idx / (2 * n))) for kk in k])


def direct_synthesis(coeffs_um: np.ndarray, n: int) -> np.ndarray:
    """O(N N') reference of y'_n, for tests."""
    c = np.asarray(coeffs_um, dtype=np.float64)
    idx = 2 * np.arange(n) + 1
    out = np.zeros(n)
    for k, ck in enumerate(c, start=1):
        out += ck * np.cos(np.pi * k * idx / (2 * n))
    return out
