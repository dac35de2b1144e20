"""Hand motion estimate from quantized encoder samples, and latency-compensating prediction.

A least-squares polynomial (order 1: velocity; order 2: velocity and acceleration) is fitted
to the last `window` (time, position) samples. A sample that departs from the current fit's
prediction by more than `glitch_um` (a single-count glitch is 0.4 µm; a hand cannot jump
hundreds of µm in 1 ms) is replaced by the prediction, so one glitching reading moves
nothing. Below a speed dead band the hand is at rest: the held position moves only when the
window's mean leaves a hold band, so ±1-count encoder dither does not reach the output.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class MotionConfig:
    window: int = 8  # samples in the fit (1 kHz status -> 8 ms)
    order: int = 1  # 0 = hold, 1 = velocity, 2 = velocity + acceleration
    glitch_um: float = 200.0
    rest_speed_mm_s: float = 0.2  # below this the hand is at rest: no extrapolation
    rest_hold_um: float = 1.0  # at rest, the held position moves only past this band (dither)
    max_predict_s: float = 0.05


class MotionEstimator:
    def __init__(self, cfg: MotionConfig | None = None) -> None:
        self.cfg = cfg or MotionConfig()
        if self.cfg.order not in (0, 1, 2) or self.cfg.window < self.cfg.order + 2:
            raise ValueError("order must be 0, 1 or 2 and window >= order + 2")
        self._t = np.zeros(self.cfg.window)
        self._x = np.zeros(self.cfg.window)
        self._n = 0
        self._coef = np.zeros(3)  # x(t) = c0 + c1 (t - t_ref) + c2 (t - t_ref)^2
        self._t_ref = 0.0
        self._rest_x: float | None = None
        self.glitches = 0

    def update(self, t_s: float, x_mm: float) -> None:
        if self._n >= self.cfg.order + 2:
            pred = self.predict(t_s)
            if abs(x_mm - pred) * 1000.0 > self.cfg.glitch_um:
                self.glitches += 1
                x_mm = pred
        # Shift in place: no allocation per encoder reading.
        self._t[:-1] = self._t[1:]
        self._x[:-1] = self._x[1:]
        self._t[-1], self._x[-1] = t_s, x_mm
        self._n = min(self._n + 1, self.cfg.window)
        self._fit()

    def _fit(self) -> None:
        n = self._n
        t = self._t[-n:]
        x = self._x[-n:]
        self._t_ref = t[-1]
        order = min(self.cfg.order, n - 1)
        if order == 0 or np.ptp(t) <= 0:
            self._coef = np.array([x[-1], 0.0, 0.0])
            self._rest_x = None
            return
        tt = t - self._t_ref
        c = np.polynomial.polynomial.polyfit(tt, x, order)
        self._coef = np.zeros(3)
        self._coef[: c.size] = c
        if abs(self._coef[1]) < self.cfg.rest_speed_mm_s:
            # At rest: hold a position; encoder dither (±1 count) must not move the output.
            mean = float(np.mean(x))
            if self._rest_x is None or abs(mean - self._rest_x) * 1000.0 > self.cfg.rest_hold_um:
                self._rest_x = mean
            self._coef = np.array([self._rest_x, 0.0, 0.0])
        else:
            self._rest_x = None

    @property
    def velocity_mm_s(self) -> float:
        return float(self._coef[1])

    def predict(self, t_s: float | np.ndarray) -> np.ndarray | float:
        dt = np.clip(np.asarray(t_s, dtype=np.float64) - self._t_ref, -self.cfg.max_predict_s,
                     self.cfg.max_predict_s)
        c = self._coef
        return c[0] + dt * (c[1] + dt * c[2])
