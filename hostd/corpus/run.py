"""`hostd corpus run`: textures x codecs x settings x geometries -> rows in the store, on a local
process pool (default: every core), in this process (`workers=1`), or on a Dask cluster.

The driver streams: jobs are generated texture by texture, batched into tasks (one profile
load per task), at most a small window of tasks is in flight, and each finished task's rows
are written in one transaction; memory does not grow with the number of jobs. A lost worker's
tasks run again (their rows are written once: the key is UNIQUE). Ctrl-C stops the run and
keeps every row already written.
"""

from __future__ import annotations

import json
import math
import os
import time
from collections import Counter
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hostd.codec import formats
from hostd.corpus import codecs, jobs
from hostd.corpus.jobs import JobSpec, Scoring, Task, TextureSpec
from hostd.errors import HostdError

DEFAULT_BATCH = 256  # at most this many jobs per task (tasks shrink towards the end: iter_tasks)
DASK_BATCH = 256  # the same on Dask, whose per-task cost (scheduler, worker event loop) is larger
FIRST_BATCH = 64  # at most this many per task until a task has told how long a job takes
TASK_TARGET_S = 2.0  # then at most this long per task (slow codecs: rows arrive, Ctrl-C loses little)
MAX_TASK_RETRIES = 3


# ----------------------------------------------------------------------------- inputs


def textures_from(inputs: Sequence[str], opts) -> list[TextureSpec]:
    """Texture specs for directories (every file of a registered format, recursively, sorted),
    manifests (.toml, or .csv whose header starts with `file`), profile files and
    synthetic:KIND[:SEED] or synthetic:KIND:FIRST-LAST names. Names must be unique."""
    from hostd.texture import formats, manifest, synth

    entries: list[tuple[str, str, Any]] = []
    groups: dict[str, str] = {}
    for raw in inputs:
        s = str(raw)
        if synth.is_spec(s):
            parts = s.split(":")
            if len(parts) == 3 and "-" in parts[2]:
                a, _, b = parts[2].partition("-")
                try:
                    seeds = range(int(a), int(b) + 1)
                except ValueError:
                    raise HostdError(f"bad synthetic range {s!r}: use synthetic:KIND:FIRST-LAST") from None
                names = [f"synthetic:{parts[1]}:{k}" for k in seeds]
            else:
                names = [s]
            for nm in names:
                synth.parse_spec(nm)
                entries.append((nm, nm, opts))
            continue
        p = Path(s)
        if p.is_dir():
            suffixes = {suf for f in formats.formats() for suf in f.suffixes}
            files = sorted(f for f in p.rglob("*") if f.is_file() and f.suffix.lower() in suffixes
                           and not manifest.is_manifest(f))
            if not files:
                raise HostdError(f"{p}: no profile of a known format ({', '.join(sorted(suffixes))})")
            for f in files:
                entries.append((str(f.relative_to(p).with_suffix("")), str(f.resolve()), opts))
        elif manifest.is_manifest(p):
            for e in manifest.read(p, opts):
                entries.append((e.name, e.source, e.options))
                groups[e.name] = e.group
        elif p.exists():
            entries.append((p.stem, str(p.resolve()), opts))
        else:
            raise HostdError(f"{s}: no such file or directory (give profiles, a directory, a "
                             "manifest .csv/.toml or synthetic:KIND[:SEED])")
    names = [n for n, _, _ in entries]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise HostdError(f"texture name(s) given twice: {', '.join(dup[:5])}; use a manifest with `name`")
    return [TextureSpec(n, src, jobs.loader_json(o), "", groups.get(n, "")) for n, src, o in entries]


def hashed(tex: TextureSpec) -> TextureSpec:
    return TextureSpec(tex.name, tex.source, tex.loader, jobs.input_sha256(tex.source), tex.group)


# ----------------------------------------------------------------------------- the sweep


@dataclass(frozen=True)
class Plan:
    """What runs on every texture: (codec name, setting) pairs and the geometries."""

    points: tuple[tuple[str, str], ...]  # (codec spec, canonical setting JSON)
    geometries: tuple[tuple[float, float], ...]  # (speed_mm_s, fmax_hz)

    @property
    def per_texture(self) -> int:
        return len(self.points) * len(self.geometries)


def make_plan(codec_specs: Sequence[str], *, speeds_mm_s: Sequence[float] = (50.0,),
              fmaxs_hz: Sequence[float] = (400.0,), methods: Sequence[str] | None = None,
              g_db: Sequence[float] | None = None, levels: Sequence[int] | None = None,
              b0_db: Sequence[float] | None = None, target_iobj: Sequence[float] = (),
              settings: Mapping[str, Sequence[Mapping]] | None = None) -> Plan:
    """The sweep. hostd's codecs take the method grids (`methods`, `g_db`, `levels`, `b0_db`;
    None = the defaults of hostd.corpus.hostdcodec) and `target_iobj` adds rate-control points;
    an external codec runs its own `settings` unless `settings[spec]` (or `settings[its name]`) gives
    others. `settings` never adds a codec: a key that is neither a spec nor a codec's name is an error."""
    from hostd.corpus import hostdcodec

    settings = dict(settings or {})
    foreign = set(settings) - set(codec_specs)
    if foreign:
        # checked before any codec is resolved: a settings file (a colleague's sweep) is data;
        # only the codecs the command line or the caller names are imported
        names = {}
        for spec in codec_specs:
            names[codecs.resolve(spec).name] = spec
        unknown = sorted(foreign - set(names))
        if unknown:
            raise HostdError(f"the sweep names codec(s) not given with --codec: {', '.join(unknown)} "
                             "(a sweep gives settings for the codecs named on the command line; add "
                             "--codec NAME)")
        for name in foreign:
            settings.setdefault(names[name], settings.pop(name))
    points: list[tuple[str, str]] = []
    for spec in codec_specs:
        codec = codecs.resolve(spec)
        if isinstance(codec, hostdcodec.HostdStream):
            # the same numbers give the same keys, as ints or floats (the API takes either)
            grid = {"shaped": None if g_db is None else [float(v) for v in g_db],
                    "quant": None if levels is None else [int(v) for v in levels],
                    "cut": None if b0_db is None else [float(v) for v in b0_db]}
            ms = [m for m in formats.get(codec.fmt).methods if methods is None or m in methods]
            if methods is not None:
                bad = set(methods) - {"shaped", "quant", "cut"}
                if bad:
                    raise HostdError(f"unknown method(s) {', '.join(sorted(bad))}: use shaped, quant, cut")
            pts: list[dict] = []
            for m in ms:
                values = grid[m] if grid[m] is not None else [s[hostdcodec.KNOB[m]] for s in codec.settings
                                                              if s["method"] == m]
                pts += [{"method": m, hostdcodec.KNOB[m]: v} for v in values]
            pts += [{"target_iobj": float(t)} for t in target_iobj]
        else:
            pts = [dict(s) for s in settings.get(spec, codec.settings)]
        if not pts:
            raise HostdError(f"codec {spec}: the sweep gives it no setting")
        points += [(spec, codecs.setting_json(s)) for s in pts]
    geoms = tuple((float(v), float(f)) for v in speeds_mm_s for f in fmaxs_hz)
    for v, f in geoms:
        if not (v > 0 and f > 0):
            raise HostdError(f"speed {v} mm/s and fmax {f} Hz must be > 0")
    return Plan(tuple(dict.fromkeys(points)), geoms)


def versions(plan: Plan) -> dict[str, tuple[str, str]]:
    """codec spec -> (name, version), resolved in this process (they go into the keys)."""
    out = {}
    for spec, _ in plan.points:
        if spec not in out:
            c = codecs.resolve(spec)
            out[spec] = (c.name, c.version)
    return out


GUIDE = 1  # tasks shrink to (jobs still to hand out) / (GUIDE x workers) towards the end


def iter_tasks(textures: Iterable[TextureSpec], plan: Plan, scoring: Scoring, batch: int,
               skip: Callable[[list[str]], set[str]], on_skip: Callable[[int], None],
               workers: int = 1, cap: Callable[[], int] | None = None) -> Iterator[Task]:
    """Tasks of one texture's jobs, leaving out the keys `skip` says are done. Guided sizes
    (guided self-scheduling): a task takes min(batch, jobs still to hand out / workers) jobs, so
    while more than a texture per worker remains, a texture's jobs go in one task (its profile
    loaded once, in one worker; a split texture is loaded by every worker that gets a part), and
    the last textures are cut into halving tasks down to single jobs, so no worker finishes a
    long last task while the others idle. `cap()`, when given, further limits each task as it is
    made (the driver's limit from how long jobs take)."""
    ver = versions(plan)
    km = jobs.KeyMaker(scoring)
    points = []
    for v, f in plan.geometries:
        for spec, sj in plan.points:
            name, version = ver[spec]
            points.append((km.point(name, version, sj, v, f), spec, sj, v, f))
    textures = list(textures)
    remaining = len(textures) * len(points)  # at most this many jobs still to hand out
    div = GUIDE * max(1, workers)
    for tex in textures:
        tex = hashed(tex)
        head = km.texture(tex)
        specs = [JobSpec(km.key(head, pp), spec, sj, v, f) for pp, spec, sj, v, f in points]
        done = skip([j.key for j in specs])
        todo = [j for j in specs if j.key not in done]
        if len(todo) < len(specs):
            on_skip(len(specs) - len(todo))
            remaining -= len(specs) - len(todo)
        i = 0
        while i < len(todo):
            size = max(1, min(batch, -(-remaining // div), cap() if cap is not None else batch))
            part = tuple(todo[i : i + size])
            i += len(part)
            remaining -= len(part)
            yield Task(tex, part, scoring)


# ----------------------------------------------------------------------------- executors


_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def _one_thread_per_worker() -> None:
    """One process per core: BLAS/OpenMP pools of one thread in the worker processes started
    from here (they inherit the environment; a variable the user set is kept)."""
    for v in _THREAD_VARS:
        os.environ.setdefault(v, "1")


class _Serial:
    """In this process (workers=1): for debugging and the bench's bare-call reference."""

    name = "serial"
    lost = ()

    def __init__(self) -> None:
        from concurrent.futures import Future

        self._Future = Future

    def submit(self, task: Task, fn=jobs.run_task):
        f = self._Future()
        f.set_result(fn(task))
        return f

    def next_done(self, pending):
        return next(iter(pending))

    def restart(self) -> None:
        pass

    def close(self, cancel: bool = False) -> None:
        pass


def _no_main_context():
    """The fork server context, whose worker processes do not import the driver's __main__: a
    plain script that calls the API without `if __name__ == "__main__":` would otherwise run
    again in every worker (multiprocessing re-imports the main module in each child). The jobs
    need nothing from __main__: codecs are named and resolved in the workers."""
    from multiprocessing.context import ForkServerContext

    class Context(ForkServerContext):
        Process = _NoMainProcess

    return Context()


try:
    from multiprocessing.context import ForkServerProcess as _ForkServerProcess
except ImportError:  # (Windows)
    _ForkServerProcess = object  # type: ignore[assignment,misc]


class _NoMainProcess(_ForkServerProcess):  # type: ignore[misc,valid-type]
    """A fork server process started with __main__'s file and spec hidden for the moment it is
    started (multiprocessing.spawn.get_preparation_data reads them then)."""

    def start(self) -> None:
        import sys

        main = sys.modules.get("__main__")
        names = ("__file__", "__spec__")
        saved = {k: main.__dict__[k] for k in names if main is not None and k in main.__dict__}
        try:
            if main is not None:
                main.__dict__.pop("__file__", None)
                main.__dict__["__spec__"] = None
            super().start()
        finally:
            if main is not None:
                main.__dict__.pop("__spec__", None)
                main.__dict__.update(saved)


class _Local:
    """A process pool over `workers` processes (default: every core). Workers die with the
    driver (hostd.corpus.lifeline); a worker whose job runs past `job_limit_s` is killed (the
    pool is then replaced, and the job gets a `timeout` row: `killed`)."""

    name = "local"

    def __init__(self, workers: int) -> None:
        from concurrent.futures.process import BrokenProcessPool

        self.workers = workers
        self.lost = (BrokenProcessPool,)
        self.job_limit_s = math.inf
        self.killed: dict[int, int] = {}  # task seq -> index of the job that ran past its limit
        self._start()

    def _start(self) -> None:
        from concurrent.futures import ProcessPoolExecutor

        from hostd.corpus import lifeline

        _one_thread_per_worker()
        os.environ[lifeline.ENV] = str(os.getpid())  # the fork server dies with this process
        ctx = _no_main_context()
        # imported once in the fork server, inherited by every worker (and every replacement)
        ctx.set_forkserver_preload(["hostd.corpus.lifeline", "hostd.corpus.jobs", "hostd.corpus.hostdcodec",
                                    "hostd.codec.stream", "hostd.codec.ratecontrol", "hostd.perception.peer",
                                    "hostd.render.series", "hostd.texture.load", "scipy.signal", "scipy.fft"])
        self.marks = ctx.Array("d", jobs.SLOT_FIELDS * self.workers, lock=False)
        counter = ctx.Value("i", 0)
        self.pool = ProcessPoolExecutor(self.workers, mp_context=ctx, initializer=jobs.pool_worker_init,
                                        initargs=(self.marks, counter))

    def submit(self, task: Task, fn=jobs.run_task):
        return self.pool.submit(fn, task)

    def warm(self, hold_s: float = 0.05) -> None:
        """Start every worker process now (the bench times runs without the pool's start-up and
        reports it apart). The pool starts a process per task submitted while none is idle; each
        warm-up task holds `hold_s` so that all are submitted before one returns."""
        for _ in range(3):
            futs = [self.pool.submit(jobs.warm_up, hold_s) for _ in range(self.workers)]
            if len({f.result() for f in futs}) == self.workers:
                return
        raise HostdError(f"could not start {self.workers} worker processes")

    def next_done(self, pending):
        from concurrent.futures import FIRST_COMPLETED, wait

        poll = None if not math.isfinite(self.job_limit_s) else min(0.25, self.job_limit_s / 4)
        while True:
            done, _ = wait(pending, timeout=poll, return_when=FIRST_COMPLETED)
            if done:
                return next(iter(done))
            self._watch()

    def _watch(self) -> None:
        """Kill every worker whose job has run past job_limit_s (+ grace)."""
        import signal

        limit = jobs.kill_after_s(self.job_limit_s)
        now = time.monotonic()
        a, f = self.marks, jobs.SLOT_FIELDS
        for i in range(self.workers):
            t = a[f * i + 3]
            pid, seq, job = int(a[f * i]), int(a[f * i + 1]), int(a[f * i + 2])
            if t > 0 and now - t > limit and a[f * i + 3] == t and pid > 0 and seq not in self.killed:
                self.killed[seq] = job
                try:
                    os.kill(pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass

    def restart(self) -> None:
        self.pool.shutdown(wait=False, cancel_futures=True)
        self._start()

    def close(self, cancel: bool = False) -> None:
        if cancel:
            for p in list(getattr(self.pool, "_processes", {}).values()):
                p.terminate()  # our own workers (Ctrl-C: do not wait for their jobs)
        self.pool.shutdown(wait=not cancel, cancel_futures=True)


class _Dask:
    """A distributed cluster: `address` (tcp://host:8786) or "local" (a LocalCluster of
    worker processes, one thread each, over every core)."""

    name = "dask"

    def __init__(self, address: str, workers: int) -> None:
        from hostd.extras import need

        need("distributed", "corpus", "--dask")
        from distributed import Client
        from distributed.client import FutureCancelledError
        from distributed.scheduler import KilledWorker
        self.cluster = None
        if address == "local":
            from hostd.corpus.dasknode import local_cluster

            _one_thread_per_worker()
            self.cluster, self.client = local_cluster(workers)
        else:
            try:
                self.client = Client(address, timeout="20s")
            except (OSError, ValueError, TypeError) as exc:
                raise HostdError(f"cannot reach the Dask scheduler at {address}: {exc} (start it with "
                                 "`dask scheduler`, workers with `dask worker ADDRESS`; a tls:// cluster "
                                 "needs a client certificate in Dask's configuration, "
                                 "distributed.comm.tls.client)") from None
        self.lost = (KilledWorker, FutureCancelledError)
        from distributed import as_completed

        self._ac = as_completed()
        # what Dask lost and ran again on its own (a task whose worker died is rescheduled by the
        # scheduler: the driver sees no error unless it dies on 3 workers): from its events
        self._keys: dict[str, int] = {}  # task key -> seq
        self.workers_lost: list[str] = []
        self.tasks_redone = 0
        # a job past its limit: its worker logs it and kills itself (hostd.corpus.jobs._watch_dask);
        # the task is cancelled here and comes back as lost, with the job to write as `timeout`
        self.killed: dict[int, int] = {}
        self._by_seq: dict[int, Any] = {}
        self.client.subscribe_topic("all", self._on_event)
        self.client.subscribe_topic(jobs.TIMEOUT_TOPIC, self._on_timeout)

    async def _on_timeout(self, event) -> None:
        msg = event[1] if isinstance(event, tuple) and len(event) == 2 else None
        try:
            seq, job = int(msg["seq"]), int(msg["job"])
        except (TypeError, KeyError, ValueError):
            return
        fut = self._by_seq.get(seq)
        if fut is None or seq in self.killed:
            return
        self.killed[seq] = job
        await self.client.cancel([fut], asynchronous=True)

    def _on_event(self, event) -> None:
        msg = event[1] if isinstance(event, tuple) and len(event) == 2 else None
        if not isinstance(msg, dict) or msg.get("action") != "remove-worker" or msg.get("expected"):
            return
        # (a worker that killed itself for a job past its limit logged that first: not "lost")
        ours = [k for k in msg.get("processing-tasks", ())
                if str(k) in self._keys and self._keys[str(k)] not in self.killed]
        if ours:
            self.workers_lost.append(str(msg.get("worker", "")))
            self.tasks_redone += len(ours)

    def slots(self) -> int:
        """Worker threads of the cluster now (at least 1)."""
        try:
            return max(1, sum(self.client.nthreads().values()))
        except Exception:  # the scheduler is busy or gone: keep going with a small window
            return 1

    def submit(self, task: Task, fn=jobs.run_task):
        f = self.client.submit(fn, task, pure=False)
        self._keys[str(f.key)] = task.seq
        self._by_seq[task.seq] = f
        self._ac.add(f)
        return f

    def next_done(self, pending):
        while True:
            f = next(self._ac)
            if f in pending:
                self._by_seq.pop(pending[f].seq, None)
                return f

    def restart(self) -> None:
        pass

    def close(self, cancel: bool = False) -> None:
        try:
            try:  # (else the scheduler sends this client the event of its own leaving, to a closed comm)
                self.client.unsubscribe_topic("all")
                self.client.unsubscribe_topic(jobs.TIMEOUT_TOPIC)
            except Exception:  # the scheduler has gone: nothing to unsubscribe from
                pass
            self.client.close()
        finally:
            if self.cluster is not None:
                self.cluster.close()


def executor(dask: str | None, workers: int | None, pool: bool = False):
    """Dask when `dask` is given; else a process pool of `workers` (default every core); one
    worker runs in this process unless `pool` (the bench's one-worker pool)."""
    n = workers or os.cpu_count() or 1
    if dask:
        return _Dask(dask, n)
    if n == 1 and not pool:
        return _Serial()
    return _Local(n)


# ----------------------------------------------------------------------------- the driver


@dataclass
class Summary:
    store: str
    total: int = 0
    skipped: int = 0
    written: int = 0
    ok: int = 0
    failed: Counter = field(default_factory=Counter)
    retried_tasks: int = 0
    workers_lost: int = 0  # Dask: workers that died running this run's tasks
    redone_by_dask: int = 0  # Dask: tasks those workers were running, run again by the scheduler
    interrupted: bool = False
    seconds: float = 0.0
    executor: str = ""

    def as_dict(self) -> dict:
        return {"store": self.store, "executor": self.executor, "total": self.total,
                "skipped": self.skipped, "written": self.written, "ok": self.ok,
                "failed": sum(self.failed.values()), "failed_by_reason": dict(self.failed),
                "retried_tasks": self.retried_tasks, "workers_lost": self.workers_lost,
                "redone_by_dask": self.redone_by_dask, "interrupted": self.interrupted,
                "seconds": round(self.seconds, 3)}

    def hard_failures(self) -> int:
        """Failed jobs, not counting those of a codec that cannot run here (`unavailable`: the
        rows say what to install; a sweep that names an absent peer is not a failed run)."""
        return sum(v for k, v in self.failed.items() if k != "unavailable")

    def lines(self) -> list[str]:
        out = [f"{self.written} rows written to {self.store} ({self.ok} ok, {sum(self.failed.values())} "
               f"failed), {self.skipped} already there, of {self.total} jobs, in {self.seconds:.1f} s "
               f"({self.executor})"]
        if self.failed:
            out.append("failed: " + ", ".join(f"{k} {v}" for k, v in self.failed.most_common())
                       + "  (the rows' `error` column says why; rerun with --retry-errors after a fix)")
        if self.retried_tasks:
            out.append(f"lost: {self.retried_tasks} tasks came back from a lost worker and ran again "
                       "(their rows are written once)")
        if self.workers_lost:
            out.append(f"lost: {self.workers_lost} Dask worker(s) died running this run's tasks; the "
                       f"scheduler ran their {self.redone_by_dask} task(s) again elsewhere (rows written "
                       "once)")
        if self.interrupted:
            out.append("interrupted: the rows above are kept; run the same command again to go on")
        return out


def run(textures: Sequence[TextureSpec], plan: Plan, store_path: str | Path, *,
        scoring: Scoring | None = None, dask: str | None = None, workers: int | None = None,
        batch: int | None = None, progress: bool | None = None, retry_errors: bool = False,
        on_rows: Callable[[list[dict]], None] | None = None, task_fn: Callable = jobs.run_task,
        pool: bool = False, using=None) -> Summary:
    """Run every job not yet in the store; returns what happened (Ctrl-C: interrupted=True).
    `using`: an executor() already started (the bench's warm pools), left open for the caller."""
    from hostd.corpus.store import Store

    if batch is None:
        batch = DASK_BATCH if dask else DEFAULT_BATCH
    if batch < 1:
        raise HostdError("--batch must be >= 1")
    scoring = scoring or Scoring()
    t0 = time.monotonic()
    st = Store(store_path)
    st.begin_run()
    summ = Summary(str(store_path), total=len(textures) * plan.per_texture)
    from hostd.tty import progress_bar

    # shown only on a terminal (hostd.tty), also when asked for: a log or a pipe gets no \r lines
    bar = progress_bar(progress is not False, total=summ.total, unit="job", desc="corpus",
                       smoothing=0.05)

    def skipped(k: int) -> None:
        summ.skipped += k
        if bar is not None:
            bar.update(k)

    n_workers = workers or os.cpu_count() or 1
    tasks: Iterator[Task] = iter(())
    ex = None
    summ.executor = (f"dask {dask}" if dask else "in this process" if n_workers == 1 and not pool
                     else f"local pool of {n_workers}")
    window = 4 * n_workers + 2  # tasks in flight (Dask: from the cluster's threads, see below)
    done_tasks = 0
    pace = [0.0, 0]  # seconds of finished tasks, their jobs

    def cap() -> int:
        """Jobs per task: FIRST_BATCH until a task has reported its time, then what takes about
        TASK_TARGET_S (cheap jobs: whole textures; a slow codec: a few jobs per task)."""
        if pace[1] == 0 or pace[0] <= 0:
            return min(batch, FIRST_BATCH)
        return max(1, min(batch, int(TASK_TARGET_S * pace[1] / pace[0])))

    pending: dict = {}
    tries: Counter = Counter()  # task seq -> times its worker was lost
    exhausted = False
    seqs = iter(range(1, 1 << 62))

    def submit(t: Task) -> None:
        t = Task(t.texture, t.jobs, t.scoring, next(seqs)) if t.seq == 0 else t
        pending[ex.submit(t, task_fn)] = t

    def timed_out(t: Task, j: int) -> None:
        """The job the driver killed its worker for: a timeout row; the task's other jobs again."""
        limit = f"{scoring.timeout_s:g} s" if math.isfinite(scoring.timeout_s) else "its limit"
        record(stamped(jobs.empty_task_rows(Task(t.texture, (t.jobs[j],), t.scoring),
                                            f"the codec did not finish within the per-job limit of {limit} "
                                            "(--timeout); its worker process was killed and replaced",
                                            "timeout")))
        rest = t.jobs[:j] + t.jobs[j + 1:]
        if rest:
            submit(Task(t.texture, rest, t.scoring))

    def stamped(rows: list[dict]) -> list[dict]:
        """Rows the driver makes (no worker ran the job): the codec's name, version and curve."""
        for r in rows:
            try:
                c = codecs.resolve(r["codec"])
                setting = json.loads(r["setting"])
                r.update(codec=c.name, codec_version=c.version, curve=codecs.curve_of(c, setting))
            except Exception:  # the row says what failed; the names stay as given
                continue
        return rows

    def fill() -> None:
        nonlocal exhausted
        nonlocal window
        if done_tasks % 50 == 0 and hasattr(ex, "slots"):  # a cluster grows and shrinks
            window = 4 * ex.slots() + 2
        while not exhausted and len(pending) < window:
            t = next(tasks, None)
            if t is None:
                exhausted = True
                return
            submit(t)

    def record(rows: list[dict]) -> None:
        if rows and rows[0].get("_task_s") is not None:
            pace[0] += rows[0]["_task_s"]
            pace[1] += len(rows)
        summ.written += st.write(rows, replace=retry_errors)
        for r in rows:
            if r["error"] is None:
                summ.ok += 1
            else:
                summ.failed[r["error_reason"] or "error"] += 1
        if bar is not None:
            bar.update(len(rows))
        if on_rows is not None:
            on_rows(rows)

    try:
        ex = using if using is not None else executor(dask, workers, pool)
        if hasattr(ex, "job_limit_s"):
            ex.job_limit_s = scoring.timeout_s
            ex.killed.clear()
        # task sizes shrink towards the end in proportion to the workers there are
        tasks = iter_tasks(textures, plan, scoring, batch, lambda keys: st.known(keys, ok_only=retry_errors),
                           skipped, ex.slots() if hasattr(ex, "slots") else n_workers, cap)
        fill()
        while pending:
            fut = ex.next_done(pending)
            task = pending.pop(fut)
            try:
                rows = fut.result()
            except ex.lost as exc:
                killed = getattr(ex, "killed", {})
                if task.seq not in killed:  # (a worker killed for a job past its limit: not lost)
                    tries[task.seq] += 1
                    summ.retried_tasks += 1
                if ex.name == "local":  # the pool is broken: every pending future with it
                    redo = [task, *pending.values()]
                    pending.clear()
                    ex.restart()
                else:
                    redo = [task]
                for t in redo:
                    if t.seq in killed:
                        timed_out(t, killed.pop(t.seq))
                    elif tries[t.seq] > MAX_TASK_RETRIES:
                        record(stamped(jobs.empty_task_rows(t, f"the worker running this job was lost "
                                                            f"{tries[t.seq]} times ({type(exc).__name__})",
                                                            "worker_lost")))
                    else:
                        submit(t)
                continue
            except Exception as exc:  # the task itself failed in the worker (not a codec: those are rows)
                text = f"the task failed in its worker: {type(exc).__name__}: {exc}"[:500]
                rows = jobs.empty_task_rows(task, text, "worker_error")
            record(rows)
            done_tasks += 1
            fill()
    except KeyboardInterrupt:
        summ.interrupted = True
        if ex is not None and using is None:
            ex.close(cancel=True)
        ex = None
    finally:
        if ex is not None and hasattr(ex, "workers_lost"):
            summ.workers_lost, summ.redone_by_dask = len(ex.workers_lost), ex.tasks_redone
        if ex is not None and using is None:
            ex.close()
        if bar is not None:
            bar.close()
        st.close()
        summ.seconds = time.monotonic() - t0
    return summ
