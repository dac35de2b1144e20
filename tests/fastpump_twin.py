"""Differential harness for the compiled pump cycle (hostd.device.fastpump) against its
reference, Pump.step: two identical host setups on real ptys (SerialTransport on the slave
side, a fake host clock), one stepped by `pump.step()`, the other by `fastpump.step(pump,
now)`, and one scripted device (hostd.device.simdev.SimDevice, the firmware core's model,
ticked by hand) whose bytes go to both. After every host action the bytes each pump wrote,
the return values, the log lines and a snapshot of every state field (floats by their bits,
arrays by their bytes) must be equal; `Mismatch` names the field, the step and the scenario.

The device is fed with setup A's output only, so both setups always get byte-identical
input; a difference in B's output is a mismatch at that step anyway.

Determinism on a pty: the kernel delivers pty bytes through a work queue, so a read right
after a write can miss them. Before each host action the harness waits until the slave's
input queue (FIONREAD) holds exactly the bytes written since the host's last read, and after
it reads both masters until they hold as many bytes as the reference's transport wrote
(counted at SerialTransport._write). Device bytes per host action are kept below the line
discipline's 4 KiB read buffer (a fuller one would be read in timing-dependent pieces).

A cycle on a serial port never reads a tty that holds nothing (a read that finds the line
discipline empty waits for the kernel's buffer work: hostd/device/seriallink.py): the harness
counts each cycle's read() calls (the thread's syscr, /proc/thread-self/io) and a cycle, of
either setup, that issued more than the bytes waiting call for (none when none wait, one for
less than 4 KiB) is a Mismatch.

The HID twin (transport="hid") is the same comparison with HidrawTransport(fd=...) on one end
of an AF_UNIX SOCK_SEQPACKET socket pair per setup, which keeps message boundaries as hidraw
keeps reports: the device writes each message as one 64-byte report (zero padding, or raw
report bytes a scenario puts on the wire, a zero-length one included) and reads the host's
65-byte reports (report id 0x00 + 64). An AF_UNIX send queues its record on the peer before
it returns, so there is no delivery delay to wait for: the harness checks that the host's
socket holds exactly what the device wrote before each action (FIONREAD) and reads every
report the host wrote after it.
"""

from __future__ import annotations

import fcntl
import math
import os
import select
import socket
import struct
import termios
import time
import types
from collections import deque

import numpy as np

from hostd.bench.accuracy import texture_coeffs
from hostd.cyclestate import state_fields
from hostd.device import protocol as pr
from hostd.device.hidlink import HidrawTransport
from hostd.device.link import DeviceLink
from hostd.device.pump import JitterConfig, Pump
from hostd.device.seriallink import SerialTransport
from hostd.device.simdev import SimDevice
from hostd.errors import DeviceBusy
from hostd.render.pipeline import Renderer
from hostd.texture import synth
from tests.readcount import ReadCounter

M32 = 0xFFFFFFFF
HOST_T0_S = 5000.0  # the fake host monotonic clock at slot 0 (a machine up for a while)
MAX_UNREAD = 4000  # device bytes per host read: below n_tty's 4096-byte read buffer
WAIT_S = 2.0  # how long bytes may take through the kernel before it counts as a mismatch


class Mismatch(AssertionError):
    """Setup B's cycle differs from the reference's."""


# ------------------------------------------------------------------------ snapshot
# Paths (from the pump) that are not compared: timing figures of Pump.run, caches that the
# compiled code may keep in its own form (their results are compared: _w, the fit), the
# transport object (its state is added explicitly below: the pty paths differ), the log
# callable (its lines are compared by the harness), and any attribute whose name starts with
# OWN_PREFIX (state the compiled cycle keeps for itself, e.g. a handle on the pump).
EXCLUDE = frozenset({
    "stats.step_us", "stats.max_late_us", "link.t", "log",
    "renderer.motion._cache", "renderer.height._w_cache", "renderer.height._tables",
})
TRANSPORT_FIELDS = ("_pending", "_queue", "_vmin")
OWN_PREFIX = "_fastpump"  # attributes the compiled cycle may add for its own state (not compared)
# Compared by whether they moved in an action, not by value. link.stats.io_retries counts the
# reference's retries of a busy write (DeviceLink._send) until retry_budget_s has passed on
# time.monotonic(), sleeping 0.1 ms between tries: how many fit in 0.5 ms of wall time differs
# from run to run (and between the two setups), that a busy write was retried does not. What the
# retries lead to (the write given up: the same bytes out, io_dropped, samples, state) is
# compared exactly.
LOOSE = ("link.stats.io_retries",)


_PACK = struct.Struct("<d").pack
_SEQUENCES = (list, tuple, deque)


def _walk(v, path: str, out: dict, seen: dict) -> None:
    """path -> a comparable value: ("f", the 8 bytes) for a float (by bits: -0.0 != 0.0, a NaN
    equals only the same NaN), ("i", n) for an integer, Python and numpy scalars alike; arrays
    by dtype, shape and bytes; containers element by element; objects attribute by attribute
    (an object seen before: a reference to its first path); callbacks by owner and name."""
    t = type(v)  # the common types first, by identity (this runs ~300 times per snapshot)
    if t is float:
        out[path] = ("f", _PACK(v))
    elif t is int:
        out[path] = ("i", v)
    elif t is bool or t is np.bool_:
        out[path] = ("b", bool(v))
    elif v is None or t is str or t is bytes:
        out[path] = v
    elif t in _SEQUENCES:
        out[path] = (t.__name__, len(v))
        for i, x in enumerate(v):
            _walk(x, f"{path}[{i}]", out, seen)
    elif t is dict:
        out[path] = ("dict", len(v))
        for k, x in v.items():
            _walk(x, f"{path}[{k!r}]", out, seen)
    elif t is np.ndarray:
        out[path] = ("nd", v.dtype.str, v.shape, v.tobytes())
    elif t is bytearray:
        out[path] = ("ba", bytes(v))
    elif isinstance(v, float | np.floating):
        out[path] = ("f", _PACK(float(v)))
    elif isinstance(v, int | np.integer):
        out[path] = ("i", int(v))
    elif isinstance(v, types.MethodType):  # a bound method (a callback): whose, which
        owner = seen.get(id(v.__self__), f"<{type(v.__self__).__name__}>") or "<the pump>"
        out[path] = ("method", owner, v.__func__.__qualname__)
    elif isinstance(v, types.FunctionType | types.BuiltinFunctionType | type):
        out[path] = ("callable", getattr(v, "__qualname__", t.__name__))
    elif hasattr(v, "__dict__"):
        if id(v) in seen:
            out[path] = ("ref", seen[id(v)])
            return
        seen[id(v)] = path
        out[path] = ("obj", t.__qualname__)
        for k, x in (*state_fields(v).items(), *vars(v).items()):  # its record's fields, then the rest
            p = f"{path}.{k}" if path else k
            if p not in EXCLUDE and not k.startswith(OWN_PREFIX):
                _walk(x, p, out, seen)
    else:
        out[path] = ("?", t.__qualname__)


def _transport_state(t) -> dict:
    """The transport's own state, name -> value: a serial port's deframer buffer, bad-frame
    count, unsent bytes and queue; a hidraw node keeps nothing between reads (a report per
    read) but its count of zero-length reads skipped."""
    if isinstance(t, HidrawTransport):
        return {"empty_reads": t.empty_reads}
    return {**{k: getattr(t, k) for k in TRANSPORT_FIELDS}, "deframer._buf": t.deframer._buf,
            "deframer.bad_frames": t.deframer.bad_frames}


def snapshot(pump: Pump) -> dict:
    """Every state field reachable from the pump (pump, stats, link, link stats, health,
    renderer: motion, position, height, equalizer, output stage, configs), path -> value,
    plus the transport's own state (_transport_state)."""
    out: dict = {}
    _walk(pump, "", out, {})
    del out[""]
    for k, v in _transport_state(pump.link.t).items():
        _walk(v, f"link.t.{k}", out, {})
    return out


def _show(v) -> str:
    if isinstance(v, tuple) and v and v[0] == "f":
        return f"{struct.unpack('<d', v[1])[0]!r} (bits {v[1][::-1].hex()})"
    if isinstance(v, tuple) and v and v[0] == "nd":
        return f"ndarray {v[1]} {v[2]} {np.frombuffer(v[3], dtype=v[1]).tolist()[:8]}..."
    s = repr(v)
    return s if len(s) < 200 else s[:200] + "..."


def compare(a: dict, b: dict, where: str) -> None:
    """Raise Mismatch naming every differing field (the first few) of two snapshots."""
    if a == b:
        return
    diffs = []
    for k in sorted(set(a) | set(b)):
        va, vb = a.get(k, "<absent>"), b.get(k, "<absent>")
        if va != vb:
            diffs.append(f"  {k}: reference {_show(va)} != compiled {_show(vb)}")
    raise Mismatch(f"{where}: {len(diffs)} field(s) differ:\n" + "\n".join(diffs[:12]))


# ------------------------------------------------------------------------ the device
class ScriptedDevice(SimDevice):
    """SimDevice (core.c's model) with a 32-bit clock and encoder counter that start where a
    scenario wants them (wrapping), encoder dither and glitches, and a simulated reset."""

    def __init__(self, hand, clock_ppm: float, time0_us: int = 0, count0: int = 0, dither: bool = False):
        super().__init__(hand=hand, clock_ppm=clock_ppm, protocol_version=1)
        self.time0_us = time0_us
        self.count0 = count0
        self.dither = dither
        self.glitch_counts = 0  # added to the next STATUS's encoder count only

    def time_us(self) -> int:
        return (self.ticks * 1_000_000 // pr.SAMPLE_RATE_HZ + self.time0_us) & M32

    def encoder_count(self) -> int:
        c = super().encoder_count() + self.count0
        if self.dither:  # ±1 count, pseudo-random per reading
            c += (self.ticks * 2654435761 >> 9) % 3 - 1
        c += self.glitch_counts
        self.glitch_counts = 0
        return c & M32

    def reset(self) -> None:
        """A firmware reset: counters and clock from zero, idle, buffer empty."""
        self.time0_us = (-(self.ticks * 1_000_000 // pr.SAMPLE_RATE_HZ)) & M32
        self.samples_played = self.underruns = self.last_seq = self.faults = 0
        self.state = pr.STATES["IDLE"]
        self.ring.clear()
        self.out = 0
        self.in_underrun = False


class Hand:
    """A hand trajectory (position in mm at time t in s) from a function."""

    def __init__(self, fn) -> None:
        self.fn = fn

    def position_mm(self, t):
        return self.fn(float(t))


def stroke(amplitude_mm: float = 20.0, hz: float = 1.25, phase: float = 0.7):
    """The metronome-like sine stroke (peak 2 pi A f = 157 mm/s at 20 mm, 1.25 Hz)."""
    return Hand(lambda t: amplitude_mm * math.sin(2 * math.pi * hz * t + phase))


def rest(x_mm: float = 3.0, move_at_s: float | None = None):
    """At rest at x_mm; from move_at_s on (if given) a stroke starts smoothly from there."""
    if move_at_s is None:
        return Hand(lambda t: x_mm)
    return Hand(lambda t: x_mm + (10.0 * (1.0 - math.cos(2 * math.pi * 1.25 * (t - move_at_s)))
                                  if t > move_at_s else 0.0))


def sweep(v0_mm_s: float = 0.3, v1_mm_s: float = 1500.0, up_s: float = 0.5):
    """Speed rising exponentially from v0 to v1 over up_s, then the hand turns at once and
    slows down exponentially: it crosses every band-limit bucket (2 % speed steps) between,
    twice (the turn at full speed is a re-lock)."""
    a = math.log(v1_mm_s / v0_mm_s) / up_s
    top = v0_mm_s / a * (math.exp(a * up_s) - 1.0)

    def x(t: float) -> float:
        if t <= up_s:
            return v0_mm_s / a * (math.exp(a * t) - 1.0)
        u = min(t - up_s, up_s)
        return top - v1_mm_s / a * (1.0 - math.exp(-a * u)) - v0_mm_s * max(0.0, t - 2 * up_s)

    return Hand(x)


def jump_at(hand: Hand, t_jump_s: float, jump_mm: float) -> Hand:
    """The hand's encoder moves by jump_mm at t_jump_s and stays there (lifted, set down)."""
    return Hand(lambda t: hand.fn(t) + (jump_mm if t >= t_jump_s else 0.0))


# ------------------------------------------------------------------------ one host setup
def _fionread(fd: int) -> int:
    return struct.unpack("i", fcntl.ioctl(fd, termios.FIONREAD, b"\0\0\0\0"))[0]


class Setup:
    """One host: pty pair, SerialTransport on its slave with a fake clock, DeviceLink, Pump.

    The interface the twin drives (HidSetup has the same): wire(msg) (a message as the device
    puts it on the wire), write_device(chunks), await_input(), take_output(want), wire_state(),
    block_output(blocked), device_reader(), reconnect(), close()."""

    kind = "serial"

    def __init__(self, name: str, jitter: JitterConfig | None, t0_s: float, period_s: float = 0.001,
                 record: bool = False) -> None:
        self.name = name
        self.now_s = t0_s
        self._open()
        self.logged: list[str] = []
        self.pump = Pump(self.link, None, period_s=period_s, jitter=jitter, log=self.logged.append)
        self.pump.record = record  # the demo's summary: sent_codes (compared array by array)

    def _attach_link(self, transport) -> None:
        self.t = transport
        self.t.now = lambda: self.now_s  # the host clock the link and the pump read
        self.link = DeviceLink(self.t, 12)

    def _open(self) -> None:
        self.master, self.slave = os.openpty()
        fcntl.fcntl(self.master, fcntl.F_SETFL, fcntl.fcntl(self.master, fcntl.F_GETFL) | os.O_NONBLOCK)
        # pyserial puts the port in raw mode (iflag = oflag = lflag = 0: no echo, no CR/LF
        # translation, no XON/XOFF); test_the_pty_passes_every_byte_both_ways checks it
        self._attach_link(SerialTransport(os.ttyname(self.slave)))
        self.unread = 0  # device bytes written to the master that the host has not read
        # bytes this host's transport has written to its port (counted for the reference, A:
        # B's must be the same bytes, however its cycle writes them)
        self.written = 0
        self.taken = 0  # of those, read from the master
        real_write = self.t._write

        def counting_write(data):
            n = real_write(data)
            self.written += n
            return n

        self.t._write = counting_write

    def reconnect(self) -> None:
        """The display was unplugged and is back: a new port, transport and link, attached
        to the same pump (the daemon's reconnection: Pump.attach)."""
        self.close()
        self._open()
        self.pump.attach(self.link)

    wire = staticmethod(pr.frame)  # a message as the device sends it: a COBS frame

    @staticmethod
    def device_reader():
        """feed(output) -> the messages the device takes from what the host wrote."""
        return pr.Deframer().feed

    def write_device(self, chunks: list[bytes]) -> None:
        """The device's wire chunks of one slot (frames, raw bytes), as one byte stream."""
        data = b"".join(chunks)
        if data:
            assert os.write(self.master, data) == len(data)
            self.unread += len(data)
        if self.unread > MAX_UNREAD:
            raise AssertionError(f"setup {self.name}: {self.unread} device bytes for one read: keep stalls "
                                 "shorter (the 4 KiB line-discipline buffer would split them)")

    def await_input(self) -> None:
        deadline = time.monotonic() + WAIT_S
        while (n := _fionread(self.slave)) != self.unread:
            if n > self.unread or time.monotonic() > deadline:
                raise Mismatch(f"setup {self.name}: {n} bytes wait on the port, {self.unread} were written "
                               "(the host read less than everything, or the kernel is stuck)")

    def take_output(self, want: int) -> bytes:
        """What the host wrote during its action: `want` bytes (what the reference wrote), and
        whatever more is there already (a surplus shows up at the next action at the latest)."""
        self.unread = _fionread(self.slave)  # all had arrived before; an action may not read (end)
        buf = bytearray()
        deadline = time.monotonic() + (WAIT_S if want else 0.0)
        while True:
            try:
                buf += os.read(self.master, 65536)
                continue
            except BlockingIOError:
                pass
            if len(buf) >= want:
                break
            left = deadline - time.monotonic()
            if left <= 0:
                break
            select.select([self.master], [], [], left)
        self.taken += len(buf)
        return bytes(buf)

    @staticmethod
    def show(out: bytes) -> str:
        return out.hex()

    def wire_state(self):
        """What the harness can tell of output the device has not read (a pty's: nothing exact)."""
        return None

    def block_output(self, blocked: bool) -> None:
        """Suspend (resume) the host's output to the port, as a device that stops reading
        does: writes fail with EAGAIN, the transport keeps what it could not write."""
        termios.tcflow(self.slave, termios.TCOOFF if blocked else termios.TCOON)

    def close(self) -> None:
        self.t.close()
        os.close(self.master)
        os.close(self.slave)


class HidSetup(Setup):
    """One host on a HID display: HidrawTransport on one end of an AF_UNIX SOCK_SEQPACKET pair
    (a record per report, as hidraw), the scripted device on the other.

    The host's send buffer is the kernel's smallest (SO_SNDBUF 4608 bytes: six 65-byte reports
    unread), the device's a large one (a stall's backlog of hundreds of reports fits): a
    device that stops reading (block_output) makes the host's seventh report fail with EAGAIN,
    as a hidraw node whose output queue is full does."""

    kind = "hid"
    DEVICE_SNDBUF = 1 << 20

    def _open(self) -> None:
        dev, host = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        host.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 1)  # (the kernel's minimum)
        dev.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, self.DEVICE_SNDBUF)
        dev.setblocking(False)
        self.dev_sock = dev
        self._attach_link(HidrawTransport(fd=host.detach()))  # (the transport closes it)
        self.unread = 0  # device bytes in reports the host has not read
        self.written = self.taken = 0  # (the serial port's count; a report is there when written)
        self.budget: int | None = None  # reports the device still reads (None: all)

    @staticmethod
    def wire(msg: bytes) -> bytes:
        return pr.pad_report(msg)  # one 64-byte report, zero padding

    @staticmethod
    def device_reader():
        def feed(reports):
            for r in reports:
                assert len(r) == 1 + pr.REPORT_SIZE and r[0] == 0, f"not a report of id 0: {r.hex()}"
            return [r[1:] for r in reports]

        return feed

    def write_device(self, chunks: list[bytes]) -> None:
        """Each chunk one report (b"": a zero-length one)."""
        for c in chunks:
            try:
                n = self.dev_sock.send(c)
            except BlockingIOError:
                raise AssertionError(f"setup {self.name}: the device's send buffer is full "
                                     f"({self.unread} bytes unread): keep stalls shorter") from None
            assert n == len(c)
            self.unread += n

    def await_input(self) -> None:
        # (zero-length reports add nothing to FIONREAD; an AF_UNIX record is queued when sent)
        if (n := _fionread(self.t.fd)) != self.unread:
            raise Mismatch(f"setup {self.name}: {n} bytes wait in reports, {self.unread} were written "
                           "(the host read less than everything)")

    def take_output(self, want: int) -> tuple[bytes, ...]:
        """The reports the host wrote during its action (all there: an AF_UNIX record is queued
        when sent), unless the device is not reading (block_output): then none, or as many as
        it was allowed to read (allow_output)."""
        self.unread = _fionread(self.t.fd)  # a host that stopped early (> 64 empty reads) left some
        out = []
        while self.budget is None or self.budget > 0:
            try:
                out.append(self.dev_sock.recv(4096))
            except BlockingIOError:
                break
            if self.budget is not None:
                self.budget -= 1
        return tuple(out)

    @staticmethod
    def show(out: tuple[bytes, ...]) -> str:
        """Each report as its bytes up to the zero padding, +n for n zero bytes after."""
        parts = []
        for r in out:
            body = r.rstrip(b"\0")
            parts.append(f"{body.hex()}+{len(r) - len(body)}")
        return " ".join(parts) or "none"

    def wire_state(self):
        """Bytes of reports the host wrote that the device has not read (while it does not)."""
        return _fionread(self.dev_sock.fileno())

    def block_output(self, blocked: bool) -> None:
        """The device stops (resumes) reading the host's reports: they stay queued, and once
        the host's send buffer is full, its writes fail with EAGAIN (DeviceBusy)."""
        self.budget = 0 if blocked else None

    def allow_output(self, n: int) -> None:
        """A device that does not read takes n more reports (room for n in the send buffer)."""
        self.budget = n

    def close(self) -> None:
        self.t.close()
        self.dev_sock.close()


SETUPS = {"serial": Setup, "hid": HidSetup}

# ------------------------------------------------------------------------ the twin
def _outcome(fn, *args):
    """fn(*args), or ("raised", "DeviceBusy") when it raises DeviceBusy (a control message that
    found the device busy for 50 ms: Pump.run counts it in io_dropped and goes on). (The
    message is not compared: it names the node, which differs between the setups.)"""
    try:
        return fn(*args)
    except DeviceBusy:
        return ("raised", "DeviceBusy")


class Twin:
    """Setups A (reference) and B (step_b) driven alike, one ms slot at a time, on a serial
    port (transport="serial") or a HID node (transport="hid")."""

    def __init__(self, scenario: str, make_renderer, hand: Hand, clock_ppm: float = 350.0,
                 time0_us: int = 123_456_789, count0: int = 1_000_000, dither: bool = False,
                 jitter: JitterConfig | None = None, step_b=None, seed: int = 7, host_cycle_ms: int = 1,
                 record: bool = False, transport: str = "serial") -> None:
        from hostd.device import fastpump

        self.scenario = scenario
        self.make_renderer = make_renderer
        self.step_b = step_b or fastpump.step
        self.host_cycle_ms = host_cycle_ms  # the host cycles in every host_cycle_ms-th slot
        kind = SETUPS[transport]
        self.a = kind("A", jitter, HOST_T0_S, host_cycle_ms * 1e-3, record)
        self.b = kind("B", jitter, HOST_T0_S, host_cycle_ms * 1e-3, record)
        self.wire = kind.wire  # a message as the device puts it on the wire (a frame, a report)
        self.dev = ScriptedDevice(hand, clock_ppm, time0_us, count0, dither)
        self.dev_rate = pr.SAMPLE_RATE_HZ * (1 + clock_ppm * 1e-6)  # device ticks per host second
        self.dev_t0 = HOST_T0_S  # host time of the device's tick 0
        self.dev_rx = kind.device_reader()
        self.rng = np.random.default_rng(seed)
        self.slot = 0
        self.actions = 0
        # one-shot wire transforms of the next STATUS frames (reports): f -> what goes on the
        # wire instead, None for nothing, (now, in the next slot) for a split
        self.transforms: deque = deque()
        self.carry: list[bytes] = []  # what a transform held back for the next slot (a split frame)
        self.extra: list[bytes] = []  # raw wire chunks to put on the wire before the next slot's frames
        self.extra_after: list[bytes] = []  # ... after them
        self.deaf = 0  # host actions whose output the device does not receive (it is not reading)
        # what the scenario exercised (setup A after each action): scenarios assert on it, so a
        # scenario that stops reaching its path fails instead of passing vacuously
        self.seen: dict = {"host_actions": 0, "max_status_per_poll": 0, "samples": 0, "xfade": 0,
                           "partial_frame": 0, "episode": 0, "guard": 0, "fill_max": 0, "fill_drops": 0,
                           "irregular_fit": 0, "rest": 0, "buckets": set(), "not_running": 0,
                           "raw_count_high": 0, "raw_count_low": 0, "pending_bytes_max": 0,
                           "empty_reads": 0, "input_left": 0, "busy_dropped": 0, "busy_partial": 0,
                           "raised": 0, "empty_port_cycles": 0}
        self.reads = ReadCounter()  # read() calls of this thread (a cycle's, on a serial port)
        self._loose: dict = {}  # LOOSE field -> (reference's, compiled's) at the last comparison
        self._compare(f"{scenario}: after construction")

    def close(self) -> None:
        self.a.close()
        self.b.close()
        self.reads.close()

    def reconnect(self, **device) -> None:
        """Unplug and re-plug: a new device (ScriptedDevice(**device), counters and clock from
        zero, the hand where it is) on new ports; both pumps attach their new links, with
        no action of their own (the next cycles find the device idle)."""
        self.dev = ScriptedDevice(self.dev.hand, self.dev.clock_ppm, **device)
        self.dev_t0 = HOST_T0_S + self.slot * 1e-3
        self.dev_rx = type(self.a).device_reader()
        self.transforms.clear()
        self.carry = []
        for s in (self.a, self.b):
            s.reconnect()
        self._compare(f"{self.scenario}: after the reconnection")

    def _compare(self, where: str) -> None:
        """Both pumps' snapshots equal, the LOOSE fields moved in both or in neither."""
        sa, sb = snapshot(self.a.pump), snapshot(self.b.pump)
        for k in LOOSE:
            va, vb = sa.pop(k, None), sb.pop(k, None)
            pa, pb = self._loose.get(k, (va, vb))
            if (va != pa) != (vb != pb):
                raise Mismatch(f"{where}: {k} moved in one setup only: reference {_show(pa)} -> {_show(va)}, "
                               f"compiled {_show(pb)} -> {_show(vb)}")
            self._loose[k] = (va, vb)
        compare(sa, sb, where)

    def finish(self, settle_s: float = 0.02) -> None:
        """The end of a scenario: nothing more may arrive from either host (a frame written
        but not counted as sent shows up here at the latest)."""
        time.sleep(settle_s)
        late = [s.take_output(0) for s in (self.a, self.b)]
        if late[0] or late[1]:
            raise Mismatch(f"scenario {self.scenario!r}, after the last action: more bytes arrived: "
                           f"reference {self.a.show(late[0])}, compiled {self.b.show(late[1])}")

    # -- the device side of one slot
    def _device_output(self, host_t: float) -> list[bytes]:
        """The device runs up to host_t; what it sent since, through the scripted wire events,
        as wire chunks (frames or reports, raw chunks of the script)."""
        due = math.floor((host_t - self.dev_t0) * self.dev_rate)
        while self.dev.ticks < due:
            self.dev.tick()
        chunks = self.carry + self.extra
        self.carry = []
        self.extra = []
        while self.dev.outbox:
            m = self.dev.outbox.popleft()
            f = self.wire(m)
            if m[0] == pr.IDS["STATUS"] and self.transforms:
                f = self.transforms.popleft()(f)
            if isinstance(f, tuple):  # (now, in the next slot)
                f, later = f
                self.carry.append(later)
            if f is not None:
                chunks.append(f)
        chunks += self.extra_after
        self.extra_after = []
        return chunks

    def _host_time(self, k: int) -> float:
        # the host wakes up to 0.4 ms late in its 1 ms slot (the device's clock runs its own rate)
        return HOST_T0_S + k * 0.001 + float(self.rng.uniform(0.0, 0.0004))

    # -- one slot
    def _slot(self, host: bool = True, action=None) -> None:
        k = self.slot
        self.slot += 1
        host_t = self._host_time(k)
        chunks = self._device_output(host_t)
        for s in (self.a, self.b):
            s.write_device(chunks)
        if host:
            self._act(action, host_t)

    def _act(self, action, host_t: float) -> None:
        """One host action on both setups at host_t: `action(pump)` (pump.begin) or, for None,
        a cycle (A: pump.step(); B: step_b(pump, host_t)); then everything is compared."""
        where = (f"scenario {self.scenario!r}, host action {self.actions} (slot {self.slot - 1}, "
                 f"host t = +{host_t - HOST_T0_S:.6f} s)")
        self.actions += 1
        for s in (self.a, self.b):
            s.await_input()
            s.now_s = host_t
        statuses_before = self.a.link.stats.statuses
        if action is None:
            waiting = (self.a.unread, self.b.unread)
            r0 = self.reads()
            ra = _outcome(self.a.pump.step)
            r1 = self.reads()
            rb = _outcome(self.step_b, self.b.pump, host_t)
            r2 = self.reads()
            if r0 is not None and self.a.kind == "serial":
                for who, n, w in (("reference", r1 - r0, waiting[0]), ("compiled", r2 - r1, waiting[1])):
                    if n > math.ceil(w / 4096):
                        raise Mismatch(f"{where}: the {who} cycle issued {n} read() call(s) with {w} bytes "
                                       "waiting on the port: a read of an empty tty waits for the kernel's "
                                       "buffer work")
                self.seen["empty_port_cycles"] += waiting[0] == 0
        else:
            ra = _outcome(action, self.a.pump)
            rb = _outcome(action, self.b.pump)
        want = self.a.written - self.a.taken
        out_a = self.a.take_output(want)
        out_b = self.b.take_output(want)
        if type(ra) is not type(rb) or ra != rb:
            raise Mismatch(f"{where}: returned {ra!r} (reference) != {rb!r} (compiled)")
        if out_a != out_b:
            raise Mismatch(f"{where}: bytes written differ:\n  reference {self.a.show(out_a)}\n"
                           f"  compiled  {self.b.show(out_b)}")
        if (wa := self.a.wire_state()) != (wb := self.b.wire_state()):
            raise Mismatch(f"{where}: bytes written differ: reference {wa} unread by the device, "
                           f"compiled {wb}")
        if self.a.logged != self.b.logged:
            raise Mismatch(f"{where}: log lines differ: {self.a.logged[-2:]} != {self.b.logged[-2:]}")
        self._compare(where)
        if self.deaf > 0:
            self.deaf -= 1
        else:
            for m in self.dev_rx(out_a):
                self.dev.on_message(m)
        self._observe(ra, self.a.link.stats.statuses - statuses_before)

    def _observe(self, ret, statuses: int) -> None:
        p, seen = self.a.pump, self.seen
        seen["host_actions"] += 1
        seen["max_status_per_poll"] = max(seen["max_status_per_poll"], statuses)
        seen["samples"] += ret if isinstance(ret, int) else 0
        seen["raised"] += isinstance(ret, tuple)  # DeviceBusy out of the cycle (_outcome)
        seen["episode"] += p._episode is not None
        seen["guard"] += p._guard_seq is not None
        seen["fill_drops"] += p._fill < seen.get("_fill_prev", p._fill)
        seen["_fill_prev"] = p._fill
        seen["fill_max"] = max(seen["fill_max"], p._fill)
        t = p.link.t
        if isinstance(t, HidrawTransport):
            seen["empty_reads"] = max(seen["empty_reads"], t.empty_reads)
        else:
            seen["partial_frame"] += bool(t.deframer._buf)
            seen["pending_bytes_max"] = max(seen["pending_bytes_max"], len(t._pending))
        seen["input_left"] += self.a.unread > 0  # device input the host left for its next cycle
        # a busy write retried (DeviceLink._send), and the message given up: all of the cycle's
        # (io_dropped), or those after the first that went out (a partial send)
        retried = p.link.stats.io_retries != seen.get("_retries_prev", 0)
        dropped = p.stats.io_dropped != seen.get("_dropped_prev", 0)
        seen["_retries_prev"], seen["_dropped_prev"] = p.link.stats.io_retries, p.stats.io_dropped
        seen["busy_dropped"] += retried and dropped
        seen["busy_partial"] += retried and not dropped and isinstance(ret, int) and ret > 0
        s = p.link.stats.last_status
        seen["not_running"] += bool(s) and s["state"] != pr.STATES["RUNNING"]
        r = p.renderer
        if r is not None:
            m = r.motion
            seen["xfade"] += r._xfade_left > 0
            seen["irregular_fit"] += m._n > 2 and m._uniform < m._n - 1
            seen["rest"] += m._rest_x is not None
            if r.height._w_bucket is not None:
                seen["buckets"].add(r.height._w_bucket)
            last = r.position._last
            if last is not None:
                seen["raw_count_high"] += last >= 1 << 31
                seen["raw_count_low"] += last < 1 << 31

    def run(self, ms: int, host: bool = True) -> None:
        """ms slots of 1 ms; host=False: the host stalls (no reads, no steps)."""
        for _ in range(ms):
            self._slot(host and self.slot % self.host_cycle_ms == 0)

    def begin(self, key=None) -> None:
        """In the next slot, instead of a cycle: pump.begin(a fresh, started renderer of
        texture `key`) on both setups (the daemon's texture selection)."""

        def action(pump):
            r = self.make_renderer(key)
            r.start()
            return pump.begin(r)

        self._slot(True, action)

    def end(self) -> None:
        """pump.end() on both in the next slot (playback stopped)."""
        self._slot(True, lambda pump: pump.end())

    def block_output(self, blocked: bool) -> None:
        """Suspend (resume) the hosts' output to the device, as a device that stops reading
        does: writes fail with EAGAIN once the kernel's buffer is full (Setup.block_output)."""
        for s in (self.a, self.b):
            s.block_output(blocked)

    def allow_output(self, n: int) -> None:
        """HID: the device, not reading, takes n reports after the next action (and no more)."""
        for s in (self.a, self.b):
            s.allow_output(n)

    # -- scripted wire events (the next STATUS frames)
    def drop_status(self, n: int = 1) -> None:
        for _ in range(n):
            self.transforms.append(lambda f: None)

    def split_status(self) -> None:
        self.transforms.append(lambda f: (f[: len(f) // 2], f[len(f) // 2 :]))

    def corrupt_status(self) -> None:
        self.transforms.append(lambda f: f[:5] + bytes([f[5] ^ 0x10 or 1]) + f[6:])

    def insert(self, msg: bytes, framed: bool = True, after: bool = False) -> None:
        """Put a message (framed=True: as the device sends it, a frame or a padded report) or a
        raw chunk (serial: bytes; HID: one report as it is, b"" a zero-length one) on the wire in
        the next slot, before (or after) that slot's STATUS frames."""
        (self.extra_after if after else self.extra).append(self.wire(msg) if framed else msg)

    def glitch(self, counts: int) -> None:
        self.dev.glitch_counts = counts


def standard_textures() -> dict:
    """The scenarios' textures: wood ('main'), sandpaper ('sand'), wood with N' = 5 ('short')."""
    wood = texture_coeffs(synth.make("wood", seed=1))
    sand = texture_coeffs(synth.make("sandpaper", seed=2))
    c, n, length_mm = wood
    return {"main": wood, "sand": sand, "short": (c[:5].copy(), n, length_mm)}


def renderer_factory(textures: dict, cfg=None):
    """make(key) -> a Renderer for textures[key] = (coeffs, n, length_mm) (key None: 'main'),
    with RenderConfig cfg (None: the defaults)."""

    def make(key=None):
        c, n, length_mm = textures[key or "main"]
        return Renderer(c, n, length_mm, cfg)

    return make
