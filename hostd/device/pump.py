"""The real-time pump: every cycle, read the device's status, render what the device's
buffer is missing for the instants it will play it, and send it.

Absolute-deadline scheduling (the next cycle is due at start + k x period, not "now +
period"), so a late cycle does not shift the ones after it; lateness past half a period is
counted as a deadline miss. The renderer supplies codes for device-clock play instants.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from hostd.device import protocol as pr
from hostd.device.link import DeviceLink


@dataclass
class PumpStats:
    cycles: int = 0
    deadline_misses: int = 0
    late_batches: int = 0  # a batch sent when the device had less than one batch queued
    max_late_us: float = 0.0
    samples: int = 0


class Pump:
    def __init__(self, link: DeviceLink, renderer, period_s: float = 0.001) -> None:
        self.renderer = renderer
        self.period_s = period_s
        self.stats = PumpStats()
        self.sent_codes: list[np.ndarray] = []  # kept when record=True (tests, demo summary)
        self.record = False
        self.attach(link)

    def attach(self, link: DeviceLink) -> None:
        """Stream to `link` from now on (after a reconnection); the counters carry on."""
        self.link = link
        link.on_status = self._on_status

    def _on_status(self, f: dict, device_time_s: float) -> None:
        if self.renderer is not None:
            self.renderer.on_encoder(device_time_s, f["encoder_count"])

    def step(self) -> int:
        """One cycle: poll, render, send. Returns the number of samples sent."""
        link = self.link
        link.poll()
        fill = link.fill_estimate()
        n = link.wanted(fill)
        if n == 0 or self.renderer is None:
            return 0
        if fill < self.renderer.cfg.samples_per_batch:
            self.stats.late_batches += 1
        t0 = link.next_play_time_s()
        t_play = t0 + np.arange(n) / pr.SAMPLE_RATE_HZ
        codes = self.renderer.render_codes(t_play)
        link.send_samples(codes.tolist())
        if self.record:
            self.sent_codes.append(codes)
        self.stats.samples += n
        return n

    def run(self, duration_s: float | None = None, stop=None, each_cycle=None) -> PumpStats:
        """Cycle until duration_s has passed or stop() returns True; each_cycle() runs at the
        start of every cycle (the daemon's pump takes its commands and publishes counters)."""
        start = time.monotonic()
        k = 0
        while True:
            now = time.monotonic()
            if duration_s is not None and now - start >= duration_s:
                break
            if each_cycle is not None:
                each_cycle()
            if stop is not None and stop():
                break
            self.step()
            self.stats.cycles += 1
            k += 1
            due = start + k * self.period_s
            now = time.monotonic()
            if now > due:
                late = (now - due) * 1e6
                self.stats.max_late_us = max(self.stats.max_late_us, late)
                if late > self.period_s * 0.5e6:
                    self.stats.deadline_misses += 1
                k = int((now - start) / self.period_s)  # skip missed cycles, keep the grid
                continue
            time.sleep(max(0.0, due - now))
        return self.stats
