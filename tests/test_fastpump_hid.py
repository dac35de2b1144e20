"""The compiled pump cycle in HID mode (hostd.device.fastpump on a HidrawTransport) against its
reference, Pump.step: the differential comparison of tests/test_fastpump.py (same harness,
tests/fastpump_twin.py, transport="hid"), each setup's HidrawTransport on an AF_UNIX
SOCK_SEQPACKET socket pair (a record per report, as hidraw). The scenarios lead the HID cycle
through its own paths: a stall backlog of more than 64 reports (the compiled cycle keeps those
beyond 64 in its overflow list), zero-length reads (counted, skipped; more than 64 in a row
end a read), a report with a non-zero byte after its STATUS, an unpadded and a truncated
STATUS, other messages, underruns, host timeouts, a device idle, deaf or reset, and recoveries,
a glitch and a re-lock, a reconnection, and a device that stops reading: writes fail with EAGAIN
(DeviceBusy), the compiled cycle hands the send to the reference, with none or the first of two
messages sent, and a restart's STOP meets the full buffer (DeviceBusy out of the cycle). The
perturbed twins prove the HID comparison sees a one-ULP, one-count, one-bit or one-report
difference and a busy write given up without its retries."""

from __future__ import annotations

import socket

import pytest

from hostd.device import fastpump
from hostd.device import protocol as pr
from hostd.device.hidlink import HidrawTransport
from hostd.device.pump import JitterConfig
from hostd.errors import DeviceBusy
from tests.fastpump_twin import Mismatch, jump_at, snapshot, standard_textures, stroke
from tests.test_fastpump import (
    PERTURBATIONS,
    _perturbed,
    _play,
    _then,
    _twin,
    sc_device_idle_reset_deaf,
    sc_glitch_and_jump,
    sc_host_stalls,
    sc_other_messages,
    sc_reconnect,
    sc_steady_stroke,
)

STATUS_LEN = pr.LAYOUTS["STATUS"].size  # (26 bytes: the rest of its report is padding)


@pytest.fixture(scope="module")
def textures():
    return standard_textures()


def _hid(textures, name, **kw):
    return _twin(textures, name, transport="hid", **kw)


def _handovers() -> dict:
    return fastpump._C.handovers() if fastpump._C is not None else {}


# ------------------------------------------------------------------------ HID's own scenarios
def sc_odd_reports(tw):
    _play(tw)
    tw.run(100)
    tw.insert(b"", framed=False)  # a zero-length report before the slot's STATUS: skipped
    tw.run(20)
    for _ in range(3):
        tw.insert(b"", framed=False, after=True)  # ... and after it
    tw.run(20)
    tw.transforms.append(lambda f: f[:STATUS_LEN])  # a STATUS without padding: a whole message
    tw.run(20)
    tw.transforms.append(lambda f: f[:40] + b"\x01" + f[41:])  # a byte in the padding: a bad message
    tw.run(20)
    tw.transforms.append(lambda f: f[: STATUS_LEN - 6])  # a truncated STATUS: a bad message
    tw.run(20)
    for _ in range(70):  # more zero-length reads than one recv takes (64): the STATUS behind waits
        tw.insert(b"", framed=False)
    tw.run(100)
    p = tw.a.pump
    assert p.link.t.empty_reads >= 1 + 3 + 70 and tw.seen["input_left"] >= 1
    assert p.link.stats.bad_messages_received == 2


def sc_busy(tw):
    _play(tw)
    tw.run(300)
    # the device stops reading for 12 ms: six reports fill the host's send buffer, every write
    # after them fails with EAGAIN (DeviceBusy: given up, io_dropped); the device plays on from
    # its 27 ms buffer
    tw.block_output(True)
    tw.run(12)
    tw.block_output(False)
    tw.run(200)
    assert tw.seen["busy_dropped"] >= 3 and tw.a.pump.health.underruns == 0
    # again, and after 15 cycles the device takes one report: the next cycle's batch (30 to 32
    # samples: two messages) gets its first message out and not the second (a partial send)
    tw.block_output(True)
    tw.run(14)
    tw.allow_output(1)
    tw.run(1)
    tw.block_output(True)
    before, partial = _handovers(), tw.seen["busy_partial"]
    tw.run(1)
    handed = {k: v - before[k] for k, v in _handovers().items() if v != before[k]}
    assert tw.seen["busy_partial"] == partial + 1  # (setup A: samples sent, a message retried, not dropped)
    if fastpump._C is not None:  # the compiled cycle sent the first message and handed the second over
        assert handed == {"write_error": 1}, handed
    tw.block_output(False)
    tw.run(200)
    # for 40 ms: the device runs dry while the host's writes fail (an underrun; its host timeout,
    # 50 ms, is not reached, so no control message meets a full buffer)
    tw.block_output(True)
    tw.run(40)
    tw.block_output(False)
    tw.run(300)
    p = tw.a.pump
    assert p.health.underruns >= 1 and p.stats.recoveries >= 1 and p.link.stats.io_retries > 0
    # for 52 ms: past the host timeout the device ramps down and goes idle, and the pump's
    # restart meets the full buffer: its STOP is retried for 50 ms, then DeviceBusy comes out of
    # the cycle (Pump.run counts it in io_dropped)
    recoveries = p.stats.recoveries
    tw.block_output(True)
    tw.run(52)  # (each cycle that meets it costs 2 x 50 ms of retries: a few)
    tw.block_output(False)
    tw.run(200)
    assert tw.seen["raised"] >= 1 and any("host timeout" in m for m in tw.a.logged)
    assert p.stats.recoveries > recoveries


# name: (script, Twin arguments, handover causes the compiled cycle must have met)
HID_SCENARIOS = {
    "steady_stroke": (sc_steady_stroke, {}, ()),
    # two stalls: > 64 reports in one poll (the overflow list), an underrun, a host timeout
    "host_stalls": (sc_host_stalls, {}, ("backlog",)),
    "odd_reports": (sc_odd_reports, {}, ("message",)),
    "other_messages": (sc_other_messages, {}, ("message",)),
    "glitch_and_jump": (sc_glitch_and_jump, {"hand": jump_at(stroke(), 0.6, 5.0)}, ("glitch",)),
    # device idle, deaf (the guard gives up, host timeout) and reset: the reference's restarts
    "device_idle_reset_deaf": (sc_device_idle_reset_deaf, {}, ("supervise",)),
    # a new socket pair, HidrawTransport and link (Pump.attach): the compiled cycle takes the new fd
    "reconnect": (sc_reconnect, {}, ()),
    # a 27 ms jitter buffer: the host's send buffer fills before the device's buffer runs dry;
    # record=True: the codes of a partial send (Pump._send_codes from the first message not sent)
    "busy": (sc_busy, {"jitter": JitterConfig(base_fill=80), "record": True}, ("write_error",)),
}
MOSTLY_COMPILED = {"steady_stroke"}


@pytest.mark.parametrize("name", list(HID_SCENARIOS))
def test_compiled_hid_cycle_equals_the_reference(textures, name):
    script, kw, causes = HID_SCENARIOS[name]
    tw = _hid(textures, f"hid:{name}", **kw)
    before = _handovers()
    try:
        script(tw)
        tw.finish()
    finally:
        tw.close()
    assert tw.seen["host_actions"] > 200
    if name == "host_stalls":
        assert tw.seen["max_status_per_poll"] > 64  # (fastpump's MAX_MSGS: the rest in its overflow list)
    if fastpump._C is not None:
        after = _handovers()
        diff = {k: after[k] - before[k] for k in after if after[k] != before[k]}
        done = diff.get("compiled", 0)
        handed = sum(v for k, v in diff.items() if k != "compiled")
        assert done > (handed if name in MOSTLY_COMPILED else 0), (name, diff)
        for cause in causes:
            assert diff.get(cause, 0) > 0, (name, cause, diff)


# ------------------------------------------------------------------------ the harness can fail
def _one_bit_off(pump, now):
    """The reference's cycle, but the last byte of each message it sends has one bit flipped."""
    t = pump.link.t
    real = t.send
    t.send = lambda msg: real(msg[:-1] + bytes([msg[-1] ^ 1]))
    try:
        return pump.step()
    finally:
        del t.send


def _give_up_at_once(pump, now):
    """The reference's cycle, but a busy write is given up without a retry."""
    link = pump.link

    def send(msg, must=False):
        link.t.send(msg)  # (DeviceBusy goes straight up)
        link.stats.messages_sent += 1

    link._send = send
    try:
        return pump.step()
    finally:
        del link._send


HID_PERTURBATIONS = {
    # (scenario, cycle, change, what the message must name)
    "motion_c1_one_ulp": PERTURBATIONS["motion_c1_one_ulp"],
    "one_report_more": PERTURBATIONS["one_frame_more"],
    "empty_reads_one_more": ("steady_stroke", 120,
                             _then(lambda p, r: (setattr(p.link.t, "empty_reads", p.link.t.empty_reads + 1),
                                                 r)[1]), r"link\.t\.empty_reads"),
    "a_code_one_bit_off": ("steady_stroke", 120, _one_bit_off, "bytes written differ"),
    "busy_write_not_retried": ("busy", 317, _give_up_at_once, r"link\.stats\.io_retries moved in one setup"),
}


@pytest.mark.parametrize("name", list(HID_PERTURBATIONS))
def test_the_hid_comparison_catches_a_perturbed_cycle(textures, name):
    scenario, at, change, names = HID_PERTURBATIONS[name]
    script, kw, _ = HID_SCENARIOS[scenario]
    label = f"hid:{scenario}+{name}"
    tw = _hid(textures, label, step_b=_perturbed(at, change), **kw)
    try:
        with pytest.raises(Mismatch, match=names) as e:
            script(tw)
    finally:
        tw.close()
    # caught at once: step_b's call `at` is host action `at` (8 lead-in cycles, begin, cycles)
    assert str(e.value).startswith(f"scenario {label!r}, host action {at} ("), str(e.value)


# ------------------------------------------------------------------------ the ground the harness stands on
def test_the_socket_pair_behaves_as_a_hidraw_node():
    """What the HID twin relies on: report boundaries kept both ways, a zero-length report read
    as zero bytes (counted in empty_reads, skipped), the host's reports as report id 0 + 64
    bytes, and a device that does not read making the host's writes fail with DeviceBusy once
    its (smallest) send buffer is full."""
    from tests.fastpump_twin import HOST_T0_S, HidSetup

    s = HidSetup("A", None, HOST_T0_S)
    try:
        status = pr.encode("STATUS")
        s.write_device([b"", s.wire(status), b"", status[:STATUS_LEN]])
        s.await_input()
        assert s.t.drain() == [pr.pad_report(status), status[:STATUS_LEN]] and s.t.empty_reads == 2
        s.t.send(pr.encode("STOP"))
        assert s.take_output(0) == (b"\0" + pr.pad_report(pr.encode("STOP")),)
        s.block_output(True)
        sent = 0
        with pytest.raises(DeviceBusy):
            for _ in range(64):
                s.t.send(pr.encode("STOP"))
                sent += 1
        assert 1 <= sent < 12 and s.take_output(0) == () and s.wire_state() == sent * 65
        s.block_output(False)
        assert len(s.take_output(0)) == sent
        assert isinstance(s.t, HidrawTransport) and s.dev_sock.type == socket.SOCK_SEQPACKET
    finally:
        s.close()


def test_the_hid_snapshot_has_the_transport_s_state(textures):
    tw = _hid(textures, "hid:coverage")
    try:
        _play(tw)
        tw.run(5)
        keys = set(snapshot(tw.a.pump))
    finally:
        tw.close()
    assert "link.t.empty_reads" in keys and not any(k.startswith("link.t.deframer") for k in keys)
    assert {"renderer.motion._c1", "link._seq", "stats.io_dropped", "link.stats.io_retries"} <= keys
