"""An in-process simulated display: the firmware core's behaviour in Python.

It follows firmware/src/core.c message for message (same limits, ramps, counters, STATUS
every 3 ticks) so the daemon and the tests can run where neither USB nor a C compiler is
available; tests/test_device.py runs the same golden vectors through both. Device-side
rendering (protocol v2) runs hostd.device.fwmodel, the float32 model of firmware/src/render.c,
with encoder edges at the simulated hand's true times; `protocol_version=1` simulates a
version-1 display (no CAPS, render messages are malformed to it). Time is either
real (ticks are run lazily, as many as have elapsed, whenever the host sends or receives)
or manual (`advance(ticks)`), and the hand is any hostd.sim.hand model.
"""

from __future__ import annotations

import time
from collections import deque

import numpy as np

from hostd.device import protocol as pr
from hostd.device.backend import Transport
from hostd.device.fwmodel import EDGE_HZ, RenderModel, hand_edges

S = pr.STATES
F = pr.FAULTS
RAMP_STEP = max(1, pr.LIMIT_CODE // pr.P["ramp_ticks"])
RENDER_IDS = {k for k, v in pr.IDS.items() if 0x20 <= v < 0x30}
EDGE_SUBSTEPS = 8  # hand samples per tick for the edge times (linear in between)
EDGE_BLOCK_TICKS = 30  # the hand's edges are computed 10 ms at a time


class SimDevice:
    def __init__(self, hand=None, clock_ppm: float = 0.0, protocol_version: int = pr.VERSION) -> None:
        self.ring: deque[int] = deque()
        self.state = S["IDLE"]
        self.faults = 0
        self.out = 0
        self.limit_code = pr.LIMIT_CODE
        self.max_step_code = pr.MAX_STEP_CODE
        self.timeout_ms = pr.P["default_timeout_ms"]
        self.ticks = 0
        self.samples_played = 0
        self.last_rx_us = 0
        self.last_seq = 0
        self.underruns = 0
        self.malformed = 0
        self.encoder_errors = 0
        self.idle_ticks = 0  # neither playing nor rendering (RENDER_STATUS)
        self.in_underrun = False
        self.hand = hand
        self.clock_ppm = clock_ppm
        self.outbox: deque[bytes] = deque()
        # codes popped from the buffer, in order; kept only when asked (tests): a daemon on the
        # simulated display runs for days
        self.played_log: list[int] | None = None
        self.protocol_version = protocol_version
        self.render = RenderModel(self._count_at(0.0))
        self._edge_s = 0.0  # device time up to which the hand's edges are computed
        self._edge_t = np.zeros(0)  # computed, not yet given to the renderer: times (s), counts
        self._edge_c = np.zeros(0, dtype=np.int64)

    def time_us(self) -> int:
        return (self.ticks * 1_000_000 // pr.SAMPLE_RATE_HZ) & 0xFFFFFFFF

    def encoder_count(self) -> int:
        return self._count_at(self.ticks / pr.SAMPLE_RATE_HZ) & 0xFFFFFFFF

    def _count_at(self, t_device_s: float) -> int:
        if self.hand is None:
            return 0
        t = t_device_s * (1 + self.clock_ppm * 1e-6)  # the hand's real time
        x_mm = float(self.hand.position_mm(t))
        return round(x_mm * 1e6 / pr.P["um_per_count_nm"])

    def _feed_edges(self, t_device_s: float) -> None:
        """The hand's encoder edges up to t_device_s, at their true times, to the renderer."""
        if self.hand is None:
            return
        if t_device_s > self._edge_s:  # the next block of the hand's edges
            end = max(t_device_s, self._edge_s + EDGE_BLOCK_TICKS / pr.SAMPLE_RATE_HZ)
            n = max(2, round((end - self._edge_s) * pr.SAMPLE_RATE_HZ * EDGE_SUBSTEPS) + 1)
            t = np.linspace(self._edge_s, end, n)
            x = self.hand.position_mm(t * (1 + self.clock_ppm * 1e-6))
            times, counts = hand_edges(t, x, pr.P["um_per_count_nm"] * 1e-3)
            self._edge_t = np.concatenate((self._edge_t, times))
            self._edge_c = np.concatenate((self._edge_c, counts))
            self._edge_s = end
        k = int(np.searchsorted(self._edge_t, t_device_s, side="right"))
        if k:
            self.render.edges(self._edge_c[:k], np.rint(self._edge_t[:k] * EDGE_HZ).astype(np.int64))
            self._edge_t, self._edge_c = self._edge_t[k:], self._edge_c[k:]

    def on_message(self, m: bytes) -> None:
        try:
            name, f = pr.decode(m)
        except pr.ProtocolError:
            self.malformed += 1
            return
        if pr.IDS[name] >= 0x80 or (name == "SAMPLES" and f["flags"] != 0):  # device->host ids
            self.malformed += 1
            return
        if name in RENDER_IDS:
            if self.protocol_version < 2:  # unknown ids to a version-1 display
                self.malformed += 1
                return
            if name == "START_RENDER" and not self.render.on and self.hand is not None:  # track from here
                now_s = self.ticks / pr.SAMPLE_RATE_HZ
                self.render.edge(self._count_at(now_s), round(now_s * EDGE_HZ))
                self._edge_s, self._edge_t, self._edge_c = now_s, np.zeros(0), np.zeros(0, dtype=np.int64)
            self.render.on_message(self, name, f)
            self.last_rx_us = self.time_us()
            return
        zero_step = name == "SET_LIMITS" and f["max_step_code"] == 0
        if zero_step or (name == "SET_TIMEOUT" and f["timeout_ms"] == 0):
            self.malformed += 1
            return
        if name == "SAMPLES":
            if len(self.ring) + f["count"] > pr.BUFFER_CAPACITY:
                self.faults |= F["OVERFLOW"]
            else:
                self.ring.extend(f["codes"])
            self.last_seq = f["seq"]
        elif name == "START":
            self.render.halt()
            self.state = S["RUNNING"]
            self.in_underrun = False
        elif name == "STOP":
            if self.state in (S["RUNNING"], S["RENDERING"]):
                self.state = S["RAMP_DOWN"]
            self.render.halt()
            self.ring.clear()
        elif name == "SET_LIMITS":
            self.limit_code = min(f["limit_code"], pr.LIMIT_CODE)
            self.max_step_code = min(f["max_step_code"], pr.MAX_STEP_CODE)
        elif name == "SET_TIMEOUT":
            self.timeout_ms = f["timeout_ms"]
        elif name == "IDENTIFY":
            self.outbox.append(self.ident())
            if self.protocol_version >= 2:
                self.outbox.append(self.caps())
        self.last_rx_us = self.time_us()

    def ident(self) -> bytes:
        fw = pr.P["fw_version"] if self.protocol_version >= 2 else [0, 1, 0]
        return pr.encode("IDENT", protocol_version=self.protocol_version, fw_major=fw[0],
                         fw_minor=fw[1], fw_patch=fw[2],
                         dac_bits=pr.P["dac_bits"], sample_rate_hz=pr.SAMPLE_RATE_HZ,
                         limit_code=self.limit_code, max_step_code=self.max_step_code,
                         buffer_capacity=pr.BUFFER_CAPACITY, max_samples=pr.MAX_SAMPLES,
                         um_per_count_nm=pr.P["um_per_count_nm"])

    @staticmethod
    def caps() -> bytes:
        r = pr.R
        return pr.encode("CAPS", render=1, max_components=r["max_components"], max_sections=r["max_sections"],
                         chunk_coeffs=r["chunk_coeffs"], edge_clock_hz=r["edge_clock_hz"],
                         xfade_ticks=r["xfade_ticks"])

    @staticmethod
    def _toward_zero(v: int) -> int:
        return v - RAMP_STEP if v > RAMP_STEP else v + RAMP_STEP if v < -RAMP_STEP else 0

    def tick(self) -> None:
        self.ticks += 1
        now = self.time_us()
        if self.state == S["RUNNING"] and (now - self.last_rx_us) & 0xFFFFFFFF > self.timeout_ms * 1000:
            self.state = S["RAMP_DOWN"]
            self.faults |= F["HOST_TIMEOUT"]
            self.ring.clear()
        if self.state == S["RUNNING"]:
            if self.ring:
                target = self.ring.popleft()
                self.in_underrun = False
                self.samples_played += 1
                if self.played_log is not None:
                    self.played_log.append(target)
            else:
                if not self.in_underrun:
                    self.underruns += 1
                    self.in_underrun = True
                self.faults |= F["UNDERRUN"]
                target = self._toward_zero(self.out)
        elif self.state == S["RENDERING"]:
            self._feed_edges((self.ticks - 1) / pr.SAMPLE_RATE_HZ)  # up to this tick's instant
            target = self.render.tick(self)
        else:
            target = self._toward_zero(self.out)
            self.idle_ticks += 1
            if self.state == S["RAMP_DOWN"] and target == 0:
                self.state = S["IDLE"]
        lim, step = self.limit_code, self.max_step_code
        if abs(target) > lim:
            target = lim if target > 0 else -lim
            self.faults |= F["CLIPPED"]
        d = target - self.out
        if abs(d) > step:
            target = self.out + (step if d > 0 else -step)
            self.faults |= F["SLEWED"]
        self.out = target
        if self.ticks % self.status_period() == 0:
            self.outbox.append(self.status())
            self.faults = 0

    def status_period(self) -> int:
        """Ticks between STATUS messages: every 1 ms, every 300 ms while rendering (core.c)."""
        return pr.R["status_period_ticks"] if self.state == S["RENDERING"] else pr.P["status_period_ticks"]

    def ticks_to_next_message(self) -> int:
        """Ticks until the device sends its next STATUS (0: something is waiting now)."""
        if self.outbox:
            return 0
        p = self.status_period()
        return p - self.ticks % p

    def status(self) -> bytes:
        return pr.encode("STATUS", state=self.state, fault_flags=self.faults, device_time_us=self.time_us(),
                         encoder_count=self.encoder_count(), samples_played=self.samples_played & 0xFFFFFFFF,
                         buffer_fill=len(self.ring), last_seq=self.last_seq,
                         underruns=self.underruns & 0xFFFF, malformed=self.malformed & 0xFFFF,
                         encoder_errors=self.encoder_errors & 0xFFFF)


class SimTransport(Transport):
    """A Transport whose device is a SimDevice, ticking in real time (default) or manually."""

    name = "sim"

    def __init__(self, device: SimDevice | None = None, realtime: bool = True, hand=None,
                 clock_ppm: float = 0.0) -> None:
        if hand is None and device is None:
            from hostd.sim.hand import Metronome

            hand = Metronome()
        self.device = device or SimDevice(hand=hand, clock_ppm=clock_ppm)
        self.realtime = realtime
        self._t0 = time.monotonic()
        self.closed = False

    def _catch_up(self) -> None:
        if not self.realtime:
            return
        rate = pr.SAMPLE_RATE_HZ * (1 + self.device.clock_ppm * 1e-6)
        due = int((time.monotonic() - self._t0) * rate)
        for _ in range(min(due - self.device.ticks, 3000)):  # at most 1 s per call
            self.device.tick()
        if due - self.device.ticks > 3000:  # far behind (debugger, suspend): jump
            self.device.ticks = due

    def now(self) -> float:
        if self.realtime:
            return time.monotonic()
        return self.device.ticks / pr.SAMPLE_RATE_HZ  # manual: host time follows the device

    def advance(self, ticks: int) -> None:
        for _ in range(ticks):
            self.device.tick()

    def send(self, msg: bytes) -> None:
        if self.closed:
            from hostd.errors import DeviceGone

            raise DeviceGone("simulated display closed")
        self._catch_up()
        self.device.on_message(msg)

    def pending(self) -> bool:
        self._catch_up()
        return bool(self.device.outbox)

    def wait(self, timeout_s: float, fds=()) -> bool:
        """Sleep until the simulated display's next message is due (it has no descriptor), one
        of `fds` is readable, or timeout_s; a manual clock advances by the time waited."""
        import select

        if self.pending():
            return True
        due_s = self.device.ticks_to_next_message() / (pr.SAMPLE_RATE_HZ * (1 + self.device.clock_ppm * 1e-6))
        if not self.realtime:
            ticks = round(min(timeout_s, due_s) * pr.SAMPLE_RATE_HZ)
            self.advance(max(1, ticks))
            return bool(self.device.outbox)
        ready, _, _ = select.select(list(fds), [], [], max(0.0, min(timeout_s, due_s)))
        return not ready and self.pending()

    def recv(self, timeout_s: float = 0.0) -> bytes | None:
        deadline = time.monotonic() + timeout_s
        while True:
            self._catch_up()
            if self.device.outbox:
                return self.device.outbox.popleft()
            if time.monotonic() >= deadline:
                return None
            time.sleep(0.0002)

    def drain(self) -> list[bytes]:
        """Every message due now, after one catch-up: a display simulated slower than real time
        (a starved machine) always had one more due, and a drain by recv() never ended."""
        self._catch_up()
        out = list(self.device.outbox)
        self.device.outbox.clear()
        return out

    def close(self) -> None:
        self.closed = True
