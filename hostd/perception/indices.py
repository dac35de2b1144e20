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

# What a value of Iobj means. The paper fitted (a, b) by least squares of Iobj against the mean
# subjective dissimilarity of each compressed texture (eq. 13; no intercept), graded 0 "same",
# 1 "probably the same", 2 "probably different", 3 "different": Iobj predicts that grade
# (R^2 = 0.790 over wood and sandpaper with (0.581, 0.464); 0.851 wood alone, 0.883 sandpaper).
GRADES = ("same", "probably the same", "probably different", "different")
IOBJ_LEGEND = ("Iobj: 0 = identical, larger = more degraded. It predicts the paper's mean dissimilarity "
               "grade (0 same, 1 probably the same, 2 probably different, 3 different; R^2 = 0.79 "
               "over wood and sandpaper at (a, b) = (0.581, 0.464)).")


def grade(iobj: float) -> str:
    """The paper's grade nearest to this Iobj (its 0..3 dissimilarity scale), in words."""
    if not math.isfinite(iobj):
        return "undefined"
    return GRADES[min(len(GRADES) - 1, max(0, math.floor(iobj + 0.5)))]  # halves round up



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


# Scaling (issue 23): P = sum (C_k / b_k)^2 over- or underflows float64 long before the
# texture stops making sense as numbers (heights x 1e150 or x 1e-300, thresholds of 1e200 µm
# or 5e-324 µm). The sums are therefore computed on C 2^-s and b 2^t, powers of two chosen
# so the largest weighted term is near 1, and carried as (mantissa, binary exponent) pairs:
# P = ldexp(p, 2 e), A = ldexp(a, e) with e = s + t. Scaling by a power of two is exact in
# float64's normal range, so every term, and the correctly rounded sum, is exactly the
# unscaled one times 2^(-2e) (or 2^-e): where the unscaled computation has no over- or
# underflow the scaled one gives the same bits (stream headers are unchanged). Inputs in that
# safe range are not scaled at all.
_SAFE_LOG2 = 400  # |log2| of b and of the largest |C_k| / b_k inside which no scaling is done


def _log2_exponent(x: float) -> int:
    """e with x = m 2^e, 0.5 <= m < 1 (x > 0, finite; subnormals included)."""
    return math.frexp(x)[1]


def pow2_scale(x: np.ndarray) -> float:
    """2^-e with e the binary exponent of max |x| (1 for an all-zero or empty x): multiplying by
    it is exact (a power of two) and brings the largest value into [0.5, 1)."""
    top = float(np.max(np.abs(x))) if np.size(x) else 0.0
    return math.ldexp(1.0, -_log2_exponent(top)) if top > 0.0 else 1.0


@dataclass(frozen=True)
class WeightedSums:
    """P = ldexp(p, 2 exp) and A = ldexp(a, exp), each mantissa sum correctly rounded."""

    p: np.ndarray
    a: np.ndarray
    exp: int

    @property
    def P(self) -> np.ndarray:
        """P as float64 (inf or a denormal when it does not fit)."""
        with np.errstate(over="ignore", under="ignore"):
            return np.ldexp(self.p, 2 * self.exp)

    @property
    def A(self) -> np.ndarray:
        with np.errstate(over="ignore", under="ignore"):
            return np.ldexp(self.a, self.exp)


def scaled_weights(threshold_um: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """(1/b'^2, 1/b', t) with b' = b 2^t: weights that are finite and nonzero for any b > 0
    (t = 0 when b is inside 2^-400..2^400, so the weights are exactly `weights(b)`)."""
    b = np.asarray(threshold_um, dtype=np.float64)
    _finite("threshold", b)
    if np.any(b <= 0):
        raise QualityError("thresholds must be > 0 µm")
    t = 0
    if b.size:
        lo, hi = float(b.min()), float(b.max())
        if not (2.0 ** -_SAFE_LOG2 <= lo and hi <= 2.0 ** _SAFE_LOG2):
            t = -_log2_exponent(hi)
            b = np.ldexp(b, t)  # max b' in [0.5, 1): exact, also for subnormal b
    w2, w1 = weights(b)
    if not (np.all(np.isfinite(w2)) and np.all(w2 > 0)):
        raise QualityError("the threshold curve spans more than float64 can weigh (its largest and "
                           "smallest value differ by more than 1e300): check its unit (µm peak)")
    return w2, w1, t


def scale_exponent(coeffs_um: np.ndarray, w1: np.ndarray) -> int:
    """s such that max |C_k 2^-s| / b_k is near 1 (0 when no scaling is needed)."""
    c = np.asarray(coeffs_um, dtype=np.float64)
    if c.ndim > 1 and c.size:
        # many variants: the largest |C_k| of each component first (two reductions, no temporary
        # of the variants' size); the scaling below is monotonic, so its maximum is the same
        c = np.maximum(c.max(axis=tuple(range(c.ndim - 1))), -c.min(axis=tuple(range(c.ndim - 1))))
    else:
        c = np.abs(c)
    cmax = float(c.max()) if c.size else 0.0
    if cmax == 0.0:
        return 0
    ec = _log2_exponent(cmax)
    r = float(np.max(np.multiply(np.ldexp(c, -ec), w1)))  # <= max w1: finite
    if r == 0.0:
        return 0
    s = ec + _log2_exponent(r)
    return 0 if abs(s) <= _SAFE_LOG2 // 2 else s


def scaled_sums(coeffs_um: np.ndarray, threshold_um: np.ndarray) -> WeightedSums:
    """P and A of eq. 8, 9 as (mantissa, exponent) pairs, never over- or underflowing.

    A 1-D spectrum is summed with `exact_sum` (the same bits on every CPU); a 2-D array of
    variants takes the BLAS path (~1e-16 relative), with one exponent for all of them.
    """
    c = np.asarray(coeffs_um, dtype=np.float64)
    if c.ndim > 1:  # (NaN and Inf reach the largest and smallest values: no mask of c's size)
        if c.size and not (np.isfinite(c.max()) and np.isfinite(c.min())):
            _finite("coefficients", c)
    else:
        _finite("coefficients", c)
    w2, w1, t = scaled_weights(threshold_um)
    if c.shape[-1] != w1.shape[-1]:
        raise QualityError(f"{c.shape[-1]} coefficients but {w1.shape[-1]} thresholds")
    s = scale_exponent(c, w1)
    if s:
        c = np.ldexp(c, -s)
    if c.ndim > 1:
        # Bulk scoring of many variants (benchmarks, sweeps): BLAS, ~1e-16 relative, and the
        # last bit may depend on the CPU. Nothing written into a stream comes from here. One
        # temporary of the variants' size, used twice (C^2, then |C|).
        tmp = np.multiply(c, c)
        p = tmp @ w2
        a = np.abs(c, out=tmp) @ w1
    else:
        p = exact_sum(np.multiply(np.multiply(c, c), w2))
        a = exact_sum(np.multiply(np.abs(c), w1))
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(a))):
        raise QualityError("weighted sums overflow float64 even after scaling; the coefficients "
                           "span too wide a range")
    return WeightedSums(p, a, s + t)


_NORMAL_MIN = float(np.finfo(np.float64).tiny)


def weighted_sums(coeffs_um: np.ndarray, threshold_um: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """P = sum C_k^2 / b(f_k)^2 and A = sum |C_k| / b(f_k) over the last axis, as float64.

    Terms: (C_k * C_k) * (1/b_k)^2 and |C_k| * (1/b_k), each an elementwise IEEE operation;
    sums of a 1-D spectrum: `exact_sum` (correctly rounded), bit-identical on every CPU; this
    is the path of every stream header and every decoded stream. A 2-D array (many variants
    at once) takes the fast BLAS path instead (equal to ~1e-16 relative).

    The values must fit float64's normal range (a stream header stores them): a sum that
    over- or underflows is refused with a message, never returned as inf or a denormal 0.
    Scores that need no header (`score`, `scores_from_weighted`) use `scaled_sums` instead and
    work for any finite input.
    """
    ws = scaled_sums(coeffs_um, threshold_um)
    P, A = ws.P, ws.A
    big = not (np.all(np.isfinite(P)) and np.all(np.isfinite(A)))
    tiny = np.any((ws.p > 0) & (P < _NORMAL_MIN)) or np.any((ws.a > 0) & (A < _NORMAL_MIN))
    if big or tiny:
        e10 = round((2 * ws.exp + math.log2(float(np.max(ws.p)) or 1.0)) * math.log10(2))
        raise QualityError(
            f"P = sum (C_k/b_k)^2 is about 1e{e10}, {'beyond' if big else 'below'} float64's range, "
            "so a stream header cannot carry it: heights or thresholds are far off the µm scale; "
            "check --y-unit and the threshold curve's unit, or rescale the heights")
    return P, A


def relative_error(x: np.ndarray | float, y: np.ndarray | float) -> np.ndarray:
    """|x - y| / ((x + y) / 2) for x, y >= 0; defined as 0 when both are 0 (never NaN)."""
    return relative_error_scaled(x, 0, y, 0)


_NO_EXP = -(1 << 20)  # the exponent of a zero sum (below every real one)


def relative_error_scaled(xm, xe, ym, ye) -> np.ndarray:
    """The relative error of x = ldexp(xm, xe) and y = ldexp(ym, ye) (x, y >= 0), computed on
    a common power-of-two scale (exact), so it is right whatever the magnitudes: 0 when both
    are 0, 2 when one is 0 (or smaller than the other by more than float64's range)."""
    xm = np.asarray(xm, dtype=np.float64)
    ym = np.asarray(ym, dtype=np.float64)
    _finite("sums", xm)
    _finite("sums", ym)
    if np.any(xm < 0) or np.any(ym < 0):
        raise QualityError("weighted sums must be >= 0")
    ex = np.where(xm > 0, np.frexp(xm)[1].astype(np.int64) + int(xe), _NO_EXP)
    ey = np.where(ym > 0, np.frexp(ym)[1].astype(np.int64) + int(ye), _NO_EXP)
    top = np.maximum(ex, ey)
    top = np.where(top == _NO_EXP, 0, top)  # both zero
    # ldexp takes a C int exponent: shifts beyond float64's range give 0 anyway
    x = np.ldexp(xm, np.clip(int(xe) - top, -2200, 2200).astype(np.int32))
    y = np.ldexp(ym, np.clip(int(ye) - top, -2200, 2200).astype(np.int32))
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
        out = {k: float(getattr(self, k))
               for k in ("P", "A", "P_prime", "A_prime", "Ip", "Ia", "Iobj", "a", "b")}
        for k in ("P", "A", "P_prime", "A_prime"):
            if not math.isfinite(out[k]):
                out[k] = None  # outside float64's range (the indices are still exact: scaled sums)
        return out


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


def scores_from_weighted(ref: WeightedSums, comp: WeightedSums, a: float = DEFAULT_AB[0],
                         b: float = DEFAULT_AB[1]) -> Scores:
    """Ip, Ia, Iobj from scaled sums (`scaled_sums`): exact whatever their magnitude."""
    a, b = check_ab(a, b)
    ip = relative_error_scaled(ref.p, 2 * ref.exp, comp.p, 2 * comp.exp)
    ia = relative_error_scaled(ref.a, ref.exp, comp.a, comp.exp)
    with np.errstate(over="ignore"):
        return Scores(P=np.asarray(ref.P), A=np.asarray(ref.A), P_prime=np.asarray(comp.P),
                      A_prime=np.asarray(comp.A), Ip=ip, Ia=ia, Iobj=a * ip + b * ia, a=a, b=b)


def score(
    reference_um: np.ndarray,
    compressed_um: np.ndarray,
    threshold_um: np.ndarray,
    a: float = DEFAULT_AB[0],
    b: float = DEFAULT_AB[1],
) -> Scores:
    """Score compressed coefficients (shape (N',) or (M, N')) against reference ones (N',).

    The sums are scaled (`scaled_sums`), so heights or thresholds anywhere in float64's range
    give the same indices as at the display's scale; the P, A fields are inf or 0 when the
    sums themselves do not fit float64.
    """
    return scores_from_weighted(scaled_sums(reference_um, threshold_um),
                                scaled_sums(compressed_um, threshold_um), a, b)
