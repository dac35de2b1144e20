"""The texture library: accepted streams stored atomically under their names.

A stream is written with hostd.fileio.write_output (a uniquely named temporary file in the
same directory, fsynced, renamed over its final name, the directory fsynced), one writer per
name at a time, so after a crash or a race of same-name uploads a name holds exactly one
whole accepted stream, never half of one or a mix.
"""

from __future__ import annotations

import hashlib
import re
import threading
from pathlib import Path

from hostd.codec import stream as vtx
from hostd.errors import HostdError, StreamError
from hostd.fileio import is_temporary, write_output

NAME_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}\Z")


def check_name(name: str) -> str:
    if not isinstance(name, str) or not NAME_RE.match(name) or name.endswith(".tmp"):
        raise HostdError(f"bad texture name {name!r}: use 1-64 letters, digits, '.', '_' or '-'")
    return name


class Library:
    def __init__(self, directory: str | Path, max_bytes: int = 1 << 20, max_n: int = 1 << 22,
                 max_n_keep: int = 1 << 22) -> None:
        self.dir = Path(directory)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.max_bytes = max_bytes
        self.max_n = max_n
        self.max_n_keep = max_n_keep
        self._locks: dict[str, threading.Lock] = {}
        self._locks_guard = threading.Lock()
        for stale in self.dir.iterdir():  # a crash mid-write leaves only temporaries
            if is_temporary(stale.name):
                stale.unlink(missing_ok=True)

    def path(self, name: str) -> Path:
        return self.dir / f"{check_name(name)}.vtx"

    def lock(self, name: str) -> threading.Lock:
        with self._locks_guard:
            return self._locks.setdefault(name, threading.Lock())

    def validate(self, data: bytes) -> vtx.Stream:
        if len(data) > self.max_bytes:
            raise StreamError(f"stream of {len(data)} bytes exceeds the limit of {self.max_bytes} "
                              "(library.max_stream_bytes)")
        s = vtx.decode(data)  # raises StreamError with the decoder's message
        if s.n > self.max_n:
            raise StreamError(f"stream has N = {s.n} samples, more than this daemon plays "
                              f"({self.max_n}, library.max_n)")
        if s.n_keep > self.max_n_keep:
            raise StreamError(f"stream has N' = {s.n_keep} coefficients, more than this daemon plays "
                              f"({self.max_n_keep}, library.max_n_keep)")
        return s

    def add(self, name: str, data: bytes) -> tuple[vtx.Stream, str]:
        """Validate and store; returns the decoded stream and its SHA-256."""
        s = self.validate(data)
        path = self.path(name)
        with self.lock(name):
            write_output(path, data, mode=0o640)
        return s, hashlib.sha256(data).hexdigest()

    def names(self) -> list[str]:
        return sorted(p.stem for p in self.dir.glob("*.vtx") if not p.name.startswith("."))

    def read(self, name: str) -> bytes:
        p = self.path(name)
        try:
            return p.read_bytes()
        except FileNotFoundError:
            raise HostdError(f"no texture named {name!r} (hostd list shows the library)") from None
