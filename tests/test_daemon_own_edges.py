"""The daemon's own edges: a start-up backlog of streams without a quality row is queued by name in a
bounded queue (the daemon's memory does not grow with it) and every row is still written; a play
that cannot be recorded (disk full) is kept pending like a quality row, across a restart too."""

from __future__ import annotations

import hashlib
import sqlite3
import subprocess
import threading
import tracemalloc
from pathlib import Path

from hostd.cli import main
from hostd.service import qualitylog
from hostd.service.config import load
from tests.daemon_helpers import wait_for

CFG = ('[device]\ntransport = "sim"\n[library]\ndir = "lib"\nspool = "spool"\n'
       '[control]\nsocket = "run/hostd.sock"\ngroup = ""\n[quality]\ndb = "{db}"\n')


def _daemon(tmp_path: Path, db: str = "q.sqlite", quality: str = ""):
    """A Daemon whose pump is never started: its quality worker and start-up scan run in this
    process's threads. quality: more [quality] keys."""
    from hostd.service.daemon import Daemon

    cfg = tmp_path / "hostd.toml"
    cfg.write_text(CFG.format(db=db) + quality)
    return Daemon(load(cfg))


def _close(d) -> None:
    d.stop()
    for c in (d.conn, d.child_conn):
        c.close()


def _big_stream(tmp_path: Path) -> bytes:
    """A 56 kB stream (32-bit values, N' = 16,000): a backlog of them is megabytes."""
    src = tmp_path / "big.vtx"
    assert main(["encode", "synthetic:sandpaper:1", "-o", str(src), "--method", "cut", "--b0-db", "-60",
                 "--fmax-hz", "40000", "--value-bits", "32"]) == 0
    return src.read_bytes()


def _rows(db: Path) -> set[str]:
    con = qualitylog.connect_readonly(db)
    try:
        return {r[0] for r in con.execute("SELECT name FROM streams")}
    finally:
        con.close()


def test_the_start_up_backlog_is_queued_by_name_in_a_bounded_queue_and_every_row_is_written(tmp_path):
    """100 stored 56-kB streams without a row (5.6 MB): the look for them at start-up holds at most
    QUALITY_QUEUE_MAX entries, each a name (no bytes), and waits for room; the memory it takes is
    that of a stream or two being read, not the backlog's. Then the worker writes all 100 rows."""
    from hostd.service.daemon import QUALITY_QUEUE_MAX

    body = _big_stream(tmp_path)
    lib = tmp_path / "lib"
    lib.mkdir()
    n = 100
    for i in range(n):
        (lib / f"t{i}.vtx").write_bytes(body)
    d = _daemon(tmp_path)
    try:
        tracemalloc.start()
        try:
            # what one stream costs the look (read, hash, decode): the compiled decoder's or, without
            # a C compiler, the reference's, whose temporaries are larger
            base = tracemalloc.get_traced_memory()[0]
            tracemalloc.reset_peak()
            lib_ = d.quality.library
            data = lib_.read(next(iter(lib_.names())))
            hashlib.sha256(data).hexdigest()
            lib_.decode(data)
            del data
            one = tracemalloc.get_traced_memory()[1] - base
            base = tracemalloc.get_traced_memory()[0]
            tracemalloc.reset_peak()
            scan = threading.Thread(target=d.rescore_missing, daemon=True)
            scan.start()
            # nobody scores yet: the scan fills the queue and waits (unbounded: it queues all 100)
            wait_for(lambda: d.quality_q.full() or not scan.is_alive(), 60, "the scan to fill the queue")
            peak = tracemalloc.get_traced_memory()[1] - base
        finally:
            tracemalloc.stop()
        held = list(d.quality_q.queue)
        assert scan.is_alive() and len(held) == QUALITY_QUEUE_MAX < n, len(held)
        assert all(item[3] is None for item in held), "the queue holds the streams' bytes"
        # a stream or two read and decoded at a time (its N' = 16,000 coefficients: 128 kB, and the
        # decoder's temporaries), never the backlog (5.6 MB)
        why = f"{peak / 1e6:.2f} MB traced, one stream {one / 1e6:.2f} MB"
        assert peak < 2 * one and peak < n * len(body) / 4, why
        worker = threading.Thread(target=d.quality_worker, daemon=True)
        worker.start()
        wait_for(lambda: len(_rows(tmp_path / "q.sqlite")) == n, 60, "the 100 rows")
        scan.join(10)
        assert not scan.is_alive()
        con = qualitylog.connect_readonly(tmp_path / "q.sqlite")
        try:
            shas = {r[0] for r in con.execute("SELECT sha256 FROM streams")}
        finally:
            con.close()
        assert shas == {hashlib.sha256(body).hexdigest()}
    finally:
        _close(d)


def _plays(db: Path) -> list[tuple]:
    con = qualitylog.connect_readonly(db)
    try:
        return con.execute("SELECT name, started_at FROM plays ORDER BY id").fetchall()
    finally:
        con.close()


def _play(d, name: str, started_at: float) -> None:
    """A play of `name` from started_at to now, ended as a select or stop ends it."""
    d.play = (name, "ab" * 32, started_at, d.counters())
    d.end_play()


def _full(path):
    raise sqlite3.OperationalError("database or disk is full")


def test_a_play_that_cannot_be_recorded_on_a_full_disk_is_kept_pending_and_written(tmp_path, monkeypatch):
    """The quality log's file system (a 1 MiB tmpfs) full: a play is kept pending, not dropped, and
    written once 64 kB are free; full again at a stop, it is kept in the pending-rows file (in the
    library's directory: the database's file system is the full one) and the next start writes it,
    once (a play already in the log is not added twice)."""
    from tests.test_quality_full_disk import FREED_B, _fill, _free, _mount_tmpfs

    fs = tmp_path / "qfs"
    _mount_tmpfs(fs)
    db = fs / "q.sqlite"
    try:
        d = _daemon(tmp_path, "qfs/q.sqlite")
        files = _fill(fs)
        _play(d, "wood", 1000.0)  # (its own connection: no -wal or -shm can be made)
        assert len(d.plays_pending) == 1 and _plays(db) == []
        _free(files, FREED_B)
        worker = threading.Thread(target=d.quality_worker, daemon=True)
        worker.start()  # the pending play is retried with the quality rows
        try:
            wait_for(lambda: _plays(db) == [("wood", 1000.0)], 30, "the pending play written")
        finally:
            _close(d)
            worker.join(10)
        # full at a stop: kept in the pending-rows file. (The log's connections fail as on a full
        # disk: a -wal left from the last writer may hold a row's frames on a real one)
        d = _daemon(tmp_path, "qfs/q.sqlite")
        files += _fill(fs)
        with monkeypatch.context() as m:
            m.setattr(qualitylog, "connect", _full)
            _play(d, "wood", 2000.0)
            assert len(d.plays_pending) == 1
            d._stop_deadline = 0.0  # (no retry at the stop: the disk stays full)
            _close(d)
            d.quality_worker()  # stopped: one try, then the pending-rows file
        kept = [p for p in qualitylog.pending_paths(db, tmp_path / "lib") if p.exists()]
        assert [(r["name"], r["started_at"]) for r in qualitylog.load_pending(kept[0])] == [("wood", 2000.0)]
        _free(files, FREED_B)
        d = _daemon(tmp_path, "qfs/q.sqlite")
        assert len(d.plays_pending) == 1 and not d.quality_pending
        worker = threading.Thread(target=d.quality_worker, daemon=True)
        worker.start()
        try:
            wait_for(lambda: not kept[0].exists(), 30, "the pending-rows file written and removed")
            # kept again (a stop before the file was removed): written once
            qualitylog.save_pending(kept[0], [{"kind": "play", "name": "wood", "sha256": "ab" * 32,
                                               "started_at": 2000.0, "ended_at": 2001.0, "device_s": 0.0,
                                               "played_s": 0.0, "played_fraction": None, "underruns": 0}])
        finally:
            _close(d)
            worker.join(10)
        d = _daemon(tmp_path, "qfs/q.sqlite")
        worker = threading.Thread(target=d.quality_worker, daemon=True)
        worker.start()
        try:
            wait_for(lambda: not kept[0].exists(), 30, "the pending-rows file written again")
        finally:
            _close(d)
            worker.join(10)
        assert _plays(db) == [("wood", 1000.0), ("wood", 2000.0)]
    finally:
        subprocess.run(["umount", "-l", str(fs)], capture_output=True)
