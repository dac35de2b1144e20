"""The device protocol: constants and layouts from protocol.toml, messages, serial framing.

Messages are transport-neutral byte strings (layouts in protocol.toml and docs/protocol.md).
Over USB each message is one 64-byte HID/interrupt report, zero-padded. Over a serial
bridge each message is framed as COBS(message + CRC-16/CCITT-FALSE, little-endian) + 0x00.
"""

from __future__ import annotations

import binascii
import struct
import tomllib
from dataclasses import dataclass
from pathlib import Path

from cobs import cobs

from hostd.errors import HostdError

SPEC_PATH = Path(__file__).with_name("protocol.toml")
SPEC = tomllib.loads(SPEC_PATH.read_text())
P = SPEC["protocol"]
IDS: dict[str, int] = SPEC["ids"]
NAMES: dict[int, str] = {v: k for k, v in IDS.items()}
STATES: dict[str, int] = SPEC["states"]
FAULTS: dict[str, int] = SPEC["faults"]

VERSION: int = P["version"]
REPORT_SIZE: int = P["report_size"]
MAX_SAMPLES: int = P["max_samples"]
SAMPLE_RATE_HZ: int = P["sample_rate_hz"]
BUFFER_CAPACITY: int = P["buffer_capacity"]
LIMIT_CODE: int = P["limit_code"]
MAX_STEP_CODE: int = P["max_step_code"]
USB_VID: int = P["usb_vid"]
USB_PID: int = P["usb_pid"]

_TYPES = {"u8": "B", "u16": "H", "u32": "I", "i16": "h"}


class ProtocolError(HostdError):
    """A message or frame that does not follow the protocol (dropped and counted)."""


@dataclass(frozen=True)
class Layout:
    name: str
    fields: tuple[tuple[str, str], ...]  # (name, struct code) of the fixed part
    fixed: struct.Struct
    variable: bool  # trailing i16 array (SAMPLES)

    @property
    def names(self) -> tuple[str, ...]:
        return _NAMES_CACHE.setdefault(self.name, tuple(f for f, _ in self.fields))

    @property
    def size(self) -> int:
        return self.fixed.size


def _layout(name: str, spec: list[str]) -> Layout:
    fields = []
    variable = False
    for item in spec:
        fname, ftype = item.split(":")
        if ftype.endswith("[]"):
            variable = True
            continue
        fields.append((fname, _TYPES[ftype]))
    return Layout(name, tuple(fields), struct.Struct("<" + "".join(c for _, c in fields)), variable)


_NAMES_CACHE: dict[str, tuple[str, ...]] = {}
LAYOUTS: dict[str, Layout] = {k: _layout(k, v) for k, v in SPEC["layouts"].items()}


def encode(name: str, **fields) -> bytes:
    """Build a message; `codes` (a sequence of ints) for SAMPLES."""
    lay = LAYOUTS[name]
    values = []
    for fname, _ in lay.fields:
        if fname == "id":
            values.append(IDS[name])
        elif fname == "count" and lay.variable:
            values.append(len(fields.get("codes", ())))
        else:
            values.append(int(fields.get(fname, 0)))
    try:
        head = lay.fixed.pack(*values)
    except struct.error as e:
        raise ProtocolError(f"{name}: a field is out of range ({e})") from None
    if lay.variable:
        codes = [int(c) for c in fields.get("codes", ())]
        if len(codes) > MAX_SAMPLES:
            raise ProtocolError(f"SAMPLES holds at most {MAX_SAMPLES} samples, got {len(codes)}")
        head += struct.pack(f"<{len(codes)}h", *codes)
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
        if n > MAX_SAMPLES:
            raise ProtocolError(f"SAMPLES count {n} > {MAX_SAMPLES}")
        end = lay.size + 2 * n
        if len(msg) < end:
            raise ProtocolError(f"SAMPLES with {n} samples needs {end} bytes, got {len(msg)}")
        out["codes"] = list(struct.unpack_from(f"<{n}h", msg, lay.size))
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
    """Accumulates serial bytes; yields complete messages, counting bad frames."""

    MAX_FRAME = REPORT_SIZE + 8

    def __init__(self) -> None:
        self._buf = bytearray()
        self.bad_frames = 0

    def feed(self, data: bytes) -> list[bytes]:
        out = []
        self._buf += data
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
