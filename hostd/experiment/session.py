"""A session's store: one SQLite file (WAL, synchronous=FULL), every answer committed before the
next trial is presented, so a crash loses at most the trial in flight; one session per token.

A session keeps its plan (the procedure's settings and seed, or the similarity trial list) so
that resuming it gives the same trials: answers are replayed in order against the plan.
"""

from __future__ import annotations

import datetime as dt
import json
import sqlite3
import threading
import time
from pathlib import Path

from hostd.errors import ExperimentError

SCHEMA = """
CREATE TABLE IF NOT EXISTS sessions (
    token TEXT PRIMARY KEY,
    kind TEXT NOT NULL,             -- threshold | similarity
    plan TEXT NOT NULL,             -- JSON: settings, seed, trial list
    created_at REAL NOT NULL,       -- unix time, s
    state TEXT NOT NULL             -- running | done | aborted
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
CREATE TABLE IF NOT EXISTS events (
    id INTEGER PRIMARY KEY,
    token TEXT NOT NULL,
    at REAL NOT NULL,
    kind TEXT NOT NULL,             -- started | resumed | paused | unpaused | display_lost | aborted | done
    detail TEXT NOT NULL
);
"""


class Store:
    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
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
            raise ExperimentError(f"token {token!r:.70}: 1..64 letters, digits, - or _")
        with self.lock:
            row = self.con.execute("SELECT kind, created_at, state FROM sessions WHERE token = ?",
                                   (token,)).fetchone()
            if row:
                when = dt.datetime.fromtimestamp(row[1]).strftime("%Y-%m-%d %H:%M")
                raise ExperimentError(f"token {token} is already the {row[0]} session of {when} ({row[2]}) "
                                      f"in {self.path}: resume it with --resume, or give a new --token")
            self.con.execute("INSERT INTO sessions VALUES (?, ?, ?, ?, 'running')",
                             (token, kind, json.dumps(plan), time.time()))
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
        with self.lock:
            self.con.execute("UPDATE sessions SET state = ? WHERE token = ?", (state, token))

    def record(self, token: str, trial: int, answer: int, stimulus: dict, presented_at: float | None) -> bool:
        """Commit one answer (durable on return). False if that trial already has one."""
        with self.lock:
            try:
                self.con.execute("INSERT INTO answers VALUES (?, ?, ?, ?, ?, ?)",
                                 (token, trial, answer, json.dumps(stimulus), presented_at, time.time()))
            except sqlite3.IntegrityError:
                return False
            except sqlite3.Error as e:
                raise ExperimentError(f"cannot record the answer in {self.path}: {e}") from None
        return True

    def answers(self, token: str) -> list[dict]:
        with self.lock:
            rows = self.con.execute("SELECT trial, answer, stimulus, presented_at, answered_at FROM answers "
                                    "WHERE token = ? ORDER BY trial", (token,)).fetchall()
        return [{"trial": r[0], "answer": r[1], "stimulus": json.loads(r[2]), "presented_at": r[3],
                 "answered_at": r[4]} for r in rows]

    def event(self, token: str, kind: str, detail: str) -> None:
        with self.lock:
            self.con.execute("INSERT INTO events (token, at, kind, detail) VALUES (?, ?, ?, ?)",
                             (token, time.time(), kind, detail))

    def events(self, token: str) -> list[dict]:
        with self.lock:
            rows = self.con.execute("SELECT at, kind, detail FROM events WHERE token = ? ORDER BY id",
                                    (token,)).fetchall()
        return [{"at": r[0], "kind": r[1], "detail": r[2]} for r in rows]
