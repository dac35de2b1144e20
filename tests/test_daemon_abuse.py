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
import struct
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
    return vtx.v1.encode_profile(rng.normal(size=n), geom, thresholds.default_curve(), method="quant",
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


# ---------------------------------------------------------------- issue 20: hostile local users
# Each test plays one reproduction of issue 20 against the real daemon (or the piece of it that
# owns the defence) and fails on the code before the fix.

NOBODY = 65534
SYSTEM_PYTHON = "/usr/bin/python3"  # an unprivileged user cannot run the venv's under /work


def _unprivileged(code: str, *args: str, **kw) -> subprocess.Popen:
    """A stdlib-only script run as nobody: another local user."""
    if os.geteuid() != 0 or not os.path.exists(SYSTEM_PYTHON):
        pytest.skip("needs root (to run a script as another user) and /usr/bin/python3")
    return subprocess.Popen([SYSTEM_PYTHON, "-I", "-c", code, *args], user=NOBODY, group=NOBODY,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kw)


def _open_dir(prefix: str, mode: int) -> Path:
    """A directory outside pytest's 0700 tree, so that nobody can reach a socket in it."""
    import tempfile

    d = Path(tempfile.mkdtemp(prefix=prefix))
    os.chmod(d, mode)
    return d


def _vm_kib(pid: int, field: str) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise AssertionError(field)


@pytest.fixture(scope="module")
def hostile(tmp_path_factory):
    """A daemon with the default max_clients (16), its socket reachable by nobody, its spool
    group-writable for nobody's group (2770, as the old tmpfiles.d made it: the daemon must make
    it sticky), its quality database on a 2 MB tmpfs (when this runs as root) so that the disk
    can really be filled."""
    import shutil

    d = tmp_path_factory.mktemp("hostile")
    qfs = d / "qfs"
    qfs.mkdir()
    mount = ["mount", "-t", "tmpfs", "-o", "size=2m,mode=0700", "tmpfs", str(qfs)]
    mounted = os.geteuid() == 0 and subprocess.run(mount, capture_output=True).returncode == 0
    rundir = _open_dir("hostd-i20-", 0o711)
    spool = _open_dir("hostd-spool-", 0o770)
    os.chown(spool, -1, NOBODY)
    os.chmod(spool, 0o2770)
    cfg = _cfg(d)
    cfg.write_text(cfg.read_text().replace('socket = "run/hostd.sock"', f'socket = "{rundir}/hostd.sock"')
                   .replace('db = "q.sqlite"', 'db = "qfs/q.sqlite"')
                   .replace('spool = "spool"', f'spool = "{spool}"'))
    proc = subprocess.Popen([sys.executable, "-m", "hostd", "run", "--config", str(cfg)],
                            stderr=open(d / "log.txt", "w"), cwd=d)
    sock = str(rundir / "hostd.sock")
    try:
        from tests.daemon_helpers import wait_for

        wait_for(lambda: request(sock, {"cmd": "status"}, timeout_s=5)["ok"], START_S, "the daemon")
        os.chmod(sock, 0o666)  # let nobody connect: the share per user, the drip clients
        yield proc, d, sock, mounted, spool
    finally:
        _stop(proc)
        if mounted:
            subprocess.run(["umount", "-l", str(qfs)], capture_output=True)
        shutil.rmtree(rundir, ignore_errors=True)
        shutil.rmtree(spool, ignore_errors=True)


def _retry_busy(fn, tries: int = 200):
    for _ in range(tries):
        try:
            return fn()
        except ClientError as e:
            if "busy" not in str(e):
                raise
            time.sleep(0.02)
    raise AssertionError("always busy")


def test_concurrent_selects_of_large_textures_keep_the_pump_alive(daemon):
    """Item 1: 8 clients select two textures of N' = 16,000 five times each at once: the pump
    pipe has one writer, so no message interleaves and the pump keeps running."""
    proc, d, sock = daemon
    from tests.daemon_helpers import wait_for

    wait_for(lambda: request(sock, {"cmd": "status"})["connected"], START_S, "the simulated display")
    for name, seed in (("big", "wood"), ("big2", "wood:7")):
        p = d / f"{name}.vtx"
        assert main(["encode", f"synthetic:{seed}", "-o", str(p), "--fmax-hz", "40000", "--method", "quant",
                     "--levels", "14"]) == 0
        assert vtx.decode(p.read_bytes()).n_keep == 16000
        send_file(sock, str(p), name)
    errors: list = []

    def selects(i: int) -> None:
        for k in range(5):
            name = ("big", "big2")[(i + k) % 2]
            try:
                _retry_busy(lambda name=name: request(sock, {"cmd": "select", "name": name}))
            except (ClientError, AssertionError) as e:
                errors.append(str(e))

    ts = [threading.Thread(target=selects, args=(i,)) for i in range(8)]
    for t in ts:
        t.start()
    for t in ts:
        t.join(120)
    assert not errors, errors[:3]
    time.sleep(0.5)
    st = request(sock, {"cmd": "status"})
    assert proc.poll() is None and st["pump_alive"] and st["texture"] in ("big", "big2")
    s0 = st["samples"]
    # still playing: the samples advance (the display refuses N' = 16,000, and the first texture
    # the host renders in auto mode loads the host renderer then: device mode never loads it)
    wait_for(lambda: request(sock, {"cmd": "status"})["samples"] > s0, 30, "the samples to advance")
    assert "UnpicklingError" not in (d / "log.txt").read_text()
    # idempotent: selecting what plays sends nothing to the pump. Counted where the daemon decides
    # it (selects_sent). The pump's texture_serial is no count of that: under load the pipe's one
    # writer was still handing the burst's last select (128 kB) over when the status said the
    # samples advanced, and the serial moved after the check (a stressed run, 2026-11-27)
    sent = request(sock, {"cmd": "status"})["selects_sent"]
    for _ in range(5):
        request(sock, {"cmd": "select", "name": st["texture"]})
    assert request(sock, {"cmd": "status"})["selects_sent"] == sent
    request(sock, {"cmd": "select", "name": "big2" if st["texture"] == "big" else "big"})
    assert request(sock, {"cmd": "status"})["selects_sent"] == sent + 1  # (one that is sent on counts)


def test_spool_symlink_swap_writes_nothing_outside(hostile):
    """Item 2, as the issue plays it: rejected/ renamed and replaced by a link to the library,
    links to a victim file and to /dev/zero planted; the daemon follows none of them."""
    proc, d, sock, _, spool = hostile
    lib = d / "lib"
    victim = d / "victim.txt"
    victim.write_bytes(b"precious\n")
    os.rename(spool / "rejected", spool / "r.old")
    os.symlink(lib, spool / "rejected")
    os.symlink(victim, spool / "evil.vtx")
    os.symlink("/dev/zero", spool / "zero.vtx")
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline and (os.path.lexists(spool / "evil.vtx")
                                           or os.path.lexists(spool / "zero.vtx")):
        time.sleep(0.1)
    # nothing in the library; moved (as links) into the directory the daemon opened, now r.old
    assert not os.path.lexists(lib / "evil.vtx") and not os.path.lexists(lib / "zero.vtx")
    assert os.path.islink(spool / "r.old" / "evil.vtx") and os.path.islink(spool / "r.old" / "zero.vtx")
    assert "regular files only" in (spool / "r.old" / "evil.vtx.error").read_text()
    good = _streams(d, 1)[0]
    assert request(sock, {"cmd": "send", "name": "evil", "size": len(good)}, good)["ok"]
    assert victim.read_bytes() == b"precious\n"
    assert stat.S_ISREG(os.lstat(lib / "evil.vtx").st_mode) and (lib / "evil.vtx").read_bytes() == good
    # a link left in the library itself (to /dev/zero, to the victim) is neither listed nor read
    rss0 = _vm_kib(proc.pid, "VmRSS")
    os.symlink("/dev/zero", lib / "zero.vtx")
    os.symlink(victim, lib / "vic.vtx")
    assert "zero" not in request(sock, {"cmd": "list"})["textures"]
    for name in ("zero", "vic"):
        with pytest.raises(ClientError, match="not a regular file"):
            request(sock, {"cmd": "select", "name": name})
    assert _vm_kib(proc.pid, "VmRSS") < rss0 + 20_000
    # a replaced file is written as a new file, the link is gone, the victim intact
    assert request(sock, {"cmd": "send", "name": "vic", "size": len(good)}, good)["ok"]
    assert victim.read_bytes() == b"precious\n" and not os.path.islink(lib / "vic.vtx")
    os.unlink(lib / "zero.vtx")
    os.unlink(spool / "rejected")
    os.rename(spool / "r.old", spool / "rejected")  # as it was, for the tests that follow
    assert proc.poll() is None


def test_group_member_cannot_swap_rejected_in_the_sticky_spool(hostile):
    """Item 2, as an unprivileged member (nobody, in the spool's group): the daemon made the
    spool sticky, so renaming rejected/ fails; a planted link is moved to rejected/ as a link."""
    proc, d, _sock, _, spool = hostile
    assert stat.S_IMODE(os.stat(spool).st_mode) & stat.S_ISVTX  # made sticky by the daemon
    code = ("import os,sys\n"
            "sp=sys.argv[1]\n"
            "try:\n    os.rename(sp+'/rejected', sp+'/r.mine'); print('renamed')\n"
            "except OSError as e: print('refused', e.errno)\n"
            "os.symlink(sys.argv[2], sp+'/member.vtx'); print('planted')\n")
    out, err = _unprivileged(code, str(spool), str(d / "lib")).communicate(timeout=30)
    assert out.split() == ["refused", str(errno.EPERM), "planted"], (out, err)
    deadline = time.monotonic() + 20
    while os.path.lexists(spool / "member.vtx") and time.monotonic() < deadline:
        time.sleep(0.1)
    assert os.path.islink(spool / "rejected" / "member.vtx") and not os.path.islink(spool / "rejected")
    assert proc.poll() is None


def test_client_refuses_an_impostor_holding_the_socket(tmp_path):
    """Item 3: another user binds the socket's name in a sticky directory; root's client sees
    who holds it (SO_PEERCRED) and sends nothing."""
    shared = _open_dir("hostd-sticky-", 0o1777)
    path = str(shared / "hostd.sock")
    code = ("import socket,sys\n"
            "s=socket.socket(socket.AF_UNIX); s.bind(sys.argv[1]); s.listen(1); print('ready', flush=True)\n"
            "s.settimeout(20); c,_=s.accept(); c.settimeout(2); got=b''\n"
            "try:\n    while True:\n        b=c.recv(65536)\n        if not b: break\n        got+=b\n"
            "        if len(got)>4:\n"
            "            c.sendall(b'{\"ok\": true, \"name\": \"x\", \"sha256\": \"0\"}\\n'); break\n"
            "except OSError: pass\n"
            "print(len(got), flush=True)\n")
    imp = _unprivileged(code, path)
    try:
        assert imp.stdout.readline().strip() == "ready", imp.stderr.read()
        with pytest.raises(ClientError, match=r"refusing to talk to .*uid 65534"):
            request(path, {"cmd": "send", "name": "x", "size": 5}, b"hello")
        out, _ = imp.communicate(timeout=20)
        assert out.split()[-1] == "0"  # the impostor received nothing
    finally:
        if imp.poll() is None:
            imp.kill()
        import shutil

        shutil.rmtree(shared, ignore_errors=True)


def _drip_code() -> str:
    return ("import socket,sys,threading,time\n"
            "path,n,period,dur=sys.argv[1],int(sys.argv[2]),float(sys.argv[3]),float(sys.argv[4])\n"
            "end=time.monotonic()+dur\n"
            "def drip():\n"
            "    while time.monotonic()<end:\n"
            "        s=socket.socket(socket.AF_UNIX)\n"
            "        try:\n"
            "            s.connect(path)\n"
            "            while time.monotonic()<end:\n"
            "                s.send(b'{'); time.sleep(period)\n"
            "        except OSError: time.sleep(period)\n"
            "        finally: s.close()\n"
            "ts=[threading.Thread(target=drip) for _ in range(n)]\n"
            "[t.start() for t in ts]; [t.join() for t in ts]\n")


@pytest.mark.parametrize("who", ["same user", "another user"])
def test_drip_clients_do_not_lock_out_a_prompt_client(hostile, who):
    """Item 4: 16 clients that send one byte every 2 s (as many as max_clients) hold every
    handler on the old code; a client that sends its request at once is served every time:
    the slowest sender is evicted (same user), or a user's share is max_clients // 4."""
    proc, _d, sock, _, _ = hostile
    args = [sock, "16", "2.0", "8"]
    if who == "another user":
        drip = _unprivileged(_drip_code(), *args)
    else:
        drip = subprocess.Popen([sys.executable, "-c", _drip_code(), *args])
    try:
        time.sleep(2.5)  # every dripper connected and older than the eviction age
        served = []
        for _ in range(15):
            try:
                served.append(request(sock, {"cmd": "status"}, timeout_s=5)["ok"])
            except ClientError as e:
                served.append(str(e))
            time.sleep(0.2)
        assert served == [True] * 15, served
    finally:
        drip.kill()
        drip.wait()
    assert proc.poll() is None


def _hostile_v2(n: int, fmax_mhz: int) -> bytes:
    """A v2 stream of a few dozen bytes whose header promises N = n (all zero indices but one)."""
    from hostd.codec.stream import v2

    ig = v2.IntGeometry(n, 500_000, 50_000, fmax_mhz)
    c = np.zeros(ig.n_keep)
    c[0] = 1.0
    return v2.encode_coefficients(c, ig, thresholds.default_curve(), method="quant", levels=2)


def test_tiny_streams_that_decode_huge_are_refused_from_the_header(hostile):
    """Item 5: 16 concurrent uploads of a 33-byte stream with N = 2^22, N' ~ 4.2 million: refused
    from the header before anything is decoded; the daemon's peak memory does not move."""
    proc, _d, sock, _, _ = hostile
    data = _hostile_v2(1 << 22, 49_999_000)
    assert len(data) < 64 and vtx.decode(data).n_keep > 4_000_000
    hwm0 = _vm_kib(proc.pid, "VmHWM")
    replies: list = []

    def up() -> None:
        try:
            _retry_busy(lambda: request(sock, {"cmd": "send", "name": "huge", "size": len(data)}, data))
            replies.append("accepted")
        except ClientError as e:
            replies.append(str(e))

    t0 = time.monotonic()
    ts = [threading.Thread(target=up) for _ in range(16)]
    for t in ts:
        t.start()
    for t in ts:
        t.join(60)
    assert len(replies) == 16 and all("library.max_n" in r for r in replies), replies[:2]
    assert time.monotonic() - t0 < 10
    # each decode of it allocates ~70 MB (17 B per coefficient): one would show
    assert _vm_kib(proc.pid, "VmHWM") - hwm0 < 30_000
    assert proc.poll() is None


def test_concurrent_decodes_stay_within_the_decode_budget(tmp_path):
    """Item 5, the budget: with limits that admit N' = 2^20, 16 threads decoding such a stream
    at once together stay within DECODE_BUDGET_BYTES (decode slots), measured by tracemalloc."""
    import tracemalloc

    from hostd.service import library as libmod

    data = _hostile_v2(1 << 21, 25_000_000)
    lib = Library(tmp_path / "lib", 4096, max_n=1 << 21, max_n_keep=1 << 20)
    assert lib.decode_slots == libmod.DECODE_BUDGET_BYTES // (libmod.DECODE_BYTES_PER_COEFF << 20) == 2
    lib.decode(data)
    tracemalloc.start()
    one = lib.decode(data)
    single = tracemalloc.get_traced_memory()[1]
    del one
    tracemalloc.reset_peak()
    ts = [threading.Thread(target=lib.decode, args=(data,)) for _ in range(16)]
    for t in ts:
        t.start()
    for t in ts:
        t.join(60)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak <= lib.decode_slots * single * 1.2 + (1 << 20), (peak, single)
    assert peak <= libmod.DECODE_BUDGET_BYTES


def test_full_disk_quality_rows_are_written_once_space_returns(hostile):
    """Item 6: the quality database's filesystem (a real 2 MB tmpfs) is full while streams are
    accepted; their rows wait in the pending queue and are all written once space returns."""
    proc, d, sock, mounted, _ = hostile
    if not mounted:
        pytest.skip("needs root to mount a small tmpfs")
    filler = d / "qfs" / "filler"
    fd = os.open(filler, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    try:  # to the last byte: the quality log's -wal is bounded now, so any slack would take rows
        for chunk in (65536, 4096, 512, 1):
            try:
                while True:
                    os.write(fd, b"\0" * chunk)
            except OSError as e:
                assert e.errno == errno.ENOSPC
    finally:
        os.close(fd)
    assert os.statvfs(d / "qfs").f_bavail == 0, "the tmpfs is not full"
    bodies = _streams(d, 6)
    names = [f"full{i}" for i in range(6)]
    for name, body in zip(names, bodies, strict=True):
        assert request(sock, {"cmd": "send", "name": name, "size": len(body)}, body)["ok"]
    from tests.daemon_helpers import wait_for

    def written() -> set:
        return set(names) & {r["name"] for r in request(sock, {"cmd": "quality"})["rows"]}

    # each row written or pending, none in flight: a row may still land in the -wal pages the log
    # kept (written, not lost); the rest wait in the pending queue (test_quality_full_disk.py
    # holds that path on a disk full from the start)
    wait_for(lambda: len(written()) + request(sock, {"cmd": "status"})["quality_pending"] == len(names),
             60, "every row written or pending")
    filler.unlink()
    wait_for(lambda: written() == set(names), 60, "the pending quality rows")
    assert request(sock, {"cmd": "status"})["quality_pending"] == 0
    assert proc.poll() is None


def _huge_step_stream() -> bytes:
    """A valid v2 quant stream whose step is 1e300: finite coefficients of ~1e300 µm."""
    from hostd.codec.stream import v2

    ig = v2.IntGeometry(100, 500_000, 50_000, 10_000_000)  # N' = 10
    c = np.zeros(ig.n_keep)
    c[:3] = (1.0, -1.0, 0.5)
    data = v2.encode_coefficients(c, ig, thresholds.default_curve(), method="quant", levels=4)
    body = data[:-2]  # CRC-16
    step = struct.pack("<d", vtx.decode(data).step_um)
    assert body.count(step) == 1
    body = body.replace(step, struct.pack("<d", 1e300))
    return body + v2._crc(body)


def test_huge_coefficients_are_refused_at_intake(daemon):
    """Item 7: a 30-odd-byte stream with quant step 1e300 decodes to finite coefficients far
    beyond the display's travel: refused at intake with the reason, never stored or played."""
    proc, d, sock = daemon
    data = _huge_step_stream()
    s = vtx.decode(data)
    assert len(data) < 48 and np.all(np.isfinite(s.coefficients)) and np.max(np.abs(s.coefficients)) > 1e299
    with pytest.raises(ClientError, match=r"travel.*output\.travel_um"):
        request(sock, {"cmd": "send", "name": "square", "size": len(data)}, data)
    assert "square" not in request(sock, {"cmd": "list"})["textures"]
    with pytest.raises(ClientError, match="no texture"):
        request(sock, {"cmd": "select", "name": "square"})
    # one stored before the limit existed (put straight into the library) is not played either
    (d / "lib" / "old-square.vtx").write_bytes(data)
    with pytest.raises(ClientError, match="travel"):
        request(sock, {"cmd": "select", "name": "old-square"})
    (d / "lib" / "old-square.vtx").unlink()
    assert proc.poll() is None


def test_names_cannot_forge_log_lines(daemon):
    """Item 8: a name with a newline is refused at intake and, in the log, escaped."""
    proc, d, sock = daemon
    good = _streams(d, 1)[0]
    forged = "x\n2026-11-23 12:00:00,000 hostd INFO FORGED accepted"
    with pytest.raises(ClientError) as refused:
        request(sock, {"cmd": "send", "name": forged, "size": len(good)}, good)
    (d / "spool" / "y\nFORGED2 line.vtx").write_bytes(good)
    deadline = time.monotonic() + 20
    while os.path.lexists(d / "spool" / "y\nFORGED2 line.vtx") and time.monotonic() < deadline:
        time.sleep(0.1)
    time.sleep(0.2)
    lines = (d / "log.txt").read_text().splitlines()
    assert not [ln for ln in lines if "FORGED" in ln and not ln.startswith(lines[0][:2])]
    assert any("\\nFORGED2" in ln for ln in lines)  # the spool name, escaped
    assert not any(ln.startswith(("2026-11-23 12:00", "FORGED")) for ln in lines)
    assert "control characters" in str(refused.value)
    assert proc.poll() is None


def test_dir_fd_reader_and_writer_follow_no_link(tmp_path):
    """The library's and spool's file operations (hostd.fileio: open_dir, read_regular_at,
    write_at): a link is replaced, never written through or read; FIFOs and devices are refused
    without blocking; the size is checked before reading; an open directory must be ours."""
    from hostd.fileio import NotRegular, open_dir, read_regular_at, write_at

    victim = tmp_path / "victim"
    victim.write_bytes(b"precious")
    d = tmp_path / "d"
    fd = open_dir(d, "test", create_mode=0o750)
    try:
        os.symlink(victim, d / "x.vtx")
        with pytest.raises(NotRegular):
            read_regular_at(fd, "x.vtx", 100)
        write_at(fd, "x.vtx", b"new", mode=0o640)
        assert victim.read_bytes() == b"precious" and (d / "x.vtx").read_bytes() == b"new"
        assert not os.path.islink(d / "x.vtx") and stat.S_IMODE(os.stat(d / "x.vtx").st_mode) == 0o640
        os.mkfifo(d / "f.vtx")
        os.symlink("/dev/zero", d / "z.vtx")
        for name in ("f.vtx", "z.vtx"):
            with pytest.raises(NotRegular):
                read_regular_at(fd, name, 100)
        (d / "big.vtx").write_bytes(b"\0" * 101)
        with pytest.raises(HostdError, match="max_stream_bytes"):
            read_regular_at(fd, "big.vtx", 100)
        assert [n for n in os.listdir(d) if n.endswith(".tmp")] == []
    finally:
        os.close(fd)
    os.symlink(d, tmp_path / "link")
    with pytest.raises(HostdError, match="symbolic link"):
        open_dir(tmp_path / "link", "test")
    os.chmod(d, 0o777)
    with pytest.raises(HostdError, match="other users"):
        open_dir(d, "test")
    os.chmod(d, 0o770)
    os.close(open_dir(d, "test", others_may_write=True))  # ours and group-writable: made sticky
    assert os.stat(d).st_mode & stat.S_ISVTX
