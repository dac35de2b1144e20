"""Device mode through the real daemon: `[render] where = "device"` on the firmware's host port.

The daemon uploads the texture and the render parameters, starts device rendering and then
only supervises. A 2 s SIGSTOP of the whole daemon (and its pump process) must not interrupt
the texture: from the DAC log, the display renders on every tick of the pause and the output
keeps following the hand; the DAC log equals the Python model of the firmware fed what the
port fed the core, within 1 code; a texture swap stays within the slew limit.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from hostd.bench import soak
from hostd.cli import main
from hostd.device import hostport
from hostd.device import protocol as pr
from hostd.service.client import request, send_file
from tests.daemon_helpers import wait_for


def test_device_mode_daemon_survives_a_2s_sigstop_and_swaps_without_a_jump(tmp_path):
    try:
        hostport.build()
    except RuntimeError as e:
        pytest.fail(str(e))
    for name, seed, levels in (("wood", 1, "14"), ("wood8", 2, "8")):
        assert main(["encode", f"synthetic:wood:{seed}", "-o", str(tmp_path / f"{name}.vtx"),
                     "--method", "quant", "--levels", levels]) == 0
    log, scen = tmp_path / "dac.bin", tmp_path / "scenario.txt"
    hp = hostport.HostPort(["--motion", "metronome", "--duration", "120", "--scenario", str(scen)], log=log,
                           clock=tmp_path / "clock.bin")
    cfg = tmp_path / "hostd.toml"
    cfg.write_text(f'[device]\ntransport = "serial:{hp.pty}"\n[render]\nwhere = "device"\n'
                   '[library]\ndir = "lib"\nspool = "spool"\n'
                   '[control]\nsocket = "hostd.sock"\ngroup = ""\n[quality]\ndb = "q.sqlite"\n')
    sock = str(tmp_path / "hostd.sock")
    daemon = subprocess.Popen([sys.executable, "-m", "hostd", "run", "--config", str(cfg)], cwd=tmp_path,
                              stderr=open(tmp_path / "hostd.log", "w"), start_new_session=True)
    try:
        wait_for(lambda: request(sock, {"cmd": "status"}, timeout_s=2)["connected"], 90, "the device")
        for name in ("wood", "wood8"):
            send_file(sock, str(tmp_path / f"{name}.vtx"), name)
        request(sock, {"cmd": "select", "name": "wood"})
        wait_for(lambda: request(sock, {"cmd": "status"})["device_state"] == "rendering", 30, "rendering")
        time.sleep(1.0)
        os.killpg(daemon.pid, signal.SIGSTOP)
        t_stop = time.monotonic()
        time.sleep(2.0)
        # 2 s of the device's clock (the port's ticks): a loaded machine slows the port too
        t_cont = hp.wait_ticks(t_stop, 6000)
        os.killpg(daemon.pid, signal.SIGCONT)
        time.sleep(0.5)
        uploads0 = request(sock, {"cmd": "status"})["device_uploads"]
        t_swap = time.monotonic()
        request(sock, {"cmd": "select", "name": "wood8"})  # a swap: the display crossfades
        # the swap's upload holds the status where it was (a loaded machine: most of a second);
        # then the hand's speed, as the display measures it, over one whole metronome period
        # (2.4 s) of the display's clock and two report periods (300 ms) and publish periods
        # (0.5 s) more: it moves faster than 5 mm/s for most of a period, slower only near
        # its turns, so at least one report in it is fast
        wait_for(lambda: request(sock, {"cmd": "status"})["device_uploads"] > uploads0, 60, "the swap")
        t_sample, speeds = time.monotonic(), []
        while not hp.ticks_since(t_sample, round((2.4 + 2 * 0.3 + 2 * 0.5) * 3000)):
            speeds.append(request(sock, {"cmd": "status"})["speed_mm_s"])
            time.sleep(0.05)
        speeds.append(request(sock, {"cmd": "status"})["speed_mm_s"])
        st = request(sock, {"cmd": "status"})
    finally:
        hp.close()
        if daemon.poll() is None:
            os.killpg(daemon.pid, signal.SIGCONT)
            daemon.send_signal(signal.SIGTERM)
            daemon.wait(20)
    journal = (tmp_path / "hostd.log").read_text()
    assert st["render_at"] == "device" and st["device_state"] == "rendering", (st, journal[-1500:])
    assert st["device_underruns"] == 0 and st["samples"] == 0  # nothing was streamed
    assert max(abs(v) for v in speeds) > 5.0, speeds  # the metronome hand moves at up to ~93 mm/s
    rec = hostport.read_log(log)
    codes = rec["code"].astype(np.int64)
    rendering = (rec["flags"] & hostport.RENDERING) != 0
    tick0 = int(rec["tick"][0])
    a, b = hp.tick_at(t_stop) - tick0, hp.tick_at(t_cont) - tick0
    assert b - a >= 6000
    assert rendering[a:b].all(), "the display stopped rendering while the daemon was stopped"
    pause = codes[a:b]
    assert np.abs(pause).max() > 1000  # the texture went on under the moving hand
    zero = np.diff(np.r_[0, (pause == 0).astype(int), 0])
    runs = np.flatnonzero(zero == -1) - np.flatnonzero(zero == 1)
    assert runs.size == 0 or runs.max() < 30  # never silent for 10 ms
    # the swap: within the slew limit, and well below a hard cut's step
    s = hp.tick_at(t_swap) - tick0
    assert np.abs(np.diff(codes[s - 30 : s + 600])).max() <= pr.MAX_STEP_CODE
    # the DAC log equals the model of the firmware fed the same inputs, within 1 code
    from hostd.device import devrender

    model, _dev = devrender.run_model(devrender.read_scenario(scen))
    n = min(model.size, codes.size)
    assert n >= codes.size - 2 and np.abs(model[:n] - codes[:n]).max() <= 1


def test_default_config_renders_on_the_device_and_played_fraction_is_the_displays_own(tmp_path):
    """Issue 22: with a default config (no [render] where) the daemon renders on a v2 display
    and says why; it sleeps between the display's reports (no wake-up per millisecond); and the
    device-mode played fraction is the display's own count of ticks rendered at full gain over
    ticks due: when the host is lost and the hand rests, the display fades out and idles, the
    fraction drops, and it equals what the firmware's DAC log shows (its full-gain flag)."""
    try:
        hostport.build()
    except RuntimeError as e:
        pytest.fail(str(e))
    assert main(["encode", "synthetic:wood:1", "-o", str(tmp_path / "wood.vtx"), "--method", "quant",
                 "--levels", "14"]) == 0
    log = tmp_path / "dac.bin"
    period = 4.0  # the hand jumps 0.4 mm every 4 s and rests in between
    hp = hostport.HostPort(["--motion", f"steps:{period}:0.4", "--duration", "120"], log=log,
                           clock=tmp_path / "clock.bin")
    cfg = tmp_path / "hostd.toml"
    cfg.write_text(f'[device]\ntransport = "serial:{hp.pty}"\n[library]\ndir = "lib"\nspool = "spool"\n'
                   '[control]\nsocket = "hostd.sock"\ngroup = ""\n[quality]\ndb = "q.sqlite"\n')
    sock = str(tmp_path / "hostd.sock")
    daemon = subprocess.Popen([sys.executable, "-m", "hostd", "run", "--config", str(cfg)], cwd=tmp_path,
                              stderr=open(tmp_path / "hostd.log", "w"), start_new_session=True)
    try:
        wait_for(lambda: request(sock, {"cmd": "status"}, timeout_s=2)["connected"], 90, "the device")
        send_file(sock, str(tmp_path / "wood.vtx"), "wood")
        t_select = time.monotonic()
        request(sock, {"cmd": "select", "name": "wood"})
        wait_for(lambda: request(sock, {"cmd": "status"})["device_state"] == "rendering", 30, "rendering")
        upload_s = time.monotonic() - t_select  # this machine's speed now: select, upload, start
        a = request(sock, {"cmd": "status"})
        t_a = time.monotonic()
        # a lean supervisor (issue 28): the pump renders nothing, so it maps no scipy (its
        # equalizer is designed in a child) nor anything else beyond numpy, runs one thread (no
        # BLAS pool), and the daemon's threads sleep until needed (one control handler at rest)
        pump = soak._pump_pid(daemon.pid)
        footprint = {"pump_libs": soak.mapped_libs(pump), "daemon_libs": soak.mapped_libs(daemon.pid),
                     "pump_threads": soak.threads(pump), "daemon_threads": soak.threads(daemon.pid),
                     "pump_policy": os.sched_getscheduler(pump), "pump_priority": os.sched_getparam(pump)}
        # stop the daemon just after a jump, for 2.5 s: lost after 1 s, the hand has rested
        # 0.5 s by then, so the display fades out and idles until the daemon is back
        # (every span on the display's own clock, its ticks: a loaded machine stretches the port's
        # time against the host's, and the hand moves on the port's time)
        rate = pr.SAMPLE_RATE_HZ
        jump_tick = (int(hp.ticks() / (period * rate)) + 1) * round(period * rate)
        hp.wait_ticks(time.monotonic(), jump_tick + round(0.1 * rate) - hp.ticks())
        os.killpg(daemon.pid, signal.SIGSTOP)
        hp.wait_ticks(time.monotonic(), round(2.5 * rate))
        os.killpg(daemon.pid, signal.SIGCONT)
        # the host's way back (the display's report that it idles, the upload again, its start)
        # costs what the first upload cost and the lost report periods: a deadline from that
        budget_s = 10.0 + 20.0 * upload_s
        try:
            wait_for(lambda: request(sock, {"cmd": "status"})["device_reuploads"] == 1, budget_s,
                     f"a re-upload ({budget_s:.1f} s: the first upload took {upload_s:.2f} s)")
        except pytest.fail.Exception as e:
            st = request(sock, {"cmd": "status"}, timeout_s=5)
            journal = (tmp_path / "hostd.log").read_text()[-3000:]
            raise AssertionError(f"{e}; status {st}; journal: {journal}") from None
        hp.wait_ticks(time.monotonic(), round(1.0 * rate))
        b = request(sock, {"cmd": "status"})
        t_b = time.monotonic()
    finally:
        hp.close()
        if daemon.poll() is None:
            os.killpg(daemon.pid, signal.SIGCONT)
            daemon.send_signal(signal.SIGTERM)
            daemon.wait(20)
    journal = (tmp_path / "hostd.log").read_text()
    assert a["render_at"] == "device" and "CAPS" in a["render_reason"], (a, journal[-1500:])
    # (the daemon's quality scoring may load the codec's DCT: scipy.fft's pocketfft alone)
    assert footprint["pump_libs"] == [] and set(footprint["daemon_libs"]) <= {"scipy.fft"}, footprint
    # the daemon: main, pump writer, control accept, quality, spool, a control handler per client
    # being served (this test's requests: one at a time, plus one that may still be ending)
    assert footprint["pump_threads"] == 1 and footprint["daemon_threads"] <= 7, footprint
    # a supervisor is not real-time (issue 28): the pump takes SCHED_FIFO only while it streams
    # (hostd.device.realtime; tests/test_realtime.py), and it never streamed here
    assert footprint["pump_policy"] & ~os.SCHED_RESET_ON_FORK == os.SCHED_OTHER, footprint
    assert footprint["pump_priority"].sched_priority == 0 and "SCHED_FIFO" not in journal
    assert a["played_fraction"] > 0.99
    # asleep between reports: a wake-up per report (300 ms) plus commands, not one per ms
    assert (b["wakeups"] - a["wakeups"]) / (t_b - t_a - 2.5) < 60, (a["wakeups"], b["wakeups"])
    assert b["device_host_lost"] == 1 and b["device_reuploads"] == 1 and b["device_state"] == "rendering"
    assert b["device_faded_s"] > 0.09 and b["device_idle_s"] > 0.5  # the fade-out and the idle time
    # the DAC log: from the display's first report at full gain (the host counts from there) to
    # the report the status was taken from
    rec = hostport.read_log(log)
    full = (rec["flags"] & hostport.FULL_GAIN) != 0
    tick = rec["tick"].astype(np.int64)
    period_ticks = pr.R["status_period_ticks"]
    k0 = int(tick[np.flatnonzero(full & (tick % period_ticks == 0))[0]])
    k1 = round(b["device_time_s"] * pr.SAMPLE_RATE_HZ) + 1  # STATUS of tick k carries (k - 1) / 3 kHz
    sel = (tick > k0) & (tick <= k1)
    truth = full[sel].mean()
    assert 0.5 < truth < 0.9  # the idle second and a half is not "played"
    # the snapshot's device time comes from the latest STATUS, its played fraction from the latest
    # RENDER_STATUS: under load they can be one report period apart, so the window is known to
    # within one period (900 ticks of the ~12,000 here: 0.075)
    tol = period_ticks / max(1, k1 - k0) + 1e-3
    assert abs(b["played_fraction"] - truth) < tol, (b["played_fraction"], truth, tol)


def test_device_mode_health_counts_full_gain_ticks_across_wraps_and_resets():
    """played_fraction in device mode: ticks rendered at full gain over ticks due, from the
    display's RENDER_STATUS counters, counted from the first report at full gain; u32 counters
    wrap; a display whose counters go back (a reset) starts a new baseline, never a negative
    count; host-lost episodes are totalled."""
    from hostd.device.health import DeviceHealth

    on, fade_in = pr.RENDER_STATES["ON"], pr.RENDER_STATES["FADE_IN"]
    base = 0xFFFFFF00  # near the u32 wrap

    def rs(ticks, rendered, faded, idle=0, state=on, lost=0):
        return {"render_state": state, "device_time_us": (base + ticks * 1000 // 3) & 0xFFFFFFFF,
                "rendered_ticks": (base + rendered) & 0xFFFFFFFF, "faded_ticks": faded,
                "idle_ticks": idle, "host_lost_count": (0xFFFF + lost) & 0xFFFF}

    h = DeviceHealth()
    h.select(True, device=True)
    h.update_render(rs(150, 0, 150, state=fade_in))  # the selection's own fade-in: not due
    h.update_render(rs(300, 150, 150))  # first report at full gain: counting starts here
    assert h.played_fraction == 1.0
    h.update_render(rs(3300, 3150, 150))  # 3000 ticks, all at full gain, across the wrap
    assert h.played_fraction == 1.0
    # the host was lost, the hand rested: the display faded out (150) and idled (1500)
    h.update_render(rs(6300, 4500, 300, idle=1500, lost=1))
    assert abs(h.played_fraction - 4350 / 6000) < 1e-9
    assert h.host_lost == 1 and h.idle_ticks == 1500 and h.faded_ticks == 150  # since the first report
    h.update_render(rs(100, 0, 0))  # a reset: counters went back
    assert h.resets == 1 and abs(h.played_fraction - 4350 / 6000) < 1e-9
    h.select(True, device=False)  # a host-rendered selection: RENDER_STATUS does not count
    h.update_render(rs(400, 300, 0))
    assert h._sel_due == 0.0


def _pump_on_sim(protocol_version: int, n_coeffs: int = 40, seconds: float = 0.5) -> dict:
    """The daemon's pump process (pump_main, forked) on a simulated display of the given
    protocol version, default config, one texture selected: its published counters."""
    import multiprocessing as mp

    from hostd.device import simdev, transport
    from hostd.service.config import Config
    from hostd.service.pumpproc import STAT_FIELDS, pump_main

    ctx = mp.get_context("fork")
    stats = ctx.Array("d", len(STAT_FIELDS), lock=False)
    parent, child = ctx.Pipe()
    cfg = Config()
    cfg.device.transport = "sim"
    orig = transport.open_transport

    def fake_open(spec="auto", **kw):  # runs in the forked pump
        if spec == "sim":
            return simdev.SimTransport(device=simdev.SimDevice(protocol_version=protocol_version))
        return orig(spec, **kw)

    transport.open_transport = fake_open
    try:
        proc = ctx.Process(target=pump_main, args=(cfg, child, stats))
        proc.start()
    finally:
        transport.open_transport = orig
    try:
        rng = np.random.default_rng(1)
        parent.send(("select", ("t", (rng.normal(0, 0.1, n_coeffs)).tolist(), 2 * n_coeffs + 2, 10.0)))
        i = STAT_FIELDS.index("texture_serial")
        t_end = time.monotonic() + 30  # the forked pump connects and plays (a loaded machine: slowly)
        while stats[i] < 1 and time.monotonic() < t_end:
            time.sleep(0.05)
        time.sleep(seconds)
        st = dict(zip(STAT_FIELDS, stats[:], strict=True))
        lines = []
        while parent.poll():
            lines.append(parent.recv()[1])
        parent.send(("quit",))
        proc.join(10)
    finally:
        if proc.is_alive():
            proc.terminate()
            proc.join(5)
    st["lines"] = lines
    return st


def test_auto_renders_on_the_host_for_a_v1_display_or_a_texture_too_large_and_says_why():
    """[render] where = "auto" (the default): a v1 display, or a texture with more components
    than the display's CAPS hold, is rendered on the host, with the reason published (status
    `render_reason`) and logged once; a v2 display that can hold it renders it itself."""
    from hostd.service.pumpproc import RENDER_REASONS

    v2 = _pump_on_sim(2)
    assert v2["render_at"] == 1 and v2["render_reason"] == 0, v2["lines"]
    v1 = _pump_on_sim(1)
    assert v1["render_at"] == 0 and "protocol v1" in RENDER_REASONS[int(v1["render_reason"])]
    assert v1["samples"] > 0  # streamed by the host
    assert sum("rendering on the host" in m for m in v1["lines"]) == 1, v1["lines"]
    big = _pump_on_sim(2, n_coeffs=pr.R["max_components"] + 1)
    assert big["render_at"] == 0 and "more components" in RENDER_REASONS[int(big["render_reason"])]
    assert any(f"at most {pr.R['max_components']} components" in m for m in big["lines"]), big["lines"]


def test_the_pump_gives_its_host_renderer_loading_a_bounded_deadline_for_the_watchdog(monkeypatch):
    """The VM rig under load: a display refused device mode (SET_EQ BUSY), the pump fell back to
    host rendering and imported the renderer and scipy.signal for more than WatchdogSec=5 with
    no cycle to show; systemd killed the daemon. While it loads, the pump publishes a deadline
    (busy_until_s, at most LOADING_ALLOWANCE_S ahead) that the daemon takes as progress; after,
    0 again, also when the import fails."""
    import sys

    from hostd.render import equalizer
    from hostd.service import pumpproc

    stats = [0.0] * len(pumpproc.STAT_FIELDS)
    i = pumpproc.STAT_INDEX["busy_until_s"]
    seen = []
    monkeypatch.delitem(sys.modules, "hostd.render.pipeline", raising=False)  # "not loaded yet"
    monkeypatch.setattr(equalizer, "preload", lambda: seen.append(stats[i] - time.monotonic()))
    pumpproc.preload_host_rendering(stats)
    assert len(seen) == 1 and 0 < seen[0] <= pumpproc.LOADING_ALLOWANCE_S and stats[i] == 0.0

    def broken():
        raise ImportError("no scipy")
    monkeypatch.setattr(equalizer, "preload", broken)
    with pytest.raises(ImportError):
        pumpproc.preload_host_rendering(stats)
    assert stats[i] == 0.0


@pytest.mark.parametrize("period_ticks", [450, pr.R["status_period_ticks"]],
                         ids=["firmware-0.4", "this-firmware"])
def test_the_keep_alive_rides_the_report_wake_ups_and_a_stopped_display_is_seen_at_once(monkeypatch,
                                                                                        period_ticks):
    """docs/protocol.md, "Reports while rendering": with the default host_lost_ms (1000 ms) the host
    wakes once per report pair (a 0.4 display's 150 ms, this firmware's 300 ms) and never on a
    timer of its own; the display hears a keep-alive at least every host_lost_ms / 3, far within
    host_lost_ms (it never counts its host lost); a display that stops rendering is uploaded to
    again at its first 1 ms STATUS. On the simulated display's clock (manual: the host's clock
    follows it), so the figures are exact whatever the machine's load."""
    from types import SimpleNamespace

    from hostd.device import devmode, fwmodel, simdev
    from hostd.device.link import DeviceLink
    from hostd.render.pipeline import RenderConfig

    class Display(simdev.SimDevice):
        def status_period(self) -> int:
            return period_ticks if self.state == pr.STATES["RENDERING"] else pr.P["status_period_ticks"]

    monkeypatch.setattr(fwmodel, "R", {**pr.R, "status_period_ticks": period_ticks})  # its RENDER_STATUS
    t = simdev.SimTransport(device=Display(), realtime=False)
    rate = pr.SAMPLE_RATE_HZ
    monkeypatch.setattr(devmode, "time", SimpleNamespace(monotonic=lambda: t.device.ticks / rate))
    heard = []  # device ticks at which the display took a message from the host
    on_message = t.device.on_message
    monkeypatch.setattr(t.device, "on_message", lambda m: (heard.append(t.device.ticks), on_message(m)))
    link = DeviceLink(t)
    link.ident = pr.decode(t.device.ident())[1]
    link.caps = pr.decode(t.device.caps())[1]
    rng = np.random.default_rng(1)
    dev = devmode.DeviceMode(link, RenderConfig(), log=lambda m: None)
    dev._taken_over = True  # (a display known idle: take_over has its own test)
    dev.begin(("t", rng.normal(0, 0.1, 40).tolist(), 82, 10.0))
    assert t.device.state == pr.STATES["RENDERING"]
    k0 = t.device.ticks
    heard.clear()
    wakes = []
    def each_wake(ready) -> None:  # as the pump's: the keep-alive and the re-upload check
        wakes.append(t.device.ticks)
        dev.tick()

    dev.run(stop=lambda: t.device.ticks >= k0 + 6 * rate, each_wake=each_wake)
    reports = 6 * rate // period_ticks
    assert reports - 1 <= len(wakes) <= reports + 1, (len(wakes), reports)
    assert all(w % period_ticks == 0 for w in wakes)  # each wake-up a report's, none a timer's
    gaps_ms = np.diff([k0, *heard]) * 1000 / rate
    assert len(heard) >= 6 / 0.34 and gaps_ms.max() <= 1000 / 3 + 1, gaps_ms  # every host_lost_ms / 3
    assert t.device.render.host_lost_count == 0 and dev.recoveries == 0
    # the display stops rendering on its own (a reset): its 1 ms STATUS brings the upload at once
    t.device.render.halt()
    t.device.state = pr.STATES["IDLE"]
    k1 = t.device.ticks
    dev.run(stop=lambda: dev.recoveries > 0 or t.device.ticks >= k1 + rate,
            each_wake=lambda ready: dev.tick())
    assert dev.recoveries == 1 and t.device.state == pr.STATES["RENDERING"]
    assert t.device.ticks - k1 <= 2 * pr.P["status_period_ticks"], t.device.ticks - k1
