"""The texture library: accepted streams stored atomically under their names.

A stream is written to a temporary file in the same directory, fsynced, renamed over its
final name and the directory fsynced, so after a crash a name holds either the whole old
stream or the whole new one, never half of one.
"""

from __future__ import annotations

import hashlib
import os
import re
from pathlib import Path

from hostd.codec import stream as vtx
from hostd.errors import HostdError, StreamError

NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$")


def check_name(name: str) -> str:
    if not NAME_RE.match(name) or name.endswith(".tmp"):
        raise HostdError(f"bad texture name {name!r}: use 1-64 letters, digits, '.', '_' or '-'")
    return name


def write_atomic(path: Path, data: bytes) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o640)
    try:
        os.write(fd, data)
        os.fsync(fd)
    finally:
        os.close(fd)
    os.replace(tmp, path)
    dfd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dfd)
    finally:
        os.close(dfd)


class Library:
    def __init__(self, directory: str | Path, max_bytes: int = 1 << 20) -> None:
        self.dir = Path(directory)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.max_bytes = max_bytes
        for stale in self.dir.glob(".*.tmp"):  # a crash mid-write leaves only these
            stale.unlink(missing_ok=True)

    def path(self, name: str) -> Path:
        return self.dir / f"{check_name(name)}.vtx"

    def validate(self, data: bytes) -> vtx.Stream:
        if len(data) > self.max_bytes:
            raise StreamError(f"stream of {len(data)} bytes exceeds the limit of {self.max_bytes} "
                              "(library.max_stream_bytes)")
        return vtx.decode(data)  # raises StreamError with the decoder's message

    def add(self, name: str, data: bytes) -> tuple[vtx.Stream, str]:
        """Validate and store; returns the decoded stream and its SHA-256."""
        s = self.validate(data)
        write_atomic(self.path(name), data)
        return s, hashlib.sha256(data).hexdigest()

    def names(self) -> list[str]:
        return sorted(p.stem for p in self.dir.glob("*.vtx") if not p.name.startswith("."))

    def read(self, name: str) -> bytes:
        p = self.path(name)
        if not p.exists():
            raise HostdError(f"no texture named {name!r} (hostd list shows the library)")
        return p.read_bytes()
