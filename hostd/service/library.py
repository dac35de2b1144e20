"""The texture library: accepted streams stored atomically under their names.

Every file operation is relative to the library directory's descriptor, opened and checked
(a real directory, ours, writable by nobody else) once at start-up, and never follows a
symbolic link: a stream is written with hostd.fileio.write_at (a new temporary, fsynced,
renamed over its name, the directory fsynced; a link found there is replaced, never written
through), read with read_regular_at (regular files only, size checked before reading). One
writer per name at a time, so after a crash or a race of same-name uploads a name holds
exactly one whole accepted stream.

Decoding is bounded twice: N and N' are checked from the header before anything of their size
is allocated (hostd.codec.stream.Limits), and at most `decode_slots` decodes run at once, so
that their worst case together stays within DECODE_BUDGET_BYTES (the unit's MemoryMax is 512M).
"""

from __future__ import annotations

import hashlib
import os
import re
import stat
import threading
from pathlib import Path

from hostd.codec import stream as vtx
from hostd.errors import HostdError, StreamError
from hostd.fileio import NotRegular, is_temporary, open_dir, read_regular_at, write_at

NAME_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}\Z")
# Peak bytes one decode allocates per coefficient N' (index array, |q|, float64 values,
# finiteness mask, the limits' |C'|: tracemalloc on the v2 and v1 quant streams of
# `hostd encode synthetic:wood --fmax 40000 --method quant --levels 14`, N' = 16,000: 24 and
# 18 B), with headroom for what tracemalloc does not see; per sample N: nothing is allocated.
DECODE_BYTES_PER_COEFF = 64
DECODE_BYTES_PER_SAMPLE = 0
DECODE_BUDGET_BYTES = 128 << 20  # concurrent decodes together; the unit's MemoryMax is 512M
TRAVEL_FACTOR = 100.0  # a coefficient beyond 100 times the display's travel is refused


def check_name(name: str) -> str:
    if not isinstance(name, str) or not NAME_RE.match(name) or name.endswith(".tmp"):
        raise HostdError(f"bad texture name {name!r}: use 1-64 letters, digits, '.', '_' or '-'")
    return name


class Library:
    def __init__(self, directory: str | Path, max_bytes: int = 1 << 20, max_n: int = 1 << 22,
                 max_n_keep: int = 1 << 22, travel_um: float | None = None) -> None:
        self.dir = Path(directory)
        self.dir.parent.mkdir(parents=True, exist_ok=True)
        self.fd = open_dir(self.dir, "library.dir", create_mode=0o750)
        self.max_bytes = max_bytes
        self.limits = vtx.Limits(max_n, max_n_keep,
                                 None if travel_um is None else TRAVEL_FACTOR * travel_um)
        self.max_n = max_n
        self.max_n_keep = max_n_keep
        worst = DECODE_BYTES_PER_COEFF * max_n_keep + DECODE_BYTES_PER_SAMPLE * max_n
        self.decode_slots = max(1, DECODE_BUDGET_BYTES // worst)
        self._decoding = threading.BoundedSemaphore(self.decode_slots)
        self._locks: dict[str, threading.Lock] = {}
        self._locks_guard = threading.Lock()
        for stale in os.listdir(self.fd):  # a crash mid-write leaves only temporaries
            if is_temporary(stale):
                try:
                    os.unlink(stale, dir_fd=self.fd)
                except OSError:
                    pass

    def close(self) -> None:
        os.close(self.fd)

    @staticmethod
    def filename(name: str) -> str:
        return f"{check_name(name)}.vtx"

    def path(self, name: str) -> Path:
        """For messages only: every operation goes through the directory's descriptor."""
        return self.dir / self.filename(name)

    def lock(self, name: str) -> threading.Lock:
        with self._locks_guard:
            return self._locks.setdefault(name, threading.Lock())

    def decode(self, data: bytes) -> vtx.Stream:
        """Decode under the limits and the decode budget; StreamError says why not."""
        if len(data) > self.max_bytes:
            raise StreamError(f"stream of {len(data)} bytes exceeds the limit of {self.max_bytes} "
                              "(library.max_stream_bytes)")
        with self._decoding:
            return vtx.decode(data, self.limits)  # raises StreamError with the decoder's message

    validate = decode

    def add(self, name: str, data: bytes) -> tuple[vtx.Stream, str]:
        """Validate and store; returns the decoded stream and its SHA-256."""
        s = self.decode(data)
        fname = self.filename(name)
        with self.lock(name):
            write_at(self.fd, fname, data, mode=0o640)
        return s, hashlib.sha256(data).hexdigest()

    def names(self) -> list[str]:
        """Stored textures: regular files only (a link or anything else in the directory is not one)."""
        out = []
        with os.scandir(self.fd) as it:
            for e in it:
                if (e.name.endswith(".vtx") and not e.name.startswith(".")
                        and e.is_file(follow_symlinks=False)):
                    out.append(e.name[:-4])
        return sorted(out)

    def read(self, name: str) -> bytes:
        try:
            return read_regular_at(self.fd, self.filename(name), self.max_bytes)
        except FileNotFoundError:
            raise HostdError(f"no texture named {name!r} (hostd list shows the library)") from None
        except NotRegular:
            raise HostdError(f"texture {name!r} is not a regular file in the library: refused "
                             f"(remove {self.path(name)})") from None

    def mtime(self, name: str) -> float:
        st = os.stat(self.filename(name), dir_fd=self.fd, follow_symlinks=False)
        if not stat.S_ISREG(st.st_mode):
            raise HostdError(f"texture {name!r} is not a regular file")
        return st.st_mtime
