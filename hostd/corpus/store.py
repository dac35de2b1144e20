"""The results store: one SQLite file, one row per key (UNIQUE), written a task at a time in one
transaction, so a `kill -9` at any moment leaves whole tasks or nothing, and a rerun skips
the keys already there. pandas (`read_sql`), DuckDB (`sqlite_scan`) and `sqlite3` read it;
`to_arrow` / `export_parquet` give a pyarrow table or a Parquet file.

A store is data, also one somebody else made: it is opened with `trusted_schema=OFF` (and
SQLite's defensive mode where this Python exposes it: `Connection.setconfig`, Python >= 3.12),
a file holding a view or a trigger is refused (a view over an endless query, or a trigger that
deletes every row written, would run on our reads and writes), and so is a file that is not a
corpus store (the daemon's quality log, any other database). A store is marked as one by
`PRAGMA application_id` and versioned by `PRAGMA user_version`; a store of an older version is
migrated in place, one of a newer hostd is refused. Reading (`report`, `export`) never creates
a file. The -wal is bounded as the quality log's is (hostd.sqlitewal).
"""

from __future__ import annotations

import os
import sqlite3
import stat
import time
from collections.abc import Iterable, Sequence
from pathlib import Path

from hostd.corpus.jobs import COLUMNS, COLUMNS_V1, SCHEMA, named_key
from hostd.errors import HostdError
from hostd.sqlitewal import bound_wal

_SQL_TYPE = {"str": "TEXT", "float": "REAL", "int": "INTEGER"}
TABLE = "results"
APPLICATION_ID = 0x48434F52  # "HCOR": this file is a hostd corpus store
VERSION = 3  # 1: results only (content keys); 2: + scoring, run, the runs table, named keys;
#             3: + texture_group
TABLES = {TABLE, "runs"}
# what a row scored before stores recorded it was scored with: the defaults of that time
_V1_SCORING = '{{"a": 0.581, "b": 0.464, "spqi": {}}}'


# rows whose job runs again on the next run (and is then overwritten): its worker was lost
RETRIED = "('worker_lost')"


class StoreError(HostdError):
    """The results file cannot be opened or written."""


def defensive_available() -> bool:
    """Whether this Python can switch on SQLite's defensive mode (sqlite3 setconfig, 3.12+)."""
    return hasattr(sqlite3.Connection, "setconfig") and hasattr(sqlite3, "SQLITE_DBCONFIG_DEFENSIVE")


class Store:
    """`create`: a run's store (made when missing); else an existing store, opened to read
    (a missing path is an error, never an empty file)."""

    def __init__(self, path: str | Path, *, create: bool = True) -> None:
        self.path = Path(path)
        self.run_id: int | None = None
        exists = os.path.lexists(self.path)
        if not exists and not create:
            raise StoreError(f"no corpus store {self.path}: make one with `hostd corpus run ... -o "
                             f"{self.path}`")
        if exists:
            try:
                st = os.stat(self.path)
            except OSError as exc:
                raise StoreError(f"cannot open the results file {self.path}: {exc.strerror}") from None
            if not stat.S_ISREG(st.st_mode):
                raise StoreError(f"{self.path} is not a regular file: give the corpus store's path")
        try:
            if create:
                self.path.parent.mkdir(parents=True, exist_ok=True)
            mode = "rwc" if create else "rw" if os.access(self.path, os.W_OK) else "ro"
            self.readonly = mode == "ro"
            self.db = sqlite3.connect(f"{self.path.resolve().as_uri()}?mode={mode}", uri=True, timeout=30.0)
        except (OSError, sqlite3.Error) as exc:
            raise StoreError(f"cannot open the results file {self.path}: {exc} (is it an SQLite file this "
                             "user may read and write?)") from None
        try:
            self._harden()
            self._check_and_migrate(create)
        except sqlite3.Error as exc:
            self.db.close()
            raise StoreError(f"cannot open the results file {self.path}: {exc} (is it a corpus store of "
                             "`hostd corpus run`?)") from None
        except BaseException:
            self.db.close()
            raise

    # ------------------------------------------------------------------------- opening

    def _harden(self) -> None:
        if defensive_available():  # no writes to the schema tables, no deliberate corruption
            self.db.setconfig(sqlite3.SQLITE_DBCONFIG_DEFENSIVE, True)
        # functions in the schema (views, triggers, defaults, generated columns) run only when
        # harmless (SQLite >= 3.31)
        self.db.execute("PRAGMA trusted_schema=OFF")

    def _objects(self) -> list[tuple[str, str, str, str | None]]:
        return list(self.db.execute("SELECT type, name, tbl_name, sql FROM sqlite_master"))

    def _check_and_migrate(self, create: bool) -> None:
        objs = self._objects()
        code = sorted(f"{t} {n}" for t, n, _, _ in objs if t in ("view", "trigger"))
        if code:
            raise StoreError(f"{self.path} holds {', '.join(code)}: a corpus store has no view or trigger, "
                             "and this one would run code as it is read or written; refusing it")
        tables = {n for t, n, _, _ in objs if t == "table" and not n.startswith("sqlite_")}
        app = int(self.db.execute("PRAGMA application_id").fetchone()[0])
        version = int(self.db.execute("PRAGMA user_version").fetchone()[0])
        virtual = sorted(n for t, n, _, sql in objs if t == "table" and (sql or "").lstrip().upper()
                         .startswith("CREATE VIRTUAL"))
        not_ours = f"{self.path} is not a corpus store of `hostd corpus run`"
        if app == APPLICATION_ID:
            if version > VERSION:
                raise StoreError(f"{self.path} was written by a newer hostd (corpus store version {version}; "
                                 f"this one reads up to {VERSION}): upgrade hostd to read it")
            if virtual or not tables <= TABLES:
                extra = ", ".join(sorted(tables - TABLES) or virtual)
                raise StoreError(f"{not_ours}: it holds table(s) {extra}")
        elif app != 0:
            raise StoreError(f"{not_ours} (its application id is {app:#x})")
        elif tables == {TABLE} and not virtual and self._columns() == list(COLUMNS_V1):
            version = 1  # a store of before the version mark: migrated below
        elif tables:
            raise StoreError(f"{not_ours}: it holds table(s) {', '.join(sorted(tables))} (give a new "
                             "file to `corpus run -o`, or a store it wrote)")
        elif not create:
            raise StoreError(f"{not_ours}: it holds no results table")
        else:
            version = 0  # an empty file: a new store
        if version < VERSION:
            if self.readonly:
                raise StoreError(f"{self.path} is a corpus store of an older version ({version}) that this "
                                 "user may not write: copy it where you may, and hostd migrates the copy")
            self._migrate(version)
        if self._columns() != list(COLUMNS):
            raise StoreError(f"{self.path} holds results of another schema: write to a new file (-o)")
        if create:
            # WAL + NORMAL: a committed task survives a killed process (not a power cut)
            self.db.execute("PRAGMA journal_mode=WAL")
            self.db.execute("PRAGMA synchronous=NORMAL")
            bound_wal(self.db)

    def _columns(self) -> list[str]:
        return [r[1] for r in self.db.execute(f"PRAGMA table_info({TABLE})")]

    def _migrate(self, version: int) -> None:
        """In one transaction: a new store's tables, or an older store's new columns (a version-1
        store's rows re-keyed with their texture's name (jobs.named_key), their scoring and run 0). (A
        second process opening the same old store at once waits, then finds it migrated.)"""
        self.db.execute("BEGIN IMMEDIATE")  # (sqlite3 would run the DDL outside a transaction)
        try:
            if int(self.db.execute("PRAGMA user_version").fetchone()[0]) >= VERSION \
                    and int(self.db.execute("PRAGMA application_id").fetchone()[0]) == APPLICATION_ID:
                self.db.rollback()
                return
            self._migrate_in(version)
            self.db.commit()
        except BaseException:
            self.db.rollback()
            raise

    def _migrate_in(self, version: int) -> None:
        if version == 0:
            cols = ", ".join(f'"{c}" {_SQL_TYPE[t]}' + (" PRIMARY KEY" if c == "key" else "")
                             for c, t in SCHEMA)
            self.db.execute(f"CREATE TABLE {TABLE} ({cols}) WITHOUT ROWID")
        else:
            have = set(self._columns())
            for c, t in SCHEMA:
                if c not in have:  # (new columns are appended: the table's order is SCHEMA's)
                    self.db.execute(f'ALTER TABLE {TABLE} ADD COLUMN "{c}" {_SQL_TYPE[t]}')
        if version == 1:
            q = f"SELECT COUNT(spqi) > 0 FROM {TABLE} WHERE error IS NULL"
            spqi = self.db.execute(q).fetchone()[0]
            self.db.create_function("hostd_named_key", 2, named_key, deterministic=True)
            self.db.execute(
                f"UPDATE {TABLE} SET key = hostd_named_key(key, texture), run = 0, scoring = CASE "
                f"WHEN error IS NULL THEN (CASE WHEN spqi IS NULL THEN ? ELSE ? END) ELSE ? END",
                (_V1_SCORING.format("false"), _V1_SCORING.format("true"),
                 _V1_SCORING.format("true" if spqi else "false")))
        self.db.execute("CREATE INDEX IF NOT EXISTS results_run ON results(run)")
        self.db.execute("CREATE TABLE IF NOT EXISTS runs (run INTEGER PRIMARY KEY, started_at REAL, "
                        "hostd_version TEXT)")
        if version == 1:
            self.db.execute("INSERT OR IGNORE INTO runs VALUES (0, NULL, ?)",
                            ("before the corpus store kept runs",))
        self.db.execute(f"PRAGMA application_id={APPLICATION_ID}")
        self.db.execute(f"PRAGMA user_version={VERSION}")

    # ------------------------------------------------------------------------- use

    def close(self) -> None:
        self.db.close()

    def begin_run(self) -> int:
        """A new run number: the rows this run writes carry it."""
        import hostd

        with self.db:
            cur = self.db.execute("INSERT INTO runs (started_at, hostd_version) VALUES (?, ?)",
                                  (time.time(), hostd.__version__))
        self.run_id = int(cur.lastrowid)
        return self.run_id

    def runs(self) -> list[dict]:
        cur = self.db.execute("SELECT run, started_at, hostd_version FROM runs ORDER BY run")
        return [{"run": r, "started_at": t, "hostd_version": v} for r, t, v in cur]

    def known(self, keys: Sequence[str], *, ok_only: bool = False) -> set[str]:
        """Which of `keys` are stored (ok_only: only rows without an error); a row of a job whose
        worker was lost (RETRIED) is not: the job runs again on the next run."""
        out: set[str] = set()
        extra = " AND error IS NULL" if ok_only else f" AND coalesce(error_reason, '') NOT IN {RETRIED}"
        for i in range(0, len(keys), 500):
            part = list(keys[i : i + 500])
            q = f"SELECT key FROM {TABLE} WHERE key IN ({','.join('?' * len(part))}){extra}"
            out.update(r[0] for r in self.db.execute(q, part))
        return out

    def write(self, rows: Iterable[dict], *, replace: bool = False) -> int:
        """Insert rows in one transaction; a key already stored is kept (replace: overwritten).
        Returns how many rows were new (or replaced a RETRIED row). Rows carry this store's run
        number (begin_run)."""
        names = ", ".join(f'"{c}"' for c in COLUMNS)
        update = ", ".join(f'"{c}" = excluded."{c}"' for c in COLUMNS[1:])
        when = "" if replace else f" WHERE {TABLE}.error_reason IN {RETRIED}"
        q = f"INSERT INTO {TABLE} ({names}) VALUES ({', '.join('?' * len(COLUMNS))}) " \
            f"ON CONFLICT(key) DO UPDATE SET {update}{when}"
        run = self.run_id
        at = COLUMNS.index("run")

        def values(r: dict) -> list:
            v = list(map(r.get, COLUMNS))
            v[at] = run
            return v

        try:
            with self.db:
                before = self.db.total_changes
                self.db.executemany(q, [values(r) for r in rows])
                return self.db.total_changes - before
        except sqlite3.Error as exc:
            raise StoreError(f"cannot write to {self.path}: {exc}") from None

    def count(self) -> int:
        return int(self.db.execute(f"SELECT COUNT(*) FROM {TABLE}").fetchone()[0])

    def rows(self, where: str = "", params: Sequence = ()) -> list[dict]:
        cur = self.db.execute(f"SELECT * FROM {TABLE} {where}", params)
        names = [d[0] for d in cur.description]
        return [dict(zip(names, r, strict=True)) for r in cur]


def _pyarrow():
    from hostd.extras import need

    return need("pyarrow", "corpus", "a table or Parquet file of the results")


def _schema():
    pa = _pyarrow()

    types = {"str": pa.string(), "float": pa.float64(), "int": pa.int64()}
    return pa.schema([(c, types[t]) for c, t in SCHEMA])


ORDER = "ORDER BY texture, codec, curve, speed_mm_s, fmax_hz, key"


def to_arrow(path: str | Path):
    """The whole store as a pyarrow Table (the schema of hostd.corpus.jobs.SCHEMA)."""
    pa = _pyarrow()

    st = Store(path, create=False)
    try:
        rows = st.rows(ORDER)
    finally:
        st.close()
    return pa.Table.from_pylist(rows, schema=_schema())


def export_parquet(path: str | Path, out: str | Path, chunk_rows: int = 50_000) -> Path:
    """Write the store as one Parquet file, `chunk_rows` rows at a time (memory stays flat),
    written beside and then renamed: never half a file under the final name."""
    pa = _pyarrow()
    import pyarrow.parquet as pq

    out = Path(out)
    tmp = out.with_name(out.name + ".part")
    schema = _schema()
    st = Store(path, create=False)
    try:
        names = ", ".join(f'"{c}"' for c in COLUMNS)
        cur = st.db.execute(f"SELECT {names} FROM {TABLE} {ORDER}")
        with pq.ParquetWriter(tmp, schema) as w:
            while True:
                part = cur.fetchmany(chunk_rows)
                if not part:
                    break
                cols = list(zip(*part, strict=True))
                w.write_table(pa.Table.from_arrays([pa.array(c, type=f.type) for c, f in zip(cols, schema,
                                                                                             strict=True)],
                                                   schema=schema))
    finally:
        st.close()
    tmp.replace(out)
    return out
