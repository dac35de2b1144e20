"""The control socket: a checked directory, a real listen backlog, a bounded pool of handlers.

- The socket's directory must not be writable by anyone but its owner (us or root), or be
  sticky and ours: otherwise a local user could replace the socket and answer our clients.
- The socket is created 0660 by bind() itself (umask), so it is never more open, and given to
  control.group through the checked directory's file descriptor (no symlink followed).
- Up to control.max_clients connections are served at once by a fixed pool of threads; one
  more is answered with a one-line refusal and closed. The listen backlog is SOMAXCONN.
- accept() failing with EMFILE/ENFILE (out of file descriptors) backs off (50 ms doubling to
  1 s) with one log line per episode, instead of spinning.
- Every connection has a read timeout, so a client that stops sending cannot hold a handler.
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
import threading
import time
from collections.abc import Callable
from pathlib import Path

from hostd.errors import ConfigError

log = logging.getLogger("hostd")
CLIENT_TIMEOUT_S = 10.0


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
    others_write = st.st_mode & (stat.S_IWGRP | stat.S_IWOTH)
    if st.st_mode & stat.S_ISVTX and st.st_uid == me:
        return
    if st.st_uid not in (me, 0) or others_write:
        raise ConfigError(f"control.socket: directory {d} can be written by other users (mode "
                          f"{stat.S_IMODE(st.st_mode):04o}, owner uid {st.st_uid}): a local user could "
                          "replace the socket; use a directory only hostd can write, such as /run/hostd")


class ControlServer:
    def __init__(self, path: str | Path, group: str, max_clients: int,
                 handle: Callable[[socket.socket], None]) -> None:
        self.path = Path(path)
        self.max_clients = max_clients
        self.handle = handle
        self.stopping = threading.Event()
        self.jobs: queue.Queue = queue.Queue()
        self.busy = 0
        self.busy_lock = threading.Lock()
        self.refused_busy = 0
        self.threads: list[threading.Thread] = []
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
    def start_pool(self) -> None:
        """The handler threads; the caller runs accept_loop (the daemon supervises it)."""
        for i in range(self.max_clients):
            t = threading.Thread(target=self._worker, name=f"control-{i}", daemon=True)
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
            with self.busy_lock:
                full = self.busy >= self.max_clients
                if not full:
                    self.busy += 1
            if full:
                self.refused_busy += 1
                self._refuse(conn)
                continue
            self.jobs.put(conn)

    def _refuse(self, conn: socket.socket) -> None:
        try:
            conn.settimeout(0.5)
            conn.sendall((json.dumps({"ok": False, "error": f"hostd is busy: {self.max_clients} clients "
                                      "are being served (control.max_clients); try again"}) + "\n").encode())
        except OSError:
            pass
        finally:
            conn.close()

    def _worker(self) -> None:
        while True:
            conn = self.jobs.get()
            if conn is None:
                return
            try:
                conn.settimeout(CLIENT_TIMEOUT_S)
                self.handle(conn)
            except Exception as e:  # one client's failure never takes a handler down
                log.warning("control socket: a client's request failed: %s", e)
            finally:
                try:
                    conn.close()
                except OSError:
                    pass
                with self.busy_lock:
                    self.busy -= 1

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
