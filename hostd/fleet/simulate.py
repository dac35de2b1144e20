"""`hostd fleet simulate`: the central store's scale, measured: many display PCs' shippers against
one PostgreSQL (a throwaway server, localpg, with fsync on as a real centre runs), without daemons.

Each simulated PC writes rows at `rows_per_pc_day` (a Poisson process: half stream rows, half
plays, with its own textures, Iobj and underruns) and looks at its log every `interval_s`, at its
own phase, as the shipper does; a look that finds rows ships them through the shipper's own code
(Shipper.ship: the one statement, the local marks after the central commit), as that PC's role
(SET ROLE on one of `workers` pooled connections, as a pooler in front of the centre would do:
row-level security holds each row to its PC). A health summary every `health_interval_s`, in a
batch of its own. Only the looks that find rows are simulated (an empty look costs the centre
nothing): the next row's commit time is drawn (the Poisson process's exponential gaps) and the
PC's first look after it ships it.

Measured over the run (after a warm-up): the rows per second committed centrally, the delay from
each row's local commit to the return of its central commit (p50, p99, max), and the CPU time of
every PostgreSQL process (utime + stime from /proc, the postmaster's reaped children included)
per 10^3 rows. `check` holds the goals of hostd/bench/guards.py (FLEET_ROWS_PER_S,
FLEET_DELAY_P99_S). The store is left for `hostd fleet report` with `--keep DIR`.
"""

from __future__ import annotations

import heapq
import math
import os
import queue
import random
import threading
import time
import uuid
from pathlib import Path

from hostd.errors import HostdError

FIRMWARE = ("0.5.2", "0.5.3", "0.6.0")
TEXTURES = tuple(f"{m}{k}" for m in ("wood", "cork", "felt", "denim", "sandpaper", "tile")
                 for k in range(1, 9))


def _pg_cpu_s(postmaster: int) -> float:
    """CPU seconds of every live child of the postmaster, then of the postmaster with its reaped
    children, from /proc. The postmaster is read last: a backend that exits while the children
    are read is then in its reaped children's time (at worst counted twice), never lost, so the
    figure only grows (read first, an exiting backend's time vanished: a negative difference)."""
    tick = os.sysconf("SC_CLK_TCK")
    total = 0
    for d in os.listdir("/proc"):
        if not d.isdigit() or int(d) == postmaster:
            continue
        try:
            with open(f"/proc/{d}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == postmaster:
            total += int(fields[11]) + int(fields[12])
    try:
        with open(f"/proc/{postmaster}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        total += sum(int(x) for x in fields[11:15])  # utime stime cutime cstime
    except OSError:
        pass
    return total / tick


def _procs_cpu_s(pids: list[int]) -> float:
    """CPU seconds (utime + stime) of these processes, from /proc (the simulator's clients)."""
    total = 0
    for pid in pids:
        try:
            with open(f"/proc/{pid}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        total += int(fields[11]) + int(fields[12])
    return total / os.sysconf("SC_CLK_TCK")


def _roles(conn, n: int, owner_role: str) -> list[str]:
    """n display PCs' roles (members of hostd_pc) that the simulator's role may SET ROLE to."""
    conn.execute(
        f"DO $$ BEGIN FOR i IN 0..{n - 1} LOOP EXECUTE format('CREATE ROLE %I NOLOGIN IN ROLE hostd_pc "
        f"ROLE %I', 'pc_sim_' || lpad(i::text, 5, '0'), {_lit(owner_role)}); END LOOP; END $$")
    return [f"pc_sim_{i:05d}" for i in range(n)]


def _lit(s: str) -> str:
    return "'" + s.replace("'", "''") + "'"


class _PC:
    __slots__ = (
        "firmware",
        "next_id",
        "next_row",
        "quality_mean",
        "rng",
        "role",
        "underrun_rate",
    )

    def __init__(self, role: str, seed: int, t0: float):
        self.role = role
        self.rng = random.Random(seed)
        self.next_id = 1
        self.quality_mean = self.rng.uniform(0.03, 0.12)
        self.firmware = self.rng.choices(FIRMWARE, (0.15, 0.6, 0.25))[0]
        self.underrun_rate = self.rng.choice((0.0, 0.0, 0.05, 0.3))
        self.next_row = t0  # the local commit time of its next row (drawn by _arrivals)


def _arrivals(pc: _PC, t_to: float, rows_per_s: float) -> list[float]:
    """The local commit times of this PC's rows up to t_to: a Poisson process, drawn as its
    exponential gaps (pc.next_row is then the first one after t_to)."""
    out = []
    while pc.next_row <= t_to:
        out.append(pc.next_row)
        pc.next_row += pc.rng.expovariate(rows_per_s)
    return out


def _next_look(first_look: float, interval_s: float, t: float) -> float:
    """The first look of the grid first_look + k * interval_s (k >= 0) at or after t."""
    return first_look + max(0, math.ceil((t - first_look) / interval_s)) * interval_s


def _rows(pc: _PC, times: list[float]) -> tuple[list[dict], list[dict]]:
    """The rows this PC committed locally at these times: half stream rows, half plays."""
    from hostd.fleet.bench import synthetic_row

    streams, plays = [], []
    for t in times:
        i = pc.next_id
        pc.next_id += 1
        name = pc.rng.choice(TEXTURES)
        if pc.rng.random() < 0.5:
            r = synthetic_row(i, t)
            r.update(name=name, iobj=max(0.0, pc.rng.gauss(pc.quality_mean, 0.02)), uuid=str(uuid.uuid4()),
                     id=i)
            streams.append(r)
        else:
            dev = pc.rng.uniform(5, 60)
            und = sum(pc.rng.random() < pc.underrun_rate for _ in range(3))
            plays.append({"id": i, "uuid": str(uuid.uuid4()), "name": name, "sha256": f"{i:064x}",
                          "started_at": t - dev, "ended_at": t, "device_s": dev,
                          "played_s": dev * (1 - 0.01 * und), "played_fraction": 1 - 0.01 * und,
                          "underruns": und})
    return streams, plays


def _client(url: str, state_dir: str, first: int, n: int, t0: float, measure_from: float, t_end: float,
            rows_per_s: float, interval_s: float, health_interval_s: float, workers: int) -> dict:
    """One client process: PCs first..first+n-1, their looks in time order, shipped by `workers`
    threads (each a Shipper on its own pooled connection). Returns the rows committed in the
    measured span and each one's delay."""
    import psycopg

    from hostd.fleet.config import FleetCfg
    from hostd.fleet.shipper import Shipper

    sim = [_PC(f"pc_sim_{k:05d}", k, t0) for k in range(first, first + n)]
    rng = random.Random(first)
    # each PC looks at its log every interval_s from its own phase; a look that finds nothing costs
    # the centre nothing, so only the looks that find rows are events here: for each PC the look
    # after its next row's commit (ROWS), and its health summary every health_interval_s (HEALTH).
    # The same process as looking at every look (the rows of a Poisson process, the looks on the
    # same grid), without the simulator spending a core on the empty ones
    rows_ev, health_ev = 0, 1
    first_look = [t0 + rng.uniform(0, interval_s) for _ in range(n)]
    events = []
    for k, pc in enumerate(sim):
        pc.next_row = t0 + pc.rng.expovariate(rows_per_s)
        events.append((_next_look(first_look[k], interval_s, pc.next_row), rows_ev, k))
        events.append((t0 + rng.uniform(0, health_interval_s), health_ev, k))  # its own phase
    heapq.heapify(events)
    work: queue.Queue = queue.Queue(maxsize=50_000)
    lock = threading.Lock()
    delays: list[float] = []
    counted = [0]
    errors: list[str] = []
    stop = threading.Event()

    def worker(w: int):
        s = Shipper(FleetCfg(url=url, role="fleet_sim", quality_db="/nonexistent",
                             state=f"{state_dir}/c{first}w{w}.sqlite", socket=""))
        conn = psycopg.connect(url, user="fleet_sim", password="sim", autocommit=True,
                               options="-c TimeZone=UTC")
        s.conn = conn
        try:
            while True:
                item = work.get()
                if item is None:
                    return
                pc, batch, t_local = item
                conn.execute(f"SET ROLE {pc.role}")
                s.cfg.role = pc.role
                n_new = s.ship(batch)
                done = time.time()
                if measure_from <= done < t_end:
                    with lock:
                        delays.extend(done - t for t in t_local)
                        counted[0] += n_new
        except Exception as e:  # reported, and the run stops
            errors.append(f"{type(e).__name__}: {e}")
            stop.set()
        finally:
            conn.close()
            s.state.close()

    threads = [threading.Thread(target=worker, args=(w,), daemon=True) for w in range(workers)]
    for t in threads:
        t.start()
    generated = 0
    while not stop.is_set():
        t_ev, what, k = events[0]
        now = time.time()
        if now >= t_end:
            break
        if t_ev > now:
            time.sleep(min(t_ev - now, 0.01))
            continue
        pc = sim[k]
        streams, plays, health = [], [], []
        if what == rows_ev:
            streams, plays = _rows(pc, _arrivals(pc, t_ev, rows_per_s))
            heapq.heapreplace(events, (_next_look(first_look[k], interval_s, pc.next_row), rows_ev, k))
        else:
            heapq.heapreplace(events, (t_ev + health_interval_s, health_ev, k))
            health.append({"id": 0, "uuid": str(uuid.uuid4()), "taken_at": t_ev,
                           "serial": f"SN{first + k:05d}",
                           "firmware": pc.firmware, "transport": "hid", "device_state": "playing",
                           "device_underruns": pc.next_id // 50, "played_fraction": 0.99, "stalls": 0,
                           "recoveries": 0, "waiting_rows": pc.rng.choice((0, 0, 0, 2, 40)),
                           "waiting_since": t_ev - pc.rng.uniform(0, 7200)})
        generated += len(streams) + len(plays)
        work.put((pc, {"streams": streams, "plays": plays, "health": health},
                  [r["received_at"] for r in streams] + [p["ended_at"] for p in plays]))
    backlog = work.qsize()
    for _ in threads:
        work.put(None)
    for t in threads:
        t.join(120)
    return {"counted": counted[0], "delays": delays, "errors": errors, "backlog": backlog,
            "generated": generated}


def run(pcs: int = 10_000, rows_per_pc_day: float = 10_000.0, interval_s: float = 1.0, seconds: float = 60.0,
        warmup_s: float = 10.0, workers: int = 12, procs: int = 2, health_interval_s: float = 300.0,
        silent_pcs: int = 0, keep: Path | None = None, on_result=None) -> dict:
    import multiprocessing

    import psycopg

    from hostd.fleet import schema
    from hostd.fleet.localpg import LocalPG

    pg = LocalPG()
    try:
        with psycopg.connect(pg.admin_url, autocommit=True) as c:
            schema.migrate(c)
            c.execute("CREATE ROLE fleet_sim LOGIN PASSWORD 'sim' NOINHERIT")
            _roles(c, pcs + silent_pcs, "fleet_sim")
            c.execute("CREATE ROLE viewer LOGIN PASSWORD 'viewer' IN ROLE hostd_reader")
            # then a real centre's durability: every commit flushed (localpg turns it off for tests)
            c.execute("ALTER SYSTEM SET fsync = on")
            c.execute("ALTER SYSTEM SET full_page_writes = on")
            c.execute("SELECT pg_reload_conf()")
        postmaster = pg.pid()
        state_dir = Path(pg.dir) / "sim-state"
        state_dir.mkdir()
        t0 = time.time() + 1.0  # the clients started
        measure_from, t_end = t0 + warmup_s, t0 + warmup_s + seconds
        share = [pcs // procs + (i < pcs % procs) for i in range(procs)]
        firsts = [sum(share[:i]) for i in range(procs)]
        ctx = multiprocessing.get_context("spawn")
        with ctx.Pool(procs) as pool:
            pending = [pool.apply_async(_client, (pg.url(), str(state_dir), f, n, t0, measure_from, t_end,
                                                  rows_per_pc_day / 86400.0, interval_s, health_interval_s,
                                                  workers)) for f, n in zip(firsts, share, strict=True)]
            clients = [p.pid for p in pool._pool]  # the pool's processes, for their CPU time
            time.sleep(max(0.0, measure_from - time.time()))
            cpu0 = (_pg_cpu_s(postmaster), time.time(), _procs_cpu_s(clients))
            time.sleep(max(0.0, t_end - time.time()))
            cpu1 = (_pg_cpu_s(postmaster), time.time(), _procs_cpu_s(clients))
            results = [p.get(timeout=300) for p in pending]
        errors = [e for r in results for e in r["errors"]]
        if errors:
            raise HostdError(f"the simulation stopped: {errors[0]}")
        wall = cpu1[1] - cpu0[1]
        delays = sorted(d for r in results for d in r["delays"])
        counted = sum(r["counted"] for r in results)
        n = len(delays)
        with psycopg.connect(pg.admin_url) as c:
            central = c.execute("SELECT (SELECT count(*) FROM fleet.quality) + (SELECT count(*) FROM "
                                "fleet.plays)").fetchone()[0]
            # the store's bytes per row: tables, indexes and the ledger, over quality rows and plays
            stored = c.execute("SELECT sum(pg_total_relation_size(c.oid)) FROM pg_class c JOIN "
                               "pg_namespace n ON n.oid = c.relnamespace WHERE n.nspname = 'fleet' "
                               "AND c.relkind = 'r'").fetchone()[0]
            ledger = c.execute("SELECT pg_relation_size('fleet.row_keys_pkey')").fetchone()[0]
        out = {"pcs": pcs, "rows_per_pc_day": rows_per_pc_day, "interval_s": interval_s, "procs": procs,
               "workers": workers, "seconds": round(wall, 1),
               "offered_rows_per_s": round(pcs * rows_per_pc_day / 86400.0, 1),
               "rows_per_s": round(counted / wall, 1), "rows_measured": counted,
               "delay_p50_s": round(delays[n // 2], 4) if n else None,
               "delay_p99_s": round(delays[min(n - 1, math.ceil(0.99 * n) - 1)], 4) if n else None,
               "delay_max_s": round(delays[-1], 4) if n else None,
               "pg_cpu_s_per_1000_rows": round((cpu1[0] - cpu0[0]) / max(counted, 1) * 1000, 4),
               "pg_cpu_share": round((cpu1[0] - cpu0[0]) / wall, 3),
               "clients_cpu_share": round((cpu1[2] - cpu0[2]) / wall, 3), "rows_central": central,
               "rows_generated": sum(r["generated"] for r in results),
               "bytes_per_row": round(stored / max(central, 1)),
               "ledger_index_bytes_per_row": round(ledger / max(central, 1)),
               "backlog_at_end": sum(r["backlog"] for r in results)}
        if on_result is not None:  # before the report: the figures are not lost if it fails
            on_result(out)
        if keep is not None:
            keep.mkdir(parents=True, exist_ok=True)
            t = time.monotonic()
            _report(pg, keep)
            out["report_s"] = round(time.monotonic() - t, 2)
        return out
    finally:
        pg.close()


def _report(pg, out: Path) -> None:
    """`hostd fleet report` of the simulated store, as its reader (viewer)."""
    import psycopg

    from hostd.fleet import report

    with psycopg.connect(pg.url(), user="viewer", password="viewer", autocommit=True,
                         options="-c TimeZone=UTC") as conn:
        report.write(conn, out, silent_hours=1.0, bucket="minute")


def check(row: dict, level: str = "goal") -> int:
    from hostd.bench.guards import FLEET_DELAY_P99_S, FLEET_ROWS_PER_S
    from hostd.bench.guards import check as guard_check

    return guard_check([row], [FLEET_ROWS_PER_S, FLEET_DELAY_P99_S], level, "fleet simulate")


def cmd_simulate(args) -> int:
    import json

    if args.pcs < 1 or args.seconds <= 0 or args.interval_s <= 0 or args.workers < 1:
        raise HostdError("--pcs, --workers must be >= 1 and --seconds, --interval-s > 0")
    try:
        import psycopg  # noqa: F401
    except ImportError:
        from hostd.extras import pip_install

        raise HostdError(f"psycopg is not installed: {pip_install('fleet')}") from None
    row = run(pcs=args.pcs, rows_per_pc_day=args.rows_per_pc_day, interval_s=args.interval_s,
              seconds=args.seconds, warmup_s=args.warmup_s, workers=args.workers, procs=args.procs,
              silent_pcs=args.silent_pcs, keep=Path(args.report) if args.report else None,
              on_result=lambda r: print(json.dumps(r), flush=True))
    if args.report:
        print(f"fleet report of the run in {args.report} ({row['report_s']} s)")
    return check(row) if args.check else 0


def add_parser(fsub) -> None:
    s = fsub.add_parser("simulate", help="measure the central store's scale: many PCs' shippers against a "
                        "throwaway local PostgreSQL (no daemons)")
    s.add_argument("--pcs", type=int, default=10_000, help="display PCs simulated (default 10000)")
    s.add_argument("--rows-per-pc-day", type=float, default=10_000.0,
                   help="quality rows and plays each PC writes a day (default 10000)")
    s.add_argument("--interval-s", type=float, default=1.0,
                   help="how often each PC's shipper looks at its log (fleet.interval_s; default 1)")
    s.add_argument("--seconds", type=float, default=60.0, help="measured span (default 60)")
    s.add_argument("--warmup-s", type=float, default=10.0, help="not measured, first (default 10)")
    s.add_argument("--workers", type=int, default=12, help="pooled connections to the centre per client "
                   "process (default 12)")
    s.add_argument("--procs", type=int, default=2, help="client processes, each its share of the PCs "
                   "(default 2)")
    s.add_argument("--silent-pcs", type=int, default=0, help="PCs with a role that never ship")
    s.add_argument("--report", default=None, metavar="DIR", help="write `hostd fleet report` of the run here")
    s.add_argument("--check", action="store_true", help="exit non-zero when a goal is missed "
                   "(rows/s and the p99 delay, hostd/bench/guards.py)")
    s.set_defaults(func=cmd_simulate)
