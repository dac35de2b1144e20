"""The quality log as the labs read it: `hostd quality` opens the service's database read-only (a
member of group hostd, daemon stopped or running), `--since 1h`, ISO 8601 times with the zone, and
per texture played what was delivered (time played, played fraction, underruns) with its row."""

from __future__ import annotations

import csv
import io
import json
import os
import shutil
import tempfile
import time
from pathlib import Path

import pytest

from hostd.cli import main
from hostd.service import qualitylog
from hostd.service.cli import parse_since
from tests.test_daemon import daemon, stream  # noqa: F401  (the fixture)

NOBODY = 65534


def _row(name: str, t: float) -> dict:
    return {"sha256": name * 4, "name": name, "received_at": t, "scored_at": t + 0.5, "bytes": 40,
            "method": "quant", "levels": 8, "b0_db": None, "n": 1000, "n_keep": 100, "length_mm": 10.0,
            "speed_mm_s": 50.0, "curve_id": "00", "ratio_coeffs": 0.1, "ratio_profile": 0.01,
            "ip": 0.01, "ia": 0.02, "iobj": 0.015, "a": 0.581, "b": 0.464}


def _read_as(uid: int, gid: int, db: Path) -> list | str:
    """query() in a child process running as uid:gid (no other groups): the reader's rights."""
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:  # pragma: no cover - child
        os.close(r)
        try:
            os.setgroups([])
            os.setgid(gid)
            os.setuid(uid)
            con = qualitylog.connect_readonly(db)
            out = json.dumps([x["name"] for x in qualitylog.query(con)])
        except Exception as e:
            out = json.dumps(f"{type(e).__name__}: {e}")
        os.write(w, out.encode())
        os._exit(0)
    os.close(w)
    data = b""
    while chunk := os.read(r, 65536):
        data += chunk
    os.close(r)
    os.waitpid(pid, 0)
    return json.loads(data)


@pytest.mark.skipif(os.geteuid() != 0, reason="needs root to act as another user")
def test_a_group_member_reads_the_log_read_only_daemon_stopped_and_running():
    top = Path(tempfile.mkdtemp(prefix="hostd-ro-"))  # pytest's tmp_path is 0700 up the tree
    os.chmod(top, 0o755)
    d = top / "lib"  # as tmpfiles makes /var/lib/hostd: 0750, owner the daemon, group hostd
    d.mkdir(mode=0o750)
    db = d / "quality.sqlite"
    old = os.umask(0o027)  # the unit's UMask
    try:
        con = qualitylog.connect(db)
        qualitylog.insert(con, _row("a", 1.0))
        con.close()  # the daemon stopped: no -wal, no -shm
        os.chown(d, 0, NOBODY)
        os.chown(db, 0, NOBODY)
        assert not Path(f"{db}-shm").exists()
        assert _read_as(NOBODY, NOBODY, db) == ["a"]  # was: attempt to write a readonly database
        writer = qualitylog.connect(db)  # the daemon running (WAL), with a commit only in the -wal
        qualitylog.insert(writer, _row("b", 2.0))
        for f in d.iterdir():
            os.chown(f, 0, NOBODY)
        assert Path(f"{db}-wal").stat().st_size > 0
        assert _read_as(NOBODY, NOBODY, db) == ["a", "b"]
        writer.close()
        assert _read_as(NOBODY, NOBODY, db) == ["a", "b"]  # checkpointed at close
        got = _read_as(NOBODY + 1, NOBODY + 1, db)  # not a member: a clear message
        assert isinstance(got, str) and "HostdError" in got and "usermod -aG hostd" in got, got
    finally:
        os.umask(old)
        shutil.rmtree(top)


def test_since_takes_durations_iso_dates_and_unix_seconds():
    now = 1_800_000_000.0
    assert parse_since("1h", now) == now - 3600
    assert parse_since("30m", now) == now - 1800
    assert parse_since("2d", now) == now - 2 * 86400
    assert parse_since("1h30m", now) == now - 5400
    assert parse_since("90s", now) == now - 90
    assert parse_since("1700000000", now) == 1_700_000_000.0
    assert parse_since("2026-11-22T10:00:00+00:00") == 1_795_341_600.0
    local = parse_since("2026-11-22")
    import datetime as dt

    assert local == dt.datetime(2026, 11, 22).astimezone().timestamp()
    from hostd.errors import HostdError

    with pytest.raises(HostdError, match=r"30m, 1h, 2d"):
        parse_since("yesterday")


def test_csv_and_json_times_are_iso_8601_with_the_zone(tmp_path, capsys):
    db = tmp_path / "q.sqlite"
    con = qualitylog.connect(db)
    now = time.time()
    qualitylog.insert(con, _row("old", now - 7200))
    qualitylog.insert(con, _row("new", now - 60))
    con.close()
    assert main(["quality", "--db", str(db), "--since", "1h", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert [r["name"] for r in rows] == ["new"]
    import datetime as dt

    t = dt.datetime.fromisoformat(rows[0]["received_at"])
    assert t.tzinfo is not None and abs(t.timestamp() - (now - 60)) < 1e-3
    assert main(["quality", "--db", str(db), "--csv"]) == 0
    rows = list(csv.DictReader(io.StringIO(capsys.readouterr().out)))
    assert [r["name"] for r in rows] == ["old", "new"]
    for r in rows:
        t = dt.datetime.fromisoformat(r["scored_at"])
        assert t.tzinfo is not None and r["scored_at"][-6] in "+-"
    assert {"plays", "played_s", "played_fraction", "underruns"} <= set(rows[0])


def test_what_was_delivered_is_logged_with_the_quality_row(daemon, capsys, monkeypatch):  # noqa: F811
    """Per texture played: the time the device played it from its buffer, its played fraction and
    the underruns it counted, from the device's own counters, next to Iobj."""
    _proc, d, sock = daemon
    from hostd.service.client import request, send_file

    for name in ("w1", "w2"):
        send_file(sock, str(stream(d, name, levels=8 if name == "w1" else 6)), None)
    request(sock, {"cmd": "select", "name": "w1"})
    for _ in range(300):
        if request(sock, {"cmd": "status"})["state"] == "playing":
            break
        time.sleep(0.05)
    time.sleep(1.0)
    before = request(sock, {"cmd": "status"})
    request(sock, {"cmd": "select", "name": "w2"})  # ends w1's play
    after = request(sock, {"cmd": "status"})
    request(sock, {"cmd": "stop"})  # ends w2's play
    for _ in range(100):
        assert main(["quality", "--config", str(d / "hostd.toml"), "--json"]) == 0
        rows = {r["name"]: r for r in json.loads(capsys.readouterr().out)}
        if len(rows) == 2:
            break
        time.sleep(0.1)
    w1, w2 = rows["w1"], rows["w2"]
    assert w1["plays"] == 1 and w2["plays"] == 1
    # the device's own sample counter, between select and the next select
    assert 0.9 * (before["device_samples_played"] / 3000) - 1 < w1["played_s"] \
        <= after["device_samples_played"] / 3000
    assert w1["played_s"] > 0.5 and 0.0 < w1["played_fraction"] <= 1.0
    assert w1["underruns"] == 0 or w1["underruns"] <= after["device_underruns"]
    monkeypatch.setenv("HOSTD_CONFIG", str(d / "hostd.toml"))  # as /etc/hostd/hostd.toml would be
    assert main(["quality"]) == 0  # no --config: the daemon's own config
    out = capsys.readouterr().out
    assert "underruns" in out.splitlines()[0] and "%" in out
    assert main(["status", "--json"]) == 0 and json.loads(capsys.readouterr().out)["library"] == 2
