"""The device link's per-message work on the real-time path: decode what the device sends
(a STATUS every millisecond) and encode SAMPLES, by the compiled hostd/device/_fastlink.c
when it is built, else by hostd.device.protocol (the reference: same fields, same bytes).

The compiled module gets the layouts from protocol.toml at import, so it follows a layout
change; it declines (None) anything unusual (a short message, garbage after it, a value out
of range) and the reference then gives the result or the ProtocolError with its message.
HOSTD_PURE_PYTHON=1 (any value but 0) selects the reference, as for the range coder.
"""

from __future__ import annotations

from hostd.compiled import load as load_compiled
from hostd.device import protocol as pr

C_REVISION = 1  # _fastlink.c's REVISION this module is written for
_CODES = set("BHIbhif")


def _load_compiled():
    _fastlink = load_compiled("hostd.device._fastlink", C_REVISION)
    if _fastlink is None:
        return None
    s = pr.LAYOUTS["SAMPLES"]
    if [c for _, c in s.fields] != ["B", "B", "H", "B"] or s.var_code != "h" or \
            [f for f, _ in s.fields] != ["id", "flags", "seq", "count"]:
        return None  # SAMPLES changed shape: the compiled encoder no longer applies
    _fastlink.init(pr.IDS["SAMPLES"], s.var_max)
    return _fastlink


_C = _load_compiled()
IMPLEMENTATION = "c" if _C is not None else "python"
# device mode's sleep over a byte stream (SerialTransport.gather), when this build has it
GATHER = getattr(_C, "gather", None)
# protocol.Deframer's loop (serial framing), when this build has it
DEFRAME = getattr(_C, "deframe", None)
# message id -> (name, struct codes, field names) of the fixed layouts the compiled decoder reads
_FIXED = {pr.IDS[name]: (name, "".join(c for _, c in lay.fields).encode(), lay.names)
          for name, lay in pr.LAYOUTS.items()
          if not lay.variable and all(c in _CODES for _, c in lay.fields)}


def decode(msg: bytes) -> tuple[str, dict]:
    """protocol.decode(msg): (name, fields), or ProtocolError."""
    if _C is not None and msg:
        spec = _FIXED.get(msg[0])
        if spec is not None:
            f = _C.decode_fixed(msg, spec[1], spec[2])
            if f is not None:
                return spec[0], f
    return pr.decode(msg)


def encode_samples(seq: int, codes) -> bytes:
    """protocol.encode("SAMPLES", seq=seq, codes=codes); codes an int16 array is the fast case."""
    if _C is not None and getattr(codes, "dtype", None) == "int16":
        m = _C.encode_samples(int(seq), codes)
        if m is not None:
            return m
    return pr.encode("SAMPLES", seq=seq, codes=codes)


def deframer() -> pr.Deframer:
    """A serial deframer: the compiled loop when this build has it (HOSTD_PURE_PYTHON=1: the
    reference), protocol.Deframer's otherwise."""
    return pr.Deframer(compiled=DEFRAME)
