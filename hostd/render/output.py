"""Output stage: displacement (µm, about the travel's centre) to signed DAC codes, safely.

Whatever enters (NaN, Inf, a huge value, a jump), what leaves respects:
  |displacement| <= travel_um / 2   and   |step between samples| <= slew_um_s / fs.
Non-finite samples are replaced by the last output and counted. A soft-start ramp follows
start(); stop() ramps to zero before the output goes silent.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hostd.cyclestate import record


@dataclass
class OutputConfig:
    sample_rate_hz: float = 3000.0
    travel_um: float = 80.0  # full piezo travel; output is ± travel/2 about the centre
    slew_um_s: float = 60000.0  # 20 µm at 400 Hz needs 2π·400·20 ≈ 50,300 µm/s
    um_per_volt: float = 80.0 / 150.0  # piezo: ~80 µm at 150 V
    amp_gain: float = 15.0  # amplifier V/V
    dac_full_scale_v: float = 10.0  # DAC output at full positive code
    dac_bits: int = 16
    ramp_s: float = 0.05  # soft start and soft stop

    @property
    def um_per_code(self) -> float:
        return self.um_per_volt * self.amp_gain * self.dac_full_scale_v / ((1 << (self.dac_bits - 1)) - 1)

    @property
    def limit_code(self) -> int:
        """Largest code magnitude allowed by the displacement limit and the DAC."""
        return min(int(np.floor(self.travel_um / 2 / self.um_per_code)), (1 << (self.dac_bits - 1)) - 1)


class OutputStage(record("output")):
    """Its numeric state is the "output" record of hostd/device/cycle_state.toml."""

    def __init__(self, cfg: OutputConfig | None = None) -> None:
        self.cfg = cfg or OutputConfig()
        c = self.cfg
        for name in ("sample_rate_hz", "travel_um", "slew_um_s", "um_per_volt", "amp_gain",
                     "dac_full_scale_v", "ramp_s"):
            v = getattr(c, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"output.{name} must be a finite number > 0")
        if not 8 <= c.dac_bits <= 24:
            raise ValueError("output.dac_bits must be 8..24")
        self.limit_um = c.limit_code * c.um_per_code
        self.max_step_um = c.slew_um_s / c.sample_rate_hz
        self.ramp_step = 1.0 / max(1.0, c.ramp_s * c.sample_rate_hz)
        self._codes_per_um = 1.0 / c.um_per_code
        self._limit_code = c.limit_code
        self._code_dtype = np.int16 if c.dac_bits <= 16 else np.int32
        self.last_um = 0.0
        self.envelope = 0.0
        self.target_envelope = 0.0
        self.nonfinite = 0
        self.clipped = 0

    def start(self) -> None:
        self.target_envelope = 1.0

    def stop(self) -> None:
        self.target_envelope = 0.0

    def restart_from(self, um: float = 0.0) -> None:
        """Soft start again from a known output (the device's, after it ramped to zero on a
        stall or an underrun): the envelope starts from zero, so nothing jumps."""
        self.last_um = float(um)
        self.envelope = 0.0
        self.target_envelope = 1.0

    @property
    def silent(self) -> bool:
        return self.envelope == 0.0 and self.target_envelope == 0.0 and self.last_um == 0.0

    def process(self, x_um: np.ndarray) -> np.ndarray:
        """Displacements in µm -> limited displacements in µm (same length)."""
        x = np.asarray(x_um, dtype=np.float64)
        if x.size > 64 and self.envelope == self.target_envelope:
            fast = self._process_steady(x)
            if fast is not None:
                return fast
        out = x.tolist()
        last, env, target = self.last_um, self.envelope, self.target_envelope
        lim, step, ramp = self.limit_um, self.max_step_um, self.ramp_step
        isfinite = math.isfinite
        for i, v in enumerate(out):
            if not isfinite(v):
                self.nonfinite += 1
                v = last
            if env != target:
                env = min(env + ramp, 1.0) if target > env else max(env - ramp, 0.0)
            v *= env
            if v > lim or v < -lim:
                self.clipped += 1
                v = lim if v > 0 else -lim
            d = v - last
            if d > step:
                v = last + step
            elif d < -step:
                v = last - step
            out[i] = v
            last = v
        self.last_um, self.envelope = last, env
        return np.array(out)

    def _process_steady(self, x: np.ndarray) -> np.ndarray | None:
        """Vectorized path for long runs with a settled envelope: exact when no sample is
        non-finite and no step (after clipping) exceeds the slew limit; None otherwise, and
        the caller falls back to the per-sample loop (state untouched)."""
        if not np.all(np.isfinite(x)):
            return None
        y = x * self.envelope
        over = np.abs(y) > self.limit_um
        y = np.clip(y, -self.limit_um, self.limit_um)
        d = np.diff(y, prepend=self.last_um)
        if np.any(np.abs(d) > self.max_step_um):
            return None
        self.clipped += int(np.count_nonzero(over))
        self.last_um = float(y[-1])
        return y

    def to_codes(self, y_um: np.ndarray) -> np.ndarray:
        lc = self._limit_code
        codes = np.rint(np.asarray(y_um, dtype=np.float64) * self._codes_per_um).clip(-lc, lc)
        return codes.astype(self._code_dtype)
