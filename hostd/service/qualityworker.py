"""The quality worker: each accepted stream scored and its row written to the quality log, with the
plays, in batches; what cannot be written is kept pending, retried, and saved for the next start."""

from __future__ import annotations

import hashlib
import itertools
import logging
import math
import os
import queue
import sqlite3
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path

from hostd.errors import HostdError
from hostd.perception.indices import DEFAULT_AB
from hostd.service import qualitylog

log = logging.getLogger("hostd")
QUALITY_RETRY_S = (0.5, 30.0)  # a quality row that cannot be written is retried, back-off doubling
# streams waiting to be scored: a producer waits for room (an upload's handler, the start-up's look
# for streams without a row), so what waits is bounded whatever the backlog; the start-up's entries
# are names (read when scored), an upload's its bytes (in memory already; at most this many kept)
QUALITY_QUEUE_MAX = 16


class QualityWorker:
    """The quality log's writer and what waits for it: the queue of streams to score (quality_q),
    the rows and plays not yet written (quality_pending, plays_pending) and the pending-rows files
    of the last run. `lock` guards `scoring` (the daemon's lock); `stop_event` is the daemon's stop."""

    def __init__(self, cfg, db_path, library, lock: threading.Lock, stop_event: threading.Event) -> None:
        self.cfg = cfg
        self.db_path = db_path
        self.library = library
        self.lock = lock
        self.stop_event = stop_event
        self.curve = None
        self.calibration = None  # NAME@ID recorded with each quality row (quality.calibration)
        if cfg.quality.calibration:
            from hostd.perception import calibration

            cal = calibration.load(cfg.quality.calibration)
            self.curve, self.calibration = cal.curve, cal.label
        elif cfg.quality.thresholds:
            from hostd.perception.calibration import load_curve

            self.curve = load_curve(cfg.quality.thresholds)
        self.quality_pending: deque = deque()  # scored rows not yet written (disk full, I/O error)
        self.plays_pending: deque = deque()  # plays not yet written (the same), kept as the rows are
        # rows the last run could not write: written first (then the pending-rows file is removed)
        self.pending_paths = qualitylog.pending_paths(self.db_path, cfg.library.dir)
        kept = []
        for p in self.pending_paths:
            try:
                kept += [r for r in qualitylog.load_pending(p) if r not in kept]
            except OSError as e:
                log.warning("quality log: cannot read the pending-rows file %s (%s); its streams are scored "
                            "again", p, e.strerror or e)
        for r in kept:
            (self.plays_pending if qualitylog.is_play(r) else self.quality_pending).append(r)
        self.pending_file_rows = len(kept)
        self.pending_keys = {(r["name"], r["sha256"]) for r in self.quality_pending}
        self.scoring: set[tuple[str, str]] = set(self.pending_keys)  # queued or pending, not yet written
        if kept:
            log.info("quality log: %d rows pending from the last run (%s); writing them first", len(kept),
                     ", ".join(str(p) for p in self.pending_paths if p.exists()))
        self._stop_deadline = math.inf  # the quality worker's last retry at shutdown
        self.quality_q: queue.Queue = queue.Queue(QUALITY_QUEUE_MAX)

    def record_play(self, name: str, row: dict) -> None:
        """Write the row of a play that ended (bound_play's, named); kept pending when it cannot be
        written now, or when plays wait already (the worker writes it with them)."""
        if not self.plays_pending:  # (else after those: the quality worker writes it with them)
            try:
                con = qualitylog.connect(self.db_path)
                try:
                    qualitylog.insert_play(con, row)
                finally:
                    con.close()
                self._played(row)
                return
            except (sqlite3.Error, OSError) as e:  # the log must not stop playback: kept pending
                log.error("quality log: cannot record the play of %s now (%s); kept pending and written with "
                          "the pending quality rows", name, e)
        self.plays_pending.append(row | {"kind": "play"})
        try:  # the quality worker retries it (woken, if it sleeps: an empty entry)
            self.quality_q.put_nowait(())
        except queue.Full:
            pass

    @staticmethod
    def _played(row: dict) -> None:
        log.info("played %s: %.1f s from the buffer, played fraction %s, %d underruns", row["name"],
                 row["played_s"], "-" if row["played_fraction"] is None else f"{row['played_fraction']:.2%}",
                 row["underruns"])

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
                if self.stop_event.is_set():  # (stop() may have found the queue full: no None)
                    item = self.quality_q.get_nowait()
                else:
                    item = self.quality_q.get(timeout=0.05 if self._pending() else None)
            except queue.Empty:
                item = None
            stopping = self.stop_event.is_set()
            if item:  # (an empty entry: a play is pending)
                self._score(*item)
                if len(self.quality_pending) < qualitylog.BATCH_ROWS:
                    continue  # (a batch's worth is written at once: a backlog does not wait in memory)
            if not self._pending():
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
                for pending in (self.quality_pending, self.plays_pending):
                    while pending:
                        batch = list(itertools.islice(pending, qualitylog.BATCH_ROWS))
                        qualitylog.insert_batch(con, batch)
                        for row in batch:
                            pending.popleft()
                            if qualitylog.is_play(row):
                                self._played(row)
                                continue
                            self.scoring.discard((row["name"], row["sha256"]))
                            log.info("quality %s: Ip=%.4f Ia=%.4f Iobj=%.4f", row["name"], row["ip"],
                                     row["ia"], row["iobj"])
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
                              "written (%s)", self.db_path, e,
                              len(self.quality_pending) + len(self.plays_pending),
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
        if self._pending():
            self.keep_pending_rows()

    def _pending(self) -> bool:
        """Rows or plays not yet written."""
        return bool(self.quality_pending or self.plays_pending)

    def _score(self, name: str, sha: str, received_at: float, data: bytes | None) -> None:
        """Score one queued stream into quality_pending; data None: read from the library now (a
        stream found without a row at start-up, queued by its name)."""
        try:
            if data is None:
                data = self.library.read(name)
                if hashlib.sha256(data).hexdigest() != sha:  # replaced since: its new content is queued
                    self.scoring.discard((name, sha))
                    log.info("quality: %s was replaced before it was scored; its new content is scored", name)
                    return
            q = self.cfg.quality
            # a stream made with another curve than the configured one: its own curve, and the
            # paper's weights under a calibration (its weights go with its curve), else quality.a, b
            own_ab = DEFAULT_AB if self.calibration else (q.a, q.b)
            row = qualitylog.score_row(data, name, sha, received_at, q.a, q.b, self.curve, self.calibration,
                                       own_ab)
            note = row.pop("scoring_note", None)
            if note:
                log.warning("quality %s: %s", name, note)
            self.quality_pending.append(row)
        except Exception as e:  # a scoring failure (or a stream removed meanwhile) must not stop the service
            self.scoring.discard((name, sha))
            log.error("quality scoring of %s failed: %s", name, e)

    def queue_for_scoring(self, name: str, data: bytes | None, sha: str, received_at: float) -> bool:
        """Once per (name, content) until its row is written: an upload during the start-up's
        look for unscored streams is not scored twice. data None: the stored stream, read when
        scored. Waits for room in the bounded queue (the worker takes an entry per score); False
        when the daemon stops meanwhile (the stream, stored, is scored at the next start)."""
        with self.lock:
            if (name, sha) in self.scoring:
                return False
            self.scoring.add((name, sha))
        while True:
            try:  # (a timer only while the queue is full)
                self.quality_q.put((name, sha, received_at, data), timeout=0.25)
                return True
            except queue.Full:
                if self.stop_event.is_set():
                    self.scoring.discard((name, sha))
                    return False

    def keep_pending_rows(self) -> None:
        """At exit: rows not written go to the pending-rows file for the next start."""
        rows = list(self.quality_pending) + list(self.plays_pending)
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

    def rescore_missing(self, stopped: Callable[[], bool]) -> None:
        """Streams stored before a crash but not yet logged are scored (after READY=1, in its own
        thread: a large library takes seconds to read; a stop request ends it: stopped())."""
        t0 = time.monotonic()
        con = qualitylog.connect(self.db_path)
        try:
            known = qualitylog.known(con)
        finally:
            con.close()
        queued = 0
        for name in self.library.names():
            if stopped():
                return
            try:
                data = self.library.read(name)
                sha = hashlib.sha256(data).hexdigest()
                if (name, sha) in known:
                    continue
                self.library.decode(data)  # within today's limits, or it would fail every start
                del data  # queued by its name (read again when scored): a backlog is not held in memory
                if self.queue_for_scoring(name, None, sha, self.library.mtime(name)):
                    queued += 1
            except (HostdError, OSError) as e:
                log.warning("library: %s not scored: %s", name, e)
        if queued:
            log.info("library: %d stored streams without a quality row queued for scoring (%.1f s)", queued,
                     time.monotonic() - t0)
