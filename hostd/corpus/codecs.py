"""The codec protocol of `hostd corpus` (and of `hostd bench codec --peers`): how any codec,
hostd's own streams, a reference program or a researcher's function, is run and scored alike.

A codec is an object with:

    name: str                  short and stable ("hostd-v2", "mpeg-rm", "my-lab-dpcm"); rows
                               and BD-rate tables name it
    version: str               changes whenever the bytes it writes may change; it is part of
                               every row's key, so a new version is evaluated afresh
    settings: Sequence[dict]   its default sweep: one dict of keyword arguments per point,
                               from coarse to fine (e.g. [{"levels": 4}, {"levels": 8}, ...]);
                               values are str, int, float or bool (they are hashed as JSON)

    encode(heights_um, spacing_um, **setting) -> bytes
    decode(data, n, spacing_um, **setting) -> numpy array of n heights, µm

and optionally

    curve(setting) -> str      which rate-quality curve of this codec a setting belongs to
                               (hostd-v2 has one per method: "shaped", "quant", "cut");
                               default: one curve per codec
    available() -> str | None  None when it can run here, else a one-line reason with what
                               to do ("binary missing: set HOSTD_PEER_VCPWQ or ..."); every
                               job of an unavailable codec becomes a row with that error
                               (reason "unavailable") instead of failing the run
    encode_decode(heights_um, spacing_um, **setting) -> (bytes, heights)
                               for programs that only encode and decode in one go; when
                               present it is used instead of encode + decode, and its CPU time
                               is reported as the encode time (decode time is NaN)

What goes in:
- `heights_um`: float64 array of the patch's N heights in micrometres (uniform grid, the
  texture's loader options already applied: units, resampling, offset, length, detrend); a
  codec must not modify it (it is read-only).
- `spacing_um`: the grid spacing in µm (patch length L = N spacing).
- `setting`: one entry of the sweep, plus the geometry keywords that are ALWAYS passed to
  encode, decode and encode_decode: `speed_mm_s` (reference hand speed v) and `fmax_hz`
  (band limit at v). A codec that does not use them accepts them through `**_`. A codec that
  works on time signals derives them from these (the stroke lasts L / v seconds).
What comes out:
- `encode` returns the complete bytes a receiver needs (side information the decoder needs,
  such as a scale factor, belongs in them: only `len(bytes)` is counted as the rate);
- `decode` returns the reconstruction on the same grid: exactly n finite heights in µm.
  A wrong length, NaN/Inf, or anything that is not bytes is an error row
  ("wrong_length", "nonfinite", "bad_output"), not a crash.
- exceptions: any exception is an error row with its one-line text (reason "codec_error");
  raise `Unavailable` from encode for "this cannot run here".

How it is scored (the same for every codec, hostd's included): the reconstruction's DCT-II
amplitudes C'_k, k = 1..N', N' = the largest k with f_k = k v / (2L) <= fmax (DC dropped, as
hostd's streams do), against the original's C_k: Ip, Ia, Iobj = a Ip + b Ia with the
detection threshold b(f_k) (hostd.perception.indices), and SPQI of the signal a hand at v feels
(hostd.perception.peer.played_spqi). Rate: bits per mm = 8 bytes / L and bits per second of
stroke = 8 bytes v / L.

CPU time: the driver measures each call as process CPU time (time.process_time) plus the CPU
time of child processes that ended during the call (resource.getrusage(RUSAGE_CHILDREN)), so
a codec that runs an external program (and waits for it) is measured with it.

Naming a codec: `hostd-v1` / `hostd-v2` (alias v1, v2) are hostd's streams; `mpeg-rm`,
`mpeg-rm-cf0` (the MPEG-I Haptics reference software: the standard's codec) and `vc-pwq` (a
research codec, CC BY-NC) are the peers of hostd.corpus.peercodecs; anything else is
"module:attr" (an importable module) or "path/to/file.py:attr". `attr` is a codec object, or
a class or function called with no arguments that returns one. The name is resolved again in
every worker process, so the module must be importable there (same PYTHONPATH, or a file path
the workers can read).

A minimal external codec (tests/corpus_codec_fixture.py is a complete one):

    class Uniform:
        name, version = "uniform-zlib", "1"
        settings = [{"step_um": s} for s in (4.0, 2.0, 1.0, 0.5)]
        def encode(self, heights_um, spacing_um, *, step_um, **_):
            q = np.rint(heights_um / step_um).astype("<i4")
            return struct.pack("<d", step_um) + zlib.compress(q.tobytes())
        def decode(self, data, n, spacing_um, **_):
            (step,) = struct.unpack_from("<d", data)
            return np.frombuffer(zlib.decompress(data[8:]), "<i4").astype(float) * step
"""

from __future__ import annotations

import importlib
import importlib.util
import json
import math
import os
import resource
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np

from hostd.codec import formats as _formats
from hostd.errors import HostdError

GEOMETRY_KEYS = ("speed_mm_s", "fmax_hz")


class CodecFailure(HostdError):
    """A codec raised, hung, or returned something unusable; `reason` is the summary's bucket."""

    reason = "codec_error"

    def __init__(self, message: str, reason: str | None = None) -> None:
        super().__init__(message)
        if reason is not None:
            self.reason = reason


class Unavailable(CodecFailure):
    """The codec cannot run on this machine (a program or package is missing): what to do."""

    reason = "unavailable"


@runtime_checkable
class Codec(Protocol):
    name: str
    version: str
    settings: Sequence[Mapping[str, Any]]

    def encode(self, heights_um: np.ndarray, spacing_um: float, **setting: Any) -> bytes: ...

    def decode(self, data: bytes, n: int, spacing_um: float, **setting: Any) -> np.ndarray: ...


# ----------------------------------------------------------------------------- settings


def setting_json(setting: Mapping[str, Any]) -> str:
    """The canonical text of a setting (sorted keys, no spaces): hashed into the row's key."""
    for k, v in setting.items():
        if not isinstance(v, str | int | float | bool) or (isinstance(v, float) and not math.isfinite(v)):
            raise HostdError(f"setting {k}={v!r}: values must be finite numbers, text or booleans")
    return json.dumps(dict(setting), sort_keys=True, separators=(",", ":"))


def curve_of(codec: Codec, setting: Mapping[str, Any]) -> str:
    """The curve label `codec/curve` a setting's point belongs to (for reports)."""
    fn = getattr(codec, "curve", None)
    sub = fn(setting) if callable(fn) else ""
    return f"{codec.name}/{sub}" if sub else codec.name


def unavailable_reason(codec: Codec) -> str | None:
    fn = getattr(codec, "available", None)
    if not callable(fn):
        return None
    try:
        return fn()
    except Exception as exc:  # a broken availability probe is itself a reason not to run
        return f"{codec.name}: available() raised {type(exc).__name__}: {exc}"


# ----------------------------------------------------------------------------- running a codec


def cpu_now_s() -> float:
    """Process CPU time plus that of finished (waited-for) child processes, seconds."""
    ch = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + ch.ru_utime + ch.ru_stime


@dataclass
class Coded:
    data: bytes
    reconstruction_um: np.ndarray
    encode_cpu_s: float
    decode_cpu_s: float


def check_reconstruction(codec_name: str, rec: Any, n: int) -> np.ndarray:
    """The decoder's output as float64 of n finite heights, or a CodecFailure saying why not."""
    try:
        y = np.asarray(rec, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise CodecFailure(f"{codec_name} decode returned {type(rec).__name__}, not an array of "
                           f"heights ({exc})", "bad_output") from None
    if y.ndim != 1 or y.size != n:
        raise CodecFailure(f"{codec_name} decode returned shape {y.shape}, expected ({n},): one "
                           "height per input sample", "wrong_length")
    bad = np.count_nonzero(~np.isfinite(y))
    if bad:
        raise CodecFailure(f"{codec_name} decode returned {bad} NaN/Inf heights of {n}", "nonfinite")
    return y


def _as_bytes(codec_name: str, data: Any) -> bytes:
    if isinstance(data, bytes | bytearray | memoryview):
        return bytes(data)
    raise CodecFailure(f"{codec_name} encode returned {type(data).__name__}, not bytes", "bad_output")


def run_codec(codec: Codec, heights_um: np.ndarray, spacing_um: float, setting: Mapping[str, Any],
              geometry: Mapping[str, float]) -> Coded:
    """Encode and decode once through the protocol, timed and checked."""
    y = np.array(heights_um, dtype=np.float64)
    y.flags.writeable = False
    kw = {**setting, **geometry}
    both = getattr(codec, "encode_decode", None)
    t0 = cpu_now_s()
    if callable(both):
        out = both(y, float(spacing_um), **kw)
        t1 = cpu_now_s()
        if not (isinstance(out, tuple) and len(out) == 2):
            raise CodecFailure(f"{codec.name} encode_decode must return (bytes, heights)", "bad_output")
        data = _as_bytes(codec.name, out[0])
        return Coded(data, check_reconstruction(codec.name, out[1], y.size), t1 - t0, math.nan)
    data = _as_bytes(codec.name, codec.encode(y, float(spacing_um), **kw))
    t1 = cpu_now_s()
    rec = codec.decode(data, int(y.size), float(spacing_um), **kw)
    t2 = cpu_now_s()
    return Coded(data, check_reconstruction(codec.name, rec, y.size), t1 - t0, t2 - t1)


# ----------------------------------------------------------------------------- naming codecs


# hostd's own stream formats (hostd.codec.formats), as hostd-NAME or NAME
BUILTIN = {alias: name for name in _formats.FORMATS for alias in (f"hostd-{name}", name)}
# the peers of hostd.corpus.peercodecs by their short names (each runs only when its programs are
# present; otherwise its rows are "unavailable" with what to do)
PEERS = {"mpeg-rm": "hostd.corpus.peercodecs:MpegRm", "mpeg-rm-cf0": "hostd.corpus.peercodecs:MpegRmCf0",
         "vc-pwq": "hostd.corpus.peercodecs:VcPwq"}


@lru_cache(maxsize=64)
def resolve(spec: str) -> Codec:
    """The codec a name stands for (see the module docstring); cached per process."""
    spec = spec.strip()
    spec = PEERS.get(spec, spec)
    if spec in BUILTIN:
        from hostd.corpus.hostdcodec import HostdStream

        return HostdStream(BUILTIN[spec])
    target, sep, attr = spec.rpartition(":")
    if not sep or not target or not attr:
        raise HostdError(f"codec {spec!r}: use hostd-v1, hostd-v2, {', '.join(PEERS)}, module:attr or "
                         "file.py:attr")
    try:
        if target.endswith(".py"):
            path = Path(target).resolve()
            mod_name = f"hostd_corpus_ext_{abs(hash(str(path))):x}"
            mod = sys.modules.get(mod_name)
            if mod is None:
                if not path.is_file():
                    raise HostdError(f"codec {spec!r}: no file {path}")
                s = importlib.util.spec_from_file_location(mod_name, path)
                mod = importlib.util.module_from_spec(s)
                sys.modules[mod_name] = mod
                s.loader.exec_module(mod)
        else:
            mod = importlib.import_module(target)
        obj = getattr(mod, attr)
    except HostdError:
        raise
    except Exception as exc:
        raise HostdError(f"codec {spec!r} cannot be loaded: {type(exc).__name__}: {exc} (is the "
                         f"module on PYTHONPATH = {os.environ.get('PYTHONPATH', '')!r}?)") from None
    if not _is_codec(obj) and callable(obj):
        try:
            obj = obj()
        except Exception as exc:
            raise HostdError(f"codec {spec!r}: calling {attr}() raised {type(exc).__name__}: {exc}") from None
    if not _is_codec(obj):
        raise HostdError(f"codec {spec!r} is not a codec: it needs name, version, settings, encode "
                         "and decode (see hostd/corpus/codecs.py)")
    return obj


def _is_codec(obj: Any) -> bool:
    return (not isinstance(obj, type) and isinstance(getattr(obj, "name", None), str)
            and isinstance(getattr(obj, "version", None), str)
            and callable(getattr(obj, "encode", None)) and callable(getattr(obj, "decode", None)))
