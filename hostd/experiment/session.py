"""A session's store: one SQLite file (WAL, synchronous=FULL), every answer committed before the
next trial is presented, so a crash loses at most the trial in flight; one session per label
(the participant id, or one hostd names).

A session keeps its plan (the procedure's settings and seed, or the similarity trial list) so
that resuming it gives the same trials: answers are replayed in order against the plan. It also
keeps what its page needs to survive a restart (`access`): the capability in the page's address,
the key its CSRF values are signed with, and the port it was served on. The file is the
experimenter's alone: created 0600 in a folder created 0700 (SQLite gives its -wal and -shm
files the database's mode).

A write the disk cannot take (full, read-only, I/O error) is StorageError: the session stops
and says so; what was committed before stays, and `--resume` goes on from it.
"""

from __future__ import annotations

import datetime as dt
import json
import os
import sqlite3
import threading
import time
from pathlib import Path

from hostd.errors import ExperimentError


class StorageError(ExperimentError):
    """The session store could not take a write (disk full, read-only, I/O error)."""


def private_dir(path: Path) -> None:
    """`path` created 0700 (missing parents too); an existing one other accounts can enter is
    refused (hostd does not change the mode of a folder it did not make)."""
    try:
        path.mkdir(mode=0o700, parents=True)
        path.chmod(0o700)  # (mkdir's mode passes through the umask)
        return
    except FileExistsError:
        pass
    except OSError as e:
        raise ExperimentError(f"cannot make the private folder {path}: {e.strerror or e}") from None
    st = path.stat()
    if st.st_mode & 0o077:
        raise ExperimentError(f"{path} is open to other accounts (mode {st.st_mode & 0o777:04o}): the "
                              f"answers must not be; give a new folder (hostd makes it 0700) or chmod 700 "
                              f"{path}")

SCHEMA = """
CREATE TABLE IF NOT EXISTS sessions (
    token TEXT PRIMARY KEY,
    kind TEXT NOT NULL,             -- threshold | similarity
    plan TEXT NOT NULL,             -- JSON: settings, seed, trial list
    created_at REAL NOT NULL,       -- unix time, s
    state TEXT NOT NULL             -- running | done | aborted | declined
);
CREATE TABLE IF NOT EXISTS answers (
    token TEXT NOT NULL REFERENCES sessions(token),
    trial INTEGER NOT NULL,
    answer INTEGER NOT NULL,
    stimulus TEXT NOT NULL,         -- JSON: what was presented
    presented_at REAL,
    answered_at REAL NOT NULL,
    PRIMARY KEY (token, trial)      -- one answer per trial: a trial is never recorded twice
);
CREATE TABLE IF NOT EXISTS access (
    token TEXT PRIMARY KEY REFERENCES sessions(token),
    capability TEXT NOT NULL,       -- the secret in the page's address (never printed but once per run)
    csrf_key TEXT NOT NULL,         -- hex: signs each page's CSRF value
    port INTEGER NOT NULL           -- the loopback port the page was served on
);
CREATE TABLE IF NOT EXISTS events (
    id INTEGER PRIMARY KEY,
    token TEXT NOT NULL,
    at REAL NOT NULL,
    kind TEXT NOT NULL,             -- started | resumed | paused | unpaused | display_lost | aborted | done
                                    -- | consented | declined | practice | practice_done | break | failed
    detail TEXT NOT NULL
);
"""


class Store:
    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        private_dir(self.path.parent)
        try:
            os.close(os.open(self.path, os.O_CREAT | os.O_RDWR, 0o600))
            self.path.chmod(0o600)
            self.con = sqlite3.connect(self.path, timeout=10.0, isolation_level=None, check_same_thread=False)
            self.con.execute("PRAGMA journal_mode=WAL")
            self.con.execute("PRAGMA synchronous=FULL")
            self.con.executescript(SCHEMA)
        except (OSError, sqlite3.Error) as e:
            raise ExperimentError(f"cannot open the session store {self.path}: {e}") from None
        self.lock = threading.Lock()

    def close(self) -> None:
        self.con.close()

    def create(self, token: str, kind: str, plan: dict) -> None:
        """A new session; a token already used (by any session in this store) is refused."""
        if not token or len(token) > 64 or not all(c.isalnum() or c in "-_" for c in token):
            raise ExperimentError(f"participant {token!r:.70}: 1..64 letters, digits, - or _")
        with self.lock:
            row = self.con.execute("SELECT kind, created_at, state FROM sessions WHERE token = ?",
                                   (token,)).fetchone()
            if row:
                when = dt.datetime.fromtimestamp(row[1]).strftime("%Y-%m-%d %H:%M")
                raise ExperimentError(f"participant {token} is already the {row[0]} session of {when} "
                                      f"({row[2]}) in {self.path}: resume it with --resume, or give a new "
                                      "--participant")
            try:
                self.con.execute("INSERT INTO sessions VALUES (?, ?, ?, ?, 'running')",
                                 (token, kind, json.dumps(plan), time.time()))
            except sqlite3.Error as e:
                raise StorageError(f"cannot create the session in {self.path}: {e}") from None
        self.event(token, "started", "")

    def load(self, token: str, kind: str) -> dict:
        with self.lock:
            row = self.con.execute("SELECT kind, plan FROM sessions WHERE token = ?", (token,)).fetchone()
        if row is None:
            raise ExperimentError(f"no session {token} in {self.path}: start one without --resume")
        if row[0] != kind:
            raise ExperimentError(f"session {token} is a {row[0]} session, not {kind}")
        return json.loads(row[1])

    def state(self, token: str) -> str:
        with self.lock:
            return self.con.execute("SELECT state FROM sessions WHERE token = ?", (token,)).fetchone()[0]

    def set_state(self, token: str, state: str) -> None:
        self._write("mark the session " + state, "UPDATE sessions SET state = ? WHERE token = ?",
                    (state, token))

    def _write(self, what: str, sql: str, args: tuple) -> None:
        with self.lock:
            try:
                self.con.execute(sql, args)
            except sqlite3.Error as e:
                raise StorageError(f"cannot {what} in {self.path}: {e}") from None

    def sessions(self) -> list[tuple[str, str, str]]:
        """(label, kind, state) of every session in the store, oldest first."""
        with self.lock:
            return self.con.execute("SELECT token, kind, state FROM sessions ORDER BY created_at").fetchall()

    def access(self, token: str) -> dict | None:
        with self.lock:
            row = self.con.execute("SELECT capability, csrf_key, port FROM access WHERE token = ?",
                                   (token,)).fetchone()
        if row is None:
            return None
        return {"capability": row[0], "csrf_key": bytes.fromhex(row[1]), "port": row[2]}

    def set_access(self, token: str, capability: str, csrf_key: bytes, port: int) -> None:
        self._write("keep the page's access", "INSERT OR REPLACE INTO access VALUES (?, ?, ?, ?)",
                    (token, capability, csrf_key.hex(), port))

    def record(self, token: str, trial: int, answer: int, stimulus: dict, presented_at: float | None) -> bool:
        """Commit one answer (durable on return). False if that trial already has one."""
        with self.lock:
            try:
                self.con.execute("INSERT INTO answers VALUES (?, ?, ?, ?, ?, ?)",
                                 (token, trial, answer, json.dumps(stimulus), presented_at, time.time()))
            except sqlite3.IntegrityError:
                return False
            except sqlite3.Error as e:
                raise StorageError(f"cannot record the answer in {self.path}: {e}") from None
        return True

    def answers(self, token: str) -> list[dict]:
        with self.lock:
            rows = self.con.execute("SELECT trial, answer, stimulus, presented_at, answered_at FROM answers "
                                    "WHERE token = ? ORDER BY trial", (token,)).fetchall()
        return [{"trial": r[0], "answer": r[1], "stimulus": json.loads(r[2]), "presented_at": r[3],
                 "answered_at": r[4]} for r in rows]

    def event(self, token: str, kind: str, detail: str) -> None:
        self._write(f"record the event {kind}",
                    "INSERT INTO events (token, at, kind, detail) VALUES (?, ?, ?, ?)",
                    (token, time.time(), kind, detail))

    def events(self, token: str) -> list[dict]:
        with self.lock:
            rows = self.con.execute("SELECT at, kind, detail FROM events WHERE token = ? ORDER BY id",
                                    (token,)).fetchall()
        return [{"at": r[0], "kind": r[1], "detail": r[2]} for r in rows]
