"""Writing output files: the one atomic writer (CLI outputs, the daemon's library, install-service).

- ``-`` is standard output.
- An existing path that is not a regular file (a character device such as /dev/null, a FIFO)
  is written through: opened and written, never replaced.
- Anything else is replaced atomically: a temporary file with a unique name in the same
  directory, written, fsynced, given its mode, renamed over the name, and the directory
  fsynced; after a crash the name holds the whole old content or the whole new one. On any
  failure (ENOSPC, EIO, ...) the temporary is removed and a one-line HostdError is raised.
- Mode: the given one; else an existing file's; else 0666 minus the umask (as open() would).
"""

from __future__ import annotations

import os
import stat
import sys
import tempfile
from pathlib import Path

from hostd.errors import HostdError

TMP_PREFIX = "."
TMP_SUFFIX = ".tmp"


def current_umask() -> int:
    """The process umask, read without changing it (Linux /proc; else the set-and-restore dance)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except OSError:
        pass
    old = os.umask(0o022)
    os.umask(old)
    return old


def _fsync_dir(d: Path) -> None:
    fd = os.open(d, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        n = os.write(fd, view)
        view = view[n:]


def _fill_and_close(fd: int, data: bytes, mode: int, durable: bool) -> None:
    """A new temporary file's contents and mode (fsync'ed when durable), then closed: what is
    renamed over the target next is complete."""
    try:
        _write_all(fd, data)
        os.fchmod(fd, mode)
        if durable:
            os.fsync(fd)
    finally:
        os.close(fd)


def write_output(path: str | os.PathLike, data: bytes, mode: int | None = None, durable: bool = True) -> None:
    """Write ``data`` to ``path`` as described in the module docstring."""
    if str(path) == "-":
        sys.stdout.flush()
        sys.stdout.buffer.write(data)
        sys.stdout.buffer.flush()
        return
    target = Path(path)
    try:
        st = os.stat(target)  # follows a symlink: its target is what gets written
    except FileNotFoundError:
        st = None
    except OSError as e:
        raise HostdError(f"cannot write {path}: {e.strerror or e}") from None
    if st is not None and not stat.S_ISREG(st.st_mode):
        if stat.S_ISDIR(st.st_mode):
            raise HostdError(f"cannot write {path}: it is a directory (give a file name)")
        try:  # a device or FIFO: write through, never replace it
            fd = os.open(target, os.O_WRONLY | os.O_NOCTTY)
            try:
                _write_all(fd, data)
            finally:
                os.close(fd)
        except OSError as e:
            raise HostdError(f"cannot write {path}: {e.strerror or e}") from None
        return
    if target.is_symlink():
        target = Path(os.path.realpath(target))
    if mode is None:
        mode = stat.S_IMODE(st.st_mode) & 0o777 if st is not None else 0o666 & ~current_umask()
    directory = target.parent
    tmp = None
    try:
        fd, tmp = tempfile.mkstemp(dir=directory, prefix=f"{TMP_PREFIX}{target.name}.", suffix=TMP_SUFFIX)
        _fill_and_close(fd, data, mode, durable)
        os.replace(tmp, target)
        tmp = None
        if durable:
            _fsync_dir(directory)
    except OSError as e:
        raise HostdError(f"cannot write {path}: {e.strerror or e}") from None
    finally:
        if tmp is not None:
            try:
                os.unlink(tmp)
            except OSError:
                pass


def is_temporary(name: str) -> bool:
    """A name write_output uses for its temporaries (removed at start-up after a crash)."""
    return name.startswith(TMP_PREFIX) and name.endswith(TMP_SUFFIX)


# ---------------------------------------------------------------- relative to a directory fd
# The daemon's library and spool: every operation is relative to a directory descriptor the
# daemon opened and checked itself, and never follows a symbolic link, so a path another user
# can change (a renamed directory, a planted link) is never trusted.


class NotRegular(HostdError):
    """A name that is not a regular file (symlink, FIFO, device, directory)."""


def open_dir(path: str | os.PathLike, what: str, *, dir_fd: int | None = None, others_may_write: bool = False,
             create_mode: int | None = None) -> int:
    """A checked directory descriptor: a real directory (not a link), owned by us, writable by
    nobody else unless others_may_write (then it must be sticky). Created with create_mode if
    missing. Raises HostdError saying what to fix."""
    flags = os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC
    if create_mode is not None:
        try:
            os.mkdir(path, create_mode, dir_fd=dir_fd)
        except FileExistsError:
            pass
        except OSError as e:
            raise HostdError(f"{what}: cannot create {path}: {e.strerror}") from None
    try:
        fd = os.open(path, flags, dir_fd=dir_fd)
    except OSError as e:
        why = "a symbolic link or not a directory" if e.errno in (40, 20) else e.strerror
        raise HostdError(f"{what}: cannot use {path}: {why}") from None
    st = os.fstat(fd)
    mode = stat.S_IMODE(st.st_mode)
    problem = None
    if st.st_uid != os.geteuid():
        problem = f"owned by uid {st.st_uid}, not by this daemon's user (uid {os.geteuid()})"
    elif mode & (stat.S_IWGRP | stat.S_IWOTH) and not others_may_write:
        problem = f"mode {mode:04o} lets other users rename or replace what is in it"
    elif mode & (stat.S_IWGRP | stat.S_IWOTH) and not mode & stat.S_ISVTX:
        # ours, so we may: with the sticky bit a writer can rename or remove only its own files
        os.fchmod(fd, mode | stat.S_ISVTX)
    if problem:
        os.close(fd)
        raise HostdError(f"{what}: {path} is {problem}: give it to hostd's user with mode 0750 "
                         "(the spool: 3770, sticky), as systemd-tmpfiles does with hostd's tmpfiles.d file")
    return fd


def read_regular_at(dir_fd: int, name: str, max_bytes: int, expect: tuple[int, int] | None = None) -> bytes:
    """A regular file's bytes, name relative to dir_fd: no link followed (O_NOFOLLOW), no FIFO
    waited on (O_NONBLOCK), the type and size checked on the open descriptor before any byte is
    read, at most max_bytes read. expect: (size, mtime_ns) it must still have, else
    BlockingIOError (still being written)."""
    try:
        fd = os.open(name, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_NOCTTY | os.O_CLOEXEC,
                     dir_fd=dir_fd)
    except OSError as e:
        if e.errno in (40, 6):  # ELOOP: a symbolic link; ENXIO: a socket or a FIFO without writer
            raise NotRegular("a symbolic link or special file: only regular files are read") from None
        raise
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise NotRegular("not a regular file (FIFO, device or directory): only regular files are read")
        if st.st_size > max_bytes:
            raise HostdError(f"stream of {st.st_size} bytes exceeds the limit of {max_bytes} "
                             "(library.max_stream_bytes)")
        if expect is not None and (st.st_size, st.st_mtime_ns) != expect:
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


def write_at(dir_fd: int, name: str, data: bytes, mode: int = 0o640, durable: bool = True) -> None:
    """Atomic replace of name in dir_fd: a new temporary (O_CREAT|O_EXCL|O_NOFOLLOW), written,
    fsynced, renamed over name (a link there is replaced, never written through), the
    directory fsynced. On failure the temporary is removed and HostdError raised."""
    tmp = None
    try:
        for _ in range(100):
            cand = f"{TMP_PREFIX}{name}.{os.urandom(6).hex()}{TMP_SUFFIX}"
            try:
                fd = os.open(cand, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC,
                             0o600, dir_fd=dir_fd)
            except FileExistsError:
                continue
            tmp = cand
            break
        else:
            raise HostdError(f"cannot write {name}: no free temporary name")
        _fill_and_close(fd, data, mode, durable)
        os.rename(tmp, name, src_dir_fd=dir_fd, dst_dir_fd=dir_fd)
        tmp = None
        if durable:
            os.fsync(dir_fd)
    except OSError as e:
        raise HostdError(f"cannot write {name}: {e.strerror or e}") from None
    finally:
        if tmp is not None:
            try:
                os.unlink(tmp, dir_fd=dir_fd)
            except OSError:
                pass


def read_stream(path: str | Path):
    """A .vtx stream file, decoded (hostd.codec.stream.decode); a file that cannot be read is a
    StreamError naming it (one line, exit 2)."""
    from hostd.codec.stream import decode
    from hostd.errors import StreamError, StreamNotFound

    try:
        data = Path(path).read_bytes()
    except FileNotFoundError:
        raise StreamNotFound(f"no such stream file: {path}") from None
    except OSError as exc:
        raise StreamError(f"cannot read {path}: {exc.strerror or exc}") from None
    return decode(data)


_KINDS = ((stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISCHR, "a character device"),
          (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"), (stat.S_ISDIR, "a directory"))


def file_kind(mode: int) -> str:
    """What a non-regular st_mode is, in words (for a message)."""
    return next((word for test, word in _KINDS if test(mode)), "not a regular file")


def open_regular(path: str | os.PathLike):
    """A regular file opened for reading in binary (a buffered file object).

    A FIFO, device, socket or directory is refused without waiting on it (the name is opened
    with O_NONBLOCK and its type checked on the open descriptor, so a name swapped after a
    check is caught too): NotRegular, one line. A missing file is FileNotFoundError, other
    failures OSError, as open() would raise them."""
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY | os.O_CLOEXEC)
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise NotRegular(f"{path} is {file_kind(st.st_mode)}: only regular files are read "
                             "(copy the data into a file first)")
        os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise
