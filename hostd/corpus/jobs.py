"""A corpus job is a pure function (profile bytes, loader options, codec, setting, geometry) ->
one result row; a task is a batch of jobs on one texture (its profile is loaded once).

Rows are keyed by a content hash (`job_key`), so running again skips known keys and a job run
twice (a worker lost mid-task, a rerun after kill -9) writes its row once.
"""

from __future__ import annotations

import ctypes
import hashlib
import json
import math
import signal
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from functools import lru_cache

import numpy as np

from hostd.errors import HostdError

KEY_VERSION = "corpus-row-1"  # changes when the scoring of a row changes

# (column, type): the result schema, in order (docs/corpus.md "Result schema")
SCHEMA: tuple[tuple[str, str], ...] = (
    ("key", "str"), ("texture", "str"), ("source", "str"), ("input_sha256", "str"), ("loader", "str"),
    ("codec", "str"), ("codec_version", "str"), ("curve", "str"), ("setting", "str"),
    ("speed_mm_s", "float"), ("fmax_hz", "float"), ("n", "int"), ("spacing_um", "float"),
    ("length_mm", "float"), ("n_keep", "int"), ("bytes", "int"), ("bits_per_mm", "float"),
    ("bits_per_s", "float"), ("Ip", "float"), ("Ia", "float"), ("Iobj", "float"), ("iobj_db", "float"),
    ("spqi", "float"), ("encode_cpu_s", "float"), ("decode_cpu_s", "float"), ("error", "str"),
    ("error_reason", "str"), ("scoring", "str"), ("run", "int"), ("texture_group", "str"),
)
# the columns of stores written before `scoring`, `run` and `texture_group` (hostd.corpus.store
# migrates them)
COLUMNS_V1 = tuple(c for c, _ in SCHEMA[:-3])
COLUMNS = tuple(c for c, _ in SCHEMA)
TIMING_COLUMNS = ("encode_cpu_s", "decode_cpu_s")

# plausible input after unit conversion: 1 nm .. 1 mm between samples, heights within 1 cm
SPACING_UM_RANGE = (1e-3, 1e3)
MAX_PEAK_TO_PEAK_UM = 1e4


class JobTimeout(HostdError):
    """A codec did not finish a job within the per-job time limit."""


@dataclass(frozen=True)
class TextureSpec:
    """Where a texture comes from and how it is loaded; `input_sha256` hashes its bytes."""

    name: str
    source: str
    loader: str  # canonical JSON of the LoadOptions
    input_sha256: str
    group: str = ""  # the manifest's label for summaries (not part of the key)


@dataclass(frozen=True)
class JobSpec:
    key: str
    codec: str  # the name resolve() takes
    setting: str  # canonical JSON
    speed_mm_s: float
    fmax_hz: float


@dataclass(frozen=True)
class Scoring:
    """How rows are scored; everything but the time limit is part of each row's key.
    `calibration`: a display's calibration label (NAME@ID, hostd.perception.calibration) whose
    threshold curve `thresholds` (frequencies, thresholds in µm) replaces the default curve."""

    spqi: bool = True
    timeout_s: float = 60.0
    a: float = 0.581
    b: float = 0.464
    calibration: str | None = None
    thresholds: tuple[tuple[float, ...], tuple[float, ...]] | None = None

    @classmethod
    def calibrated(cls, cal, **kw) -> Scoring:
        """Scored with a Calibration: its (a, b) and its threshold curve."""
        return cls(a=float(cal.a), b=float(cal.b), calibration=cal.label,
                   thresholds=(tuple(map(float, cal.curve.freq_hz)),
                               tuple(map(float, cal.curve.threshold_um))), **kw)

    def as_json(self) -> str:
        d = {"spqi": self.spqi, "a": self.a, "b": self.b}
        if self.calibration is not None:  # (absent: the keys of rows scored before calibrations)
            d["calibration"] = self.calibration
        return json.dumps(d, sort_keys=True)

    def curve(self):
        """The detection-threshold curve b(f) of this scoring."""
        from hostd.perception import thresholds as th

        if self.thresholds is None:
            return th.default_curve()
        return _curve_of(self.thresholds, self.calibration or "calibration")


@lru_cache(maxsize=8)
def _curve_of(table: tuple[tuple[float, ...], tuple[float, ...]], name: str):
    from hostd.perception.thresholds import ThresholdCurve

    return ThresholdCurve(np.array(table[0]), np.array(table[1]), name=name)


@dataclass(frozen=True)
class Task:
    texture: TextureSpec
    jobs: tuple[JobSpec, ...]
    scoring: Scoring
    seq: int = 0  # the driver's number for it: a worker says which job of which task it runs


# ----------------------------------------------------------------------------- keys


# The loader options the first stores keyed on: always in the key. An option added since counts
# only when it differs from its default, so a new option (full_scale_um) re-keys, hence re-runs,
# no row of an existing store.
KEYED_LOADER_FIELDS = ("x_unit", "y_unit", "spacing", "length_mm", "offset_mm", "detrend", "columns",
                       "decimal_comma", "member")


def loader_json(opts) -> str:
    d = asdict(opts)
    d.pop("progress", None)
    defaults = asdict(type(opts)())
    d = {k: v for k, v in d.items() if k in KEYED_LOADER_FIELDS or v != defaults.get(k)}
    return json.dumps(d, sort_keys=True, separators=(",", ":"))


def input_sha256(source: str) -> str:
    """sha256 of the profile's bytes (synthetic: of its name and hostd's version)."""
    from hostd.texture import synth

    h = hashlib.sha256()
    if synth.is_spec(source):
        import hostd

        h.update(f"{source}|hostd {hostd.__version__}".encode())
        return h.hexdigest()
    from hostd.fileio import NotRegular, open_regular

    try:
        with open_regular(source) as fh:  # a FIFO or device is not waited on: its load fails
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
    except (OSError, NotRegular) as exc:
        why = getattr(exc, "strerror", None) or exc
        return "unreadable:" + hashlib.sha256(f"{source}|{why}".encode()).hexdigest()
    return h.hexdigest()


def job_key(tex: TextureSpec, codec_name: str, codec_version: str, setting_json: str,
            speed_mm_s: float, fmax_hz: float, scoring: Scoring) -> str:
    blob = json.dumps([KEY_VERSION, tex.input_sha256, tex.loader, codec_name, codec_version,
                       setting_json, repr(float(speed_mm_s)), repr(float(fmax_hz)), scoring.as_json()])
    return named_key(hashlib.sha256(blob.encode()).hexdigest(), tex.name)


def named_key(content_key: str, texture_name: str) -> str:
    """A row's key: its content's hash and the texture's name, so two textures of identical
    bytes under two names each get their rows (stores of content-only keys are re-keyed by
    this same function when they are opened: hostd.corpus.store)."""
    return hashlib.sha256(f"{content_key}|{texture_name}".encode()).hexdigest()


class KeyMaker:
    """job_key's exact bytes, built from parts encoded once (the driver makes a key per job:
    ~2 µs here instead of ~25 µs through json.dumps). `point(...)` once per (codec, setting,
    geometry) of the plan, `texture(tex)` once per texture, then `key(tex_part, point_part)`."""

    def __init__(self, scoring: Scoring) -> None:
        from json.encoder import encode_basestring_ascii

        self._enc = encode_basestring_ascii  # what json.dumps uses for a str (ensure_ascii)
        self._tail = ", " + self._enc(scoring.as_json()) + "]"

    def texture(self, tex: TextureSpec) -> tuple[str, str]:
        e = self._enc
        return f"[{e(KEY_VERSION)}, {e(tex.input_sha256)}, {e(tex.loader)}, ", tex.name

    def point(self, codec_name: str, codec_version: str, setting_json: str, speed_mm_s: float,
              fmax_hz: float) -> str:
        e = self._enc
        return (f"{e(codec_name)}, {e(codec_version)}, {e(setting_json)}, {e(repr(float(speed_mm_s)))}, "
                f"{e(repr(float(fmax_hz)))}") + self._tail

    @staticmethod
    def key(texture_part: tuple[str, str], point_part: str) -> str:
        content = hashlib.sha256((texture_part[0] + point_part).encode()).hexdigest()
        return named_key(content, texture_part[1])


# ----------------------------------------------------------------------------- time limit


@contextmanager
def deadline(seconds: float) -> Iterator[None]:
    """Raise JobTimeout in this thread after `seconds`: SIGALRM on the main thread (interrupts
    sleeps and waits), else an asynchronous exception (Dask's worker threads), which lands at
    the next Python bytecode: a codec stuck inside one C call is stopped when it returns."""
    if not (seconds and math.isfinite(seconds) and seconds > 0):
        yield
        return
    msg = f"the codec did not finish within the per-job limit of {seconds:g} s (--timeout)"
    if threading.current_thread() is threading.main_thread() and hasattr(signal, "setitimer"):
        def on_alarm(signum, frame):
            raise JobTimeout(msg)

        old = signal.signal(signal.SIGALRM, on_alarm)
        signal.setitimer(signal.ITIMER_REAL, seconds)
        try:
            yield
        finally:
            signal.setitimer(signal.ITIMER_REAL, 0)
            signal.signal(signal.SIGALRM, old)
        return
    tid = threading.get_ident()
    fired = threading.Event()
    lock = threading.Lock()
    done = [False]

    def fire() -> None:
        with lock:
            if not done[0]:
                fired.set()
                ctypes.pythonapi.PyThreadState_SetAsyncExc(ctypes.c_ulong(tid), ctypes.py_object(JobTimeout))

    timer = threading.Timer(seconds, fire)
    timer.daemon = True
    timer.start()
    try:
        yield
    except JobTimeout:
        raise JobTimeout(msg) from None
    finally:
        with lock:
            done[0] = True
        timer.cancel()
        if fired.is_set():  # fired but not yet delivered: withdraw it
            ctypes.pythonapi.PyThreadState_SetAsyncExc(ctypes.c_ulong(tid), None)


# ----------------------------------------------------------------------------- loading


class InputError(HostdError):
    reason = "unreadable_profile"

    def __init__(self, message: str, reason: str) -> None:
        super().__init__(message)
        self.reason = reason


@lru_cache(maxsize=4)
def load_texture(tex: TextureSpec):
    """The texture's Profile (µm), checked for plausible units; cached per process."""
    from hostd.texture import synth
    from hostd.texture.load import LoadOptions, cut_patch, load_profile

    d = json.loads(tex.loader)
    if d.get("columns") is not None:
        d["columns"] = tuple(d["columns"])
    opts = LoadOptions(**d)
    try:
        if synth.is_spec(tex.source):
            whole = synth.from_spec(tex.source)
            prof = cut_patch(whole.heights_um, whole.spacing_um, opts, tex.source)
        else:
            prof = load_profile(tex.source, opts)
    except HostdError as exc:  # the loader's hints name the unit when units are the likely cause
        units = "-unit" in str(exc)
        raise InputError(str(exc), "implausible_units" if units else "unreadable_profile") from None
    except Exception as exc:  # a reader that crashed on a malformed file
        raise InputError(f"{tex.source}: {type(exc).__name__}: {exc}", "unreadable_profile") from None
    lo, hi = SPACING_UM_RANGE
    if not lo <= prof.spacing_um <= hi:
        raise InputError(f"{tex.name}: sample spacing {prof.spacing_um:.3g} µm is implausible "
                         f"(expected {lo:g}..{hi:g} µm): check the x unit / spacing of this entry",
                         "implausible_units")
    ptp = float(np.ptp(prof.heights_um))
    if ptp > MAX_PEAK_TO_PEAK_UM:
        raise InputError(f"{tex.name}: heights span {ptp:.3g} µm, implausible for a texture: check "
                         "the y unit of this entry", "implausible_units")
    prof.heights_um.flags.writeable = False
    return prof


@lru_cache(maxsize=16)
def _reference(tex: TextureSpec, speed_mm_s: float, fmax_hz: float, scoring: Scoring | None = None):
    """(geometry, N', b_k, C_k) of a texture at one geometry (b_k: the scoring's curve)."""
    from hostd.codec import transform

    prof = load_texture(tex)
    geom = transform.Geometry(prof.n, prof.length_mm, speed_mm_s, fmax_hz)
    nk = geom.n_keep
    b_k = (scoring or Scoring()).curve()(geom.frequencies_hz(nk))
    return geom, nk, b_k, transform.analyze(prof.heights_um, nk)


# ----------------------------------------------------------------------------- running


def empty_row(tex: TextureSpec, job: JobSpec) -> dict:
    row = dict.fromkeys(COLUMNS)
    row.update(key=job.key, texture=tex.name, source=tex.source, input_sha256=tex.input_sha256,
               loader=tex.loader, codec=job.codec, setting=job.setting,
               speed_mm_s=float(job.speed_mm_s), fmax_hz=float(job.fmax_hz), texture_group=tex.group or None)
    return row


def empty_task_rows(task: Task, error: str, reason: str) -> list[dict]:
    """A row per job of a task that gave no rows of its own (its worker was lost or killed)."""
    return [{**empty_row(task.texture, j), "scoring": task.scoring.as_json(), "error": error,
             "error_reason": reason} for j in task.jobs]


def run_job(tex: TextureSpec, job: JobSpec, scoring: Scoring) -> dict:
    """One row: encode, decode, score; any failure is the row's error, never an exception."""
    from hostd.codec import transform
    from hostd.corpus import codecs
    from hostd.perception import indices, peer

    row = empty_row(tex, job)
    row["scoring"] = scoring.as_json()
    try:
        codec = codecs.resolve(job.codec)
        row.update(codec=codec.name, codec_version=codec.version)
        setting = json.loads(job.setting)
        row["curve"] = codecs.curve_of(codec, setting)
        prof = load_texture(tex)
        row.update(n=prof.n, spacing_um=prof.spacing_um, length_mm=prof.length_mm)
        try:
            _geom, nk, b_k, c_ref = _reference(tex, float(job.speed_mm_s), float(job.fmax_hz), scoring)
        except HostdError as exc:
            raise InputError(str(exc), "geometry") from None
        row["n_keep"] = nk
        why = codecs.unavailable_reason(codec)
        if why:
            raise codecs.Unavailable(why)
        geometry = {"speed_mm_s": float(job.speed_mm_s), "fmax_hz": float(job.fmax_hz)}
        with deadline(scoring.timeout_s):
            t_work = time.process_time()  # the bare work (codec and scoring), for `hostd bench corpus`
            coded = codecs.run_codec(codec, prof.heights_um, prof.spacing_um, setting, geometry)
        c_dec = transform.analyze(coded.reconstruction_um, nk)
        sc = indices.score(c_ref, c_dec, b_k, scoring.a, scoring.b)
        nbytes = len(coded.data)
        iobj = float(sc.Iobj)
        row.update(bytes=nbytes, bits_per_mm=8.0 * nbytes / prof.length_mm,
                   bits_per_s=8.0 * nbytes * float(job.speed_mm_s) / prof.length_mm,
                   Ip=float(sc.Ip), Ia=float(sc.Ia), Iobj=iobj,
                   iobj_db=-10.0 * math.log10(iobj) if iobj > 0 else None,
                   encode_cpu_s=coded.encode_cpu_s,
                   decode_cpu_s=None if math.isnan(coded.decode_cpu_s) else coded.decode_cpu_s)
        if scoring.spqi:
            row["spqi"] = float(peer.played_spqi(c_ref, c_dec, prof.n, prof.length_mm, float(job.speed_mm_s)))
        row["_work_cpu_s"] = time.process_time() - t_work  # not a column: the store ignores it
    except JobTimeout as exc:
        row.update(error=str(exc), error_reason="timeout")
    except (InputError, codecs.CodecFailure) as exc:
        row.update(error=str(exc), error_reason=exc.reason)
    except HostdError as exc:
        row.update(error=str(exc), error_reason="codec_error")
    except MemoryError:
        row.update(error="out of memory", error_reason="codec_error")
    except SystemExit as exc:  # a codec must not end the worker
        row.update(error=f"the codec called exit({exc.code})", error_reason="codec_error")
    except Exception as exc:  # the codec's own exception: its type and one line
        text = str(exc).strip().splitlines()
        row.update(error=f"{type(exc).__name__}: {text[0] if text else ''}"[:500], error_reason="codec_error")
    return row


# A pool worker's slot in an array the driver reads (hostd.corpus.run._Local): pid, task seq,
# job index, CLOCK_MONOTONIC start of the job (0: idle). The driver kills a worker whose job has
# run past the time limit, whatever the job is doing (a C call, a blocked signal).
SLOT_FIELDS = 4
_slot: tuple | None = None


def _mark(task_seq: int, job: int, start: float) -> None:
    if _slot is not None:
        arr, i = _slot
        base = SLOT_FIELDS * i
        arr[base + 3] = 0.0  # (the driver reads t, seq, job, t again: a torn read is skipped)
        arr[base + 1] = float(task_seq)
        arr[base + 2] = float(job)
        arr[base + 3] = start


KILL_GRACE_S = 1.0  # a worker is killed this long (+ 10 %) after a job's limit; SIGALRM (or, on a
#                     Dask thread, the asynchronous exception) comes first for a codec stuck in Python
TIMEOUT_TOPIC = "hostd-corpus-timeout"  # Dask: the event a worker logs before it kills itself
_watched: dict[int, tuple[int, int, float, float]] = {}  # thread -> (task seq, job, start, limit)
_watch_lock = threading.Lock()
_watchdog: list = []


def kill_after_s(timeout_s: float) -> float:
    return timeout_s * 1.1 + KILL_GRACE_S if math.isfinite(timeout_s) and timeout_s > 0 else math.inf


def _dask_worker():
    """The Dask worker running this thread's task, or None (a pool worker, the driver)."""
    import sys

    if _slot is not None or "distributed" not in sys.modules \
            or threading.current_thread() is threading.main_thread():
        return None
    try:
        from distributed import get_worker

        return get_worker()
    except Exception:  # not in a worker
        return None


def _watch_dask(worker) -> None:
    """A Dask worker's watchdog thread: a job past its limit (a codec stuck where the asynchronous
    exception cannot reach it: a C call, a sleep, a waited-for child) makes the worker log the
    job (TIMEOUT_TOPIC: the driver writes its timeout row and cancels the task) and SIGKILL
    itself; its nanny starts a new worker."""
    import os

    while True:
        time.sleep(0.25)
        now = time.monotonic()
        with _watch_lock:
            late = [(seq, job) for seq, job, start, limit in _watched.values() if now - start > limit]
        if late:
            for seq, job in late:
                try:
                    worker.log_event(TIMEOUT_TOPIC, {"seq": seq, "job": job})
                except Exception:  # the scheduler is gone: the task is lost anyway
                    pass
            time.sleep(0.5)  # the event's batched send goes out
            os.kill(os.getpid(), signal.SIGKILL)


def run_task(task: Task) -> list[dict]:
    """Every job of a task, in order (what a worker process runs); the first row carries the
    task's wall time in "_task_s" (the driver sizes later tasks by it; the store ignores it)."""
    t0 = time.perf_counter()
    rows = []
    worker = _dask_worker()
    limit = kill_after_s(task.scoring.timeout_s)
    me = threading.get_ident()
    if worker is not None and math.isfinite(limit):
        with _watch_lock:
            if not _watchdog:
                th = threading.Thread(target=_watch_dask, args=(worker,), name="hostd-watchdog", daemon=True)
                th.start()
                _watchdog.append(th)
    try:
        for i, j in enumerate(task.jobs):
            start = time.monotonic()
            _mark(task.seq, i, start)
            if worker is not None:
                with _watch_lock:
                    _watched[me] = (task.seq, i, start, limit)
            rows.append(run_job(task.texture, j, task.scoring))
    finally:
        _mark(task.seq, 0, 0.0)
        if worker is not None:
            with _watch_lock:
                _watched.pop(me, None)
    if rows:
        rows[0]["_task_s"] = time.perf_counter() - t0
    return rows


def pool_worker_init(slots, counter) -> None:
    """A local pool worker's initializer: Ctrl-C is the driver's; die with the fork server (which
    dies with the driver: hostd.corpus.lifeline); take the next slot of `slots`."""
    import os

    from hostd.corpus.lifeline import die_with_parent

    global _slot
    ignore_sigint()
    die_with_parent()
    with counter.get_lock():
        i = counter.value
        counter.value += 1
    n = len(slots) // SLOT_FIELDS
    if i < n:
        slots[SLOT_FIELDS * i] = float(os.getpid())
        _slot = (slots, i)


def run_task_measured(task: Task) -> list[dict]:
    """run_task, with the worker's CPU time for the whole task in the first row's
    "_worker_cpu_s", and in "_load_cpu_s" the CPU time of loading the texture and its references
    when this process had not loaded it yet (0 when cached here): for `hostd bench corpus`,
    which counts one load per texture as input work and every further load (the same texture
    loaded again in another worker) as the machinery's. The store ignores both fields."""
    t0 = time.process_time()
    misses = load_texture.cache_info().misses + _reference.cache_info().misses
    try:
        load_texture(task.texture)
        for v, f in dict.fromkeys((float(j.speed_mm_s), float(j.fmax_hz)) for j in task.jobs):
            _reference(task.texture, v, f, task.scoring)
    except Exception:  # run_job makes the error row
        pass
    loaded = load_texture.cache_info().misses + _reference.cache_info().misses > misses
    t1 = time.process_time()
    rows = run_task(task)
    if rows:
        rows[0]["_worker_cpu_s"] = time.process_time() - t0
        rows[0]["_load_cpu_s"] = t1 - t0 if loaded else 0.0
    return rows


def warm_up(hold_s: float = 0.0) -> int:
    """A task that imports what a job uses (the fork server preloads most of it) and waits
    `hold_s` (no CPU): the bench starts a pool's workers with it before timing a run. Returns
    the worker's pid."""
    import os

    from hostd.codec import transform  # noqa: F401
    from hostd.corpus import codecs  # noqa: F401
    from hostd.perception import indices, peer  # noqa: F401

    time.sleep(hold_s)
    return os.getpid()


def ignore_sigint() -> None:
    """Worker initializer: Ctrl-C is the driver's to handle (it keeps the finished rows)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
