"""Rate control: the smallest stream whose Iobj does not exceed a target.

Candidates span both methods and their parameters: quantization with L = 2..MAX_L levels, and
threshold-cut for b0 on a 0.5 dB grid, with survivors exact (float64) or on 8/16/32-bit grids,
plus a keep-everything cut. Each candidate is encoded for real and its decoded coefficients
scored, so the reported bytes and Iobj are those of the stream that is written.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from hostd.codec import stream as vtx
from hostd.codec import transform
from hostd.codec.methods import db_to_ratio
from hostd.errors import CodecError
from hostd.perception import indices
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
