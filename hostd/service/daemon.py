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
import threading
import time
from collections.abc import Callable
from pathlib import Path

from hostd.errors import ConfigError, HostdError
from hostd.service import qualitylog
from hostd.service.config import Config, check_paths
from hostd.service.control import REQUEST_DEADLINE_S, BadRequest, ClientConn, ControlServer
from hostd.service.lean import children_with_one_blas_thread
from hostd.service.library import Library, check_name
from hostd.service.logsetup import CONTROL_CHARS
from hostd.service.notify import Notifier
from hostd.service.pumplink import PumpWriter, bound_play, read_counters
from hostd.service.pumpproc import pump_main
from hostd.service.pumpstate import STAT_FIELDS
from hostd.service.qualityworker import QUALITY_QUEUE_MAX, QualityWorker  # noqa: F401 (tests import it here)
from hostd.service.spool import SpoolWatcher, _drain
from hostd.service.stimuli import Stimuli, StimulusFailed  # noqa: F401 (StimulusFailed: named here before)
from hostd.service.supervisor import RESTARTS_PER_MINUTE, Supervisor  # noqa: F401 (tests import it here)

log = logging.getLogger("hostd")
MAX_HEADER = 4096


class Daemon:
    """The service: intake (accept, select, stop) and the control socket's requests here; the
    quality worker (QualityWorker), the spool (SpoolWatcher), the stimuli (Stimuli), the pump's
    pipe (PumpWriter) and the worker threads' supervision (Supervisor) are the parts it holds."""

    def __init__(self, cfg: Config, notifier: Notifier | None = None) -> None:
        self.cfg = cfg
        check_paths(cfg)
        self.spool = Path(cfg.library.spool)
        self.db_path = cfg.quality.db
        try:
            self.library = Library(cfg.library.dir, cfg.library.max_stream_bytes, cfg.library.max_n,
                                   cfg.library.max_n_keep, travel_um=cfg.output.travel_um)
            self.spool.parent.mkdir(parents=True, exist_ok=True)
            self.spool_watch = SpoolWatcher(cfg, self.spool, self.accept)
            qualitylog.connect(self.db_path).close()
        except (OSError, sqlite3.Error, HostdError) as e:
            raise ConfigError(f"{cfg.path}: cannot set up the library, spool or quality log: {e}") from None
        self.lock = threading.Lock()
        self.stop_event = threading.Event()
        self.quality = QualityWorker(cfg, self.db_path, self.library, self.lock, self.stop_event)
        ctx = mp.get_context("spawn")
        self.select_lock = threading.Lock()  # one select or stop at a time
        self.selected_sha: str | None = None
        self.stats = ctx.Array("d", len(STAT_FIELDS), lock=False)
        self.conn, self.child_conn = ctx.Pipe()
        self.proc = ctx.Process(target=pump_main, args=(cfg, self.child_conn, self.stats),
                                name="hostd-pump", daemon=True)
        self.pump_writer: PumpWriter | None = None
        self.signalled = False  # set by the SIGTERM/SIGINT handler, which must take no lock
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
        self.notifier = notifier if notifier is not None else Notifier()
        self.control: ControlServer | None = None
        self.metrics = None  # the Prometheus endpoint's server, when metrics.listen is set
        self.supervisor = Supervisor(self.stop_event, self._wake)
        self.stimuli = Stimuli(cfg, self.lock, self.refuse, self.take_over)

    # ------------------------------------------------------------ the parts' state, as before
    @property
    def quality_q(self) -> queue.Queue:
        return self.quality.quality_q

    @property
    def quality_pending(self):
        return self.quality.quality_pending

    @property
    def plays_pending(self):
        return self.quality.plays_pending

    @property
    def _stop_deadline(self) -> float:
        return self.quality._stop_deadline

    @_stop_deadline.setter
    def _stop_deadline(self, t: float) -> None:
        self.quality._stop_deadline = t

    @property
    def workers(self) -> dict:
        return self.supervisor.workers

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
        self.quality.queue_for_scoring(name, data, sha, time.time())
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
        self.quality.record_play(name, row)

    def take_over(self, msg: tuple) -> str | None:
        """The texture being played (if any) ends and msg (a stimulus) goes to the pump in its
        place, under the select lock; the name of the texture stopped."""
        with self.select_lock:
            stopped = self.selected
            self.end_play()
            self.selected = self.selected_sha = None
            self.pump_writer.send(msg)
        return stopped

    def counters(self) -> dict:
        """The pump's counters (pumplink.read_counters)."""
        return read_counters(self.stats)

    def status(self) -> dict:
        st = self.counters()
        st.update({"texture": self.selected, "pid": os.getpid(), "pump_alive": self.proc.is_alive(),
                   "accepted": self.accepted, "refused": self.refused, "library": len(self.library.names()),
                   "selects_sent": self.selects_sent,
                   "quality_pending": self.quality_q.qsize() + len(self.quality_pending),
                   "plays_pending": len(self.plays_pending),
                   "device": self.cfg.device.transport})
        st.update(self.pump_info)
        return st

    # ------------------------------------------------------------ workers
    def quality_worker(self) -> None:
        self.quality.quality_worker()

    def rescore_missing(self) -> None:
        self.quality.rescore_missing(lambda: self.stop_event.is_set() or self.signalled)

    def spool_watcher(self) -> None:
        self.spool_watch.spool_watcher(self.stop_event, self.stop_r)

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
    def reach(self, req: dict) -> dict:
        return self.stimuli.reach(req)

    def play_stimulus(self, req: dict) -> dict:
        return self.stimuli.play_stimulus(req)

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
        self.supervisor.start_worker(name, target)

    def supervise(self) -> bool:
        """Restart a worker thread that died (with a log line); False when one stays dead."""
        return self.supervisor.supervise()

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
                    self.stimuli.answered(msg)
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
        try:  # (full: the worker is not asleep on it, and sees the stop after its next entry)
            self.quality_q.put_nowait(None)
        except queue.Full:
            pass

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
