"""Effects a scene can name. Each is a separate component, constructed only when named.

Closed-loop effects change what the host sees or when (encoder, transport, clock_drift,
cpu_load): when any is named the scene runs the host's real render pipeline batch by batch.
Output effects act on the command stream after the host (dac, actuator, finger_load).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np


class Effect:
    name = ""
    closed_loop = False

    def __init__(self, rng: np.random.Generator, **params) -> None:
        self.rng = rng
        for k, v in params.items():
            if k not in self.PARAMS:
                known = ", ".join(self.PARAMS) or "no fields"
                raise ValueError(f"effects.{self.name}: unknown field {k!r} (expected {known})")
            default = self.PARAMS[k]
            if isinstance(default, str):
                if not isinstance(v, str):
                    raise ValueError(f"effects.{self.name}.{k} must be a string")
            elif isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v) or v < 0:
                raise ValueError(f"effects.{self.name}.{k} must be a finite number >= 0")
        self.p = {**self.PARAMS, **params}
        self.check()

    PARAMS: ClassVar[dict] = {}

    def check(self) -> None:
        pass


class Encoder(Effect):
    """Quantization to the encoder's resolution, count noise and missed counts."""
    name, closed_loop = "encoder", True
    PARAMS: ClassVar[dict] = {"resolution_um": 0.4, "noise_counts": 0.0, "missed_count_prob": 0.0}

    def check(self) -> None:
        if self.p["resolution_um"] <= 0:
            raise ValueError("effects.encoder.resolution_um must be > 0")
        if self.p["missed_count_prob"] > 1:
            raise ValueError("effects.encoder.missed_count_prob must be <= 1")

    def counts(self, x_mm: np.ndarray) -> np.ndarray:
        from hostd.sim.chain import quantize_counts

        c = quantize_counts(x_mm, self.p["resolution_um"])
        if self.p["noise_counts"] > 0:
            c += np.round(self.rng.normal(0, self.p["noise_counts"], c.size)).astype(np.int64)
        if self.p["missed_count_prob"] > 0:  # each report may have lost counts, cumulatively
            lost = self.rng.random(c.size) < self.p["missed_count_prob"]
            c -= np.cumsum(lost)
        return c


class Transport(Effect):
    """Status reports arrive late (latency + jitter) or not at all; samples need a buffer."""
    name, closed_loop = "transport", True
    PARAMS: ClassVar[dict] = {"latency_ms": 1.0, "jitter_ms": 0.0, "loss": 0.0, "buffer_ms": 3.0}

    def check(self) -> None:
        if self.p["loss"] >= 1:
            raise ValueError("effects.transport.loss must be < 1")

    def arrivals(self, t_s: np.ndarray) -> np.ndarray:
        a = t_s + self.p["latency_ms"] * 1e-3
        if self.p["jitter_ms"] > 0:
            a = a + self.rng.exponential(self.p["jitter_ms"] * 1e-3, t_s.size)
        if self.p["loss"] > 0:
            a[self.rng.random(t_s.size) < self.p["loss"]] = np.inf
        return a


class ClockDrift(Effect):
    """The device's clock runs fast or slow by ppm against the hand's real time."""
    name, closed_loop = "clock_drift", True
    PARAMS: ClassVar[dict] = {"ppm": 500.0}

    def __init__(self, rng, **params) -> None:  # ppm may be negative
        ppm = params.pop("ppm", 500.0)
        if isinstance(ppm, bool) or not isinstance(ppm, int | float) or not abs(ppm) <= 1e5:
            raise ValueError("effects.clock_drift.ppm must be a number within ±100000")
        super().__init__(rng, **params)
        self.p["ppm"] = float(ppm)


class CpuLoad(Effect):
    """Other load stalls the host's pump now and then; a stall longer than the device's buffer
    is an underrun (the device ramps toward zero until samples arrive)."""
    name, closed_loop = "cpu_load", True
    PARAMS: ClassVar[dict] = {"stall_prob": 0.01, "stall_ms": 5.0}

    def stalls(self, n_batches: int, batch_s: float) -> np.ndarray:
        """Extra delay (s) of each batch's rendering."""
        hit = self.rng.random(n_batches) < self.p["stall_prob"]
        d = np.zeros(n_batches)
        d[hit] = self.p["stall_ms"] * 1e-3
        # a stall delays the batches after it until the host has caught up
        out = np.zeros(n_batches)
        debt = 0.0
        for i in range(n_batches):
            debt = max(0.0, debt - batch_s) + d[i]  # catching up takes no time: render is fast
            out[i] = debt
        return out


class Dac(Effect):
    """The DAC's quantization: commands become integer codes."""
    name = "dac"
    PARAMS: ClassVar[dict] = {}


class Actuator(Effect):
    """The actuator's dynamics (the rendering issue's model); the host's equalizer is enabled."""
    name = "actuator"
    PARAMS: ClassVar[dict] = {"model": "paper-parametric"}

    def check(self) -> None:
        from hostd.render.equalizer import load_actuator

        self.model = load_actuator(self.p["model"])


class FingerLoad(Effect):
    """The finger's stiffness and damping load the actuator: the displacement drops by
    1/(1 + stiffness_ratio) and the tissue's damping adds a first-order roll-off."""
    name = "finger_load"
    PARAMS: ClassVar[dict] = {"stiffness_ratio": 0.2, "corner_hz": 600.0}

    def check(self) -> None:
        if self.p["corner_hz"] <= 0:
            raise ValueError("effects.finger_load.corner_hz must be > 0")

    def apply(self, y: np.ndarray, fs: float) -> np.ndarray:
        import scipy.signal

        g = 1.0 / (1.0 + self.p["stiffness_ratio"])
        b, a = scipy.signal.butter(1, self.p["corner_hz"], fs=fs)
        return g * scipy.signal.lfilter(b, a, y)


REGISTRY: dict[str, type[Effect]] = {c.name: c for c in (Encoder, Transport, ClockDrift, CpuLoad, Dac,
                                                          Actuator, FingerLoad)}


@dataclass
class EffectSet:
    encoder: Encoder | None = None
    transport: Transport | None = None
    clock_drift: ClockDrift | None = None
    cpu_load: CpuLoad | None = None
    dac: Dac | None = None
    actuator: Actuator | None = None
    finger_load: FingerLoad | None = None

    @property
    def closed_loop(self) -> bool:
        return any(getattr(self, n) is not None and REGISTRY[n].closed_loop for n in REGISTRY)

    @property
    def names(self) -> list[str]:
        return [n for n in REGISTRY if getattr(self, n) is not None]


def build(spec: dict[str, dict], seed: int) -> EffectSet:
    """Construct exactly the named effects (and nothing else)."""
    es = EffectSet()
    for i, (name, params) in enumerate(spec.items()):
        cls = REGISTRY.get(name)
        if cls is None:
            raise ValueError(f"effects.{name}: unknown effect (known: {', '.join(REGISTRY)})")
        if not isinstance(params, dict):
            raise ValueError(f"effects.{name} must be a table [effects.{name}]")
        setattr(es, name, cls(np.random.default_rng([seed, i]), **dict(params)))
    return es
