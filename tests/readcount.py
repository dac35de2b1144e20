"""read() calls of the calling thread, counted by the kernel (syscr in /proc/thread-self/io): what
a test needs to see that a transport never reads a tty holding nothing (such a read waits for the
kernel's buffer work: hostd/device/seriallink.py)."""

from __future__ import annotations

import os


class ReadCounter:
    """read() calls of this thread so far (the kernel's count, syscr), not counting its own: one
    pread per call. A call returns None where the kernel does not count (no task I/O accounting);
    the counter belongs to the thread that made it."""

    def __init__(self) -> None:
        try:
            self.fd = os.open("/proc/thread-self/io", os.O_RDONLY)
        except OSError:
            self.fd = None
        self.own = 0

    def __call__(self) -> int | None:
        if self.fd is None:
            return None
        raw = os.pread(self.fd, 4096, 0)
        self.own += 1
        return int(raw.split(b"syscr:")[1].split()[0]) - self.own

    def close(self) -> None:
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None
