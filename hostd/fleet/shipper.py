"""The shipper: the daemon's quality log, read as it grows, shipped to the central PostgreSQL.

An outbox, not a second source of truth. The local log stays authoritative and the daemon its only
writer: the shipper reads it (WAL mode lets a reader in beside the writer) and keeps what it has
shipped in its own state file (hostd.service.outbox). Per batch: one central transaction inserts
each row's uuid into fleet.row_keys (ON CONFLICT DO NOTHING: the uuids the centre has not had come
back) and then those rows, and commits; only then is the batch marked shipped locally. A crash
before the commit: nothing central, the batch is sent again. A crash after the commit and before
the mark: the batch is sent again and every row of it is a no-op. So a retry never doubles a row and
a crash never loses one. The daemon never waits on any of this: it knows nothing of the shipper.

While the centre is away (down, restarted, unreachable) the shipper waits, doubling from
backoff_min_s to backoff_max_s, and the rows wait in the local log. What cannot mend by waiting
(a wrong password, a certificate that does not match, an unsupported server, a schema newer than
this PC knows, a wrong database name) stops it with one line saying what to do (FatalError).
"""

from __future__ import annotations

import functools
import json
import logging
import os
import signal
import sqlite3
import threading
import time
import uuid
from pathlib import Path

from hostd.errors import HostdError
from hostd.fleet.config import FleetCfg, password
from hostd.service import outbox

log = logging.getLogger("hostd.fleet")

QUALITY_COLS = ("sha256", "name", "bytes", "method", "levels", "b0_db", "n", "n_keep", "length_mm",
                "speed_mm_s", "curve_id", "ratio_coeffs", "ratio_profile", "ip", "ia", "iobj", "a", "b",
                "calibration")
QUALITY_TIMES = ("received_at", "scored_at")  # unix s on the PC -> pc_received_at, scored_at (UTC)
PLAY_COLS = ("name", "sha256", "device_s", "played_s", "played_fraction", "underruns")
PLAY_TIMES = ("started_at", "ended_at")
HEALTH_COLS = ("serial", "firmware", "transport", "device_state", "device_underruns", "played_fraction",
               "stalls", "recoveries", "waiting_rows")
HEALTH_TIMES = ("taken_at", "waiting_since")
# the central columns' types (hostd/fleet/sql), for the rows sent as one JSON array per kind
TYPES = {"sha256": "text", "name": "text", "bytes": "integer", "method": "text", "levels": "integer",
         "n": "integer", "n_keep": "integer", "curve_id": "text", "calibration": "text",
         "underruns": "bigint",
         "serial": "text", "firmware": "text", "transport": "text", "device_state": "text",
         "device_underruns": "bigint", "stalls": "bigint", "recoveries": "bigint", "waiting_rows": "bigint"}
KIND_TABLES = {"quality": "quality", "play": "plays", "health": "health"}


KINDS = {"quality": (QUALITY_COLS, QUALITY_TIMES), "play": (PLAY_COLS, PLAY_TIMES),
         "health": (HEALTH_COLS, HEALTH_TIMES)}
BATCH_KEYS = {"quality": "streams", "play": "plays", "health": "health"}  # the batch's lists


@functools.cache
def ship_sql(kinds: tuple[str, ...]) -> str:
    """Per kind the batch carries: the rows (a JSON array), their uuids into the ledger (ON CONFLICT
    DO NOTHING: those the centre has not had come back), those rows into their table; the count of
    rows new. Only the kinds present: the server plans (and, on a pooled connection that changes
    role, plans again) a statement of one or two kinds, not of all three (a third of the planning
    for the usual batch of one stream row or one play). Each row records the PC's clock offset
    (this PC's clock when it sent minus the server's: it includes the one-way network delay) and
    gets the server's receive time (the default, now())."""
    ctes, counts = [], []
    for kind in kinds:
        cols, times = KINDS[kind]
        table, local = KIND_TABLES[kind], kind != "health"
        spec = ", ".join(["uuid uuid", *(["id bigint"] if local else []),
                          *(f"{c} {TYPES.get(c, 'double precision')}" for c in (*cols, *times))])
        dest = ["pc_received_at" if (kind, t) == ("quality", "received_at") else t for t in times]
        ctes += [f"{kind}_r AS (SELECT * FROM jsonb_to_recordset(%({kind})s::jsonb) AS r({spec}))",
                 f"{kind}_k AS (INSERT INTO fleet.row_keys (uuid, pc_id, kind) SELECT uuid, %(pc)s, "
                 f"'{kind}' FROM {kind}_r ON CONFLICT DO NOTHING RETURNING uuid)",
                 f"{kind}_i AS (INSERT INTO fleet.{table} (uuid, pc_id, pc_clock_offset_s, "
                 f"{'local_id, ' if local else ''}{', '.join((*cols, *dest))}) "
                 f"SELECT uuid, %(pc)s, %(pc_now)s::float8 - extract(epoch FROM clock_timestamp()), "
                 f"{'id, ' if local else ''}{', '.join((*cols, *(f'to_timestamp({t})' for t in times)))} "
                 f"FROM {kind}_r JOIN {kind}_k USING (uuid) ON CONFLICT DO NOTHING RETURNING 1)"]
        counts.append(f"(SELECT count(*) FROM {kind}_i)")
    return f"WITH {', '.join(ctes)} SELECT {' + '.join(counts)}"


RELOOK_S = 60.0  # the log is read at least this often, changed or not


class FatalError(HostdError):
    """What waiting does not mend: the one line says what to do."""


def classify(e: Exception, cfg: FleetCfg) -> Exception:
    """A connection error as FatalError (bad input: one line saying what to do) or as itself (the
    centre is away: wait and try again)."""
    import psycopg

    msg = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
    low = str(e).lower()
    where = cfg.url.split("?")[0]
    if isinstance(e, psycopg.ProgrammingError) or "invalid connection option" in low \
            or "invalid uri" in low or "invalid integer value" in low:
        return FatalError(f"fleet.url {where} is not a valid PostgreSQL URL ({msg}): "
                          f"correct it in {cfg.path}")
    if "password authentication failed" in low or "no password supplied" in low:
        return FatalError(f"the central server refused role {cfg.role}'s password: write the role's password "
                          "in fleet.password_file (or the systemd credential), or reset it on the server "
                          "(hostd fleet add-pc)")
    if "certificate" in low or "ssl error" in low or "sslmode" in low or "server common name" in low \
            or "does not match host name" in low:
        return FatalError(f"TLS to {where} failed ({msg}): the server's certificate does not match "
                          "sslrootcert/the host name, or this PC's client certificate is refused; fix the "
                          f"certificates or sslmode in fleet.url ({cfg.path})")
    if "does not exist" in low and "database" in low:
        return FatalError(f"fleet.url {where}: {msg}: correct the database name in {cfg.path}")
    if "role" in low and "does not exist" in low:
        return FatalError(f"{msg}: create this PC's role on the server (hostd fleet add-pc) or correct "
                          f"fleet.role in {cfg.path}")
    if "could not translate host name" in low or "name or service not known" in low:
        return FatalError(f"fleet.url {where}: unknown host ({msg}): correct the host in {cfg.path}")
    if "no pg_hba.conf entry" in low:
        return FatalError(f"{msg}: the server's pg_hba.conf must let role {cfg.role} in from this PC")
    return e


def _serial(spec: str | None, sysfs: str = "/sys") -> str | None:
    """The USB serial number of the display on a transport spec (hid:/dev/hidrawN, serial:/dev/ttyX,
    usb:BUS/DEV), read from sysfs as udev reads it; None for the simulated display, a pty, or none
    found. Read here, not through hostd.device's enumeration, which would cost the shipper its
    imports (and a thread) for a string taken once every health_interval_s."""
    if not spec or ":" not in spec:
        return None
    kind, _, where = spec.partition(":")
    node = os.path.basename(where)
    try:
        if kind == "hid":
            for line in Path(f"{sysfs}/class/hidraw/{node}/device/uevent").read_text().splitlines():
                if line.startswith("HID_UNIQ="):
                    return line[9:] or None
        elif kind == "serial" and not where.startswith("/dev/pts/"):
            dev = Path(f"{sysfs}/class/tty/{node}/device").resolve()
            for d in (dev, *dev.parents):  # the USB device above the interface
                if (d / "serial").is_file():
                    return (d / "serial").read_text().strip() or None
        elif kind == "usb" and "/" in where:
            bus, num = (int(x) for x in where.split("/"))
            for d in Path(f"{sysfs}/bus/usb/devices").iterdir():
                if (d / "busnum").is_file() and int((d / "busnum").read_text()) == bus \
                        and int((d / "devnum").read_text()) == num:
                    return (d / "serial").read_text().strip() if (d / "serial").is_file() else None
    except (OSError, ValueError):
        pass
    return None


def release_free_heap() -> None:
    """Give the C heap's free pages back to the system (glibc's malloc_trim): what the start-up
    freed (imports, modules compiled where no cached bytecode could be written, the first
    connection's TLS and SCRAM exchange) is otherwise held for the process's life, about 1 MB of
    the shipper's PSS. Nothing elsewhere than glibc."""
    try:
        import ctypes

        ctypes.CDLL(None).malloc_trim(0)
    except (OSError, AttributeError):
        pass


class Shipper:
    def __init__(self, cfg: FleetCfg, clock=time.time, status=None):
        self.cfg = cfg
        self.clock = clock  # this PC's clock (unix s); a test gives it one wrong by hours
        self.status = status if status is not None else self._daemon_status
        self.conn = None
        self.stop_event = threading.Event()
        self.backoff_s = cfg.backoff_min_s
        self.failing_since: float | None = None
        self.last_health = -1e18
        self.last_partitions = -1e18
        self._sig = None
        self._looked = -1e18
        self._more = False
        self.state = self._open_state(Path(cfg.state))
        self.shipped = 0  # rows committed centrally by this process (each counted once)
        self.trim_after_start = False  # release_free_heap() after the first step that went through

    # ------------------------------------------------------------ local files
    @staticmethod
    def _open_state(p: Path) -> sqlite3.Connection:
        p.parent.mkdir(parents=True, exist_ok=True)
        if not p.exists():  # readable by the daemon's group (hostd status), written by the shipper only
            os.close(os.open(p, os.O_WRONLY | os.O_CREAT | os.O_NOFOLLOW, 0o640))
        con = sqlite3.connect(p, timeout=10.0, isolation_level=None)
        con.execute("PRAGMA journal_mode=WAL")
        # NORMAL: a power cut can take the last marks back, never leave the file broken; a mark
        # taken back only sends its rows again, which the centre ignores
        con.execute("PRAGMA synchronous=NORMAL")
        con.executescript(outbox.STATE_SCHEMA)
        return con

    def _signature(self):
        """What changes when the daemon commits: the log's and its -wal's inode, size and mtime."""
        out = []
        for p in (self.cfg.quality_db, self.cfg.quality_db + "-wal"):
            try:
                st = os.stat(p)
                out.append((st.st_ino, st.st_size, st.st_mtime_ns))
            except FileNotFoundError:
                out.append(None)
        return tuple(out)

    def _log(self) -> sqlite3.Connection | None:
        """The daemon's log, read only, beside its writer (WAL), opened for one look and closed: a
        reader held open would see a daemon killed and started again through a stale view, and keep
        the daemon's checkpoints from cutting the -wal. None while it does not exist or cannot be
        read yet (the daemon creating it): tried again at the next look. Never opened immutable, as
        `hostd quality` may open a stopped daemon's log."""
        if not os.path.exists(self.cfg.quality_db):
            return None
        uri = Path(self.cfg.quality_db).absolute().as_uri()
        con = sqlite3.connect(f"{uri}?mode=ro", uri=True, timeout=5.0, isolation_level=None)
        try:
            con.execute("SELECT count(*) FROM sqlite_master").fetchone()
        except sqlite3.OperationalError as e:
            con.close()
            log.debug("the quality log cannot be read yet: %s", e)
            return None
        return con

    def _set_info(self, **kv) -> None:
        self.state.executemany("INSERT INTO info (key, value) VALUES (?, ?) ON CONFLICT (key) DO UPDATE "
                               "SET value = excluded.value", [(k, None if v is None else str(v))
                                                              for k, v in kv.items()])

    # ------------------------------------------------------------ what waits
    def pending(self, limit: int) -> dict[str, list[dict]]:
        """The rows not yet shipped, at most `limit` of each kind, in the log's id order."""
        out: dict[str, list[dict]] = {"streams": [], "plays": [], "health": []}
        sig, now = self._signature(), time.monotonic()
        # unchanged since the last look that found all there was: nothing new (a look every
        # RELOOK_S all the same, for a commit within the file system's mtime tick of the last look)
        fresh = sig != self._sig or self._more or now - self._looked > RELOOK_S
        con = self._log() if fresh else None
        if con is not None:
            try:
                self._read_log(con, limit, out)
            finally:
                con.close()
            self._sig, self._looked = sig, now  # all there was at sig (else: read again next time)
        for hid, uid, taken, doc in self.state.execute(
                "SELECT id, uuid, taken_at, doc FROM health WHERE shipped = 0 ORDER BY id LIMIT ?", (limit,)):
            out["health"].append({"id": hid, "uuid": uid, "taken_at": taken, **json.loads(doc)})
        return out

    def _read_log(self, con: sqlite3.Connection, limit: int, out: dict) -> None:
        self._more = False
        marks = outbox.marks(self.state)
        have = {r[0] for r in con.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        for table, _when in outbox.KINDS:
            if table not in have:
                continue
            if "uuid" not in {r[1] for r in con.execute(f"PRAGMA table_info({table})")}:
                raise sqlite3.OperationalError("the log has no uuid column yet: start (or restart) hostd "
                                               "of this version once, which adds it")
            first = outbox.start_id(con, marks.get(table), table)
            cur = con.execute(f"SELECT * FROM {table} WHERE id > ? ORDER BY id LIMIT ?", (first, limit))
            names = [d[0] for d in cur.description]
            rows = [dict(zip(names, r, strict=True)) for r in cur]
            keyless = next((i for i, r in enumerate(rows) if not r["uuid"]), None)
            if keyless is not None:  # written by an older hostd: keyed at the daemon's next start
                log.warning("the quality log's %s row %d has no uuid (an older hostd wrote it): rows "
                            "from it on wait until hostd of this version starts", table, rows[keyless]["id"])
                rows = rows[:keyless]
            out[table] = rows
            self._more |= len(rows) == limit

    def _daemon_status(self) -> dict | None:
        if not self.cfg.socket or not os.path.exists(self.cfg.socket):
            return None
        from hostd.service.client import request

        try:
            return request(self.cfg.socket, {"cmd": "status"}, timeout_s=2.0)
        except HostdError:
            return None

    def take_health(self) -> None:
        """A device-health summary from the daemon's status, kept in the state file (its outbox)
        before it is shipped: serial, firmware, underruns, played fraction, what waits."""
        st = self.status()
        if not st:
            return
        w = outbox.waiting(self.cfg.quality_db, self.cfg.state) if Path(self.cfg.quality_db).exists() \
            else None
        doc = {"serial": st.get("serial") or _serial(st.get("transport")), "firmware": st.get("firmware"),
               "transport": st.get("transport") or st.get("device"), "device_state": st.get("device_state"),
               "device_underruns": st.get("device_underruns"), "played_fraction": st.get("played_fraction"),
               "stalls": st.get("stalls"), "recoveries": st.get("recoveries"),
               "waiting_rows": w["waiting"] if w else None, "waiting_since": w["since"] if w else None}
        self.state.execute("INSERT INTO health (uuid, taken_at, doc) VALUES (?, ?, ?)",
                           (str(uuid.uuid4()), self.clock(), json.dumps(doc)))

    # ------------------------------------------------------------ the centre
    def connect(self):
        import psycopg

        from hostd.fleet import schema

        try:
            conn = psycopg.connect(self.cfg.url, user=self.cfg.role, password=password(self.cfg),
                                   autocommit=True, connect_timeout=max(1, round(self.cfg.connect_timeout_s)),
                                   application_name="hostd-fleet", options="-c TimeZone=UTC")
        except psycopg.Error as e:
            raise classify(e, self.cfg) from None
        try:
            schema.check_server(conn)
            schema.check_client(conn)
        except BaseException:
            conn.close()
            raise
        self.conn = conn
        self.last_partitions = -1e18
        return conn

    def _close(self) -> None:
        if self.conn is not None:
            try:
                self.conn.close()
            except Exception:
                pass
        self.conn = None

    def ship(self, batch: dict[str, list[dict]]) -> int:
        """One central transaction for the batch; the local marks after its commit. Rows new to
        the centre (those it had already: no-ops)."""
        conn = self.conn
        now_mono = time.monotonic()
        if now_mono - self.last_partitions > 3600:
            conn.execute("SELECT fleet.ensure_partitions()")
            self.last_partitions = now_mono
        kinds = tuple(k for k in KINDS if batch[BATCH_KEYS[k]])
        docs = {kind: json.dumps([{c: r.get(c) for c in ("uuid", "id", *KINDS[kind][0], *KINDS[kind][1])}
                                  for r in batch[BATCH_KEYS[kind]]]) for kind in kinds}
        # one statement, one round trip, its own transaction (autocommit): all of it or none
        new_rows = conn.execute(ship_sql(kinds), {"pc": self.cfg.role, "pc_now": self.clock(), **docs},
                                prepare=True).fetchone()[0] if kinds else 0
        # committed centrally: now, and only now, marked shipped here (a crash in between: sent again,
        # and each row of it a no-op there)
        when = self.clock()
        self.state.execute("BEGIN IMMEDIATE")
        try:
            for table in ("streams", "plays"):
                if batch[table]:
                    last = batch[table][-1]
                    self.state.execute("INSERT INTO marks (kind, last_id, last_uuid, shipped_at) VALUES "
                                       "(?, ?, ?, ?) ON CONFLICT (kind) DO UPDATE SET "
                                       "last_id = excluded.last_id, "
                                       "last_uuid = excluded.last_uuid, shipped_at = excluded.shipped_at",
                                       (table, last["id"], last["uuid"], when))
            self.state.executemany("UPDATE health SET shipped = 1 WHERE id = ?",
                                   [(h["id"],) for h in batch["health"]])
            self.state.execute("COMMIT")
        except BaseException:
            self.state.execute("ROLLBACK")
            raise
        self.shipped += new_rows
        return new_rows

    # ------------------------------------------------------------ the loop
    def step(self) -> int:
        """Take a health summary when due, ship what waits (batch by batch); the rows shipped.
        Connection errors propagate (the caller waits and tries again)."""
        now = time.monotonic()
        if now - self.last_health >= self.cfg.health_interval_s:
            self.last_health = now
            self.take_health()
        total = 0
        while not self.stop_event.is_set():
            batch = self.pending(self.cfg.batch_rows)
            if not any(batch.values()):
                break
            if self.conn is None:
                self.connect()
            total += self.ship(batch)
        return total

    def run(self, once: bool = False) -> int:
        """Ship until stopped (SIGTERM, SIGINT). once: ship what waits now and return; any failure
        is then an error. FatalError stops the loop."""
        import psycopg

        while not self.stop_event.is_set():
            try:
                self.step()
                if self.failing_since is not None:
                    log.info("the central store is back after %.0f s; shipping", time.monotonic()
                             - self.failing_since)
                    self.failing_since = None
                    self._set_info(last_error=None)
                self.backoff_s = self.cfg.backoff_min_s
                if self.trim_after_start:
                    self.trim_after_start = False
                    release_free_heap()
                if once:
                    return 0
                self.stop_event.wait(self.cfg.interval_s)
            except FatalError:
                self._close()
                raise
            except sqlite3.Error as e:  # the local log busy or being replaced: look again soon
                log.warning("reading the quality log: %s; trying again", e)
                self._sig = None
                if once:
                    raise HostdError(f"cannot read the quality log {self.cfg.quality_db}: {e}") from None
                self.stop_event.wait(self.cfg.backoff_min_s)
            except (psycopg.Error, OSError) as e:
                err = classify(e, self.cfg) if isinstance(e, psycopg.Error) else e
                self._close()
                if isinstance(err, FatalError):
                    raise err from None
                if once:
                    why = str(e).strip().splitlines()[0].strip("'") if str(e).strip() else repr(e)
                    raise HostdError(f"cannot ship to {self.cfg.url.split('?')[0]}: {why}: is the "
                                     "central server up and fleet.url right?") from None
                if self.failing_since is None:
                    self.failing_since = time.monotonic()
                    log.warning("the central store is away (%s); rows wait in the local log, retried "
                                "from %.3g s up to every %.3g s", str(e).strip().splitlines()[0] if str(e)
                                else type(e).__name__, self.backoff_s, self.cfg.backoff_max_s)
                self._set_info(last_error=str(e).strip().splitlines()[0] if str(e).strip() else repr(e))
                self.stop_event.wait(self.backoff_s)
                self.backoff_s = min(self.backoff_s * 2, self.cfg.backoff_max_s)
        self._close()
        return 0


def main(cfg: FleetCfg, once: bool = False) -> int:
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    s = Shipper(cfg)
    s.trim_after_start = True  # its own long-lived process: the start-up's garbage given back
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: s.stop_event.set())
    return s.run(once=once)
