"""The control socket: a checked directory, a real listen backlog, a bounded pool of handlers.

- The socket's directory must be owned by the daemon's user and writable by nobody else (not
  merely sticky: in a sticky directory another user can take the name after a stop and answer
  our clients). Clients check who holds the socket (SO_PEERCRED, hostd.service.client).
- The socket is created 0660 by bind() itself (umask), so it is never more open, and given to
  control.group through the checked directory's file descriptor (no symlink followed).
- Up to control.max_clients connections are served at once by a pool of threads that grows on
  demand (one handler at rest, one more per client being served, each ending after
  HANDLER_IDLE_S idle); one more is answered with a one-line refusal and closed. The listen
  backlog is SOMAXCONN.
- accept() failing with EMFILE/ENFILE (out of file descriptors) backs off (50 ms doubling to
  1 s) with one log line per episode, instead of spinning.
- Every request has a deadline for the whole of it (REQUEST_DEADLINE_S, not per read) and a
  byte budget (the request line and the announced upload, nothing more). When every handler is
  busy, a new connection evicts the client that has been sending its request the longest (at
  least EVICT_AFTER_S), so clients that drip bytes cannot lock out one that sends promptly.
- A user other than root and the daemon's own (SO_PEERCRED) is served at most
  max(1, max_clients // 4) connections at once: one group member cannot take every handler.
"""

from __future__ import annotations

import errno
import grp
import json
import logging
import os
import queue
import socket
import stat
import struct
import threading
import time
from collections.abc import Callable
from pathlib import Path

from hostd.errors import ConfigError, HostdError

log = logging.getLogger("hostd")
REQUEST_DEADLINE_S = 10.0  # the whole request (line and upload) from accept to the last byte
EVICT_AFTER_S = 1.0  # a client still sending its request after this may give its handler away
REPLY_TIMEOUT_S = 5.0


class BadRequest(HostdError):
    """A control-socket request that is not well formed."""


class RequestTimeout(TimeoutError):
    """The client did not send its whole request within the deadline (or was evicted)."""


class ClientConn:
    """One client's connection as the handler reads it: readline/read under one deadline for
    the whole request and a byte budget; done_reading() once the request is in."""

    def __init__(self, conn: socket.socket, budget: int, deadline_s: float = REQUEST_DEADLINE_S,
                 uid: int = -1, peer_uid: int | None = None) -> None:
        self.conn = conn
        self.uid = uid  # -1: root or the daemon's own user (no share limit); else the limited uid
        self.peer_uid = peer_uid  # the connected process's uid (SO_PEERCRED); None: not known
        self.started = time.monotonic()
        self.deadline = self.started + deadline_s
        self.budget = budget
        self.buf = bytearray()
        self.reading = True
        self.evicted = False

    def _fill(self, want: int) -> bool:
        """Receive more (at most want bytes); False at end of stream."""
        left = self.deadline - time.monotonic()
        if left <= 0 or self.evicted:
            raise RequestTimeout("request not complete within the deadline")
        if self.budget <= 0:
            raise RequestTimeout("request larger than announced")
        self.conn.settimeout(left)
        try:
            b = self.conn.recv(max(1, min(want, self.budget, 1 << 16)))
        except TimeoutError:
            raise RequestTimeout("request not complete within the deadline") from None
        if self.evicted:
            raise RequestTimeout("evicted")
        self.budget -= len(b)
        self.buf += b
        return bool(b)

    def readline(self, limit: int) -> bytes:
        """Up to and including the first newline, or limit + 1 bytes if none came by then."""
        while b"\n" not in self.buf and len(self.buf) <= limit:
            if not self._fill(limit + 1 - len(self.buf)):
                break
        i = self.buf.find(b"\n")
        end = i + 1 if 0 <= i <= limit else min(len(self.buf), limit + 1)
        out = bytes(self.buf[:end])
        del self.buf[:end]
        return out

    def read(self, n: int) -> bytes:
        while len(self.buf) < n:
            if not self._fill(n - len(self.buf)):
                break
        out = bytes(self.buf[:n])
        del self.buf[:n]
        return out

    def done_reading(self) -> None:
        self.reading = False

    def evict(self) -> None:
        self.evicted = True
        try:
            self.conn.shutdown(socket.SHUT_RD)  # its handler's recv returns at once
        except OSError:
            pass

    def reply(self, data: bytes) -> None:
        try:
            self.conn.settimeout(REPLY_TIMEOUT_S)
            self.conn.sendall(data)
        except OSError:
            pass


def check_socket_dir(d: Path) -> None:
    """Refuse a directory that others could write into (see the module docstring)."""
    try:
        fd = os.open(d, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW)
    except OSError as e:
        raise ConfigError(f"control.socket: cannot use directory {d}: {e.strerror}") from None
    try:
        st = os.fstat(fd)
    finally:
        os.close(fd)
    me = os.geteuid()
    if st.st_uid != me or st.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
        raise ConfigError(f"control.socket: directory {d} (mode {stat.S_IMODE(st.st_mode):04o}, owner "
                          f"uid {st.st_uid}) is not owned by hostd's user (uid {me}) or can be written by "
                          "others: "
                          "another user could take the socket's name; set control.socket in a directory "
                          "only hostd's user owns and writes, such as /run/hostd (RuntimeDirectory=hostd)")


def peer_uid(conn: socket.socket) -> int:
    """The connected process's uid (SO_PEERCRED: the kernel's word, not the client's)."""
    _pid, uid, _gid = struct.unpack("3i", conn.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED,
                                                          struct.calcsize("3i")))
    return uid


class ControlServer:
    def __init__(self, path: str | Path, group: str, max_clients: int,
                 handle: Callable[[ClientConn], None], budget: int = 1 << 20) -> None:
        self.path = Path(path)
        self.budget = budget  # bytes one request may send: its line and the largest upload
        self.clients: set[ClientConn] = set()  # being served, under busy_lock
        self.evicted = 0
        self.per_user: dict[int, int] = {}  # connections held per (untrusted) uid, under busy_lock
        self.user_share = max(1, max_clients // 4)
        self.max_clients = max_clients
        self.handle = handle
        self.stopping = threading.Event()
        self.jobs: queue.Queue = queue.Queue()
        self.busy = 0
        self.busy_lock = threading.Lock()
        self.refused_busy = 0
        self.threads: list[threading.Thread] = []
        self.handlers = 0  # handler threads alive, under busy_lock (started on demand, start_pool)
        d = self.path.parent
        d.mkdir(parents=True, exist_ok=True, mode=0o750)
        check_socket_dir(d)
        self._remove_stale()
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        old = os.umask(0o117)  # bind creates the node 0660: never world-accessible, not even briefly
        try:
            self.sock.bind(str(self.path))
        finally:
            os.umask(old)
        self.sock.listen(socket.SOMAXCONN)
        if group:
            self._give_to_group(group)

    def _remove_stale(self) -> None:
        try:
            st = os.lstat(self.path)
        except FileNotFoundError:
            return
        if not stat.S_ISSOCK(st.st_mode):
            raise ConfigError(f"control.socket: {self.path} exists and is not a socket: remove it or "
                              "choose another path")
        probe = socket.socket(socket.AF_UNIX)
        try:
            probe.connect(str(self.path))
            raise ConfigError(f"{self.path}: another hostd is already running on this socket")
        except (ConnectionRefusedError, FileNotFoundError):
            self.path.unlink(missing_ok=True)  # stale, from a crash
        finally:
            probe.close()

    def _give_to_group(self, group: str) -> None:
        try:
            gid = grp.getgrnam(group).gr_gid
        except KeyError:
            log.warning("control.group %r does not exist; the socket keeps the daemon's group", group)
            return
        dfd = os.open(self.path.parent, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW)
        try:
            os.chown(self.path.name, -1, gid, dir_fd=dfd, follow_symlinks=False)
        except PermissionError:
            log.warning("cannot give the socket to group %r (not a member); it keeps the daemon's group",
                        group)
        finally:
            os.close(dfd)

    # ------------------------------------------------------------ serving
    HANDLER_IDLE_S = 30.0  # a handler thread idle this long ends (one stays while none is busy)

    def start_pool(self) -> None:
        """The first handler thread; the caller runs accept_loop (the daemon supervises it). The
        pool grows on demand up to max_clients threads, a thread for each client being served
        when all are busy, and shrinks again when they idle: a daemon nobody talks to holds one
        handler, not max_clients."""
        with self.busy_lock:
            self._add_handler()

    def _add_handler(self) -> None:
        """Under busy_lock: one more handler thread."""
        self.threads = [t for t in self.threads if t.is_alive()]
        t = threading.Thread(target=self._worker, name=f"control-{len(self.threads)}", daemon=True)
        self.handlers += 1
        t.start()
        self.threads.append(t)

    def accept_loop(self) -> None:
        backoff = 0.0
        while not self.stopping.is_set():
            try:
                conn, _ = self.sock.accept()
            except OSError as e:
                if self.stopping.is_set():
                    return
                if e.errno in (errno.EMFILE, errno.ENFILE, errno.ENOBUFS, errno.ENOMEM):
                    if backoff == 0.0:
                        log.error("control socket: cannot accept (%s); backing off until descriptors "
                                  "are free (LimitNOFILE)", e.strerror)
                    backoff = min(max(backoff * 2, 0.05), 1.0)
                    self.stopping.wait(backoff)
                    continue
                if e.errno in (errno.EINTR, errno.ECONNABORTED):
                    continue
                raise
            if backoff:
                log.info("control socket: accepting again")
                backoff = 0.0
            uid = peer_uid(conn)
            limited = uid not in (0, os.geteuid())
            with self.busy_lock:
                over_share = limited and self.per_user.get(uid, 0) >= self.user_share
                full = over_share or self.busy >= self.max_clients
                if full and not over_share and self._evict_slowest():
                    full = False
                if not full:
                    self.busy += 1
                    if self.busy > self.handlers:  # every handler is serving someone: one more
                        self._add_handler()
                    if limited:
                        self.per_user[uid] = self.per_user.get(uid, 0) + 1
            if full:
                self.refused_busy += 1
                self._refuse(conn, f"hostd is busy: uid {uid} already has {self.user_share} requests being "
                                   "served (a user's share of control.max_clients); try again" if over_share
                              else None)
                continue
            self.jobs.put((conn, uid, limited))

    def _evict_slowest(self) -> bool:
        """Under busy_lock: drop the client that has been sending its request the longest, if
        for at least EVICT_AFTER_S; its handler answers it and is free again at once."""
        now = time.monotonic()
        slow = [c for c in self.clients if c.reading and not c.evicted and now - c.started >= EVICT_AFTER_S]
        if not slow:
            return False
        victim = min(slow, key=lambda c: c.started)
        victim.evict()
        self.evicted += 1
        log.warning("control socket: all %d handlers busy; dropped a client still sending its request "
                    "after %.1f s", self.max_clients, now - victim.started)
        return True

    def _refuse(self, conn: socket.socket, why: str | None = None) -> None:
        why = why or (f"hostd is busy: {self.max_clients} clients are being served (control.max_clients); "
                      "try again")
        try:
            conn.settimeout(0.5)
            conn.sendall((json.dumps({"ok": False, "error": why, "retry": True}) + "\n").encode())
        except OSError:
            pass
        finally:
            conn.close()

    def _worker(self) -> None:
        while True:
            try:
                job = self.jobs.get(timeout=self.HANDLER_IDLE_S)
            except queue.Empty:
                with self.busy_lock:  # idle: end unless every other handler is needed
                    if self.busy < self.handlers and self.handlers > 1 and not self.stopping.is_set():
                        self.handlers -= 1
                        return
                continue
            if job is None:
                return
            conn, uid, limited = job
            limited_uid = uid if limited else None
            client = ClientConn(conn, self.budget, uid=-1 if limited_uid is None else limited_uid,
                                peer_uid=uid)
            with self.busy_lock:
                self.clients.add(client)
            try:
                self.handle(client)
            except Exception as e:  # one client's failure never takes a handler down
                log.warning("control socket: a client's request failed: %s", e)
            finally:
                try:
                    conn.close()
                except OSError:
                    pass
                with self.busy_lock:
                    self.clients.discard(client)
                    self.busy -= 1
                    if limited_uid is not None:
                        self.per_user[limited_uid] -= 1

    def close(self) -> None:
        self.stopping.set()
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self.sock.close()
        for _ in self.threads:
            self.jobs.put(None)
        deadline = time.monotonic() + 2.0
        for t in self.threads:
            t.join(max(0.0, deadline - time.monotonic()))
