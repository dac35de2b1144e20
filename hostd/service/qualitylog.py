"""The quality log: one SQLite row per accepted stream (WAL mode, synchronous=FULL).

Rows are written off the real-time path by the daemon's quality worker. A row is committed
before it counts as logged; WAL with synchronous=FULL makes every commit durable across a
kill -9 or power loss, and the daemon re-scores at start-up any stored stream that has no
row yet, so an accepted stream is never left unlogged.
"""

from __future__ import annotations

import sqlite3
import time
from pathlib import Path

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
    UNIQUE (name, sha256)   -- one row per stored (name, content); re-sending it adds none
);
CREATE INDEX IF NOT EXISTS streams_received ON streams(received_at);
"""

COLUMNS = ("id", "sha256", "name", "received_at", "scored_at", "bytes", "method", "levels", "b0_db",
           "n", "n_keep", "length_mm", "speed_mm_s", "curve_id", "ratio_coeffs", "ratio_profile",
           "ip", "ia", "iobj", "a", "b")


def connect(path: str | Path) -> sqlite3.Connection:
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    con = sqlite3.connect(p, timeout=10.0, isolation_level=None)
    con.execute("PRAGMA journal_mode=WAL")
    con.execute("PRAGMA synchronous=FULL")
    con.executescript(SCHEMA)
    return con


def score_row(data: bytes, name: str, sha: str, received_at: float, a: float, b: float,
              curve=None) -> dict:
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
           "ip": float(sc.Ip), "ia": float(sc.Ia), "iobj": float(sc.Iobj), "a": a, "b": b}
    return row


def insert(con: sqlite3.Connection, row: dict) -> None:
    cols = [c for c in COLUMNS if c != "id"]
    con.execute(f"INSERT OR IGNORE INTO streams ({', '.join(cols)}) VALUES ({', '.join('?' * len(cols))})",
                [row.get(c) for c in cols])


def known(con: sqlite3.Connection) -> set[tuple[str, str]]:
    return {(r[0], r[1]) for r in con.execute("SELECT name, sha256 FROM streams")}


def query(con: sqlite3.Connection, since: float | None = None) -> list[dict]:
    sql = f"SELECT {', '.join(COLUMNS)} FROM streams"
    args: list = []
    if since is not None:
        sql += " WHERE received_at >= ?"
        args.append(since)
    sql += " ORDER BY received_at, id"
    return [dict(zip(COLUMNS, r, strict=True)) for r in con.execute(sql, args)]
