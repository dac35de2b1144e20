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


# ---------------------------------------------------------------- issue 32: who may stop the daemon

NOBODY = 65534
SYSTEM_PYTHON = "/usr/bin/python3"  # an unprivileged user cannot run the venv's under /work


def test_stop_daemon_is_for_its_user_or_root(tmp_path):
    """A member of the socket's group (here nobody, given the socket) sends textures and reads the
    log; `hostd stop --daemon` from it is refused (SO_PEERCRED on the control socket, the
    kernel's word) and the daemon keeps running; root's stops it."""
    import shutil
    import tempfile

    from hostd.cli import main

    if os.geteuid() != 0 or not os.path.exists(SYSTEM_PYTHON):
        pytest.skip("needs root (to run a client as another user) and /usr/bin/python3")
    rundir = Path(tempfile.mkdtemp(prefix="hostd-i32-"))  # outside pytest's 0700 tree
    os.chmod(rundir, 0o711)
    cfg = write_cfg(tmp_path)
    cfg.write_text(cfg.read_text().replace('socket = "hostd.sock"', f'socket = "{rundir}/hostd.sock"'))
    proc = subprocess.Popen([sys.executable, "-m", "hostd", "run", "--config", str(cfg)], cwd=tmp_path,
                            stderr=open(tmp_path / "log.txt", "a"), start_new_session=True)
    sock = str(rundir / "hostd.sock")
    try:
        _wait_connected(proc, sock, tmp_path / "log.txt")
        os.chmod(sock, 0o666)  # as the group's member would reach it
        code = ("import socket,sys\n"
                "s=socket.socket(socket.AF_UNIX); s.connect(sys.argv[1])\n"
                "s.sendall(b'{\"cmd\": \"shutdown\"}\\n'); print(s.makefile().readline(), end='')\n")
        out = subprocess.run([SYSTEM_PYTHON, "-I", "-c", code, sock], user=NOBODY, group=NOBODY,
                             capture_output=True, text=True, timeout=30)
        assert '"ok": false' in out.stdout and "only root or hostd's own user" in out.stdout, out
        assert f"not uid {NOBODY}" in out.stdout
        time.sleep(1.0)  # a shutdown takes effect at once; the daemon must still be there
        assert proc.poll() is None and request(sock, {"cmd": "status"}, timeout_s=5)["ok"]
        assert main(["stop", "--daemon", "--socket", sock]) == 0  # root: the daemon's own user here
        _exits_within(proc, BOUND_S, tmp_path / "log.txt")
        assert proc.returncode == 0
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        shutil.rmtree(rundir, ignore_errors=True)


def test_under_systemd_stop_daemon_is_refused_for_anyone(tmp_path, monkeypatch):
    """Under systemd a clean exit is not restarted (Restart=on-failure): even root is told to use
    systemctl stop. The service is recognized by its cgroup (a .service, not a shell's .scope)
    and systemd's INVOCATION_ID."""
    import threading
    import types

    from hostd.errors import HostdError
    from hostd.service import notify
    from hostd.service.daemon import Daemon

    cg = tmp_path / "cgroup"
    cg.write_text("0::/system.slice/hostd.service\n")
    assert notify.service_unit(str(cg), {"INVOCATION_ID": "0f"}) == "hostd.service"
    assert notify.service_unit(str(cg), {}) is None  # not started by systemd
    cg.write_text("0::/user.slice/user-1000.slice/user@1000.service/app.slice/vte-spawn-1.scope\n")
    assert notify.service_unit(str(cg), {"INVOCATION_ID": "0f"}) is None  # a terminal's shell
    cg.write_text("12:cpu:/\n1:name=systemd:/system.slice/hostd.service\n")  # cgroup v1
    assert notify.service_unit(str(cg), {"INVOCATION_ID": "0f"}) == "hostd.service"

    d = types.SimpleNamespace(lock=threading.Lock(), refused=0)
    d.refuse = lambda msg: Daemon.refuse(d, msg)
    monkeypatch.setattr(notify, "service_unit", lambda: "hostd.service")
    for uid in (0, os.geteuid(), NOBODY):
        with pytest.raises(HostdError, match=r"runs as the systemd service hostd\.service: use systemctl "
                           r"stop hostd"):
            Daemon.may_shut_down(d, uid)
    monkeypatch.setattr(notify, "service_unit", lambda: None)
    Daemon.may_shut_down(d, 0)
    Daemon.may_shut_down(d, os.geteuid())
    with pytest.raises(HostdError, match="only root or hostd's own user"):
        Daemon.may_shut_down(d, NOBODY)
    assert d.refused == 4
