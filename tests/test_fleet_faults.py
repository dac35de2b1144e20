"""Three real daemons (`hostd run` on the simulated display) play while their shippers (`hostd fleet
ship`, its own process each) send to a real PostgreSQL that is stopped longer than the shippers'
largest backoff, crashed, and started again; a shipper and a daemon are SIGKILLed at random points
meanwhile. Afterwards every row of each local log is in the central store exactly once, compared
row by row on key and content; the plays went on while the centre was away; `hostd status` said
what waited and since when."""

from __future__ import annotations

import os
import random
import signal
import sqlite3
import subprocess
import sys
import time

import pytest

from hostd.cli import main
from hostd.service import outbox
from hostd.service.client import request, send_file
from tests.daemon_helpers import wait_for
from tests.test_fleet import ROOT, _assert_exactly_once, _server_or_fail

psycopg = pytest.importorskip("psycopg") if os.environ.get("CI") != "true" else __import__("psycopg")

PCS = ("pc_x", "pc_y", "pc_z")
BACKOFF_MAX_S = 0.4


def _env():
    return {**os.environ, "PYTHONPATH": str(ROOT), "OPENBLAS_NUM_THREADS": "1"}


class PC:
    """A display PC: its daemon, its shipper, their files."""

    def __init__(self, tmp, name, pg, pw):
        self.name, self.dir = name, tmp / name
        self.dir.mkdir()
        self.db = self.dir / "q.sqlite"
        self.sock = str(self.dir / "hostd.sock")
        self.state = self.dir / "outbox.sqlite"
        (self.dir / "hostd.toml").write_text(
            '[device]\ntransport = "sim"\n[library]\ndir = "lib"\nspool = "spool"\n'
            '[control]\nsocket = "hostd.sock"\ngroup = ""\n[quality]\ndb = "q.sqlite"\n')
        (self.dir / "fleet.toml").write_text(
            f'[fleet]\nurl = "{pg.url()}"\nrole = "{name}"\npassword_file = "{pw}"\n'
            f'quality_db = "{self.db}"\nstate = "{self.state}"\nsocket = "{self.sock}"\n'
            f"interval_s = 0.1\nhealth_interval_s = 0.5\nbatch_rows = 2\nbackoff_min_s = 0.05\n"
            f"backoff_max_s = {BACKOFF_MAX_S}\nconnect_timeout_s = 2\n")
        self.daemon = self.shipper = None

    def start_daemon(self):
        self.daemon = subprocess.Popen([sys.executable, "-m", "hostd", "run", "--config", "hostd.toml"],
                                       cwd=self.dir, env=_env(), start_new_session=True,
                                       stderr=open(self.dir / "hostd.log", "a"))

    def start_shipper(self):
        self.shipper = subprocess.Popen([sys.executable, "-m", "hostd", "fleet", "ship", "--config",
                                         str(self.dir / "fleet.toml")], cwd=self.dir, env=_env(),
                                        start_new_session=True, stderr=open(self.dir / "fleet.log", "a"))

    def kill(self, which):
        p = getattr(self, which)
        os.killpg(p.pid, signal.SIGKILL)
        p.wait(10)

    def status(self):
        return request(self.sock, {"cmd": "status"}, timeout_s=2)

    def plays(self) -> int:
        con = sqlite3.connect(self.db)
        try:
            return con.execute("SELECT count(*) FROM plays").fetchone()[0]
        finally:
            con.close()

    def close(self):
        for which in ("shipper", "daemon"):
            p = getattr(self, which)
            if p is not None and p.poll() is None:
                os.killpg(p.pid, signal.SIGTERM)
                try:
                    p.wait(10)
                except subprocess.TimeoutExpired:
                    self.kill(which)


def _central_n(pg) -> int:
    with psycopg.connect(pg.admin_url) as c:
        return c.execute("SELECT count(*) FROM fleet.row_keys").fetchone()[0]


def test_three_daemons_ship_exactly_once_through_outages_and_kills(tmp_path):
    rng = random.Random(os.getpid())
    pg = _server_or_fail()
    pcs = []
    try:
        assert main(["fleet", "migrate", "--url", pg.admin_url]) == 0
        for name in PCS:
            pw = tmp_path / f"{name}.pw"
            pw.write_text(f"pw-{name}\n")
            os.chmod(pw, 0o600)
            assert main(["fleet", "add-pc", name, "--url", pg.admin_url, "--password-file", str(pw)]) == 0
            pcs.append(PC(tmp_path, name, pg, pw))
        vtx = []
        for i, levels in enumerate((10, 14, 18, 22)):
            f = tmp_path / f"t{i}.vtx"
            assert main(["encode", f"synthetic:wood:{i + 1}", "-o", str(f), "--method", "quant",
                         "--levels", str(levels)]) == 0
            vtx.append(f)
        for pc in pcs:
            pc.start_daemon()
            pc.start_shipper()
        for pc in pcs:
            wait_for(lambda pc=pc: pc.status()["connected"], 60, f"{pc.name}'s daemon")

        def play_round(k: int) -> None:
            for pc in pcs:
                send_file(pc.sock, str(vtx[k % len(vtx)]), f"tex{k}")
                request(pc.sock, {"cmd": "select", "name": f"tex{k}"}, timeout_s=5)

        for k in range(3):
            play_round(k)
        wait_for(lambda: _central_n(pg) >= 3 * 4, 30, "the first rows centrally")
        # the centre goes away (a clean stop, then a crash) for longer than the largest backoff;
        # the daemons play on, and a shipper and a daemon are killed at random points meanwhile
        for mode, rounds in (("fast", range(3, 6)), ("immediate", range(6, 9))):
            pg.stop(mode)
            t_down = time.monotonic()
            before = [pc.plays() for pc in pcs]
            for k in rounds:
                t0 = time.monotonic()
                play_round(k)
                assert time.monotonic() - t0 < 5, "a select waited"
                time.sleep(rng.uniform(0.05, 0.3))
            victim = pcs[rng.randrange(3)]
            victim.kill("shipper")
            victim.start_shipper()
            wait_for(lambda before=before: all(pc.plays() > b for pc, b in zip(pcs, before, strict=True)), 20,
                     "plays logged while the centre is away")
            while time.monotonic() - t_down < 3 * BACKOFF_MAX_S:
                time.sleep(0.05)
            w = outbox.waiting(pcs[0].db, pcs[0].state)
            assert w["waiting"] > 0 and w["since"] is not None
            out = subprocess.run([sys.executable, "-m", "hostd", "status", "--config", "hostd.toml"],
                                 cwd=pcs[0].dir, capture_output=True, text=True, env={
                                     **_env(), "HOSTD_FLEET_STATE": str(pcs[0].state)}, timeout=30)
            assert out.returncode == 0, out.stderr
            assert "rows wait to be shipped, the oldest since" in out.stdout, out.stdout
            pg.start()
            # kills at random points while the backlog drains
            time.sleep(rng.uniform(0.0, 0.4))
            pcs[rng.randrange(3)].kill("shipper")
            for pc in pcs:
                if pc.shipper.poll() is not None:
                    pc.start_shipper()
        dead = pcs[rng.randrange(3)]
        dead.kill("daemon")  # the daemon SIGKILLed mid-play: its log keeps what it committed
        dead.start_daemon()
        wait_for(lambda: dead.status()["connected"], 60, "the daemon again")
        play_round(9)
        # the daemons stop here (SIGTERM: what plays is logged as they end), so nothing writes a
        # local log any more: the rows there are the acknowledged ones, and every one of them must
        # reach the centre exactly once (a row scored or logged after the check below would be a
        # race of the test, not a loss)
        assert all(pc.daemon.poll() is None for pc in pcs), "a daemon died"
        for pc in pcs:
            os.killpg(pc.daemon.pid, signal.SIGTERM)
        for pc in pcs:
            pc.daemon.wait(30)
        for pc in pcs:
            t_end = time.monotonic() + 30
            while outbox.waiting(pc.db, pc.state)["waiting"] and time.monotonic() < t_end:
                time.sleep(0.05)
            assert not outbox.waiting(pc.db, pc.state)["waiting"], (
                pc.name, outbox.waiting(pc.db, pc.state), pc.shipper.poll(),
                sqlite3.connect(pc.state).execute("SELECT * FROM marks").fetchall(),
                sqlite3.connect(pc.state).execute("SELECT * FROM health WHERE shipped = 0").fetchall(),
                sqlite3.connect(pc.db).execute("SELECT id, uuid, name FROM streams").fetchall(),
                sqlite3.connect(pc.db).execute("SELECT id, uuid, name FROM plays").fetchall(),
                (pc.dir / "fleet.log").read_text()[-800:])
        for pc in pcs:
            n = _assert_exactly_once(pg, pc.name, pc.db)
            assert n >= 2 * 10 - 2, n  # streams and plays of ten rounds (a killed play is not a row)
        with psycopg.connect(pg.admin_url) as c:
            health = c.execute("SELECT pc_id, count(*), count(firmware), max(transport) FROM fleet.health "
                               "GROUP BY pc_id ORDER BY pc_id").fetchall()
        assert [h[0] for h in health] == list(PCS), health
        assert all(h[1] >= 2 and h[2] >= 1 for h in health), health
    finally:
        for pc in pcs:
            pc.close()
            print((pc.dir / "fleet.log").read_text()[-1500:] if (pc.dir / "fleet.log").exists() else "")
        pg.close()
