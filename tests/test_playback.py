"""Playback that survives host stalls, checked against the firmware's own DAC log.

The real daemon (`hostd run`, its pump process included) on the firmware's host port: it is
paused with SIGSTOP for 100 ms, 300 ms and 2 s, as a loaded desktop pauses it. What the design
guarantees, from the DAC log (ground truth, never the host's bookkeeping): playback from the
buffer resumes within 100 ms of SIGCONT; during the pause the output ramped to zero; it comes
back with a soft start and never past the slew limit; and the daemon's health figures equal
what the device did.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from hostd.cli import main
from hostd.device import hostport
from hostd.device import protocol as pr
from hostd.render.output import OutputConfig
from hostd.service.client import request, send_file
from hostd.service.config import DeviceCfg
from tests.daemon_helpers import wait_for
from tests.test_recovery import soft_start_limit

RATE = pr.SAMPLE_RATE_HZ
# The soft start's bound (tests/test_recovery.soft_start_limit) times this, over the samples the
# pump rendered at the restart (its prime: at least the configured fill target): the texture's
# value may exceed the peak sampled at full envelope, and the motion fit restarted after the
# pause from its first readings (a speed briefly off). Measured on a loaded machine: at most 1.32
# of the bound over 198 pauses (the equalizer's state from before the pause, before it restarted
# on the texture where the hand is: up to 7.4, and above 1.5 in 81 of 84 runs of this test)
SOFT_START_MARGIN = 1.5


@pytest.fixture(scope="module")
def port_factory():
    try:
        hostport.build()
    except RuntimeError as e:
        pytest.fail(str(e))
    return hostport.HostPort


def test_daemon_rides_through_sigstop_of_100ms_300ms_and_2s(port_factory, tmp_path):
    log = tmp_path / "dac.bin"
    hp = port_factory(["--motion", "constant:20", "--duration", "120"], log=log,
                      clock=tmp_path / "clock.bin")
    cfg = tmp_path / "hostd.toml"
    cfg.write_text(f'[device]\ntransport = "serial:{hp.pty}"\n[render]\nwhere = "host"\n'
                   '[library]\ndir = "lib"\nspool = "spool"\n'
                   '[control]\nsocket = "hostd.sock"\ngroup = ""\n[quality]\ndb = "q.sqlite"\n')
    sock = str(tmp_path / "hostd.sock")
    daemon = subprocess.Popen([sys.executable, "-m", "hostd", "run", "--config", str(cfg)], cwd=tmp_path,
                              stderr=open(tmp_path / "hostd.log", "w"), start_new_session=True)
    stalls = (0.1, 0.3, 2.0)
    events = []
    try:
        t_spawn = time.monotonic()
        wait_for(lambda: request(sock, {"cmd": "status"}, timeout_s=2)["connected"], 30, "the device")
        # what follows waits on the daemon's start-up work (its pump's first render): a budget in
        # units of the start it just made, as loaded as the machine is now
        start_s = time.monotonic() - t_spawn
        vtx = tmp_path / "wood.vtx"
        assert main(["encode", "synthetic:wood:1", "-o", str(vtx), "--method", "quant",
                     "--levels", "14"]) == 0
        send_file(sock, str(vtx), "wood")
        request(sock, {"cmd": "select", "name": "wood"})
        wait_for(lambda: request(sock, {"cmd": "status"})["device_samples_played"] > 3000,
                 max(20.0, 10 * start_s), f"playback (the daemon started in {start_s:.1f} s)")
        for stall_s in stalls:
            time.sleep(1.0)
            os.killpg(daemon.pid, signal.SIGSTOP)  # the daemon and its pump process
            t_stop = time.monotonic()
            # the pause is stall_s of the device's clock (the port's ticks): a loaded machine
            # slows the port too, and the device's host timeout counts its ticks, not ours
            time.sleep(stall_s)
            t_cont = hp.wait_ticks(t_stop, round(stall_s * RATE))
            os.killpg(daemon.pid, signal.SIGCONT)
            events.append((t_stop, t_cont))
        time.sleep(1.5)
        st = request(sock, {"cmd": "status"})
    finally:
        hp.close()  # ends the DAC log first (the daemon's ramp at exit is not under test)
        if daemon.poll() is None:
            os.killpg(daemon.pid, signal.SIGCONT)
            daemon.send_signal(signal.SIGTERM)
            daemon.wait(20)
    journal = (tmp_path / "hostd.log").read_text()
    rec = hostport.read_log(log)
    codes = rec["code"].astype(np.int64)
    played = (rec["flags"] & hostport.PLAYED) != 0
    tick0 = int(rec["tick"][0])
    max_step = int(min(60000.0 / RATE / (80.0 / 150.0 * 15.0 * 10.0 / 32767) + 1, 32767))
    assert np.abs(np.diff(codes)).max() <= max_step, "slew limit broken"
    # the device's guarantee: host silence past its timeout, then a ramp of at most ramp_ticks
    # (+ a STATUS period for the last bytes still in the pty), and the output is zero
    silent_ticks = pr.P["default_timeout_ms"] * RATE // 1000 + pr.P["ramp_ticks"] + 3
    # the texture's amplitude while it played from the buffer (the 99th percentile of |code|),
    # and its peak at full envelope (played, after a ramp's worth of ticks that all played)
    steady = float(np.percentile(np.abs(codes[played]), 99))
    assert steady > 500
    ramp = round(OutputConfig().ramp_s * RATE)
    unplayed = np.concatenate([[0], np.cumsum(~played)])
    k = np.arange(codes.size)
    full = played & (unplayed[k + 1] == unplayed[np.maximum(k + 1 - ramp, 0)])
    peak = float(np.abs(codes[full]).max())
    prime = DeviceCfg().target_fill
    for (t_stop, t_cont), stall_s in zip(events, stalls, strict=True):
        c = hp.tick_at(t_cont) - tick0
        s0 = hp.tick_at(t_stop) - tick0
        # during the pause the device ran dry or timed out and ramped to zero (a 100 ms pause may
        # end within its ramp: the design says zero from s0 + silent_ticks on, not before)
        assert c - s0 >= round(stall_s * RATE), "the pause is measured in the device's ticks"
        assert not codes[s0 + silent_ticks : c + 1].any(), f"{stall_s} s: output not at zero before SIGCONT"
        # (what the buffer held at most: the highest fill target and a cycle's worth in flight)
        held = 90 + 2 * pr.MAX_SAMPLES
        assert not played[s0 + held + 30 : c].any(), f"{stall_s} s: played from the buffer during the pause?"
        # playback from the buffer resumes within 100 ms of SIGCONT
        resumed = c + int(np.argmax(played[c:]))
        assert played[c:].any() and resumed - c <= RATE // 10, \
            f"{stall_s} s pause: resumed {(resumed - c) / RATE * 1e3:.0f} ms after SIGCONT\n{journal[-1500:]}"
        # soft start from zero: the pump lets a device still ramping down after its host timeout
        # reach zero first; then each sample of the prime is within the envelope times the
        # texture's peak (the later ones follow the motion fit as its window fills)
        assert codes[resumed - 3 : resumed].tolist() == [0, 0, 0], f"{stall_s} s: from {codes[resumed - 1]}"
        first = np.abs(codes[resumed : resumed + prime])
        lim = soft_start_limit(played[resumed : resumed + prime], peak * SOFT_START_MARGIN)
        assert np.all(first <= lim), f"{stall_s} s: {(first / lim).max():.2f} x the soft start's bound"
        # and it comes back to the texture's amplitude before the next pause (at least 1 s on;
        # a loaded machine's own underruns start soft again, so not within a fixed window)
        nxt = next((hp.tick_at(a) - tick0 for a, _ in events if hp.tick_at(a) - tick0 > c), codes.size)
        assert np.abs(codes[resumed:nxt]).max() >= 0.5 * steady, f"{stall_s} s: did not come back"
    # health figures = what the device did (its counters, cut at the status's device time)
    g = int(np.ceil(st["device_time_s"] * RATE - 1e-6))
    fig = hostport.playback_figures(rec[rec["tick"] <= g + 1])
    assert st["device_underruns"] == fig["underrun_episodes"] >= 1
    assert st["device_samples_played"] == int(played[: g + 1 - tick0 + 1].sum())
    # every pause was recovered from; a burst of silences inside one episode counts once
    assert len(stalls) <= st["recoveries"] <= len(fig["silences"]), (st, fig["silences"])
    assert st["stalls"] >= len(stalls)
    assert abs(st["played_fraction"] - fig["played_fraction"]) < 0.01
    assert st["device_state"] == "running" and st["state"] == "playing"
    # the daemon's pump streams through the compiled cycle it was handed (where it is built)
    from hostd.device import fastpump

    assert (st["compiled_cycles"] > 0) == (fastpump.IMPLEMENTATION == "c"), st["compiled_cycles"]
    assert isinstance(st["device_faults"], list)
    # each episode logged once: never more lines than episodes. The journal holds back a line
    # identical to a recent one (hostd.service.logsetup's back-off) and counts it in a later
    # "(repeated N more times" line, so a machine whose load adds underrun episodes of equal text
    # logs fewer; the pauses' host timeouts, seconds apart, are each there
    lines = [ln for ln in journal.splitlines() if "playback recovered after" in ln]
    held = sum(int(n) for n in re.findall(r"\(repeated (\d+) more times", "\n".join(lines)))
    assert len(lines) + held <= st["recoveries"], (len(lines), held, st["recoveries"])
    assert sum("after host timeout" in ln for ln in lines) >= len(stalls), lines


def test_a_real_jump_of_the_hand_is_relocked_within_5_reports(port_factory, tmp_path):
    from hostd.device.link import DeviceLink
    from hostd.device.pump import Pump
    from hostd.device.seriallink import SerialTransport
    from tests.test_device import _renderer

    log = tmp_path / "dac.bin"
    r = _renderer()
    with port_factory(["--motion", "constant:20", "--jump-at", "2.5:0.5", "--duration", "30"], log=log) as hp:
        link = DeviceLink(SerialTransport(hp.pty), target_fill=30)
        link.handshake(timeout_s=2.0)
        pump = Pump(link, None)
        trace = []
        on_status = pump._on_status

        def spy(f, t_s, fresh=True):
            on_status(f, t_s, fresh)
            if fresh:  # a reading the estimator was fed
                m = r.motion
                trace.append((t_s, f["encoder_count"] * 0.4e-3, m.predict_one(t_s), m.velocity_mm_s))

        link.on_status = spy
        link.poll(0.01)
        pump.begin(r)
        pump.run(4.0)
        link.stop()
    tr = np.array(trace)
    tr = tr[(tr[:, 0] > 2.0) & (tr[:, 0] < 3.5)]  # around the jump (2.5 s)
    t_s, true_x, est_x, v = tr[:, 0], tr[:, 1], tr[:, 2], tr[:, 3]
    # the jump: 0.5 mm between readings 1 ms apart (a host stall also makes the readings jump,
    # by the way the hand went meanwhile: 20 mm/s x the gap)
    step = np.diff(true_x) - 20.0 * np.diff(t_s)
    jumps = np.flatnonzero(np.abs(step - 0.5) < 0.05) + 1
    assert jumps.size == 1, "one jump of 0.5 mm"
    j = int(jumps[0])
    # locked = within 5 µm and 3 mm/s (the jump is 500 µm)
    ok = (np.abs(est_x - true_x) < 0.005) & (np.abs(v - 20.0) < 3.0)
    after = ok[j:]
    k = int(np.argmax(after))
    assert after.any() and k <= 5, f"re-locked after {k} reports"
    assert after[k : k + 500].mean() > 0.95  # and stays locked
    assert r.motion.relocks >= 1 and np.abs(v).max() < 100.0  # no runaway speed
    codes = hostport.read_log(log)["code"].astype(np.int64)
    assert np.abs(np.diff(codes)).max() <= pr.MAX_STEP_CODE
