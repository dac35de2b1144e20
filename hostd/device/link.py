"""The host end of the device link: handshake, limits, and buffer-fill flow control.

The device is the clock master. Every STATUS reports its buffer fill and the sequence number
of the last SAMPLES message it took in; messages sent after that are still in flight. The
host keeps fill + in flight at a target by sending just what is missing (the feedback of
asynchronous USB audio), so a device clock that runs fast or slow by ±500 ppm is followed
without an underrun. Play instants are in the device's clock.

"Now" in the device's clock is the host's monotonic clock plus an offset, estimated as the
largest (device time - host arrival time) over recent STATUS messages: a STATUS is never
received before it is sent, so the freshest one gives the tightest bound, and a backlog of
stale ones (read after a host stall) does not fool it. The bound decays at 1000 ppm so a
slow device clock is followed.

Transient write errors (a timeout, EAGAIN) are retried within the cycle and counted; only a
vanished device (DeviceGone) ends the link.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

from hostd.cyclestate import record
from hostd.device import fastlink
from hostd.device import protocol as pr
from hostd.errors import DeviceBusy, DeviceError, DeviceGone, DeviceVersion


@dataclass
class LinkStats(record("link_stats")):  # statuses, messages_sent, samples_sent: in the record
    bad_messages_received: int = 0
    last_status: dict = field(default_factory=dict)
    io_retries: int = 0  # transient write errors retried
    last_bad: str = ""  # what the last bad message was (its ProtocolError), for the log


# what names a display in its IDENT (limit_code and max_step_code follow SET_LIMITS: not identity)
IDENTITY = ("protocol_version", "fw_major", "fw_minor", "fw_patch", "dac_bits", "sample_rate_hz",
            "buffer_capacity", "max_samples", "um_per_count_nm")


class DeviceLink(record("link")):
    def __init__(self, transport, target_fill: int = 12) -> None:
        if not 1 <= target_fill <= pr.BUFFER_CAPACITY - pr.MAX_SAMPLES:
            raise DeviceError(f"target_fill must be 1..{pr.BUFFER_CAPACITY - pr.MAX_SAMPLES} samples")
        self.t = transport
        self.target_fill = target_fill
        self.ident: dict | None = None
        self.caps: dict | None = None
        self.render_status: dict | None = None
        self.stats = LinkStats()
        self._seq = 0
        self._un_n = 0  # SAMPLES messages not yet seen by the device: _un_seq, _un_cnt[:_un_n] (a record)
        self._time_hi = 0  # unwrapping the device's 32-bit µs clock
        self._last_us: int | None = None
        self.device_time_s = 0.0
        self.status_host_time = 0.0
        self._offset_s: float | None = None  # device time - host monotonic time (lower bound)
        self._offset_host_t = 0.0
        self._fill_from_seq: int | None = None  # after reset_stream: fill counts from this seq
        # callback(status dict, device_time_s, fresh): fresh is False for a STATUS that a newer
        # one in the same poll makes stale (a backlog read after a host stall): counters and
        # faults still count, but nothing needs its encoder reading
        self.on_status = None
        self.on_render_status = None  # callback(RENDER_STATUS dict): device mode's counters
        self.retry_budget_s = 0.0005  # how long one message may be retried within a cycle

    # ---------------------------------------------------------------- control
    def handshake(self, timeout_s: float = 1.0) -> dict:
        """IDENTIFY, then check that the device speaks our protocol with our parameters."""
        self.ident = None
        self.caps = None
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

    def await_caps(self, timeout_s: float = 2.0) -> dict | None:
        """A v2 display's CAPS, which it sends right after IDENT: waited for up to timeout_s, and
        asked for once more (IDENTIFY again) halfway, since a report can be lost (a slow or
        emulated host missed it and then rendered on the host for the whole connection, VM rig).
        None for a v1 display or when none came."""
        if self.caps is not None or (self.ident or {}).get("protocol_version", 0) < 2:
            return self.caps
        t0 = time.monotonic()
        asked = False
        while self.caps is None and (now := time.monotonic()) < t0 + timeout_s:
            if not asked and now >= t0 + timeout_s / 2:
                self._send(pr.encode("IDENTIFY"), must=True)
                asked = True
            self.poll(0.05)
        return self.caps

    def _send(self, msg: bytes, must: bool = False) -> None:
        """Send one message; a transient error is retried for retry_budget_s (a control
        message that must arrive: up to 50 ms), then DeviceBusy is raised."""
        deadline = time.monotonic() + (0.05 if must else self.retry_budget_s)
        while True:
            try:
                self.t.send(msg)
                self.stats.messages_sent += 1
                return
            except DeviceBusy:
                self.stats.io_retries += 1
                if time.monotonic() >= deadline:
                    raise
                time.sleep(0.0001)

    def set_limits(self, limit_code: int, max_step_code: int) -> None:
        self._send(pr.encode("SET_LIMITS", limit_code=limit_code, max_step_code=max_step_code), True)

    def set_timeout(self, timeout_ms: int) -> None:
        self._send(pr.encode("SET_TIMEOUT", timeout_ms=timeout_ms), True)

    def start(self) -> None:
        self._send(pr.encode("START"), True)

    def stop(self) -> None:
        self._send(pr.encode("STOP"), True)
        self._un_n = 0

    def reset_stream(self) -> None:
        """STOP, and forget what the device holds: it clears its buffer when it takes STOP,
        so until it acknowledges a SAMPLES message sent after this, its reported fill is
        stale and counts as zero."""
        self.stop()
        self._fill_from_seq = self.next_seq()

    def next_seq(self) -> int:
        return (self._seq + 1) & 0xFFFF

    def acked(self, seq: int) -> bool:
        """Has the device taken the SAMPLES message `seq` (or a later one)?"""
        s = self.stats.last_status
        return bool(s) and ((s["last_seq"] - seq) & 0xFFFF) < 0x8000 and self._seq_sent_since(seq)

    def _seq_sent_since(self, seq: int) -> bool:
        return ((self._seq - seq) & 0xFFFF) < 0x8000

    # ---------------------------------------------------------------- status
    def _status(self, f: dict, fresh: bool = True) -> None:
        us = f["device_time_us"]
        if self._last_us is not None and us < self._last_us and self._last_us - us > 1 << 31:
            self._time_hi += 1 << 32
        self._last_us = us
        self.device_time_s = (self._time_hi + us) * 1e-6
        now = self.t.now()
        self.status_host_time = now
        off = self.device_time_s - now
        if self._offset_s is None or off < self._offset_s - 30.0:  # first, or the device reset
            self._offset_s = off
        else:
            decayed = self._offset_s - 1e-3 * (now - self._offset_host_t)
            self._offset_s = max(off, decayed)
        self._offset_host_t = now
        # messages up to last_seq have reached the device
        last, k = f["last_seq"], 0
        while k < self._un_n and ((last - self._un_seq[k]) & 0xFFFF) < 0x8000:
            k += 1
        self._drop_unacked(k)
        self.stats.statuses += 1
        self.stats.last_status = f
        if self._fill_from_seq is not None and self.acked(self._fill_from_seq):
            self._fill_from_seq = None  # the device has taken STOP and what followed it
        if self.on_status is not None:
            self.on_status(f, self.device_time_s, fresh)

    def _take(self, m: bytes, fresh: bool = True) -> str | None:
        """Decode and act on one message from the device; returns its name (None if bad)."""
        try:
            name, f = fastlink.decode(m)  # protocol.decode, compiled when built
        except pr.ProtocolError as e:
            self.stats.bad_messages_received += 1
            self.stats.last_bad = str(e)
            return None
        if name == "STATUS":
            self._status(f, fresh)
        elif name == "IDENT":
            if self.ident is not None and any(f[k] != self.ident[k] for k in IDENTITY):
                self._changed_identity("IDENT", self.ident, f)
            self.ident = f
        elif name == "CAPS":
            if self.caps is not None and f != self.caps:
                self._changed_identity("CAPS", self.caps, f)
            self.caps = f  # protocol v2: what the display can render (after IDENT)
        elif name == "RENDER_STATUS":
            self.render_status = f
            if self.on_render_status is not None:
                self.on_render_status(f)
        return name

    def _changed_identity(self, what: str, old: dict, new: dict) -> None:
        """Another IDENT or CAPS mid-session (another firmware, a swapped board behind the same
        port, a device that lies): a new device. Nothing it said before is believed: the link
        ends (DeviceGone) and the pump identifies it again as on a replug."""
        diff = ", ".join(f"{k} {old.get(k)} -> {new.get(k)}" for k in new
                         if (k in IDENTITY or what == "CAPS") and k != "id" and new.get(k) != old.get(k))
        raise DeviceGone(f"{self.t.describe()} changed its identity mid-session ({what}: {diff}): a new "
                         "device; identifying it again as on a replug")

    FRESH = 32  # statuses of one poll whose encoder readings are used (the motion window's 16, +)

    def poll(self, timeout_s: float = 0.0, read: bool = True) -> int:
        """Take in every message waiting; returns how many STATUS arrived. read=False: only those
        the transport has read already (Transport.gather did; a tty's read that finds nothing
        first waits for the kernel's buffer work, a wake-up of its own)."""
        msgs = []
        if timeout_s > 0:
            m = self.t.recv(timeout_s)
            if m is None:
                return 0
            msgs.append(m)
        # one read of a byte stream, not one per message plus an empty one
        msgs += self.t.drain() if read else self.t.take()
        stale = len(msgs) - self.FRESH
        n = 0
        for i, m in enumerate(msgs):
            if self._take(m, fresh=i >= stale) == "STATUS":
                n += 1
        return n

    # A STATUS older than this plus two of its state's report periods, on the device's clock as
    # the link knows it (device_now_s), is a backlog's, not the device's present.
    CURRENT_SLACK_S = 0.005

    def _status_period_s(self) -> float:
        s = self.stats.last_status
        rendering = bool(s) and s["state"] == pr.STATES["RENDERING"]
        return (pr.R if rendering else pr.P)["status_period_ticks"] / pr.SAMPLE_RATE_HZ

    def stale(self) -> bool:
        """Is the latest STATUS taken known to be from a backlog: older on the device's clock
        (as far as the link knows it) than two of its report periods and CURRENT_SLACK_S? False
        when there is none, or when nothing fresher ever came to tell."""
        if not self.stats.last_status:
            return False
        return self.device_time_s < self.device_now_s() - 2 * self._status_period_s() - self.CURRENT_SLACK_S

    def catch_up(self, budget_s: float = 0.25) -> bool:
        """Read the link up to the device's present: take in every message waiting, and go on
        reading while the reports run ahead of the host's clock (a backlog: many reports, each
        from later on the device's clock, in one short read) or are stale(), for at most
        budget_s. A link left unread for a while (a texture built between the handshake and the
        start) holds a tty buffer of old reports (a pty: ~700 STATUS, the device's first 0.7 s
        of the pause), handed over 4 KB per read as a kernel worker refills it; flow control on
        them counts what the device took since as still in flight, and sends nothing (a pty's
        backlog took 7-13 ms to read here). Returns whether the last read kept pace (False: the
        budget ran out, or the device is silent)."""
        deadline = time.monotonic() + budget_s
        self.poll(0.0)
        while (h0 := time.monotonic()) < deadline:
            d0 = self.device_time_s
            # the next report, and all that waits behind it: a current link has one or two
            n = self.poll(min(deadline - h0, 0.005))
            h1 = time.monotonic()
            if n == 0:  # none for 5 ms: nothing behind (or a device that reports every 50 ms),
                if not self.stale():  # unless what it said last is known to be old: then the
                    return True  # tty's worker has not handed the rest over yet (a busy machine)
                continue
            ahead_s = (self.device_time_s - d0) - (h1 - h0)
            if ahead_s <= 2 * self._status_period_s() + self.CURRENT_SLACK_S and not self.stale():
                return True
        return False

    @property
    def in_flight(self) -> int:
        return sum(self._un_cnt[: self._un_n])

    def _drop_unacked(self, k: int) -> None:
        """Forget the first k unacknowledged messages (the rest move to the front)."""
        n = self._un_n - k
        if k:
            self._un_seq[:n], self._un_cnt[:n] = self._un_seq[k : k + n], self._un_cnt[k : k + n]
            self._un_n = n

    def device_now_s(self) -> float:
        """The device's clock now (its latest STATUS's time if none has set the offset yet)."""
        if self._offset_s is None:
            return self.device_time_s
        return max(self.device_time_s, self.t.now() + self._offset_s)

    def _device_fill(self) -> float:
        """Samples in the device's buffer now, from its latest report: minus what it has
        played since (only while it runs), zero while its report predates a reset_stream."""
        s = self.stats.last_status
        if not s or self._fill_from_seq is not None:
            return 0.0
        fill = float(s["buffer_fill"])
        if s["state"] == pr.STATES["RUNNING"]:
            fill -= (self.device_now_s() - self.device_time_s) * pr.SAMPLE_RATE_HZ
        return max(0.0, fill)

    def fill_estimate(self) -> float:
        """Samples queued on the device now, plus those in flight to it."""
        return self._device_fill() + self.in_flight

    def next_play_time_s(self) -> float:
        """Device-clock instant at which the next sample sent will be played: after what the
        device holds and what is in flight, and never before now."""
        s = self.stats.last_status
        fill = s["buffer_fill"] if s and self._fill_from_seq is None else 0
        queued = self.device_time_s + (fill + self.in_flight + 1) / pr.SAMPLE_RATE_HZ
        return max(queued, self.device_now_s() + (self.in_flight + 1) / pr.SAMPLE_RATE_HZ)

    def wanted(self, fill: float | None = None) -> int:
        """How many samples to send now to bring the device back to its target fill."""
        fill = self.fill_estimate() if fill is None else fill
        return max(0, min(round(self.target_fill - fill), 2 * pr.MAX_SAMPLES))

    def wanted_to_prime(self) -> int:
        """Samples to send before START: the whole target at once."""
        return max(0, round(self.target_fill - self.fill_estimate()))

    def send_samples(self, codes) -> int:
        """Send codes (an int16 array: the fast case; or any sequence of ints) in SAMPLES
        messages; returns how many went out (a transient error after the first message ends
        the call early; before it, DeviceBusy is raised)."""
        if not hasattr(codes, "dtype"):
            codes = list(codes)
        sent = 0
        for i in range(0, len(codes), pr.MAX_SAMPLES):
            part = codes[i : i + pr.MAX_SAMPLES]
            seq = (self._seq + 1) & 0xFFFF
            try:
                self._send(fastlink.encode_samples(seq, part))
            except DeviceBusy:
                if sent == 0:
                    raise
                break
            self._seq = seq
            if self._un_n == len(self._un_seq):  # (the flow control never sends this far ahead)
                self._drop_unacked(1)
            self._un_seq[self._un_n], self._un_cnt[self._un_n] = seq, len(part)
            self._un_n += 1
            self.stats.samples_sent += len(part)
            sent += len(part)
        return sent
