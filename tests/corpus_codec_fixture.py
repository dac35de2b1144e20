"""External codecs for tests/test_corpus.py, written as a researcher would (hostd.corpus.codecs):
a plain uniform quantizer with zlib, and codecs that misbehave in each way the driver must
survive (raise, hang, wrong length, NaN, not installed)."""

from __future__ import annotations

import os
import struct
import time
import zlib
from pathlib import Path

import numpy as np


class UniformZlib:
    """Heights rounded to multiples of step_um, as int32, zlib-compressed; the step travels in
    the first 8 bytes (the decoder needs it, so it is counted)."""

    name = "uniform-zlib"
    version = "1"
    settings = tuple({"step_um": s} for s in (2.0, 1.0, 0.5, 0.25, 0.125))
    pad = 0.0  # a test's "new version" that wastes this fraction of the bytes (zero bytes appended)

    def encode(self, heights_um, spacing_um, *, step_um, **_):
        q = np.rint(np.asarray(heights_um) / step_um).astype("<i4")
        data = struct.pack("<d", step_um) + zlib.compress(q.tobytes(), 9)
        return data + bytes(round(self.pad * len(data)))

    def decode(self, data, n, spacing_um, **_):
        (step,) = struct.unpack_from("<d", data)
        return np.frombuffer(zlib.decompress(data[8:]), "<i4").astype(np.float64) * step


uniform = UniformZlib  # "tests.corpus_codec_fixture:uniform": a class, called with no arguments


class Misbehaving(UniformZlib):
    """setting fault = none | raise | hang | short | nan | str | deaf (hangs where no time limit
    inside the process reaches it: SIGALRM blocked, waiting in C)."""

    name = "misbehaving"
    settings = tuple({"step_um": 1.0, "fault": f} for f in ("none", "raise", "hang", "short", "nan", "str"))

    def encode(self, heights_um, spacing_um, *, fault="none", **kw):
        if fault == "raise":
            raise ValueError("this codec always fails on fault=raise")
        if fault == "hang":
            while True:
                time.sleep(0.01)
        if fault == "deaf":
            import signal

            signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGALRM})
            time.sleep(3600)
        if fault == "str":
            return "not bytes"
        return super().encode(heights_um, spacing_um, **kw)

    def decode(self, data, n, spacing_um, *, fault="none", **kw):
        y = super().decode(data, n, spacing_um, **kw)
        if fault == "short":
            return y[:-1]
        if fault == "nan":
            y = y.copy()
            y[3] = np.nan
        return y


class NotInstalled(UniformZlib):
    name = "not-installed"

    def available(self):
        return "binary missing: set HOSTD_TEST_CODEC to the encoder (this fixture never has one)"


class Gated(UniformZlib):
    """The uniform quantizer behind a gate the test holds: with HOSTD_TEST_GATE=DIR:N in the
    environment, N encodes (over all worker processes) pass, the rest wait until DIR/open exists
    (a run that is surely still going when the test stops it, however slow the machine)."""

    name = "gated-uniform"
    settings = tuple({"step_um": s} for s in (2.0, 1.0, 0.5, 0.25))

    def encode(self, heights_um, spacing_um, **kw):
        gate = os.environ.get("HOSTD_TEST_GATE")
        if gate:
            d, n = gate.rsplit(":", 1)
            for i in range(int(n)):  # one pass token each, taken once across processes
                try:
                    os.close(os.open(Path(d) / f"pass-{i}", os.O_CREAT | os.O_EXCL | os.O_WRONLY))
                    break
                except FileExistsError:
                    continue
            else:
                t_end = time.monotonic() + 600.0
                while not (Path(d) / "open").exists() and time.monotonic() < t_end:
                    time.sleep(0.01)
        return super().encode(heights_um, spacing_um, **kw)


class Slow(UniformZlib):
    """The uniform quantizer, waiting `delay_s` (wall time, not CPU) per encode: a run long enough
    to be killed in the middle."""

    name = "slow-uniform"
    settings = tuple({"step_um": s, "delay_s": 0.05} for s in (2.0, 1.0, 0.5, 0.25))

    def encode(self, heights_um, spacing_um, *, delay_s=0.05, **kw):
        time.sleep(delay_s)
        return super().encode(heights_um, spacing_um, **kw)
