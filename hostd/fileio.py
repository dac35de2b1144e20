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
        try:
            _write_all(fd, data)
            os.fchmod(fd, mode)
            if durable:
                os.fsync(fd)
        finally:
            os.close(fd)
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
