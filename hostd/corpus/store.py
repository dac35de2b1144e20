"""The results store: one SQLite file, one row per key (UNIQUE), written a task at a time in one
transaction, so a `kill -9` at any moment leaves whole tasks or nothing, and a rerun skips
the keys already there. pandas (`read_sql`), DuckDB (`sqlite_scan`) and `sqlite3` read it;
`to_arrow` / `export_parquet` give a pyarrow table or a Parquet file.
"""

from __future__ import annotations

import sqlite3
from collections.abc import Iterable, Sequence
from pathlib import Path

from hostd.corpus.jobs import COLUMNS, SCHEMA
from hostd.errors import HostdError

_SQL_TYPE = {"str": "TEXT", "float": "REAL", "int": "INTEGER"}
TABLE = "results"


class StoreError(HostdError):
    """The results file cannot be opened or written."""


class Store:
    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self.db = sqlite3.connect(str(self.path), timeout=30.0)
            self.db.execute("PRAGMA journal_mode=WAL")
            # WAL + NORMAL: a committed task survives a killed process (not a power cut)
            self.db.execute("PRAGMA synchronous=NORMAL")
            cols = ", ".join(f'"{c}" {_SQL_TYPE[t]}' + (" PRIMARY KEY" if c == "key" else "")
                             for c, t in SCHEMA)
            self.db.execute(f"CREATE TABLE IF NOT EXISTS {TABLE} ({cols}) WITHOUT ROWID")
            have = [r[1] for r in self.db.execute(f"PRAGMA table_info({TABLE})")]
        except sqlite3.Error as exc:
            raise StoreError(f"cannot open the results file {self.path}: {exc} (is it an SQLite "
                             "file this user may write?)") from None
        if have != list(COLUMNS):
            raise StoreError(f"{self.path} holds results of another schema: write to a new file (-o)")

    def close(self) -> None:
        self.db.close()

    def known(self, keys: Sequence[str], *, ok_only: bool = False) -> set[str]:
        """Which of `keys` are stored (ok_only: only rows without an error)."""
        out: set[str] = set()
        extra = " AND error IS NULL" if ok_only else ""
        for i in range(0, len(keys), 500):
            part = list(keys[i : i + 500])
            q = f"SELECT key FROM {TABLE} WHERE key IN ({','.join('?' * len(part))}){extra}"
            out.update(r[0] for r in self.db.execute(q, part))
        return out

    def write(self, rows: Iterable[dict], *, replace: bool = False) -> int:
        """Insert rows in one transaction; a key already stored is kept (replace: overwritten).
        Returns how many rows were new."""
        verb = "INSERT OR REPLACE" if replace else "INSERT OR IGNORE"
        q = f"{verb} INTO {TABLE} ({', '.join(f'{chr(34)}{c}{chr(34)}' for c in COLUMNS)}) " \
            f"VALUES ({', '.join('?' * len(COLUMNS))})"
        try:
            with self.db:
                before = self.db.total_changes
                self.db.executemany(q, [tuple(map(r.get, COLUMNS)) for r in rows])
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

    st = Store(path)
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
    st = Store(path)
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
