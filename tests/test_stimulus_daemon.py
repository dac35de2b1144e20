"""Issue 31: `hostd experiment threshold --display daemon` plays its sinusoids on the display
through the running daemon, on the firmware's host port (the real firmware core, its DAC log).

One daemon in device mode (the default: the port renders textures itself) for the module, its
display behind a symlink so that a test can unplug it and plug in another. What is checked
comes from the device's own DAC log: every stimulus the session answered was played whole and
equals the sinusoid asked for (the output stage's codes, exactly), nothing ever passed the
limits, silent intervals run through the device too; over-reach and hostile requests are
refused with one line (also from another user, `nobody`); a display lost mid-stimulus makes
the trial repeat and nothing is recorded twice.
"""

from __future__ import annotations

import json
import os
import resource
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("questplus")

from hostd.device import hostport
from hostd.device import protocol as pr
from hostd.errors import DeviceGone, ExperimentError, HostdError
from hostd.experiment.display import DaemonDisplay, Reach, Sinusoid
from hostd.render.output import OutputStage
from hostd.render.stimulus import LEAD_SAMPLES, StimulusBound
from hostd.service.client import ClientError, request, send_file
from hostd.service.config import load
from tests.daemon_helpers import wait_for

NOBODY = 65534
SYSTEM_PYTHON = "/usr/bin/python3"


class Rig:
    def __init__(self, d: Path) -> None:
        self.d = d
        self.rundir = Path(tempfile.mkdtemp(prefix="hostd-stim-"))  # nobody may reach the socket
        os.chmod(self.rundir, 0o711)
        self.sock = str(self.rundir / "hostd.sock")
        self.tty = d / "display"  # the daemon's display: a symlink to the port's pty
        self.log = d / "dac.bin"
        self.hp = self.plug(self.log)
        self.cfg_path = d / "hostd.toml"
        self.cfg_path.write_text(
            f'[device]\ntransport = "serial:{self.tty}"\nreconnect_s = 0.2\n'
            '[library]\ndir = "lib"\nspool = "spool"\n'
            f'[control]\nsocket = "{self.sock}"\ngroup = ""\n[quality]\ndb = "q.sqlite"\n'
            '[experiment]\nstimuli = true\n')
        self.cfg = load(self.cfg_path)
        self.daemon = subprocess.Popen([sys.executable, "-m", "hostd", "run", "--config", str(self.cfg_path)],
                                       cwd=d, stderr=open(d / "hostd.log", "w"))

    def plug(self, log: Path) -> hostport.HostPort:
        hp = hostport.HostPort(["--motion", "none", "--duration", "300"], log=log)
        tmp = self.d / "display.new"
        tmp.unlink(missing_ok=True)
        tmp.symlink_to(hp.pty)
        tmp.replace(self.tty)
        return hp

    def status(self) -> dict:
        return request(self.sock, {"cmd": "status"}, timeout_s=5)

    def journal(self) -> str:
        return (self.d / "hostd.log").read_text()[-3000:]


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    try:
        hostport.build()
    except RuntimeError as e:
        pytest.fail(str(e))
    r = Rig(tmp_path_factory.mktemp("stim"))
    try:
        def up() -> bool:
            if r.daemon.poll() is not None:
                pytest.fail(r.journal())
            return r.status()["connected"]

        wait_for(up, 90, "the display")
        os.chmod(r.sock, 0o666)  # a member of the socket's group: here, anyone (nobody included)
        yield r
    finally:
        if r.daemon.poll() is None:
            r.daemon.send_signal(signal.SIGTERM)
            r.daemon.wait(20)
        r.hp.close()
        shutil.rmtree(r.rundir, ignore_errors=True)


def dac_log(path: Path) -> np.ndarray:
    """The port's DAC log so far (it is being written: whole records only)."""
    raw = Path(path).read_bytes()
    return np.frombuffer(raw[: len(raw) // hostport.LOG_DTYPE.itemsize * hostport.LOG_DTYPE.itemsize],
                         dtype=hostport.LOG_DTYPE)


def settled_log(path: Path, since: int = 0) -> np.ndarray:
    """The DAC log from record `since`, once it shows the display idle for 30 ticks after its last
    RUNNING tick (the port writes its log as it runs: a stimulus just answered is all in it)."""
    t_end = time.monotonic() + 10
    while True:
        rec = dac_log(path)[since:]
        run = (rec["flags"] & hostport.RUNNING) != 0
        if rec.size > 30 and not run[-30:].any():
            return rec
        if time.monotonic() > t_end:
            pytest.fail("the port's DAC log does not show the display idle")
        time.sleep(0.02)


def expected_codes(cfg, f_hz: float, amplitude_um: float, duration_s: float) -> np.ndarray:
    """The codes the output stage sends for this stimulus (no sample limited: checked)."""
    rc = cfg.render_config()
    cmd = StimulusBound(rc).command_um(f_hz, amplitude_um, duration_s)
    return OutputStage(rc.output).to_codes(cmd).astype(np.int64)


def running_runs(rec: np.ndarray) -> list[tuple[int, int]]:
    """[start, end) of each run of ticks the device spent RUNNING (one START..STOP each)."""
    return hostport.runs((rec["flags"] & hostport.RUNNING) != 0)


def played_prefix(rec: np.ndarray, a: int, b: int) -> int:
    """Ticks from a that played a sample from the buffer without a break (an underrun ends it)."""
    p = (rec["flags"][a:b] & hostport.PLAYED) != 0
    return int(np.argmin(p)) if not p.all() else b - a


def limits(cfg) -> tuple[int, int]:
    """The limits the daemon sets on the display (pumpproc: SET_LIMITS)."""
    out = cfg.render_config().output
    return out.limit_code, int(min(out.slew_um_s / pr.SAMPLE_RATE_HZ / out.um_per_code + 1, 32767))


def assert_within_limits(cfg, rec: np.ndarray) -> None:
    lim, step = limits(cfg)
    codes = rec["code"].astype(np.int64)
    assert np.abs(codes).max() <= lim
    assert np.abs(np.diff(codes)).max() <= step


def test_a_threshold_session_through_the_daemon_plays_every_stimulus_whole(rig, tmp_path):
    """`hostd experiment threshold --display daemon` end to end (a simulated observer answers):
    every answered trial's sinusoid is in the device's DAC log, played whole and equal to the
    output stage's codes for it; the silent intervals ran through the device as well."""
    out = tmp_path / "o"
    t0_tick = dac_log(rig.log).size
    r = subprocess.run([sys.executable, "-m", "hostd", "experiment", "threshold", "--display", "daemon",
                        "--socket", rig.sock, "--config", str(rig.cfg_path), "-o", str(out),
                        "--participant", "s1", "--frequencies", "40,250", "--trials", "2", "--afc", "2",
                        "--simulate", "weibull"], capture_output=True, text=True, timeout=180)
    assert r.returncode == 0, (r.stderr[-2000:], rig.journal())
    from hostd.experiment.session import Store

    answers = Store(out / "session.sqlite").answers("s1")
    assert [a["trial"] for a in answers] == [0, 1, 2, 3]  # each trial once (a repeat records nothing)
    assert (out / "thresholds.csv").exists() and len((out / "trials.csv").read_text().splitlines()) >= 5
    rec = settled_log(rig.log, t0_tick)
    assert_within_limits(rig.cfg, rec)
    codes = rec["code"].astype(np.int64)
    targets = {(a["stimulus"]["frequency_hz"], a["stimulus"]["amplitude_um"]) for a in answers}
    expect = {k: expected_codes(rig.cfg, *k, 0.5) for k in targets}
    whole: set = set()
    silent = 0
    # presentations the daemon answered "not played whole" (an underrun, a buffer overflow: the
    # display's own flags), each repeated by the session: the one run its DAC log may not match
    lost = [e for e in Store(out / "session.sqlite").events("s1") if e["kind"] == "display_lost"]
    unmatched = []
    for a, b in running_runs(rec):
        got = codes[a + LEAD_SAMPLES : b]
        n_played = max(played_prefix(rec, a, b) - LEAD_SAMPLES, 0)
        if not got.any():
            silent += 1
            continue
        # a run that plays something is one of the session's stimuli, sample for sample, as far
        # as the device played it from its buffer (a run cut by an underrun was repeated)
        match = [k for k, e in expect.items() if np.array_equal(got[: min(n_played, e.size)],
                                                                e[: min(n_played, e.size)])]
        if not match:
            unmatched.append(f"tick {int(rec['tick'][a])}: run of {b - a} ticks, {n_played} played "
                             f"before a break, codes {got[:12].tolist()}")
            continue
        if n_played >= expect[match[0]].size:
            assert not got[expect[match[0]].size:].any()  # then silence until the STOP
            whole.update(match)
    assert len(unmatched) <= len(lost), (
        f"{len(unmatched)} stimuli in the DAC log match none of the session's, {len(lost)} were answered "
        f"as not played whole", unmatched, lost, rig.journal())
    assert whole == targets, (sorted(targets - whole), rig.journal())
    assert silent >= len(answers)  # each trial's other interval: an amplitude-0 stimulus, played
    st = rig.status()
    assert st["state"] == "idle" and st["texture"] is None


@pytest.mark.parametrize("pause_ms", [30, 150])
def test_a_display_that_falls_behind_mid_stimulus_is_answered_not_played_whole(rig, pause_ms):
    """The display's process held up mid-stimulus (SIGSTOP: a loaded machine does it to the
    port): the host, still sending for the device's clock, fills its buffer past what it holds
    and the device drops samples (its OVERFLOW flag; no underrun, and the count of samples
    played comes out right). The answer is either "played whole", and then the DAC log shows
    the sinusoid exactly, or "not played whole, ask again". (Before the flag was read: answered
    whole, the DAC log 3 samples short from the pause on.)"""
    n0 = dac_log(rig.log).size
    f_hz, a_um = 250.0, 2.0

    def hold_up() -> None:
        time.sleep(0.15)  # into the stimulus (on a loaded machine perhaps not: then it is whole)
        os.kill(rig.hp.proc.pid, signal.SIGSTOP)
        try:
            time.sleep(pause_ms / 1e3)
        finally:
            os.kill(rig.hp.proc.pid, signal.SIGCONT)

    th = threading.Thread(target=hold_up)
    th.start()
    try:
        request(rig.sock, {"cmd": "stimulus", "frequency_hz": f_hz, "amplitude_um": a_um,
                           "duration_s": 0.5}, timeout_s=20)
        whole = True
    except ClientError as e:
        assert e.reply.get("retry"), e
        whole = False
    finally:
        th.join()
    rec = settled_log(rig.log, n0)
    assert_within_limits(rig.cfg, rec)
    if whole:
        e = expected_codes(rig.cfg, f_hz, a_um, 0.5)
        a, _b = running_runs(rec)[-1]
        dac = rec["code"][a + LEAD_SAMPLES : a + LEAD_SAMPLES + e.size].astype(np.int64)
        assert np.array_equal(dac, e), f"answered whole, but the DAC log differs from sample " \
                                       f"{int(np.argmax(dac != e[: dac.size]))}"


def test_the_device_logs_the_sinusoid_within_a_code_and_the_daemons_reach_is_the_hosts(rig):
    reach = Reach(rig.cfg.render_config())
    fs = [40.0, 250.0, 500.0]
    assert DaemonDisplay(rig.sock).reach.reach_um(250.0) == reach.reach_um(250.0)
    got = request(rig.sock, {"cmd": "reach", "frequencies_hz": fs})["reach_um"]
    assert got == [reach.reach_um(f) for f in fs]
    # at the reach itself, where the displacement limit binds (40 Hz) and the slew limit (500 Hz)
    for f in (40.0, 500.0):
        n0 = dac_log(rig.log).size
        for _ in range(5):  # a stimulus cut by a host stall (a loaded machine) is asked again
            try:
                rep = request(rig.sock, {"cmd": "stimulus", "frequency_hz": f,
                                         "amplitude_um": got[fs.index(f)], "duration_s": 0.3}, timeout_s=20)
                break
            except ClientError as e:
                assert e.reply.get("retry"), e
        else:
            pytest.fail("five stimuli in a row cut short")
        e = expected_codes(rig.cfg, f, got[fs.index(f)], 0.3)
        assert rep["played"]["samples"] >= e.size and rep["played"]["limited"] == 0  # the device's count
        rec = settled_log(rig.log, n0)
        a, _b = running_runs(rec)[-1]
        dac = rec["code"][a + LEAD_SAMPLES : a + LEAD_SAMPLES + e.size].astype(np.int64)
        assert np.array_equal(dac, e)
        # in µm at the actuator's input: the sinusoid within half a code (the DAC's rounding)
        rc = rig.cfg.render_config()
        cmd = StimulusBound(rc).command_um(f, got[fs.index(f)], 0.3)
        assert np.abs(dac * rc.output.um_per_code - cmd).max() <= rc.output.um_per_code / 2 + 1e-12
        assert_within_limits(rig.cfg, rec)


def test_a_stimulus_stops_device_rendering_and_the_display_idles_after(rig, tmp_path):
    from hostd.bench import soak
    from hostd.cli import main

    assert main(["encode", "synthetic:wood:1", "-o", str(tmp_path / "w.vtx"), "--method", "quant",
                 "--levels", "8", "--length-mm", "5"]) == 0
    send_file(rig.sock, str(tmp_path / "w.vtx"), "wood")
    request(rig.sock, {"cmd": "select", "name": "wood"})
    wait_for(lambda: rig.status()["device_state"] == "rendering", 30, "device rendering")
    for _ in range(5):
        try:
            rep = request(rig.sock, {"cmd": "stimulus", "frequency_hz": 100.0, "amplitude_um": 2.0,
                                     "duration_s": 0.2}, timeout_s=20)
            break
        except ClientError as e:
            assert e.reply.get("retry"), e
            request(rig.sock, {"cmd": "select", "name": "wood"})
            wait_for(lambda: rig.status()["device_state"] == "rendering", 30, "device rendering")
    else:
        pytest.fail("five stimuli in a row cut short")
    assert rep["stopped"] == "wood"
    st = rig.status()
    assert st["texture"] is None and st["state"] == "idle", st
    # the display ramps down and idles (its state as it reports it, published a few times a second)
    wait_for(lambda: rig.status()["device_state"] == "idle", 10, "the display idle")
    rec = settled_log(rig.log)
    rendering = (rec["flags"] & hostport.RENDERING) != 0
    a, _b = running_runs(rec)[-1]
    assert rendering[:a].any() and not rendering[a:].any()  # rendered, streamed, then neither
    # device mode stays lean: the stimulus path loads no scipy (nor matplotlib) into the pump
    pump = soak._pump_pid(rig.daemon.pid)
    assert soak.mapped_libs(pump) == []
    # a select while a stimulus plays interrupts it (answered "retry") and the display renders
    res: dict = {}

    def long_stimulus() -> None:
        try:
            res["reply"] = request(rig.sock, {"cmd": "stimulus", "frequency_hz": 100.0, "amplitude_um": 1.0,
                                              "duration_s": 3.0}, timeout_s=20)
        except ClientError as e:
            res["error"] = e

    th = threading.Thread(target=long_stimulus)
    th.start()
    wait_for(lambda: rig.status()["state"] == "playing", 10, "the stimulus playing")
    streaming = os.sched_getscheduler(pump), os.sched_getparam(pump).sched_priority
    request(rig.sock, {"cmd": "select", "name": "wood"})
    th.join(20)
    assert "error" in res and res["error"].reply.get("retry"), res  # (interrupted, or cut by a stall)
    wait_for(lambda: rig.status()["device_state"] == "rendering", 30, "device rendering again")
    supervising = os.sched_getscheduler(pump), os.sched_getparam(pump).sched_priority
    request(rig.sock, {"cmd": "stop"})
    # the pump streams the stimulus real-time where permitted ([realtime] sched_fifo_priority, 10
    # by default) and supervises the display's own rendering as an ordinary process again
    if os.geteuid() == 0 or resource.getrlimit(resource.RLIMIT_RTPRIO)[0] >= 10:
        assert streaming == (os.SCHED_FIFO | os.SCHED_RESET_ON_FORK, 10), streaming
    assert supervising[0] & ~os.SCHED_RESET_ON_FORK == os.SCHED_OTHER and supervising[1] == 0, supervising


HOSTILE = r"""
import json, socket, sys
def ask(line):
    s = socket.socket(socket.AF_UNIX)
    s.settimeout(30)
    s.connect(sys.argv[1])
    s.sendall(line.encode() + b"\n")
    r = s.makefile().readline()
    s.close()
    return r
for line in sys.stdin.read().splitlines():
    print(ask(line).strip(), flush=True)
"""


def test_over_reach_and_hostile_stimuli_are_refused_and_nothing_passes_the_limits(rig):
    """Another user with access to the socket (nobody, when this runs as root) asks for what a
    hostile client would: beyond the reach, non-finite, negative, too long, too high, of the
    wrong type; each is refused with one line and nothing reaches the display. What it may play
    (at the reach) stays inside the limits, by the device's own log."""
    r250 = request(rig.sock, {"cmd": "reach", "frequencies_hz": [250.0]})["reach_um"][0]
    bad = [{"frequency_hz": 250, "amplitude_um": r250 * 1.001, "duration_s": 0.2},
           {"frequency_hz": 250, "amplitude_um": 1e9, "duration_s": 0.2},
           {"frequency_hz": 40, "amplitude_um": -1.0, "duration_s": 0.2},
           {"frequency_hz": 250, "amplitude_um": 1.0, "duration_s": 0.0},
           {"frequency_hz": 250, "amplitude_um": 1.0, "duration_s": 11.0},
           {"frequency_hz": 250, "amplitude_um": 1.0, "duration_s": 1e308},
           {"frequency_hz": 0, "amplitude_um": 1.0, "duration_s": 0.2},
           {"frequency_hz": 1e9, "amplitude_um": 1e-9, "duration_s": 0.2},
           {"frequency_hz": True, "amplitude_um": 1.0, "duration_s": 0.2},
           {"frequency_hz": "250", "amplitude_um": 1.0, "duration_s": 0.2},
           {"frequency_hz": [250], "amplitude_um": 1.0, "duration_s": 0.2},
           {"amplitude_um": 1.0, "duration_s": 0.2}]
    lines = [json.dumps({"cmd": "stimulus", **b}) for b in bad]
    lines += ['{"cmd": "stimulus", "frequency_hz": 250, "amplitude_um": NaN, "duration_s": 0.2}',
              '{"cmd": "stimulus", "frequency_hz": Infinity, "amplitude_um": 1, "duration_s": 0.2}',
              '{"cmd": "stimulus", "frequency_hz": 250, "amplitude_um": 1, "duration_s": -Infinity}',
              '{"cmd": "reach", "frequencies_hz": [NaN]}', '{"cmd": "reach", "frequencies_hz": 250}']
    n0 = dac_log(rig.log).size
    played0 = rig.status()["device_samples_played"]
    if os.geteuid() == 0 and os.path.exists(SYSTEM_PYTHON):
        p = subprocess.run([SYSTEM_PYTHON, "-I", "-c", HOSTILE, rig.sock], input="\n".join(lines),
                           user=NOBODY, group=NOBODY, capture_output=True, text=True, timeout=120)
        assert p.returncode == 0, p.stderr
        replies = [json.loads(x) for x in p.stdout.splitlines()]
    else:  # (not root: the same requests from this user)
        replies = [_ask(rig.sock, line) for line in lines]
    assert len(replies) == len(lines)
    for line, rep in zip(lines, replies, strict=True):
        assert rep["ok"] is False and not rep.get("retry") and "\n" not in rep["error"], (line, rep)
    assert "reaches" in replies[0]["error"] and "refused" in replies[1]["error"]
    rec = settled_log(rig.log, n0)
    assert rig.status()["device_samples_played"] == played0  # nothing was played
    assert not ((rec["flags"] & hostport.RUNNING) != 0).any()
    assert_within_limits(rig.cfg, dac_log(rig.log))  # the whole run of the port so far


def _ask(sock: str, line: str) -> dict:
    import socket

    with socket.socket(socket.AF_UNIX) as s:
        s.settimeout(30)
        s.connect(sock)
        s.sendall(line.encode() + b"\n")
        return json.loads(s.makefile().readline())


def test_stimuli_are_off_unless_the_config_says_so(tmp_path):
    from hostd.service.daemon import Daemon

    cfg_path = tmp_path / "hostd.toml"
    cfg_path.write_text('[device]\ntransport = "sim"\n[library]\ndir = "lib"\nspool = "spool"\n'
                        '[control]\nsocket = "s/hostd.sock"\ngroup = ""\n[quality]\ndb = "q.sqlite"\n')
    d = Daemon(load(cfg_path))
    for req in ({"cmd": "stimulus", "frequency_hz": 250, "amplitude_um": 0.1, "duration_s": 0.2},
                {"cmd": "reach", "frequencies_hz": [250]}):
        with pytest.raises(HostdError, match=r"\[experiment\] stimuli = true") as e:
            d.play_stimulus(req) if req["cmd"] == "stimulus" else d.reach(req)
        assert "\n" not in str(e.value)


def test_a_display_lost_mid_stimulus_repeats_the_trial_and_nothing_is_recorded_twice(rig, tmp_path):
    """The port dies while a trial's interval plays: the session records a display_lost event and
    no answer; once another display is plugged in the same trial is presented again."""
    from hostd.experiment.plan import check_plan
    from hostd.experiment.runner import ThresholdSession
    from hostd.experiment.session import Store
    from hostd.experiment.threshold import ThresholdConfig

    display = DaemonDisplay(rig.sock)
    cfg = ThresholdConfig([250.0], [0.1], [display.reach.reach_um(250.0)], n_afc=2, max_trials=2, seed=1,
                          duration_s=1.0, gap_s=0.1)
    st = Store(tmp_path / "s.sqlite")
    st.create("lost", "threshold", {"config": {}})
    sess = ThresholdSession(st, "lost", display, cfg, check_plan({"practice": {"trials": 0}}))
    sess.open("pg")
    sess.step("pg", "continue")
    first = sess.current()

    def unplug() -> None:  # once a stimulus streams (amplitude 0 or not)
        wait_for(lambda: rig.status()["state"] == "playing", 30, "a stimulus playing")
        time.sleep(0.2)
        rig.hp.close()

    killer = threading.Thread(target=unplug)
    killer.start()
    sess.present("pg")
    sess.player.join()
    killer.join()
    assert sess.retry and "not answering" in sess.retry, sess.retry
    assert st.answers("lost") == [] and [e["kind"] for e in st.events("lost")][-1] == "display_lost"
    with pytest.raises(DeviceGone):  # unplugged: no display (the trial would be repeated again)
        display.play(Sinusoid(250.0, 0.1, 0.2))
    rig.hp = rig.plug(rig.d / "dac2.bin")
    wait_for(lambda: rig.status()["connected"], 30, "the display plugged in again")
    while not sess.finished():
        sess.present("pg")
        sess.player.join()
        if sess.retry:  # (a stimulus cut by a host stall on a loaded machine)
            continue
        t = sess.current()
        if t["index"] == 0:
            assert t == first  # the same trial, presented again
        sess.answer("pg", t["index"], t["target"])
    rows = st.answers("lost")
    assert [a["trial"] for a in rows] == [0, 1] and rows[0]["stimulus"] == first
    with pytest.raises(ExperimentError, match="reaches"):  # beyond the reach: refused, not retried
        display.play(Sinusoid(250.0, display.reach.reach_um(250.0) * 1.01, 0.2))


def test_the_pump_streams_a_stimulus_after_a_texture_sample_for_sample():
    """Host rendering (a texture streamed, then a stimulus), on the simulated display with a
    manual clock: the display plays the stimulus' codes exactly, from a full buffer; after it
    the pump's fill target is the texture's again. A link too busy to take a batch loses none
    of the stimulus' samples (they go out in the next cycle)."""
    from hostd.bench.accuracy import texture_coeffs
    from hostd.device.link import DeviceLink
    from hostd.device.pump import Pump
    from hostd.device.simdev import SimTransport
    from hostd.errors import DeviceBusy
    from hostd.render import Renderer
    from hostd.render.stimulus import StimulusRenderer
    from hostd.texture import synth

    cfg = load(None)
    rc = cfg.render_config()
    t = SimTransport(realtime=False)
    t.device.played_log = []
    link = DeviceLink(t, target_fill=12)
    t.advance(3)
    link.handshake(timeout_s=0.1)
    c, n, length = texture_coeffs(synth.make("wood", seed=1))
    tex = Renderer(c, n, length, rc)
    tex.start()
    pump = Pump(link, tex)
    pump.step()
    link.start()
    for _ in range(300):
        t.advance(3)
        pump.step()
    stim = StimulusRenderer(rc, 250.0, 1.0, 0.3)
    stim.start()
    real_send, calls = link._send, [0]

    def sometimes_busy(data, must=False):  # every 7th SAMPLES write: the port would block
        calls[0] += 1
        if not must and calls[0] % 7 == 0:
            raise DeviceBusy("busy")
        return real_send(data, must)

    link._send = sometimes_busy
    l0 = len(t.device.played_log)
    pump.begin(stim)
    assert link.target_fill == pr.BUFFER_CAPACITY - pr.MAX_SAMPLES  # the whole buffer
    for _ in range(400):
        t.advance(3)
        pump.step()
    link._send = real_send
    e = expected_codes(cfg, 250.0, 1.0, 0.3)
    played = np.array(t.device.played_log[l0:], dtype=np.int64)
    starts = [k for k in range(0, 400) if np.array_equal(played[k : k + e.size], e)]
    assert starts and not played[starts[0] + e.size :].any(), "the stimulus is not in what the display played"
    assert t.device.underruns == 0 and stim.limited == 0 and calls[0] > 7
    pump.end()
    assert link.target_fill == 12
