"""`hostd bench corpus`: what the corpus machinery (hostd.corpus: keys, batching, pool or Dask,
the SQLite store) costs per job beside the bare codec call, parallel efficiency, and the
driver's memory over 10^4 jobs.

Cheap jobs on purpose (the machinery must be cheap next to them): hostd-v2's shaped quantizer
on synthetic patches of `length_mm` (default 1 mm = 2000 heights), Iobj only (no SPQI).

- work_ms_per_job: CPU time of the codec calls (encode + decode through the protocol) and the
  scoring, measured inside the workers during the run itself (jobs.run_job's "_work_cpu_s").
- pool_cpu_ms_per_job: CPU time of the whole run per job: the driver (job generation, content
  hashes, scheduling, the store's transactions, and for Dask the in-process scheduler) plus
  every worker's CPU per task (measured in the worker around the task).
- overhead_ms_per_job = pool_cpu_ms_per_job - work_ms_per_job: what the machinery adds, in one
  run, in the same processes (so a loaded machine inflates both sides alike).
- bare_ms_per_job: the same work called in a plain loop in this process (a researcher's script),
  and overhead_vs_bare_loop_ms_per_job = pool_cpu_ms_per_job - bare_ms_per_job, for reference:
  it also contains the cost of running in other processes (cold caches, contention).
- parallel_efficiency = jobs/s with W worker processes / (W x jobs/s with one worker process),
  wall clock, medians of alternating runs: on a machine shared with other work it says little
  (the load average at the start and end is reported beside it);
  parallel_efficiency_cpu = CPU per job with one worker / CPU per job with W workers: what
  running in parallel costs in CPU, the bound for idle cores.
- RSS: the driver's resident memory after job 10^3 and after the last job (10^4 by default).
"""

from __future__ import annotations

import os
import time


def _rss_mb() -> float:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def _plan(n_settings: int):
    from hostd.corpus import run

    # g from -24 dB in 0.25 dB steps: every job its own setting, all cheap
    g = [-24.0 + 0.25 * i for i in range(n_settings)]
    return run.make_plan(["hostd-v2"], methods=["shaped"], g_db=g)


def _textures(n: int, length_mm: float):
    from hostd.corpus import run
    from hostd.texture.load import LoadOptions

    half = max(1, n // 2)
    return run.textures_from([f"synthetic:wood:1-{half}", f"synthetic:sandpaper:1-{n - half}"]
                             if n > 1 else ["synthetic:wood:1"], LoadOptions(length_mm=length_mm))


def bare_ms_per_job(textures, plan, scoring) -> float:
    """CPU ms per job of the same work called directly in this process: codec encode + decode
    (through the protocol) and the Iobj scoring of the reconstruction; no keys, no row, no
    time limit, no store, no pool."""
    import json

    from hostd.codec import transform
    from hostd.corpus import codecs, jobs
    from hostd.corpus.run import hashed
    from hostd.perception import indices

    total = 0.0
    n = 0
    points = [(codecs.resolve(spec), json.loads(sj)) for spec, sj in plan.points]
    for tex in textures:
        t = hashed(tex)
        prof = jobs.load_texture(t)  # loaded once per texture, as a task does
        refs = {(v, f): jobs._reference(t, v, f) for v, f in plan.geometries}
        t0 = time.process_time()
        for (v, f), (_, nk, b_k, c_ref) in refs.items():
            for codec, setting in points:
                coded = codecs.run_codec(codec, prof.heights_um, prof.spacing_um, setting,
                                         {"speed_mm_s": v, "fmax_hz": f})
                c_dec = transform.analyze(coded.reconstruction_um, nk)
                indices.score(c_ref, c_dec, b_k, scoring.a, scoring.b)
                n += 1
        total += time.process_time() - t0
    return 1e3 * total / n


def pool_run(textures, plan, scoring, store, *, workers: int, dask: str | None = None,
             batch: int | None = None, rss_at: int | None = None) -> dict:
    """One run: wall s, jobs/s, driver + worker CPU ms per job, driver RSS at `rss_at` and at the end."""
    from hostd.corpus import jobs, run

    worker_cpu = [0.0]
    work_cpu = [0.0]
    rss = {}
    seen = [0]

    def on_rows(rows):
        worker_cpu[0] += rows[0].get("_worker_cpu_s", 0.0) if rows else 0.0
        work_cpu[0] += sum(r.get("_work_cpu_s", 0.0) for r in rows)
        seen[0] += len(rows)
        if rss_at is not None and "at" not in rss and seen[0] >= rss_at:
            rss["at"] = _rss_mb()

    c0 = time.process_time()
    w0 = time.perf_counter()
    summ = run.run(textures, plan, store, scoring=scoring, workers=workers, dask=dask, batch=batch,
                   progress=False, on_rows=on_rows, task_fn=jobs.run_task_measured, pool=True)
    wall = time.perf_counter() - w0
    driver = time.process_time() - c0
    if summ.ok != summ.total:
        raise RuntimeError(f"bench corpus: {summ.total - summ.ok} jobs failed: {dict(summ.failed)}")
    out = {"jobs": summ.total, "wall_s": wall, "jobs_per_s": summ.total / wall,
           "driver_cpu_ms_per_job": 1e3 * driver / summ.total,
           "worker_cpu_ms_per_job": 1e3 * worker_cpu[0] / summ.total,
           "work_cpu_ms_per_job": 1e3 * work_cpu[0] / summ.total,
           "rss_end_mb": _rss_mb()}
    if "at" in rss:
        out["rss_at_mb"] = rss["at"]
    return out


def run(*, jobs_scale: int = 10_000, length_mm: float = 1.0, dask: bool = True, workers: int | None = None,
        batch: int = 16, repeats: int = 3) -> dict:
    import statistics
    import tempfile
    from pathlib import Path

    from hostd.corpus.jobs import Scoring

    w = workers or os.cpu_count() or 1
    scoring = Scoring(spqi=False, timeout_s=60.0)
    res: dict = {"bench": "corpus", "workers": w, "batch": batch, "length_mm": length_mm,
                 "heights_per_job": round(length_mm * 2000), "load_avg_1min_at_start": os.getloadavg()[0]}
    with tempfile.TemporaryDirectory(prefix="hostd-bench-corpus-") as d:
        d = Path(d)
        # CPU overhead: 20 textures x 50 settings = 1000 jobs
        tex, plan = _textures(20, length_mm), _plan(50)
        res["bare_ms_per_job"] = bare_ms_per_job(tex, plan, scoring)
        many = pool_run(tex, plan, scoring, d / "many.sqlite", workers=w, batch=batch)
        res["pool_cpu_ms_per_job"] = many["driver_cpu_ms_per_job"] + many["worker_cpu_ms_per_job"]
        res["driver_cpu_ms_per_job"] = many["driver_cpu_ms_per_job"]
        # the codec calls and scoring as measured inside the workers during this very run
        res["work_ms_per_job"] = many["work_cpu_ms_per_job"]
        res["overhead_ms_per_job"] = res["pool_cpu_ms_per_job"] - res["work_ms_per_job"]
        res["overhead_vs_bare_loop_ms_per_job"] = res["pool_cpu_ms_per_job"] - res["bare_ms_per_job"]
        res["cpu_efficiency"] = res["work_ms_per_job"] / res["pool_cpu_ms_per_job"]
        # wall-clock efficiency: one worker and w workers alternately, medians of `repeats` runs
        small_tex, small_plan = _textures(12, length_mm), _plan(50)
        one_rates, many_rates, one_cpu, many_cpu = [], [], [], []
        for i in range(repeats):
            o = pool_run(small_tex, small_plan, scoring, d / f"one{i}.sqlite", workers=1, batch=batch)
            m = pool_run(small_tex, small_plan, scoring, d / f"many{i}.sqlite", workers=w, batch=batch)
            one_rates.append(o["jobs_per_s"])
            many_rates.append(m["jobs_per_s"])
            one_cpu.append(o["driver_cpu_ms_per_job"] + o["worker_cpu_ms_per_job"])
            many_cpu.append(m["driver_cpu_ms_per_job"] + m["worker_cpu_ms_per_job"])
        # CPU time per job with one worker / with w workers: the extra CPU that running in
        # parallel costs (IPC, contention); on otherwise idle cores this bounds the wall-clock
        # efficiency from above, and it is far less disturbed by other load than wall time
        res["parallel_efficiency_cpu"] = statistics.median(one_cpu) / statistics.median(many_cpu)
        res["jobs_per_s_one_worker"] = statistics.median(one_rates)
        res["jobs_per_s"] = statistics.median(many_rates)
        res["jobs_per_s_per_core"] = res["jobs_per_s"] / w
        res["parallel_efficiency"] = res["jobs_per_s"] / (w * res["jobs_per_s_one_worker"])
        res["parallel_efficiency_runs"] = [m / (w * o) for o, m in zip(one_rates, many_rates, strict=True)]
        if dask:
            res.update(_dask(tex, plan, scoring, d, w, None, res["bare_ms_per_job"]))
        # memory: jobs_scale jobs through the local pool, rows streamed to disk
        n_tex = max(1, jobs_scale // 100)
        big = pool_run(_textures(n_tex, length_mm), _plan(100), scoring, d / "big.sqlite", workers=w,
                       batch=batch, rss_at=1000)
        res["scale_jobs"] = big["jobs"]
        res["scale_jobs_per_s"] = big["jobs_per_s"]
        res["driver_rss_mb_at_1000"] = big.get("rss_at_mb")
        res["driver_rss_mb_at_end"] = big["rss_end_mb"]
        res["driver_rss_growth_mb"] = big["rss_end_mb"] - big.get("rss_at_mb", big["rss_end_mb"])
        res["store_mb"] = (d / "big.sqlite").stat().st_size / 1e6
    res["load_avg_1min_at_end"] = os.getloadavg()[0]
    res["hours_for_1e6_jobs_per_worker"] = 1e6 / res["jobs_per_s_per_core"] / 3600.0
    return res


def _dask(tex, plan, scoring, d, w: int, batch: int | None, bare_ms: float) -> dict:
    """The same 1000 jobs on a LocalCluster of w worker processes (1 thread each, as
    `--dask local` starts it), started and warmed up (imports) before the measured run; its
    scheduler runs in this process, so its CPU time is counted as the driver's. batch None:
    the Dask default (run.DASK_BATCH)."""
    try:
        from distributed import LocalCluster
    except ImportError:
        from hostd.extras import pip_install

        return {"dask_note": f"distributed not installed: {pip_install('corpus')}"}
    from hostd.corpus import run as crun

    os.environ.setdefault("DASK_DISTRIBUTED__WORKER__PROFILE__ENABLED", "False")  # as --dask local
    crun._one_thread_per_worker()
    cluster = LocalCluster(n_workers=w, threads_per_worker=1, processes=True, dashboard_address=None)
    try:
        pool_run(tex[:2], plan, scoring, d / "dask-warm.sqlite", workers=w, dask=cluster.scheduler_address,
                 batch=batch)
        dk = pool_run(tex, plan, scoring, d / "dask.sqlite", workers=w, dask=cluster.scheduler_address,
                      batch=batch)
    finally:
        cluster.close()
    cpu = dk["driver_cpu_ms_per_job"] + dk["worker_cpu_ms_per_job"]
    return {"dask_batch": batch or crun.DASK_BATCH,
            "dask_cpu_ms_per_job": cpu, "dask_overhead_ms_per_job": cpu - dk["work_cpu_ms_per_job"],
            "dask_overhead_vs_bare_loop_ms_per_job": cpu - bare_ms,
            "dask_driver_cpu_ms_per_job": dk["driver_cpu_ms_per_job"], "dask_jobs_per_s": dk["jobs_per_s"]}
