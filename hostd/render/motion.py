"""Hand motion estimate from quantized encoder samples, and latency-compensating prediction.

A least-squares polynomial (order 1: velocity; order 2: velocity and acceleration; order 3: and
jerk) is fitted to the last `window` (time, position) samples. A sample that departs from the current fit's
prediction by more than `glitch_um` (a single-count glitch is 0.4 µm; a hand cannot jump
hundreds of µm in 1 ms) is replaced by the prediction, so one glitching reading moves
nothing. But readings that disagree with the prediction `relock_reports` times in a row, and
agree with each other, are a real move (the device caught up after a host stall, the hand was
lifted and set down): the fit restarts from them (`relocks` counts it; the renderer
crossfades across the discontinuity). A gap in the readings longer than `max_gap_s` also
restarts the fit: a prediction that far ahead is no reference. A speed estimate beyond
`max_speed_mm_s` is physically impossible for a hand: it is rejected (`implausible` counts
it) and the fit restarts from the newest reading. Below a speed dead band, with readings that
stay within what that speed covers over the window (a reversal passes through zero speed but
not through rest), the hand is at rest: the held position moves only when the window's mean
leaves a hold band, so ±1-count encoder dither does not reach the output.

This runs once per encoder reading (1 kHz) on the real-time path. Readings come evenly
spaced (device timestamps), so the least-squares solution matrix depends only on the
window's length and spacing: it is computed once (the normal equations solved by numpy, time
in ms relative to the newest reading, which keeps them well conditioned) and each update is
up to four dot products in scalar Python (a few µs). Irregular spacing (a lost report) solves afresh.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hostd.cyclestate import record

SMALL_BATCH = 32  # at or below this many instants, predict in scalar Python (same values)
# A cubic needs this many readings in its window (after a start or a re-lock it has fewer): the
# encoder's 0.4 µm steps reach a prediction 6 ms ahead as 3.7 µm RMS from a cubic over 8
# readings, 0.38 µm over 24 (a parabola over 8: 0.77 µm); the compiled cycle uses the same number
CUBIC_MIN_READINGS = 24


@dataclass
class MotionConfig:
    # Order 3 over 40 ms: the most accurate setting of `hostd bench accuracy` under the paper's
    # strokes. The renderer predicts ~6 ms past the newest reading (transport, the device's
    # buffer, the chain's delay); a quadratic lags there wherever the hand's acceleration
    # changes, and only a short window keeps that lag small, which leaves the 0.4 µm encoder
    # steps little averaging (order 2 over 16 ms: 1.31 % RMS on sandpaper, where both errors are
    # about equal). A cubic follows the changing acceleration, so the window can grow until the
    # steps average out: 0.74 % (docs/rendering.md, DEVELOPMENT.md)
    window: int = 40  # samples in the fit (1 kHz status -> 40 ms)
    order: int = 3  # 0 = hold, 1 = velocity, 2 = + acceleration, 3 = + jerk
    glitch_um: float = 200.0
    rest_speed_mm_s: float = 0.2  # below this the hand is at rest: no extrapolation
    rest_hold_um: float = 1.0  # at rest, the held position moves only past this band (dither)
    max_predict_s: float = 0.05
    relock_reports: int = 3  # consecutive disagreeing readings that mean a real move
    max_gap_s: float = 0.02  # readings further apart than this restart the fit
    max_speed_mm_s: float = 3000.0  # faster than any hand: an estimate above it is rejected


def _dot(w, x) -> float:
    """sum_i w_i x_i, left to right from 0.0 in IEEE doubles: the order the compiled cycle
    (hostd/device/_fastpump.c) uses. Not sum(), which compensates its rounding from Python 3.12."""
    acc = 0.0
    for a, b in zip(w, x, strict=True):
        acc += a * b
    return acc


def _dots(rows, x) -> list[float]:
    """[_dot(r, x) for r in rows], the same sums in the same order, in one pass over x (the
    four rows of a cubic fit over 40 readings, 1000 times a second, cost half as much)."""
    if len(rows) == 4:
        w0, w1, w2, w3 = rows
        a0 = a1 = a2 = a3 = 0.0
        for xi, b0, b1, b2, b3 in zip(x, w0, w1, w2, w3, strict=True):
            a0 += b0 * xi
            a1 += b1 * xi
            a2 += b2 * xi
            a3 += b3 * xi
        return [a0, a1, a2, a3]
    return [_dot(r, x) for r in rows]


class MotionEstimator(record("motion")):
    """Its numeric state (its config's too, copied, and the window of readings: _tw[:_n],
    _xw[:_n], oldest first) is the "motion" record of hostd/device/cycle_state.toml."""

    def __init__(self, cfg: MotionConfig | None = None) -> None:
        self.cfg = cfg = cfg or MotionConfig()
        if cfg.order not in (0, 1, 2, 3) or not cfg.order + 2 <= cfg.window <= len(self._tw):
            raise ValueError(f"order must be 0, 1, 2 or 3 and order + 2 <= window <= {len(self._tw)}")
        if cfg.relock_reports < 1:
            raise ValueError("relock_reports must be >= 1")
        for name in ("glitch_um", "rest_speed_mm_s", "rest_hold_um", "max_predict_s", "max_gap_s",
                     "max_speed_mm_s"):
            v = getattr(cfg, name)
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"motion.{name} must be a finite number >= 0")
        self._window, self._order, self._glitch_um = cfg.window, cfg.order, cfg.glitch_um
        self._rest_speed_mm_s, self._rest_hold_um = cfg.rest_speed_mm_s, cfg.rest_hold_um
        self._max_predict_s, self._max_gap_s = cfg.max_predict_s, cfg.max_gap_s
        self._max_speed_mm_s = cfg.max_speed_mm_s
        # x(t) = c0 + c1 (t - t_ref) + c2 (t - t_ref)^2 + c3 (t - t_ref)^3, t in s, x in mm
        self._c0 = self._c1 = self._c2 = self._c3 = 0.0
        self._t_ref = 0.0
        self._rest_x: float | None = None
        self._dt_us = -1
        self._uniform = 0  # how many of the latest spacings equal _dt_us
        self._cache: dict[tuple[int, int, int], tuple[list[float], ...]] = {}
        self.glitches = 0
        self.relocks = 0
        self.implausible = 0
        self._outliers: list[tuple[float, float]] = []
        self._since_restart = 1 << 30  # readings since the fit last restarted
        # the fit in force before the latest re-lock: (c0, c1, c2, c3, t_ref), for a crossfade
        self.previous_fit: tuple[float, float, float, float, float] | None = None

    def _restart(self, readings: list[tuple[float, float]]) -> None:
        self.previous_fit = (self._c0, self._c1, self._c2, self._c3, self._t_ref)
        self._n = 0
        self._outliers.clear()
        self._rest_x = None
        self._dt_us = -1
        self._uniform = 0
        self._since_restart = 0
        for t, x in readings:
            self._append(t, x)
        self._fit()

    def update(self, t_s: float, x_mm: float) -> None:
        t_s, x_mm = float(t_s), float(x_mm)
        if not (math.isfinite(t_s) and math.isfinite(x_mm)):
            self.glitches += 1
            return
        n = self._n
        if n and t_s <= self._tw[n - 1]:
            return  # a stale or repeated reading adds nothing
        cfg = self.cfg
        if n and t_s - self._tw[n - 1] > cfg.max_gap_s:
            self.relocks += 1
            self._restart([(t_s, x_mm)])
            return
        if n >= cfg.order + 2:
            pred = self.predict_one(t_s)
            if abs(x_mm - pred) * 1000.0 > cfg.glitch_um:
                out = self._outliers
                out.append((t_s, x_mm))
                if len(out) > cfg.relock_reports:
                    del out[0]
                if len(out) >= cfg.relock_reports and self._consistent(out):
                    self.relocks += 1
                    self._restart(list(out))
                    return
                self.glitches += 1
                x_mm = pred
            else:
                self._outliers.clear()
        self._append(t_s, x_mm)
        self._fit()
        if abs(self._c1) > cfg.max_speed_mm_s:
            self.implausible += 1
            n = self._n
            self._restart([(self._tw[n - 1], self._xw[n - 1])])

    def _consistent(self, pts: list[tuple[float, float]]) -> bool:
        """Do these readings agree with each other (one hand, moving at most max_speed)?"""
        xs = [x for _, x in pts]
        span_s = pts[-1][0] - pts[0][0]
        return (max(xs) - min(xs)) * 1000.0 <= self.cfg.glitch_um + self.cfg.max_speed_mm_s * span_s * 1000.0

    def _append(self, t_s: float, x_mm: float) -> None:
        self._since_restart += 1
        n = self._n
        if n:
            dt_us = round((t_s - self._tw[n - 1]) * 1e6)
            self._uniform = self._uniform + 1 if dt_us == self._dt_us else 1
            self._dt_us = dt_us
        if n == self._window:  # full: the oldest reading leaves
            self._tw[: n - 1], self._xw[: n - 1] = self._tw[1:n], self._xw[1:n]
            n -= 1
        self._tw[n], self._xw[n] = t_s, x_mm
        self._n = n + 1

    def _weights(self, tau_ms: np.ndarray, order: int) -> tuple[list[float], ...]:
        """Rows of the least-squares solution matrix: coefficients = W @ x."""
        v = np.vander(tau_ms, order + 1, increasing=True)
        w = np.linalg.solve(v.T @ v, v.T)  # = pinv(v) (full column rank: distinct times), 4x faster
        return tuple(row.tolist() for row in w)

    def _fit(self) -> None:
        n = self._n
        t, x = self._tw[:n], self._xw[:n]
        tr = t[-1]
        self._t_ref = tr
        order = min(self.cfg.order, n - 1)
        if self._since_restart < 2 * (self.cfg.order + 1):
            order = min(order, 1)  # a fresh restart: too few readings for an acceleration
        if order == 3 and n < CUBIC_MIN_READINGS:
            order = 2  # a short window: a cubic would amplify the encoder's steps (see there)
        if order == 0:
            self._c0, self._c1, self._c2, self._c3 = x[-1], 0.0, 0.0, 0.0
            self._rest_x = None
            return
        if self._uniform >= n - 1:
            # evenly spaced readings (the normal case): the solution matrix depends only on
            # (n, spacing, order), so it is computed once and reused
            key = (n, self._dt_us, order)
            w = self._cache.get(key)
            if w is None:
                w = self._weights(np.arange(1 - n, 1) * (self._dt_us * 1e-3), order)
                self._cache[key] = w
        else:
            w = self._weights((np.array(t) - tr) * 1e3, order)  # irregular: solve afresh
        d = _dots(w, x)  # one row per coefficient, order + 1 of them
        c0 = d[0]
        c1 = d[1] * 1e3
        c2 = d[2] * 1e6 if order >= 2 else 0.0
        c3 = d[3] * 1e9 if order == 3 else 0.0
        self._c0, self._c1, self._c2, self._c3 = c0, c1, c2, c3
        rest = self.cfg.rest_speed_mm_s
        if abs(c1) < rest and max(x) - min(x) <= rest * (t[-1] - t[0]) + self.cfg.rest_hold_um * 1e-3:
            # At rest: hold a position; encoder dither (±1 count) must not move the output. Rest
            # is a slow fit whose readings stay within what that speed covers over the window
            # (plus the hold band): a hand passing through zero speed at a reversal is not at
            # rest, and holding the window's mean there (20 ms behind at 40 readings) would jump
            # the texture by tens of µm.
            mx = _dot((1.0,) * n, x) / n
            if self._rest_x is None or abs(mx - self._rest_x) * 1000.0 > self.cfg.rest_hold_um:
                self._rest_x = mx
            self._c0, self._c1, self._c2, self._c3 = self._rest_x, 0.0, 0.0, 0.0
        else:
            self._rest_x = None

    @property
    def velocity_mm_s(self) -> float:
        """The speed at the newest reading."""
        return self._c1

    def velocity_at(self, t_s: float) -> float:
        """The fit's speed (mm/s) at instant t_s (clipped to max_predict_s past the newest reading,
        as the prediction): the speed the hand will have when the samples planned for t_s play.
        The operations of the compiled cycle (hostd/device/_fastpump.c), in the same order."""
        m = self.cfg.max_predict_s
        dt = min(max(t_s - self._t_ref, -m), m)
        return self._c1 + dt * (2.0 * self._c2 + dt * (3.0 * self._c3))

    def predict_previous(self, t_s: np.ndarray) -> np.ndarray:
        """The fit in force before the latest restart, extrapolated (for a crossfade)."""
        c0, c1, c2, c3, tr = self.previous_fit or (self._c0, 0.0, 0.0, 0.0, self._t_ref)
        m = self.cfg.max_predict_s
        dt = (np.asarray(t_s, dtype=np.float64) - tr).clip(-m, m)
        return c0 + dt * (c1 + dt * (c2 + dt * c3))

    def predict_one(self, t_s: float) -> float:
        m = self.cfg.max_predict_s
        dt = min(max(t_s - self._t_ref, -m), m)
        return self._c0 + dt * (self._c1 + dt * (self._c2 + dt * self._c3))

    def predict(self, t_s: float | np.ndarray) -> np.ndarray | float:
        if isinstance(t_s, float | int):
            return self.predict_one(float(t_s))
        m = self.cfg.max_predict_s
        t = np.asarray(t_s, dtype=np.float64)
        c0, c1, c2, c3, tr = self._c0, self._c1, self._c2, self._c3, self._t_ref
        if t.ndim == 1 and t.size <= SMALL_BATCH:
            # a real-time batch: the same operations sample by sample in Python floats (IEEE
            # doubles, as numpy's), which costs less than the numpy calls below
            dts = [min(max(x - tr, -m), m) for x in t.tolist()]
            return np.array([c0 + dt * (c1 + dt * (c2 + dt * c3)) for dt in dts], dtype=np.float64)
        dt = (t - tr).clip(-m, m)
        return c0 + dt * (c1 + dt * (c2 + dt * c3))
