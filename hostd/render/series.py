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

import functools
import importlib.util
import math
import threading

import numpy as np

from hostd.render import fastrender


def phase_rad(x_mm, n: int, length_mm: float) -> np.ndarray:
    """theta(x) = pi (x/dx + 1/2) / N in rad, x (mm) reduced to one period 2L first (in float64,
    so that a hand far from the origin keeps full phase precision)."""
    x = np.asarray(x_mm, dtype=np.float64)
    if x.ndim == 1 and x.size <= 32:
        # a real-time batch (3 samples): the same operations in Python floats (IEEE doubles;
        # % is np.mod's floored remainder), cheaper than four numpy calls
        two_l, dx, k = 2.0 * length_mm, length_mm / n, np.pi / n
        return np.array([((v % two_l) / dx + 0.5) * k for v in x.tolist()], dtype=np.float64)
    x = np.mod(x, 2.0 * length_mm)
    return (x / (length_mm / n) + 0.5) * (np.pi / n)


NUFFT_EPS = 1e-14  # relative tolerance of the nonuniform FFTs (finufft), near float64 rounding


def _nufft_sums(theta: np.ndarray, w: np.ndarray, kmax: int) -> np.ndarray:
    """sum_i w_i exp(i k theta_i) for k = 0..kmax: one type-1 nonuniform FFT (finufft, one
    thread: the offline benchmarks charge the calling thread's CPU time), O(S + K log K)."""
    from hostd.extras import need

    finufft = need("finufft", "sim", "the scene simulator's series fit")

    f = finufft.nufft1d1(theta, np.asarray(w, dtype=np.complex128), 2 * kmax + 1, eps=NUFFT_EPS,
                         isign=1, nthreads=1)  # modes -kmax..kmax
    return f[kmax:]


try:  # the `sim` extra; a finder that refuses the name counts as absent
    _HAVE_FINUFFT = importlib.util.find_spec("finufft") is not None
except ImportError:
    _HAVE_FINUFFT = False
NUFFT_MIN_TERMS = 16384  # evaluate by the cosine matrix below this many (sample, component) terms
TRIM_MIN_TERMS = 2048  # from this many terms, trailing zero coefficients are trimmed first
_plans = threading.local()  # type-2 NUFFT plans of this thread, by mode count (reused across calls)


def _type2_plan(kmax: int):
    """A type-2 NUFFT plan for modes -M..M, M = kmax rounded up to a power of two (so that a few
    plans serve every truncation of one series), cached per thread."""
    import finufft

    m = 1 << max(4, (kmax - 1).bit_length())
    cache = _plans.__dict__.setdefault("by_m", {})
    plan = cache.get(m)
    if plan is None:
        if len(cache) >= 8:
            cache.pop(next(iter(cache)))
        plan = cache[m] = finufft.Plan(2, (2 * m + 1,), eps=NUFFT_EPS, isign=1, nthreads=1)
    return plan, m


@functools.lru_cache(maxsize=64)
def _orders(k0: int, count: int, dtype: str) -> np.ndarray:
    """k0, k0 + 1, ..., k0 + count - 1 as floats (read-only; cached for the real-time path)."""
    k = np.arange(k0, k0 + count, dtype=dtype)
    k.flags.writeable = False
    return k


SMALL_BATCH = 32  # float64 phases at or below this many (a real-time batch): Clenshaw


def clenshaw_py(coeffs, theta, k0: int = 1) -> np.ndarray:
    """The real-time batch's sum, the reference: sum_j coeffs[j] cos((k0 + j) theta_i), k0 >= 1, by
    Clenshaw's recurrence in Reinsch's form, from the last non-zero component down to k = 1, one
    phase at a time in IEEE doubles.

    Clenshaw: b_k = c_k + 2 cos(theta) b_(k+1) - b_(k+2), sum = b_1 cos(theta) - b_2. Near theta = 0
    or pi, 2 cos(theta) rounds to nearly +-2 and the phase it carries is lost (an error growing
    with K^2: 1e-9 of sum |c_k| at K = 16 000 for a lone top component, theta = 1/K). Reinsch's
    form carries the differences d_k = b_k -+ b_(k+1) instead and the small u = 2 cos(theta) -+ 2,
    computed from sin(theta/2)^2 (cos(theta) >= 0) or cos(theta/2)^2 (< 0), which keeps its
    relative precision: d_k = c_k + u b_(k+1) +- d_(k+1), b_k = d_k +- b_(k+1), and
    sum = +-d_1 + (u/2) b_1. Error (tests/test_render.py), up to K = 16 000 at any phase: below 1e-14
    of sum |c_k| for a texture's decaying spectrum, 1e-12 for a lone top component; one step of a
    16-bit DAC is 3e-5 of full scale.

    Why a recurrence and not the cosine matrix: its result is defined by its operations alone
    (two libm calls per phase, then multiplies and adds in a fixed order), so the compiled version
    (hostd/render/render_core.h: the same operations, no FMA) gives the same samples bit for bit;
    numpy's vectorized cosine and its matrix product round differently with the SIMD width and
    the BLAS kernel."""
    c = np.asarray(coeffs, dtype=np.float64)
    nz = np.flatnonzero(c)
    # components k0-1 .. 1 below the first coefficient are zero: the recurrence runs over them too
    cl = c[: nz[-1] + 1].tolist()[::-1] + [0.0] * (int(k0) - 1) if nz.size else []
    out = []
    for t in np.asarray(theta, dtype=np.float64).tolist():
        if not math.isfinite(t):  # no phase: no height (the output stage holds its last value)
            out.append(math.nan)
            continue
        b = d = 0.0
        if math.cos(t) >= 0.0:  # theta near 0 (mod 2 pi): d_k = b_k - b_(k+1)
            h = math.sin(0.5 * t)
            u = -4.0 * (h * h)
            for ck in cl:
                d = ck + u * b + d
                b = d + b
            out.append(d + 0.5 * u * b)
        else:  # theta near pi: d_k = b_k + b_(k+1)
            h = math.cos(0.5 * t)
            u = 4.0 * (h * h)
            for ck in cl:
                d = ck + u * b - d
                b = d - b
            out.append(0.5 * u * b - d)
    return np.array(out, dtype=np.float64)


def clenshaw(coeffs, theta, k0: int = 1) -> np.ndarray:
    """clenshaw_py's values, compiled (hostd/render/_fastrender.c) when it is built."""
    _C = fastrender._C
    if _C is not None:
        c = np.ascontiguousarray(coeffs, dtype=np.float64)
        th = np.ascontiguousarray(theta, dtype=np.float64)
        if c.ndim == 1 and th.ndim == 1 and k0 >= 1:
            out = np.empty(th.size, dtype=np.float64)
            _C.clenshaw(c, th, out, int(k0))
            return out
    return clenshaw_py(coeffs, theta, k0)


def evaluate(coeffs: np.ndarray, theta: np.ndarray, k0: int = 1) -> np.ndarray:
    """sum_j coeffs[j] cos((k0 + j) theta) at arbitrary phases, in theta's float type.

    A real-time batch (<= SMALL_BATCH float64 phases): Clenshaw's recurrence (`clenshaw`, the
    same samples compiled or not). Few terms otherwise: the len(theta) x K cosine matrix. Many
    (the scene simulator, the fits' intended signal): one type-2 nonuniform FFT (finufft;
    float64), O(len(theta) + K log K), with a plan reused across calls. All agree to float
    rounding. Trailing zero coefficients (components past the speed's band) are left out of
    the sum when that saves more than it costs.
    """
    c = np.asarray(coeffs)
    th = np.asarray(theta)
    if th.dtype != np.float32 and th.dtype != np.float64:
        th = th.astype(np.float64)
    if th.dtype == np.float64 and th.ndim == 1 and th.size <= SMALL_BATCH and k0 >= 1 \
            and c.dtype == np.float64 and c.ndim == 1:
        return clenshaw(c, th, k0)
    if th.size * c.size >= TRIM_MIN_TERMS:
        nz = np.flatnonzero(c)
        c = c[: nz[-1] + 1 if nz.size else 0]
    if th.size * c.size < NUFFT_MIN_TERMS or th.dtype == np.float32:
        k = _orders(k0, c.size, th.dtype.char)
        return np.cos(np.multiply.outer(th, k)) @ c.astype(th.dtype, copy=False)
    if not _HAVE_FINUFFT:  # a daemon-only install (no `sim` extra): the same sum, in blocks
        k = _orders(k0, c.size, th.dtype.char)
        flat = np.ravel(th)
        step = max(1, (1 << 20) // max(c.size, 1))
        out = np.concatenate([np.cos(np.multiply.outer(flat[i : i + step], k)) @ c
                              for i in range(0, flat.size, step)]) if flat.size else flat.copy()
        return out.reshape(th.shape)
    plan, m = _type2_plan(k0 + c.size - 1)
    modes = np.zeros(2 * m + 1, dtype=np.complex128)  # modes -m..m; Re(c_k e^{ik theta}) = c_k cos
    modes[m + k0 : m + k0 + c.size] = c
    plan.setpts(np.mod(np.ravel(th), 2.0 * np.pi))
    return np.real(plan.execute(modes)).reshape(th.shape)


def evaluate_faded(coeffs: np.ndarray, theta: np.ndarray, speed: np.ndarray, f_pass: float,
                   f_stop: float, gain, k0: int = 1) -> np.ndarray:
    """sum_j g((k0 + j) s_i) coeffs[j] cos((k0 + j) theta_i), with a per-sample scale s_i >= 0
    (speed / 2L: component k sounds at f = k s_i) and a gain g(f) that is 1 for f <= f_pass, 0
    for f >= f_stop, and gain(k, s) (vectorized over s) between. Exact (no speed buckets).

    Horner's rule on z_i = exp(i theta_i) from the top component down, over the samples sorted
    by s: at component k only the samples with k s_i < f_stop are still active (a prefix), so
    the work is sum_i min(K, f_stop / s_i), not S x K.
    """
    c = np.asarray(coeffs, dtype=np.float64)
    th = np.asarray(theta, dtype=np.float64)
    s = np.abs(np.asarray(speed, dtype=np.float64))
    order = np.argsort(s, kind="stable")
    ss = s[order]
    z = np.exp(1j * th[order])
    acc = np.zeros(z.shape, dtype=np.complex128)
    for j in range(c.size - 1, -1, -1):
        k = k0 + j
        n_on = int(np.searchsorted(ss, f_stop / k, side="left"))  # k s < f_stop
        if n_on == 0:
            continue
        n_full = int(np.searchsorted(ss, f_pass / k, side="right"))  # k s <= f_pass
        a = acc[:n_on]
        a *= z[:n_on]
        a[:n_full] += c[j]
        if n_full < n_on:
            a[n_full:] += c[j] * gain(k, ss[n_full:n_on])
    out = np.empty(th.shape)
    out[order] = np.real(acc * z**k0)
    return out


@functools.lru_cache(maxsize=8)
def _czt(n: int, count: int, dtheta: float) -> _Czt:
    """The chirp-z transform sum_j x_j w^(m j), w = exp(i dtheta): its chirps and their FFT are
    built once per (size, count, step) and reused (a sweep synthesizes many signals alike)."""
    return _Czt(n, count, np.exp(1j * dtheta))


class _Czt:
    """scipy.signal.CZT(n, m, w, a=1.0), operation for operation (the same bits,
    tests/test_lean.py), on scipy.fft's transforms alone (hostd.pocketfft): importing
    scipy.signal costs a command line call such as `hostd encode --target-iobj` (its SPQI check
    plays the signal through here) more CPU than all its work. Bluestein's algorithm: the
    chirps and their FFT are made once; a call is one FFT of the input, one product and one
    inverse FFT."""

    def __init__(self, n: int, m: int, w: complex) -> None:
        from hostd.pocketfft import fft, next_fast_len

        if n < 1 or m < 1:
            raise ValueError(f"chirp-z transform of {n} points to {m}: both must be >= 1")
        k = np.arange(max(m, n), dtype=np.min_scalar_type(-max(m, n) ** 2))
        wk2 = w ** (k**2 / 2.0)
        a = 1.0
        self.n = n
        self._nfft = next_fast_len(n + m - 1)
        self._Awk2 = a ** -k[:n] * wk2[:n]
        self._Fwk2 = fft(1 / np.hstack((wk2[n - 1 : 0 : -1], wk2[:m])), self._nfft)
        self._wk2 = wk2[:m]
        self._yidx = slice(n - 1, n + m - 1)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """The transform along the last axis."""
        from hostd.pocketfft import fft, ifft

        x = np.asarray(x)
        if x.shape[-1] != self.n:
            raise ValueError(f"chirp-z transform defined for length {self.n}, not {x.shape[-1]}")
        y = ifft(self._Fwk2 * fft(x * self._Awk2, self._nfft))
        return y[..., self._yidx] * self._wk2


def evaluate_uniform(coeffs: np.ndarray, theta0: float, dtheta: float, count: int,
                     k0: int = 1) -> np.ndarray:
    """sum_j coeffs[j] cos((k0 + j)(theta0 + m dtheta)) for m = 0..count-1: a hand at constant
    speed, sampled at a constant rate. One chirp-z transform (FFT-based,
    O((count + K) log(count + K))) instead of a count x K cosine matrix."""
    c = np.asarray(coeffs, dtype=np.float64)
    k = np.arange(k0, k0 + c.size, dtype=np.float64)
    x = c * np.exp(1j * (k - k0) * theta0)
    y = _czt(c.size, int(count), float(dtheta))(x)  # sum_j x_j w^(m j)
    m = np.arange(count, dtype=np.float64)
    return np.real(y * np.exp(1j * k0 * (theta0 + m * dtheta)))


class Projector:
    """Least-squares fits y ~ sum_k c_k cos(k theta), k = 0..K (K = n_keep), at fixed phases.

    The normal equations come from nonuniform Fourier sums of the phases and of the data
    (type-1 NUFFTs): with m_d = sum_i cos(d theta_i) (d = 0..2K) and r_k = sum_i y_i cos(k theta_i),
    G_jk = (m_|j-k| + m_(j+k)) / 2 (Toeplitz + Hankel) and G c = r. That is O(S + K log K) for
    the sums, not an S x K basis and its O(S K^2) Gram product. G depends only on the phases:
    it is factored once (Cholesky, O(K^3)) and `fit` reuses the factor for every y (the runs of
    one scene report that deliver at the same instants share it). When the phases do not cover
    the period (G singular): the minimum-norm solution, from one eigendecomposition of G.
    """

    def __init__(self, theta: np.ndarray, n_keep: int) -> None:
        import scipy.linalg

        self.theta = np.asarray(theta, dtype=np.float64)
        self.n_keep = K = int(n_keep)
        m = _nufft_sums(self.theta, np.ones(self.theta.size), 2 * K).real
        j = np.arange(K + 1)
        gram = scipy.linalg.toeplitz(m[: K + 1])
        gram += m[j[:, None] + j[None, :]]
        gram *= 0.5
        self._eig = None
        try:
            self._cho = scipy.linalg.cho_factor(gram, overwrite_a=True)
        except np.linalg.LinAlgError:
            # singular (the phases do not cover the period): the minimum-norm least-squares
            # solution, as np.linalg.lstsq(G, r) gives it (same cutoff on G's singular values,
            # which are |eigenvalues| here), from one eigendecomposition shared by every fit
            self._cho = None
            gram = 0.5 * (scipy.linalg.toeplitz(m[: K + 1]) + m[j[:, None] + j[None, :]])
            lam, vec = scipy.linalg.eigh(gram)
            cutoff = np.finfo(np.float64).eps * (K + 1) * np.abs(lam).max()
            keep = np.abs(lam) > cutoff
            self._eig = (vec[:, keep], 1.0 / lam[keep])

    @property
    def nbytes(self) -> int:
        return (self.n_keep + 1) ** 2 * 8 + self.theta.nbytes

    def fit(self, y: np.ndarray) -> np.ndarray:
        """c_0..c_K for samples y at the projector's phases."""
        r = _nufft_sums(self.theta, np.asarray(y, dtype=np.float64), self.n_keep).real
        if self._cho is not None:
            import scipy.linalg

            return scipy.linalg.cho_solve(self._cho, r)
        vec, inv = self._eig
        return vec @ (inv * (vec.T @ r))


def project(theta: np.ndarray, y: np.ndarray, n_keep: int) -> np.ndarray:
    """Least-squares c_0..c_K (K = n_keep) of y ~ sum_k c_k cos(k theta) at arbitrary phases
    (see Projector; one fit)."""
    return Projector(theta, n_keep).fit(y)
