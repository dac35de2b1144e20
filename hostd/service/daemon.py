"""`hostd run`: the background service.

Threads of the main process: the control socket (a pool of handlers), the spool watcher,
the quality worker (scoring and SQLite, with its pending queue), the pump writer (the one
writer of the pump's pipe), and the main loop (systemd notify and watchdog, pump log lines,
signals). The real-time pump is a separate process (pumpproc).
"""

from __future__ import annotations

import hashlib
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

from hostd.device.health import STATE_NAMES as DEVICE_STATES
from hostd.device.health import fault_names
from hostd.device.protocol import SAMPLE_RATE_HZ
from hostd.errors import ConfigError, HostdError
from hostd.fileio import open_dir, read_regular_at, write_at
from hostd.service import qualitylog
from hostd.service.config import Config, check_paths
from hostd.service.control import REQUEST_DEADLINE_S, ClientConn, ControlServer
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


class BadRequest(HostdError):
    """A control-socket request that is not well formed."""


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
        if cfg.quality.thresholds:
            from hostd.perception.thresholds import load_csv

            self.curve = load_csv(cfg.quality.thresholds)
        ctx = mp.get_context("spawn")
        self.select_lock = threading.Lock()  # one select or stop at a time
        self.selected_sha: str | None = None
        self.quality_pending: deque = deque()  # scored rows not yet written (disk full, I/O error)
        self.stats = ctx.Array("d", len(STAT_FIELDS), lock=False)
        self.conn, self.child_conn = ctx.Pipe()
        self.proc = ctx.Process(target=pump_main, args=(cfg, self.child_conn, self.stats),
                                name="hostd-pump", daemon=True)
        self.pump_writer: PumpWriter | None = None
        self._stop_deadline = math.inf  # the quality worker's last retry at shutdown
        self.signalled = False  # set by the SIGTERM/SIGINT handler, which must take no lock
        self.quality_q: queue.Queue = queue.Queue()
        self.stop_event = threading.Event()
        self.selected: str | None = None
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
        self.quality_q.put((name, data, sha, time.time()))
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
        device_s = max(c1["device_time_s"] - c0["device_time_s"], 0.0)
        fraction = c1["played_fraction"] if device_s > 0 else None
        if c1["render_at"] == "device":  # the display renders: nothing is played from its buffer,
            played_s = (fraction or 0.0) * device_s  # the share of device time it reported rendering
        else:
            played_s = max(c1["device_samples_played"] - c0["device_samples_played"], 0) / SAMPLE_RATE_HZ
        row = {"name": name, "sha256": sha, "started_at": started, "ended_at": time.time(),
               "device_s": device_s, "played_s": played_s, "played_fraction": fraction,
               "underruns": max(c1["device_underruns"] - c0["device_underruns"], 0)}
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
        return st

    def status(self) -> dict:
        st = self.counters()
        st.update({"texture": self.selected, "pid": os.getpid(), "pump_alive": self.proc.is_alive(),
                   "accepted": self.accepted, "refused": self.refused, "library": len(self.library.names()),
                   "quality_pending": self.quality_q.qsize() + len(self.quality_pending),
                   "device": self.cfg.device.transport})
        st.update(self.pump_info)
        return st

    # ------------------------------------------------------------ workers
    def quality_worker(self) -> None:
        """Score each accepted stream and write its row. A row that cannot be written (disk full,
        I/O error, a locked or unopenable database) stays in quality_pending and is retried,
        back-off doubling from 0.5 s to 30 s, until it is written; one log line when writing
        fails and one when it works again. What is still pending at exit is scored again at
        the next start (a stored stream without a row)."""
        con = None
        failing_since = None
        retry_at = 0.0
        backoff = QUALITY_RETRY_S[0]
        while True:
            stopping = self.stop_event.is_set()
            try:
                # idle: one wake-up a second; a pending row is retried sooner
                item = self.quality_q.get(timeout=0.05 if self.quality_pending else 1.0)
            except queue.Empty:
                item = None
            if item is not None:
                name, data, sha, t = item
                try:
                    q = self.cfg.quality
                    row = qualitylog.score_row(data, name, sha, t, q.a, q.b, self.curve)
                    self.quality_pending.append(row)
                except Exception as e:  # a scoring failure must not stop the service
                    log.error("quality scoring of %s failed: %s", name, e)
                continue
            if not self.quality_pending:
                if stopping:
                    break
                continue
            if time.monotonic() < retry_at:
                if stopping and time.monotonic() > self._stop_deadline:
                    break
                continue
            try:
                if con is None:
                    con = qualitylog.connect(self.db_path)
                while self.quality_pending:
                    row = self.quality_pending[0]
                    qualitylog.insert(con, row)
                    self.quality_pending.popleft()
                    log.info("quality %s: Ip=%.4f Ia=%.4f Iobj=%.4f", row["name"], row["ip"], row["ia"],
                             row["iobj"])
                if failing_since is not None:
                    log.warning("quality log: writing again after %.0f s; every pending row is written",
                                time.monotonic() - failing_since)
                failing_since, backoff = None, QUALITY_RETRY_S[0]
            except (sqlite3.Error, OSError) as e:
                if failing_since is None:
                    failing_since = time.monotonic()
                    log.error("quality log: cannot write to %s (%s); %d rows kept pending and retried until "
                              "written (free disk space)", self.db_path, e, len(self.quality_pending))
                if con is not None:
                    con.close()
                    con = None
                retry_at = time.monotonic() + backoff
                backoff = min(backoff * 2, QUALITY_RETRY_S[1])
                if stopping and time.monotonic() > self._stop_deadline:
                    break
        if self.quality_pending:
            log.error("quality log: %d rows not written at exit; their streams are scored again at the "
                      "next start", len(self.quality_pending))
        if con is not None:
            con.close()

    def rescore_missing(self) -> None:
        """Streams stored before a crash but not yet logged are scored now."""
        con = qualitylog.connect(self.db_path)
        known = qualitylog.known(con)
        con.close()
        for name in self.library.names():
            try:
                data = self.library.read(name)
                sha = hashlib.sha256(data).hexdigest()
                if (name, sha) in known:
                    continue
                self.library.decode(data)  # within today's limits, or it would fail every start
                self.quality_q.put((name, data, sha, self.library.mtime(name)))
            except (HostdError, OSError) as e:
                log.warning("library: %s not scored: %s", name, e)

    def spool_watcher(self) -> None:
        """Take in .vtx files dropped into the spool once their writer is done: size and mtime
        unchanged for library.spool_settle_s and the mtime at least that old. Anything else
        named *.vtx (symlink, FIFO, device, directory, too big) is moved to rejected/ with a note.
        Every operation is relative to the spool's and rejected/'s descriptors (opened and
        checked at start-up) and follows no link: a member who renames rejected/ or plants
        links changes nothing the daemon writes or reads."""
        settle = self.cfg.library.spool_settle_s
        limit = self.cfg.library.max_stream_bytes
        seen: dict[str, tuple[tuple[int, int], float]] = {}  # name -> (size, mtime_ns), since
        while not self.stop_event.wait(min(0.3, settle / 2)):
            try:
                with os.scandir(self.spool_fd) as it:
                    entries = list(it)
            except OSError as e:
                log.error("spool: cannot list %s: %s", self.spool, e.strerror)
                continue
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
            con = qualitylog.connect(self.db_path)
            try:
                return {"rows": qualitylog.query(con, since)}
            finally:
                con.close()
        if cmd == "shutdown":
            self.stop_event.set()
            return {"shutting_down": True}
        raise BadRequest(f"unknown command {cmd!r:.40}")

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
            self.metrics = start(listen, self.status, self.latest_quality)

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

    def pump_messages(self) -> None:
        """Log the pump's lines and take its info (transport, hotplug, reconnection time)."""
        try:
            while self.conn.poll():
                kind, msg = self.conn.recv()
                if kind == "info":
                    self.pump_info = msg
                    continue
                # the pump's lines carry their level: device loss and recoveries are
                # warnings (journald priority 4), the rest information
                log.log(logging.WARNING if kind == "warn" else logging.INFO, "%s", msg)
        except (EOFError, OSError):
            pass  # the pump is gone: the main loop says so

    # ------------------------------------------------------------ main
    def on_signal(self, *_) -> None:
        """SIGTERM/SIGINT: only a flag. The handler runs in the main thread between two bytecodes,
        possibly while that thread holds stop_event's internal lock (inside Event.wait); calling
        stop_event.set() here would then wait for itself forever."""
        self.signalled = True

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
        self.serve_metrics()  # a wrong or busy metrics.listen stops the start, before the pump runs
        self.proc.start()
        self.pump_writer = PumpWriter(self.conn)
        # our copy of the pump's end: closed, so a dead pump reads as EOF (a pending recv() or a
        # send into a full pipe would otherwise wait forever for a peer that no longer exists)
        self.child_conn.close()
        self.serve_socket()
        log.info("listening on %s", self.cfg.control.socket)
        self.start_worker("control", self.control.accept_loop)
        self.start_worker("quality", self.quality_worker)
        self.start_worker("spool", self.spool_watcher)
        self.rescore_missing()
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, self.on_signal)
        ready = False
        last_cycles = -1.0
        try:
            while not (self.signalled or self.stop_event.is_set()):
                # asleep until the pump writes a line, or 0.5 s (watchdog, STATUS=): a daemon
                # playing a texture wakes a few times a second (docs/daemon.md, bench soak)
                try:
                    self.conn.poll(0.5)
                except (EOFError, OSError):
                    self.stop_event.wait(0.2)  # the pump is gone (said just below): no busy loop
                if self.signalled or self.stop_event.is_set():
                    break
                self.pump_messages()
                if not self.proc.is_alive():
                    log.error("the real-time pump exited (code %s); stopping", self.proc.exitcode)
                    return 1
                healthy = self.supervise()
                st = self.counters()
                state = st["state"]
                if not ready and state in ("waiting", "idle", "playing"):
                    self.notifier.ready()
                    ready = True
                # the watchdog is fed only when the real-time loop made progress (cycles, or
                # reconnection attempts or wake-ups while it waits for a device) and every worker thread is
                # alive, never by a timer alone
                progress = st["cycles"] + st["reconnects"] + st["wait_ticks"]
                if progress != last_cycles and healthy:
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
            self.stop_event.set()
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
            log.info("stopped")
        return 0
