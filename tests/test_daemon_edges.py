"""Issue 29: the daemon at its edges. A daemon killed by SIGKILL leaves a pump that says one line
and exits (no multiprocessing traceback); a start tells systemd READY=1 and takes SIGTERM before
it looks through the library for streams to rescore."""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from hostd.cli import main
from hostd.service.client import request
from tests.daemon_helpers import wait_for
from tests.test_daemon_abuse import START_S

DEVICE_CFG = ('[device]\ntransport = "sim"\n[render]\nwhere = "device"\n'
              '[library]\ndir = "lib"\nspool = "spool"\n[control]\nsocket = "hostd.sock"\ngroup = ""\n'
              '[quality]\ndb = "q.sqlite"\n')


def _children(pid: int) -> list[int]:
    try:
        return [int(c) for c in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
    except OSError:
        return []


def _comm(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/comm").read_text().strip()
    except OSError:
        return ""


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0] != "Z"
    except OSError:
        return False


def test_kill_9_of_the_daemon_in_device_rendering_leaves_one_line_from_the_pump(tmp_path):
    cfg = tmp_path / "hostd.toml"
    cfg.write_text(DEVICE_CFG)
    assert main(["encode", "synthetic:wood:1", "-o", str(tmp_path / "wood.vtx"), "--method", "quant",
                 "--levels", "8"]) == 0
    sock = str(tmp_path / "hostd.sock")
    log = tmp_path / "log.txt"
    daemon = subprocess.Popen([sys.executable, "-m", "hostd", "run", "--config", str(cfg)], cwd=tmp_path,
                              stderr=open(log, "w"))
    pump = None
    try:
        wait_for(lambda: request(sock, {"cmd": "status"}, timeout_s=2)["connected"], 2 * START_S,
                 "the device")
        assert request(sock, {"cmd": "send", "name": "wood", "size": (tmp_path / "wood.vtx").stat().st_size},
                       (tmp_path / "wood.vtx").read_bytes())["ok"]
        request(sock, {"cmd": "select", "name": "wood"})
        # the pump sleeps in the device-mode loop (woken by the pipe: where the EOFError was)
        wait_for(lambda: "renders the texture from its own encoder" in log.read_text(), 30,
                 "device rendering")
        assert request(sock, {"cmd": "status"})["render_at"] == "device"
        # the pump names itself (PR_SET_NAME); the daemon may have other children (multiprocessing's
        # resource tracker)
        pump = next(c for c in _children(daemon.pid) if _comm(c) == "hostd-pump")
        daemon.kill()
        daemon.wait(10)
        wait_for(lambda: not _alive(pump), 30, "the orphaned pump to exit")
    finally:
        if daemon.poll() is None:
            daemon.kill()
        if pump is not None and _alive(pump):
            os.kill(pump, signal.SIGKILL)
    text = log.read_text()
    assert text.count("daemon gone; pump exiting") == 1, text[-3000:]
    assert "Traceback" not in text and "EOFError" not in text, text[-3000:]


def test_ready_and_sigterm_come_before_the_library_is_rescored(tmp_path):
    """40 stored streams without a quality row (as after a crash): READY=1 reaches the notify
    socket and "ready" is logged before the look for them ends; a SIGTERM as soon as the socket
    answers (before READY) is a clean stop, exit 0."""
    lib = tmp_path / "lib"
    lib.mkdir()
    src = tmp_path / "s.vtx"
    assert main(["encode", "synthetic:wood:3", "-o", str(src), "--method", "quant", "--levels", "6",
                 "--length-mm", "2"]) == 0
    for i in range(40):
        shutil.copy(src, lib / f"t{i}.vtx")
    cfg = tmp_path / "hostd.toml"
    cfg.write_text(DEVICE_CFG.replace('where = "device"', 'where = "host"'))
    ns = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    ns.bind(str(tmp_path / "notify"))
    ns.settimeout(2 * START_S)
    env = dict(os.environ, NOTIFY_SOCKET=str(tmp_path / "notify"))
    sock = str(tmp_path / "hostd.sock")
    log = tmp_path / "log.txt"
    daemon = subprocess.Popen([sys.executable, "-m", "hostd", "run", "--config", str(cfg)], cwd=tmp_path,
                              stderr=open(log, "w"), env=env)
    try:
        got = b""
        while b"READY=1" not in got:
            got = ns.recv(4096)
        wait_for(lambda: len(request(sock, {"cmd": "quality"})["rows"]) == 40, 2 * START_S, "the 40 rows")
    finally:
        daemon.send_signal(signal.SIGTERM)
        assert daemon.wait(30) == 0
    lines = log.read_text().splitlines()
    ready = next(i for i, ln in enumerate(lines) if ln.endswith(" ready"))
    looked = next(i for i, ln in enumerate(lines) if "40 stored streams without a quality row queued" in ln)
    scored = [i for i, ln in enumerate(lines) if " INFO quality t" in ln]
    assert ready < looked and len(scored) == 40 and ready < min(scored), lines[:12]

    # a stop during the start: the handler is in place before the control socket answers
    (tmp_path / "q.sqlite").unlink()
    for f in tmp_path.glob("q.sqlite-*"):
        f.unlink()
    daemon = subprocess.Popen([sys.executable, "-m", "hostd", "run", "--config", str(cfg)], cwd=tmp_path,
                              stderr=open(log, "w"), env=env)
    try:
        wait_for(lambda: request(sock, {"cmd": "status"}, timeout_s=2)["ok"], 2 * START_S, "the socket")
        assert b"READY=1" not in b"".join(_drain(ns))
        daemon.send_signal(signal.SIGTERM)
        assert daemon.wait(30) == 0, log.read_text()[-2000:]
    finally:
        if daemon.poll() is None:
            daemon.kill()
    assert "stopped" in log.read_text()


def _drain(ns: socket.socket) -> list[bytes]:
    out = []
    ns.setblocking(False)
    try:
        while True:
            out.append(ns.recv(4096))
    except BlockingIOError:
        return out


def _counters(**kw) -> dict:
    c = {"device_elapsed_s": 100.0, "played_fraction": 1.0, "render_at": "host", "device_samples_played": 0,
         "samples": 0, "device_underruns": 0}
    c.update(kw)
    return c


def test_forged_device_counters_are_bounded_by_what_the_host_knows():
    """A device that claims 601.6 s played after 3 s of play (issue 29), a clock that runs back or
    far ahead, more samples played than were sent and buffered, a fraction above 1, underruns that
    go back: the plays row holds what the host can vouch for, and each claim is named."""
    from hostd.device.protocol import BUFFER_CAPACITY, SAMPLE_RATE_HZ
    from hostd.service.daemon import bound_play

    honest, bad = bound_play(_counters(), _counters(device_elapsed_s=103.0, device_samples_played=9000,
                                                   samples=9100, device_underruns=1), 3.0)
    assert not bad and honest["played_s"] == 3.0 and honest["device_s"] == 3.0 and honest["underruns"] == 1

    forged = 601.6 * SAMPLE_RATE_HZ
    row, bad = bound_play(_counters(), _counters(device_elapsed_s=701.6, device_samples_played=forged,
                                                 samples=9000), 3.0)
    assert row["played_s"] <= (9000 + BUFFER_CAPACITY) / SAMPLE_RATE_HZ and row["device_s"] == 3.0
    assert any("of its clock in 3.0 s" in b for b in bad) and any("sent and buffered" in b for b in bad)

    row, bad = bound_play(_counters(device_elapsed_s=5e9, device_underruns=7),
                          _counters(device_elapsed_s=2.0, device_underruns=2), 3.0)  # back, or wrapped
    assert row["device_s"] == 0.0 and row["underruns"] == 0 and len(bad) == 2

    row, bad = bound_play(_counters(), _counters(device_elapsed_s=103.0, render_at="device",
                                                 played_fraction=7.5), 3.0)
    assert row["played_fraction"] == 1.0 and row["played_s"] == 3.0 and bad == ["a played fraction of 7.5"]

    row, bad = bound_play(_counters(), _counters(device_elapsed_s=float("nan"), device_underruns=10**9), 3.0)
    assert row["device_s"] == 0.0 and row["underruns"] <= 3.0 * 1.01 * SAMPLE_RATE_HZ and len(bad) == 2


def test_a_device_that_changes_identity_mid_session_is_a_new_device():
    """An IDENT with another protocol version (or CAPS that differ) after the handshake ends the
    link with DeviceGone naming the device and the change (the pump then identifies it again as
    on a replug); the same IDENT again (an answer to a repeated IDENTIFY) changes nothing."""
    import pytest

    from hostd.device import protocol as pr
    from hostd.device.link import DeviceLink
    from hostd.device.simdev import SimDevice, SimTransport
    from hostd.errors import DeviceGone

    t = SimTransport(SimDevice(protocol_version=2), realtime=False)
    link = DeviceLink(t)
    link.handshake(timeout_s=1.0)
    assert link.await_caps() is not None
    t.device.outbox.append(t.device.ident())  # the same identity again
    link.poll()
    assert link.ident["protocol_version"] == 2
    t.device.protocol_version = 1
    t.device.outbox.append(t.device.ident())
    with pytest.raises(DeviceGone,
                       match=r"sim.* changed its identity mid-session \(IDENT: protocol_version 2 -> 1"):
        link.poll()
    t2 = SimTransport(SimDevice(protocol_version=2), realtime=False)
    link2 = DeviceLink(t2)
    link2.handshake(timeout_s=1.0)
    link2.await_caps()
    caps = pr.decode(t2.device.caps())[1]
    forged = {k: v for k, v in caps.items() if k != "id"} | {"render": 0}
    t2.device.outbox.append(pr.encode("CAPS", **forged))
    with pytest.raises(DeviceGone, match=r"\(CAPS: render 1 -> 0\)"):
        link2.poll()


def test_counters_that_leap_within_the_device_s_own_clock_are_shown_within_what_the_host_knows():
    """A STATUS whose clock is 400 s on and whose samples played 1 M more (333 s' worth) is
    believed by DeviceHealth (a host may stall that long; the device's figures agree with each
    other); what the pump shows is bounded by the samples the link sent plus the buffer: the
    excess is set aside for good, and honest growth after it shows again."""
    from hostd.device import protocol as pr
    from hostd.device.health import DeviceHealth, HostBound

    def status(us: int, played: int) -> dict:
        return {"state": 1, "fault_flags": 0, "device_time_us": us & 0xFFFFFFFF,
                "samples_played": played & 0xFFFFFFFF, "underruns": 0}

    h = DeviceHealth()
    h.update(status(1_000_000, 100))
    h.update(status(2_000_000, 3100))
    h.update(status(402_000_000, 1_003_100))
    assert h.samples_played == 1_003_000 and h.resets == 0  # the leap is believed here

    b = HostBound()
    b.link_up(0.0, 0.0)
    sent = 3000 + 1000  # what the host sent on this link by then
    buf = pr.BUFFER_CAPACITY
    assert b.take(3000, b.base + sent + buf, buf) == 0 and b.shown == 3000
    over = b.take(h.samples_played, b.base + sent + buf, buf)
    assert over == h.samples_played - sent - buf and b.shown == sent  # set aside to the bound less its slack
    # honest counting after it: the buffer drains (a second more played than sent): not a claim
    sent += 2800
    assert b.take(h.samples_played + 3000, b.base + sent + buf, buf) == 0 and b.shown == sent + 200
    # a new link: its counts grow from what the device claims then (what the old link counted
    # after the last look is not the new link's), within its own time up
    b.link_up(100.0, h.samples_played + 3500)
    assert b.base == sent + 700
    most, slack = b.within_time(101.0, pr.SAMPLE_RATE_HZ)
    assert most == pytest.approx(sent + 700 + (1.01 + 0.5) * pr.SAMPLE_RATE_HZ)
    assert slack == 0.5 * pr.SAMPLE_RATE_HZ
