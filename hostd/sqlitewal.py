"""The write-ahead log's bound, one rule for every SQLite file hostd writes (the daemon's
quality log, the corpus store): on a small disk SQLite's default checkpoint (1000 pages, 4 MB)
is never reached, and the -wal would grow with every row and squat what a full disk frees."""

from __future__ import annotations

import sqlite3

JOURNAL_LIMIT_BYTES = 16 * 1024  # the -wal is cut back to this when a writer restarts it
WAL_AUTOCHECKPOINT_PAGES = 16   # (SQLite's default, 1000 pages = 4 MB, is never reached on a small disk)


def bound_wal(con: sqlite3.Connection) -> None:
    """Keep this connection's -wal small: cut back to JOURNAL_LIMIT_BYTES, checkpointed every
    WAL_AUTOCHECKPOINT_PAGES pages."""
    con.execute(f"PRAGMA journal_size_limit={JOURNAL_LIMIT_BYTES}")
    con.execute(f"PRAGMA wal_autocheckpoint={WAL_AUTOCHECKPOINT_PAGES}")
