"""Coverage-guided fuzzing (atheris) of the Python paths that read device bytes, differential
where two implementations exist:

- hostd.device.fastlink.decode (the compiled _fastlink.decode_fixed when built) against
  hostd.device.protocol.decode (the reference): the same (name, fields) or the same ProtocolError;
- protocol.Deframer.feed (serial framing: COBS + CRC-16, resync) over the input cut into reads:
  every message it yields decodes or raises ProtocolError, bad frames are counted, its buffer
  stays bounded (4 x MAX_FRAME + one read);
- half of the inputs are framed first (a valid COBS frame with a valid CRC), so the fuzzer gets
  past the CRC to the message decoders.

    pip install atheris
    python tests/fuzz/fuzz_device_link.py -atheris_runs=1000000 [corpus_dir]
    tests/fuzz/sanitize_device_link.sh -atheris_runs=1000000 [corpus_dir]   # _fastlink.c under ASan + UBSan

Anything but ProtocolError (another exception, a divergence, a hang) is a finding. The compiled
C parsers also have libFuzzer harnesses under ASan + UBSan (tests/fuzz/run_fuzzers.sh).
"""

import importlib.machinery
import importlib.util
import math
import os
import sys

import atheris

if os.environ.get("HOSTD_FASTLINK_SO"):  # a sanitizer build (tests/fuzz/sanitize_device_link.sh)
    _loader = importlib.machinery.ExtensionFileLoader("hostd.device._fastlink",
                                                      os.environ["HOSTD_FASTLINK_SO"])
    _so = importlib.util.module_from_spec(importlib.util.spec_from_loader(_loader.name, _loader))
    _loader.exec_module(_so)
    sys.modules[_loader.name] = _so  # what hostd.compiled.load imports

with atheris.instrument_imports(include=["hostd.device"]):
    from hostd.device import fastlink
    from hostd.device import protocol as pr

# a differential needs both: the reference against itself would find nothing
if fastlink.IMPLEMENTATION != "c" or (os.environ.get("HOSTD_FASTLINK_SO") and fastlink._C is not _so):
    sys.exit("fuzz_device_link: the compiled _fastlink is not in use (build it: python setup.py build_ext "
             "--inplace; HOSTD_PURE_PYTHON unset)")
print(f"fuzz_device_link: protocol.decode against {fastlink._C.__file__}", file=sys.stderr)

READ = 4096


def _same(a, b) -> bool:
    if isinstance(a, float) and isinstance(b, float):
        return a == b or (math.isnan(a) and math.isnan(b))
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, list | tuple):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    return type(a) is type(b) and a == b


def _decode_both(msg: bytes) -> None:
    try:
        want = pr.decode(msg)
    except pr.ProtocolError as e:
        want = ("error", str(e))
    try:
        got = fastlink.decode(msg)
    except pr.ProtocolError as e:
        got = ("error", str(e))
    if not _same(want, got):
        raise AssertionError(f"divergence on {msg.hex()}: reference {want!r}, "
                             f"{fastlink.IMPLEMENTATION} {got!r}")


def one_input(data: bytes) -> None:
    if not data:
        return
    mode, data = data[0], data[1:]
    if mode & 1:  # a message as is (a HID report is one message)
        _decode_both(data)
        return
    if mode & 2:  # a valid frame of it, then the rest of the input
        cut = (mode >> 2) % (len(data) + 1)
        data = pr.frame(data[:cut]) + data[cut:]
    d = fastlink.deframer()  # what the daemon runs (compiled when built)
    at = 0
    step = 1 + (mode >> 3) * 97
    while at < len(data):
        for msg in d.feed(data[at:at + step]):
            _decode_both(msg)
        at += step
        assert len(d._buf) <= 4 * pr.Deframer.MAX_FRAME + READ


def main() -> None:
    atheris.Setup(sys.argv, one_input)
    atheris.Fuzz()


if __name__ == "__main__":
    main()
