"""Coverage-guided fuzzing of the .vtx decoders (v1 and v2) with atheris.

    tests/fuzz/run_atheris.sh fuzz_stream 60     # makes FUZZ_OUT, seeds it with tests/vectors/*.vtx

Every input must either decode to a valid stream or raise StreamError; anything else (another
exception, a hang, unbounded memory) is a finding. The seed corpus is the golden vectors, and
half of the inputs get a valid CRC appended (so the fuzzer reaches past the CRC check).
Not collected by pytest (it needs atheris, which is not a project dependency).
"""

import binascii
import struct
import sys
import zlib

import atheris
import numpy as np

with atheris.instrument_imports(include=["hostd"]):
    from hostd.codec import rangecoder  # noqa: F401
    from hostd.codec import stream as vtx
    from hostd.codec.stream import v2  # noqa: F401
    from hostd.errors import StreamError


def _with_crc(body: bytes) -> bytes:
    if body[:2] == b"VT":
        return body + struct.pack("<I", zlib.crc32(body))
    if len(body) + 2 < 4096:
        return body + struct.pack("<H", binascii.crc_hqx(body, 0xFFFF))
    return body + struct.pack("<I", zlib.crc32(body))


def one_input(data: bytes) -> None:
    if not data:
        return
    fix_crc = data[0] & 1
    data = data[1:]
    if fix_crc:
        data = _with_crc(data)
    try:
        s = vtx.decode(data)
    except StreamError:
        return
    assert s.coefficients.shape == (s.n_keep,) and np.all(np.isfinite(s.coefficients))


def main() -> None:
    atheris.Setup(sys.argv, one_input)
    atheris.Fuzz()


if __name__ == "__main__":
    main()
