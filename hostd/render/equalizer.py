"""Actuator model and its regularized inverse, as second-order sections at the output rate.

Parametric default after the paper's display: no resonance up to 400 Hz, -3 dB at 270 Hz
(a 2nd-order Butterworth low-pass at 270 Hz). The inverse of that is improper, so it is
regularized: the equalizer is  H_act^-1(s) · L(s)  with L a Butterworth low-pass at
`reg_hz` whose order matches the model's, which also caps the high-frequency gain at
(reg_hz / fc)^order. Discretized with the bilinear transform (no pre-warping; the
flatness figure includes that warping and the DAC's zero-order hold) and applied with
scipy.signal.sosfilt, whose state is carried across batches.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.signal


@dataclass
class ActuatorModel:
    corner_hz: float = 270.0
    order: int = 2

    def response(self, f_hz: np.ndarray) -> np.ndarray:
        """Continuous-time complex response of the actuator (displacement per command)."""
        b, a = scipy.signal.butter(self.order, 2 * np.pi * self.corner_hz, analog=True)
        return scipy.signal.freqs(b, a, worN=2 * np.pi * np.asarray(f_hz, dtype=np.float64))[1]


@dataclass
class EqualizerConfig:
    enabled: bool = True
    reg_hz: float = 800.0  # regularizing low-pass corner: caps gain at (reg_hz/corner)^order
    sample_rate_hz: float = 3000.0


def design(model: ActuatorModel, cfg: EqualizerConfig) -> np.ndarray:
    """SOS of the regularized inverse at cfg.sample_rate_hz."""
    fs = cfg.sample_rate_hz
    if not (0 < model.corner_hz < cfg.reg_hz < fs / 2):
        raise ValueError("need 0 < actuator corner < reg_hz < fs/2")
    b_act, a_act = scipy.signal.butter(model.order, 2 * np.pi * model.corner_hz, analog=True)
    b_reg, a_reg = scipy.signal.butter(model.order, 2 * np.pi * cfg.reg_hz, analog=True)
    # inverse: a_act / b_act, times b_reg / a_reg
    num = np.polymul(a_act, b_reg)
    den = np.polymul(b_act, a_reg)
    bz, az = scipy.signal.bilinear(num, den, fs=fs)
    return scipy.signal.tf2sos(bz, az)


class Equalizer:
    """Stateful SOS filter; a no-op passthrough when disabled."""

    def __init__(self, model: ActuatorModel | None = None, cfg: EqualizerConfig | None = None) -> None:
        self.model = model or ActuatorModel()
        self.cfg = cfg or EqualizerConfig()
        self.sos = design(self.model, self.cfg) if self.cfg.enabled else None
        self.zi = (np.zeros((self.sos.shape[0], 2)) if self.sos is not None else None)

    def reset(self, value_um: float = 0.0) -> None:
        if self.sos is not None:
            self.zi = scipy.signal.sosfilt_zi(self.sos) * value_um

    def __call__(self, x_um: np.ndarray) -> np.ndarray:
        if self.sos is None:
            return np.asarray(x_um, dtype=np.float64)
        y, self.zi = scipy.signal.sosfilt(self.sos, x_um, zi=self.zi)
        return y

    def chain_response(self, f_hz: np.ndarray) -> np.ndarray:
        """Actuator x equalizer (including the DAC's zero-order hold) at f_hz."""
        f = np.asarray(f_hz, dtype=np.float64)
        fs = self.cfg.sample_rate_hz
        zoh = np.sinc(f / fs) * np.exp(-1j * np.pi * f / fs)
        eq = (scipy.signal.sosfreqz(self.sos, worN=f, fs=fs)[1] if self.sos is not None
              else np.ones_like(f, dtype=complex))
        return self.model.response(f) * eq * zoh

    def flatness_db(self, lo_hz: float = 10.0, hi_hz: float = 400.0) -> tuple[float, float]:
        """(min, max) gain in dB of actuator x equalizer over [lo, hi]."""
        f = np.linspace(lo_hz, hi_hz, 400)
        g = 20 * np.log10(np.abs(self.chain_response(f)))
        return float(g.min()), float(g.max())

    def group_delay_ms(self, f_hz: float = 100.0) -> float:
        """Group delay the equalizer adds at f_hz (ms)."""
        if self.sos is None:
            return 0.0
        b, a = scipy.signal.sos2tf(self.sos)
        _w, gd = scipy.signal.group_delay((b, a), w=[f_hz], fs=self.cfg.sample_rate_hz)
        return float(gd[0]) / self.cfg.sample_rate_hz * 1e3
