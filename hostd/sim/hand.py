"""Hand motion models: position x(t) in mm and velocity v(t) in mm/s, vectorized over t.

- Metronome: the paper's protocol. Strokes of `stroke_mm` paced by a metronome at
  `beat_hz`: forward over `forward_beats` beats, back over `back_beats` beats (paper: 40 mm,
  1.25 Hz, 1 and 2, so 50 mm/s on average forward). Within a stroke the velocity follows a
  minimum-jerk profile x = x0 + D (10 s^3 - 15 s^4 + 6 s^5), s = t / T (Flash & Hogan 1985),
  so speed and acceleration are continuous and zero at each reversal.
- Constant: x = x0 + v t.
- Recorded: a (time s, position mm) trajectory from CSV, interpolated with a monotone cubic
  (scipy PchipInterpolator) so no overshoot is invented between samples.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np


class Hand:
    def position_mm(self, t_s: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def velocity_mm_s(self, t_s: np.ndarray) -> np.ndarray:
        raise NotImplementedError


@dataclass
class Metronome(Hand):
    stroke_mm: float = 40.0
    beat_hz: float = 1.25
    forward_beats: int = 1
    back_beats: int = 2
    start_mm: float = 0.0

    def __post_init__(self) -> None:
        if not (self.stroke_mm > 0 and self.beat_hz > 0 and self.forward_beats >= 1
                and self.back_beats >= 1):
            raise ValueError("metronome: stroke_mm, beat_hz > 0 and beats >= 1")
        self.t_fwd = self.forward_beats / self.beat_hz
        self.t_back = self.back_beats / self.beat_hz
        self.period_s = self.t_fwd + self.t_back

    def _phase(self, t_s):
        t = np.mod(np.asarray(t_s, dtype=np.float64), self.period_s)
        fwd = t < self.t_fwd
        s = np.where(fwd, t / self.t_fwd, (t - self.t_fwd) / self.t_back)
        return fwd, s

    def position_mm(self, t_s):
        fwd, s = self._phase(t_s)
        p = s ** 3 * (10 - 15 * s + 6 * s * s)
        return self.start_mm + self.stroke_mm * np.where(fwd, p, 1.0 - p)

    def velocity_mm_s(self, t_s):
        fwd, s = self._phase(t_s)
        dp = 30 * s * s * (1 - s) ** 2
        return self.stroke_mm * np.where(fwd, dp / self.t_fwd, -dp / self.t_back)

    @property
    def mean_forward_speed_mm_s(self) -> float:
        return self.stroke_mm / self.t_fwd


@dataclass
class Constant(Hand):
    speed_mm_s: float = 50.0
    start_mm: float = 0.0

    def position_mm(self, t_s):
        return self.start_mm + self.speed_mm_s * np.asarray(t_s, dtype=np.float64)

    def velocity_mm_s(self, t_s):
        return np.full(np.shape(t_s), float(self.speed_mm_s))


class Recorded(Hand):
    def __init__(self, t_s: np.ndarray, x_mm: np.ndarray, name: str = "recorded") -> None:
        import scipy.interpolate

        t = np.asarray(t_s, dtype=np.float64)
        x = np.asarray(x_mm, dtype=np.float64)
        if t.ndim != 1 or t.size < 2 or t.size != x.size:
            raise ValueError(f"{name}: need >= 2 rows of (time_s, position_mm)")
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(x))):
            raise ValueError(f"{name}: non-finite time or position")
        if np.any(np.diff(t) <= 0):
            raise ValueError(f"{name}: times must be strictly increasing")
        self.t0, self.t1 = float(t[0]), float(t[-1])
        self._p = scipy.interpolate.PchipInterpolator(t, x, extrapolate=False)
        self._v = self._p.derivative()

    def _clip(self, t_s):
        return np.clip(np.asarray(t_s, dtype=np.float64), self.t0, self.t1)

    def position_mm(self, t_s):
        return self._p(self._clip(t_s))

    def velocity_mm_s(self, t_s):
        t = np.asarray(t_s, dtype=np.float64)
        v = self._v(self._clip(t))
        return np.where((t < self.t0) | (t > self.t1), 0.0, v)

    @classmethod
    def from_csv(cls, path: str | Path) -> Recorded:
        p = Path(path)
        try:
            rows = np.loadtxt(p, delimiter=",", comments="#", ndmin=2)
        except (OSError, ValueError) as e:
            raise ValueError(f"{p}: cannot read a (time_s, position_mm) CSV ({e})") from None
        if rows.shape[1] < 2:
            raise ValueError(f"{p}: need two columns (time_s, position_mm)")
        return cls(rows[:, 0], rows[:, 1], name=str(p))
