"""`hostd run`: the background service.

Threads of the main process: the control socket (a pool of handlers), the spool watcher,
the quality worker (scoring and SQLite, with its pending queue), the pump writer (the one
writer of the pump's pipe), and the main loop (systemd notify and watchdog, pump log lines,
signals). The real-time pump is a separate process (pumpproc).
"""

from __future__ import annotations

import hashlib
import itertools
import json
import logging
import math
import multiprocessing as mp
import os
import queue
import signal
import sqlite3
import stat
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path

from hostd.device.health import CLOCK_TOLERANCE, REPORT_SLACK_S, fault_names
from hostd.device.health import STATE_NAMES as DEVICE_STATES
from hostd.device.protocol import BUFFER_CAPACITY, SAMPLE_RATE_HZ
from hostd.errors import ConfigError, HostdError
from hostd.fileio import open_dir, read_regular_at, write_at
from hostd.service import qualitylog
from hostd.service.config import Config, check_paths
from hostd.service.control import REQUEST_DEADLINE_S, ClientConn, ControlServer
from hostd.service.lean import children_with_one_blas_thread
from hostd.service.library import Library, check_name
from hostd.service.logsetup import CONTROL_CHARS
from hostd.service.notify import Notifier
from hostd.service.pumpproc import (
    FLOAT_FIELDS,
    PUBLISH_SEQ,
    RENDER_REASONS,
    STAT_FIELDS,
    STATE_NAMES,
    pump_main,
)

log = logging.getLogger("hostd")
MAX_HEADER = 4096
RESTARTS_PER_MINUTE = 3  # a worker that dies more often stays dead and the watchdog starves
QUALITY_RETRY_S = (0.5, 30.0)  # a quality row that cannot be written is retried, back-off doubling


IN_MODIFY, IN_ATTRIB, IN_CLOSE_WRITE, IN_MOVED_TO, IN_CREATE = 0x2, 0x4, 0x8, 0x80, 0x100


def _spool_events(dir_fd: int) -> int | None:
    """An inotify descriptor that turns readable when an entry of the directory `dir_fd` is
    created, written, closed, moved in or changes its attributes (Linux; the directory by its
    descriptor, so a rename of the path changes nothing); None where there is none (the
    watcher then scans every period)."""
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        fd = libc.inotify_init1(os.O_NONBLOCK | os.O_CLOEXEC)
        if fd < 0:
            return None
        mask = IN_MODIFY | IN_ATTRIB | IN_CLOSE_WRITE | IN_MOVED_TO | IN_CREATE
        if libc.inotify_add_watch(fd, f"/proc/self/fd/{dir_fd}".encode(), mask) < 0:
            os.close(fd)
            return None
        return fd
    except (OSError, AttributeError):
        return None


def _drain(fd: int) -> None:
    """Read whatever is waiting on a non-blocking descriptor (the events themselves do not matter:
    any change means a look at the directory)."""
    try:
        while os.read(fd, 4096):
            pass
    except BlockingIOError:
        pass


class BadRequest(HostdError):
    """A control-socket request that is not well formed."""


class StimulusFailed(HostdError):
    """A stimulus that was not played whole (no display, the display lost or running dry
    mid-stimulus, interrupted): the client may ask again (its reply says "retry": true)."""

    retry = True


STIMULUS_SLACK_S = 5.0  # beyond its duration, how long a stimulus may take before hostd gives up
MAX_REACH_FREQUENCIES = 256  # per `reach` request


class PumpWriter:
    """The one writer of the pump's pipe. Handler threads hand their commands to this thread, so
    no two messages ever interleave on the pipe (a texture of N' = 16,000 pickles to more than
    a pipe's atomic write). A select or stop still waiting to be sent is superseded by a newer
    one: only the latest choice matters to the pump."""

    def __init__(self, conn) -> None:
        self.conn = conn
        self.cv = threading.Condition()
        self.pending: deque = deque()
        self.closed = False
        self.thread = threading.Thread(target=self._run, name="pump-writer", daemon=True)
        self.thread.start()

    def send(self, msg: tuple) -> None:
        with self.cv:
            if self.closed:
                raise HostdError("hostd is stopping")
            if msg[0] in ("select", "stop"):
                kept = [m for m in self.pending if m[0] not in ("select", "stop")]
                self.pending.clear()
                self.pending.extend(kept)
            self.pending.append(msg)
            self.cv.notify()

    def _run(self) -> None:
        while True:
            with self.cv:
                while not self.pending:
                    self.cv.wait()
                msg = self.pending.popleft()
            if msg is None:
                return
            try:
                self.conn.send(msg)
            except (OSError, ValueError) as e:  # the pump is gone: the main loop says so and stops
                log.error("cannot send %s to the pump: %s", msg[0], e)

    def close(self, last: tuple = ("quit",), timeout_s: float = 3.0) -> None:
        with self.cv:
            if self.closed:
                return
            self.pending.append(last)
            self.pending.append(None)
            self.closed = True
            self.cv.notify()
        self.thread.join(timeout_s)


# what a device's counters may claim over a play, beyond the host's own clock: the device's
# clock runs at most this much fast (crystal tolerance, with margin), plus its report's age


def bound_play(c0: dict, c1: dict, host_s: float) -> tuple[dict, list[str]]:
    """What a play delivered, from the device's counters at its start (c0) and end (c1), bounded by
    what the host knows: its own clock (host_s elapsed), the samples it sent and the device's
    buffer. Returns the plays row's device_s, played_s, played_fraction and underruns, and the
    counters that claimed the impossible (empty when none did), each said in a few words."""
    bad: list[str] = []
    limit_s = max(host_s, 0.0) * (1 + CLOCK_TOLERANCE) + REPORT_SLACK_S
    # device time elapsed between its reports, summed over links (the pump's, never going back;
    # bounded there by the links' time up): a play that began before the device's first report,
    # or spans a replug, compares no two clocks
    device_s = c1["device_elapsed_s"] - c0["device_elapsed_s"]
    if not math.isfinite(device_s) or device_s < 0:
        bad.append(f"its clock went from {c0['device_elapsed_s']:.3f} s to {c1['device_elapsed_s']:.3f} s")
        device_s = 0.0
    elif device_s > limit_s:
        bad.append(f"{device_s:.1f} s of its clock in {host_s:.1f} s")
        device_s = max(host_s, 0.0)
    fraction = c1["played_fraction"] if device_s > 0 else None
    if fraction is not None and not (math.isfinite(fraction) and 0.0 <= fraction <= 1.0):
        bad.append(f"a played fraction of {fraction}")
        fraction = min(max(fraction, 0.0), 1.0) if math.isfinite(fraction) else None
    if c1["render_at"] == "device":  # the display renders: nothing is played from its buffer,
        played_s = (fraction or 0.0) * device_s  # the share of device time it reported rendering
    else:
        played = c1["device_samples_played"] - c0["device_samples_played"]
        # at most what was sent meanwhile, plus what the buffer held at the start
        most = max(c1["samples"] - c0["samples"], 0) + BUFFER_CAPACITY
        if played < 0:
            bad.append(f"samples played went back by {-played}")
            played = 0
        elif played > most:
            bad.append(f"{played} samples played of at most {most} sent and buffered")
            played = most
        played_s = played / SAMPLE_RATE_HZ
        if played_s > limit_s:
            bad.append(f"{played_s:.1f} s played in {host_s:.1f} s")
            played_s = max(host_s, 0.0)
    underruns = c1["device_underruns"] - c0["device_underruns"]
    most_underruns = int(limit_s * SAMPLE_RATE_HZ / 2) + 1  # an episode: a sample missed, one played
    if underruns < 0:
        bad.append(f"underruns went back by {-underruns}")
        underruns = 0
    elif underruns > most_underruns:
        bad.append(f"{underruns} underruns in {host_s:.1f} s")
        underruns = most_underruns
    return {"device_s": device_s, "played_s": played_s, "played_fraction": fraction,
            "underruns": underruns}, bad


class Daemon:
    def __init__(self, cfg: Config, notifier: Notifier | None = None) -> None:
        self.cfg = cfg
        check_paths(cfg)
        self.spool = Path(cfg.library.spool)
        self.db_path = cfg.quality.db
        try:
            self.library = Library(cfg.library.dir, cfg.library.max_stream_bytes, cfg.library.max_n,
                                   cfg.library.max_n_keep, travel_um=cfg.output.travel_um)
            self.spool.parent.mkdir(parents=True, exist_ok=True)
            # group members may drop files here: the spool is sticky (made so if it is not), so
            # they cannot rename or remove what is not theirs, rejected/ included
            self.spool_fd = open_dir(self.spool, "library.spool", others_may_write=True, create_mode=0o1770)
            self.rejected_fd = self._open_rejected()
            qualitylog.connect(self.db_path).close()
        except (OSError, sqlite3.Error, HostdError) as e:
            raise ConfigError(f"{cfg.path}: cannot set up the library, spool or quality log: {e}") from None
        self.curve = None
        self.calibration = None  # NAME@ID recorded with each quality row (quality.calibration)
        if cfg.quality.calibration:
            from hostd.perception import calibration

            cal = calibration.load(cfg.quality.calibration)
            self.curve, self.calibration = cal.curve, cal.label
        elif cfg.quality.thresholds:
            from hostd.perception.calibration import load_curve

            self.curve = load_curve(cfg.quality.thresholds)
        ctx = mp.get_context("spawn")
        self.select_lock = threading.Lock()  # one select or stop at a time
        self.selected_sha: str | None = None
        self.quality_pending: deque = deque()  # scored rows not yet written (disk full, I/O error)
        # rows the last run could not write: written first (then the pending-rows file is removed)
        self.pending_paths = qualitylog.pending_paths(self.db_path, cfg.library.dir)
        kept = []
        for p in self.pending_paths:
            try:
                kept += [r for r in qualitylog.load_pending(p) if r not in kept]
            except OSError as e:
                log.warning("quality log: cannot read the pending-rows file %s (%s); its streams are scored "
                            "again", p, e.strerror or e)
        self.quality_pending.extend(kept)
        self.pending_file_rows = len(kept)
        self.pending_keys = {(r["name"], r["sha256"]) for r in kept}
        self.scoring: set[tuple[str, str]] = set(self.pending_keys)  # queued or pending, not yet written
        if kept:
            log.info("quality log: %d rows pending from the last run (%s); writing them first", len(kept),
                     ", ".join(str(p) for p in self.pending_paths if p.exists()))
        self.stats = ctx.Array("d", len(STAT_FIELDS), lock=False)
        self.conn, self.child_conn = ctx.Pipe()
        self.proc = ctx.Process(target=pump_main, args=(cfg, self.child_conn, self.stats),
                                name="hostd-pump", daemon=True)
        self.pump_writer: PumpWriter | None = None
        self._stop_deadline = math.inf  # the quality worker's last retry at shutdown
        self.signalled = False  # set by the SIGTERM/SIGINT handler, which must take no lock
        self.quality_q: queue.Queue = queue.Queue()
        self.stop_event = threading.Event()
        # the threads sleep on descriptors, not on timers: stop_r turns readable (for good) at the
        # stop; wake_r wakes the main loop (a signal through set_wakeup_fd, a worker that ended)
        self.stop_r, self.stop_w = os.pipe2(os.O_NONBLOCK | os.O_CLOEXEC)
        self.wake_r, self.wake_w = os.pipe2(os.O_NONBLOCK | os.O_CLOEXEC)
        self.selected: str | None = None
        self.selects_sent = 0  # selects handed to the pump (status: an idempotent one is not)
        self.play: tuple[str, str, float, dict] | None = None  # name, sha256, started, counters
        self.accepted = 0
        self.refused = 0
        # from the pump, on change: transport in use, hotplug mode, last reconnection time
        self.pump_info: dict = {"transport": None, "hotplug": None, "last_reconnect_s": None}
        self.lock = threading.Lock()
        self.notifier = notifier if notifier is not None else Notifier()
        self.control: ControlServer | None = None
        self.metrics = None  # the Prometheus endpoint's server, when metrics.listen is set
        self.workers: dict[str, tuple[Callable[[], None], threading.Thread | None, list[float]]] = {}
        self.dead_workers: set[str] = set()
        # stimuli ([experiment] stimuli): one at a time; the pump's answers by stimulus id
        self.stimulus_lock = threading.Lock()
        self.stimulus_ids = itertools.count(1)
        self.stimulus_answers: dict[int, list] = {}  # id -> [Event, answer], under self.lock
        self._stimulus_bound = None

    def _open_rejected(self) -> int:
        """spool/rejected, created and checked by us (a directory, ours, not a link). Anything
        else by that name (a member's link or directory, left before the spool was sticky) is
        moved aside first; afterwards its descriptor is used, so renaming it changes nothing."""
        try:
            return open_dir("rejected", "library.spool rejected/", dir_fd=self.spool_fd, create_mode=0o750)
        except HostdError as e:
            aside = f"rejected.untrusted-{int(time.time())}"
            log.warning("spool: %s; moved aside as %s", e, aside)
            os.rename("rejected", aside, src_dir_fd=self.spool_fd, dst_dir_fd=self.spool_fd)
            return open_dir("rejected", "library.spool rejected/", dir_fd=self.spool_fd, create_mode=0o750)

    # ------------------------------------------------------------ intake
    def accept(self, name: str, data: bytes, source: str) -> dict:
        """Validate and store a stream; the texture being played is not disturbed."""
        try:
            check_name(name)
            s, sha = self.library.add(name, data)
        except HostdError as e:
            with self.lock:
                self.refused += 1
            log.warning("refused %s from %s: %s", name, source, e)
            raise
        with self.lock:
            self.accepted += 1
        self.queue_for_scoring(name, data, sha, time.time())
        log.info("accepted %s from %s: %d bytes, %s, N'=%d", name, source, len(data), s.method, s.n_keep)
        return {"name": name, "sha256": sha, "bytes": len(data), "method": s.method, "n_keep": s.n_keep}

    def select(self, name: str) -> dict:
        """Serialized and idempotent: the texture already playing (same name, same bytes) is not
        sent again; the pipe has one writer (PumpWriter)."""
        with self.select_lock:
            data = self.library.read(name)
            sha = hashlib.sha256(data).hexdigest()
            if self.selected == name and self.selected_sha == sha:
                return {"playing": name}
            s = self.library.decode(data)  # the library's limits, again: it may predate them
            self.end_play()
            self.pump_writer.send(("select", (name, s.coefficients, s.n, s.length_mm)))
            self.selects_sent += 1
            self.selected, self.selected_sha = name, sha
            self.play = (name, sha, time.time(), self.counters())
        log.info("playing %s", name)
        return {"playing": name}

    def stop_playing(self) -> dict:
        with self.select_lock:
            self.end_play()
            self.pump_writer.send(("stop",))
            self.selected = self.selected_sha = None
        return {"playing": None}

    def end_play(self) -> None:
        """Log what the texture being played was delivered, from the device's own counters (the
        pump's health snapshot) before the next select, stop or shutdown: the time the device
        played it from its buffer, its played_fraction and the underruns it counted meanwhile."""
        with self.lock:
            play, self.play = self.play, None
        if play is None:
            return
        name, sha, started, c0 = play
        c1 = self.counters()
        ended = time.time()
        row, impossible = bound_play(c0, c1, ended - started)
        row.update({"name": name, "sha256": sha, "started_at": started, "ended_at": ended})
        if impossible:  # one line per play: what the device said, and what the host logged instead
            log.warning("device %s reported the impossible while playing %s: %s; logged within what the "
                        "host knows", self.pump_info.get("transport") or self.cfg.device.transport, name,
                        "; ".join(impossible))
        try:
            con = qualitylog.connect(self.db_path)
            try:
                qualitylog.insert_play(con, row)
            finally:
                con.close()
            log.info("played %s: %.1f s from the buffer, played fraction %s, %d underruns", name,
                     row["played_s"], "-" if row["played_fraction"] is None else
                     f"{row['played_fraction']:.2%}", row["underruns"])
        except sqlite3.Error as e:  # the log must not stop playback
            log.error("quality log: cannot record the play of %s: %s", name, e)

    def counters(self) -> dict:
        """The pump's counters, from shared memory: one snapshot of one publish (the pump's
        seqlock), so the device's counters and its clock agree; a pump stopped in the middle of
        a publish (SIGSTOP) leaves a torn one after 10 ms of retries rather than a hang."""
        for _ in range(20):
            seq = self.stats[PUBLISH_SEQ]
            vals = self.stats[:]
            if seq % 2 == 0 and self.stats[PUBLISH_SEQ] == seq:
                break
            time.sleep(0.0005)
        st = dict(zip(STAT_FIELDS, vals, strict=True))
        del st["publish_seq"]
        for k in st:
            if k not in FLOAT_FIELDS:
                st[k] = int(st[k])
        st["state"] = STATE_NAMES.get(st["state"], "?")
        st["connected"] = bool(st["connected"])
        # from the device's own STATUS counters (hostd.device.health)
        code = st["device_state"]
        st["device_state"] = DEVICE_STATES.get(code, "unknown") if st["connected"] else "unknown"
        st["device_faults"] = fault_names(st.pop("device_fault_bits"))
        st["underruns"] = st["device_underruns"]  # the name older clients read
        st["render_at"] = "device" if st["render_at"] else "host"  # who renders the texture now
        st["render_reason"] = RENDER_REASONS[st["render_reason"]] if 0 <= st["render_reason"] < len(
            RENDER_REASONS) else "?"  # and why there ([render] where, the display's version and CAPS)
        st["target_fill_ms"] = round(st["target_fill"] / SAMPLE_RATE_HZ * 1e3, 2)
        pf = st["played_fraction"]  # a share: whatever a device says, shown within [0, 1]
        st["played_fraction"] = min(max(pf, 0.0), 1.0) if math.isfinite(pf) else 0.0
        return st

    def status(self) -> dict:
        st = self.counters()
        st.update({"texture": self.selected, "pid": os.getpid(), "pump_alive": self.proc.is_alive(),
                   "accepted": self.accepted, "refused": self.refused, "library": len(self.library.names()),
                   "selects_sent": self.selects_sent,
                   "quality_pending": self.quality_q.qsize() + len(self.quality_pending),
                   "device": self.cfg.device.transport})
        st.update(self.pump_info)
        return st

    # ------------------------------------------------------------ workers
    def quality_worker(self) -> None:
        """Score each accepted stream and write its row. Rows are written in batches (at most
        qualitylog.BATCH_ROWS per transaction). A batch that cannot be written (disk full, I/O
        error, a locked or unopenable database) stays in quality_pending and is retried, back-off
        doubling from 0.5 s to 30 s, and at once when the database's file system has 16 kB more
        free than at the failure; after a full-disk error the -wal is checkpointed and cut to zero
        bytes (its frames would squat the space freed). One log line when writing fails and one
        when it works again. What is still pending at exit goes to the pending-rows file, which
        the next start writes first (or, if even that cannot be written, the streams are scored
        again at the next start: a stored stream without a row)."""
        try:  # opened now, while there is space: its -shm (32 kB) is not made again on a full disk
            con = qualitylog.connect(self.db_path)
        except sqlite3.Error:
            con = None
        failing_since = None
        retry_at = 0.0
        backoff = QUALITY_RETRY_S[0]
        free_at_fail = None
        while True:
            try:
                # idle: asleep until a stream arrives or the stop (a None); a pending row is retried
                item = self.quality_q.get(timeout=0.05 if self.quality_pending else None)
            except queue.Empty:
                item = None
            stopping = self.stop_event.is_set()
            if item is not None:
                name, data, sha, t = item
                try:
                    q = self.cfg.quality
                    row = qualitylog.score_row(data, name, sha, t, q.a, q.b, self.curve, self.calibration)
                    self.quality_pending.append(row)
                except Exception as e:  # a scoring failure must not stop the service
                    self.scoring.discard((name, sha))
                    log.error("quality scoring of %s failed: %s", name, e)
                continue
            if not self.quality_pending:
                if stopping:
                    break
                continue
            if time.monotonic() < retry_at and not self._db_space_grew(free_at_fail):
                if stopping and time.monotonic() > self._stop_deadline:
                    break
                continue
            try:
                if con is None:
                    con = qualitylog.connect(self.db_path)
                while self.quality_pending:
                    batch = list(itertools.islice(self.quality_pending, qualitylog.BATCH_ROWS))
                    qualitylog.insert_batch(con, batch)
                    for row in batch:
                        self.quality_pending.popleft()
                        self.scoring.discard((row["name"], row["sha256"]))
                        log.info("quality %s: Ip=%.4f Ia=%.4f Iobj=%.4f", row["name"], row["ip"], row["ia"],
                                 row["iobj"])
                if self.pending_file_rows:  # every row of the pending-rows files is in the log now
                    for p in self.pending_paths:
                        p.unlink(missing_ok=True)
                    self.pending_file_rows = 0
                if failing_since is not None:
                    qualitylog.checkpoint(con)  # the -wal back to zero bytes
                    log.warning("quality log: writing again after %.0f s; every pending row is written",
                                time.monotonic() - failing_since)
                failing_since, backoff, free_at_fail = None, QUALITY_RETRY_S[0], None
            except (sqlite3.Error, OSError) as e:
                full = qualitylog.is_full(e)
                if con is not None and full:
                    qualitylog.checkpoint(con)  # gives back what the -wal holds beyond its last commit
                if failing_since is None:
                    failing_since = time.monotonic()
                    log.error("quality log: cannot write to %s (%s); %d rows kept pending and retried until "
                              "written (%s)", self.db_path, e, len(self.quality_pending),
                              "free 64 kB or more on its file system" if full else "see the error")
                if con is not None and not full:  # (full: kept open, with its -shm)
                    con.close()
                    con = None
                free_at_fail = self._db_free_bytes()
                retry_at = time.monotonic() + backoff
                backoff = min(backoff * 2, QUALITY_RETRY_S[1])
                if stopping and time.monotonic() > self._stop_deadline:
                    break
        if con is not None:
            con.close()
        if self.quality_pending:
            self.keep_pending_rows()

    def queue_for_scoring(self, name: str, data: bytes, sha: str, received_at: float) -> bool:
        """Once per (name, content) until its row is written: an upload during the start-up's
        look for unscored streams is not scored twice."""
        with self.lock:
            if (name, sha) in self.scoring:
                return False
            self.scoring.add((name, sha))
        self.quality_q.put((name, data, sha, received_at))
        return True

    def keep_pending_rows(self) -> None:
        """At exit: rows not written go to the pending-rows file for the next start."""
        rows = list(self.quality_pending)
        why = []
        for path in self.pending_paths:
            try:
                qualitylog.save_pending(path, rows)
                log.error("quality log: %d rows not written at exit; kept in %s, written at the next start",
                          len(rows), path)
                return
            except OSError as e:
                why.append(f"{path}: {e.strerror or e}")
        log.error("quality log: %d rows not written at exit and not kept (%s); their streams are scored "
                  "again at the next start", len(rows), "; ".join(why))

    def _db_free_bytes(self) -> int | None:
        try:
            st = os.statvfs(Path(self.db_path).parent)
            return st.f_bavail * st.f_frsize
        except OSError:
            return None

    def _db_space_grew(self, free_at_fail: int | None) -> bool:
        """True when the database's file system has 16 kB more free than at the last failure."""
        if free_at_fail is None:
            return False
        free = self._db_free_bytes()
        return free is not None and free >= free_at_fail + 16 * 1024

    def rescore_missing(self) -> None:
        """Streams stored before a crash but not yet logged are scored (after READY=1, in its own
        thread: a large library takes seconds to read; a stop request ends it)."""
        t0 = time.monotonic()
        con = qualitylog.connect(self.db_path)
        try:
            known = qualitylog.known(con)
        finally:
            con.close()
        queued = 0
        for name in self.library.names():
            if self.stop_event.is_set() or self.signalled:
                return
            try:
                data = self.library.read(name)
                sha = hashlib.sha256(data).hexdigest()
                if (name, sha) in known:
                    continue
                self.library.decode(data)  # within today's limits, or it would fail every start
                if self.queue_for_scoring(name, data, sha, self.library.mtime(name)):
                    queued += 1
            except (HostdError, OSError) as e:
                log.warning("library: %s not scored: %s", name, e)
        if queued:
            log.info("library: %d stored streams without a quality row queued for scoring (%.1f s)", queued,
                     time.monotonic() - t0)

    def spool_watcher(self) -> None:
        """Take in .vtx files dropped into the spool once their writer is done: size and mtime
        unchanged for library.spool_settle_s and the mtime at least that old. Anything else
        named *.vtx (symlink, FIFO, device, directory, too big) is moved to rejected/ with a note.
        Every operation is relative to the spool's and rejected/'s descriptors (opened and
        checked at start-up) and follows no link: a member who renames rejected/ or plants
        links changes nothing the daemon writes or reads."""
        import select

        settle = self.cfg.library.spool_settle_s
        limit = self.cfg.library.max_stream_bytes
        seen: dict[str, tuple[tuple[int, int], float]] = {}  # name -> (size, mtime_ns), since
        events = _spool_events(self.spool_fd)  # inotify where there is one, else a scan per period
        period = min(0.3, settle / 2)
        first = True
        try:
            while not self.stop_event.is_set():
                if not first:
                    # asleep until the spool changes (or the stop); a timer only while a file settles
                    wait = [self.stop_r] + ([events] if events is not None else [])
                    ready = select.select(wait, [], [], period if seen or events is None else None)[0]
                    if self.stop_event.is_set():
                        break
                    if events is not None and events in ready:
                        _drain(events)
                first = False
                self._scan_spool(seen, settle, limit)
        finally:
            if events is not None:
                os.close(events)

    def _scan_spool(self, seen: dict, settle: float, limit: int) -> None:
        """One look at the spool (spool_watcher)."""
        try:
            with os.scandir(self.spool_fd) as it:
                entries = list(it)
        except OSError as e:
            log.error("spool: cannot list %s: %s", self.spool, e.strerror)
            return
        now = time.time()
        for ent in entries:
            name = ent.name
            if not name.endswith(".vtx") or name.startswith("."):
                continue
            try:
                st = ent.stat(follow_symlinks=False)
            except FileNotFoundError:
                continue
            if not stat.S_ISREG(st.st_mode):
                self._reject_spool(name, "not a regular file (symlink, FIFO, device or directory): the "
                                         "spool takes regular files only")
                continue
            if st.st_size > limit:
                self._reject_spool(name, f"stream of {st.st_size} bytes exceeds the limit of {limit} "
                                         "(library.max_stream_bytes)")
                continue
            sig = (st.st_size, st.st_mtime_ns)
            prev = seen.get(name)
            if prev is None or prev[0] != sig:
                seen[name] = (sig, now)  # (still) being written: wait until it holds still
                continue
            if now - prev[1] < settle or now - st.st_mtime_ns / 1e9 < settle:
                continue
            seen.pop(name, None)
            try:
                data = read_regular_at(self.spool_fd, name, limit, expect=sig)
            except BlockingIOError:
                continue
            except HostdError as e:  # NotRegular (swapped since the stat), too big
                self._reject_spool(name, str(e))
                continue
            except OSError as e:
                log.error("spool: cannot take in %s: %s", name, e.strerror or e)
                continue
            try:
                self.accept(name[:-4], data, "spool")
                os.unlink(name, dir_fd=self.spool_fd)
            except HostdError as e:
                self._reject_spool(name, str(e))
            except OSError:
                pass  # taken in; its writer removed or replaced it meanwhile
        for name in set(seen) - {e.name for e in entries}:
            seen.pop(name, None)

    def _reject_spool(self, name: str, why: str) -> None:
        try:  # the reason first, so that whoever sees the rejected file finds why
            write_at(self.rejected_fd, name + ".error", (why + "\n").encode(), mode=0o640)
            # renameat moves the entry itself (a link, not its target) into our rejected/
            os.rename(name, name, src_dir_fd=self.spool_fd, dst_dir_fd=self.rejected_fd)
            log.warning("spool: rejected %s: %s", name, why)
        except (OSError, HostdError) as e:
            log.error("spool: cannot move %s to rejected/ (%s); it stays: %s", name, e, why)

    # ------------------------------------------------------------ control socket
    def handle_conn(self, client: ClientConn) -> None:
        """One client: one request line (and an upload's bytes), one reply line, always."""
        try:
            reply = {"ok": True, **self.respond(client)}
        except HostdError as e:
            reply = {"ok": False, "error": str(e)}
            if getattr(e, "retry", False):
                reply["retry"] = True
        except TimeoutError:
            reply = {"ok": False, "error": f"request not complete within {REQUEST_DEADLINE_S:g} s (or "
                                           "dropped to serve another client): send the whole request at once"}
            log.warning("control socket: dropped a client that did not send its request in time")
        except Exception as e:  # a bug must still give the client an answer and the log one line
            log.error("control socket: request failed: %s: %s", type(e).__name__, e)
            reply = {"ok": False, "error": f"internal error ({type(e).__name__}): see hostd's log"}
        client.reply((json.dumps(reply) + "\n").encode())

    def refuse(self, msg: str) -> None:
        with self.lock:
            self.refused += 1
        raise HostdError(msg)

    def respond(self, rfile: ClientConn) -> dict:
        line = rfile.readline(MAX_HEADER)
        if len(line) > MAX_HEADER or not line.endswith(b"\n"):
            raise BadRequest(f"bad request: one JSON object of at most {MAX_HEADER} bytes on one line "
                             "expected")
        try:
            req = json.loads(line)
        except (ValueError, UnicodeDecodeError, RecursionError):
            raise BadRequest("bad request: one JSON object per line expected") from None
        if not isinstance(req, dict):
            raise BadRequest("bad request: one JSON object per line expected")
        cmd = req.get("cmd")
        if cmd == "send":
            size = req.get("size")
            if not isinstance(size, int) or isinstance(size, bool):
                self.refuse(f"bad request: size must be an integer number of bytes, not {size!r:.40}")
            limit = self.cfg.library.max_stream_bytes
            if not 0 < size <= limit:
                log.warning("refused an upload of %d bytes (limit %d)", size, limit)
                self.refuse(f"stream of {size} bytes refused: the limit is {limit} "
                            "(library.max_stream_bytes)")
            name = req.get("name", "")
            if not isinstance(name, str):
                self.refuse("bad request: name must be a string")
            if not isinstance(name, str) or CONTROL_CHARS.search(name):
                self.refuse(f"bad texture name {name!r}: control characters are not allowed")
            data = rfile.read(size)
            rfile.done_reading()
            if len(data) != size:
                self.refuse(f"upload truncated: got {len(data)} of {size} bytes")
            return self.accept(name, data, "socket")
        rfile.done_reading()
        if cmd == "list":
            return {"textures": self.library.names(), "playing": self.selected}
        if cmd == "select":
            name = req.get("name")
            if not isinstance(name, str):
                raise BadRequest("bad request: name must be a string")
            return self.select(check_name(name))
        if cmd == "stop":
            return self.stop_playing()
        if cmd == "status":
            return self.status()
        if cmd == "quality":
            since = req.get("since")
            if since is not None and (not isinstance(since, int | float) or isinstance(since, bool)
                                      or not math.isfinite(since)):
                raise BadRequest(f"bad request: since must be unix seconds (a number), not {since!r:.40}")
            con = qualitylog.connect_readonly(self.db_path)  # answers with the disk full, too
            try:
                return {"rows": qualitylog.query(con, since)}
            finally:
                con.close()
        if cmd == "stimulus":
            return self.play_stimulus(req)
        if cmd == "reach":
            return self.reach(req)
        if cmd == "shutdown":
            self.may_shut_down(rfile.peer_uid)
            self.stop()
            return {"shutting_down": True}
        raise BadRequest(f"unknown command {cmd!r:.40}")

    # ------------------------------------------------------------ stimuli
    def stimulus_bound(self):
        """The bound every stimulus is checked against (hostd.render.stimulus, from this
        daemon's config: output.travel_um, output.slew_um_s, render.actuator)."""
        if not self.cfg.experiment.stimuli:
            self.refuse(f"this hostd does not play stimuli: set [experiment] stimuli = true in "
                        f"{self.cfg.path} and restart hostd (`hostd experiment threshold --help`)")
        if self._stimulus_bound is None:
            from hostd.render.stimulus import StimulusBound

            self._stimulus_bound = StimulusBound(self.cfg.render_config())
        return self._stimulus_bound

    def reach(self, req: dict) -> dict:
        """The largest stimulus (µm peak at the finger) at each frequency asked."""
        from hostd.render.stimulus import MAX_DURATION_S, MAX_FREQUENCY_HZ

        bound = self.stimulus_bound()
        fs = req.get("frequencies_hz")
        if not (isinstance(fs, list) and 0 < len(fs) <= MAX_REACH_FREQUENCIES
                and all(isinstance(f, int | float) and not isinstance(f, bool) and math.isfinite(f)
                        and 0 < f <= MAX_FREQUENCY_HZ for f in fs)):
            raise BadRequest(f"bad request: frequencies_hz must be a list of 1..{MAX_REACH_FREQUENCIES} "
                             f"frequencies in (0, {MAX_FREQUENCY_HZ:g}] Hz")
        return {"reach_um": [bound.reach_um(float(f)) for f in fs], "max_duration_s": MAX_DURATION_S,
                "max_frequency_hz": MAX_FREQUENCY_HZ}

    def play_stimulus(self, req: dict) -> dict:
        """Play one sinusoid (frequency_hz, amplitude_um at the finger, duration_s) on the display
        and answer once the device has played it (its own count of samples played), then the
        display is idle. Checked here against the display's reach (StimulusRefused: nothing is
        played), and again by the pump; it stops a texture being played. One at a time."""
        bound = self.stimulus_bound()
        f, a, d = (req.get(k) for k in ("frequency_hz", "amplitude_um", "duration_s"))
        try:
            bound.check(f, a, d)
        except HostdError as e:
            log.warning("control socket: %s", e)
            self.refuse(str(e))
        if not self.stimulus_lock.acquire(blocking=False):
            raise StimulusFailed("another stimulus is being played: one at a time")
        sid = None
        try:
            with self.select_lock:  # the texture being played (if any) ends here
                stopped = self.selected
                self.end_play()
                self.selected = self.selected_sha = None
                sid = next(self.stimulus_ids)
                waiting = [threading.Event(), None]
                with self.lock:
                    self.stimulus_answers[sid] = waiting
                self.pump_writer.send(("stimulus", (sid, float(f), float(a), float(d))))
            if not waiting[0].wait(d + STIMULUS_SLACK_S) or waiting[1] is None:
                raise StimulusFailed(f"the pump did not report the stimulus played within "
                                     f"{d + STIMULUS_SLACK_S:g} s")
            _sid, error, retry, played = waiting[1]
            if error:
                if retry:
                    raise StimulusFailed(error)
                self.refuse(error)
            return {"played": played, "stopped": stopped}
        finally:
            with self.lock:
                self.stimulus_answers.pop(sid, None)
            self.stimulus_lock.release()

    def may_shut_down(self, peer_uid: int | None) -> None:
        """`hostd stop --daemon`: refused for anyone under systemd (a clean exit is not restarted:
        systemctl stop is the way), and outside it for anyone but the daemon's user and root (a
        member of the socket's group sends textures and reads the log; it does not stop hostd)."""
        from hostd.service.notify import service_unit

        unit = service_unit()
        if unit:
            log.warning("control socket: refused to shut down (uid %s): runs as %s", peer_uid, unit)
            self.refuse(f"hostd runs as the systemd service {unit}: use systemctl stop "
                        f"{unit.removesuffix('.service')} (hostd stop --daemon would leave it stopped "
                        "for good)")
        me = os.geteuid()
        if peer_uid not in (0, me):
            log.warning("control socket: refused to shut down for uid %s", peer_uid)
            self.refuse(f"only root or hostd's own user (uid {me}) may stop the daemon, not uid "
                        f"{peer_uid}; hostd stop (without --daemon) stops playing")

    def latest_quality(self) -> list[dict]:
        """The latest quality row per texture name, with what was delivered (for the metrics)."""
        con = qualitylog.connect_readonly(self.db_path)
        try:
            return list({r["name"]: r for r in qualitylog.query(con)}.values())
        finally:
            con.close()

    def serve_metrics(self) -> None:
        from hostd.service.metrics import parse_listen, start

        listen = parse_listen(self.cfg.metrics.listen, f"{self.cfg.path}: metrics.listen")
        if listen is not None:
            self.metrics = start(listen, self.status, self.latest_quality, self.cfg.quality.db)

    def serve_socket(self) -> None:
        c = self.cfg.control
        self.control = ControlServer(c.socket, c.group, c.max_clients, self.handle_conn,
                                     budget=MAX_HEADER + 1 + self.cfg.library.max_stream_bytes)
        self.control.start_pool()

    # ------------------------------------------------------------ supervision
    def start_worker(self, name: str, target: Callable[[], None]) -> None:
        def body() -> None:
            try:
                target()
            except Exception as e:
                log.error("worker %s failed: %s: %s", name, type(e).__name__, e)
            finally:
                self._wake()  # the main loop restarts it (supervise), not a timer

        t = threading.Thread(target=body, name=name, daemon=True)
        prev = self.workers.get(name)
        self.workers[name] = (target, t, prev[2] if prev else [])
        t.start()

    def supervise(self) -> bool:
        """Restart a worker thread that died (with a log line); False when one stays dead."""
        now = time.monotonic()
        for name, (target, t, restarts) in list(self.workers.items()):
            if t is None or t.is_alive() or self.stop_event.is_set() or name in self.dead_workers:
                continue
            restarts[:] = [r for r in restarts if now - r < 60.0]
            if len(restarts) >= RESTARTS_PER_MINUTE:
                self.dead_workers.add(name)
                log.error("worker %s stopped %d times within a minute: left stopped; the watchdog is no "
                          "longer fed, so systemd restarts hostd", name, len(restarts) + 1)
                continue
            restarts.append(now)
            log.error("worker %s stopped; restarted", name)
            self.start_worker(name, target)
        return not self.dead_workers

    def pump_messages(self) -> bool:
        """Log the pump's lines and take its info (transport, hotplug, reconnection time); False
        when the pump's end of the pipe is closed."""
        try:
            while self.conn.poll():
                kind, msg = self.conn.recv()
                if kind == "info":
                    self.pump_info = msg
                    continue
                if kind == "stimulus":  # (id, error or None, retry, what the device played)
                    with self.lock:
                        waiting = self.stimulus_answers.get(msg[0])
                    if waiting is not None:
                        waiting[1] = msg
                        waiting[0].set()
                    continue
                # the pump's lines carry their level: device loss and recoveries are
                # warnings (journald priority 4), the rest information
                log.log(logging.WARNING if kind == "warn" else logging.INFO, "%s", msg)
        except (EOFError, OSError):
            return False  # the pump is gone: the main loop says so
        return True

    # ------------------------------------------------------------ main
    def _wake(self) -> None:
        """Wake the main loop."""
        try:
            os.write(self.wake_w, b"w")
        except OSError:  # full: it is awake anyway
            pass

    def stop(self) -> None:
        """Every thread stops: the event, the descriptor the sleeping ones wait on, and the quality
        worker's queue."""
        self.stop_event.set()
        try:
            os.write(self.stop_w, b"s")
        except OSError:
            pass
        self.quality_q.put(None)

    def main_period_s(self, ready: bool) -> float:
        """How long the main loop may sleep when nothing wakes it: 0.5 s until READY=1, then a
        third of systemd's watchdog timeout (WatchdogSec=5: 1.7 s), or 5 s without a watchdog
        (STATUS= lines and the worker threads' supervision; a signal, a pump line, a pump's
        exit, a worker's end and the stop wake it at once)."""
        if not ready:
            return 0.5
        usec = self.notifier.watchdog_usec
        try:
            return max(0.5, min(5.0, int(usec) / 3e6)) if usec else 5.0
        except ValueError:
            return 0.5

    def on_signal(self, *_) -> None:
        """SIGTERM/SIGINT: only a flag. The handler runs in the main thread between two bytecodes,
        possibly while that thread holds stop_event's internal lock (inside Event.wait); calling
        stop_event.set() here would then wait for itself forever."""
        self.signalled = True

    def start_pump(self) -> None:
        """Start the pump process: it imports numpy anew, with one BLAS thread (hostd.service.lean)."""
        with children_with_one_blas_thread():
            self.proc.start()

    def send_to_pump(self, msg: tuple, timeout_s: float = 1.0) -> bool:
        """Send a command unless the pipe stays full for timeout_s (a pump that stopped reading)."""
        import select

        try:
            if select.select([], [self.conn.fileno()], [], timeout_s)[1]:
                self.conn.send(msg)
                return True
        except (OSError, ValueError):
            pass
        return False

    def stop_pump(self) -> None:
        """Bounded: ask the pump to quit (it ramps the output to zero), then SIGTERM, then SIGKILL;
        the process is reaped in every case, so interpreter exit has no child left to wait for
        (multiprocessing joins daemonic children without a timeout at exit)."""
        if self.pump_writer is not None:  # the pipe's one writer sends the last message
            self.pump_writer.close(("quit",), timeout_s=1.0)
        else:
            self.send_to_pump(("quit",))
        self.proc.join(3.0)
        if self.proc.is_alive():
            log.warning("the pump did not stop within 3 s; terminating it")
            self.proc.terminate()
            self.proc.join(2.0)
        if self.proc.is_alive():
            log.error("the pump ignored SIGTERM; killing it (the firmware ramps to zero on host timeout)")
            self.proc.kill()
            self.proc.join(2.0)

    def run(self) -> int:
        # first: a stop request during the start is a clean stop (the flag is read by the main loop)
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, self.on_signal)
        self.serve_metrics()  # a wrong or busy metrics.listen stops the start, before the pump runs
        self.start_pump()
        self.pump_writer = PumpWriter(self.conn)
        # our copy of the pump's end: closed, so a dead pump reads as EOF (a pending recv() or a
        # send into a full pipe would otherwise wait forever for a peer that no longer exists)
        self.child_conn.close()
        self.serve_socket()
        log.info("listening on %s", self.cfg.control.socket)
        self.start_worker("control", self.control.accept_loop)
        self.start_worker("quality", self.quality_worker)
        self.start_worker("spool", self.spool_watcher)
        from multiprocessing.connection import wait

        signal.set_wakeup_fd(self.wake_w, warn_on_full_buffer=False)  # a signal wakes the loop
        ready = False
        last_cycles = -1.0
        try:
            while not (self.signalled or self.stop_event.is_set()):
                # asleep until the pump writes a line (or exits), a signal, a worker's end or the
                # stop; else main_period_s (watchdog, STATUS=): docs/daemon.md, bench soak
                try:
                    woken = wait([self.conn, self.wake_r, self.stop_r], self.main_period_s(ready))
                except (EOFError, OSError):
                    woken = []
                    self.stop_event.wait(0.2)  # the pump is gone (said just below): no busy loop
                if self.wake_r in woken:
                    _drain(self.wake_r)
                if self.signalled or self.stop_event.is_set():
                    break
                if not self.pump_messages():
                    self.proc.join(0.2)  # the pump's end of the pipe closed: it is exiting
                if not self.proc.is_alive():
                    log.error("the real-time pump exited (code %s); stopping", self.proc.exitcode)
                    return 1
                healthy = self.supervise()
                st = self.counters()
                state = st["state"]
                if not ready and state in ("waiting", "idle", "playing"):
                    self.notifier.ready()
                    ready = True
                    log.info("ready")
                    # the library's streams without a row are looked for after READY=1, in the
                    # background (5,644 stored streams took 18 s to read before READY=1)
                    threading.Thread(target=self.rescore_missing, name="rescore", daemon=True).start()
                # the watchdog is fed only when the real-time loop made progress (cycles, or
                # reconnection attempts or wake-ups while it waits for a device) and every worker thread is
                # alive, never by a timer alone
                progress = st["cycles"] + st["reconnects"] + st["wait_ticks"]
                # (the pump loading the host renderer, a fallback from device mode: seconds on a
                # slow CPU with no cycle to show, bounded by its own deadline: busy_until_s)
                loading = st.get("busy_until_s", 0.0) > time.monotonic()
                if (progress != last_cycles or not ready or loading) and healthy:
                    # before READY=1 the pump is still starting (its imports, the display's
                    # equalizer designed in a child: a minute and more on a slow or emulated CPU)
                    # and has no progress to show; this loop running and the pump alive is the
                    # liveness then, and TimeoutStartSec= bounds the start itself
                    self.notifier.notify("WATCHDOG=1")
                last_cycles = progress
                self.notifier.notify(f"STATUS={state} {self.selected or '-'} device={st['device_state']} "
                                     f"played={st['played_fraction']:.2%} underruns={st['device_underruns']} "
                                     f"stalls={st['stalls']} recoveries={st['recoveries']}")
        finally:
            self.notifier.notify("STOPPING=1")
            if self.proc.is_alive():
                self.end_play()
            self.stop_pump()
            self.pump_messages()  # its last lines (a recovery just before the stop) reach the log
            self.stop()
            if self.metrics is not None:
                self.metrics.shutdown()
            if self.control is not None:
                self.control.close()
                Path(self.cfg.control.socket).unlink(missing_ok=True)
            quality = self.workers.get("quality")
            if quality is not None and quality[1] is not None:
                # rows for everything accepted are written before exit; a disk that stays full
                # is retried for 5 s (TimeoutStopSec=10), the rest is scored at the next start
                self._stop_deadline = time.monotonic() + 5.0
                quality[1].join(8.0)
            signal.set_wakeup_fd(-1)
            log.info("stopped")
        return 0
