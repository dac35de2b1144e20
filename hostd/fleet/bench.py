"""The shipper's cost, measured: `hostd fleet ship` (its own process, its default config) against a
live PostgreSQL (a throwaway server, localpg) while the quality log grows by `rows_per_s` rows a
second, each a stream row as the daemon writes it. Its CPU share (every thread's time on a CPU,
schedstat, as `hostd bench soak` measures the daemon) and its peak PSS over the run; and every
row written is checked to be central at the end (a cost is worth nothing for a shipper that
ships nothing). `hostd bench soak` runs it beside the daemon (its --check holds the budget)."""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from hostd.errors import HostdError


def synthetic_row(i: int, t: float) -> dict:
    """A stream row as the daemon's quality worker writes it (its content varies with i)."""
    return {"sha256": f"{i:064x}", "name": f"tex{i}", "received_at": t, "scored_at": t + 0.25,
            "bytes": 100 + i, "method": "quant", "levels": 14, "b0_db": None, "n": 512, "n_keep": 300 + i,
            "length_mm": 120.0, "speed_mm_s": 50.0, "curve_id": "ab" * 8, "ratio_coeffs": 0.5,
            "ratio_profile": 0.25, "ip": 0.01 * i, "ia": 0.002 * i, "iobj": 0.011 * i, "a": 1.0, "b": 0.5,
            "calibration": None}


def _shipped(db: Path, state: Path) -> bool:
    """Whether the shipper has committed a batch centrally (its state file can exist before its
    tables: the shipper creating it)."""
    import sqlite3

    from hostd.service import outbox

    try:
        return state.exists() and bool(outbox.waiting(db, state)["last_shipped_at"])
    except sqlite3.OperationalError:
        return False


def measure(seconds: float = 30.0, rows_per_s: float = 1.0, db: str | Path | None = None,
            socket: str = "", interval_s: float | None = None) -> dict:
    """{"fleet_cpu_share", "fleet_cpu_ms_per_commit", "fleet_commits", "fleet_pss_mb", "fleet_threads",
    "fleet_rows", "fleet_rows_central"}. db: the log to grow (default: one of its own); socket: the
    daemon's, for the health summaries. interval_s: the shipper's look (default: its config's
    default); with another one its CPU share says nothing of the default's and is left out, while
    its CPU per central commit (a look that found rows: the cost the share is made of) holds: a
    short run (CI's) looks every 2 s to see commits at all in a few seconds."""
    import psycopg

    from hostd.fleet import schema
    from hostd.fleet.localpg import LocalPG
    from hostd.procstat import CpuClock, pss_kb, threads
    from hostd.service import outbox, qualitylog

    pg = LocalPG()
    shipper = None
    stop = threading.Event()
    try:
        with tempfile.TemporaryDirectory(prefix="hostd-fleet-bench-") as tmp:
            d = Path(tmp)
            db = Path(db) if db else d / "q.sqlite"
            pw = d / "pc.pw"
            pw.write_text("bench-password\n")
            os.chmod(pw, 0o600)
            with psycopg.connect(pg.admin_url, autocommit=True) as c:
                schema.migrate(c)
                c.execute("CREATE ROLE pc_bench LOGIN IN ROLE hostd_pc PASSWORD 'bench-password'")
            cfg = d / "fleet.toml"
            cfg.write_text(f'[fleet]\nurl = "{pg.url()}"\nrole = "pc_bench"\npassword_file = "{pw}"\n'
                           f'quality_db = "{db}"\nstate = "{d / "outbox.sqlite"}"\nsocket = "{socket}"\n'
                           + (f"interval_s = {interval_s}\n" if interval_s is not None else ""))
            qualitylog.connect(db).close()
            written = [0]

            def writer():  # one row each 1/rows_per_s s, committed as the daemon commits it
                con = qualitylog.connect(db)
                try:
                    while not stop.wait(1.0 / rows_per_s):
                        qualitylog.insert_batch(con, [synthetic_row(10**6 + written[0], time.time())])
                        written[0] += 1
                finally:
                    con.close()

            shipper = subprocess.Popen([sys.executable, "-m", "hostd", "fleet", "ship", "--config", str(cfg)],
                                       stdout=subprocess.DEVNULL, stderr=open(d / "fleet.log", "w"),
                                       env={**os.environ, "OPENBLAS_NUM_THREADS": "1"})  # as the unit
            w = threading.Thread(target=writer, daemon=True)
            w.start()
            # its start-up (imports, the first connection and its SCRAM exchange) is not the steady
            # state: measured from its first central commit on
            t_first = time.monotonic() + 60
            while not _shipped(db, d / "outbox.sqlite"):
                if time.monotonic() > t_first or shipper.poll() is not None:
                    raise HostdError(f"the shipper did not ship: {(d / 'fleet.log').read_text()[-300:]}")
                time.sleep(0.2)
            clock = CpuClock(shipper.pid)
            peak_pss = peak_threads = 0
            t0, w0 = time.monotonic(), time.time()
            while (el := time.monotonic() - t0) < seconds:
                time.sleep(min(1.0, seconds - el))
                clock.sample()
                peak_pss = max(peak_pss, pss_kb(shipper.pid))
                peak_threads = max(peak_threads, threads(shipper.pid))
            wall = time.monotonic() - t0
            cpu_s = clock.elapsed_s()
            w1 = time.time()
            stop.set()
            w.join(10)
            t_end = time.monotonic() + 30
            while (outbox.waiting(db, d / "outbox.sqlite") or {"waiting": 1})["waiting"] and \
                    time.monotonic() < t_end:
                time.sleep(0.2)
            if shipper.poll() is not None:
                raise HostdError(f"the shipper stopped: {(d / 'fleet.log').read_text()[-300:]}")
            with psycopg.connect(pg.admin_url) as c:
                central = c.execute("SELECT count(*) FROM fleet.quality WHERE name LIKE 'tex1______'"
                                    ).fetchone()[0]
                # the central commits in the window: a batch's rows share its transaction's now()
                commits = c.execute("SELECT count(DISTINCT received_at) FROM fleet.quality WHERE received_at "
                                    ">= to_timestamp(%s) AND received_at < to_timestamp(%s)", (w0, w1)
                                    ).fetchone()[0]
    finally:
        stop.set()
        if shipper is not None and shipper.poll() is None:
            shipper.terminate()
            shipper.wait(10)
        pg.close()
    return {**({"fleet_cpu_share": round(cpu_s / wall, 6)} if interval_s is None else {}),
            "fleet_cpu_ms_per_commit": round(cpu_s * 1000 / commits, 3) if commits else None,
            "fleet_commits": commits, "fleet_pss_mb": round(peak_pss / 1024, 1),
            "fleet_threads": peak_threads, "fleet_rows": written[0], "fleet_rows_central": central,
            "fleet_rows_per_s": rows_per_s}
