"""The systemd unit starts: `hostd run` under the unit's own seccomp filter (SystemCallFilter=,
MemoryDenyWriteExecute=, RestrictAddressFamilies=, LimitNOFILE=, Environment=, UMask=) reaches
READY=1 and plays; the pump ramps down and exits cleanly on SIGTERM; the unit's other settings."""

from __future__ import annotations

import grp
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from hostd.bench.soak import child_pids
from hostd.cli import main
from hostd.service.client import ClientError, request, send_file

ROOT = Path(__file__).resolve().parent.parent
UNIT = ROOT / "systemd" / "hostd.service"
sys.path.insert(0, str(Path(__file__).resolve().parent))
import unit_sandbox  # noqa: E402


def _cfg(d: Path) -> Path:
    group = grp.getgrgid(os.getegid()).gr_name  # the socket's chown runs (needs @chown)
    p = d / "hostd.toml"
    p.write_text(f'[device]\ntransport = "sim"\n[render]\nwhere = "host"\n'
                 '[library]\ndir = "lib"\nspool = "spool"\n'
                 f'[control]\nsocket = "hostd.sock"\ngroup = "{group}"\n[quality]\ndb = "q.sqlite"\n')
    return p


def _unit_env() -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("OPENBLAS", "OMP"))}
    for line in unit_sandbox.unit_settings(UNIT).get("Environment", []):
        for kv in line.split():
            k, v = kv.split("=", 1)
            env[k] = v
    return env


def _wait_socket(sock: str, proc: subprocess.Popen, log: Path) -> None:
    """Until the daemon answers, within the start allowance it asks systemd for (a loaded machine
    takes more than a quiet one's few seconds)."""
    from hostd.service.notify import START_WATCHDOG_S

    deadline = time.monotonic() + START_WATCHDOG_S
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            pytest.fail(f"hostd exited with {proc.returncode}:\n{log.read_text()[-3000:]}")
        try:
            request(sock, {"cmd": "status"}, timeout_s=2)
            return
        except ClientError:
            time.sleep(0.1)
    pytest.fail(log.read_text()[-3000:])


def test_hostd_run_starts_and_plays_under_the_units_seccomp_filter(tmp_path):
    lib, why = unit_sandbox.libseccomp()
    if lib is None:
        pytest.skip(why)
    text, source = unit_sandbox.groups_text()
    allowed = unit_sandbox.allowed_syscalls(UNIT, unit_sandbox.parse_groups(text))
    assert "mbind" in allowed and "fchown" in allowed, source
    assert "reboot" not in allowed and "mount" not in allowed and "ptrace" not in allowed
    cfg = _cfg(tmp_path)
    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    notify.bind(str(tmp_path / "notify"))
    notify.settimeout(0.2)
    env = _unit_env()
    env["NOTIFY_SOCKET"] = str(tmp_path / "notify")
    env["WATCHDOG_USEC"] = "5000000"  # as systemd sets it for the unit's WatchdogSec=5
    nofile = int(unit_sandbox.unit_settings(UNIT)["LimitNOFILE"][-1])
    umask = int(unit_sandbox.unit_settings(UNIT)["UMask"][-1], 8)

    def limits() -> None:
        import resource

        resource.setrlimit(resource.RLIMIT_NOFILE, (nofile, nofile))
        os.umask(umask)

    log = tmp_path / "log.txt"
    proc = subprocess.Popen([sys.executable, unit_sandbox.__file__, str(UNIT), "--", sys.executable, "-m",
                             "hostd", "run", "--config", str(cfg)], cwd=tmp_path, env=env,
                            stderr=open(log, "w"), preexec_fn=limits)
    msgs: list[str] = []
    done = threading.Event()

    def drain() -> None:  # as systemd does: read every notification
        while not done.is_set():
            try:
                msgs.extend(notify.recv(4096).decode().split("\n"))
            except TimeoutError:
                pass

    reader = threading.Thread(target=drain, daemon=True)
    reader.start()
    try:
        # the design's bound: hostd asks systemd for START_WATCHDOG_S to reach READY=1 (a loaded
        # machine takes more than a quiet one's few seconds; past the allowance systemd kills it)
        from hostd.service.notify import START_WATCHDOG_S

        deadline = time.monotonic() + START_WATCHDOG_S
        while "READY=1" not in msgs and time.monotonic() < deadline:
            if proc.poll() is not None:
                sig = -proc.returncode if proc.returncode < 0 else 0
                pytest.fail(f"hostd died under the unit's filter (exit {proc.returncode}"
                            f"{', SIGSYS: a syscall the filter forbids' if sig == signal.SIGSYS else ''}):\n"
                            + log.read_text()[-3000:])
            time.sleep(0.05)
        assert "READY=1" in msgs, log.read_text()[-3000:]
        # systemd arms the watchdog at exec: the start asks for its allowance before anything
        # slow, and READY=1 gives the unit's WatchdogSec= back (hostd.service.notify)
        assert msgs[0] == "WATCHDOG_USEC=120000000", msgs[:4]
        ready = msgs.index("READY=1")
        assert msgs[ready + 1] == "WATCHDOG_USEC=5000000", msgs[ready:ready + 3]
        sock = str(tmp_path / "hostd.sock")
        _wait_socket(sock, proc, log)
        out = tmp_path / "w.vtx"
        assert main(["encode", "synthetic:wood:3", "-o", str(out), "--method", "quant", "--levels", "8"]) == 0
        send_file(sock, str(out), None)
        request(sock, {"cmd": "select", "name": "w"})
        for _ in range(200):
            if request(sock, {"cmd": "status"})["state"] == "playing":
                break
            time.sleep(0.1)
        a = request(sock, {"cmd": "status"})
        time.sleep(0.5)
        b = request(sock, {"cmd": "status"})
        assert b["state"] == "playing" and b["samples"] > a["samples"] + 300, (a, b)
        for _ in range(50):  # the quality worker (SQLite, scoring) runs under the filter too
            if request(sock, {"cmd": "quality"})["rows"]:
                break
            time.sleep(0.1)
        else:
            pytest.fail("no quality row: " + log.read_text()[-2000:])
        assert "WATCHDOG=1" in msgs
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(20) == 0, log.read_text()[-3000:]
        assert "STOPPING=1" in msgs
    finally:
        if proc.poll() is None:
            proc.kill()
        done.set()
        reader.join()
        notify.close()


def test_pump_ramps_to_zero_and_exits_cleanly_on_sigterm(tmp_path):
    """KillMode=mixed / systemctl kill: a SIGTERM to the pump stops output (ramp) and exits 0."""
    cfg = _cfg(tmp_path)
    log = tmp_path / "log.txt"
    proc = subprocess.Popen([sys.executable, "-m", "hostd", "run", "--config", str(cfg)], cwd=tmp_path,
                            stderr=open(log, "w"))
    try:
        sock = str(tmp_path / "hostd.sock")
        _wait_socket(sock, proc, log)
        out = tmp_path / "w.vtx"
        assert main(["encode", "synthetic:wood:3", "-o", str(out), "--method", "quant", "--levels", "8"]) == 0
        send_file(sock, str(out), None)
        request(sock, {"cmd": "select", "name": "w"})
        for _ in range(200):  # the pump's start-up (imports) can take seconds on a loaded machine
            if request(sock, {"cmd": "status"})["state"] == "playing":
                break
            time.sleep(0.1)
        pumps = [p for p in child_pids(proc.pid)
                 if b"spawn_main" in Path(f"/proc/{p}/cmdline").read_bytes()]
        assert len(pumps) == 1
        os.kill(pumps[0], signal.SIGTERM)
        proc.wait(15)
        text = log.read_text()
        assert "the real-time pump exited (code 0)" in text, text[-2000:]
    finally:
        if proc.poll() is None:
            proc.kill()


def test_unit_settings():
    s = unit_sandbox.unit_settings(UNIT)
    assert s["KillMode"] == ["mixed"]
    assert "systemd-udev-settle" not in UNIT.read_text()
    for key in ("LimitNOFILE", "TasksMax", "MemoryMax"):
        assert key in s, key


def test_unit_hardening_and_the_documented_exposure(tmp_path):
    s = unit_sandbox.unit_settings(UNIT)
    assert s["PrivateMounts"] == ["yes"] and "SupplementaryGroups" not in s  # the udev rule gives group hostd
    assert "Documentation=man:hostd(8)" in UNIT.read_text() and "file://" not in UNIT.read_text()
    assert "tests/test_service_unit.py" in UNIT.read_text() and "test_unit_sandbox" not in UNIT.read_text()
    if shutil.which("systemd-analyze") is None:
        pytest.skip("systemd-analyze is not installed (apt-get install systemd)")
    unit = tmp_path / "hostd.service"  # as documented: ExecStart pointed at an existing binary
    unit.write_text(UNIT.read_text().replace("/opt/hostd/bin/hostd", "/bin/true"))
    r = subprocess.run(["systemd-analyze", "security", "--offline=true", str(unit)], capture_output=True,
                       text=True, cwd=tmp_path)
    m = re.search(r"Overall exposure level for hostd.service: (\d+\.\d) (\w+)", r.stdout)
    assert m, r.stdout[-2000:] + r.stderr
    figure = f"exposure **{m[1]} {m[2]}**"
    for doc in (ROOT / "docs" / "daemon.md", ROOT / "README.md"):
        assert figure in doc.read_text(), (doc, figure)
