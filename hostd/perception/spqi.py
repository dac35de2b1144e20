"""SPQI, the Spectral Perceptual Quality Index (Hassen & Steinbach), implemented in hostd.

Rate control certifies its streams with SPQI (hostd.codec.ratecontrol), so it must always be
available, not only with the optional `vibromaf` package. This is an independent
implementation of vibromaf's definition (tests/test_spqi.py: equal to vibromaf's `spqi()` to
1e-12 on many signals), written from the definition:

- Both signals (1-D, sampled at 8 kHz) are cut into blocks of B = 512 samples (a trailing
  partial block is dropped); a distorted signal longer than the reference is truncated to the
  reference's length, a shorter one is refused; identical signals score exactly 1.
- Per block, the orthonormal DCT-II X_i, i = 0..B-1, and its perceptual power
  p_i = X_i^2 10^(-T(f_i)/10) at f_i = i fs / (2B - 1) (vibromaf's frequency grid), with the
  vibrotactile threshold T(f) = |62 / log10(c)^2 · log10(f/550 + c)^2| - 77 dB, c = 1 - 250/550,
  held at its value at the first grid frequency where it is above 0 dB (about 800 Hz).
- Per block, D = 10 log10( Σ_i |p_i(ref) - p_i(dist)| / (Σ_i p_i(ref) + ε) ) dB, ε = 2^-52
  (the float64 epsilon vibromaf adds), and the block score (1 - tanh(η D - θ)) / 2 with
  η = 0.3 and θ = -2 (vibromaf's defaults); a block with no difference scores 1.
- SPQI = the mean of the block scores (1 = identical, towards 0 = very different).

Range and the one deliberate difference: both signals are scaled by the one power of two
(exact) that brings the reference's peak into [0.5, 1) before squaring, and ε is added at
that scale. So SPQI is scale-invariant over the float64 range (heights of 1e-300 or 1e150 µm
score as at 1 µm, instead of overflowing to NaN or of ε swamping every difference), and it
equals vibromaf's exactly when the reference's peak is in [0.5, 1). At other scales vibromaf
adds ε to the unscaled sums, which matters only where Σ p(ref) of a block is within ~1e12 ε
of the peak's scale: (nearly) silent reference blocks, or signals below ~1e-5 overall, where
vibromaf's score tends to 1 whatever the distortion. The reference's half (its block powers) is
computed once per reference (`Reference`), since rate control scores many candidates
against one original.

Not bit-exact across CPUs: the DCT is an FFT (pocketfft), whose last bit may depend on the
SIMD width; a candidate whose SPQI lies within ~1e-15 of the 0.9 criterion could be judged
differently on another machine (the Iobj decisions are exact; see docs/conventions.md).
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from hostd import pocketfft
from hostd.errors import QualityError
from hostd.perception.indices import pow2_scale

BLOCK = 512
FS_HZ = 8000.0
ETA = 0.3  # slope of the mapping from spectral difference (dB) to score
THETA = -2.0  # its offset (vibromaf calls it `threshold`)
EPS = float(np.finfo(np.float64).eps)
CRITERION = 0.9  # SPQI the default rate control guarantees (hostd.codec.ratecontrol)

# the vibrotactile threshold curve T(f) of the model (vibromaf's PerceptualThreshold defaults)
_X_SCALE_DB = 62.0
_F_SCALE_HZ = 550.0
_C = 1.0 - 250.0 / 550.0
_Y_OFFSET_DB = 77.0


@lru_cache(maxsize=4)
def _weights(block: int, fs_hz: float) -> np.ndarray:
    """10^(-T(f_i)/10) on the block's frequency grid f_i = i fs / (2B - 1)."""
    f = np.arange(block, dtype=np.float64) * (fs_hz / (2 * block - 1))
    t = np.abs(_X_SCALE_DB / math.log10(_C) ** 2 * np.log10(f / _F_SCALE_HZ + _C) ** 2) - _Y_OFFSET_DB
    above = np.flatnonzero(t > 0.0)
    first = int(above[0]) if above.size else 0
    t[first:] = t[first]
    w = np.power(10.0, -t / 10.0)
    w.flags.writeable = False
    return w


def _as_signal(x: np.ndarray, name: str) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    if a.ndim != 1:
        raise QualityError(f"SPQI needs 1-D signals; the {name} has shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise QualityError(f"the {name} signal contains NaN or Inf; SPQI needs finite samples")
    return a


def _block_powers(x: np.ndarray, scale: float, n_blocks: int, w: np.ndarray) -> np.ndarray:
    blocks = (x[: n_blocks * BLOCK] * scale).reshape(n_blocks, BLOCK)
    X = pocketfft.dct(blocks, type=2, norm="ortho", axis=1)
    return np.multiply(np.multiply(X, X), w)


class Reference:
    """The reference's half of SPQI, computed once: its block powers and their sums."""

    def __init__(self, reference: np.ndarray, *, eta: float = ETA, theta: float = THETA):
        ref = _as_signal(reference, "reference")
        if ref.size < BLOCK:
            raise QualityError(f"SPQI needs at least {BLOCK} samples, the reference has {ref.size}")
        self.signal = ref
        self.eta, self.theta = float(eta), float(theta)
        self.n_blocks = ref.size // BLOCK
        self.scale = pow2_scale(ref)  # exact: the reference's peak into [0.5, 1)
        self._w = _weights(BLOCK, FS_HZ)
        self._p = _block_powers(ref, self.scale, self.n_blocks, self._w)
        self._den = self._p.sum(axis=1) + EPS  # ε at the normalized scale (see the docstring)

    def score(self, distorted: np.ndarray) -> float:
        """SPQI of `distorted` against this reference (vibromaf's spqi(distorted, reference))."""
        d = _as_signal(distorted, "distorted")
        if d.size < self.signal.size:
            raise QualityError(f"the distorted signal ({d.size} samples) must not be shorter "
                               f"than the reference ({self.signal.size})")
        d = d[: self.signal.size]
        if np.array_equal(d, self.signal):
            return 1.0
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            pd = _block_powers(d, self.scale, self.n_blocks, self._w)
            diff = np.abs(self._p - pd).sum(axis=1)
            ratio = diff / self._den
            scores = np.where(ratio > 0.0,
                              (1.0 - np.tanh(self.eta * (10.0 * np.log10(np.where(ratio > 0.0, ratio, 1.0)))
                                             - self.theta)) / 2.0,
                              1.0)
        if not np.all(np.isfinite(scores)):
            raise QualityError("SPQI is not finite for this signal pair (NaN in a block spectrum)")
        return float(np.mean(scores))


def spqi(distorted: np.ndarray, reference: np.ndarray, *, eta: float = ETA, theta: float = THETA) -> float:
    """SPQI of a distorted signal against a reference (both 1-D, 8 kHz; argument order as
    vibromaf's `spqi(distorted, reference)`). For many candidates of one reference, build a
    `Reference` once and call its `score`."""
    return Reference(reference, eta=eta, theta=theta).score(distorted)
