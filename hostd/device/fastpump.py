"""The host-rendering pump's steady-state cycle, compiled (hostd/device/_fastpump.c), with
hostd.device.pump.Pump.step and the loop of Pump.run as its reference.

A Python cycle costs 100–190 µs of CPU (at 1 kHz, a tenth to a fifth of a core, issue 22); the
compiled one does the same work, operation for operation, for the kernel's wake-up and a few
µs. It takes a cycle only while everything is ordinary (a display streaming: STATUS messages, a
motion fit and band-limit weights already cached, nothing to recover) and hands the rest of
any other cycle to the reference, so recovery, re-locks and new speed buckets have one
implementation. tests/test_fastpump.py drives both on the same scripted display and checks,
cycle by cycle, the same bytes on the wire and the same state bit for bit.

The state both share is declared once (hostd/device/cycle_state.toml): the stages hold their
fields in records the C reads and writes in place. This module is the C's thin face: _parts hands
it the stages and the objects that are not records, _put puts back what changed in those, and
_hand finishes a cycle the C handed over, with the reference's own methods.

Used when: it is built (and its REVISION matches), HOSTD_PURE_PYTHON is unset, the transport is
a SerialTransport (the firmware's host port, CDC-ACM and serial bridges) or a HidrawTransport
(a USB HID display on Linux; raw USB through pyusb and hidapi go through the reference), the
renderer evaluates the series in float64 on an int16 DAC. The series of a
real-time batch is the Clenshaw recurrence on both sides (hostd.render.series.clenshaw_py).
"""

from __future__ import annotations

import ctypes
import functools

import numpy as np

from hostd import cyclestate
from hostd.compiled import load as load_compiled
from hostd.device import fastlink
from hostd.device import protocol as pr
from hostd.errors import DeviceBusy
from hostd.render import equalizer, fastrender, motion
from hostd.render.pipeline import Renderer

C_REVISION = 10  # _fastpump.c's REVISION this module is written for
_PREVIOUS = pr.LAYOUTS["STATUS"].names  # the latest STATUS's fields the compiled cycle goes on from


def _load():
    c = load_compiled("hostd.device._fastpump", C_REVISION)
    if c is None or fastrender._C is None:
        return None
    if c.RECORD_SIZES != {k: ctypes.sizeof(r) for k, r in cyclestate.RECORDS.items()}:
        return None  # built from another cycle_state.toml (or another ABI): not the records here
    from hostd.device.health import MAX_GAP_US

    c.init(MAX_GAP_US, equalizer.SMALL_BATCH, motion.CUBIC_MIN_READINGS, _codes_from_bytes)
    return c


def _codes_from_bytes(raw: bytes) -> np.ndarray:
    """A batch's codes as the renderer returns them (int16), for the reference to finish sending."""
    return np.frombuffer(raw, dtype=np.int16).copy()


_C = _load()
IMPLEMENTATION = "c" if _C is not None else "python"
# the longest run of compiled cycles between two of the Python loop's (each_cycle: commands, counters)
BUDGET_S = 0.25


MODE_SERIAL, MODE_HID = 0, 1  # _fastpump.c's transports


def _mode(t) -> int | None:
    """The compiled cycle's mode for this transport, or None (it streams through the reference)."""
    from hostd.device.hidlink import HidrawTransport
    from hostd.device.seriallink import SerialTransport

    kind = type(t)
    return MODE_SERIAL if kind is SerialTransport else MODE_HID if kind is HidrawTransport else None


def usable(pump) -> bool:
    """Can the compiled cycle stream for this pump (its transport, its renderer)? The run loop
    reads CLOCK_MONOTONIC, so a transport with a clock of its own (a simulation) cannot."""
    if _C is None:
        return False
    from hostd.device.backend import Transport

    t = pump.link.t
    r = pump.renderer
    return (_mode(t) is not None and type(t).now is Transport.now and "now" not in vars(t)
            and (r is None or _renderer_ok(r)))


@functools.cache
def _methods(cls: type) -> frozenset:
    return frozenset(k for k in dir(cls) if not k.startswith("__") and callable(getattr(cls, k, None)))


def _plain(obj, cls: type) -> bool:
    """obj is exactly a cls, with none of its methods replaced on the instance (a test's spy, a
    wrapper): the compiled cycle does what cls's methods do, so it must be them that run."""
    return type(obj) is cls and _methods(cls).isdisjoint(vars(obj))


def _ordinary(pump) -> bool:
    """The objects of the cycle are the classes the compiled cycle mirrors, unpatched, wired to
    each other as Pump.attach wires them."""
    from hostd.device.health import DeviceHealth
    from hostd.device.link import DeviceLink
    from hostd.render.equalizer import Equalizer
    from hostd.render.height import HeightEvaluator
    from hostd.render.motion import MotionEstimator
    from hostd.render.output import OutputStage
    from hostd.render.position import EncoderPosition

    link, r = pump.link, pump.renderer
    if not (vars(type(pump)).get("COMPILED_MIRROR") is True and _plain(pump, type(pump))
            and _plain(link, DeviceLink) and _plain(pump.health, DeviceHealth)
            and link.on_status == pump._on_status):
        return False
    return r is None or (_renderer_ok(r) and _plain(r.motion, MotionEstimator)
                         and _plain(r.position, EncoderPosition) and _plain(r.height, HeightEvaluator)
                         and _plain(r.eq, Equalizer) and _plain(r.out, OutputStage))


def _renderer_ok(r) -> bool:
    return (type(r) is Renderer and _methods(Renderer).isdisjoint(vars(r)) and r.height.method == "series"
            and r.height.dtype is np.float64 and r.out._code_dtype is np.int16)


def _parts(pump, mode: int) -> tuple | None:
    """What the compiled cycle takes, in _fastpump.c's order (its P_* enum): the stages, which it
    reads and writes as their records (hostd/device/cycle_state.toml), then the objects that are
    not records. None when the cycle is not ordinary here (what the records cannot say: an
    episode object, a queue, a crossfade's fit, the STATUS dict the health shares)."""
    link, r, t = pump.link, pump.renderer, pump.link.t
    status = link.stats.last_status
    if r is None or pump._episode is not None or not status or status is not pump.health._last:
        return None
    m, h = r.motion, r.height
    if m._outliers:
        return None
    if mode == MODE_HID:
        tr = (t.fd, t.empty_reads, None, 0)
    elif t._queue or t._pending or t._vmin:
        return None
    else:
        tr = (t.ser.fd, 0, t.deframer._buf, t.deframer.bad_frames)
    return (pump, pump.stats, link, link.stats, pump.health, r, r.position, m, h, r.out,
            pump.stats.step_us, tuple(map(status.get, _PREVIOUS)),
            m._cache, h._w, h._w_cache, r.eq.sos, r.eq.zi,
            pump.sent_codes.append if pump.record else None, *tr)


def _put(pump, w) -> None:
    """Put back what the compiled cycle changed that is not a record (_fastpump.c's writes())."""
    status, weights, *tr = w
    link, r = pump.link, pump.renderer
    if status is not None:  # the latest STATUS, decoded: one dict for the link and the health
        link.stats.last_status = pump.health._last = fastlink.decode(status)[1]
    r.height._w = weights
    t = link.t
    if len(tr) == 1:
        (t.empty_reads,) = tr
    else:
        t.deframer.bad_frames, buf, t._pending = tr
        t.deframer._buf = bytearray(buf)


def _hand(pump, hand) -> int:
    """The rest of a cycle the compiled one handed over, the reference's way."""
    code, arg, extra = hand
    if code == _HAND_MSGS:  # link.poll's loop over the messages from `arg` on, then the cycle's tail
        link = pump.link
        stale = len(extra) - link.FRESH
        for i in range(arg, len(extra)):
            link._take(extra[i], i >= stale)
        return pump.after_poll()
    if code == _HAND_AFTER:
        return pump.after_poll()
    if code == _HAND_SEND:  # the batch's SAMPLES from the message that did not go out
        sent = pump._send_codes(extra, arg)
        pump._motion_stats()
        return sent
    return pump.step()  # a read failed: the reference's cycle from the top (it reads again)


_HAND_MSGS, _HAND_AFTER, _HAND_READERR, _HAND_SEND = 1, 2, 3, 4  # _fastpump.c's hand-over codes


def step(pump, now_s: float | None = None) -> int:
    """pump.step(), compiled where the cycle is ordinary. now_s: the host clock the cycle reads
    (tests: it must equal what pump.link.t.now() returns during the call); None: the monotonic
    clock, which is what the transport's now() reads. Returns the number of samples sent."""
    mode = _mode(pump.link.t) if _C is not None else None
    parts = _parts(pump, mode) if mode is not None and _ordinary(pump) else None
    res = _C.step(parts, now_s, mode) if mode is not None else None
    if res is None:
        return pump.step()
    sent, hand, w = res
    _put(pump, w)
    return sent if hand is None else _hand(pump, hand)


def run(pump, start_s: float, k: int, duration_s: float | None, fds=(), top_done: bool = True
        ) -> tuple[int, str, float]:
    """Pump.run's iterations, compiled, while they are ordinary and for at most BUDGET_S:
    (k, why, due_s). top_done: the caller's loop began the first iteration (its stall check,
    _last_cycle_start, each_cycle, stop) and this does its cycle on. why: "end", "stall",
    "budget", "wake" (one of fds is readable: a command, a udev event), "signal", "handed" (the
    reference finished a cycle), "reference" (nothing done: not ordinary). due_s > 0: the
    caller sleeps until then (the grid's next deadline)."""
    mode = _mode(pump.link.t)
    if mode is None or pump.renderer is None or not _ordinary(pump):
        return k, "reference", 0.0
    res = _C.run(_parts(pump, mode), start_s, k, duration_s, BUDGET_S, tuple(fds), mode, top_done)
    if res is None:
        return k, "reference", 0.0
    k, why, due, hand, c0, w = res
    _put(pump, w)
    if hand is not None:  # the reference finishes the cycle; Pump.run's tail ends it
        try:
            _hand(pump, hand)
        except DeviceBusy:
            pump.stats.io_dropped += 1
        k, due = pump._end_cycle(c0, start_s, k)
    return k, why, due


def compiled_cycles() -> int:
    """Host-rendering cycles this process ran compiled (0 where the compiled cycle is not built);
    `hostd status` shows it (compiled_cycles) next to the pump's cycles."""
    return _C.handovers()["compiled"] if _C is not None else 0
