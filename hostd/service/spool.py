"""The spool watcher: .vtx files dropped into library.spool are taken in once their writer is done;
anything else by that name is moved to rejected/ with a note (a thread of the daemon)."""

from __future__ import annotations

import logging
import os
import stat
import time
from collections.abc import Callable
from pathlib import Path

from hostd.errors import HostdError
from hostd.fileio import open_dir, read_regular_at, write_at

log = logging.getLogger("hostd")

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


class SpoolWatcher:
    """The spool and its rejected/ directory, opened and checked at start-up, and the thread that
    watches them; what settles is handed to `accept` (name, bytes, "spool")."""

    def __init__(self, cfg, spool: Path, accept: Callable[[str, bytes, str], dict]) -> None:
        self.cfg = cfg
        self.spool = spool
        self.accept = accept
        # group members may drop files here: the spool is sticky (made so if it is not), so
        # they cannot rename or remove what is not theirs, rejected/ included
        self.spool_fd = open_dir(self.spool, "library.spool", others_may_write=True, create_mode=0o1770)
        self.rejected_fd = self._open_rejected()

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

    def spool_watcher(self, stop_event, stop_r: int) -> None:
        """Take in .vtx files dropped into the spool once their writer is done: size and mtime
        unchanged for library.spool_settle_s and the mtime at least that old. Anything else
        named *.vtx (symlink, FIFO, device, directory, too big) is moved to rejected/ with a note.
        Every operation is relative to the spool's and rejected/'s descriptors (opened and
        checked at start-up) and follows no link: a member who renames rejected/ or plants
        links changes nothing the daemon writes or reads. Until stop_event is set (stop_r, a
        descriptor that turns readable at the stop, wakes it)."""
        import select

        settle = self.cfg.library.spool_settle_s
        limit = self.cfg.library.max_stream_bytes
        seen: dict[str, tuple[tuple[int, int], float]] = {}  # name -> (size, mtime_ns), since
        events = _spool_events(self.spool_fd)  # inotify where there is one, else a scan per period
        period = min(0.3, settle / 2)
        first = True
        try:
            while not stop_event.is_set():
                if not first:
                    # asleep until the spool changes (or the stop); a timer only while a file settles
                    wait = [stop_r] + ([events] if events is not None else [])
                    ready = select.select(wait, [], [], period if seen or events is None else None)[0]
                    if stop_event.is_set():
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
