"""Device-side rendering (protocol v2): messages and helpers, the firmware renderer's Python
model against the C firmware on shared vectors, refused uploads, and the safety stage."""

from __future__ import annotations

import time

import numpy as np
import pytest

from hostd.device import protocol as pr
from hostd.errors import DeviceVersion

IDENT_V1 = dict(protocol_version=1, sample_rate_hz=3000, dac_bits=16, max_samples=29)
IDENT_V2 = dict(IDENT_V1, protocol_version=2)
CAPS = dict(render=1, max_components=512, max_sections=4, chunk_coeffs=14, edge_clock_hz=12_000_000,
            xfade_ticks=150)


def test_a_version_1_device_streams_but_device_mode_says_what_to_do():
    assert pr.check_version(IDENT_V1) == 1 and pr.check_version(IDENT_V2) == 2
    with pytest.raises(DeviceVersion, match="update the firmware"):
        pr.check_version(dict(IDENT_V1, protocol_version=3))
    assert not pr.render_capable(IDENT_V1, None)
    with pytest.raises(DeviceVersion, match=r'protocol v1 firmware.*where = "host"'):
        pr.require_render(IDENT_V1, None)
    with pytest.raises(DeviceVersion, match="did not report render capability"):
        pr.require_render(IDENT_V2, dict(CAPS, render=0))
    with pytest.raises(DeviceVersion, match="at most 512 components"):
        pr.require_render(IDENT_V2, CAPS, n_coeffs=513)
    with pytest.raises(DeviceVersion, match="at most 4 equalizer sections"):
        pr.require_render(IDENT_V2, CAPS, n_sections=5)
    pr.require_render(IDENT_V2, CAPS, n_coeffs=512, n_sections=4)


def test_texture_upload_messages_fit_a_report_and_carry_the_crc():
    coeffs = [0.001 * (i % 17) - 0.005 for i in range(300)]
    msgs = pr.texture_messages(2, coeffs, 2048, 12.5, scale=1.0)
    assert all(len(m) <= pr.REPORT_SIZE for m in msgs)
    name, head = pr.decode(msgs[0])
    assert name == "LOAD_TEXTURE" and head["n_coeffs"] == 300 and head["length_nm"] == 12_500_000
    got = []
    for m in msgs[1:-1]:
        name, f = pr.decode(m)
        assert name == "LOAD_CHUNK" and f["first"] == len(got)
        got += f["coeffs"]
    assert got == pr.f32(coeffs) and pr.texture_crc32(got) == head["crc32"]
    assert pr.decode(msgs[-1]) == ("LOAD_END", {"id": pr.IDS["LOAD_END"], "slot": 2})
    with pytest.raises(pr.ProtocolError, match=r"1\.\.512 components"):
        pr.texture_messages(0, [0.0] * 513, 2048, 12.5)
    with pytest.raises(pr.ProtocolError, match="finite"):
        pr.texture_messages(0, [float("nan")], 2048, 12.5)
    with pytest.raises(pr.ProtocolError, match="LOAD_CHUNK holds at most 14"):
        pr.encode("LOAD_CHUNK", coeffs=[0.0] * 15)


# ------------------------------------------------------------------ the model against the C firmware
def _setup(name: str, slot: int = 1):
    from hostd.bench.accuracy import texture_coeffs
    from hostd.device import devrender
    from hostd.texture import synth

    c, n, length = texture_coeffs(synth.make(name, seed=1))
    return devrender.setup_messages(c, n, length, slot=slot), (c, n, length)


def test_python_model_matches_the_c_firmware_within_one_code():
    """Shared scenario: setup and START_RENDER, metronome strokes with edges at the true times,
    a corrupt upload (refused, output unchanged), a swap to another texture (crossfade), and
    STOP_RENDER. C (fw-replay) and the model (SimDevice) agree within 1 DAC code on every tick."""
    from hostd.device import devrender
    from hostd.sim.hand import Metronome

    setup, _ = _setup("wood")
    swap, (c2, n2, len2) = _setup("sandpaper", slot=2)
    corrupt = pr.texture_messages(7, c2, n2, len2)
    corrupt[3] = corrupt[3][:5] + bytes([0x00, 0x00, 0xC0, 0x7F]) + corrupt[3][9:]  # a NaN
    at = {0: [*setup, pr.encode("START_RENDER", host_lost_ms=5000)],
          1200: corrupt, 2400: [m for m in swap if 0x20 <= m[0] <= 0x22], 4000: [pr.encode("STOP_RENDER")]}
    ev = devrender.scenario(Metronome(), 1.5, at)
    c_codes, _ = devrender.run_c(ev)
    py_codes, dev = devrender.run_model(ev)
    assert c_codes.size == py_codes.size == 4500
    diff = np.abs(c_codes - py_codes)
    assert diff.max() <= 1, (int(diff.max()), int(np.argmax(diff)))
    assert np.abs(c_codes[300:2400]).max() > 1000  # a real texture was rendered
    assert dev.render.refused >= 2 and dev.render.loads == 2  # corrupt refused, swap loaded
    assert c_codes[-1] == 0 and dev.state == pr.STATES["IDLE"]  # faded out after STOP_RENDER


# ------------------------------------------------------------------ the simulated display in device mode
def _render_on_sim(protocol_version: int = pr.VERSION):
    from hostd.device.link import DeviceLink
    from hostd.device.simdev import SimTransport
    from hostd.sim.hand import Metronome

    t = SimTransport(realtime=False, hand=Metronome())
    t.device.protocol_version = protocol_version
    link = DeviceLink(t)
    t.advance(3)
    ident = link.handshake(timeout_s=0.1)
    caps = None
    while (m := t.recv(0.0)) is not None:
        name, f = pr.decode(m)
        caps = f if name == "CAPS" else caps
    return t, link, ident, caps


def test_device_mode_on_the_simulated_display_survives_a_silent_host():
    """Upload + START_RENDER, then 2 s in which the host sends nothing: the display keeps
    rendering, code for code as a twin whose host kept talking; no fade, no refusal."""
    t, _link, ident, caps = _render_on_sim()
    twin, _l2, _i2, _c2 = _render_on_sim()
    pr.require_render(ident, caps, n_coeffs=160, n_sections=1)
    setup, _ = _setup("wood")
    acks = []
    for tr in (t, twin):
        for m in [*setup, pr.encode("START_RENDER", host_lost_ms=1000)]:
            tr.send(m)
        while (m := tr.recv(0.0)) is not None:
            name, f = pr.decode(m)
            if name == "ACK" and tr is t:
                acks.append(f)
    assert acks and all(a["result"] == 0 for a in acks)
    assert acks[-1]["for_id"] == pr.IDS["START_RENDER"]
    silent, talking = [], []
    for _ in range(3 * 2000):  # 2 s; the twin's host sends IDENTIFY every 1 ms
        t.advance(1)
        twin.advance(1)
        if twin.device.ticks % 3 == 0:
            twin.send(pr.encode("IDENTIFY"))
        silent.append(t.device.out)
        talking.append(twin.device.out)
    dev = t.device
    assert dev.state == pr.STATES["RENDERING"] and dev.render.env_target == 1
    assert dev.render.host_lost  # past host_lost_ms, flagged, yet still rendering: the hand moves
    assert silent == talking and np.abs(np.array(silent)).max() > 1000
    assert dev.underruns == 0 and dev.render.refused == 0


def test_a_version_1_simulated_display_refuses_device_mode_clearly():
    t, _link, ident, caps = _render_on_sim(protocol_version=1)
    assert ident["protocol_version"] == 1 and caps is None
    with pytest.raises(DeviceVersion, match="cannot render on the device"):
        pr.require_render(ident, caps)
    t.send(pr.encode("START_RENDER"))  # an unknown message to v1 firmware
    assert t.device.malformed == 1 and t.device.state == pr.STATES["IDLE"]


# ------------------------------------------------------------------ the real firmware on a pty
def test_device_mode_through_the_firmware_host_port_survives_a_silent_host(tmp_path):
    """The C firmware on the host port renders from its own (simulated) encoder, edges at the
    hand's true times: setup and START_RENDER over the serial link, then the host says nothing
    for 2 s (as if stopped): the texture is not interrupted (no zero stretch, no fade); every
    render message was accepted; and the DAC log equals the Python model fed what the port
    fed the core (its --scenario: bytes, timed edges, ticks) within 1 code."""
    import subprocess
    import time

    from hostd.device import hostport
    from hostd.device.link import DeviceLink
    from hostd.device.seriallink import SerialTransport

    exe = hostport.build()
    setup, _ = _setup("wood")  # before the pty opens: a slow import after it can hang it up here
    log = tmp_path / "dac.bin"
    scen = tmp_path / "scenario.txt"
    proc = subprocess.Popen([str(exe), "--motion", "metronome", "--log", str(log), "--duration", "4.5",
                             "--scenario", str(scen)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline().split()
        assert line[0] == "PTY", line
        t = SerialTransport(line[1])
        link = DeviceLink(t)
        ident = link.handshake(timeout_s=2.0)
        for m in [*setup, pr.encode("START_RENDER", host_lost_ms=1000)]:
            t.send(m)
        acks, caps, deadline = [], None, time.monotonic() + 1.0
        while time.monotonic() < deadline and not (acks and acks[-1]["for_id"] == pr.IDS["START_RENDER"]):
            m = t.recv(0.01)
            if m is None:
                continue
            name, f = pr.decode(m)
            acks += [f] if name == "ACK" else []
            caps = f if name == "CAPS" else caps
        pr.require_render(ident, caps, n_coeffs=160, n_sections=1)
        assert acks and all(a["result"] == 0 for a in acks), acks
        t_start = time.monotonic()
        time.sleep(2.0)  # a silent host
        link.poll(0.05)
        status = link.stats.last_status
        t.close()
    finally:
        proc.terminate()
        proc.communicate(timeout=10)
    assert status["state"] == pr.STATES["RENDERING"]
    rec = hostport.read_log(log)
    codes = rec["code"].astype(np.int64)
    start = int(np.argmax(codes != 0))  # rendering began (after the fade-in starts)
    silent = codes[start + 600 : start + 600 + int((time.monotonic() - t_start - 0.3) * 3000)]
    assert silent.size > 4500
    assert np.abs(silent).max() > 1000
    d = np.diff(np.r_[0, (silent == 0).astype(int), 0])
    zero_runs = np.flatnonzero(d == -1) - np.flatnonzero(d == 1)
    assert zero_runs.size == 0 or zero_runs.max() < 30, zero_runs.max()  # never silent for 10 ms
    from hostd.device import devrender

    ev = devrender.read_scenario(scen)
    model, _dev = devrender.run_model(ev)
    n = min(model.size, codes.size)
    assert n >= codes.size - 1 and n > 4500  # the log may hold one tick more than the file
    assert np.abs(model[:n] - codes[:n]).max() <= 1
    replayed, _ = devrender.run_c(ev)
    assert np.array_equal(replayed[:n], codes[:n])  # the scenario is complete: C replays it exactly


def test_send_and_confirm_uploads_swaps_and_names_a_refusal(monkeypatch):
    """The host helper on the simulated display: setup and START_RENDER confirmed, a
    swap during a crossfade waits (BUSY, resent), a corrupt upload raises saying what happened."""
    from hostd.device import devrender
    from hostd.device.simdev import SimTransport
    from hostd.errors import DeviceError

    class Polled(SimTransport):  # the display's clock advances 1 ms per empty poll: fast and exact
        def recv(self, timeout_s=0.0):
            if not self.device.outbox:
                self.advance(3)
            return super().recv(0.0)

    t = Polled(realtime=False)
    # the host's pause before resending a BUSY swap passes on the display's clock too
    monkeypatch.setattr(time, "sleep", lambda s: t.advance(round(s * pr.SAMPLE_RATE_HZ)))
    setup, _ = _setup("wood")
    acks = devrender.send_and_confirm(t, [*setup, pr.encode("START_RENDER")])
    assert [a["for_id"] for a in acks][-2:] == [pr.IDS["LOAD_END"], pr.IDS["START_RENDER"]]
    swap2, (c2, n2, len2) = _setup("sandpaper", slot=2)
    devrender.send_and_confirm(t, [m for m in swap2 if 0x20 <= m[0] <= 0x22])
    devrender.send_and_confirm(t, pr.texture_messages(3, c2[:50], n2, len2))  # BUSY, then accepted
    dev = t.device
    assert dev.render.loads == 3 and dev.render.refused >= 1  # the BUSY answer counts as refused
    bad = pr.texture_messages(4, c2, n2, len2)
    bad[2] = bad[2][:5] + bytes([0, 0, 0x80, 0x7F]) + bad[2][9:]  # +Inf
    with pytest.raises(DeviceError, match=r"refused LOAD_CHUNK \(NONFINITE"):
        devrender.send_and_confirm(t, bad)
    assert dev.state == pr.STATES["RENDERING"]
    t.close()


def test_an_upload_not_answered_in_time_is_a_timeout_and_is_sent_once_more(monkeypatch):
    """No ACK within the wait is DeviceTimeout, not a refusal; DeviceMode.begin then sends the
    whole upload once more with RETRY_ACK_S to wait before the host renders instead (the VM rig
    under load missed a SET_EQ's ACK by the 1 s and rendered on the host for the connection)."""
    from hostd.device import devmode, devrender
    from hostd.device.link import DeviceLink
    from hostd.device.simdev import SimTransport
    from hostd.errors import DeviceTimeout
    from hostd.render.pipeline import RenderConfig

    clock = [0.0]

    class Deaf:  # a display that never answers, on a clock that moves 10 ms per poll
        def send(self, m):
            pass

        def recv(self, timeout_s=0.0):
            clock[0] += 0.01
            return None

        def describe(self):
            return "deaf"

    monkeypatch.setattr(time, "monotonic", lambda: clock[0])
    setup, _ = _setup("wood")
    with pytest.raises(DeviceTimeout, match="no ACK for SET_EQ within 1 s"):
        devrender.send_and_confirm(Deaf(), setup)
    # an idle display reports every 1 ms: the line is never quiet, and an answer it dropped (its
    # queue to a paused host full) never comes; the wait still ends (it did not: a re-upload
    # after a host pause waited for ever while the reports flowed)
    status = pr.encode("STATUS", **{k: 0 for k, _ in pr.LAYOUTS["STATUS"].fields if k != "id"})
    taken = []

    class Chatty(Deaf):
        def recv(self, timeout_s=0.0):
            clock[0] += 0.001
            assert clock[0] < 60.0, "still waiting after 60 s of the display's reports"
            return status

    with pytest.raises(DeviceTimeout, match="no ACK for SET_EQ within 1 s"):
        devrender.send_and_confirm(Chatty(), setup, on_other=taken.append)
    assert 900 <= len(taken) <= 1100  # the reports of that second went to the link meanwhile
    monkeypatch.undo()

    t = SimTransport(realtime=False)  # its IDENT and CAPS, taken without running its clock
    link = DeviceLink(t)
    link.ident = pr.decode(t.device.ident())[1]
    link.caps = pr.decode(t.device.caps())[1]
    waits = []

    def first_unanswered(tr, msgs, timeout_s=1.0, **kw):
        waits.append(timeout_s)
        if len(waits) == 1:
            raise DeviceTimeout("no ACK for SET_EQ within 1 s")
        return []

    monkeypatch.setattr(devrender, "send_and_confirm", first_unanswered)
    _, (c, n, length) = _setup("wood")
    dev = devmode.DeviceMode(link, RenderConfig(), log=lambda m: None)
    dev._taken_over = True  # (a display known idle: take_over has its own test)
    dev.begin(("wood", c, n, length))
    assert waits == [1.0, devmode.DeviceMode.RETRY_ACK_S] and dev.rendering and dev.uploads == 1
    waits.clear()
    def never_answered(tr, msgs, timeout_s=1.0, **kw):
        waits.append(timeout_s)
        raise DeviceTimeout("no ACK")

    monkeypatch.setattr(devrender, "send_and_confirm", never_answered)
    dev2 = devmode.DeviceMode(link, RenderConfig(), log=lambda m: None)
    dev2._taken_over = True
    with pytest.raises(DeviceTimeout):  # twice unanswered: the caller renders on the host
        dev2.begin(("wood", c, n, length))
    assert len(waits) == 2 and not dev2.rendering
    t.close()


def test_device_rendering_is_within_one_percent_and_inside_the_slew_limit():
    """Issue 12's accuracy goal on its hardest texture, measured as `hostd bench accuracy`
    measures the render_at = device row: the C firmware (fw-replay) renders from edges at the
    hand's true times, the held DAC drives the actuator model, and the delivered displacement
    is compared with the exact series at the true position and speed (default band). And the
    default band keeps the equalized command of the steepest bench texture (wood) inside the
    piezo's slew limit at the metronome's ~93 mm/s peak, with margin: the safety stage limits,
    it must not shape the texture."""
    from hostd.bench import accuracy
    from hostd.device import devrender
    from hostd.render.output import OutputConfig
    from hostd.render.pipeline import RenderConfig
    from hostd.sim.hand import Metronome
    from hostd.texture import synth

    c, n, length = accuracy.texture_coeffs(synth.make("sandpaper", seed=1))
    got = accuracy.measure_device(c, n, length, RenderConfig(), 1.6, Metronome(), {})
    assert got["rms_error_pct"] <= 1.0, got
    assert got["ideal_rms_um"] > 0.5  # a real texture, not a silent one

    c, n, length = accuracy.texture_coeffs(synth.make("wood", seed=1))
    cfg = RenderConfig()
    msgs = [*devrender.setup_messages(c, n, length, cfg), pr.encode("START_RENDER")]
    codes, _ns = devrender.run_c(devrender.scenario(Metronome(), 1.2, {0: msgs}), timed=True)
    out = OutputConfig()
    step_limit = out.slew_um_s / out.sample_rate_hz / out.um_per_code  # codes per tick
    steps = np.abs(np.diff(codes.astype(np.float64)))
    assert np.abs(codes).max() > 5000  # the stroke's fast part was rendered
    assert steps.max() <= 0.9 * step_limit, (steps.max(), step_limit)  # 88 %; a 1200 Hz band: 100 %


def test_a_stop_while_an_upload_waits_for_its_answers_still_says_stop_render(monkeypatch):
    """The VM rig: `systemctl stop` came while the display already rendered but its answers to
    the upload were not in (a slow guest); the pump's stop path skipped STOP_RENDER and the
    display, its host lost but the hand moving, rendered on. Now a stop interrupts the wait
    (UploadAborted, at once) and end() says STOP_RENDER whenever START_RENDER went out, answered
    or not; the same after an upload that timed out twice."""
    for case in ("abort", "timeout"):
        _stop_during_upload(case, monkeypatch)
        monkeypatch.undo()


def _stop_during_upload(case, monkeypatch):
    from hostd.device import devmode, devrender
    from hostd.device.link import DeviceLink
    from hostd.device.simdev import SimTransport
    from hostd.errors import DeviceTimeout
    from hostd.render.pipeline import RenderConfig

    _, (c, n, length) = _setup("wood")
    t = SimTransport(realtime=False)
    link = DeviceLink(t)
    link.ident = pr.decode(t.device.ident())[1]
    link.caps = pr.decode(t.device.caps())[1]
    sent = []
    monkeypatch.setattr(t, "send", lambda m: sent.append(pr.NAMES[m[0]]))  # taken, never answered
    monkeypatch.setattr(t, "recv", lambda timeout_s=0.0: None)
    dev = devmode.DeviceMode(link, RenderConfig(), log=lambda m: None)
    dev._taken_over = True  # (a display known idle: take_over has its own test)
    if case == "abort":
        polls = [0]

        def stopping():
            polls[0] += 1
            return polls[0] > 3  # the stop arrives during the wait for the first answer
        dev.abort = stopping
        with pytest.raises(devrender.UploadAborted):
            dev.begin(("wood", c, n, length))
        assert polls[0] == 4  # given way at the first poll after the stop, not at a deadline
    else:
        def unanswered(tr, msgs, timeout_s=1.0, **kw):
            for m in msgs:
                tr.send(m)
            raise DeviceTimeout("no ACK")
        monkeypatch.setattr(devrender, "send_and_confirm", unanswered)
        with pytest.raises(DeviceTimeout):
            dev.begin(("wood", c, n, length))
        assert "START_RENDER" in sent  # it went out: the display may be rendering
    assert not dev.rendering
    sent.clear()
    dev.end()
    assert sent == ["STOP_RENDER"], case
    sent.clear()
    dev.end()  # said once: a second end() has nothing to stop
    assert sent == [], case


def test_an_upload_counts_each_answer_as_progress_for_the_watchdog():
    """The VM rig under load: a display's upload took longer than WatchdogSec=5 and systemd
    killed the daemon at every try. send_and_confirm calls alive() for each message that
    arrives (an ACK, a STATUS meanwhile): the pump counts them as progress; silence is not."""
    from hostd.device import devrender

    setup, _ = _setup("wood")

    class Answering:  # ACKs each message that expects one, with a STATUS before it
        def __init__(self):
            self.out = []

        def send(self, m):
            if devrender.expects_ack(m):
                self.out += [pr.encode("STATUS", state=pr.STATES["IDLE"]),
                             pr.encode("ACK", for_id=m[0], result=pr.RESULTS["OK"])]

        def recv(self, timeout_s=0.0):
            return self.out.pop(0) if self.out else None

        def describe(self):
            return "answering"

    calls = []
    acks = devrender.send_and_confirm(Answering(), setup, alive=lambda: calls.append(1))
    assert len(acks) == sum(devrender.expects_ack(m) for m in setup) > 1
    assert len(calls) == 2 * len(acks)  # every arrival, the STATUS too


def test_a_new_host_takes_over_a_display_still_rendering_a_previous_hosts_texture():
    """The VM rig after `systemctl kill -s KILL`: the display rendered the killed host's texture
    on (a lost host, the hand moving), the restarted host's SET_EQ was refused BUSY and it
    rendered on the host with the old texture still under it. DeviceMode.begin on a display it
    did not start stops it first (STOP_RENDER, then its STATUS of a state other than
    RENDERING), and the upload is accepted."""
    from hostd.device import devmode
    from hostd.device.link import DeviceLink
    from hostd.device.simdev import SimTransport
    from hostd.render.pipeline import RenderConfig
    from hostd.sim.hand import Metronome

    t = SimTransport(realtime=True, hand=Metronome())
    try:
        link = DeviceLink(t)
        link.handshake(timeout_s=2.0)
        link.await_caps(1.0)
        _, (c, n, length) = _setup("wood")
        first = devmode.DeviceMode(link, RenderConfig(), log=lambda m: None)
        first.begin(("wood", c, n, length))
        assert t.device.state == pr.STATES["RENDERING"]
        # the first host is gone without a word; a second one connects to the same display
        second = devmode.DeviceMode(link, RenderConfig(), log=lambda m: None)
        second.begin(("wood", c, n, length))  # raised DeviceError (SET_EQ BUSY) before
        assert second.rendering and second.uploads == 1 and t.device.state == pr.STATES["RENDERING"]
        assert t.device.render.refused == 0
    finally:
        t.close()
