"""The fleet's central store (hostd/fleet/, docs/fleet.md) against a real PostgreSQL started here:
exactly once by key and content through retries, replays and kills; each PC confined to its own
rows by the server; bad input stopped with one line; the daemon's log keyed and unaffected.

Under CI=true a missing PostgreSQL fails instead of skipping (./run test installs it)."""

from __future__ import annotations

import os
import re
import sqlite3
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest

from hostd.service import outbox, qualitylog

psycopg = pytest.importorskip("psycopg") if os.environ.get("CI") != "true" else __import__("psycopg")

ROOT = Path(__file__).resolve().parents[1]
PCS = ("pc_a", "pc_b", "pc_c", "pc_d", "pc_e", "pc_f")  # one per test that compares a PC's whole store


def _server_or_fail(**kw):
    from hostd.errors import HostdError
    from hostd.fleet.localpg import LocalPG, bindir

    if bindir() is None:
        msg = "PostgreSQL's server is not installed (./run test installs it: apt-get install postgresql)"
        if os.environ.get("CI") == "true":
            pytest.fail(msg)
        pytest.skip(msg)
    try:
        return LocalPG(**kw)
    except HostdError as e:
        pytest.fail(str(e))


def _certs(d: Path) -> tuple[Path, Path, Path, Path]:
    """A CA that signs the server's certificate (CN localhost, IP 127.0.0.1), and another CA."""
    def ssl(*a):
        subprocess.run(["openssl", *a], check=True, capture_output=True, cwd=d)

    for ca in ("ca", "other"):
        ssl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "2", "-subj", f"/CN={ca}",
            "-keyout", f"{ca}.key", "-out", f"{ca}.pem")
    ssl("req", "-newkey", "rsa:2048", "-nodes", "-subj", "/CN=localhost", "-keyout", "server.key",
        "-out", "server.csr")
    (d / "ext").write_text("subjectAltName=DNS:localhost,IP:127.0.0.1\n")
    ssl("x509", "-req", "-in", "server.csr", "-CA", "ca.pem", "-CAkey", "ca.key", "-CAcreateserial",
        "-days", "2", "-extfile", "ext", "-out", "server.pem")
    for cn in ("pc_cert", "pc_a"):  # client certificates (CN = the role) signed by the same CA
        ssl("req", "-newkey", "rsa:2048", "-nodes", "-subj", f"/CN={cn}", "-keyout", f"{cn}.key",
            "-out", f"{cn}.csr")
        ssl("x509", "-req", "-in", f"{cn}.csr", "-CA", "ca.pem", "-CAkey", "ca.key", "-CAcreateserial",
            "-days", "2", "-out", f"{cn}.pem")
        os.chmod(d / f"{cn}.key", 0o600)
    return d / "ca.pem", d / "other.pem", d / "server.pem", d / "server.key"


@pytest.fixture(scope="module")
def pg(tmp_path_factory):
    """One server for the module: TLS on (its own CA), the schema migrated, the PCs' roles with
    their passwords in root-only files, and a reader."""
    from hostd.cli import main

    d = tmp_path_factory.mktemp("pgcerts")
    ca, other, cert, key = _certs(d)
    server = _server_or_fail(ssl=(str(cert), str(key)), client_ca=str(ca), cert_roles=("pc_cert",))
    server.ca, server.other_ca, server.certs = ca, other, d
    server.pw = {}
    try:
        assert main(["fleet", "migrate", "--url", server.admin_url]) == 0
        for role in (*PCS, "viewer"):
            f = d / f"{role}.pw"
            f.write_text(f"secret-{role}-{uuid.uuid4().hex[:8]}\n")
            os.chmod(f, 0o600)
            server.pw[role] = f
            args = ["fleet", "add-pc", role, "--url", server.admin_url, "--password-file", str(f)]
            assert main([*args, "--reader"] if role == "viewer" else args) == 0
        assert main(["fleet", "add-pc", "pc_cert", "--url", server.admin_url]) == 0  # no password
        yield server
    finally:
        server.close()


def _admin(pg):
    return psycopg.connect(pg.admin_url, autocommit=True)


def _as(pg, role, **kw):
    return psycopg.connect(pg.url(), user=role, password=pg.pw[role].read_text().strip(), **kw)


def _row(i: int, t: float) -> dict:
    """A stream row as the daemon's quality worker writes it (content varies with i)."""
    from hostd.fleet.bench import synthetic_row

    return synthetic_row(i, t)


def _play(i: int, t: float) -> dict:
    return {"name": f"tex{i}", "sha256": f"{i:064x}", "started_at": t, "ended_at": t + 3.5, "device_s": 3.5,
            "played_s": 3.45, "played_fraction": 0.99 - 0.001 * i, "underruns": i % 3}


def _write(db: Path, start: int, n: int, t0: float | None = None) -> None:
    """n stream rows and n plays appended to the log, as the daemon writes them."""
    t0 = time.time() if t0 is None else t0
    con = qualitylog.connect(db)
    try:
        qualitylog.insert_batch(con, [_row(i, t0 + i) for i in range(start, start + n)])
        for i in range(start, start + n):
            qualitylog.insert_play(con, _play(i, t0 + i))
    finally:
        con.close()


def _cfg(tmp: Path, pg, role: str, **over) -> Path:
    kv = {"url": pg.url(sslmode="verify-full", sslrootcert=pg.ca).replace("127.0.0.1", "localhost"),
          "role": role, "password_file": str(pg.pw.get(role, "")), "quality_db": str(tmp / "q.sqlite"),
          "state": str(tmp / "outbox.sqlite"), "socket": "", "interval_s": 0.05, "backoff_min_s": 0.05,
          "backoff_max_s": 0.3, "connect_timeout_s": 2.0, "batch_rows": 7, **over}
    p = tmp / f"fleet-{role}.toml"
    p.write_text("[fleet]\n" + "".join(f"{k} = {v!r}\n".replace("'", '"') if isinstance(v, str)
                                       else f"{k} = {v}\n" for k, v in kv.items()))
    return p


def _local(db: Path) -> dict[str, dict]:
    """uuid -> (kind, content) of every row of the local log."""
    con = sqlite3.connect(db)
    con.row_factory = sqlite3.Row
    out = {}
    for r in con.execute("SELECT * FROM streams"):
        out[r["uuid"]] = ("quality", r["id"], r["sha256"], r["name"], r["bytes"], r["n_keep"], r["ip"],
                          r["iobj"], round(r["received_at"] * 1e6))
    for r in con.execute("SELECT * FROM plays"):
        out[r["uuid"]] = ("play", r["id"], r["sha256"], r["name"], r["underruns"], r["played_fraction"],
                          round(r["started_at"] * 1e6))
    con.close()
    return out


def _central(pg, pc: str) -> tuple[dict, int]:
    """uuid -> (kind, content) of the PC's central rows, and the number of rows (duplicates count)."""
    with _admin(pg) as c:
        q = c.execute("SELECT uuid::text, 'quality', local_id, sha256, name, bytes, n_keep, ip, iobj, "
                      "(extract(epoch FROM pc_received_at) * 1e6)::bigint FROM fleet.quality "
                      "WHERE pc_id = %s", (pc,)).fetchall()
        p = c.execute("SELECT uuid::text, 'play', local_id, sha256, name, underruns, played_fraction, "
                      "(extract(epoch FROM started_at) * 1e6)::bigint FROM fleet.plays "
                      "WHERE pc_id = %s", (pc,)).fetchall()
        keys = c.execute("SELECT count(*) FROM fleet.row_keys WHERE pc_id = %s AND kind <> 'health'",
                         (pc,)).fetchone()[0]
    rows = q + p
    assert keys == len({r[0] for r in rows}), "the ledger and the rows disagree"
    return {r[0]: tuple(r[1:]) for r in rows}, len(rows)


def _assert_exactly_once(pg, pc: str, db: Path) -> int:
    local = _local(db)
    central, n = _central(pg, pc)
    assert n == len(central), f"{n - len(central)} rows doubled centrally"
    # content equal; the PC's time (last) to the microsecond, as timestamptz keeps it
    differ = [(local[k], central[k]) for k in local if k in central and (
        central[k][:-1] != local[k][:-1] or abs(central[k][-1] - local[k][-1]) > 1)]
    assert set(central) == set(local) and not differ, (
        f"missing centrally: {sorted(set(local) - set(central))[:3]}, "
        f"foreign: {sorted(set(central) - set(local))[:3]}, differing: {differ[:2]}")
    return n


def _ship(cfg: Path, *extra: str, env=None, timeout=60) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "hostd", "fleet", "ship", "--config", str(cfg), *extra],
                          capture_output=True, text=True, timeout=timeout, cwd=ROOT,
                          env={**os.environ, "PYTHONPATH": str(ROOT), **(env or {})})


# ---------------------------------------------------------------- the local log's keys
def test_an_old_log_gets_a_stable_uuid_on_every_row_in_place(tmp_path):
    """A log written before rows had keys: the daemon's next connect adds the column and keys every
    row once (the keys stay the same on the next connect); new rows are keyed as written."""
    db = tmp_path / "old.sqlite"
    old = sqlite3.connect(db)
    old.executescript(re.sub(r"\n\s*uuid TEXT[^\n]*", "", qualitylog.SCHEMA)
                      .replace("underruns INTEGER NOT NULL,", "underruns INTEGER NOT NULL"))
    assert "uuid" not in {r[1] for r in old.execute("PRAGMA table_info(streams)")}
    assert "uuid" not in {r[1] for r in old.execute("PRAGMA table_info(plays)")}
    cols = [c for c in qualitylog.COLUMNS if c != "id"]
    for i in range(5):
        r = _row(i, 1e9 + i)
        old.execute(f"INSERT INTO streams ({', '.join(cols)}) VALUES ({', '.join('?' * len(cols))})",
                    [r[c] for c in cols])
        p = _play(i, 1e9 + i)
        old.execute(f"INSERT INTO plays ({', '.join(p)}) VALUES ({', '.join('?' * len(p))})",
                    list(p.values()))
    old.commit()
    old.close()
    qualitylog.connect(db).close()
    first = _local(db)
    assert len(first) == 10 and all(uuid.UUID(k).version == 4 for k in first)
    qualitylog.connect(db).close()
    assert _local(db) == first
    _write(db, 5, 2)
    after = _local(db)
    assert set(first) < set(after) and len(after) == 14


# ---------------------------------------------------------------- exactly once
def test_rows_ship_exactly_once_by_key_and_content_through_replays(pg, tmp_path):
    from hostd.fleet import config
    from hostd.fleet.shipper import Shipper

    db = tmp_path / "q.sqlite"
    _write(db, 0, 20)
    cfg = _cfg(tmp_path, pg, "pc_a")
    r = _ship(cfg, "--once")
    assert r.returncode == 0, r.stderr
    assert _assert_exactly_once(pg, "pc_a", db) == 40
    w = outbox.waiting(db, tmp_path / "outbox.sqlite")
    assert w["waiting"] == 0 and w["since"] is None
    # the whole log replayed (the shipper's marks lost) and one batch sent twice: no-ops
    (tmp_path / "outbox.sqlite").unlink()
    s = Shipper(config.load(cfg))
    batch = s.pending(1000)
    assert len(batch["streams"]) == 20
    s.connect()
    assert s.ship(batch) == 0
    assert s.ship(batch) == 0
    _write(db, 20, 3)
    batch = s.pending(1000)
    assert [r["id"] for r in batch["streams"]] == [21, 22, 23]
    assert s.ship(batch) == 6 and s.ship(batch) == 0
    s._close()
    assert _assert_exactly_once(pg, "pc_a", db) == 46


def test_a_pc_clock_hours_wrong_keeps_its_rows_in_the_servers_month(pg, tmp_path):
    """PC times are kept as the PC said them; the partition is the server's receive time, and
    each row records the PC's clock offset."""
    from hostd.fleet import config
    from hostd.fleet.shipper import Shipper

    skew_s = -5 * 3600.0
    db = tmp_path / "q.sqlite"
    _write(db, 100, 2, t0=time.time() + skew_s - 40 * 86400)  # rows stamped 40 days and 5 h back
    s = Shipper(config.load(_cfg(tmp_path, pg, "pc_b")), clock=lambda: time.time() + skew_s)
    assert s.run(once=True) == 0
    with _admin(pg) as c:
        rows = c.execute("SELECT tableoid::regclass::text, pc_clock_offset_s, received_at, "
                         "extract(epoch FROM received_at - pc_received_at) FROM fleet.quality WHERE pc_id = "
                         "'pc_b' AND name = 'tex100'").fetchall()
        month = c.execute("SELECT to_char(now(), 'YYYYMM')").fetchone()[0]
    assert len(rows) == 1
    part, offset, _received, behind = rows[0]
    assert part == f"fleet.quality_{month}"
    assert abs(offset - skew_s) < 5, offset
    assert behind > 40 * 86400


# ---------------------------------------------------------------- isolation
def test_the_server_confines_each_pc_to_its_own_rows(pg, tmp_path):
    db = tmp_path / "q.sqlite"
    _write(db, 200, 2)
    assert _ship(_cfg(tmp_path, pg, "pc_c"), "--once").returncode == 0
    theirs = str(uuid.uuid4())
    with _as(pg, "pc_a") as c:
        # writing as another PC
        with pytest.raises(psycopg.errors.InsufficientPrivilege, match="row-level security"):
            c.execute("INSERT INTO fleet.row_keys (uuid, pc_id, kind) VALUES (%s, 'pc_c', 'quality')",
                      (theirs,))
        c.rollback()
        with pytest.raises(psycopg.errors.InsufficientPrivilege, match="row-level security"):
            c.execute("INSERT INTO fleet.plays (uuid, pc_id, pc_clock_offset_s, local_id, name, sha256, "
                      "started_at, ended_at, device_s, played_s, underruns) VALUES (%s, 'pc_c', 0, 1, 'x', "
                      "'y', now(), now(), 1, 1, 0)", (theirs,))
        c.rollback()
        # reading others' rows: none visible, through the parent or a partition
        for t in ("quality", "plays", "row_keys"):
            assert c.execute(f"SELECT count(*) FROM fleet.{t} WHERE pc_id <> 'pc_a'").fetchone()[0] == 0
        month = c.execute("SELECT to_char(now(), 'YYYYMM')").fetchone()[0]
        with pytest.raises(psycopg.errors.InsufficientPrivilege):
            c.execute(f"SELECT count(*) FROM fleet.quality_{month}")
        c.rollback()
        # altering a shipped row, its own or another's
        for sql in ("UPDATE fleet.quality SET iobj = 0", "DELETE FROM fleet.plays",
                    "UPDATE fleet.row_keys SET pc_id = 'pc_a'", "TRUNCATE fleet.quality"):
            with pytest.raises(psycopg.errors.InsufficientPrivilege):
                c.execute(sql)
            c.rollback()
    with _as(pg, "viewer") as c:  # the views' role reads every PC and writes nothing
        assert c.execute("SELECT count(*) FROM fleet.quality WHERE pc_id = 'pc_c'").fetchone()[0] == 2
        with pytest.raises(psycopg.errors.InsufficientPrivilege):
            c.execute("INSERT INTO fleet.row_keys (uuid, pc_id, kind) VALUES (%s, 'viewer', 'quality')",
                      (theirs,))
    _assert_exactly_once(pg, "pc_c", db)


# ---------------------------------------------------------------- bad input
def _one_line(r: subprocess.CompletedProcess, *words: str) -> str:
    assert r.returncode != 0, r.stdout
    lines = [ln for ln in r.stderr.strip().splitlines() if ln.strip()]
    assert len(lines) == 1, r.stderr
    for w in words:
        assert w in lines[0], lines[0]
    print(lines[0])
    return lines[0]


def test_bad_input_gets_one_line_and_a_nonzero_exit(pg, tmp_path):
    db = tmp_path / "q.sqlite"
    _write(db, 0, 1)
    good = pg.url(sslmode="verify-full", sslrootcert=pg.ca).replace("127.0.0.1", "localhost")
    # a wrong URL: an unknown database, a port where nothing listens, no URL at all
    _one_line(_ship(_cfg(tmp_path, pg, "pc_a", url=good.replace("/postgres?", "/nosuchdb?")), "--once"),
              "nosuchdb", "correct the database name")
    _one_line(_ship(_cfg(tmp_path, pg, "pc_a", url=good.replace(f":{pg.port}/", ":1/")), "--once"),
              "is the central server up and fleet.url right?")
    _one_line(_ship(_cfg(tmp_path, pg, "pc_a", url="http://example.org/")), "not a postgresql:// URL")
    _one_line(_ship(_cfg(tmp_path, pg, "pc_a", url=good.replace("//localhost", "//pc_a:pw@localhost"))),
              "carries a password")
    # a wrong password (the long-running shipper stops too: waiting does not mend it)
    wrong = tmp_path / "wrong.pw"
    wrong.write_text("not-it\n")
    os.chmod(wrong, 0o600)
    _one_line(_ship(_cfg(tmp_path, pg, "pc_a", password_file=str(wrong))), "refused role pc_a's password")
    # a password file others can read
    os.chmod(wrong, 0o640)
    _one_line(_ship(_cfg(tmp_path, pg, "pc_a", password_file=str(wrong)), "--once"), "chmod 600")
    # a certificate that does not match: the server's is signed by another CA than the PC trusts
    _one_line(_ship(_cfg(tmp_path, pg, "pc_a", url=good.replace(str(pg.ca), str(pg.other_ca)))),
              "TLS", "certificate")
    assert outbox.waiting(db, tmp_path / "outbox.sqlite")["waiting"] == 2  # nothing lost


def test_a_server_of_an_unsupported_major_version_is_refused(pg, tmp_path, monkeypatch, capsys):
    from hostd.cli import main
    from hostd.fleet import schema

    _write(tmp_path / "q.sqlite", 0, 1)
    monkeypatch.setattr(schema, "SUPPORTED_MAJORS", range(9, 12))
    assert main(["fleet", "ship", "--once", "--config", str(_cfg(tmp_path, pg, "pc_a"))]) != 0
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and "supports 9..11" in err[0], err


def test_an_older_pc_keeps_shipping_and_a_schema_too_new_stops_it(pg, tmp_path):
    """A second, additive migration (min_client 1): this PC, which knows 1, ships on. A third that
    needs clients of version 3: it stops with one line to upgrade hostd."""
    from hostd.cli import main
    from hostd.fleet import schema

    with _admin(pg) as c:
        c.execute("CREATE DATABASE newer")
    url = pg.admin_url.replace("/postgres?", "/newer?")
    extra = tmp_path / "sql"
    extra.mkdir()
    (extra / f"{schema.KNOWN + 1:03d}_note.sql").write_text(
        "-- min_client: 1\nALTER TABLE fleet.quality ADD COLUMN note text;\n")
    assert main(["fleet", "migrate", "--url", url, "--extra", str(extra)]) == 0
    assert main(["fleet", "migrate", "--url", url, "--extra", str(extra)]) == 0  # applied once
    db = tmp_path / "q.sqlite"
    _write(db, 0, 3)
    cfg = _cfg(tmp_path, pg, "pc_a", url=pg.url(db="newer", sslmode="require"))
    assert _ship(cfg, "--once").returncode == 0
    with psycopg.connect(url) as c:
        assert c.execute("SELECT count(*), count(note) FROM fleet.quality").fetchone() == (3, 0)
        assert c.execute("SELECT max(version) FROM fleet.schema_version").fetchone()[0] == schema.KNOWN + 1
    (extra / f"{schema.KNOWN + 2:03d}_break.sql").write_text(
        f"-- min_client: {schema.KNOWN + 2}\nALTER TABLE fleet.quality ADD COLUMN must text;\n")
    assert main(["fleet", "migrate", "--url", url, "--extra", str(extra)]) == 0
    _write(db, 3, 1)
    _one_line(_ship(cfg, "--once"), f"knows {schema.KNOWN}", "upgrade hostd on this PC")
    assert outbox.waiting(db, tmp_path / "outbox.sqlite")["waiting"] == 2


def test_the_default_largest_backoff_is_at_least_a_minute(tmp_path):
    from hostd.fleet import config

    p = tmp_path / "f.toml"
    p.write_text('[fleet]\nurl = "postgresql://h/db"\nrole = "pc_x"\n')
    assert config.load(p).backoff_max_s >= 60.0


# ---------------------------------------------------------------- crashes at the two edges of a commit
class _CrashAfterCommit:
    """The state file, as a shipper killed right after the central commit sees it: the marks never
    written (the process is gone before its local transaction)."""

    def __init__(self, con):
        self.con = con

    def execute(self, sql, *a):
        if sql.startswith("BEGIN IMMEDIATE"):
            raise KeyboardInterrupt("killed between the central commit and the local mark")
        return self.con.execute(sql, *a)

    def __getattr__(self, name):
        return getattr(self.con, name)


def test_a_shipper_killed_either_side_of_the_central_commit_loses_and_doubles_nothing(pg, tmp_path):
    from hostd.fleet import config
    from hostd.fleet.shipper import Shipper

    db = tmp_path / "q.sqlite"
    _write(db, 300, 4)
    cfg = config.load(_cfg(tmp_path, pg, "pc_d"))
    # killed before the commit: the server is cut off mid-transaction (its backend terminated)
    s = Shipper(cfg)
    s.connect()
    pid = s.conn.info.backend_pid
    with _admin(pg) as c:
        c.execute("SELECT pg_terminate_backend(%s)", (pid,))
    with pytest.raises(psycopg.OperationalError):
        s.ship(s.pending(100))
    assert outbox.waiting(db, cfg.state)["waiting"] == 8
    with _admin(pg) as c:
        assert c.execute("SELECT count(*) FROM fleet.quality WHERE name = 'tex300'").fetchone()[0] == 0
    # killed after the commit, before the mark: the rows are central, the marks are not
    s = Shipper(cfg)
    s.connect()
    s.state = _CrashAfterCommit(s.state)
    with pytest.raises(KeyboardInterrupt):
        s.ship(s.pending(100))
    s._close()
    assert outbox.waiting(db, cfg.state)["waiting"] == 8
    # the next shipper sends them again: each a no-op, then marked
    s = Shipper(cfg)
    assert s.run(once=True) == 0 and s.shipped == 0
    assert outbox.waiting(db, cfg.state)["waiting"] == 0
    _assert_exactly_once(pg, "pc_d", db)


def test_the_password_from_a_systemd_credential_and_the_unit_keeps_it_out_of_argv(pg, tmp_path):
    import shutil

    creds = tmp_path / "creds"
    creds.mkdir()
    shutil.copy(pg.pw["pc_e"], creds / "hostd-fleet-password")
    os.chmod(creds / "hostd-fleet-password", 0o400)
    _write(tmp_path / "q.sqlite", 400, 1)
    r = _ship(_cfg(tmp_path, pg, "pc_e", password_file=""), "--once",
              env={"CREDENTIALS_DIRECTORY": str(creds)})
    assert r.returncode == 0, r.stderr
    unit = (ROOT / "systemd" / "hostd-fleet.service").read_text()
    assert "LoadCredential=hostd-fleet-password:" in unit
    exec_start = next(ln for ln in unit.splitlines() if ln.startswith("ExecStart="))
    assert exec_start.split()[1:] == ["fleet", "ship", "--config", "/etc/hostd/fleet.toml"]
    if shutil.which("systemd-analyze"):
        f = tmp_path / "hostd-fleet.service"
        f.write_text(unit.replace("/opt/hostd/bin/hostd", shutil.which("true")))
        out = subprocess.run(["systemd-analyze", "security", "--offline=true", str(f)], capture_output=True,
                             text=True, timeout=60)
        m = re.search(r"Overall exposure level for hostd-fleet.service: (\d+\.\d)", out.stdout)
        assert m and float(m.group(1)) <= 2.0, out.stdout[-300:]


def test_doctor_says_how_many_rows_wait_and_since_when(pg, tmp_path, monkeypatch, capsys):
    from hostd.cli import main

    db = tmp_path / "q.sqlite"
    _write(db, 500, 2, t0=1.7e9)
    (tmp_path / "hostd.toml").write_text(f'[device]\ntransport = "sim"\n[quality]\ndb = "{db}"\n'
                                         f'[control]\nsocket = "{tmp_path / "none.sock"}"\n')
    monkeypatch.setenv("HOSTD_FLEET_STATE", str(tmp_path / "outbox.sqlite"))
    main(["doctor", "--config", str(tmp_path / "hostd.toml")])
    assert "fleet:" not in capsys.readouterr().out  # no shipper on this PC: nothing said
    bad = tmp_path / "bad.pw"
    bad.write_text("nope\n")
    os.chmod(bad, 0o600)
    assert _ship(_cfg(tmp_path, pg, "pc_e", password_file=str(bad)), "--once").returncode != 0
    main(["doctor", "--config", str(tmp_path / "hostd.toml")])
    out = capsys.readouterr().out
    assert "fleet: 4 rows wait to be shipped, the oldest since 2023-11-14T22:21:40+00:00" in out, out
    assert _ship(_cfg(tmp_path, pg, "pc_e"), "--once").returncode == 0
    main(["doctor", "--config", str(tmp_path / "hostd.toml")])
    assert "fleet: nothing waits to be shipped" in capsys.readouterr().out


def test_the_display_serial_is_read_from_sysfs_as_udev_has_it(tmp_path):
    from hostd.fleet.shipper import _serial

    hid = tmp_path / "class/hidraw/hidraw3/device"
    hid.mkdir(parents=True)
    (hid / "uevent").write_text("DRIVER=hid-generic\nHID_NAME=hostd display\nHID_UNIQ=VT-00042\n")
    usb = tmp_path / "devices/usb1/1-2"
    (usb / "1-2:1.0/tty/ttyACM0").mkdir(parents=True)
    (usb / "serial").write_text("VT-00043\n")
    (tmp_path / "class/tty/ttyACM0").mkdir(parents=True)
    (tmp_path / "class/tty/ttyACM0/device").symlink_to(usb / "1-2:1.0")
    s = str(tmp_path)
    assert _serial("hid:/dev/hidraw3", s) == "VT-00042"
    assert _serial("serial:/dev/ttyACM0", s) == "VT-00043"
    assert _serial("serial:/dev/pts/4", s) is None and _serial("sim", s) is None
    assert _serial("hid:/dev/hidraw9", s) is None


def test_a_pc_logs_in_with_its_tls_client_certificate_and_not_with_anothers(pg, tmp_path):
    db = tmp_path / "q.sqlite"
    _write(db, 600, 2)
    base = pg.url(sslmode="verify-full", sslrootcert=pg.ca).replace("127.0.0.1", "localhost")
    d = pg.certs

    def with_cert(cn):
        return _cfg(tmp_path, pg, "pc_cert",
                    url=f"{base}&sslcert={d / f'{cn}.pem'}&sslkey={d / f'{cn}.key'}")

    # another PC's certificate, presented as this PC's role: refused by the server
    _one_line(_ship(with_cert("pc_a"), "--once"), "TLS", "client certificate")
    r = _ship(with_cert("pc_cert"), "--once")
    assert r.returncode == 0, r.stderr
    _assert_exactly_once(pg, "pc_cert", db)


def test_a_batch_sends_only_its_own_kinds_and_each_ships_exactly_once(pg, tmp_path):
    """The batch's statement names only the kinds it carries (the server analyses and plans a third
    of the usual three-kind statement for a lone stream row: on a pooled connection that changes
    role, every batch); batches of one kind, of two, and of health alone all commit exactly once."""
    from hostd.fleet import config
    from hostd.fleet.shipper import Shipper, ship_sql

    for kinds, table in ((("quality",), "quality"), (("play",), "plays"), (("health",), "health")):
        sql = ship_sql(kinds)
        others = {"quality", "plays", "health"} - {table}
        assert f"fleet.{table} " in sql and not any(f"fleet.{t} " in sql for t in others), sql[:200]
    db = tmp_path / "q.sqlite"
    con = qualitylog.connect(db)
    t0 = time.time()
    qualitylog.insert_batch(con, [_row(i, t0 + i) for i in range(4)])  # stream rows alone
    s = Shipper(config.load(_cfg(tmp_path, pg, "pc_f")), status=lambda: {"firmware": "0.6.0"})
    s.connect()
    assert s.ship(s.pending(100)) == 4
    qualitylog.insert_play(con, _play(10, t0))  # a play alone
    assert s.ship(s.pending(100)) == 1
    s.take_health()  # health alone, then all three kinds in one batch
    assert s.ship(s.pending(100)) == 1
    qualitylog.insert_batch(con, [_row(20, t0)])
    qualitylog.insert_play(con, _play(21, t0))
    s.take_health()
    batch = s.pending(100)
    assert [len(batch[k]) for k in ("streams", "plays", "health")] == [1, 1, 1]
    assert s.ship(batch) == 3 and s.ship(batch) == 0  # sent again: no-ops
    assert s.ship({"streams": [], "plays": [], "health": []}) == 0  # nothing: no statement
    con.close()
    s._close()
    assert _assert_exactly_once(pg, "pc_f", db) == 7
    with _admin(pg) as c:
        assert c.execute("SELECT count(*), count(DISTINCT uuid) FROM fleet.health WHERE pc_id = 'pc_f'"
                         ).fetchone() == (2, 2)


def test_the_shipper_process_leaves_out_what_psycopg_imports_for_nothing():
    """The lean entry's stand-ins (as `hostd fleet ship` runs: on the system's libpq): psycopg works
    and knows its own version without importlib.metadata, TypeVar(default=) without
    typing_extensions; any other use of typing_extensions gets the real module."""
    import importlib.metadata

    code = ("import json, sys; from hostd.fleet.__main__ import _lighter_psycopg; _lighter_psycopg(); "
            "from hostd.fleet.cli import _prefer_system_libpq; _prefer_system_libpq(); "
            "import psycopg; from hostd.fleet import shipper; "
            "out = {'metadata': 'importlib.metadata' in sys.modules, "
            "'te_real': hasattr(sys.modules['typing_extensions'], '__file__'), "
            "'version': psycopg.__version__}; "
            "from typing_extensions import Literal; import typing_extensions; "
            "out['te_after'] = hasattr(sys.modules['typing_extensions'], '__file__') and "
            "typing_extensions.Literal is Literal; print(json.dumps(out))")
    r = subprocess.run([sys.executable, "-OO", "-c", code], capture_output=True, text=True, cwd=ROOT,
                       env={**os.environ, "PYTHONPATH": str(ROOT)}, timeout=60)
    assert r.returncode == 0, r.stderr
    import json

    out = json.loads(r.stdout)
    assert out == {"metadata": False, "te_real": False, "version": importlib.metadata.version("psycopg"),
                   "te_after": True}


def test_the_shipper_short_run_measures_its_pss_and_cpu_per_commit():
    """What CI's short soak holds: the shipper (its own process, a live server, a row a second,
    looking every second here) commits several times in 4 s, every row arrives, its PSS is within
    the budget, and its CPU is given per central commit, not as a share of the default look's."""
    from hostd.bench.guards import FLEET_PSS_MB
    from hostd.fleet.bench import measure
    from hostd.fleet.localpg import bindir

    if bindir() is None:
        _server_or_fail()
    out = measure(4.0, interval_s=1.0)
    assert out["fleet_commits"] >= 2 and out["fleet_rows_central"] == out["fleet_rows"] >= 4
    assert "fleet_cpu_share" not in out and out["fleet_cpu_ms_per_commit"] > 0
    assert out["fleet_pss_mb"] <= FLEET_PSS_MB.goal and out["fleet_threads"] == 1


def test_install_service_installs_the_shippers_unit_and_user_when_asked(tmp_path, capsys):
    """`hostd install-service --fleet` stages hostd-fleet.service (pointed at this hostd, the
    password still a systemd credential) and its sysusers file beside the daemon's; without
    --fleet, neither."""
    from hostd.cli import main

    exe = "/opt/lab/bin/hostd"
    assert main(["install-service", "--prefix", str(tmp_path / "plain"), "--exec", exe]) == 0
    assert not (tmp_path / "plain/etc/systemd/system/hostd-fleet.service").exists()
    assert not (tmp_path / "plain/etc/sysusers.d/hostd-fleet.conf").exists()
    root = tmp_path / "fleet"
    assert main(["install-service", "--prefix", str(root), "--exec", exe, "--fleet"]) == 0
    out = capsys.readouterr().out
    unit = (root / "etc/systemd/system/hostd-fleet.service").read_text()
    assert f"ExecStart={exe} fleet ship --config /etc/hostd/fleet.toml" in unit
    assert "/opt/hostd/bin/hostd" not in unit
    assert "LoadCredential=hostd-fleet-password:/etc/hostd/fleet.password" in unit
    assert oct((root / "etc/systemd/system/hostd-fleet.service").stat().st_mode & 0o777) == "0o644"
    assert "u hostd-fleet " in (root / "etc/sysusers.d/hostd-fleet.conf").read_text()
    assert (root / "etc/systemd/system/hostd.service").exists()  # the daemon's unit as before
    assert "systemctl enable --now hostd-fleet" in out and "fleet.toml" in out
