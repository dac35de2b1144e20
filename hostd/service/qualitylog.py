"""The quality log: one SQLite row per accepted stream (WAL mode, synchronous=FULL).

Rows are written off the real-time path by the daemon's quality worker. A row is committed
before it counts as logged; WAL with synchronous=FULL makes every commit durable across a
kill -9 or power loss, and the daemon re-scores at start-up any stored stream that has no
row yet, so an accepted stream is never left unlogged.

A full disk: the write-ahead log is bounded (journal_size_limit, an automatic checkpoint every
WAL_AUTOCHECKPOINT_PAGES, a checkpoint(TRUNCATE) after a full-disk error), rows are written in
batches of at most BATCH_ROWS per transaction (each commit writes its B-tree pages once, not once
per row), and rows still pending when the daemon stops are kept in the pending-rows file beside
the database (PENDING_SUFFIX), which the next start writes first.
"""

from __future__ import annotations

import json
import os
import sqlite3
import time
import uuid
from pathlib import Path

from hostd.errors import HostdError

SCHEMA = """
CREATE TABLE IF NOT EXISTS streams (
    id INTEGER PRIMARY KEY,
    sha256 TEXT NOT NULL,
    name TEXT NOT NULL,
    received_at REAL NOT NULL,      -- unix time, s
    scored_at REAL NOT NULL,
    bytes INTEGER NOT NULL,
    method TEXT NOT NULL,
    levels INTEGER,
    b0_db REAL,
    n INTEGER NOT NULL,
    n_keep INTEGER NOT NULL,
    length_mm REAL NOT NULL,
    speed_mm_s REAL NOT NULL,
    curve_id TEXT NOT NULL,
    ratio_coeffs REAL NOT NULL,
    ratio_profile REAL NOT NULL,
    ip REAL NOT NULL,
    ia REAL NOT NULL,
    iobj REAL NOT NULL,
    a REAL NOT NULL,
    b REAL NOT NULL,
    calibration TEXT,               -- NAME@ID of the calibration that scored it (NULL: none)
    uuid TEXT,                      -- the row's stable key, written with it (hostd fleet ships by it)
    UNIQUE (name, sha256)   -- one row per stored (name, content); re-sending it adds none
);
CREATE INDEX IF NOT EXISTS streams_received ON streams(received_at);
-- what was delivered: one row per time a texture was played (selected until the next select,
-- stop or shutdown), from the device's own counters (hostd.device.health via the pump)
CREATE TABLE IF NOT EXISTS plays (
    id INTEGER PRIMARY KEY,
    name TEXT NOT NULL,
    sha256 TEXT NOT NULL,
    started_at REAL NOT NULL,       -- unix time, s (host clock)
    ended_at REAL NOT NULL,
    device_s REAL NOT NULL,         -- device clock elapsed while selected, s
    played_s REAL NOT NULL,         -- samples played from the device's buffer / 3 kHz, s (device
                                    -- mode: played_fraction x device_s, the time it rendered)
    played_fraction REAL,           -- the pump's played_fraction at the end (NULL: never ran)
    underruns INTEGER NOT NULL,     -- underrun episodes the device counted meanwhile
    uuid TEXT                       -- the row's stable key, written with it (hostd fleet ships by it)
);
CREATE INDEX IF NOT EXISTS plays_stream ON plays(name, sha256);
"""

COLUMNS = ("id", "sha256", "name", "received_at", "scored_at", "bytes", "method", "levels", "b0_db",
           "n", "n_keep", "length_mm", "speed_mm_s", "curve_id", "ratio_coeffs", "ratio_profile",
           "ip", "ia", "iobj", "a", "b", "calibration")


JOURNAL_LIMIT_BYTES = 16 * 1024  # the -wal is cut back to this when a writer restarts it
WAL_AUTOCHECKPOINT_PAGES = 16   # (SQLite's default, 1000 pages = 4 MB, is never reached on a small disk)
BATCH_ROWS = 16                 # rows per transaction: bounded so that a batch fits in 64 kB free
PENDING_SUFFIX = ".pending"     # rows not written when the daemon stopped, one JSON object per line


def connect(path: str | Path) -> sqlite3.Connection:
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    con = sqlite3.connect(p, timeout=10.0, isolation_level=None)
    con.execute("PRAGMA journal_mode=WAL")
    con.execute("PRAGMA synchronous=FULL")
    con.execute(f"PRAGMA journal_size_limit={JOURNAL_LIMIT_BYTES}")
    con.execute(f"PRAGMA wal_autocheckpoint={WAL_AUTOCHECKPOINT_PAGES}")
    con.executescript(SCHEMA)
    if "calibration" not in _stream_columns(con):  # a log written before calibrations: add it
        con.execute("ALTER TABLE streams ADD COLUMN calibration TEXT")
    _add_uuids(con)
    return con


def _add_uuids(con: sqlite3.Connection) -> None:
    """A log written before rows had a stable key: add the uuid column to streams and plays and
    give every existing row one (the rows of a table in one transaction: all keyed or none, and
    those not keyed are keyed at the next connect). Rows an older hostd wrote since (a downgrade)
    are keyed the same way; a partial index finds them at once."""
    for table in ("streams", "plays"):
        if "uuid" not in {r[1] for r in con.execute(f"PRAGMA table_info({table})")}:
            con.execute("BEGIN IMMEDIATE")
            try:
                if "uuid" not in {r[1] for r in con.execute(f"PRAGMA table_info({table})")}:
                    con.execute(f"ALTER TABLE {table} ADD COLUMN uuid TEXT")
                con.execute("COMMIT")
            except BaseException:
                con.execute("ROLLBACK")
                raise
        con.execute(f"CREATE INDEX IF NOT EXISTS {table}_keyless ON {table}(id) WHERE uuid IS NULL")
        if con.execute(f"SELECT 1 FROM {table} WHERE uuid IS NULL LIMIT 1").fetchone() is None:
            continue
        con.execute("BEGIN IMMEDIATE")
        try:
            ids = [r[0] for r in con.execute(f"SELECT id FROM {table} WHERE uuid IS NULL")]
            con.executemany(f"UPDATE {table} SET uuid = ? WHERE id = ?",
                            [(str(uuid.uuid4()), i) for i in ids])
            con.execute("COMMIT")
        except BaseException:
            con.execute("ROLLBACK")
            raise


def _stream_columns(con: sqlite3.Connection) -> set[str]:
    return {r[1] for r in con.execute("PRAGMA table_info(streams)")}


def is_full(e: BaseException) -> bool:
    """A full disk (SQLITE_FULL, or ENOSPC/EDQUOT from the file system)."""
    if isinstance(e, sqlite3.Error):
        return getattr(e, "sqlite_errorcode", None) == sqlite3.SQLITE_FULL or "full" in str(e)
    return isinstance(e, OSError) and e.errno in (28, 122)  # ENOSPC, EDQUOT


def checkpoint(con: sqlite3.Connection) -> bool:
    """Copy the -wal into the database and cut the -wal to zero bytes (after a full-disk error
    its frames squat the space that was freed). False when it could not (still full, a reader)."""
    try:
        busy, _, _ = con.execute("PRAGMA wal_checkpoint(TRUNCATE)").fetchone()
        return busy == 0
    except sqlite3.Error:
        return False


def insert_batch(con: sqlite3.Connection, rows: list[dict]) -> None:
    """Rows in one transaction: all of them are written or none. Then a passive checkpoint (it
    waits for no reader): the next batch starts the -wal from its beginning, cut to
    JOURNAL_LIMIT_BYTES, so the -wal stays at about one batch rather than growing with every row."""
    con.execute("BEGIN IMMEDIATE")
    try:
        for row in rows:
            insert(con, row)
        con.execute("COMMIT")
    except BaseException:
        try:
            con.execute("ROLLBACK")
        except sqlite3.Error:
            pass
        raise
    try:
        con.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchone()
    except sqlite3.Error:
        pass  # committed; the -wal is checkpointed by a later batch


def pending_paths(db: str | Path, library_dir: str | Path) -> list[Path]:
    """Where rows not written at exit are kept: beside the database, else (its file system is the
    one that is full) in the library's directory (a dot-file: not a texture)."""
    p = Path(db)
    return [p.with_name(p.name + PENDING_SUFFIX), Path(library_dir) / (".quality" + PENDING_SUFFIX)]


def save_pending(p: Path, rows: list[dict]) -> Path:
    """Keep rows not yet written (with those already in the file) for the next start: written to a
    temporary file, flushed and renamed over the pending-rows file p, so it is whole or unchanged.
    OSError (the disk is full) propagates."""
    keep = {(r["name"], r["sha256"]): r for r in load_pending(p) + list(rows)}.values()
    tmp = p.with_name(p.name + ".tmp")
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NOFOLLOW, 0o640)
        with os.fdopen(fd, "w") as f:
            for row in keep:
                f.write(json.dumps(row) + "\n")
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, p)
    except OSError:
        tmp.unlink(missing_ok=True)
        raise
    return p


def load_pending(p: Path) -> list[dict]:
    """The rows of the pending-rows file p ([] when there is none); a line that is not a row (a file
    cut short) is skipped: its stream is scored again from the library."""
    try:
        text = p.read_text()
    except FileNotFoundError:
        return []
    rows = []
    for line in text.splitlines():
        try:
            row = json.loads(line)
        except ValueError:
            continue
        if isinstance(row, dict) and isinstance(row.get("name"), str) and isinstance(row.get("sha256"), str):
            rows.append({c: row.get(c) for c in COLUMNS if c != "id"})
    return rows


def score_row(data: bytes, name: str, sha: str, received_at: float, a: float, b: float,
              curve=None, calibration: str | None = None) -> dict:
    """Ip, Ia, Iobj of a received stream from its header's reference (the receiver has no
    original; the peer metrics ST-SIM and SPQI need one, so they are not logged here)."""
    from hostd.codec import stream as vtx
    from hostd.quality import score_stream

    s = vtx.decode(data)
    sc = score_stream(s, curve=curve, a=a, b=b)
    row = {"sha256": sha, "name": name, "received_at": received_at, "scored_at": time.time(),
           "bytes": len(data), "method": s.method, "levels": getattr(s, "levels", None),
           "b0_db": getattr(s, "b0_db", None), "n": s.n, "n_keep": s.n_keep,
           "length_mm": s.length_mm, "speed_mm_s": s.speed_mm_s, "curve_id": s.threshold_id.hex(),
           "ratio_coeffs": s.ratio_coeffs, "ratio_profile": s.ratio_profile,
           "ip": float(sc.Ip), "ia": float(sc.Ia), "iobj": float(sc.Iobj), "a": a, "b": b,
           "calibration": calibration}
    return row


def insert(con: sqlite3.Connection, row: dict) -> None:
    cols = [c for c in COLUMNS if c != "id"] + ["uuid"]
    con.execute(f"INSERT OR IGNORE INTO streams ({', '.join(cols)}) VALUES ({', '.join('?' * len(cols))})",
                [row.get(c) for c in cols[:-1]] + [row.get("uuid") or str(uuid.uuid4())])


def known(con: sqlite3.Connection) -> set[tuple[str, str]]:
    return {(r[0], r[1]) for r in con.execute("SELECT name, sha256 FROM streams")}


PLAY_COLUMNS = ("name", "sha256", "started_at", "ended_at", "device_s", "played_s", "played_fraction",
                "underruns")
# per stream, over all its plays: how often, how long, the played fraction weighted by time, underruns
DELIVERED = ("plays", "played_s", "played_fraction", "underruns")


def insert_play(con: sqlite3.Connection, play: dict) -> None:
    marks = ", ".join("?" * (len(PLAY_COLUMNS) + 1))
    con.execute(f"INSERT INTO plays ({', '.join(PLAY_COLUMNS)}, uuid) VALUES ({marks})",
                [play.get(c) for c in PLAY_COLUMNS] + [play.get("uuid") or str(uuid.uuid4())])


def query(con: sqlite3.Connection, since: float | None = None) -> list[dict]:
    """Every stream row (received at or after `since`), with what was delivered when it played."""
    has_plays = con.execute("SELECT 1 FROM sqlite_master WHERE type='table' AND name='plays'").fetchone()
    if has_plays:  # a log written before plays were recorded has no such table (read-only: not added)
        delivered = ("LEFT JOIN (SELECT name, sha256, COUNT(*) AS plays, SUM(played_s) AS played_s, "
                     "SUM(played_fraction * device_s) / NULLIF(SUM(CASE WHEN played_fraction IS NULL "
                     "THEN 0 ELSE device_s END), 0) AS played_fraction, SUM(underruns) AS underruns "
                     "FROM plays GROUP BY name, sha256) p USING (name, sha256)")
        extra = "COALESCE(p.plays, 0), p.played_s, p.played_fraction, p.underruns"
    else:
        delivered, extra = "", "0, NULL, NULL, NULL"
    have = _stream_columns(con)  # a log older than a column (read-only: not added) reads it as NULL
    sel = ", ".join(f"s.{c}" if c in have else "NULL" for c in COLUMNS)
    sql = f"SELECT {sel}, {extra} FROM streams s {delivered}"
    args: list = []
    if since is not None:
        sql += " WHERE s.received_at >= ?"
        args.append(since)
    sql += " ORDER BY s.received_at, s.id"
    return [dict(zip(COLUMNS + DELIVERED, r, strict=True)) for r in con.execute(sql, args)]


def connect_readonly(path: str | Path) -> sqlite3.Connection:
    """The log for a reader (`hostd quality`): opened read-only, so a member of group hostd can read
    the service's database, which it cannot write. With the daemon running (WAL mode), SQLite reads
    the -wal through the existing -shm. With the daemon stopped there is no -shm, and a read-only
    connection cannot create one in a directory it cannot write: then, and only when no -wal holds
    commits not yet in the main file, the file is opened immutable (nothing else is writing it)."""
    p = Path(path)
    try:
        with open(p, "rb"):
            pass
    except PermissionError:
        raise HostdError(f"permission denied on the quality log {p}: add yourself to the daemon's group "
                         "(sudo usermod -aG hostd $USER, then log in again)") from None
    except OSError:
        raise HostdError(f"no quality log at {p} (quality.db of the config; is this the daemon's "
                         "config? --config or --db name another)") from None
    uri = p.absolute().as_uri()
    con = sqlite3.connect(f"{uri}?mode=ro", uri=True)
    try:
        con.execute("SELECT count(*) FROM sqlite_master").fetchone()
        return con
    except sqlite3.OperationalError as e:
        con.close()
        wal = p.with_name(p.name + "-wal")
        if wal.exists() and wal.stat().st_size > 0:
            raise HostdError(f"cannot read the quality log {p} read-only ({e}): its -wal holds commits "
                             "and its -shm is missing or unreadable; start hostd (it checkpoints "
                             "them), or read it as the daemon's user") from None
    return sqlite3.connect(f"{uri}?mode=ro&immutable=1", uri=True)
