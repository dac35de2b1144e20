"""The quality log's outbox: which rows wait to be shipped to the fleet's central store.

The shipper (`hostd fleet ship`, hostd/fleet/) reads the daemon's quality log and keeps what it has
shipped in a small SQLite file of its own (the state file, STATE_DEFAULT): the daemon's log has
one writer, the daemon. Rows are shipped in the log's id order (one writer: ids are committed in
increasing order, and rows are never deleted), so "shipped" is one mark per table: the highest id
the central server has committed, with that row's uuid (a log moved away and begun anew, its ids
restarting, does not match it: then every row of the new log waits). Device-health summaries,
which the shipper takes itself, wait in the state file's own health table.

Here, and not in hostd/fleet, because `hostd status` and `hostd doctor` say how many rows wait
and since when, and the service never imports the fleet room.
"""

from __future__ import annotations

import os
import sqlite3
from pathlib import Path

STATE_DEFAULT = "/var/lib/hostd-fleet/outbox.sqlite"
STATE_ENV = "HOSTD_FLEET_STATE"  # where `hostd status` / `hostd doctor` look, when not the default
KINDS = (("streams", "received_at"), ("plays", "ended_at"))  # table, its local time of the row

STATE_SCHEMA = """
CREATE TABLE IF NOT EXISTS marks (
    kind TEXT PRIMARY KEY,          -- streams, plays
    last_id INTEGER NOT NULL,       -- the log's rows with id <= this are committed centrally
    last_uuid TEXT,                 -- the uuid of row last_id (the same log, not a new one)
    shipped_at REAL NOT NULL        -- unix time, s, of the central commit
);
CREATE TABLE IF NOT EXISTS health (
    id INTEGER PRIMARY KEY,
    uuid TEXT NOT NULL UNIQUE,
    taken_at REAL NOT NULL,         -- unix time, s (this PC's clock)
    doc TEXT NOT NULL,              -- JSON: serial, firmware, underruns, played fraction, ...
    shipped INTEGER NOT NULL DEFAULT 0
);
CREATE TABLE IF NOT EXISTS info (key TEXT PRIMARY KEY, value TEXT);
"""


def state_path(given: str | None = None) -> Path:
    return Path(given or os.environ.get(STATE_ENV) or STATE_DEFAULT)


def marks(state: sqlite3.Connection) -> dict[str, tuple[int, str | None]]:
    return {k: (i, u) for k, i, u in state.execute("SELECT kind, last_id, last_uuid FROM marks")}


def start_id(log: sqlite3.Connection, mark: tuple[int, str | None] | None, table: str) -> int:
    """The id after which the log's rows of `table` wait: the mark's, when its row is still the one
    marked (else 0: the log was begun anew, and every row waits)."""
    if mark is None or mark[0] <= 0:
        return 0
    row = log.execute(f"SELECT uuid FROM {table} WHERE id = ?", (mark[0],)).fetchone()
    return mark[0] if row is not None and row[0] == mark[1] else 0


def waiting(log_db: str | Path, state: str | Path | None = None) -> dict | None:
    """{"waiting": rows not yet shipped, "since": the oldest one's local unix time (None: none wait),
    "last_shipped_at", "last_error"}; None when this PC has no shipper (no state file)."""
    sp = state_path(str(state) if state else None)
    if not sp.exists():
        return None
    st = sqlite3.connect(f"{sp.absolute().as_uri()}?mode=ro", uri=True)
    try:
        m = marks(st)
        info = dict(st.execute("SELECT key, value FROM info"))
        health = st.execute("SELECT count(*), min(taken_at) FROM health WHERE shipped = 0").fetchone()
        shipped_at = st.execute("SELECT max(shipped_at) FROM marks").fetchone()[0]
    finally:
        st.close()
    from hostd.service.qualitylog import connect_readonly

    n, since = health[0], health[1]
    log = connect_readonly(log_db)
    try:
        tables = {r[0] for r in log.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        for table, when in KINDS:
            if table not in tables:
                continue
            first = start_id(log, m.get(table), table)
            k, t = log.execute(f"SELECT count(*), min({when}) FROM {table} WHERE id > ?", (first,)).fetchone()
            n += k
            if t is not None and (since is None or t < since):
                since = t
    finally:
        log.close()
    return {"waiting": n, "since": since, "last_shipped_at": shipped_at, "last_error": info.get("last_error")}


def describe(w: dict) -> str:
    """One line: how many rows wait and since when (`hostd status`, `hostd doctor`)."""
    import datetime as dt

    def at(t):
        return dt.datetime.fromtimestamp(t, dt.UTC).isoformat(timespec="seconds") if t else "never"

    if not w["waiting"]:
        return f"fleet: nothing waits to be shipped (last shipped {at(w['last_shipped_at'])})"
    return (f"fleet: {w['waiting']} rows wait to be shipped, the oldest since {at(w['since'])} (this PC's "
            f"clock); last shipped {at(w['last_shipped_at'])}"
            + (f"; last error: {w['last_error']}" if w.get("last_error") else ""))


def status_of(log_db: str | Path) -> tuple[dict | None, str | None]:
    """(waiting(...), its line), or (None, None) without a shipper; a log or state file this user
    cannot read gives (None, the line saying so)."""
    from hostd.errors import HostdError

    try:
        w = waiting(log_db)
    except (sqlite3.Error, OSError, HostdError) as e:
        return None, f"fleet: cannot read what waits to be shipped ({e})"
    return w, (describe(w) if w is not None else None)
