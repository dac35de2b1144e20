"""The central store's schema: numbered SQL migrations (hostd/fleet/sql/NNN_name.sql), each applied
in one transaction with its row in fleet.schema_version, and the checks a PC makes when it connects.

Each migration states on its first line the oldest PC schema that can still ship after it
(`-- min_client: N`): an additive migration keeps it, so a PC on an older hostd keeps shipping; a
migration that breaks old PCs raises it, and those PCs stop with a line saying to upgrade hostd.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from importlib import resources

from hostd.errors import HostdError

SUPPORTED_MAJORS = range(13, 18)  # PostgreSQL 13..17: row-level security, partitions, ON CONFLICT
_HEAD = re.compile(r"--\s*min_client:\s*(\d+)")


@dataclass(frozen=True)
class Migration:
    version: int
    name: str
    min_client: int
    sql: str


def migrations(extra_dir=None) -> list[Migration]:
    """The package's migrations in order (and, for tests, those of extra_dir after them)."""
    files = [f for f in resources.files("hostd.fleet").joinpath("sql").iterdir() if f.name.endswith(".sql")]
    if extra_dir is not None:
        files += [f for f in extra_dir.iterdir() if f.name.endswith(".sql")]
    out = []
    for f in files:
        m = re.match(r"(\d+)_(\w+)\.sql$", f.name)
        if not m:
            continue
        text = f.read_text()
        head = _HEAD.match(text)
        if not head:
            raise HostdError(f"migration {f.name} does not begin with `-- min_client: N`")
        out.append(Migration(int(m.group(1)), m.group(2), int(head.group(1)), text))
    out.sort(key=lambda m: m.version)
    if len({m.version for m in out}) != len(out):
        raise HostdError("two migrations share a number")
    return out


KNOWN = migrations()[-1].version  # the schema this hostd writes


def check_server(conn) -> None:
    major = conn.info.server_version // 10000
    if major not in SUPPORTED_MAJORS:
        raise HostdError(f"the central server is PostgreSQL {major}; this hostd supports "
                         f"{SUPPORTED_MAJORS.start}..{SUPPORTED_MAJORS.stop - 1}: point fleet.url at a "
                         "supported server, or upgrade hostd")


def migrate(conn, extra_dir=None) -> list[int]:
    """Apply the migrations the database has not had, each in its own transaction (all of it or
    none); two migrators at once take turns (an advisory lock). The versions applied."""
    check_server(conn)
    applied = []
    with conn.transaction():
        conn.execute("CREATE SCHEMA IF NOT EXISTS fleet")
        conn.execute("CREATE TABLE IF NOT EXISTS fleet.schema_version (version integer PRIMARY KEY, "
                     "name text NOT NULL, min_client integer NOT NULL, "
                     "applied_at timestamptz NOT NULL DEFAULT now())")
    for m in migrations(extra_dir):
        with conn.transaction():
            conn.execute("SELECT pg_advisory_xact_lock(hashtext('hostd fleet migrate'))")
            if conn.execute("SELECT 1 FROM fleet.schema_version WHERE version = %s",
                            (m.version,)).fetchone():
                continue
            conn.execute(m.sql)
            conn.execute("INSERT INTO fleet.schema_version (version, name, min_client) VALUES (%s, %s, %s)",
                         (m.version, m.name, m.min_client))
            applied.append(m.version)
    return applied


def check_client(conn, known: int = KNOWN) -> int:
    """The server's schema version, when a PC that knows up to `known` may ship to it; else
    HostdError saying what to do."""
    row = conn.execute("SELECT max(version), max(min_client) FROM fleet.schema_version").fetchone() \
        if conn.execute("SELECT to_regclass('fleet.schema_version')").fetchone()[0] else (None, None)
    conn.rollback()
    version, min_client = row
    if version is None:
        raise HostdError("the central database has no fleet schema: its owner runs "
                         "`hostd fleet migrate --url URL` once")
    if min_client > known:
        raise HostdError(f"the central schema (version {version}) needs a PC that knows version {min_client} "
                         f"or later; this hostd knows {known}: upgrade hostd on this PC")
    return version
