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

from hostd.procstat import descendants

ROOT = Path(__file__).resolve().parent.parent
FIX = "tests.corpus_codec_fixture"


def _env(**extra) -> dict:
    return {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""), **extra}


# ----------------------------------------------------------------------------- Dask on loopback


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
import signal
def alarm(*_):
    raise TimeoutError
signal.signal(signal.SIGALRM, alarm)
for port in sorted(set(map(int, sys.argv[1:])) - set(res["http"])):
    for addr, sec in ((f"tcp://127.0.0.1:{port}", None), (f"tls://127.0.0.1:{port}", mine)):
        signal.alarm(6)  # (on an unprotected cluster a Client on a worker's port may wait)
        try:
            c = Client(addr, timeout="3s", security=sec)
        except Exception:
            signal.alarm(0)
            continue
        try:
            res["client"].append([addr, c.run(os.getuid)])
        except BaseException as e:
            res["client"].append([addr, repr(e)[:80]])
        signal.alarm(0)
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
        ports = _listeners(descendants(p.pid))
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


# ----------------------------------------------------------------------------- the store is data


def _corpus(*args, timeout=60):
    return subprocess.run([sys.executable, "-m", "hostd", "corpus", *args], capture_output=True, text=True,
                          env=_env(), cwd=ROOT, timeout=timeout)


RUN = ["run", "synthetic:wood:1", "--codec", f"{FIX}:uniform", "--length-mm", "2", "--no-spqi",
       "--workers", "1", "--no-progress"]


def _one_line_refusal(r, says: str) -> None:
    assert r.returncode == 2 and says in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr


def test_a_store_with_a_view_or_a_trigger_is_refused_at_once(tmp_path):
    """An endless recursive view named `results` (report and run spun at 100 % CPU for ever), and
    a trigger that deletes every row written (run said "rows written" and kept none)."""
    view = tmp_path / "view.sqlite"
    c = sqlite3.connect(view)
    from hostd.corpus.jobs import COLUMNS_V1

    cols = ", ".join(f'x AS "{c}"' for c in COLUMNS_V1)  # the columns of a store: it looks like one
    c.execute(f"CREATE VIEW results AS WITH RECURSIVE n(x) AS (SELECT 1 UNION ALL SELECT x + 1 FROM n) "
              f"SELECT {cols} FROM n")
    c.close()
    for args in (["report", str(view), "-o", str(tmp_path / "rep")], [*RUN, "-o", str(view)],
                 ["export", str(view), "-o", str(tmp_path / "x.csv")]):
        _one_line_refusal(_corpus(*args, timeout=30), "view results")
    trig = tmp_path / "trig.sqlite"
    assert _corpus(*RUN, "-o", str(trig)).returncode == 0
    c = sqlite3.connect(trig)
    c.execute("CREATE TRIGGER eat AFTER INSERT ON results BEGIN DELETE FROM results WHERE key = new.key; END")
    c.execute("DELETE FROM results")
    c.commit()
    c.close()
    r = _corpus(*RUN, "-o", str(trig))
    _one_line_refusal(r, "trigger eat")
    assert "rows written" not in r.stdout


def test_reading_never_creates_a_file_and_other_databases_are_refused(tmp_path):
    from hostd.service import qualitylog

    missing = tmp_path / "nope.sqlite"
    for args in (["report", str(missing), "-o", str(tmp_path / "rep")],
                 ["export", str(missing), "-o", str(tmp_path / "x.csv")]):
        _one_line_refusal(_corpus(*args), "no corpus store")
        assert not missing.exists()
    log = tmp_path / "quality.sqlite"
    qualitylog.connect(log).close()
    before = log.read_bytes()
    for args in (["report", str(log), "-o", str(tmp_path / "rep")], [*RUN, "-o", str(log)]):
        _one_line_refusal(_corpus(*args), "not a corpus store")
    assert log.read_bytes() == before and not (tmp_path / "rep").exists()
    junk = tmp_path / "junk.sqlite"
    junk.write_bytes(os.urandom(4096))
    _one_line_refusal(_corpus("report", str(junk), "-o", str(tmp_path / "rep")), "cannot open")


def test_a_store_records_its_version_and_one_of_a_newer_hostd_is_refused(tmp_path):
    from hostd.corpus import store

    db = tmp_path / "r.sqlite"
    assert _corpus(*RUN, "-o", str(db)).returncode == 0
    c = sqlite3.connect(db)
    assert c.execute("PRAGMA application_id").fetchone()[0] == store.APPLICATION_ID
    assert c.execute("PRAGMA user_version").fetchone()[0] == store.VERSION >= 2
    c.execute(f"PRAGMA user_version={store.VERSION + 1}")
    c.close()
    _one_line_refusal(_corpus("report", str(db), "-o", str(tmp_path / "rep")), "written by a newer hostd")


def test_a_store_of_the_previous_hostd_is_migrated_in_place_and_its_rows_still_count(tmp_path):
    """tests/data/corpus_v1/store-v1.sqlite was written by the hostd before stores had versions
    (`hostd corpus run tests/data/corpus_v1/bumps.txt --codec tests.corpus_codec_fixture:uniform
    --no-spqi --workers 1`): opened, it gains the new columns and keeps its rows, re-keyed, so the
    same command finds all 5 of them there."""
    data = ROOT / "tests" / "data" / "corpus_v1"
    db = tmp_path / "old.sqlite"
    shutil.copy(data / "store-v1.sqlite", db)
    r = _corpus("run", str(data / "bumps.txt"), "--codec", f"{FIX}:uniform", "--no-spqi", "--workers", "1",
                "--no-progress", "-o", str(db), "--json")
    assert r.returncode == 0, r.stderr
    summ = json.loads(r.stdout)
    assert summ["skipped"] == 5 and summ["written"] == 0
    c = sqlite3.connect(db)
    assert [tuple(x) for x in c.execute("SELECT run, COUNT(*) FROM results GROUP BY run")] == [(0, 5)]
    assert {json.loads(s)["spqi"] for (s,) in c.execute("SELECT scoring FROM results")} == {False}
    c.close()


def test_the_stores_write_ahead_log_stays_bounded(tmp_path):
    """60 transactions of 100 rows: the -wal stays near one transaction's size (it grew to the
    whole run's, ~3 MB, up to SQLite's default checkpoint at 4 MB)."""
    from hostd.corpus import jobs
    from hostd.corpus.store import Store
    from hostd.service.qualitylog import JOURNAL_LIMIT_BYTES

    db = tmp_path / "r.sqlite"
    st = Store(db)
    wal = Path(str(db) + "-wal")
    sizes = []
    for t in range(60):
        rows = [{**dict.fromkeys(jobs.COLUMNS), "key": f"{t}-{i}", "texture": "t" * 200, "loader": "x" * 200,
                 "bytes": i} for i in range(100)]
        assert st.write(rows) == 100
        sizes.append(wal.stat().st_size)
    one = sizes[0]  # one transaction's pages
    assert max(sizes) <= JOURNAL_LIMIT_BYTES + 2 * one, sizes
    st.close()
