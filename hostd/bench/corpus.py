"""`hostd bench corpus`: what the corpus machinery (hostd.corpus: keys, batching, pool or Dask,
the SQLite store) costs per job beside the bare codec call, parallel efficiency, and the
driver's memory over 10^4 jobs.

Two job sizes, the same figures for each:
- tiny (the top-level fields): hostd-v2's shaped quantizer on synthetic patches of `heights`
  (default 2000 = 1 mm), Iobj only (no SPQI), 50 settings per texture: the machinery is measured
  against little work on purpose;
- typical (the "typical" object; `--no-typical` skips it): whole synthetic textures of 20 000
  heights (10 mm), hostd-v2's default sweep (24 settings: shaped, quant, cut), with SPQI.

Per size, `repeats` rounds of one run on one worker process and one run on W worker processes,
the same jobs, alternating; every run on a pool started and warmed up (each worker has run a
no-op task) before its clock starts, each run with its own store and pool (no texture cached
from an earlier run). Start-up is not in the efficiency: it is reported apart
(`pool_start_s`: from creating the pool until every worker has run a task, without the
warm-up task's 50 ms wait; `pool_start_cold_s` for the first pool of a process, which starts
the fork server and its imports).

- work_ms_per_job: CPU time of the codec calls (encode + decode through the protocol) and the
  scoring, measured inside the workers (jobs.run_job's "_work_cpu_s");
- input_load_ms_per_job: loading each texture once and analysing its reference, measured in
  the workers (the first load of each texture; jobs.run_task_measured's "_load_cpu_s"), per job;
- pool_cpu_ms_per_job: CPU time of the whole run per job: the driver process (job generation,
  content hashes, scheduling, receiving rows, the store's transactions), measured in it,
  plus every worker process's CPU time (from /proc/PID/schedstat, before and after the run:
  everything the worker did, its task and row pickling included);
- overhead_ms_per_job = pool_cpu_ms_per_job - work_ms_per_job - input_load_ms_per_job: what the
  machinery adds, in the same run and processes (a texture loaded again in a second worker is
  machinery); medians over the W-worker runs (`overhead_ms_per_job_one_worker`: the 1-worker runs);
- bare_ms_per_job: the same work called in a plain loop in this process (a researcher's
  script), with `bare_load_ms_per_texture` apart; overhead_vs_bare_loop_ms_per_job =
  pool_cpu_ms_per_job - bare_ms_per_job - input_load_ms_per_job, for reference: it also holds the
  cost of running in other processes (cold caches, contention);
- parallel_efficiency = jobs/s with W workers / (W x jobs/s with one worker), wall clock, the
  medians of the runs (each round's own ratio in parallel_efficiency_runs);
  parallel_efficiency_cpu = CPU per job with one worker / CPU per job with W workers: what
  running in parallel costs in CPU;
- other_load_cores: the CPU time the machine spent on other processes during the runs, in cores
  (from /proc/stat, minus this run's driver and workers), median over the runs; with W = every
  core, efficiency can only be shown when it is near 0. The load averages are given too.
- RSS: the driver's resident memory after job 10^3 and after the last job (10^4 by default).
"""

from __future__ import annotations

import os
import statistics
import time

TYPICAL_HEIGHTS = 20_000
WARM_HOLD_S = 0.05  # each warm-up task waits this long (not counted in the start-up)


def _rss_mb() -> float:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def _proc_cpu_s(pid: int) -> float:
    """CPU time of a process's main thread (a pool worker has one), ns resolution."""
    try:
        with open(f"/proc/{pid}/schedstat") as fh:
            return int(fh.read().split()[0]) / 1e9
    except (OSError, ValueError, IndexError):
        return float("nan")


def _busy_s() -> float:
    """CPU time the whole machine spent not idle, all cores, since boot."""
    with open("/proc/stat") as fh:
        f = [int(x) for x in fh.readline().split()[1:]]
    idle = f[3] + (f[4] if len(f) > 4 else 0)
    return (sum(f[:8]) - idle) / os.sysconf("SC_CLK_TCK")


def _plan(n_settings: int):
    from hostd.corpus import run

    # g from -24 dB in 0.25 dB steps: every job its own setting, all cheap
    g = [-24.0 + 0.25 * i for i in range(n_settings)]
    return run.make_plan(["hostd-v2"], methods=["shaped"], g_db=g)


def _textures(n: int, heights: int):
    from hostd.corpus import run
    from hostd.texture.load import LoadOptions

    half = max(1, n // 2)
    return run.textures_from([f"synthetic:wood:1-{half}", f"synthetic:sandpaper:1-{n - half}"]
                             if n > 1 else ["synthetic:wood:1"], LoadOptions(length_mm=heights / 2000.0))


def bare_ms_per_job(textures, plan, scoring) -> tuple[float, float]:
    """(CPU ms per job, CPU ms of loading per texture) of the same work called directly in this
    process: codec encode + decode (through the protocol) and the scoring of the reconstruction
    (SPQI when `scoring.spqi`); each texture loaded once; no keys, no row, no time limit, no
    store, no pool."""
    import json

    from hostd.codec import transform
    from hostd.corpus import codecs, jobs
    from hostd.corpus.run import hashed
    from hostd.perception import indices, peer

    total = 0.0
    load = 0.0
    n = 0
    points = [(codecs.resolve(spec), json.loads(sj)) for spec, sj in plan.points]
    for tex in textures:
        t = hashed(tex)
        t0 = time.process_time()
        prof = jobs.load_texture(t)  # loaded once per texture, as a task does
        refs = {(v, f): jobs._reference(t, v, f, scoring) for v, f in plan.geometries}
        t1 = time.process_time()
        load += t1 - t0
        for (v, f), (_, nk, b_k, c_ref) in refs.items():
            for codec, setting in points:
                coded = codecs.run_codec(codec, prof.heights_um, prof.spacing_um, setting,
                                         {"speed_mm_s": v, "fmax_hz": f})
                c_dec = transform.analyze(coded.reconstruction_um, nk)
                indices.score(c_ref, c_dec, b_k, scoring.a, scoring.b)
                if scoring.spqi:
                    peer.played_spqi(c_ref, c_dec, prof.n, prof.length_mm, v)
                n += 1
        total += time.process_time() - t1
    return 1e3 * total / n, 1e3 * load / len(textures)


def pool_run(textures, plan, scoring, store, *, workers: int, dask: str | None = None,
             batch: int | None = None, rss_at: int | None = None, warm: bool = False,
             workers_cpu_s=None, using=None) -> dict:
    """One run: wall s, jobs/s, driver + worker CPU ms per job, driver RSS at `rss_at` and at
    the end. warm: on a local pool started (and timed: start_s) before the run's clock starts.
    Worker CPU: from /proc for a warm pool, else `workers_cpu_s()` (the workers' total CPU s
    now) before and after, else as measured around each task in the workers."""
    from hostd.corpus import jobs, run

    worker_cpu = [0.0]
    work_cpu = [0.0]
    loads: dict[str, list[float]] = {}
    rss = {}
    seen = [0]

    def on_rows(rows):
        if rows:
            worker_cpu[0] += rows[0].get("_worker_cpu_s", 0.0)
            if rows[0].get("_load_cpu_s"):
                loads.setdefault(rows[0]["texture"], []).append(rows[0]["_load_cpu_s"])
        work_cpu[0] += sum(r.get("_work_cpu_s", 0.0) for r in rows)
        seen[0] += len(rows)
        if rss_at is not None and "at" not in rss and seen[0] >= rss_at:
            rss["at"] = _rss_mb()

    ex = None
    out: dict = {}
    if warm:
        s0 = time.perf_counter()
        ex = run.executor(None, workers, pool=True)
        ex.warm(WARM_HOLD_S)
        out["start_s"] = time.perf_counter() - s0 - WARM_HOLD_S
        pids = list(ex.pool._processes)
    try:
        if ex is not None:
            p0 = [_proc_cpu_s(p) for p in pids]
        elif workers_cpu_s is not None:
            k0 = workers_cpu_s()
        b0 = _busy_s()
        c0 = time.process_time()
        w0 = time.perf_counter()
        summ = run.run(textures, plan, store, scoring=scoring, workers=workers, dask=dask, batch=batch,
                       progress=False, on_rows=on_rows, task_fn=jobs.run_task_measured, pool=True,
                       using=ex if ex is not None else using)
        wall = time.perf_counter() - w0
        driver = time.process_time() - c0
        busy = _busy_s() - b0
        if ex is not None:
            if set(ex.pool._processes) != set(pids):
                raise RuntimeError("bench corpus: a worker process was replaced during the run")
            proc = sum(_proc_cpu_s(p) - c for p, c in zip(pids, p0, strict=True))
            if proc == proc:  # no /proc/PID/schedstat (NaN): keep the CPU measured around each task
                worker_cpu[0] = proc
        elif workers_cpu_s is not None:
            worker_cpu[0] = workers_cpu_s() - k0
    finally:
        if ex is not None:
            ex.close()
    if summ.ok != summ.total:
        raise RuntimeError(f"bench corpus: {summ.total - summ.ok} jobs failed: {dict(summ.failed)}")
    n = summ.total
    first_loads = sum(v[0] for v in loads.values())
    out.update({"jobs": n, "wall_s": wall, "jobs_per_s": n / wall,
                "driver_cpu_ms_per_job": 1e3 * driver / n,
                "worker_cpu_ms_per_job": 1e3 * worker_cpu[0] / n,
                "work_cpu_ms_per_job": 1e3 * work_cpu[0] / n,
                "input_load_ms_per_job": 1e3 * first_loads / n,
                "texture_loads": sum(len(v) for v in loads.values()),
                "other_load_cores": max(0.0, busy - driver - worker_cpu[0]) / wall,
                "rss_end_mb": _rss_mb()})
    out["cpu_ms_per_job"] = out["driver_cpu_ms_per_job"] + out["worker_cpu_ms_per_job"]
    out["overhead_ms_per_job"] = (out["cpu_ms_per_job"] - out["work_cpu_ms_per_job"]
                                  - out["input_load_ms_per_job"])
    if "at" in rss:
        out["rss_at_mb"] = rss["at"]
    return out


def efficiency(tex, plan, scoring, d, w: int, batch: int | None, repeats: int, tag: str) -> dict:
    """One worker and w workers alternately on warm pools, the same jobs: medians."""
    med = statistics.median
    ones, manys = [], []
    la0 = os.getloadavg()[0]
    for i in range(repeats):
        for out, n in ((ones, 1), (manys, w)):
            out.append(pool_run(tex, plan, scoring, d / f"{tag}-{n}w{i}.sqlite", workers=n, batch=batch,
                                warm=True))
    one_rate = med(r["jobs_per_s"] for r in ones)
    rate = med(r["jobs_per_s"] for r in manys)
    return {
        "textures": len(tex), "jobs_per_run": manys[0]["jobs"],
        "work_ms_per_job": med(r["work_cpu_ms_per_job"] for r in manys),
        # the same work with one worker: CPU time per job that grows with W workers is contention
        # for the cores and caches (or other load), not the machinery
        "work_ms_per_job_one_worker": med(r["work_cpu_ms_per_job"] for r in ones),
        "input_load_ms_per_job": med(r["input_load_ms_per_job"] for r in manys),
        "pool_cpu_ms_per_job": med(r["cpu_ms_per_job"] for r in manys),
        "driver_cpu_ms_per_job": med(r["driver_cpu_ms_per_job"] for r in manys),
        "overhead_ms_per_job": med(r["overhead_ms_per_job"] for r in manys),
        "overhead_ms_per_job_one_worker": med(r["overhead_ms_per_job"] for r in ones),
        "texture_loads": med(r["texture_loads"] for r in manys),
        "jobs_per_s_one_worker": one_rate,
        "jobs_per_s": rate,
        "jobs_per_s_per_core": rate / w,
        "parallel_efficiency": rate / (w * one_rate),
        "parallel_efficiency_runs": [m["jobs_per_s"] / (w * o["jobs_per_s"]) for o, m in zip(ones, manys,
                                                                                            strict=True)],
        "parallel_efficiency_cpu": med(r["cpu_ms_per_job"] for r in ones) / med(r["cpu_ms_per_job"]
                                                                              for r in manys),
        "pool_start_s": med(r["start_s"] for r in manys),
        "pool_start_s_one_worker": med(r["start_s"] for r in ones),
        "other_load_cores": med(r["other_load_cores"] for r in ones + manys),
        "load_avg_1min": [round(la0, 2), round(os.getloadavg()[0], 2)],
    }


def _section(tex, plan, scoring, d, w, batch, repeats, tag) -> dict:
    bare, bare_load = bare_ms_per_job(tex, plan, scoring)
    res = {"heights_per_job": None, "spqi": scoring.spqi, "settings_per_texture": plan.per_texture,
           "bare_ms_per_job": bare, "bare_load_ms_per_texture": bare_load}
    res.update(efficiency(tex, plan, scoring, d, w, batch, repeats, tag))
    res["overhead_vs_bare_loop_ms_per_job"] = (res["pool_cpu_ms_per_job"] - bare
                                               - res["input_load_ms_per_job"])
    res["cpu_efficiency"] = res["work_ms_per_job"] / res["pool_cpu_ms_per_job"]
    return res


def run(*, jobs_scale: int = 10_000, heights: int = 2000, spqi: bool = False, dask: bool = True,
        workers: int | None = None, batch: int | None = None, repeats: int = 7,
        typical: bool = True) -> dict:
    import tempfile
    from pathlib import Path

    from hostd.corpus import run as crun
    from hostd.corpus.jobs import Scoring

    w = workers or os.cpu_count() or 1
    res: dict = {"bench": "corpus", "workers": w, "batch": batch or crun.DEFAULT_BATCH,
                 "load_avg_1min_at_start": os.getloadavg()[0]}
    with tempfile.TemporaryDirectory(prefix="hostd-bench-corpus-") as d:
        d = Path(d)
        # the first pool of this process starts the fork server (its imports): timed apart
        s0 = time.perf_counter()
        ex = crun.executor(None, w, pool=True)
        ex.warm(WARM_HOLD_S)
        res["pool_start_cold_s"] = time.perf_counter() - s0 - WARM_HOLD_S
        ex.close()
        # tiny jobs: 20 textures x 50 settings = 1000 jobs per run
        tex, plan = _textures(20, heights), _plan(50)
        res.update(_section(tex, plan, Scoring(spqi=spqi, timeout_s=60.0), d, w, batch, repeats, "tiny"))
        res["heights_per_job"] = heights
        if typical:
            # typical jobs: 20 whole textures x hostd-v2's default sweep (24) = 480 jobs per run
            ttex, tplan = _textures(20, TYPICAL_HEIGHTS), crun.make_plan(["hostd-v2"])
            t = _section(ttex, tplan, Scoring(spqi=True, timeout_s=60.0), d, w, batch, repeats, "typical")
            t["heights_per_job"] = TYPICAL_HEIGHTS
            res["typical"] = t
        if dask:
            res.update(_dask(tex, plan, Scoring(spqi=spqi, timeout_s=60.0), d, w, batch))
        # memory: jobs_scale jobs through the local pool, rows streamed to disk
        n_tex = max(1, jobs_scale // 100)
        big = pool_run(_textures(n_tex, heights), _plan(100), Scoring(spqi=spqi, timeout_s=60.0),
                       d / "big.sqlite", workers=w, batch=batch, rss_at=1000)
        res["scale_jobs"] = big["jobs"]
        res["scale_jobs_per_s"] = big["jobs_per_s"]
        res["driver_rss_mb_at_1000"] = big.get("rss_at_mb")
        res["driver_rss_mb_at_end"] = big["rss_end_mb"]
        res["driver_rss_growth_mb"] = big["rss_end_mb"] - big.get("rss_at_mb", big["rss_end_mb"])
        res["store_mb"] = (d / "big.sqlite").stat().st_size / 1e6
    res["load_avg_1min_at_end"] = os.getloadavg()[0]
    res["hours_for_1e6_jobs_per_worker"] = 1e6 / res["jobs_per_s_per_core"] / 3600.0
    return res


def _dask(tex, plan, scoring, d, w: int, batch: int | None) -> dict:
    """The same jobs on the cluster `--dask local` starts (w worker processes of 1 thread, over
    TLS: hostd.corpus.dasknode), started and warmed up (imports, a run on 2 textures) before the
    measured run; its scheduler runs in this process, so its CPU time is counted as the driver's;
    the workers' CPU is their processes' whole CPU time (every thread: the task's, the event
    loop's, heartbeats), before and after the run; their nannies' is not counted."""
    try:
        import distributed  # noqa: F401
    except ImportError:
        from hostd.extras import pip_install

        return {"dask_note": f"distributed not installed: {pip_install('corpus')}"}
    from hostd.corpus import run as crun

    ex = crun.executor("local", w)
    try:
        pool_run(tex[:2], plan, scoring, d / "dask-warm.sqlite", workers=w, dask="local", batch=batch,
                 using=ex)

        def workers_cpu_s() -> float:
            return float(sum(ex.client.run(time.process_time).values()))

        dk = pool_run(tex, plan, scoring, d / "dask.sqlite", workers=w, dask="local", batch=batch,
                      workers_cpu_s=workers_cpu_s, using=ex)
    finally:
        ex.close()
    return {"dask_batch": batch or crun.DASK_BATCH, "dask_cpu_ms_per_job": dk["cpu_ms_per_job"],
            "dask_overhead_ms_per_job": dk["overhead_ms_per_job"],
            "dask_driver_cpu_ms_per_job": dk["driver_cpu_ms_per_job"], "dask_jobs_per_s": dk["jobs_per_s"],
            "dask_texture_loads": dk["texture_loads"]}
