"""The daemon under load and abuse: same-name upload races, many clients, malformed requests,
oversize uploads, hostile spool entries, the socket's directory, worker supervision, resource
caps; and the one atomic writer (devices, FIFOs, stdout, umask, ENOSPC)."""

from __future__ import annotations

import errno
import json
import logging
import os
import signal
import socket
import stat
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from hostd.cli import main
from hostd.codec import stream as vtx
from hostd.codec import transform
from hostd.errors import ConfigError, HostdError, StreamError
from hostd.perception import thresholds
from hostd.service.client import ClientError, request, send_file
from hostd.service.library import Library, check_name

START_S = 60  # start-up on a loaded 2-core machine can take many seconds


def _cfg(d: Path, extra_library: str = "", extra_control: str = "", max_bytes: int = 4096) -> Path:
    p = d / "hostd.toml"
    p.write_text(f'[device]\ntransport = "sim"\n[library]\ndir = "lib"\nspool = "spool"\n'
                 f'max_stream_bytes = {max_bytes}\nspool_settle_s = 0.4\n{extra_library}'
                 f'[control]\nsocket = "run/hostd.sock"\ngroup = ""\n{extra_control}'
                 '[quality]\ndb = "q.sqlite"\n')
    return p


def _start(d: Path, cfg: Path) -> tuple[subprocess.Popen, str]:
    (d / "run").mkdir(exist_ok=True, mode=0o700)
    proc = subprocess.Popen([sys.executable, "-m", "hostd", "run", "--config", str(cfg)],
                            stderr=open(d / "log.txt", "w"), cwd=d)
    sock = str(d / "run" / "hostd.sock")
    deadline = time.monotonic() + START_S
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            pytest.fail((d / "log.txt").read_text()[-3000:])
        try:
            request(sock, {"cmd": "status"}, timeout_s=5)
            return proc, sock
        except ClientError:
            time.sleep(0.1)
    proc.kill()
    pytest.fail((d / "log.txt").read_text()[-3000:])


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(20)
        except subprocess.TimeoutExpired:
            proc.kill()


@pytest.fixture(scope="module")
def daemon(tmp_path_factory):
    d = tmp_path_factory.mktemp("abuse")
    proc, sock = _start(d, _cfg(d, extra_control="max_clients = 4\n"))
    yield proc, d, sock
    _stop(proc)


def _streams(d: Path, k: int) -> list[bytes]:
    out = []
    for i in range(k):
        p = d / f"s{i}.vtx"
        if not p.exists():
            assert main(["encode", f"synthetic:wood:{i}", "-o", str(p), "--method", "quant",
                         "--levels", str(4 + i), "--length-mm", "2"]) == 0
        out.append(p.read_bytes())
    return out


def _raw(sock: str, payload: bytes, timeout_s: float = 10) -> dict:
    s = socket.socket(socket.AF_UNIX)
    s.settimeout(timeout_s)
    s.connect(sock)
    try:
        s.sendall(payload)
    except BrokenPipeError:
        pass
    f = s.makefile("rb")
    line = f.readline()
    s.close()
    assert line, "no reply"
    return json.loads(line)


def test_same_name_uploads_race_every_client_answered_stored_file_is_one_upload(daemon):
    _proc, d, sock = daemon
    bodies = _streams(d, 8)
    for _round in range(3):
        replies: list = [None] * 8

        def up(i: int, replies: list = replies) -> None:
            try:
                replies[i] = request(sock, {"cmd": "send", "name": "race", "size": len(bodies[i])},
                                     bodies[i])
            except ClientError as e:
                replies[i] = e

        ts = [threading.Thread(target=up, args=(i,)) for i in range(8)]
        for t in ts:
            t.start()
        for t in ts:
            t.join(60)
        assert all(r is not None for r in replies), replies
        acked = [bodies[i] for i, r in enumerate(replies) if isinstance(r, dict) and r["ok"]]
        assert acked, replies  # "busy" refusals are answers too, but some must get through
        stored = (d / "lib" / "race.vtx").read_bytes()
        assert stored in acked
        vtx.decode(stored)
    assert not [p for p in (d / "lib").iterdir() if p.name.startswith(".")]


def test_many_clients_all_answered_and_a_full_server_says_so(daemon):
    _proc, _d, sock = daemon
    answered = []

    def client() -> None:
        for _ in range(40):
            try:
                request(sock, {"cmd": "list"}, timeout_s=20)
                answered.append("ok")
            except ClientError as e:
                answered.append(str(e))

    ts = [threading.Thread(target=client) for _ in range(8)]
    for t in ts:
        t.start()
    for t in ts:
        t.join(120)
    assert len(answered) == 320
    # nothing lost to a short backlog: every failure is the daemon's own "busy" answer
    assert all(a == "ok" or "busy" in a for a in answered), {a for a in answered if a != "ok"}
    # hold every handler (max_clients = 4) with a silent client: the next one is told why
    import select

    for _attempt in range(5):
        time.sleep(1.0)  # let the handlers of the load above finish
        held = []
        for _ in range(4):
            s = socket.socket(socket.AF_UNIX)
            s.connect(sock)
            held.append(s)
        time.sleep(0.5)
        if not select.select(held, [], [], 0)[0]:  # all four are being served (none refused)
            break
        for s in held:
            s.close()
    try:
        with pytest.raises(ClientError, match=r"busy.*control\.max_clients"):
            request(sock, {"cmd": "status"})
    finally:
        for s in held:
            s.close()
    time.sleep(0.3)
    assert request(sock, {"cmd": "status"})["ok"]


@pytest.mark.parametrize("payload, needle", [
    (b'{"cmd": "send", "name": "x", "size": "abc"}\n', "size must be an integer"),
    (b'{"cmd": "send", "name": "x", "size": 1.5}\n', "size must be an integer"),
    (b'{"cmd": "send", "name": ["x"], "size": 10}\n0123456789', "name must be a string"),
    (b'{"cmd": "quality", "since": [1, 2]}\n', "since must be unix seconds"),
    (b'{"cmd": "select", "name": {"a": 1}}\n', "name must be a string"),
    (b"[" * 2000 + b"]" * 2000 + b"\n", "one JSON object"),
    (b'{"a": ' * 1500 + b"1" + b"}" * 1500 + b"\n", "one JSON object"),
    (b"x" * 5000 + b"\n", "at most 4096 bytes"),
    (b'{"cmd": "nope"}\n', "unknown command"),
])
def test_every_malformed_request_gets_an_error_reply(daemon, payload, needle):
    _proc, d, sock = daemon
    r = _raw(sock, payload)
    assert r["ok"] is False and needle in r["error"], r
    assert "Traceback" not in (d / "log.txt").read_text()


def test_oversize_upload_gets_the_size_limit_message(daemon):
    _proc, d, sock = daemon
    big = d / "big.vtx"
    big.write_bytes(b"\0" * 300_000)
    t0 = time.monotonic()
    with pytest.raises(ClientError, match="max_stream_bytes"):
        send_file(sock, str(big), "big")
    assert time.monotonic() - t0 < 5


def test_spool_takes_regular_finished_files_only(daemon):
    _proc, d, sock = daemon
    spool, rejected = d / "spool", d / "spool" / "rejected"
    good = _streams(d, 2)[1]
    os.mkfifo(spool / "fifo.vtx")
    (spool / "zero.vtx").symlink_to("/dev/zero")
    (spool / "dir.vtx").mkdir()
    (spool / "huge.vtx").write_bytes(b"\0" * 5000)
    # a slow writer: chunks with pauses shorter than the settle time
    with open(spool / "slow.vtx", "wb") as f:
        for i in range(0, len(good), 16):
            f.write(good[i:i + 16])
            f.flush()
            time.sleep(0.15)
    deadline = time.monotonic() + 30
    want = {"fifo.vtx", "zero.vtx", "dir.vtx", "huge.vtx"}
    while time.monotonic() < deadline:
        names = request(sock, {"cmd": "list"})["textures"]
        if "slow" in names and want <= {p.name for p in rejected.iterdir()}:
            break
        time.sleep(0.2)
    assert (d / "lib" / "slow.vtx").read_bytes() == good  # the whole file, not half of it
    for n in want:
        assert (rejected / f"{n}.error").read_text().strip(), n
    assert "regular files only" in (rejected / "zero.vtx.error").read_text()
    assert "max_stream_bytes" in (rejected / "huge.vtx.error").read_text()
    # the spool thread survived all of it
    (spool / "after.vtx").write_bytes(good)
    deadline = time.monotonic() + 20
    while "after" not in request(sock, {"cmd": "list"})["textures"] and time.monotonic() < deadline:
        time.sleep(0.2)
    assert "after" in request(sock, {"cmd": "list"})["textures"]


def test_socket_directory_others_can_write_is_refused(tmp_path):
    """Issue 20 item 3: only a directory the daemon's user owns and nobody else writes; a
    sticky one (root's 1777) is refused too: after a stop another user could bind the name."""
    from hostd.service.control import check_socket_dir

    d = tmp_path / "open"
    d.mkdir()
    os.chmod(d, 0o777)
    with pytest.raises(ConfigError, match="can be written by others"):
        check_socket_dir(d)
    os.chmod(d, 0o1777)  # sticky: another user can still take the name once we are stopped
    with pytest.raises(ConfigError, match="RuntimeDirectory=hostd"):
        check_socket_dir(d)
    os.chmod(d, 0o750)
    check_socket_dir(d)
    os.chown(d, 65534, -1)  # owned by someone else (nobody), even if closed
    with pytest.raises(ConfigError, match="not owned by hostd's user"):
        check_socket_dir(d)
    os.chown(d, os.geteuid(), -1)
    cfg = _cfg(tmp_path)
    cfg.write_text(cfg.read_text().replace('socket = "run/hostd.sock"', f'socket = "{d}/x/hostd.sock"'))
    (d / "x").mkdir()
    os.chmod(d / "x", 0o777)
    r = subprocess.run([sys.executable, "-m", "hostd", "run", "--config", str(cfg)], capture_output=True,
                       text=True, cwd=tmp_path, timeout=120)
    assert r.returncode == 2 and "can be written by others" in r.stderr, r.stderr


def test_dead_worker_is_restarted_then_starves_the_watchdog(tmp_path, caplog):
    from hostd.service import daemon as dm
    from hostd.service.config import load

    dmn = dm.Daemon(load(_cfg(tmp_path)))
    calls = []

    def broken() -> None:
        calls.append(1)
        raise OSError(errno.EMFILE, "Too many open files")

    caplog.set_level(logging.INFO, logger="hostd")
    dmn.start_worker("spool", broken)
    healthy = []
    for _ in range(dm.RESTARTS_PER_MINUTE + 2):
        time.sleep(0.05)
        healthy.append(dmn.supervise())
    assert healthy[0] is True and healthy[-1] is False
    assert len(calls) == dm.RESTARTS_PER_MINUTE + 1
    text = caplog.text
    assert "worker spool failed: OSError" in text and "restarted" in text and "no longer fed" in text


def _quant_stream(n_keep: int) -> bytes:
    """A quant stream with about n_keep coefficients (N' = 2 L fmax / v)."""
    n = max(4 * n_keep, 64)
    geom = transform.Geometry(n, n_keep * 50.0 / 800.0, 50.0, 400.0)
    rng = np.random.default_rng(1)
    return vtx.encode_profile(rng.normal(size=n), geom, thresholds.default_curve(), method="quant",
                              levels=8)


def test_library_caps_names_and_enospc(tmp_path, monkeypatch):
    lib = Library(tmp_path / "lib", 1 << 20, max_n=1 << 20, max_n_keep=50)
    big = _quant_stream(4000)
    assert vtx.decode(big).n_keep > 50
    with pytest.raises(StreamError, match="max_n_keep"):
        lib.add("big", big)
    small_lib = Library(tmp_path / "lib2", 1 << 20, max_n=100, max_n_keep=1 << 20)
    with pytest.raises(StreamError, match=r"library\.max_n\b"):
        small_lib.add("big", big)
    for bad in ("abc\n", "abc\nx", "", "../x", ".hidden", "a" * 65):
        with pytest.raises(HostdError, match="bad texture name"):
            check_name(bad)
    # ENOSPC while storing: a clear refusal, the old content intact, no temporary left
    ok = _quant_stream(20)
    lib.add("t", ok)
    real_write = os.write

    def full(fd, b):
        if os.fstat(fd).st_size > 10:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_write(fd, b[:11])

    monkeypatch.setattr(os, "write", full)
    with pytest.raises(HostdError, match="No space left on device"):
        lib.add("t", _quant_stream(30))
    monkeypatch.undo()
    assert (tmp_path / "lib" / "t.vtx").read_bytes() == ok
    assert [p.name for p in (tmp_path / "lib").iterdir()] == ["t.vtx"]


def test_v1_decoder_refuses_q_min_that_overflows(monkeypatch):
    n_keep = 12

    def evil_payload(q):
        return vtx.zigzag_varint(-(2 ** 63)) + bytes([1]) + bytes(n_keep)

    monkeypatch.setattr(vtx.v1, "_quant_payload", evil_payload)
    data = _quant_stream(n_keep)
    monkeypatch.undo()
    with pytest.raises(StreamError, match="out of range"):
        vtx.decode(data)


# ---------------------------------------------------------------- the one atomic writer


def test_writer_writes_through_fifos_and_stdout_and_honours_umask(tmp_path, capfdbinary):
    from hostd.fileio import write_output

    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    got = []
    reader = threading.Thread(target=lambda: got.append(open(fifo, "rb").read()))
    reader.start()
    assert main(["encode", "synthetic:wood:1", "-o", str(fifo), "--method", "quant", "--levels", "14",
                 "--length-mm", "2"]) == 0
    reader.join(20)
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode)  # not replaced by a regular file
    vtx.decode(got[0])
    old = os.umask(0o022)
    try:
        assert main(["encode", "synthetic:wood:1", "-o", str(tmp_path / "x.vtx"), "--method", "quant",
                     "--levels", "14", "--length-mm", "2"]) == 0
        assert stat.S_IMODE(os.stat(tmp_path / "x.vtx").st_mode) == 0o644
        os.umask(0o077)
        write_output(tmp_path / "y", b"1")
        assert stat.S_IMODE(os.stat(tmp_path / "y").st_mode) == 0o600
    finally:
        os.umask(old)
    capfdbinary.readouterr()
    assert main(["encode", "synthetic:wood:1", "-o", "-", "--method", "quant", "--levels", "14",
                 "--length-mm", "2"]) == 0
    out = capfdbinary.readouterr().out
    vtx.decode(out)
    assert not (Path.cwd() / "-").exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]
