"""Actuator model and its regularized inverse, as second-order sections at the output rate.

The actuator is modelled as  H(s) = g w0^2 / (s^2 + 2 zeta w0 s + w0^2) · exp(-s tau):
the paper's display (flat to 400 Hz without resonance, -3 dB at 270 Hz) is the default,
zeta = 1/sqrt(2) (Butterworth) at 270 Hz. A measured response table (Hz, gain dB, phase deg)
can replace it: the model is then fitted to the table by least squares (_fit_second_order),
and the table itself is kept so flatness is reported against the measurement.

The equalizer inverts the actuator as the DAC drives it: the actuator behind a zero-order
hold, discretized exactly at the output rate (in closed form, _zoh_second_order), is
G(z) = z^-1 B(z) / A(z) with B of first order (the sampling zero) for the second-order model.
The equalizer is  z G(z)^-1 · R(z) = A(z) / B(z) · R(z), with R a digital Butterworth low-pass
at `reg_hz` of order `reg_order` (>= 2). At the sample instants the chain DAC → actuator →
displacement is then exactly  z^-1 R(z):  one sample of delay (which the renderer's look-ahead
compensates, with R's group delay) times a filter that is flat far into the band. R caps the
gain near fs/2, where the exact inverse would reach about 94 at 3 kHz for the paper's
actuator. The sampling zero must lie inside the unit circle (it does for any corner below
fs/2 with this model); otherwise the design is refused. Designing the inverse in continuous
time and discretizing it (bilinear) instead ignores the hold's droop and delay: 3 % gain
error at 400 Hz, the largest error of the whole chain before this design (docs/rendering.md).
The pure delay tau cannot be inverted; the renderer compensates it by predicting the hand
further ahead.

State is carried across batches. Small batches (the 3-sample, 1 ms frames of the real-time
path) run a scalar transposed direct form II that is bit-compatible with scipy.signal.sosfilt's
state, because a numpy call per section costs more than the arithmetic there.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hostd.render import exactmath as xm

SMALL_BATCH = 32  # at or below this many samples, filter in scalar Python
DENORMAL_GUARD = 1e-30  # µm: filter state below this is flushed to zero
SETTLE_TOL = 1e-9  # Equalizer.settle_samples: the weight of the past left in the state


def _signal():
    """scipy.signal, imported on first use: a process that only reads an equalizer's settings
    (the device-mode pump, hostd encode) does not load it."""
    import scipy.signal

    return scipy.signal


def preload() -> None:
    """Import what designing and running an equalizer needs (scipy.signal) now, not at the first
    texture: a process that will render on the host (the pump, host rendering) pays it up front."""
    _signal()


@dataclass(eq=False)
class ActuatorModel:
    corner_hz: float = 270.0
    damping: float = 1.0 / math.sqrt(2.0)
    dc_gain: float = 1.0
    delay_s: float = 0.0
    name: str = "paper-parametric"
    # measured table (optional): frequencies, gain (dB) and phase (deg)
    table_hz: np.ndarray | None = field(default=None, repr=False)
    table_db: np.ndarray | None = field(default=None, repr=False)
    table_deg: np.ndarray | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        for name in ("corner_hz", "damping", "dc_gain"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"actuator.{name} must be a finite number > 0")
        if not (math.isfinite(self.delay_s) and 0 <= self.delay_s < 0.01):
            raise ValueError("actuator.delay_s must be in [0, 0.01) s")

    def analog_ba(self) -> tuple[np.ndarray, np.ndarray]:
        w0 = 2 * math.pi * self.corner_hz
        return np.array([self.dc_gain * w0 * w0]), np.array([1.0, 2 * self.damping * w0, w0 * w0])

    def response(self, f_hz: np.ndarray) -> np.ndarray:
        """The model's complex response (displacement per command), delay included."""
        f = np.asarray(f_hz, dtype=np.float64)
        h = _model_response(self.corner_hz, self.damping, self.dc_gain, self.delay_s, f.ravel().tolist())
        return np.array(h, dtype=np.complex128).reshape(f.shape)

    def measured(self, f_hz: np.ndarray) -> np.ndarray:
        """The measured table interpolated at f_hz (the model where there is no table)."""
        if self.table_hz is None:
            return self.response(f_hz)
        f = np.asarray(f_hz, dtype=np.float64)
        db = np.interp(f, self.table_hz, self.table_db)
        deg = np.interp(f, self.table_hz, self.table_deg)
        return 10 ** (db / 20) * np.exp(1j * np.deg2rad(deg))

    @classmethod
    def fit_table(cls, f_hz, gain_db, phase_deg, name: str = "measured") -> ActuatorModel:
        f = np.asarray(f_hz, dtype=np.float64)
        db = np.asarray(gain_db, dtype=np.float64)
        deg = np.asarray(phase_deg, dtype=np.float64)
        if not (f.ndim == 1 and f.size >= 4 and f.size == db.size == deg.size):
            raise ValueError("actuator response table needs >= 4 rows of (hz, gain_db, phase_deg)")
        if not (np.all(np.isfinite(f)) and np.all(np.isfinite(db)) and np.all(np.isfinite(deg))):
            raise ValueError("actuator response table has a non-finite value")
        if np.any(f <= 0) or np.any(np.diff(f) <= 0):
            raise ValueError("actuator response table: frequencies must be > 0 and increasing")
        p = _fit_second_order(f.tolist(), db.tolist(), deg.tolist())
        return cls(corner_hz=xm.exp(p[0]), damping=xm.exp(p[1]), dc_gain=xm.exp(p[2]),
                   delay_s=p[3] * 1e-3, name=name, table_hz=f, table_db=db, table_deg=deg)


# bounds of the fit's parameters (log corner, log damping, log dc gain, delay in ms)
_FIT_LO = (-math.inf, xm.log(0.05), -math.inf, 0.0)
_FIT_HI = (math.inf, xm.log(5.0), math.inf, 10.0)


def _model_response(corner_hz: float, damping: float, dc_gain: float, delay_s: float,
                    f_hz: list[float]) -> list[complex]:
    """g w0^2 / (w0^2 - w^2 + 2j zeta w0 w) · exp(-j w tau) at each f (the model of analog_ba, with
    its delay), in Python complex arithmetic: the same bits on every CPU."""
    w0 = 2 * math.pi * corner_hz
    out = []
    for f in f_hz:
        w = 2 * math.pi * f
        h = dc_gain * w0 * w0 / complex(w0 * w0 - w * w, 2 * damping * w0 * w)
        if delay_s:
            sin, cos = xm.sin_cos(w * delay_s)
            h *= complex(cos, -sin)
        out.append(h)
    return out


def _fit_second_order(f_hz: list[float], gain_db: list[float], phase_deg: list[float]) -> list[float]:
    """Least-squares fit of the model to a response table: p = [log corner_hz, log damping,
    log dc_gain, delay_ms] minimizing sum |model / table - 1|^2, by Levenberg-Marquardt with an
    analytic Jacobian, bounds by projection, sums by math.fsum, a 4x4 solve by elimination.
    Hand-written, not scipy.optimize.least_squares: its steps come from LAPACK (QR/SVD), whose
    rounding differs under each OpenBLAS kernel, so the fitted model, hence the equalizer the
    display gets, would differ in the last bits between CPUs; this loop is pure float arithmetic."""
    target = []
    for g_db, ph_deg in zip(gain_db, phase_deg, strict=True):
        mag, (sin, cos) = xm.db_ratio(g_db), xm.sin_cos(math.radians(ph_deg))
        target.append(complex(mag * cos, mag * sin))

    def evaluate(p: list[float]) -> tuple[list[float], list[list[float]]]:
        corner, zeta, delay_s = xm.exp(p[0]), xm.exp(p[1]), p[3] * 1e-3
        w0 = 2 * math.pi * corner
        model = _model_response(corner, zeta, xm.exp(p[2]), delay_s, f_hz)
        re, im, jre, jim = [], [], [], []
        for f, m, t in zip(f_hz, model, target, strict=True):
            w = 2 * math.pi * f
            den = complex(w0 * w0 - w * w, 2 * zeta * w0 * w)
            q = m / t
            re.append(q.real - 1.0)
            im.append(q.imag)
            # d(m/t)/dp = (m/t) · d(log m)/dp
            dlog = (2.0 - complex(2 * w0 * w0, 2 * zeta * w0 * w) / den,
                    -complex(0.0, 2 * zeta * w0 * w) / den, 1.0 + 0j, complex(0.0, -w * 1e-3))
            row = [q * d for d in dlog]
            jre.append([v.real for v in row])
            jim.append([v.imag for v in row])
        return re + im, jre + jim

    db0 = gain_db[0]
    if min(gain_db) < db0 - 3:  # the -3 dB frequency, linearly interpolated on the table
        guess_fc = f_hz[-1]
        for i in range(len(f_hz) - 1):
            f1, g1, f2, g2 = f_hz[i], gain_db[i], f_hz[i + 1], gain_db[i + 1]
            if g2 <= db0 - 3.0 < g1:
                guess_fc = f1 + (db0 - 3.0 - g1) * (f2 - f1) / (g2 - g1)
                break
    else:
        guess_fc = f_hz[-1]
    p = [xm.log(max(guess_fc, 1.0)), xm.log(0.7), db0 / 20.0 * xm.log(10.0), 0.0]
    r, jac = evaluate(p)
    cost = math.fsum(v * v for v in r)
    lam = 1e-3
    for _ in range(500):
        jtj = [[math.fsum(row[i] * row[j] for row in jac) for j in range(4)] for i in range(4)]
        grad = [math.fsum(row[i] * v for row, v in zip(jac, r, strict=True)) for i in range(4)]
        a = [[jtj[i][j] + (lam * max(jtj[i][i], 1e-30) if i == j else 0.0) for j in range(4)] + [-grad[i]]
             for i in range(4)]
        step = _solve(a)
        trial = [min(max(v + d, lo), hi) for v, d, lo, hi in zip(p, step, _FIT_LO, _FIT_HI, strict=True)]
        r_new, jac_new = evaluate(trial)
        cost_new = math.fsum(v * v for v in r_new)
        if cost_new <= cost:
            moved = max(abs(t - v) / (1.0 + abs(v)) for t, v in zip(trial, p, strict=True))
            p, r, jac, cost = trial, r_new, jac_new, cost_new
            lam = max(lam / 3.0, 1e-12)
            if moved <= 1e-13:
                break
        else:
            lam *= 4.0
            if lam > 1e12:
                break
    if not all(math.isfinite(v) for v in p):
        raise ValueError("actuator response table: the model fit did not converge")
    return p


def _solve(a: list[list[float]]) -> list[float]:
    """x with A x = b for the augmented n x (n+1) matrix [A | b] (Gauss with partial pivoting)."""
    n = len(a)
    a = [row[:] for row in a]
    for c in range(n):
        piv = max(range(c, n), key=lambda i: abs(a[i][c]))
        a[c], a[piv] = a[piv], a[c]
        if a[c][c] == 0.0:
            return [0.0] * n
        for i in range(c + 1, n):
            k = a[i][c] / a[c][c]
            for j in range(c, n + 1):
                a[i][j] -= k * a[c][j]
    x = [0.0] * n
    for i in range(n - 1, -1, -1):
        x[i] = (a[i][n] - math.fsum(a[i][j] * x[j] for j in range(i + 1, n))) / a[i][i]
    return x


def load_actuator(path: str | Path) -> ActuatorModel:
    """An actuator model from TOML: either [model] (corner_hz, damping, dc_gain, delay_s) or
    [response] with equal-length arrays hz, gain_db, phase_deg (a measured table). A bare name
    (no directory, no suffix) is a shipped model under config/actuators/."""
    from hostd import tomlfile

    p = Path(path)
    if not p.suffix and len(p.parts) == 1:
        from hostd.paths import find

        p = find("actuators", f"{p}.toml")
    doc = tomlfile.read(p, "actuator model", exc=ValueError)
    name = str(doc.get("name", p.stem))
    unknown = set(doc) - {"name", "description", "model", "response"}
    if unknown:
        raise ValueError(f"{p}: unknown key {sorted(unknown)[0]!r} (expected name, description, "
                         "model, response)")
    if "response" in doc:
        r = doc["response"]
        try:
            return ActuatorModel.fit_table(r["hz"], r["gain_db"], r["phase_deg"], name=name)
        except KeyError as e:
            raise ValueError(f"{p}: [response] needs key {e.args[0]!r}") from None
        except (ValueError, TypeError) as e:
            raise ValueError(f"{p}: {e}") from None
    m = doc.get("model", {})
    allowed = {"corner_hz", "damping", "dc_gain", "delay_s"}
    bad = set(m) - allowed
    if bad:
        raise ValueError(f"{p}: unknown key model.{sorted(bad)[0]} (expected {sorted(allowed)})")
    try:
        return ActuatorModel(name=name, **{k: float(v) for k, v in m.items()})
    except (ValueError, TypeError) as e:
        raise ValueError(f"{p}: {e}") from None


@dataclass
class EqualizerConfig:
    enabled: bool = True
    reg_hz: float = 1400.0  # regularizing low-pass corner (digital Butterworth)
    reg_order: int = 2  # order of the regularizing Butterworth (>= 2 keeps the inverse proper)
    sample_rate_hz: float = 3000.0


def design(model: ActuatorModel, cfg: EqualizerConfig) -> np.ndarray:
    """SOS of the regularized inverse of the zero-order-held actuator at cfg.sample_rate_hz.

    The same bytes on every CPU: the zeros, poles and gain are known in closed form (the
    actuator's exact zero-order-hold discretization, _zoh_second_order; the digital Butterworth,
    _butter_zpk) and paired into sections by scipy.signal.zpk2sos's rule (_zpk2sos_nearest), all
    in Python float/complex arithmetic. scipy's path (cont2discrete: expm; tf2sos: np.roots, an
    eigen-solve; np.polymul: np.convolve, a BLAS dot) rounds differently under each OpenBLAS
    kernel (FMA or not, AVX-512 or not), so two CPUs would upload different sections."""
    fs = cfg.sample_rate_hz
    if not (0 < model.corner_hz < cfg.reg_hz < fs / 2):
        raise ValueError("equalizer: need 0 < actuator corner < reg_hz < sample_rate/2")
    if not 2 <= cfg.reg_order <= 8:
        raise ValueError("equalizer.reg_order must be 2..8")
    b1, b2, act_poles = _zoh_second_order(model, fs)
    # G(z) = z^-1 B(z) / A(z), B(z) = b1 z + b2: the second-order model always has its sample of
    # delay (b0 = 0) and one sampling zero
    zero = -b2 / b1
    if abs(zero) >= 0.98:
        raise ValueError("equalizer: the sampled actuator's zero lies on or outside the unit circle "
                         f"(|z| = {abs(zero):.3f}); raise the output rate or lower reg_hz")
    reg_poles, k_reg = _butter_zpk(cfg.reg_order, cfg.reg_hz, fs)
    # equalizer A(z) R(z) / B(z): zeros = the actuator's poles and R's zeros (all at -1), poles =
    # the sampling zero and R's poles, gain = R's over b1 (what tf2sos(A·R / B) made of it)
    zeros = [*act_poles, *[complex(-1.0, 0.0)] * cfg.reg_order]
    poles = [complex(zero, 0.0), *reg_poles]
    return np.array(_zpk2sos_nearest(zeros, poles, k_reg / b1), dtype=np.float64)


def _zoh_second_order(model: ActuatorModel, fs: float) -> tuple[float, float, list[complex]]:
    """The actuator model (ActuatorModel.analog_ba: g w0^2 / (s^2 + 2 zeta w0 s + w0^2)) behind a
    zero-order hold at fs, exactly: G(z) = (b1 z + b2) / ((z - z1)(z - z2)), z1,2 = exp(p1,2 T).
    b1 is the step response at T, b1 + b2 = g (1 - (z1 + z2) + z1 z2) keeps the DC gain. With
    sigma = zeta w0:  C = cos(wd T), S = sin(wd T) / wd  (under-damped, wd = w0 sqrt(1 - zeta^2)),
    C = cosh(beta T), S = sinh(beta T) / beta (over-damped, beta = w0 sqrt(zeta^2 - 1)),
    C = 1, S = T (critically damped);  b1 = g (1 - e^(-sigma T) (C + sigma S)),
    b2 = g (e^(-2 sigma T) - e^(-sigma T) (C - sigma S)). Returns (b1, b2, [z1, z2])."""
    t = 1.0 / fs
    w0 = 2 * math.pi * model.corner_hz
    zeta, g = model.damping, model.dc_gain
    sigma = zeta * w0
    decay = xm.exp(-sigma * t)
    # dc = e^(-sigma T) C, ds = e^(-sigma T) S
    if zeta < 1.0:
        wd = w0 * math.sqrt((1.0 - zeta) * (1.0 + zeta))
        sin, cos = xm.sin_cos(wd * t)
        dc, ds = decay * cos, decay * sin / wd
        poles = [complex(dc, decay * sin), complex(dc, -decay * sin)]
    elif zeta > 1.0:
        root = math.sqrt((zeta - 1.0) * (zeta + 1.0))
        beta = w0 * root
        slow = w0 / (zeta + root)  # sigma - beta, without the cancellation
        z1, z2 = xm.exp(-slow * t), xm.exp(-(sigma + beta) * t)
        if beta * t < 1.0:  # near critical damping: z1 - z2 would cancel
            cosh, sinh = xm.cosh_sinh(beta * t)
            dc, ds = decay * cosh, decay * sinh / beta
        else:  # cosh(beta T) could overflow: e^(-sigma T) cosh(beta T) = (z1 + z2) / 2
            dc, ds = (z1 + z2) / 2, (z1 - z2) / (2 * beta)
        poles = [complex(z1, 0.0), complex(z2, 0.0)]
    else:
        dc, ds = decay, decay * t
        poles = [complex(decay, 0.0), complex(decay, 0.0)]
    b1 = g * (1.0 - (dc + sigma * ds))
    b2 = g * (decay * decay - (dc - sigma * ds))
    return b1, b2, poles


def _butter_zpk(order: int, hz: float, fs: float) -> tuple[list[complex], float]:
    """Poles and gain of the digital Butterworth low-pass (its zeros: `order` at z = -1), as
    scipy.signal.butter(order, hz, fs=fs, output="zpk") makes them (analog prototype, prewarped
    corner, bilinear transform) in Python arithmetic: numpy's vectorized exp/tan may take a
    different (AVX-512) code path on another CPU."""
    warped = 4.0 * xm.tan(math.pi * hz / fs)  # scipy: 2 fs' tan(pi Wn / fs') with fs' = 2, Wn = 2 hz / fs
    poles = []
    for m in range(-order + 1, order, 2):
        if 2 * m > 0:  # the conjugate of the pole already made for -m: exactly conjugate
            poles.append(poles[(order - 1 - m) // 2].conjugate())
            continue
        ang = math.pi * m / (2 * order)
        sin, cos = xm.sin_cos(ang)
        p = complex(-cos, -sin) * warped if m else complex(-warped, 0.0)
        poles.append(p)
    den = complex(1.0, 0.0)
    for p in poles:
        den *= 4.0 - p
    gain = 1.0
    for _ in range(order):  # warped^order by multiplication: float ** int is libm's pow
        gain *= warped
    gain /= den.real
    return [(4.0 + p) / (4.0 - p) for p in poles], gain


def _zpk2sos_nearest(zeros: list[complex], poles: list[complex], k: float) -> list[list[float]]:
    """scipy.signal.zpk2sos(z, p, k, pairing="nearest") for conjugate-symmetric zeros and poles,
    in Python float/complex arithmetic (scipy multiplies out each pair with np.poly, a BLAS dot
    whose rounding depends on the CPU). The same rule: pad with zeros at the origin to equal, even
    counts; from the pole closest to the unit circle outwards, fill the sections from the last,
    pairing each pole (with its conjugate, or the next-closest real pole) with the nearest zeros;
    the gain goes into the first section."""
    p = [complex(v) for v in poles] + [0j] * max(len(zeros) - len(poles), 0)
    z = [complex(v) for v in zeros] + [0j] * max(len(poles) - len(zeros), 0)
    n_sections = (len(p) + 1) // 2
    if len(p) % 2:
        p.append(0j)
        z.append(0j)
    p, z = _cplxreal(p), _cplxreal(z)

    def worst(vals: list[complex], among=None) -> int:
        idx = range(len(vals)) if among is None else among
        return min(idx, key=lambda i: abs(1.0 - abs(vals[i])))

    def nearest(to: complex, which: str) -> int:
        order = sorted(range(len(z)), key=lambda i: abs(z[i] - to))
        return next(i for i in order if which == "any" or (z[i].imag == 0) == (which == "real"))

    def section(zs: list[complex], ps: list[complex]) -> list[float]:
        return [*_pair_poly(zs), *_pair_poly(ps)]

    sos: list[list[float]] = [[]] * n_sections
    for si in range(n_sections - 1, -1, -1):
        p1 = p.pop(worst(p))
        n_real_p = sum(v.imag == 0 for v in p)
        if p1.imag == 0 and n_real_p == 0:  # the last real pole: with the nearest real zero
            z1 = z.pop(nearest(p1, "real"))
            sos[si] = section([z1, 0j], [p1, 0j])
        elif (len(p) + 1 == len(z) and p1.imag != 0 and n_real_p == 1
              and sum(v.imag == 0 for v in z) == 1):  # must take a complex zero pair
            z1 = z.pop(nearest(p1, "complex"))
            sos[si] = section([z1, z1.conjugate()], [p1, p1.conjugate()])
        else:
            if p1.imag == 0:
                p2 = p.pop(worst(p, [i for i, v in enumerate(p) if v.imag == 0]))
            else:
                p2 = p1.conjugate()
            z1 = z.pop(nearest(p1, "any"))
            if z1.imag != 0:
                sos[si] = section([z1, z1.conjugate()], [p1, p2])
            else:
                z2 = z.pop(nearest(p1, "real"))
                sos[si] = section([z1, z2], [p1, p2])
    if p or z:
        raise AssertionError("equalizer: zeros and poles left over after pairing")
    sos[0] = [v * k for v in sos[0][:3]] + sos[0][3:]
    return sos


def _cplxreal(vals: list[complex]) -> list[complex]:
    """One element (imag > 0) of each conjugate pair, sorted by real part, then the real values
    sorted (scipy.signal's _cplxreal order, which decides between equally good candidates)."""
    tol = 100 * np.finfo(np.float64).eps
    real = [complex(r, 0.0) for r in sorted(v.real for v in vals if abs(v.imag) <= tol * abs(v))]
    upper = sorted((v for v in vals if v.imag > tol * abs(v)), key=lambda v: (v.real, abs(v.imag)))
    return [*upper, *real]


def _pair_poly(roots: list[complex]) -> list[float]:
    """(z - r1)(z - r2) for a conjugate pair or two real roots: [1, -(r1 + r2), r1 r2]."""
    r1, r2 = roots
    if r1.imag != 0:  # a conjugate pair
        return [1.0, -2.0 * r1.real, r1.real * r1.real + r1.imag * r1.imag]
    return [1.0, -(r1.real + r2.real), r1.real * r2.real + 0.0]  # + 0.0: no -0.0 for a root at 0


def sos_response(sos: np.ndarray, f_hz: list[float], fs: float) -> list[complex]:
    """The sections' complex response at each f (scipy.signal.sosfreqz's numbers), in Python
    complex arithmetic: what device_params needs (the chain's delay) without loading
    scipy.signal, and the same bits on every CPU."""
    rows = [tuple(float(v) for v in r) for r in sos]
    out = []
    for f in f_hz:
        ang = 2 * math.pi * f / fs
        sin, cos = xm.sin_cos(ang)
        z1 = complex(cos, -sin)  # z^-1 on the unit circle
        z2 = z1 * z1
        h = complex(1.0, 0.0)
        for b0, b1, b2, a0, a1, a2 in rows:
            h *= (b0 + b1 * z1 + b2 * z2) / (a0 + a1 * z1 + a2 * z2)
        out.append(h)
    return out


class Equalizer:
    """Stateful SOS filter; a no-op passthrough when disabled."""

    def __init__(self, model: ActuatorModel | None = None, cfg: EqualizerConfig | None = None) -> None:
        self.model = model or ActuatorModel()
        self.cfg = cfg or EqualizerConfig()
        self.sos = design(self.model, self.cfg) if self.cfg.enabled else None
        self.zi = np.zeros((self.sos.shape[0], 2)) if self.sos is not None else None
        self._rows = [tuple(float(v) for v in r) for r in self.sos] if self.sos is not None else []

    def reset(self, value_um: float = 0.0) -> None:
        if self.sos is not None:
            self.zi = _signal().sosfilt_zi(self.sos) * value_um

    @property
    def settle_samples(self) -> int:
        """Samples after which what the filter was fed before weighs less than SETTLE_TOL in
        its state (its slowest pole, |p|^n <= SETTLE_TOL; 0 when disabled): 140 for the paper's
        actuator at 3 kHz (poles 0.765, 0.862)."""
        if self.sos is None:
            return 0
        r = 0.0
        for _b0, _b1, _b2, _a0, a1, a2 in self._rows:  # z^2 + a1 z + a2 (a0 = 1)
            disc = a1 * a1 - 4.0 * a2
            r = max(r, math.sqrt(a2) if disc < 0 else (abs(a1) + math.sqrt(disc)) / 2.0)
        if r <= 0.0:
            return 1
        return math.ceil(math.log(SETTLE_TOL) / math.log(r))

    def warm(self, x_um: np.ndarray) -> None:
        """Forget the past: the state is the one `x_um` (settle_samples of the signal to come,
        just before it) leaves from rest, as if the filter had always been fed that signal."""
        if self.sos is not None:
            self.zi = np.zeros_like(self.zi)
            x = np.asarray(x_um, dtype=np.float64)
            for i in range(0, x.size, SMALL_BATCH):  # the scalar recurrence: no scipy.signal
                self(x[i : i + SMALL_BATCH])

    def __call__(self, x_um: np.ndarray) -> np.ndarray:
        x = np.asarray(x_um, dtype=np.float64)
        if self.sos is None:
            return x
        if x.size > SMALL_BATCH:
            y, zi = _signal().sosfilt(self.sos, x, zi=self.zi)
            zi[np.abs(zi) < DENORMAL_GUARD] = 0.0
            self.zi = zi
            return y
        # scalar transposed direct form II, the same recurrence and state as sosfilt
        ys = x.tolist()
        zi = self.zi
        for s, (b0, b1, b2, _a0, a1, a2) in enumerate(self._rows):
            z0, z1 = float(zi[s, 0]), float(zi[s, 1])
            for i, v in enumerate(ys):
                y = b0 * v + z0
                z0 = b1 * v - a1 * y + z1
                z1 = b2 * v - a2 * y
                ys[i] = y
            # a decaying state would otherwise sink into subnormals (slow on x86) for ever
            zi[s, 0] = z0 if abs(z0) >= DENORMAL_GUARD else 0.0
            zi[s, 1] = z1 if abs(z1) >= DENORMAL_GUARD else 0.0
        return np.array(ys)

    def chain_response(self, f_hz: np.ndarray, measured: bool = True) -> np.ndarray:
        """Actuator x equalizer (including the DAC's zero-order hold) at f_hz; the actuator
        is the measured table when there is one (measured=True), else the model. The
        actuator's pure delay is excluded (prediction compensates it, not the filter)."""
        f = np.asarray(f_hz, dtype=np.float64)
        fs = self.cfg.sample_rate_hz
        zoh = np.sinc(f / fs) * np.exp(-1j * np.pi * f / fs)
        eq = (np.array(sos_response(self.sos, f.ravel().tolist(), fs)).reshape(f.shape)
              if self.sos is not None else np.ones_like(f, dtype=complex))
        act = self.model.measured(f) if measured else self.model.response(f)
        act = act * np.exp(2j * np.pi * f * self.model.delay_s)
        return act * eq * zoh

    def flatness_db(self, lo_hz: float = 10.0, hi_hz: float = 400.0) -> tuple[float, float]:
        """(min, max) gain in dB of actuator x equalizer over [lo, hi]."""
        f = np.linspace(lo_hz, hi_hz, 400)
        g = 20 * np.log10(np.abs(self.chain_response(f)))
        return float(g.min()), float(g.max())

    def group_delay_ms(self, f_hz: float = 100.0) -> float:
        """Group delay the equalizer adds at f_hz (ms); negative is a phase lead."""
        if self.sos is None:
            return 0.0
        b, a = _signal().sos2tf(self.sos)
        _w, gd = _signal().group_delay((b, a), w=[f_hz], fs=self.cfg.sample_rate_hz)
        return float(gd[0]) / self.cfg.sample_rate_hz * 1e3

    def chain_delay_ms(self, f_hz: float = 100.0) -> float:
        """Group delay of actuator x equalizer x ZOH at f_hz (ms), from the phase slope."""
        df = 0.5
        h = self.chain_response(np.array([f_hz - df, f_hz + df]), measured=False)
        dphi = np.angle(h[1] / h[0])
        return float(-dphi / (2 * np.pi * 2 * df) * 1e3) + self.model.delay_s * 1e3
