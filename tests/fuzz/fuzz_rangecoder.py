"""Differential fuzzing of the two stream-v2 index coders: atheris (coverage-guided) or a plain
random run, against the built module or a sanitizer build of it.

    pip install atheris
    python tests/fuzz/fuzz_rangecoder.py -atheris_runs=0 -max_total_time=60
    python tests/fuzz/fuzz_rangecoder.py --random 200000      # no atheris needed
    tests/fuzz/sanitize_rangecoder.sh --random 10000          # C under ASan + UBSan

Each input is a payload for the decoders (first two bytes: N') or, when its first byte is odd,
indices for the encoders. The compiled coder (hostd/codec/_rangecoder.c; the file named by
$HOSTD_RANGECODER_SO if set) and the Python reference (hostd/codec/rangecoder.py, instrumented
under atheris: its branches guide the fuzzer) must give the same indices or the same
StreamError message, and the same bytes. Any difference, any other exception or a crash is a
finding. Not collected by pytest.
"""

import importlib.machinery
import importlib.util
import os
import sys

import numpy as np

RANDOM = len(sys.argv) == 3 and sys.argv[1] == "--random"
if RANDOM:
    from hostd.codec import rangecoder
    from hostd.errors import StreamError
else:
    import atheris

    with atheris.instrument_imports(include=["hostd.codec.rangecoder"]):
        from hostd.codec import rangecoder
        from hostd.errors import StreamError

if os.environ.get("HOSTD_RANGECODER_SO"):
    loader = importlib.machinery.ExtensionFileLoader("hostd.codec._rangecoder",
                                                     os.environ["HOSTD_RANGECODER_SO"])
    spec = importlib.util.spec_from_loader(loader.name, loader)
    rangecoder._C = importlib.util.module_from_spec(spec)
    loader.exec_module(rangecoder._C)
if rangecoder._C is None:
    sys.exit("the compiled coder is not built (or HOSTD_PURE_PYTHON is set): nothing to compare")
print(f"compiled coder: {rangecoder._C.__file__}", file=sys.stderr)


def _outcome(dec, data: bytes, n_keep: int):
    try:
        return ("ok", dec(data, n_keep).tolist())
    except StreamError as exc:
        return ("error", str(exc))


def _ints(data: bytes, count: int, big: bool) -> np.ndarray:
    raw = np.frombuffer(data[: 8 * count].ljust(8 * count, b"\0"), dtype="<i8")
    return raw % (2**41 - 1) - (2**40 - 1) if big else raw % 9 - 4


def one_input(data: bytes) -> None:
    if len(data) < 2:
        return
    if data[0] & 1:  # encoder: up to 48 indices, small (|q| <= 4) or up to the 2^40 bound
        q = _ints(data[2:], data[1] % 49, bool(data[0] & 2))
        enc = rangecoder.encode_indices_py(q)
        assert rangecoder.encode_indices_c(q) == enc, q
        assert np.array_equal(rangecoder.decode_indices_c(enc, q.size), q)
        return
    n_keep = int.from_bytes(data[:2], "little") % 1024
    payload = data[2:]
    c = _outcome(rangecoder.decode_indices_c, payload, n_keep)
    assert c == _outcome(rangecoder.decode_indices_py, payload, n_keep), (payload.hex(), n_keep, c)


def random_run(count: int) -> None:
    """`count` random inputs: garbage, and real index streams truncated, flipped or extended."""
    r = np.random.default_rng(int.from_bytes(os.urandom(8), "little"))
    for i in range(count):
        kind = i % 3
        if kind == 0:
            one_input(r.bytes(int(r.integers(2, 64))))
        elif kind == 1:
            one_input(bytes([1 | (2 if r.random() < 0.2 else 0), int(r.integers(0, 49))])
                      + r.bytes(400))
        else:
            q = (r.integers(-3, 4, int(r.integers(1, 300))) * (r.random(1) < 0.5)).astype(np.int64)
            q[r.random(q.size) < 0.02] = r.integers(-(2**40) + 1, 2**40, 1)
            good = bytearray(rangecoder.encode_indices_py(q) or b"\0")
            good[int(r.integers(0, len(good)))] ^= 1 << int(r.integers(0, 8))
            cut = bytes(good[: int(r.integers(0, len(good) + 1))]) + r.bytes(int(r.integers(0, 4)))
            n_keep = max(0, q.size + int(r.integers(-3, 4)))
            one_input(n_keep.to_bytes(2, "little") + cut)
    print(f"{count} random inputs: the compiled and the reference coder agreed on every one")


def main() -> None:
    if RANDOM:
        random_run(int(sys.argv[2]))
        return
    atheris.Setup(sys.argv, one_input)
    atheris.Fuzz()


if __name__ == "__main__":
    main()
