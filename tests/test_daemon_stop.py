"""A stop is bounded: `hostd run` exits within seconds of SIGTERM whatever the pump is doing,
starting up, killed, or stuck (in 1 of ~30 start/stop trials `timeout 4 hostd run` had left the
main process blocked for over 10 minutes with the pump gone)."""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from hostd.bench.soak import child_pids
from hostd.service.client import ClientError, request
from tests.test_daemon import write_cfg

BOUND_S = 15.0  # quit 3 s + SIGTERM 2 s + SIGKILL 2 s + quality worker; far from "over 10 minutes"


def _start(tmp_path: Path) -> subprocess.Popen:
    cfg = write_cfg(tmp_path)
    return subprocess.Popen([sys.executable, "-m", "hostd", "run", "--config", str(cfg)], cwd=tmp_path,
                            stderr=open(tmp_path / "log.txt", "a"), start_new_session=True)


def _pump(proc: subprocess.Popen) -> int | None:
    pumps = [p for p in child_pids(proc.pid) if b"spawn_main" in Path(f"/proc/{p}/cmdline").read_bytes()]
    return pumps[0] if pumps else None


def _wait_connected(proc: subprocess.Popen, sock: str, log: Path) -> None:
    for _ in range(900):
        if proc.poll() is not None:
            pytest.fail(log.read_text()[-2000:])
        try:
            if request(sock, {"cmd": "status"}, timeout_s=2)["connected"]:
                return
        except ClientError:
            pass
        time.sleep(0.1)
    pytest.fail(log.read_text()[-2000:])


def _exits_within(proc: subprocess.Popen, seconds: float, log: Path) -> None:
    try:
        proc.wait(seconds)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(10)
        pytest.fail(f"hostd run still running {seconds:g} s after SIGTERM:\n{log.read_text()[-2000:]}")


def test_stop_is_bounded_when_the_pump_is_stuck(tmp_path):
    """The pump stopped (SIGSTOP: it reads no pipe and handles no signal): the daemon still exits,
    and takes the pump with it. The old code joined it without a timeout at interpreter exit."""
    proc = _start(tmp_path)
    log = tmp_path / "log.txt"
    pump = None
    try:
        _wait_connected(proc, str(tmp_path / "hostd.sock"), log)
        pump = _pump(proc)
        os.kill(pump, signal.SIGSTOP)
        proc.send_signal(signal.SIGTERM)
        _exits_within(proc, BOUND_S, log)
        assert "killing it" in log.read_text()
        time.sleep(0.2)
        assert not Path(f"/proc/{pump}").exists() or b"State:\tZ" in Path(f"/proc/{pump}/status").read_bytes()
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        if pump is not None and Path(f"/proc/{pump}").exists():
            os.kill(pump, signal.SIGKILL)


def test_stop_is_bounded_at_random_moments_of_the_start_up(tmp_path):
    """As `timeout T hostd run` does: SIGTERM to the whole process group (daemon and pump) at a
    random moment while the pump starts, and once when the pump alone was killed first."""
    rng = random.Random(24)
    for trial in range(4):
        d = tmp_path / f"t{trial}"
        d.mkdir()
        proc = _start(d)
        try:
            if trial == 3:  # the pump dies on its own, then the daemon is stopped
                _wait_connected(proc, str(d / "hostd.sock"), d / "log.txt")
                os.kill(_pump(proc), signal.SIGKILL)
                time.sleep(0.3)
                if proc.poll() is None:
                    os.killpg(proc.pid, signal.SIGTERM)
            else:
                time.sleep(rng.uniform(0.3, 2.5))
                os.killpg(proc.pid, signal.SIGTERM)
            _exits_within(proc, BOUND_S, d / "log.txt")
        finally:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
