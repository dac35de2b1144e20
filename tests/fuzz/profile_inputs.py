"""Profile files for the readers' fuzzer (fuzz_profiles.py) and tests: well-formed seeds, crafted
hostile inputs (declared sizes the bytes do not back, a zlib bomb), written with nothing but the
standard library and numpy, so that each byte is the one the test means.

An input of the fuzzer is one byte choosing the file's suffix (SUFFIXES[b % len]) and the file's
bytes: `as_input(".wav", data)`. `python tests/fuzz/profile_inputs.py DIR` writes the seeds and
the regression inputs (tests/fuzz/corpus/profiles holds them, made so).
"""

from __future__ import annotations

import io
import struct
import sys
import zlib
from pathlib import Path

import numpy as np

SUFFIXES = (".csv", ".npy", ".mat", ".wav", ".txt")

MI_INT8, MI_UINT8, MI_INT32, MI_UINT32, MI_DOUBLE, MI_MATRIX, MI_COMPRESSED = 1, 2, 5, 6, 9, 14, 15
MX_CELL, MX_STRUCT, MX_DOUBLE = 1, 2, 6


def as_input(suffix: str, data: bytes) -> bytes:
    """The fuzzer's input for a file of this suffix (".wav+ch": a WAV read with --columns 1)."""
    base, _, ch = suffix.partition("+")
    return bytes([SUFFIXES.index(base) | (0x80 if ch else 0)]) + data


def options(first: int):
    """(suffix, LoadOptions) an input's first byte chooses."""
    from hostd.texture.load import LoadOptions

    suffix = SUFFIXES[(first & 0x7F) % len(SUFFIXES)]
    columns = (0,) if first & 0x80 and suffix == ".wav" else None
    return suffix, LoadOptions(spacing=1.0, length_mm=None, columns=columns)


# ------------------------------------------------------------------------------------ MATLAB v5


def mat5_header() -> bytes:
    text = b"MATLAB 5.0 MAT-file, written by tests/fuzz/profile_inputs.py"
    return text.ljust(116, b" ") + b"\0" * 8 + struct.pack("<H", 0x0100) + b"IM"


def _element(typ: int, payload: bytes, declared: int | None = None) -> bytes:
    n = len(payload) if declared is None else declared
    return struct.pack("<II", typ, n) + payload + b"\0" * (-len(payload) % 8)


def mat_matrix(name: str, dims: tuple[int, ...], cls: int = MX_DOUBLE, data: bytes = b"",
               data_type: int = MI_DOUBLE, declared: int | None = None, children: bytes = b"",
               fields: tuple[str, ...] = ()) -> bytes:
    """One miMATRIX element (its tag and body); `declared` overrides the data's byte count."""
    body = _element(MI_UINT32, struct.pack("<II", cls, 0))
    body += _element(MI_INT32, struct.pack(f"<{len(dims)}i", *dims))
    body += _element(MI_INT8, name.encode())
    if cls == MX_STRUCT:
        body += struct.pack("<HHi", MI_INT32, 4, 32)  # field name length: a small data element
        body += _element(MI_INT8, b"".join(f.encode().ljust(32, b"\0") for f in fields))
    if cls in (MX_CELL, MX_STRUCT):
        body += children
    else:
        body += _element(data_type, data, declared)
    return _element(MI_MATRIX, body)


def compressed(element: bytes) -> bytes:
    blob = zlib.compress(element, 9)
    return struct.pack("<II", MI_COMPRESSED, len(blob)) + blob


def mat_bomb(n_doubles: int) -> bytes:
    """A v5 file with one compressed double vector of n_doubles zeros, compressed as it is made
    (the whole vector is never in memory): 8 MiB of zeros take some 8 kB."""
    z = zlib.compressobj(9)
    head = mat_matrix("h", (n_doubles, 1), data=b"", declared=8 * n_doubles)
    parts = [z.compress(head)]
    zeros = bytes(1 << 20)
    left = 8 * n_doubles
    while left > 0:
        parts.append(z.compress(zeros[: min(left, len(zeros))]))
        left -= min(left, len(zeros))
    parts.append(z.flush())
    blob = b"".join(parts)
    return mat5_header() + struct.pack("<II", MI_COMPRESSED, len(blob)) + blob


def mat_v4(name: str, rows: int, cols: int, data: bytes) -> bytes:
    return struct.pack("<5i", 0, rows, cols, 0, len(name) + 1) + name.encode() + b"\0" + data


# ------------------------------------------------------------------------------------ WAV


def wav(data: bytes, *, fmt_tag: int = 1, channels: int = 1, rate: int = 48000, bits: int = 16,
        align: int | None = None, fmt_size: int = 16, extra: bytes = b"") -> bytes:
    align = channels * bits // 8 if align is None else align
    fmt = struct.pack("<HHIIHH", fmt_tag, channels, rate, rate * align, align, bits)
    body = b"WAVE" + struct.pack("<4sI", b"fmt ", fmt_size) + fmt + extra
    body += struct.pack("<4sI", b"data", len(data)) + data
    return b"RIFF" + struct.pack("<I", len(body)) + body


# ------------------------------------------------------------------------------------ the corpus


def seeds() -> dict[str, bytes]:
    """name -> fuzzer input: the well-formed files each reader takes."""
    x = np.arange(64, dtype=np.float64)
    y = np.sin(x / 5.0)
    npy = io.BytesIO()
    np.save(npy, np.column_stack([x, y]))
    vec = mat_matrix("h", (64, 1), data=y.tobytes())
    rows = list(zip(x, y, strict=True))
    return {
        "seed-two-columns.csv": as_input(".csv", "".join(f"{a:g},{b:.6f}\n" for a, b in rows).encode()),
        "seed-preamble.txt": as_input(".txt", b"Scan Parameters\nLateral um,Raw um\n"
                                      + "".join(f"{a:g}\t{b:.4f}\n" for a, b in rows).encode()),
        "seed-heights.npy": as_input(".npy", npy.getvalue()),
        "seed-v5.mat": as_input(".mat", mat5_header() + vec),
        "seed-v5-compressed.mat": as_input(".mat", mat5_header() + compressed(vec)),
        "seed-v5-cell.mat": as_input(".mat", mat5_header() + vec.replace(b"h\0", b"g\0", 1)
                                     + mat_matrix("c", (1, 1), cls=MX_CELL, children=mat_matrix("", (2, 1),
                                                  data=b"\0" * 16))),
        "seed-v4.mat": as_input(".mat", mat_v4("h", 64, 1, y.tobytes())),
        "seed-int16.wav": as_input(".wav", wav((y * 3000).astype("<i2").tobytes())),
        "seed-float-stereo.wav": as_input(".wav+ch", wav(np.column_stack([y, -y]).astype("<f4").tobytes(),
                                                      fmt_tag=3, channels=2, bits=32)),
    }


def regressions() -> dict[str, bytes]:
    """name -> fuzzer input: hostile files each reader must refuse in one line, in bounded memory."""
    y = np.zeros(8)
    return {
        # a vector declaring 2^31-1 doubles, backed by 64 bytes
        "mat-declared-huge.mat": as_input(".mat", mat5_header() + mat_matrix(
            "h", (2**31 - 1, 1), data=y.tobytes(), declared=8 * (2**31 - 1) & 0xFFFFFFFF)),
        # a cell array declaring 10^9 cells in a few bytes (scipy would make the object array first)
        "mat-cell-billion.mat": as_input(".mat", mat5_header() + mat_matrix("c", (10**9, 1), cls=MX_CELL)),
        # 16 MiB of zeros in some 16 kB: a zlib bomb (over 64x its size and over 8 MiB)
        # a million cells in a few bytes
        "mat-cell-million.mat": as_input(".mat", mat5_header() + mat_matrix("c", (10**6, 1), cls=MX_CELL)),
        "mat-zlib-bomb.mat": as_input(".mat", mat_bomb(2 << 20)),
        "mat-v4-huge.mat": as_input(".mat", mat_v4("h", 2**30, 2**30, b"\0" * 64)),
        "wav-zero-channels.wav": as_input(".wav", wav(b"\0" * 64, channels=0, align=0)),
        "wav-fmt-4gb.wav": as_input(".wav", wav(b"\0" * 64, fmt_size=0xFFFFFFF0)),
        "wav-cut-short.wav": as_input(".wav", wav(b"\0" * 64)[:30]),
        # a fmt chunk and no data chunk (scipy's reader once ended with UnboundLocalError)
        "wav-no-data-chunk.wav": as_input(".wav", wav(b"")[:-8].replace(b"RIFF\x24", b"RIFF\x1c", 1)),
        "wav-align-not-channels.wav": as_input(".wav", wav(b"\0" * 64, channels=3, align=4)),
        "npy-random-bytes.npy": as_input(".npy", bytes(range(256)) * 4),
        "npy-declared-huge.npy": as_input(".npy", b"\x93NUMPY\x01\x00v\x00" + (
            b"{'descr': '<f8', 'fortran_order': False, 'shape': (1000000000,), }".ljust(117) + b"\n")
            + b"\0" * 64),
        "npy-pickle.npy": as_input(".npy", b"\x93NUMPY\x01\x00v\x00" + (
            b"{'descr': '|O', 'fortran_order': False, 'shape': (2,), }".ljust(117) + b"\n")
            + b"\x80\x04N."),
        "csv-is-a-wav.csv": as_input(".csv", wav(b"\x10\x00" * 64)),
        "txt-nul-bytes.txt": as_input(".txt", b"1,2\n3,\0\n" * 8),
    }


def write_corpus(folder: Path) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for name, data in {**seeds(), **regressions()}.items():
        (folder / name).write_bytes(data)


if __name__ == "__main__":
    write_corpus(Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).parent / "corpus" / "profiles")
