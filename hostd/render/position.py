"""Encoder counts to position: unwraps the device's 32-bit counter and scales to mm."""

from __future__ import annotations

import numpy as np

from hostd.cyclestate import record

COUNTER_MOD = 1 << 32


class EncoderPosition(record("position")):
    """Unwraps a wrapping 32-bit (unsigned or two's-complement) count into an unbounded one.

    Between two readings the hand moves far less than half the counter range (2^31 counts =
    859 m at 0.4 µm), so the shortest signed difference is the true one. Its state is the
    "position" record of hostd/device/cycle_state.toml.
    """

    def __init__(self, um_per_count: float = 0.4) -> None:
        if not (np.isfinite(um_per_count) and um_per_count > 0):
            raise ValueError("um_per_count must be a finite number > 0")
        self.um_per_count = float(um_per_count)
        self._last: int | None = None
        self._total = 0

    def update(self, raw_count: int) -> float:
        """Feed one raw 32-bit reading; returns the position in mm."""
        raw = int(raw_count) % COUNTER_MOD
        if self._last is not None:
            d = (raw - self._last) % COUNTER_MOD
            if d >= COUNTER_MOD // 2:
                d -= COUNTER_MOD
            self._total += d
        else:
            self._total = raw if raw < COUNTER_MOD // 2 else raw - COUNTER_MOD
        self._last = raw
        return self.position_mm

    @property
    def counts(self) -> int:
        return self._total

    @property
    def position_mm(self) -> float:
        return self._total * self.um_per_count * 1e-3
