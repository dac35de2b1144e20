"""The compiled pump cycle (hostd.device.fastpump.step) against its reference, Pump.step, on
real ptys: the same device bytes, then the same bytes written, the same return value and the
same state, field by field (floats by their bits), after every cycle of every scenario
(harness: tests/fastpump_twin.py). The scenarios lead the cycle through every hand-over to
the Python reference: host stalls (a backlog of more than 32 STATUS), underruns, a device
gone idle and reset, encoder glitches and re-locks, lost / split / corrupt frames, other
messages, 32-bit wraps, jitter-target decay and texture switches. The perturbed twins prove
that the comparison sees a one-ULP, one-count or one-byte difference."""

from __future__ import annotations

import math
import os
import select
import time

import numpy as np
import pytest

from hostd import cyclestate
from hostd.device import fastpump
from hostd.device import protocol as pr
from hostd.device.pump import JitterConfig
from hostd.render.equalizer import EqualizerConfig
from hostd.render.motion import MotionConfig
from hostd.render.pipeline import RenderConfig
from tests.fastpump_twin import (
    EXCLUDE,
    Mismatch,
    Twin,
    jump_at,
    renderer_factory,
    rest,
    snapshot,
    standard_textures,
    stroke,
    sweep,
)

M32 = 1 << 32


@pytest.fixture(scope="module")
def textures():
    return standard_textures()


def _twin(textures, name, hand=None, step_b=None, cfg=None, **kw) -> Twin:
    return Twin(name, renderer_factory(textures, cfg), hand or stroke(), step_b=step_b, **kw)


def _play(tw: Twin, key=None, lead_ms: int = 8) -> None:
    """The device reports for lead_ms before the host selects a texture (nothing selected)."""
    tw.run(lead_ms)
    tw.begin(key)


# ------------------------------------------------------------------------ scenarios
def sc_steady_stroke(tw):
    _play(tw)
    tw.run(700)
    p = tw.a.pump
    assert tw.seen["samples"] > 1900 and p.stats.recoveries == 0 and p.health.underruns == 0


def sc_sandpaper_slow_device_clock(tw):
    _play(tw, "sand")
    tw.run(500)
    assert tw.a.pump.health.samples_played > 1300 and tw.a.pump.stats.recoveries == 0


def sc_short_texture(tw):
    _play(tw, "short")
    tw.run(400)
    assert tw.a.pump.renderer.height.c.size == 5 and tw.seen["samples"] > 1000


def sc_other_render_settings(tw):
    _play(tw)
    tw.run(400)
    tw.run(10, host=False)
    tw.run(100)
    assert tw.seen["samples"] > 1000 and tw.a.pump.health.underruns >= 1


def sc_two_ms_cycle(tw):
    _play(tw)
    tw.run(400)
    p = tw.a.pump
    assert p._extra == 3 and p.link.target_fill == 15
    assert tw.seen["host_actions"] == 4 + 1 + 200  # lead-in cycles, begin, cycles
    assert len(p.sent_codes) > 150 and tw.seen["samples"] > 1100


def sc_rest_with_dither(tw):
    _play(tw)
    tw.run(500)  # the hand starts moving at 0.35 s
    m = tw.a.pump.renderer.motion
    assert tw.seen["rest"] > 300 and m.glitches == 0 and m.relocks == 0
    assert abs(m.velocity_mm_s) > 10


def sc_implausible_speed(tw):
    _play(tw)
    tw.run(400)
    p = tw.a.pump
    assert p.stats.implausible_speed >= 1 and p.stats.implausible_speed == p.renderer.motion.implausible


def sc_speed_sweep(tw):
    _play(tw)
    tw.run(1000)
    assert len(tw.seen["buckets"]) > 150, len(tw.seen["buckets"])


def sc_host_stalls(tw):
    _play(tw)
    tw.run(200)
    tw.run(40, host=False)  # > 32 STATUS in one poll, an underrun, no host timeout
    tw.run(250)
    tw.run(100, host=False)  # past the device's 50 ms host timeout: it ramps down, goes idle
    tw.run(300)
    p = tw.a.pump
    assert tw.seen["max_status_per_poll"] >= 99 and p.stats.recoveries >= 2
    assert any("host timeout" in m for m in tw.a.logged) and any("underrun" in m for m in tw.a.logged)


def sc_underrun_fill_rises_and_decays(tw):
    _play(tw)
    tw.run(150)
    tw.run(12, host=False)  # dry after ~4 ms: UNDERRUN flag and counter
    tw.run(20)
    tw.run(12, host=False)  # again while the target is still raised (within its quiet period)
    tw.run(1100)
    p = tw.a.pump
    assert p.health.underruns >= 2 and tw.seen["fill_max"] >= 36, tw.seen["fill_max"]
    assert tw.seen["fill_drops"] >= 1 and p._fill == p.jitter.base_fill


def sc_device_idle_reset_deaf(tw):
    from hostd.device.pump import HOST_TIMEOUT_BIT

    _play(tw)
    tw.run(150)
    d = tw.dev
    d.state, d.faults = pr.STATES["RAMP_DOWN"], d.faults | HOST_TIMEOUT_BIT  # its timeout fired
    d.ring.clear()
    tw.run(150)
    d.state = pr.STATES["IDLE"]  # idle, no flag: "device idle"
    d.ring.clear()
    tw.run(150)
    tw.deaf = 130  # the device stops reading: the guard gives up after 100 ms, host timeout
    tw.run(350)
    # last: a firmware reset (counters and clock from zero; over a serial bridge the port stays):
    # the device's clock restarts below the episode's silent_since_s, and the pump must still
    # see it playing again (it once kept the episode open for the old uptime)
    before = tw.a.pump.stats.recoveries
    d.reset()
    tw.run(150)
    p = tw.a.pump
    assert p.health.resets >= 1 and p.stats.recoveries >= 3 and tw.seen["not_running"] > 5
    assert p.stats.recoveries > before and not p.recovering, "still recovering after a device reset"
    assert any("device idle" in m for m in tw.a.logged)
    assert sum("host timeout" in m for m in tw.a.logged) >= 2


def sc_glitch_and_jump(tw):
    _play(tw)
    tw.run(250)
    tw.glitch(50_000)  # one wild reading (20 mm): replaced by the prediction
    tw.run(250)  # the hand's real jump (5 mm at 0.6 s): re-lock, crossfade
    tw.run(200)
    m = tw.a.pump.renderer.motion
    assert m.glitches >= 1 and m.relocks >= 1 and tw.seen["xfade"] >= 3 and m.previous_fit is not None


def sc_lost_status(tw):
    _play(tw)
    tw.run(150)
    tw.drop_status(1)
    tw.run(60)
    tw.drop_status(2)
    tw.run(60)
    tw.drop_status(25)  # a 26 ms gap: past motion.max_gap_s, the fit restarts
    tw.run(150)
    for _ in range(3):
        tw.transforms.append(lambda f: f + f)  # the same STATUS twice: a repeated reading
        tw.run(30)
    m = tw.a.pump.renderer.motion
    assert tw.seen["irregular_fit"] > 10 and m.relocks >= 1


def sc_wraps_32bit(tw):
    _play(tw)
    tw.run(900)
    p = tw.a.pump
    assert p.link._time_hi == M32  # device_time_us wrapped once
    assert tw.seen["raw_count_high"] and tw.seen["raw_count_low"]  # encoder_count wrapped


def sc_split_status(tw):
    _play(tw)
    tw.run(100)
    for _ in range(5):
        tw.split_status()  # half a frame in one read, the rest in the next
        tw.run(40)
    tw.transforms.append(lambda f: (f[:-1], f[-1:]))  # all but the delimiter
    tw.run(60)
    assert tw.seen["partial_frame"] >= 5 and tw.a.pump.link.t.deframer.bad_frames == 0


def sc_corrupt_frames(tw):
    _play(tw)
    tw.run(100)
    tw.corrupt_status()  # CRC mismatch: the frame is dropped
    tw.run(50)
    tw.insert(b"\x05\x07\x09", framed=False)  # a cut frame: spoils the next one
    tw.run(50)
    tw.insert(bytes(range(1, 256)) * 2, framed=False, after=True)  # no delimiter in sight
    tw.run(50)
    tw.insert(b"\x7f\x01\x02")  # a valid frame of an unknown message id
    tw.insert(pr.encode("STATUS")[:9])  # a STATUS too short
    tw.run(150)
    p = tw.a.pump
    assert p.link.t.deframer.bad_frames >= 3 and p.link.stats.bad_messages_received >= 2


def sc_other_messages(tw):
    _play(tw)
    tw.run(80)
    for i in range(10):
        tw.insert(pr.encode("ACK", for_id=pr.IDS["LOAD_END"], detail=i))
        tw.run(7)
        tw.insert(pr.encode("RENDER_STATUS", render_state=0, device_time_us=1000 * i))
        tw.insert(pr.encode("IDENT", protocol_version=1, sample_rate_hz=3000), after=True)
        tw.run(11)
    tw.insert(pr.encode("SAMPLES", seq=3, codes=[1, 2, 3]))  # a host->device id from the device
    tw.run(20)
    for name in ("CLIPPED", "SLEWED", "OVERFLOW", "ENCODER"):  # faults the pump does not act on
        tw.dev.faults |= pr.FAULTS[name]
        tw.run(20)
    p = tw.a.pump
    assert p.link.render_status is not None and p.link.ident is not None and p.health._last_rs is not None
    assert len(p.health._recent_flags) == 4


def sc_texture_switch(tw):
    _play(tw)
    tw.run(250)
    tw.begin("sand")  # a new renderer mid-run: STOP, prime, START
    tw.run(200)
    tw.end()
    tw.run(30)
    tw.begin("short")
    tw.run(200)
    p = tw.a.pump
    assert p.renderer.height.c.size == 5 and tw.seen["guard"] >= 3


def sc_reconnect(tw):
    _play(tw)
    tw.run(200)
    tw.run(30, host=False)  # unplugged
    # a new device, its clock ahead of the old one's: the pump brings it back by itself
    tw.reconnect(time0_us=200_000_000, count0=77)
    tw.run(150)
    assert tw.a.pump.stats.recoveries == 1
    tw.run(20, host=False)
    # another, its clock from zero (the episode then stays open until a begin: reported), and
    # the daemon's own flow: attach, then begin
    tw.reconnect(time0_us=5_000, count0=M32 - 100)
    tw.run(50)
    tw.begin("sand")
    tw.run(200)
    p = tw.a.pump
    assert p.health.samples_played > 3 * 300 and p._episode is None


def sc_output_blocked(tw):
    _play(tw)
    tw.run(150)
    tw.block_output(True)  # the port takes nothing for 40 ms: the transport keeps it, in order
    tw.run(40)
    tw.block_output(False)
    tw.run(150)
    tw.block_output(True)  # for long: the device times out, the pump's restarts wait too
    tw.run(330)
    tw.block_output(False)
    tw.run(250)
    p = tw.a.pump
    # (MAX_PENDING is not reached: unacknowledged samples count as in flight, so the pump
    # stops sending; DeviceBusy from a serial port is not exercised here)
    assert tw.seen["pending_bytes_max"] > 300 and p.stats.recoveries >= 2 and not p.link.t._pending
    assert any("host timeout" in m for m in tw.a.logged)


SCENARIOS = {
    "steady_stroke": (sc_steady_stroke, {}),
    "sandpaper_slow_device_clock": (sc_sandpaper_slow_device_clock, {"clock_ppm": -450.0}),
    "short_texture": (sc_short_texture, {}),
    # the table height method in float32, order-1 motion, no equalizer, the demo's record=True
    "table_float32_order1_no_eq": (sc_other_render_settings, {"cfg": RenderConfig(
        height_method="table-cubic", dtype="float32", motion=MotionConfig(order=1, window=8),
        equalizer=EqualizerConfig(enabled=False)), "record": True}),
    # [device] host_cycle_ms = 2: one SAMPLES of 2 ms per wake-up, fill target + 3 samples
    "two_ms_cycle": (sc_two_ms_cycle, {"host_cycle_ms": 2, "record": True}),
    "rest_with_dither": (sc_rest_with_dither, {"hand": rest(move_at_s=0.35), "dither": True}),
    # faster than any hand (> motion.max_speed_mm_s = 3000): rejected, the fit restarts
    "implausible_speed": (sc_implausible_speed, {"hand": sweep(100.0, 6000.0, 0.3)}),
    "speed_sweep": (sc_speed_sweep, {"hand": sweep()}),
    "host_stalls": (sc_host_stalls, {}),
    # a quiet period of 40 ms (the default is 1 s): the raised target comes down within the run
    "underrun_fill_rises_and_decays": (sc_underrun_fill_rises_and_decays,
                                       {"jitter": JitterConfig(quiet_s=0.04)}),
    "device_idle_reset_deaf": (sc_device_idle_reset_deaf, {}),
    "glitch_and_jump": (sc_glitch_and_jump, {"hand": jump_at(stroke(), 0.6, 5.0)}),
    "lost_status": (sc_lost_status, {}),
    # the clock wraps 0.4 s in; the count wraps whenever the hand is past +8 mm
    "wraps_32bit": (sc_wraps_32bit, {"time0_us": M32 - 400_000, "count0": M32 - 20_000}),
    "split_status": (sc_split_status, {}),
    "corrupt_frames": (sc_corrupt_frames, {}),
    "other_messages": (sc_other_messages, {}),
    "texture_switch": (sc_texture_switch, {}),
    # a new port, transport and link (Pump.attach), with and without a begin after it
    "reconnect": (sc_reconnect, {}),
    # the port takes nothing for a while (TCOOFF): EAGAIN, SerialTransport._pending, in order
    "output_blocked": (sc_output_blocked, {}),
}


# scenarios whose cycles are mostly ordinary: the compiled cycle must have done most of them
# itself (not handed them all to the reference, which would make the comparison vacuous)
# (a short scenario's first ~130 cycles visit new speed buckets and motion fits: the reference's)
MOSTLY_COMPILED = {"steady_stroke", "sandpaper_slow_device_clock", "short_texture", "two_ms_cycle",
                   "rest_with_dither", "wraps_32bit", "split_status"}


@pytest.mark.parametrize("name", list(SCENARIOS))
def test_compiled_cycle_equals_the_reference(textures, name):
    script, kw = SCENARIOS[name]
    tw = _twin(textures, name, **kw)
    before = fastpump._C.handovers() if fastpump._C is not None else {}
    try:
        script(tw)
        tw.finish()
    finally:
        tw.close()
    assert tw.seen["host_actions"] > 200
    if fastpump._C is not None:
        after = fastpump._C.handovers()
        done = after["compiled"] - before["compiled"]
        handed = sum(after[k] - before[k] for k in after if k != "compiled")
        if name in MOSTLY_COMPILED:
            assert done > handed, (name, {k: after[k] - before[k] for k in after if after[k] != before[k]})
        elif name != "table_float32_order1_no_eq":  # (not a renderer the compiled cycle takes)
            assert done > 0, (name, {k: after[k] - before[k] for k in after if after[k] != before[k]})


# ------------------------------------------------------------------------ the harness can fail
def _perturbed(at: int, change):
    """step_b for setup B: fastpump.step, except at its at-th call (1-based), where
    change(pump, now) runs the cycle its own (perturbed) way and returns its result. The
    perturbed cycle is the Python reference's with one change, so what it proves does not
    depend on how fastpump is implemented (the C cycle never reads link.FRESH, say)."""
    calls = [0]

    def step(pump, now):
        calls[0] += 1
        if calls[0] != at:
            return fastpump.step(pump, now)
        return change(pump, now)

    return step


def _write_one_byte_short(pump, now):
    t = pump.link.t
    real = t._write

    def short(data):
        n = real(data[:1] + data[2:])  # one byte lost on the way
        return n + 1 if n == len(data) - 1 else n

    t._write = short
    try:
        return pump.step()
    finally:
        t._write = real


def _all_fresh(pump, now):
    pump.link.FRESH = 1 << 30  # every STATUS of a backlog would feed the motion fit
    try:
        return pump.step()
    finally:
        del pump.link.FRESH


def _no_decay(pump, now):
    pump._decay = lambda: None
    try:
        return pump.step()
    finally:
        del pump._decay


def _late_clock(pump, now):
    t = pump.link.t
    clock, t.now = t.now, lambda: math.nextafter(now, math.inf)  # the cycle reads one ULP later
    try:
        return pump.step()
    finally:
        t.now = clock


def _then(fn):
    def change(pump, now):
        r = pump.step()
        return fn(pump, r)

    return change


def _nudge_c1(p, r):
    m = p.renderer.motion
    m._c1 = math.nextafter(m._c1, math.inf)
    return r


def _nudge_zi(p, r):
    p.renderer.eq.zi[0, 0] = np.nextafter(p.renderer.eq.zi[0, 0], np.inf)
    return r


def _bump(obj_path: str, attr: str):
    def fn(p, r):
        o = p
        for a in obj_path.split(".") if obj_path else ():
            o = getattr(o, a)
        setattr(o, attr, getattr(o, attr) + 1)
        return r

    return fn


PERTURBATIONS = {
    # (scenario, cycle, change, what the message must name)
    "motion_c1_one_ulp": ("steady_stroke", 120, _then(_nudge_c1), r"renderer\.motion\._c1"),
    "equalizer_state_one_ulp": ("steady_stroke", 120, _then(_nudge_zi), r"renderer\.eq\.zi"),
    "crossfade_one_more": ("steady_stroke", 120, _then(_bump("renderer", "_xfade_left")),
                           r"renderer\._xfade_left"),
    "statuses_counted_twice": ("steady_stroke", 120, _then(_bump("link.stats", "statuses")),
                               r"link\.stats\.statuses"),
    "position_one_count": ("steady_stroke", 120, _then(_bump("renderer.position", "_total")),
                           r"renderer\.position\._total"),
    "fill_target": ("steady_stroke", 120, _then(_bump("", "_fill")), r"\b_fill\b"),
    "deframer_keeps_a_byte": ("steady_stroke", 120,
                              _then(lambda p, r: (p.link.t.deframer._buf.append(7), r)[1]),
                              r"link\.t\.deframer\._buf"),
    "one_sample_more_reported": ("steady_stroke", 120, _then(lambda p, r: r + 1), "returned"),
    "a_log_line": ("steady_stroke", 120, _then(lambda p, r: (p.log("x"), r)[1]), "log lines differ"),
    "one_byte_lost": ("steady_stroke", 120, _write_one_byte_short, "bytes written differ"),
    # a frame more than the reference writes (caught at this action or, if the kernel has not
    # passed it on yet, at the next)
    "one_frame_more": ("steady_stroke", 120, _then(lambda p, r: (p.link.t.send(pr.encode("STOP")), r)[1]),
                        "bytes written differ"),
    "clock_one_ulp_late": ("steady_stroke", 120, _late_clock, r"status_host_time|_last_decay|_offset"),
    "no_fill_decay": ("underrun_fill_rises_and_decays", 40, _no_decay, r"_last_decay"),
    # the extra readings change the fit; the cubic's prediction (order 3) moves the codes
    # written in that same cycle, before the state is compared
    "backlog_all_fresh": ("host_stalls", 209, _all_fresh, r"renderer\.motion\.|bytes written differ"),
}


@pytest.mark.parametrize("name", list(PERTURBATIONS))
def test_the_comparison_catches_a_perturbed_cycle(textures, name):
    scenario, at, change, names = PERTURBATIONS[name]
    script, kw = SCENARIOS[scenario]
    tw = _twin(textures, f"{scenario}+{name}", step_b=_perturbed(at, change), **kw)
    try:
        with pytest.raises(Mismatch, match=names) as e:
            script(tw)
    finally:
        tw.close()
    # caught at once: step_b's call `at` is host action `at` (8 lead-in cycles, begin, cycles)
    late = 1 if name == "one_frame_more" else 0
    assert any(str(e.value).startswith(f"scenario '{scenario}+{name}', host action {k} (")
               for k in range(at, at + late + 1)), str(e.value)


def test_no_cycle_reads_an_empty_port_and_the_harness_sees_one_that_does(textures):
    """Neither cycle reads a tty that holds nothing (a read that finds the line discipline empty
    waits for the kernel's buffer work, which held a 1 ms cycle 9-14 ms on a busy machine): the
    harness counts each cycle's read() calls. Cycles with nothing waiting happen (lost STATUS
    frames), and a compiled cycle with one more read() of the empty port is caught there."""
    script, kw = SCENARIOS["lost_status"]
    tw = _twin(textures, "empty_port", **kw)
    try:
        script(tw)
    finally:
        tw.close()
    if tw.reads.fd is None and tw.seen["empty_port_cycles"] == 0:
        pytest.skip("this kernel does not count a thread's read() calls (/proc/thread-self/io)")
    assert tw.seen["empty_port_cycles"] >= 20, tw.seen["empty_port_cycles"]

    def one_more_read(pump, now):
        try:
            os.read(pump.link.t.ser.fd, 4096)
        except BlockingIOError:
            pass
        return fastpump.step(pump, now)

    tw = _twin(textures, "empty_port+read", step_b=one_more_read, **kw)
    try:
        with pytest.raises(Mismatch, match=r"the compiled cycle issued 1 read\(\) call\(s\) with 0 bytes"):
            script(tw)
    finally:
        tw.close()


def test_a_mismatch_names_the_field_the_step_and_the_scenario(textures):
    tw = _twin(textures, "naming", step_b=_perturbed(50, _then(_nudge_c1)))
    try:
        with pytest.raises(Mismatch) as e:
            _play(tw)
            tw.run(100)
    finally:
        tw.close()
    msg = str(e.value)
    # cycle 50 of step_b is host action 50 (action 0 .. 7: lead-in cycles, 8: begin, ...)
    assert msg.startswith("scenario 'naming', host action 50 (slot 50,") and "renderer.motion._c1" in msg
    assert "bits" in msg and "1 field(s) differ" in msg


# ------------------------------------------------------------------------ the ground the harness stands on
def test_the_pty_passes_every_byte_both_ways(textures):
    tw = _twin(textures, "bytes")
    try:
        fd = tw.a.t.ser.fd
        every = bytes(range(256)) * 4
        os.write(tw.a.master, every)  # device -> host: no echo, no CR/LF or XON/XOFF handling
        got = b""
        deadline = time.monotonic() + 2
        while len(got) < len(every) and time.monotonic() < deadline:
            select.select([fd], [], [], 0.1)
            try:
                got += os.read(fd, 4096)
            except BlockingIOError:
                pass
        assert got == every
        os.write(fd, every)  # host -> device
        got = b""
        while len(got) < len(every) and time.monotonic() < deadline:
            select.select([tw.a.master], [], [], 0.1)
            try:
                got += os.read(tw.a.master, 4096)
            except BlockingIOError:
                pass
        assert got == every
    finally:
        tw.close()


def test_the_snapshot_covers_the_cycle_s_state(textures):
    """The fields the compiled cycle must keep equal are in the snapshot (a rename in the
    reference that drops one from it fails here, not silently)."""
    tw = _twin(textures, "coverage")
    try:
        _play(tw)
        tw.run(5)
        keys = set(snapshot(tw.a.pump))
    finally:
        tw.close()
    records = {"pump": "", "pump_stats": "stats.", "link": "link.", "link_stats": "link.stats.",
               "health": "health.", "renderer": "renderer.", "position": "renderer.position.",
               "motion": "renderer.motion.", "height": "renderer.height.", "output": "renderer.out."}
    assert set(records) == set(cyclestate.SCHEMA)
    want = {p + f for kind, p in records.items() for f in cyclestate.SCHEMA[kind]} - EXCLUDE | {
        "_episode", "_started", "_retries_base", "stats.recoveries", "stats.io_dropped",
        "link.stats.bad_messages_received", "link.stats.last_status", "link.render_status",
        "link.ident", "health._last", "health._recent_flags", "renderer.motion._outliers",
        "renderer.motion.previous_fit", "renderer.height._w", "renderer.eq.zi",
        "link.t._pending", "link.t._queue", "link.t.deframer._buf", "link.t.deframer.bad_frames",
    }
    assert want <= keys, sorted(want - keys)
    assert not {"stats.step_us", "stats.max_late_us"} & keys

