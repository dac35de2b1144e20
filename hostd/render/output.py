"""Output stage: displacement (µm, about the travel's centre) to signed DAC codes, safely.

Whatever enters (NaN, Inf, a huge value, a jump), what leaves respects:
  |displacement| <= travel_um / 2   and   |step between samples| <= slew_um_s / fs.
Non-finite samples are replaced by the last output and counted. A soft-start ramp follows
start(); stop() ramps to zero before the output goes silent.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


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


class OutputStage:
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
        self.last_um = 0.0
        self.envelope = 0.0
        self.target_envelope = 0.0
        self.nonfinite = 0
        self.clipped = 0

    def start(self) -> None:
        self.target_envelope = 1.0

    def stop(self) -> None:
        self.target_envelope = 0.0

    @property
    def silent(self) -> bool:
        return self.envelope == 0.0 and self.target_envelope == 0.0 and self.last_um == 0.0

    def process(self, x_um: np.ndarray) -> np.ndarray:
        """Displacements in µm -> limited displacements in µm (same length)."""
        x = np.asarray(x_um, dtype=np.float64)
        out = np.empty(x.size)
        last, env = self.last_um, self.envelope
        lim, step = self.limit_um, self.max_step_um
        for i in range(x.size):
            v = x[i]
            if not np.isfinite(v):
                self.nonfinite += 1
                v = last
            if env != self.target_envelope:
                if self.target_envelope > env:
                    env = min(env + self.ramp_step, 1.0)
                else:
                    env = max(env - self.ramp_step, 0.0)
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
        return out

    def to_codes(self, y_um: np.ndarray) -> np.ndarray:
        lc = self.cfg.limit_code
        codes = np.clip(np.rint(np.asarray(y_um) / self.cfg.um_per_code), -lc, lc)
        return codes.astype(np.int16 if self.cfg.dac_bits <= 16 else np.int32)
