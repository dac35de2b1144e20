"""The patch's mirror-even cosine series, in one place: its phase convention and fast ways to
evaluate it and to fit it.

A patch of N heights over L mm (spacing dx = L/N) with amplitudes C_k (the DCT-II of
hostd.codec.transform) is the series

    h(x) = sum_k C_k cos(k theta(x)),    theta(x) = pi (x/dx + 1/2) / N  [rad],

which at x = n dx is the DCT-II's cos(pi k (2n+1) / (2N)), and for any real x the mirror-even,
2L-periodic extension of the patch (theta runs over 2 pi per 2L). Every module that evaluates or
fits the series (the renderer, the scene simulator, the peer metrics) uses `phase_rad`.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg
import scipy.signal


def phase_rad(x_mm, n: int, length_mm: float) -> np.ndarray:
    """theta(x) = pi (x/dx + 1/2) / N in rad, x (mm) reduced to one period 2L first (in float64,
    so that a hand far from the origin keeps full phase precision)."""
    x = np.mod(np.asarray(x_mm, dtype=np.float64), 2.0 * length_mm)
    return (x / (length_mm / n) + 0.5) * (np.pi / n)


def evaluate(coeffs: np.ndarray, theta: np.ndarray, k0: int = 1) -> np.ndarray:
    """sum_j coeffs[j] cos((k0 + j) theta) at arbitrary phases, by Horner's rule on
    z = exp(i theta): O(len(theta) * len(coeffs)) time, O(len(theta)) memory."""
    c = np.asarray(coeffs, dtype=np.float64)
    z = np.exp(1j * np.asarray(theta, dtype=np.float64))
    acc = np.zeros(z.shape, dtype=np.complex128)
    for ck in c[::-1]:
        acc = acc * z + ck
    return np.real(acc * z**k0)


def evaluate_uniform(coeffs: np.ndarray, theta0: float, dtheta: float, count: int,
                     k0: int = 1) -> np.ndarray:
    """sum_j coeffs[j] cos((k0 + j)(theta0 + m dtheta)) for m = 0..count-1: a hand at constant
    speed, sampled at a constant rate. One chirp-z transform (FFT-based,
    O((count + K) log(count + K))) instead of a count x K cosine matrix."""
    c = np.asarray(coeffs, dtype=np.float64)
    k = np.arange(k0, k0 + c.size, dtype=np.float64)
    x = c * np.exp(1j * k0 * 0.0 + 1j * (k - k0) * theta0)
    w = np.exp(1j * dtheta)
    y = scipy.signal.czt(x, m=count, w=w, a=1.0)  # sum_j x_j w^(m j)
    m = np.arange(count, dtype=np.float64)
    return np.real(y * np.exp(1j * k0 * (theta0 + m * dtheta)))


def project(theta: np.ndarray, y: np.ndarray, n_keep: int, chunk: int = 64) -> np.ndarray:
    """Least-squares c_0..c_K (K = n_keep) of y ~ sum_k c_k cos(k theta) at arbitrary phases.

    The normal equations come from a nonuniform Fourier transform of the phases and of the
    data: with m_d = sum_i cos(d theta_i) (d = 0..2K) and r_k = sum_i y_i cos(k theta_i),
    G_jk = (m_|j-k| + m_(j+k)) / 2 (Toeplitz + Hankel) and G c = r. That is O(S K) time and
    O(S chunk + K^2) memory, not an S x K basis and its O(S K^2) Gram product. Solved by
    Cholesky (the cosines are nearly orthogonal over many strokes); least squares on G when
    the phases do not cover the period.
    """
    th = np.asarray(theta, dtype=np.float64)
    yy = np.asarray(y, dtype=np.float64)
    K = int(n_keep)
    z = np.exp(1j * th)
    zc = z[:, None] ** np.arange(chunk)  # z^0..z^(chunk-1), S x chunk
    step = z**chunk
    m = np.empty(2 * K + 1)
    r = np.empty(K + 1)
    base = np.ones_like(z)  # z^d0
    for d0 in range(0, 2 * K + 1, chunk):
        w = np.ascontiguousarray((base[:, None] * zc).real)  # cos(d theta_i), S x chunk
        hi = min(chunk, 2 * K + 1 - d0)
        m[d0 : d0 + hi] = w[:, :hi].sum(axis=0)
        if d0 <= K:
            rk = min(chunk, K + 1 - d0)
            r[d0 : d0 + rk] = yy @ w[:, :rk]
        base = base * step
    j = np.arange(K + 1)
    gram = 0.5 * (scipy.linalg.toeplitz(m[: K + 1]) + m[j[:, None] + j[None, :]])
    try:
        return scipy.linalg.cho_solve(scipy.linalg.cho_factor(gram), r)
    except np.linalg.LinAlgError:
        return np.linalg.lstsq(gram, r, rcond=None)[0]
