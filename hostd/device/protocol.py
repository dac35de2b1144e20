"""The device protocol: constants and layouts from protocol.toml, messages, serial framing.

Messages are transport-neutral byte strings (layouts in protocol.toml and docs/protocol.md).
Over USB each message is one 64-byte HID/interrupt report, zero-padded. Over a serial
bridge each message is framed as COBS(message + CRC-16/CCITT-FALSE, little-endian) + 0x00.
"""

from __future__ import annotations

import binascii
import math
import struct
import tomllib
import zlib
from dataclasses import dataclass
from pathlib import Path

from cobs import cobs

from hostd.errors import DeviceVersion, HostdError

SPEC_PATH = Path(__file__).with_name("protocol.toml")
SPEC = tomllib.loads(SPEC_PATH.read_text())
P = SPEC["protocol"]
IDS: dict[str, int] = SPEC["ids"]
NAMES: dict[int, str] = {v: k for k, v in IDS.items()}
STATES: dict[str, int] = SPEC["states"]
FAULTS: dict[str, int] = SPEC["faults"]

VERSION: int = P["version"]
MIN_VERSION: int = P["min_version"]
R = SPEC["render"]
RENDER_STATES: dict[str, int] = SPEC["render_states"]
RESULTS: dict[str, int] = SPEC["results"]
RESULT_NAMES: dict[int, str] = {v: k for k, v in RESULTS.items()}
REPORT_SIZE: int = P["report_size"]
MAX_SAMPLES: int = P["max_samples"]
SAMPLE_RATE_HZ: int = P["sample_rate_hz"]
BUFFER_CAPACITY: int = P["buffer_capacity"]
LIMIT_CODE: int = P["limit_code"]
MAX_STEP_CODE: int = P["max_step_code"]
USB_VID: int = P["usb_vid"]
USB_PID: int = P["usb_pid"]

_TYPES = {"u8": "B", "u16": "H", "u32": "I", "i16": "h", "i32": "i", "f32": "f"}


class ProtocolError(HostdError):
    """A message or frame that does not follow the protocol (dropped and counted)."""


@dataclass(frozen=True)
class Layout:
    name: str
    fields: tuple[tuple[str, str], ...]  # (name, struct code) of the fixed part
    fixed: struct.Struct
    variable: bool  # a trailing array (SAMPLES codes, LOAD_CHUNK coeffs), length in `count`
    var_name: str = ""
    var_code: str = ""

    @property
    def names(self) -> tuple[str, ...]:
        return _NAMES_CACHE.setdefault(self.name, tuple(f for f, _ in self.fields))

    @property
    def size(self) -> int:
        return self.fixed.size

    @property
    def var_max(self) -> int:
        """Most items the trailing array may hold in one report."""
        return (REPORT_SIZE - self.size) // struct.calcsize("<" + self.var_code) if self.variable else 0


def _layout(name: str, spec: list[str]) -> Layout:
    fields = []
    var_name = var_code = ""
    for item in spec:
        fname, ftype = item.split(":")
        if ftype.endswith("[]"):
            var_name, var_code = fname, _TYPES[ftype[:-2]]
            continue
        fields.append((fname, _TYPES[ftype]))
    return Layout(name, tuple(fields), struct.Struct("<" + "".join(c for _, c in fields)), bool(var_name),
                  var_name, var_code)


_NAMES_CACHE: dict[str, tuple[str, ...]] = {}
LAYOUTS: dict[str, Layout] = {k: _layout(k, v) for k, v in SPEC["layouts"].items()}


def encode(name: str, **fields) -> bytes:
    """Build a message; the trailing array by its name (`codes` of SAMPLES, `coeffs` of
    LOAD_CHUNK), its `count` is filled in."""
    lay = LAYOUTS[name]
    values = []
    for fname, code in lay.fields:
        if fname == "id":
            values.append(IDS[name])
        elif fname == "count" and lay.variable:
            values.append(len(fields.get(lay.var_name, ())))
        elif code == "f":
            values.append(float(fields.get(fname, 0.0)))
        else:
            values.append(int(fields.get(fname, 0)))
    try:
        head = lay.fixed.pack(*values)
    except (struct.error, OverflowError) as e:
        raise ProtocolError(f"{name}: a field is out of range ({e})") from None
    if lay.variable:
        conv = float if lay.var_code == "f" else int
        items = [conv(c) for c in fields.get(lay.var_name, ())]
        if len(items) > lay.var_max:
            raise ProtocolError(f"{name} holds at most {lay.var_max} {lay.var_name}, got {len(items)}")
        try:
            head += struct.pack(f"<{len(items)}{lay.var_code}", *items)
        except (struct.error, OverflowError) as e:
            raise ProtocolError(f"{name}: a {lay.var_name} value is out of range ({e})") from None
    return head


def decode(msg: bytes) -> tuple[str, dict]:
    """Parse a message (trailing zero padding allowed, as in a HID report)."""
    if not msg:
        raise ProtocolError("empty message")
    name = NAMES.get(msg[0])
    if name is None:
        raise ProtocolError(f"unknown message id 0x{msg[0]:02x}")
    lay = LAYOUTS[name]
    if len(msg) < lay.size:
        raise ProtocolError(f"{name} needs {lay.size} bytes, got {len(msg)}")
    out = dict(zip(lay.names, lay.fixed.unpack_from(msg), strict=True))
    end = lay.size
    if lay.variable:
        n = out["count"]
        if n > lay.var_max:
            raise ProtocolError(f"{name} count {n} > {lay.var_max}")
        end = lay.size + struct.calcsize(f"<{n}{lay.var_code}")
        if len(msg) < end:
            raise ProtocolError(f"{name} with {n} {lay.var_name} needs {end} bytes, got {len(msg)}")
        out[lay.var_name] = list(struct.unpack_from(f"<{n}{lay.var_code}", msg, lay.size))
    if len(msg) > end and msg[end:] != bytes(len(msg) - end):
        raise ProtocolError(f"{name}: non-zero bytes after the message")
    return name, out


def pad_report(msg: bytes) -> bytes:
    if len(msg) > REPORT_SIZE:
        raise ProtocolError(f"message of {len(msg)} bytes does not fit a {REPORT_SIZE}-byte report")
    return msg + bytes(REPORT_SIZE - len(msg))


def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF), as binascii.crc_hqx computes it."""
    return binascii.crc_hqx(data, 0xFFFF)


def frame(msg: bytes) -> bytes:
    """Serial framing: COBS(msg + CRC16 LE) + 0x00."""
    return cobs.encode(msg + crc16(msg).to_bytes(2, "little")) + b"\x00"


def unframe(body: bytes) -> bytes:
    """One frame's bytes between delimiters -> message; raises ProtocolError."""
    try:
        raw = cobs.decode(body)
    except cobs.DecodeError as e:
        raise ProtocolError(f"bad COBS frame ({e})") from None
    if len(raw) < 3:
        raise ProtocolError("frame too short")
    msg, crc = raw[:-2], int.from_bytes(raw[-2:], "little")
    if crc16(msg) != crc:
        raise ProtocolError("frame CRC mismatch")
    return msg


class Deframer:
    """Accumulates serial bytes; yields complete messages, counting bad frames. The loop below is
    the reference; `compiled` (hostd/device/_fastlink.c's deframe, handed in by
    hostd.device.fastlink.deframer() when it is built) runs the same loop compiled: device mode's
    wake-up then deframes its report pair without Python's per-frame work."""

    MAX_FRAME = REPORT_SIZE + 8

    def __init__(self, compiled=None) -> None:
        self._buf = bytearray()
        self.bad_frames = 0
        self._compiled = compiled

    def feed(self, data: bytes) -> list[bytes]:
        self._buf += data
        if self._compiled is not None:
            out, bad = self._compiled(self._buf, self.MAX_FRAME)
            self.bad_frames += bad
            return out
        out = []
        while True:
            i = self._buf.find(0)
            if i < 0:
                if len(self._buf) > 4 * self.MAX_FRAME:  # no delimiter in sight: resync
                    self._buf.clear()
                    self.bad_frames += 1
                return out
            body = bytes(self._buf[:i])
            del self._buf[: i + 1]
            if not body:
                continue
            try:
                out.append(unframe(body))
            except ProtocolError:
                self.bad_frames += 1


# ---------------------------------------------------------------- version 2: device rendering
assert LAYOUTS["SAMPLES"].var_max == MAX_SAMPLES and LAYOUTS["LOAD_CHUNK"].var_max == R["chunk_coeffs"]


def check_version(ident: dict, who: str = "the display") -> int:
    """The device's protocol version if hostd can stream to it (v1 and v2: stream mode is the
    same in both), else DeviceVersion saying what to update."""
    v = ident["protocol_version"]
    if not MIN_VERSION <= v <= VERSION:
        raise DeviceVersion(f"{who} speaks protocol v{v}, hostd speaks v{MIN_VERSION}..v{VERSION}: "
                            "update the firmware (or hostd) so they match")
    return v


def render_capable(ident: dict, caps: dict | None) -> bool:
    """True when the device can render itself: protocol >= 2 and CAPS with the render bit."""
    return ident.get("protocol_version", 0) >= 2 and caps is not None and bool(caps.get("render", 0) & 1)


# why a display cannot render a texture (render_refusal's first element), in a fixed order:
# the daemon publishes the index (hostd status `render_reason`)
RENDER_REFUSALS = ("v1", "no_caps", "components", "sections")


def render_refusal(ident: dict, caps: dict | None, n_coeffs: int = 1, n_sections: int = 0,
                   who: str = "the display") -> tuple[str, str] | None:
    """None if the device can render this texture, else (one of RENDER_REFUSALS, a message
    saying what to do)."""
    v = ident.get("protocol_version", 0)
    if v < 2:
        return "v1", (f"{who} runs protocol v{v} firmware, which cannot render on the device: "
                      "update its firmware to protocol v2, or set [render] where = \"host\"")
    if not render_capable(ident, caps):
        return "no_caps", (f"{who} did not report render capability (no CAPS with the render bit): "
                           "set [render] where = \"host\", or update its firmware")
    if n_coeffs > caps["max_components"]:
        return "components", (f"{who} renders at most {caps['max_components']} components, the texture "
                              f"has {n_coeffs}: lower the texture's band (fewer components) or render on "
                              "the host")
    if n_sections > caps["max_sections"]:
        return "sections", (f"{who} runs at most {caps['max_sections']} equalizer sections, the equalizer "
                            f"has {n_sections}: lower equalizer.reg_order or render on the host")
    return None


def require_render(ident: dict, caps: dict | None, n_coeffs: int = 1, n_sections: int = 0,
                   who: str = "the display") -> None:
    """Raise DeviceVersion, saying what to do, unless the device can render this texture."""
    why = render_refusal(ident, caps, n_coeffs, n_sections, who)
    if why is not None:
        raise DeviceVersion(why[1])


def f32(values) -> list[float]:
    """Values as the device will hold them (IEEE single precision), as Python floats."""
    vals = list(values)
    return list(struct.unpack(f"<{len(vals)}f", struct.pack(f"<{len(vals)}f", *vals)))


def texture_crc32(coeffs) -> int:
    """CRC-32 (IEEE 802.3, as zlib) over the coefficients as little-endian float32."""
    vals = list(coeffs)
    return zlib.crc32(struct.pack(f"<{len(vals)}f", *vals))


def texture_messages(slot: int, coeffs, n_samples: int, length_mm: float, scale: float = 1.0) -> list[bytes]:
    """LOAD_TEXTURE, the LOAD_CHUNKs and LOAD_END that upload one texture (µm coefficients
    C'_1..C'_N' of a patch of n_samples over length_mm). Raises ProtocolError if it cannot be."""
    c = [float(x) for x in coeffs]
    if not c or len(c) > R["max_components"]:
        raise ProtocolError(f"a texture has 1..{R['max_components']} components, got {len(c)}")
    if not all(math.isfinite(x) for x in c) or not math.isfinite(scale):
        raise ProtocolError("texture coefficients and scale must be finite")
    length_nm = round(length_mm * 1e6)
    if not 0 < length_nm <= R["max_length_nm"]:
        raise ProtocolError(f"texture length must be in (0, {R['max_length_nm'] / 1e6:g}] mm")
    msgs = [encode("LOAD_TEXTURE", slot=slot, n_samples=n_samples, n_coeffs=len(c), length_nm=length_nm,
                   scale=scale, crc32=texture_crc32(c))]
    k = R["chunk_coeffs"]
    for i in range(0, len(c), k):
        msgs.append(encode("LOAD_CHUNK", slot=slot, first=i, coeffs=c[i : i + k]))
    msgs.append(encode("LOAD_END", slot=slot))
    return msgs


def eq_messages(sos) -> list[bytes]:
    """SET_EQ, one per second-order section (rows b0 b1 b2 a0 a1 a2 with a0 = 1); an empty
    sos (equalizer off) sends one SET_EQ with n_sections = 0."""
    rows = [] if sos is None else [list(map(float, r)) for r in sos]
    if not rows:
        return [encode("SET_EQ", index=0, n_sections=0)]
    out = []
    for i, (b0, b1, b2, a0, a1, a2) in enumerate(rows):
        if abs(a0 - 1.0) > 1e-12:
            raise ProtocolError("SET_EQ: sections must be normalized (a0 = 1)")
        out.append(encode("SET_EQ", index=i, n_sections=len(rows), b0=b0, b1=b1, b2=b2, a1=a1, a2=a2))
    return out
