"""`hostd run`: the background service.

Threads of the main process: the control socket (one thread per client), the spool watcher,
the quality worker (scoring and SQLite), and the main loop (systemd notify and watchdog,
pump log lines, signals). The real-time pump is a separate process (pumpproc).
"""

from __future__ import annotations

import grp
import hashlib
import json
import logging
import multiprocessing as mp
import os
import queue
import signal
import socket
import socketserver
import threading
import time
from pathlib import Path

from hostd.device.health import STATE_NAMES as DEVICE_STATES
from hostd.device.health import fault_names
from hostd.device.protocol import SAMPLE_RATE_HZ
from hostd.errors import ConfigError, HostdError
from hostd.service import qualitylog
from hostd.service.config import Config
from hostd.service.library import Library, check_name
from hostd.service.pumpproc import FLOAT_FIELDS, STAT_FIELDS, STATE_NAMES, pump_main

log = logging.getLogger("hostd")
MAX_HEADER = 4096


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
        self.library = Library(cfg.library.dir, cfg.library.max_stream_bytes, cfg.library.max_n,
                               cfg.library.max_n_keep)
        self.spool = Path(cfg.library.spool)
        self.spool.mkdir(parents=True, exist_ok=True)
        (self.spool / "rejected").mkdir(exist_ok=True)
        self.db_path = cfg.quality.db
        qualitylog.connect(self.db_path).close()
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
        self.lock = threading.Lock()
        self.notifier = Notifier()
        self.server: socketserver.ThreadingUnixStreamServer | None = None

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
        seen: dict[Path, tuple[int, float]] = {}
        while not self.stop_event.wait(0.3):
            for p in sorted(self.spool.glob("*.vtx")):
                if p.name.startswith("."):
                    continue
                try:
                    st = p.stat()
                except FileNotFoundError:
                    continue
                sig = (st.st_size, st.st_mtime)
                if seen.get(p) != sig:  # still being written? take it when it holds still
                    seen[p] = sig
                    continue
                seen.pop(p, None)
                try:
                    data = p.read_bytes()
                    self.accept(p.stem, data, f"spool {p}")
                    p.unlink()
                except HostdError as e:
                    dest = self.spool / "rejected" / p.name
                    dest.with_suffix(".vtx.error").write_text(str(e) + "\n")  # the reason first
                    os.replace(p, dest)
                except OSError as e:
                    log.error("spool: cannot take in %s: %s", p, e)

    # ------------------------------------------------------------ control socket
    def handle(self, rfile, wfile) -> None:
        def reply(obj: dict) -> None:
            wfile.write((json.dumps(obj) + "\n").encode())

        line = rfile.readline(MAX_HEADER)
        try:
            req = json.loads(line)
            if not isinstance(req, dict):
                raise ValueError("not an object")
        except (ValueError, UnicodeDecodeError):
            reply({"ok": False, "error": "bad request: one JSON object per line expected"})
            return
        cmd = req.get("cmd")
        try:
            if cmd == "send":
                size = int(req.get("size", -1))
                if not 0 < size <= self.cfg.library.max_stream_bytes:
                    with self.lock:
                        self.refused += 1
                    log.warning("refused an upload of %d bytes (limit %d)", size,
                                self.cfg.library.max_stream_bytes)
                    raise HostdError(f"stream of {size} bytes refused: the limit is "
                                     f"{self.cfg.library.max_stream_bytes} (library.max_stream_bytes)")
                data = rfile.read(size)
                if len(data) != size:
                    with self.lock:
                        self.refused += 1
                    raise HostdError(f"upload truncated: got {len(data)} of {size} bytes")
                out = self.accept(str(req.get("name", "")), data, "socket")
            elif cmd == "list":
                out = {"textures": self.library.names(), "playing": self.selected}
            elif cmd == "select":
                out = self.select(str(req.get("name", "")))
            elif cmd == "stop":
                out = self.stop_playing()
            elif cmd == "status":
                out = self.status()
            elif cmd == "quality":
                con = qualitylog.connect(self.db_path)
                out = {"rows": qualitylog.query(con, req.get("since"))}
                con.close()
            elif cmd == "shutdown":
                out = {"shutting_down": True}
                self.stop_event.set()
            else:
                raise HostdError(f"unknown command {cmd!r}")
        except HostdError as e:
            reply({"ok": False, "error": str(e)})
            return
        reply({"ok": True, **out})

    def serve_socket(self) -> None:
        path = Path(self.cfg.control.socket)
        path.parent.mkdir(parents=True, exist_ok=True)
        if path.exists():
            probe = socket.socket(socket.AF_UNIX)
            try:
                probe.connect(str(path))
                raise ConfigError(f"{path}: another hostd is already running on this socket")
            except (ConnectionRefusedError, FileNotFoundError):
                path.unlink()  # stale, from a crash
            finally:
                probe.close()
        daemon = self

        class Handler(socketserver.StreamRequestHandler):
            def handle(self) -> None:
                try:
                    daemon.handle(self.rfile, self.wfile)
                except (BrokenPipeError, ConnectionResetError):
                    pass

        old = os.umask(0o117)  # the socket is created 0660: never world-accessible
        try:
            self.server = socketserver.ThreadingUnixStreamServer(str(path), Handler)
        finally:
            os.umask(old)
        self.server.daemon_threads = True
        os.chmod(path, 0o660)
        if self.cfg.control.group:
            try:
                os.chown(path, -1, grp.getgrnam(self.cfg.control.group).gr_gid)
            except KeyError:
                log.warning("control.group %r does not exist; the socket keeps the daemon's group",
                            self.cfg.control.group)
            except PermissionError:
                log.warning("cannot give the socket to group %r (not a member); it keeps the daemon's "
                            "group", self.cfg.control.group)
        threading.Thread(target=self.server.serve_forever, name="control", daemon=True).start()

    # ------------------------------------------------------------ main
    def run(self) -> int:
        self.proc.start()
        self.serve_socket()
        log.info("listening on %s", self.cfg.control.socket)
        workers = [threading.Thread(target=self.quality_worker, name="quality"),
                   threading.Thread(target=self.spool_watcher, name="spool", daemon=True)]
        for w in workers:
            w.start()
        self.rescore_missing()
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, lambda *_: self.stop_event.set())
        ready = False
        last_cycles = -1.0
        try:
            while not self.stop_event.wait(0.2):
                try:
                    while self.conn.poll():
                        _kind, msg = self.conn.recv()
                        log.info("%s", msg)
                except (EOFError, OSError):
                    pass  # the pump is gone: said just below
                if not self.proc.is_alive():
                    log.error("the real-time pump exited (code %s); stopping", self.proc.exitcode)
                    return 1
                st = self.counters()
                state = st["state"]
                if not ready and state in ("waiting", "idle", "playing"):
                    self.notifier.notify("READY=1")
                    ready = True
                # the watchdog is fed only when the real-time loop made progress (cycles, or
                # reconnection attempts while it waits for a device), never by a timer alone
                progress = st["cycles"] + st["reconnects"]
                if progress != last_cycles:
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
            self.stop_event.set()
            if self.server is not None:
                self.server.shutdown()
                self.server.server_close()
            Path(self.cfg.control.socket).unlink(missing_ok=True)
            workers[0].join(30.0)
            log.info("stopped")
        return 0
