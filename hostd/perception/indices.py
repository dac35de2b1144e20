"""The paper's objective quality indices: P, A (eq. 8, 9), Ip, Ia (eq. 11, 12) and Iobj (eq. 10).

All functions are vectorized: coefficient arrays may carry leading axes (one row per
compressed variant) and the sums are taken over the last axis, k = 1..N'.

The sums P and A travel in stream headers, so they must come out bit-identical on every CPU:
each term is one IEEE operation per element (no fused multiply-add, no SIMD-width-dependent
reduction), and the terms are added with `math.fsum`, which is correctly rounded and so
independent of the order and width of any summation kernel (numpy's dot/sum are not: their
BLAS and SIMD kernels differ per CPU in the last bit). P' and A' of a decoded stream are
computed by the same function, so a lossless stream scores exactly Iobj = 0.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hostd.errors import QualityError

# (a, b) fitted in the paper, Section VI.
PRESETS: dict[str, tuple[float, float]] = {
    "both": (0.581, 0.464),
    "wood": (0.67, 0.44),
    "sandpaper": (0.52, 0.58),
}
DEFAULT_AB = PRESETS["both"]



def _finite(name: str, x: np.ndarray) -> None:
    if not np.all(np.isfinite(x)):
        raise QualityError(f"{name} contains NaN or Inf; the quality index needs finite numbers")


def weights(threshold_um: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(1/b^2, 1/b) for the power and amplitude sums."""
    b = np.asarray(threshold_um, dtype=np.float64)
    _finite("threshold", b)
    if np.any(b <= 0):
        raise QualityError("thresholds must be > 0 µm")
    inv = 1.0 / b
    return inv * inv, inv


def exact_sum(terms: np.ndarray) -> np.ndarray:
    """Correctly rounded sum over the last axis (math.fsum per row): the same bits on every CPU."""
    t = np.asarray(terms, dtype=np.float64)
    try:
        if t.ndim == 1:
            return np.float64(math.fsum(t.tolist()))
        rows = t.reshape(-1, t.shape[-1]).tolist()
        return np.array([math.fsum(r) for r in rows], dtype=np.float64).reshape(t.shape[:-1])
    except OverflowError:
        raise QualityError("a weighted sum overflows float64; the coefficients are too large") from None


def weighted_sums(coeffs_um: np.ndarray, threshold_um: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """P = sum C_k^2 / b(f_k)^2 and A = sum |C_k| / b(f_k) over the last axis.

    Terms: (C_k * C_k) * (1/b_k)^2 and |C_k| * (1/b_k), each an elementwise IEEE operation;
    sums of a 1-D spectrum: `exact_sum` (correctly rounded), bit-identical on every CPU; this
    is the path of every stream header and every decoded stream. A 2-D array (many variants
    at once) takes the fast BLAS path instead (equal to ~1e-16 relative).
    """
    c = np.asarray(coeffs_um, dtype=np.float64)
    _finite("coefficients", c)
    w2, w1 = weights(threshold_um)
    if c.shape[-1] != w1.shape[-1]:
        raise QualityError(f"{c.shape[-1]} coefficients but {w1.shape[-1]} thresholds")
    if c.ndim > 1:
        # Bulk scoring of many variants (benchmarks, sweeps): BLAS, ~1e-16 relative, and the
        # last bit may depend on the CPU. Nothing written into a stream comes from here.
        P, A = np.multiply(c, c) @ w2, np.abs(c) @ w1
    else:
        P = exact_sum(np.multiply(np.multiply(c, c), w2))
        A = exact_sum(np.multiply(np.abs(c), w1))
    if not (np.all(np.isfinite(P)) and np.all(np.isfinite(A))):
        raise QualityError("weighted sums overflow float64; the coefficients are too large")
    return P, A


def relative_error(x: np.ndarray | float, y: np.ndarray | float) -> np.ndarray:
    """|x - y| / ((x + y) / 2) for x, y >= 0; defined as 0 when both are 0 (never NaN)."""
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    _finite("sums", x)
    _finite("sums", y)
    if np.any(x < 0) or np.any(y < 0):
        raise QualityError("weighted sums must be >= 0")
    mean = 0.5 * (x + y)
    diff = np.abs(x - y)
    safe = np.where(mean > 0, mean, 1.0)
    return np.where(mean > 0, diff / safe, 0.0)


@dataclass(frozen=True)
class Scores:
    """The indices of one or many compressed variants against one reference."""

    P: np.ndarray
    A: np.ndarray
    P_prime: np.ndarray
    A_prime: np.ndarray
    Ip: np.ndarray
    Ia: np.ndarray
    Iobj: np.ndarray
    a: float
    b: float

    def as_dict(self) -> dict[str, float]:
        """Scalar fields as plain floats (for a single variant)."""
        return {
            k: float(getattr(self, k))
            for k in ("P", "A", "P_prime", "A_prime", "Ip", "Ia", "Iobj", "a", "b")
        }


def check_ab(a: float, b: float) -> tuple[float, float]:
    if not (np.isfinite(a) and np.isfinite(b)):
        raise QualityError("index coefficients a and b must be finite")
    return float(a), float(b)


def scores_from_sums(
    P: np.ndarray | float,
    A: np.ndarray | float,
    P_prime: np.ndarray | float,
    A_prime: np.ndarray | float,
    a: float = DEFAULT_AB[0],
    b: float = DEFAULT_AB[1],
) -> Scores:
    """Ip, Ia and Iobj = a Ip + b Ia from reference and compressed weighted sums."""
    a, b = check_ab(a, b)
    ip = relative_error(P, P_prime)
    ia = relative_error(A, A_prime)
    return Scores(
        P=np.asarray(P, dtype=np.float64),
        A=np.asarray(A, dtype=np.float64),
        P_prime=np.asarray(P_prime, dtype=np.float64),
        A_prime=np.asarray(A_prime, dtype=np.float64),
        Ip=ip,
        Ia=ia,
        Iobj=a * ip + b * ia,
        a=a,
        b=b,
    )


def score(
    reference_um: np.ndarray,
    compressed_um: np.ndarray,
    threshold_um: np.ndarray,
    a: float = DEFAULT_AB[0],
    b: float = DEFAULT_AB[1],
) -> Scores:
    """Score compressed coefficients (shape (N',) or (M, N')) against reference ones (N',)."""
    P, A = weighted_sums(reference_um, threshold_um)
    Pp, Ap = weighted_sums(compressed_um, threshold_um)
    return scores_from_sums(P, A, Pp, Ap, a, b)
