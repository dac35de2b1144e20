"""An honest display is never called a liar, however loaded the host: the firmware's host port (the
firmware core on a pty) and the daemon beside two CPU hogs, textures selected and stopped at once,
plays of 0-0.12 s. Each play's device time is compared with the host's time between the same two
reports (not with the play's own host time: the pump's snapshot of the counters is up to a
publish period old, longer when the host holds the pump up: 1.2 s here, by SIGSTOP). A display
that forges its clock is still named."""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import time

from hostd.cli import main
from hostd.device import protocol as pr
from hostd.service.client import request, send_file
from tests.daemon_helpers import wait_for
from tests.test_daemon_abuse import START_S
from tests.test_daemon_edges import _children, _comm
from tests.test_misbehaving_display import _display_and_daemon, _end, _lines

HOG_S = 40  # each hog's own bound: it ends by itself even if this test is killed


def _hogs(n: int = 2) -> list[subprocess.Popen]:
    """n busy loops, one per core of a 2-core machine, each ending by itself after HOG_S."""
    code = f"import time\nt = time.monotonic() + {HOG_S}\nwhile time.monotonic() < t:\n    pass\n"
    return [subprocess.Popen([sys.executable, "-c", code]) for _ in range(n)]


def _plays(sock: str, seconds: float, rnd: random.Random) -> int:
    """Select and stop `wood` for `seconds`: plays of 0-0.12 s, 0.05-0.3 s apart."""
    n = 0
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end:
        assert request(sock, {"cmd": "select", "name": "wood"}, timeout_s=10)["ok"]
        time.sleep(rnd.uniform(0.0, 0.12))
        assert request(sock, {"cmd": "stop"}, timeout_s=10)["ok"]
        n += 1
        time.sleep(rnd.uniform(0.05, 0.3))
    return n


def _honest_under_load(daemon_pid: int, sock: str, log, seconds: float) -> None:
    """Beside two CPU hogs, plays of 0-0.12 s for `seconds`, then three with the pump held up
    before them: every play logged, none accused."""
    hogs = _hogs()
    try:
        n = _plays(sock, seconds, random.Random(50))
        # the host at its worst: the pump held up 1.2 s (SIGSTOP) just before a texture is selected,
        # so the counters the play starts from are that old, and stopped 0.7 s after it resumes
        pump = next(c for c in _children(daemon_pid) if _comm(c) == "hostd-pump")
        for _ in range(3):
            os.kill(pump, signal.SIGSTOP)
            try:
                time.sleep(1.2)
                assert request(sock, {"cmd": "select", "name": "wood"}, timeout_s=10)["ok"]
            finally:
                os.kill(pump, signal.SIGCONT)
            time.sleep(0.7)  # (past the pump's next publish: 0.5 s apart in device mode)
            assert request(sock, {"cmd": "stop"}, timeout_s=10)["ok"]
            n += 1
            time.sleep(0.5)
    finally:
        for h in hogs:
            h.kill()
            h.wait()
    # (the journal folds repeated lines: the plays are counted in the quality log)
    wait_for(lambda: request(sock, {"cmd": "quality"})["rows"][0]["plays"] == n, 30, "every play logged")
    text = log.read_text()
    assert "reported the impossible" not in text, [ln for ln in text.splitlines() if "impossible" in ln]
    assert n >= 6, n


def test_the_honest_host_port_is_never_accused_under_load_and_a_forged_clock_is_named(tmp_path):
    hp, cable, daemon, sock, log, dac, link = _display_and_daemon(
        tmp_path, "device", ["--motion", "metronome", "--duration", "300"])
    try:
        wait_for(lambda: request(sock, {"cmd": "status"}, timeout_s=2)["connected"], 2 * START_S,
                 "the display")
        send_file(sock, str(tmp_path / "wood.vtx"), "wood")
        _honest_under_load(daemon.pid, sock, log, 12.0)

        # a display that forges its clock (400 s on in one report) while it plays: named
        at = len(log.read_text().splitlines())
        request(sock, {"cmd": "select", "name": "wood"})
        wait_for(lambda: request(sock, {"cmd": "status"})["device_state"] == "rendering", 30, "rendering")
        f = {k: v for k, v in cable.next_status().items() if k != "id"}
        f["device_time_us"] = (f["device_time_us"] + 400_000_000) & 0xFFFFFFFF
        cable.inject(pr.frame(pr.encode("STATUS", **f)))
        wait_for(lambda: _lines(log, at, "reported the impossible"), 30, "the forged clock named")
        request(sock, {"cmd": "stop"})
        said = _lines(log, at, "reported the impossible")
        assert said and all(str(link) in ln for ln in said) and "of its clock" in said[0], said
    finally:
        _end(hp, cable, daemon, log, dac, honest=False)


def test_the_simulated_display_is_never_accused_under_load(tmp_path):
    from tests.test_daemon_abuse import _cfg, _start, _stop

    assert main(["encode", "synthetic:wood:1", "-o", str(tmp_path / "wood.vtx"), "--method", "quant",
                 "--levels", "14"]) == 0
    proc, sock = _start(tmp_path, _cfg(tmp_path))
    try:
        wait_for(lambda: request(sock, {"cmd": "status"}, timeout_s=2)["connected"], 2 * START_S,
                 "the simulated display")
        send_file(sock, str(tmp_path / "wood.vtx"), "wood")
        _honest_under_load(proc.pid, sock, tmp_path / "log.txt", 5.0)
    finally:
        _stop(proc)
    assert "Traceback" not in (tmp_path / "log.txt").read_text()


def _counters(**kw) -> dict:
    c = {"device_elapsed_s": 100.0, "played_fraction": 1.0, "render_at": "device", "device_samples_played": 0,
         "samples": 0, "device_underruns": 0, "device_report_host_s": 5000.0}
    return c | kw


def test_a_play_sets_the_device_s_time_against_the_host_s_time_of_the_same_reports():
    """A play of 0.1 s whose first snapshot is 1.2 s old: the device's clock ran 1.3 s between the two
    reports, which the host received 1.3 s apart: not impossible (the play's own 0.1 s is not what
    the reports span). 400 s of its clock between the same reports is, and the row holds 1.3 s."""
    from hostd.service.daemon import bound_play

    row, bad = bound_play(_counters(), _counters(device_elapsed_s=101.3, device_report_host_s=5001.3), 0.1)
    assert not bad and abs(row["device_s"] - 1.3) < 1e-9 and abs(row["played_s"] - 1.3) < 1e-9
    row, bad = bound_play(_counters(), _counters(device_elapsed_s=500.0, device_report_host_s=5001.3), 0.1)
    assert bad == ["400.0 s of its clock in 1.3 s"] and abs(row["device_s"] - 1.3) < 1e-9
    # the clock 1 % fast and a report 0.5 s late, at most
    _, bad = bound_play(_counters(), _counters(device_elapsed_s=100 + 1.3 * 1.01 + 0.49,
                                               device_report_host_s=5001.3), 0.1)
    assert not bad
