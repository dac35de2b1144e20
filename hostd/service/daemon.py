"""`hostd run`: the background service.

Threads of the main process: the control socket (one thread per client), the spool watcher,
the quality worker (scoring and SQLite), and the main loop (systemd notify and watchdog,
pump log lines, signals). The real-time pump is a separate process (pumpproc).
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
import socket
import sqlite3
import stat
import threading
import time
from collections.abc import Callable
from pathlib import Path

from hostd.device.health import STATE_NAMES as DEVICE_STATES
from hostd.device.health import fault_names
from hostd.device.protocol import SAMPLE_RATE_HZ
from hostd.errors import ConfigError, HostdError
from hostd.fileio import write_output
from hostd.service import qualitylog
from hostd.service.config import Config, check_paths
from hostd.service.control import ControlServer
from hostd.service.library import Library, check_name
from hostd.service.pumpproc import FLOAT_FIELDS, STAT_FIELDS, STATE_NAMES, pump_main

log = logging.getLogger("hostd")
MAX_HEADER = 4096
RESTARTS_PER_MINUTE = 3  # a worker that dies more often stays dead and the watchdog starves


class BadRequest(HostdError):
    """A control-socket request that is not well formed."""


def _read_spool_file(path: Path, max_bytes: int, expect: tuple[int, int]) -> bytes:
    """A spool file's bytes: a regular file only (no symlink, FIFO, device, directory), at most
    max_bytes, and unchanged since it was seen to hold still (size, mtime_ns)."""
    try:  # O_NONBLOCK: a FIFO must not block the spool thread waiting for a writer
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_NOCTTY)
    except OSError as e:
        if e.errno == 40:  # ELOOP: a symbolic link
            raise HostdError("a symbolic link: the spool takes regular files only") from None
        raise
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise HostdError("not a regular file: the spool takes regular files only")
        if st.st_size > max_bytes:
            raise HostdError(f"stream of {st.st_size} bytes exceeds the limit of {max_bytes} "
                             "(library.max_stream_bytes)")
        if (st.st_size, st.st_mtime_ns) != expect:
            raise BlockingIOError("still being written")
        chunks, left = [], max_bytes + 1
        while left > 0:
            b = os.read(fd, min(left, 1 << 16))
            if not b:
                break
            chunks.append(b)
            left -= len(b)
        data = b"".join(chunks)
        if len(data) > max_bytes:
            raise HostdError(f"stream exceeds the limit of {max_bytes} bytes (library.max_stream_bytes)")
        return data
    finally:
        os.close(fd)


class Notifier:
    """systemd sd_notify, a no-op outside systemd (no NOTIFY_SOCKET)."""

    def __init__(self) -> None:
        self.n = None
        if os.environ.get("NOTIFY_SOCKET"):
            try:
                import sdnotify

                self.n = sdnotify.SystemdNotifier()
                if self.n.socket is not None:  # never block the main loop on a full notify queue
                    self.n.socket.setblocking(False)
            except ImportError:
                log.warning("sdnotify is not installed: systemd readiness and watchdog disabled")

    def notify(self, msg: str) -> None:
        if self.n is not None:
            self.n.notify(msg)


class Daemon:
    def __init__(self, cfg: Config) -> None:
        self.cfg = cfg
        check_paths(cfg)
        self.spool = Path(cfg.library.spool)
        self.db_path = cfg.quality.db
        try:
            self.library = Library(cfg.library.dir, cfg.library.max_stream_bytes, cfg.library.max_n,
                                   cfg.library.max_n_keep)
            self.spool.mkdir(parents=True, exist_ok=True)
            (self.spool / "rejected").mkdir(exist_ok=True)
            qualitylog.connect(self.db_path).close()
        except (OSError, sqlite3.Error) as e:
            raise ConfigError(f"{cfg.path}: cannot set up the library, spool or quality log: {e}") from None
        self.curve = None
        if cfg.quality.thresholds:
            from hostd.perception.thresholds import load_csv

            self.curve = load_csv(cfg.quality.thresholds)
        ctx = mp.get_context("spawn")
        self.stats = ctx.Array("d", len(STAT_FIELDS), lock=False)
        self.conn, child = ctx.Pipe()
        self.proc = ctx.Process(target=pump_main, args=(cfg, child, self.stats), name="hostd-pump",
                                daemon=True)
        self.quality_q: queue.Queue = queue.Queue()
        self.stop_event = threading.Event()
        self.selected: str | None = None
        self.accepted = 0
        self.refused = 0
        # from the pump, on change: transport in use, hotplug mode, last reconnection time
        self.pump_info: dict = {"transport": None, "hotplug": None, "last_reconnect_s": None}
        self.lock = threading.Lock()
        self.notifier = Notifier()
        self.control: ControlServer | None = None
        self.workers: dict[str, tuple[Callable[[], None], threading.Thread | None, list[float]]] = {}
        self.dead_workers: set[str] = set()

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
        from hostd.codec import stream as vtx

        s = vtx.decode(self.library.read(name))
        self.conn.send(("select", (name, s.coefficients.tolist(), s.n, s.length_mm)))
        self.selected = name
        log.info("playing %s", name)
        return {"playing": name}

    def stop_playing(self) -> dict:
        self.conn.send(("stop",))
        self.selected = None
        return {"playing": None}

    def counters(self) -> dict:
        """The pump's counters, from shared memory."""
        st = dict(zip(STAT_FIELDS, self.stats[:], strict=True))
        for k in STAT_FIELDS:
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
        st["target_fill_ms"] = round(st["target_fill"] / SAMPLE_RATE_HZ * 1e3, 2)
        return st

    def status(self) -> dict:
        st = self.counters()
        st.update({"texture": self.selected, "pid": os.getpid(), "pump_alive": self.proc.is_alive(),
                   "accepted": self.accepted, "refused": self.refused, "library": len(self.library.names()),
                   "quality_pending": self.quality_q.qsize(), "device": self.cfg.device.transport})
        st.update(self.pump_info)
        return st

    # ------------------------------------------------------------ workers
    def quality_worker(self) -> None:
        con = qualitylog.connect(self.db_path)
        while not self.stop_event.is_set() or not self.quality_q.empty():
            try:
                name, data, sha, t = self.quality_q.get(timeout=0.2)
            except queue.Empty:
                continue
            try:
                q = self.cfg.quality
                row = qualitylog.score_row(data, name, sha, t, q.a, q.b, self.curve)
                qualitylog.insert(con, row)
                log.info("quality %s: Ip=%.4f Ia=%.4f Iobj=%.4f", name, row["ip"], row["ia"], row["iobj"])
            except Exception as e:  # a scoring failure must not stop the service
                log.error("quality logging of %s failed: %s", name, e)
        con.close()

    def rescore_missing(self) -> None:
        """Streams stored before a crash but not yet logged are scored now."""
        con = qualitylog.connect(self.db_path)
        known = qualitylog.known(con)
        con.close()
        for name in self.library.names():
            data = self.library.read(name)
            sha = hashlib.sha256(data).hexdigest()
            if (name, sha) not in known:
                self.quality_q.put((name, data, sha, self.library.path(name).stat().st_mtime))

    def spool_watcher(self) -> None:
        """Take in .vtx files dropped into the spool once their writer is done: size and mtime
        unchanged for library.spool_settle_s and the mtime at least that old. Anything else
        named *.vtx (symlink, FIFO, device, directory, too big) is moved to rejected/ with a note."""
        settle = self.cfg.library.spool_settle_s
        seen: dict[str, tuple[tuple[int, int], float]] = {}  # name -> (size, mtime_ns), since
        while not self.stop_event.wait(min(0.3, settle / 2)):
            try:
                entries = list(os.scandir(self.spool))
            except OSError as e:
                log.error("spool: cannot list %s: %s", self.spool, e.strerror)
                continue
            now = time.time()
            for ent in entries:
                if not ent.name.endswith(".vtx") or ent.name.startswith("."):
                    continue
                p = Path(ent.path)
                try:
                    st = ent.stat(follow_symlinks=False)
                except FileNotFoundError:
                    continue
                if not stat.S_ISREG(st.st_mode):
                    self._reject_spool(p, "not a regular file (symlink, FIFO, device or directory): the "
                                          "spool takes regular files only")
                    continue
                if st.st_size > self.cfg.library.max_stream_bytes:
                    self._reject_spool(p, f"stream of {st.st_size} bytes exceeds the limit of "
                                          f"{self.cfg.library.max_stream_bytes} (library.max_stream_bytes)")
                    continue
                sig = (st.st_size, st.st_mtime_ns)
                prev = seen.get(ent.name)
                if prev is None or prev[0] != sig:
                    seen[ent.name] = (sig, now)  # (still) being written: wait until it holds still
                    continue
                if now - prev[1] < settle or now - st.st_mtime_ns / 1e9 < settle:
                    continue
                try:
                    data = _read_spool_file(p, self.cfg.library.max_stream_bytes, sig)
                except BlockingIOError:
                    seen.pop(ent.name, None)
                    continue
                except HostdError as e:
                    seen.pop(ent.name, None)
                    self._reject_spool(p, str(e))
                    continue
                except OSError as e:
                    log.error("spool: cannot take in %s: %s", p, e.strerror or e)
                    continue
                seen.pop(ent.name, None)
                try:
                    self.accept(p.stem, data, f"spool {p}")
                    p.unlink()
                except HostdError as e:
                    self._reject_spool(p, str(e))
            for name in set(seen) - {e.name for e in entries}:
                seen.pop(name, None)

    def _reject_spool(self, p: Path, why: str) -> None:
        dest = self.spool / "rejected" / p.name
        try:  # the reason first, so that whoever sees the rejected file finds why
            write_output(dest.with_name(dest.name + ".error"), (why + "\n").encode(), mode=0o640)
            os.replace(p, dest)
            log.warning("spool: rejected %s: %s", p.name, why)
        except (OSError, HostdError) as e:
            log.error("spool: cannot move %s to %s (%s); it stays: %s", p, dest.parent, e, why)

    # ------------------------------------------------------------ control socket
    def handle_conn(self, conn: socket.socket) -> None:
        """One client: one request line (and an upload's bytes), one reply line, always."""
        rfile = conn.makefile("rb")
        try:
            reply = {"ok": True, **self.respond(rfile)}
        except HostdError as e:
            reply = {"ok": False, "error": str(e)}
        except TimeoutError:
            reply = {"ok": False, "error": "timed out waiting for the request"}
            log.warning("control socket: a client timed out")
        except Exception as e:  # a bug must still give the client an answer and the log one line
            log.error("control socket: request failed: %s: %s", type(e).__name__, e)
            reply = {"ok": False, "error": f"internal error ({type(e).__name__}): see hostd's log"}
        finally:
            rfile.close()
        try:
            conn.sendall((json.dumps(reply) + "\n").encode())
        except OSError:
            pass

    def refuse(self, msg: str) -> None:
        with self.lock:
            self.refused += 1
        raise HostdError(msg)

    def respond(self, rfile) -> dict:
        line = rfile.readline(MAX_HEADER + 1)
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
            data = rfile.read(size)
            if len(data) != size:
                self.refuse(f"upload truncated: got {len(data)} of {size} bytes")
            return self.accept(name, data, "socket")
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

    def serve_socket(self) -> None:
        c = self.cfg.control
        self.control = ControlServer(c.socket, c.group, c.max_clients, self.handle_conn)
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
    def run(self) -> int:
        self.proc.start()
        self.serve_socket()
        log.info("listening on %s", self.cfg.control.socket)
        self.start_worker("control", self.control.accept_loop)
        self.start_worker("quality", self.quality_worker)
        self.start_worker("spool", self.spool_watcher)
        self.rescore_missing()
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, lambda *_: self.stop_event.set())
        ready = False
        last_cycles = -1.0
        try:
            while not self.stop_event.wait(0.2):
                self.pump_messages()
                if not self.proc.is_alive():
                    log.error("the real-time pump exited (code %s); stopping", self.proc.exitcode)
                    return 1
                healthy = self.supervise()
                st = self.counters()
                state = st["state"]
                if not ready and state in ("waiting", "idle", "playing"):
                    self.notifier.notify("READY=1")
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
            try:
                self.conn.send(("quit",))
            except (OSError, BrokenPipeError):
                pass
            self.proc.join(3.0)
            if self.proc.is_alive():
                self.proc.terminate()
            self.pump_messages()  # its last lines (a recovery just before the stop) reach the log
            self.stop_event.set()
            if self.control is not None:
                self.control.close()
                Path(self.cfg.control.socket).unlink(missing_ok=True)
            quality = self.workers.get("quality")
            if quality is not None and quality[1] is not None:
                quality[1].join(30.0)  # rows for everything accepted are written before exit
            log.info("stopped")
        return 0
