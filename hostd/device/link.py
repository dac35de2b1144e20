"""The host end of the device link: handshake, limits, and buffer-fill flow control.

The device is the clock master. Every STATUS reports its buffer fill and the sequence number
of the last SAMPLES message it took in; messages sent after that are still in flight. The
host keeps fill + in flight at a target by sending just what is missing (the feedback of
asynchronous USB audio), so a device clock that runs fast or slow by ±500 ppm is followed
without an underrun. Play instants are in the device's clock: the next sample sent plays
(fill + in flight + 1) ticks after the latest STATUS's device time.
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, field

from hostd.device import protocol as pr
from hostd.errors import DeviceError, DeviceVersion


@dataclass
class LinkStats:
    statuses: int = 0
    messages_sent: int = 0
    samples_sent: int = 0
    bad_messages_received: int = 0
    last_status: dict = field(default_factory=dict)
    underruns_at_start: int | None = None

    @property
    def underruns(self) -> int:
        """Device underruns since streaming started."""
        s = self.last_status
        if not s or self.underruns_at_start is None:
            return 0
        return (s["underruns"] - self.underruns_at_start) & 0xFFFF


class DeviceLink:
    def __init__(self, transport, target_fill: int = 12) -> None:
        if not 1 <= target_fill <= pr.BUFFER_CAPACITY - pr.MAX_SAMPLES:
            raise DeviceError(f"target_fill must be 1..{pr.BUFFER_CAPACITY - pr.MAX_SAMPLES} samples")
        self.t = transport
        self.target_fill = target_fill
        self.ident: dict | None = None
        self.stats = LinkStats()
        self._seq = 0
        self._unacked: deque[tuple[int, int]] = deque()  # (seq, count) not yet seen by the device
        self._time_hi = 0  # unwrapping the device's 32-bit µs clock
        self._last_us: int | None = None
        self.device_time_s = 0.0
        self.status_host_time = 0.0
        self.on_status = None  # callback(status dict, device_time_s)

    # ---------------------------------------------------------------- control
    def handshake(self, timeout_s: float = 1.0) -> dict:
        """IDENTIFY, then check that the device speaks our protocol with our parameters."""
        self.ident = None
        self.t.send(pr.encode("IDENTIFY"))
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            m = self.t.recv(0.01)
            if m is not None and self._take(m) == "IDENT":
                break
        if self.ident is None:
            raise DeviceError(f"{self.t.describe()}: no answer to IDENTIFY within {timeout_s:g} s; "
                              "is it a hostd display running its firmware?")
        f = self.ident
        pr.check_version(f, self.t.describe())  # v1 and v2 devices stream alike
        for key, want in (("sample_rate_hz", pr.SAMPLE_RATE_HZ), ("dac_bits", pr.P["dac_bits"]),
                          ("max_samples", pr.MAX_SAMPLES)):
            if f[key] != want:
                raise DeviceVersion(f"{self.t.describe()} reports {key}={f[key]}, hostd expects {want}")
        return f

    def set_limits(self, limit_code: int, max_step_code: int) -> None:
        self.t.send(pr.encode("SET_LIMITS", limit_code=limit_code, max_step_code=max_step_code))

    def set_timeout(self, timeout_ms: int) -> None:
        self.t.send(pr.encode("SET_TIMEOUT", timeout_ms=timeout_ms))

    def start(self) -> None:
        self.t.send(pr.encode("START"))
        self.stats.messages_sent += 1

    def stop(self) -> None:
        self.t.send(pr.encode("STOP"))
        self._unacked.clear()

    # ---------------------------------------------------------------- status
    def _status(self, f: dict) -> None:
        us = f["device_time_us"]
        if self._last_us is not None and us < self._last_us and self._last_us - us > 1 << 31:
            self._time_hi += 1 << 32
        self._last_us = us
        self.device_time_s = (self._time_hi + us) * 1e-6
        self.status_host_time = time.monotonic()
        # messages up to last_seq have reached the device
        last = f["last_seq"]
        while self._unacked and ((last - self._unacked[0][0]) & 0xFFFF) < 0x8000:
            self._unacked.popleft()
        self.stats.statuses += 1
        self.stats.last_status = f
        if self.on_status is not None:
            self.on_status(f, self.device_time_s)

    def _take(self, m: bytes) -> str | None:
        """Decode and act on one message from the device; returns its name (None if bad)."""
        try:
            name, f = pr.decode(m)
        except pr.ProtocolError:
            self.stats.bad_messages_received += 1
            return None
        if name == "STATUS":
            self._status(f)
        elif name == "IDENT":
            self.ident = f
        return name

    def poll(self, timeout_s: float = 0.0) -> int:
        """Take in every message waiting; returns how many STATUS arrived."""
        n = 0
        timeout = timeout_s
        while (m := self.t.recv(timeout)) is not None:
            timeout = 0.0
            if self._take(m) == "STATUS":
                n += 1
        return n

    @property
    def in_flight(self) -> int:
        return sum(c for _, c in self._unacked)

    def fill_estimate(self) -> float:
        """Samples queued on the device now: its last report, plus what is in flight, minus
        what it has played since the report (host time elapsed x rate)."""
        s = self.stats.last_status
        if not s:
            return float(self.in_flight)
        played = (time.monotonic() - self.status_host_time) * pr.SAMPLE_RATE_HZ
        return max(0.0, s["buffer_fill"] - played) + self.in_flight

    def next_play_time_s(self) -> float:
        """Device-clock instant at which the next sample sent will be played."""
        s = self.stats.last_status
        fill = s["buffer_fill"] if s else 0
        return self.device_time_s + (fill + self.in_flight + 1) / pr.SAMPLE_RATE_HZ

    def wanted(self, fill: float | None = None) -> int:
        """How many samples to send now to bring the device back to its target fill."""
        fill = self.fill_estimate() if fill is None else fill
        return max(0, min(round(self.target_fill - fill), 2 * pr.MAX_SAMPLES))

    def send_samples(self, codes) -> None:
        codes = list(codes)
        for i in range(0, len(codes), pr.MAX_SAMPLES):
            part = codes[i : i + pr.MAX_SAMPLES]
            self._seq = (self._seq + 1) & 0xFFFF
            self.t.send(pr.encode("SAMPLES", seq=self._seq, codes=part))
            self._unacked.append((self._seq, len(part)))
            self.stats.messages_sent += 1
            self.stats.samples_sent += len(part)
