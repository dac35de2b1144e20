"""USB HID backend through hidapi (`import hid`): one message per 64-byte report.

hidapi's write() takes the report ID as the first byte; the display uses no report IDs, so
every report is sent as 0x00 + 64 bytes. Reads return up to 64 bytes (no report ID).
"""

from __future__ import annotations

from hostd.device import protocol as pr
from hostd.device.transport import Transport, os_error
from hostd.errors import DeviceGone, DeviceNotFound, DevicePermission


def _hid():
    try:
        import hid
    except ImportError as e:  # the package or the system library is missing
        raise DeviceNotFound(f"HID backend unavailable ({e}); pip install 'hostd[device]'") from None
    return hid


def enumerate_specs() -> list[str]:
    hid = _hid()
    return [f"hid:{d['path'].decode(errors='replace')}" for d in hid.enumerate(pr.USB_VID, pr.USB_PID)]


class HidTransport(Transport):
    name = "hid"

    def __init__(self, path: str | None = None, hid_module=None) -> None:
        hid = hid_module or _hid()
        if path is None:
            devs = hid.enumerate(pr.USB_VID, pr.USB_PID)
            if not devs:
                seen = sorted({f"{d['vendor_id']:04x}:{d['product_id']:04x}" for d in hid.enumerate()})
                raise DeviceNotFound(f"no HID display {pr.USB_VID:04x}:{pr.USB_PID:04x} "
                                     f"(HID devices seen: {', '.join(seen) or 'none'})")
            path_b = devs[0]["path"]
        else:
            path_b = path.encode()
        self.path = path_b.decode(errors="replace")
        self.dev = hid.device()
        try:
            self.dev.open_path(path_b)
        except OSError as e:
            # hidapi raises a bare OSError('open failed'): tell permission from absence
            import os

            p = self.path
            if p.startswith("/dev/") and os.path.exists(p) and not os.access(p, os.R_OK | os.W_OK):
                raise DevicePermission(f"permission denied on {self.path}: "
                                       f"{os_error(PermissionError(13, 'denied'), self.path)}") from None
            raise DeviceNotFound(f"cannot open HID device {self.path} ({e})") from None
        self.dev.set_nonblocking(False)

    def send(self, msg: bytes) -> None:
        report = b"\x00" + pr.pad_report(msg)
        try:
            n = self.dev.write(report)
        except OSError as e:
            raise os_error(e, f"HID {self.path}") from None
        if n < 0:
            raise DeviceGone(f"HID {self.path}: write failed (unplugged?); hostd reconnects when it returns")

    def recv(self, timeout_s: float = 0.0) -> bytes | None:
        try:
            data = self.dev.read(pr.REPORT_SIZE, int(timeout_s * 1000))
        except OSError as e:
            raise os_error(e, f"HID {self.path}") from None
        if not data:
            return None
        return bytes(data)

    def close(self) -> None:
        try:
            self.dev.close()
        except OSError:
            pass

    def describe(self) -> str:
        return f"hid:{self.path}"
