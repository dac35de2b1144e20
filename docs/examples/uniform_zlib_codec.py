"""An external codec for `hostd corpus run --codec docs/examples/uniform_zlib_codec.py:UniformZlib`
(the protocol: hostd/corpus/codecs.py, docs/corpus.md): heights rounded to multiples of
step_um, stored as int32 and zlib-compressed; the step travels in the first 8 bytes."""

import struct
import zlib

import numpy as np


class UniformZlib:
    name = "uniform-zlib"
    version = "1"  # change it when the bytes change: it is part of every row's key
    settings = tuple({"step_um": s} for s in (2.0, 1.0, 0.5, 0.25, 0.125, 0.0625))

    def encode(self, heights_um, spacing_um, *, step_um, **_):
        q = np.rint(np.asarray(heights_um) / step_um).astype("<i4")
        return struct.pack("<d", step_um) + zlib.compress(q.tobytes(), 9)

    def decode(self, data, n, spacing_um, **_):
        (step,) = struct.unpack_from("<d", data)
        return np.frombuffer(zlib.decompress(data[8:]), "<i4").astype(np.float64) * step
