"""hostd corpus: nothing another local account or a shared file can make it do. A local Dask
cluster refuses a Client of another uid and keeps no HTTP server; a sweep settings file names
settings, never code; a store is opened as data (no view, no trigger, no file made on read, a
schema version, a bounded -wal)."""

from __future__ import annotations

import json
import os
import shutil
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
FIX = "tests.corpus_codec_fixture"


def _env(**extra) -> dict:
    return {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""), **extra}


# ----------------------------------------------------------------------------- Dask on loopback


def _tree(pid: int) -> set[int]:
    """pid and every descendant (from /proc/*/stat)."""
    parent = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                parent[int(d.name)] = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                pass
    out, grew = {pid}, True
    while grew:
        new = {p for p, pp in parent.items() if pp in out} - out
        out |= new
        grew = bool(new)
    return out


def _listeners(pids: set[int]) -> list[int]:
    """TCP ports in LISTEN owned by one of `pids` (ss -ltnpH)."""
    out = subprocess.run(["ss", "-ltnpH"], capture_output=True, text=True, check=True).stdout
    ports = []
    for line in out.splitlines():
        owners = {int(t.split("=")[1].rstrip(",)")) for t in line.split() for t in t.split(",")
                  if t.startswith("pid=")}
        if owners & pids:
            ports.append(int(line.split()[3].rsplit(":", 1)[1]))
    return sorted(ports)


_ATTACK = r"""
import json, os, socket, sys, tempfile
os.chdir(tempfile.gettempdir())
res = {"uid": os.getuid(), "http": [], "client": []}
for port in map(int, sys.argv[1:]):
    s = socket.create_connection(("127.0.0.1", port), timeout=3)
    s.settimeout(3)
    try:
        s.sendall(b"GET /info/main/workers.html HTTP/1.0\r\nHost: 127.0.0.1\r\n\r\n")
        head = s.recv(16)
    except OSError:
        head = b""
    s.close()
    if head.startswith(b"HTTP/"):
        res["http"].append(port)
from distributed import Client
from distributed.security import Security
mine = Security.temporary()  # a certificate of the attacker's own: not the cluster's
for port in map(int, sys.argv[1:]):
    for addr, sec in ((f"tcp://127.0.0.1:{port}", None), (f"tls://127.0.0.1:{port}", mine)):
        try:
            c = Client(addr, timeout="3s", security=sec)
        except Exception:
            continue
        try:
            res["client"].append([addr, c.run(os.getuid)])
        except Exception as e:
            res["client"].append([addr, repr(e)[:80]])
        c.close()
print(json.dumps(res))
"""


def _as_nobody() -> list[str]:
    if os.getuid() != 0 or not shutil.which("setpriv") or not shutil.which("ss"):
        pytest.skip("needs root (to act as another uid), setpriv and ss")
    cmd = ["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups", sys.executable]
    probe = subprocess.run([*cmd, "-c", "import distributed"], capture_output=True, env=_env())
    if probe.returncode != 0:
        pytest.skip("uid 65534 cannot run this Python with distributed")
    return cmd


def test_local_dask_cluster_refuses_another_uid_and_keeps_no_http_server(tmp_path):
    """The run's every listener (scheduler, nannies, workers) refuses a Client of uid 65534, over
    tcp:// and over tls:// with a certificate of its own, and none of them answers HTTP."""
    pytest.importorskip("distributed")
    pytest.importorskip("cryptography")
    nobody = _as_nobody()
    db = tmp_path / "r.sqlite"
    gate = tmp_path / "gate"
    gate.mkdir()
    p = subprocess.Popen([sys.executable, "-m", "hostd", "corpus", "run", "synthetic:wood:1-2",
                          "--codec", f"{FIX}:Gated", "--length-mm", "2", "--no-spqi", "--dask", "local",
                          "--workers", "2", "--no-progress", "-o", str(db)],
                         env=_env(HOSTD_TEST_GATE=f"{gate}:1"), cwd=ROOT,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        deadline = time.monotonic() + 120
        while not (gate / "pass-0").exists() and p.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)  # a job has started: the cluster is up, its HTTP servers closed
        assert p.poll() is None, p.stderr.read()
        ports = _listeners(_tree(p.pid))
        assert len(ports) >= 5, ports  # scheduler, 2 nannies, 2 workers
        out = subprocess.run([*nobody, "-c", _ATTACK, *map(str, ports)], capture_output=True, text=True,
                             env=_env(), timeout=120)
        assert out.returncode == 0, out.stderr[-2000:]
        res = json.loads(out.stdout.strip().splitlines()[-1])
        assert res["uid"] == 65534
        assert res["client"] == [] and res["http"] == [], res
    finally:
        (gate / "open").touch()
        try:
            p.communicate(timeout=120)
        finally:
            if p.poll() is None:
                os.killpg(p.pid, 9)
    assert p.returncode == 0


# ----------------------------------------------------------------------------- no code run by data


def test_a_sweep_file_names_settings_never_a_codec_to_load(tmp_path, capsys):
    """`[codec."payload.py:X"]` in a sweep file, with no --codec or another --codec: a one-line
    error and payload.py is never imported; a sweep keyed by a --codec's name gives its settings."""
    from hostd.cli import main
    from hostd.corpus import run as crun

    marker = tmp_path / "ran"
    payload = tmp_path / "payload.py"
    payload.write_text(f"open({str(marker)!r}, 'w').close()\n"
                       "from tests.corpus_codec_fixture import uniform as X\n")
    sweep = tmp_path / "sweep.toml"
    sweep.write_text(f'[codec."{payload}:X"]\nsettings = [{{step_um = 1.0}}]\n')
    db = tmp_path / "r.sqlite"
    base = ["corpus", "run", "synthetic:wood:1", "--length-mm", "2", "--no-spqi", "--workers", "1",
            "--no-progress", "-o", str(db), "--sweep", str(sweep)]
    for extra in ([], ["--codec", f"{FIX}:uniform"]):
        assert main([*base, *extra]) == 2
        err = capsys.readouterr().err
        assert "not given with --codec" in err and str(payload) in err and len(err.strip().splitlines()) == 1
        assert not marker.exists() and not db.exists()
    with pytest.raises(crun.HostdError, match="not given with --codec"):  # the API alike
        crun.make_plan([f"{FIX}:uniform"], settings={f"{payload}:X": [{"step_um": 1.0}]})
    assert not marker.exists()
    # keyed by the codec's own name: the settings of the codec named on the command line
    sweep.write_text('[codec."uniform-zlib"]\nsettings = [{step_um = 1.0}, {step_um = 0.5}]\n')
    assert main([*base, "--codec", f"{FIX}:uniform"]) == 0, capsys.readouterr().err
    st = sqlite3.connect(db)
    assert sorted(r[0] for r in st.execute("SELECT setting FROM results")) == ['{"step_um":0.5}',
                                                                              '{"step_um":1.0}']
    st.close()
