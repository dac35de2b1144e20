"""USB HID backend: one message per 64-byte report.

On Linux the display is talked to through its hidraw node (`/dev/hidrawN`) directly, with usbhid
left bound: found by VID:PID in sysfs (`/sys/class/hidraw/*/device/uevent`, HID_ID), opened
O_RDWR|O_NONBLOCK, written with os.write and read after poll(). Why not hidapi here: the
`hid` module of the PyPI hidapi wheel is hidapi's *libusb* backend on Linux, which detaches
usbhid while open (the hidraw node disappears), names devices `1-1:1.0` and hands zero-length
packets to the reader as empty reports (docs/protocol.md); the same wheel's `hidraw` module
would work, but a report is one read() and one write() on a descriptor, so the kernel's own
interface is fewer layers on the real-time path, gives the pump a descriptor to block on, and
lets the error messages name the node. hidapi (`import hid`) stays for systems without hidraw
(macOS, Windows).

Reports: the display uses no report IDs. Writes carry the report-ID byte 0x00 in front of the
64 bytes (hidraw and hidapi both take the report number first and usbhid strips a 0);
reads return the 64 bytes without it. A zero-length read is not a report (counted in
`empty_reads` and skipped); a short report is passed on as it came (a complete message
without padding decodes, a truncated one is counted as malformed by the link).
"""

from __future__ import annotations

import os
import select
import sys
import time
from pathlib import Path

from hostd.device import protocol as pr
from hostd.device.backend import Transport, os_error, permission_error
from hostd.errors import DeviceBusy, DeviceGone, DeviceNotFound

SYSFS = "/sys"
HID_BUS_USB = 0x0003
READ_SIZE = 4096  # larger than any report: a read never truncates one silently


# ------------------------------------------------------------------ Linux: hidraw
def hidraw_present(sysfs: str = SYSFS) -> bool:
    """Linux: hidraw is the way, even before /sys/class/hidraw exists (the HID modules load
    with the first HID device); elsewhere (macOS, Windows) hidapi."""
    return sys.platform == "linux" or Path(sysfs, "class", "hidraw").is_dir()


def _uevent(path: Path) -> dict[str, str]:
    try:
        text = path.read_text()
    except OSError:
        return {}
    return dict(line.split("=", 1) for line in text.splitlines() if "=" in line)


def parse_hid_id(hid_id: str) -> tuple[int, int, int] | None:
    """HID_ID=0003:00001209:00007470 -> (bus, vid, pid)."""
    try:
        bus, vid, pid = (int(x, 16) for x in hid_id.split(":"))
    except ValueError:
        return None
    return bus, vid, pid


def enumerate_hidraw(sysfs: str = SYSFS) -> list[dict]:
    """Every hidraw node: {"node", "vid", "pid", "name", "serial", "sysfs"}."""
    out = []
    base = Path(sysfs, "class", "hidraw")
    for d in sorted(base.glob("hidraw*"), key=lambda p: (len(p.name), p.name)):
        ids = parse_hid_id(_uevent(d / "device" / "uevent").get("HID_ID", ""))
        if ids is None:
            continue
        hid = _uevent(d / "device" / "uevent")
        devname = _uevent(d / "uevent").get("DEVNAME", d.name)
        try:
            where = str(d.resolve(strict=True))
        except OSError:  # unplugged since the listing (a replug under way): not there
            continue
        out.append({"node": f"/dev/{devname}", "bus": ids[0], "vid": ids[1], "pid": ids[2],
                    "name": hid.get("HID_NAME", ""), "serial": hid.get("HID_UNIQ", ""),
                    "sysfs": where})
    return out


def _is_display(d: dict) -> bool:
    return (d["vid"], d["pid"]) == (pr.USB_VID, pr.USB_PID)


def enumerate_displays(sysfs: str = SYSFS) -> list[dict]:
    """The displays reachable over HID, as {"spec": "hid:/dev/hidrawN", "node", ...}."""
    if hidraw_present(sysfs):
        return [{"spec": f"hid:{d['node']}", **d} for d in enumerate_hidraw(sysfs) if _is_display(d)]
    hid = _hid()
    return [{"spec": f"hid:{d['path'].decode(errors='replace')}", "node": None,
             "serial": d.get("serial_number") or ""} for d in hid.enumerate(pr.USB_VID, pr.USB_PID)]


class HidrawTransport(Transport):
    """The display's /dev/hidrawN, opened non-blocking; reads wait in poll()."""

    name = "hid"

    def __init__(self, node: str | None = None, *, fd: int | None = None, sysfs: str = SYSFS) -> None:
        if fd is None:
            if node is None:
                node = self._find(sysfs)
            else:
                self._check_ids(node, sysfs)
            try:
                fd = os.open(node, os.O_RDWR | os.O_NONBLOCK | os.O_CLOEXEC | os.O_NOCTTY)
            except FileNotFoundError:
                raise DeviceNotFound(f"{node} does not exist (unplugged?); hostd doctor lists the "
                                     "displays it finds") from None
            except OSError as e:
                raise os_error(e, f"HID {node}", node) from None
        os.set_blocking(fd, False)  # (a descriptor handed in, too): reads wait in poll(), never in read()
        self.fd = fd
        self.node = node or f"fd {fd}"
        self.empty_reads = 0  # zero-length reads skipped (not reports)
        self._poll = select.poll()
        self._poll.register(fd, select.POLLIN)

    @staticmethod
    def _find(sysfs: str) -> str:
        devs = enumerate_hidraw(sysfs)
        mine = [d for d in devs if _is_display(d)]
        if not mine:
            seen = sorted({f"{d['vid']:04x}:{d['pid']:04x}" for d in devs})
            raise DeviceNotFound(f"no HID display {pr.USB_VID:04x}:{pr.USB_PID:04x} "
                                 f"(hidraw devices seen: {', '.join(seen) or 'none'})")
        return mine[0]["node"]

    @staticmethod
    def _check_ids(node: str, sysfs: str) -> None:
        """A named node that sysfs says is another device is refused before a byte is written
        to it (a mouse's or a keyboard's hidraw node)."""
        name = os.path.basename(os.path.realpath(node))
        uevent = _uevent(Path(sysfs, "class", "hidraw", name, "device", "uevent"))
        ids = parse_hid_id(uevent.get("HID_ID", ""))
        if ids is not None and (ids[1], ids[2]) != (pr.USB_VID, pr.USB_PID):
            raise DeviceNotFound(f"{node} is {ids[1]:04x}:{ids[2]:04x}, not the display "
                                 f"{pr.USB_VID:04x}:{pr.USB_PID:04x}; hostd doctor lists the displays")

    def _err(self, e: OSError):
        return os_error(e, f"HID {self.node}", self.node if self.node.startswith("/") else None)

    def send(self, msg: bytes) -> None:
        report = b"\x00" + pr.pad_report(msg)
        try:
            n = os.write(self.fd, report)
        except BlockingIOError:
            raise DeviceBusy(f"HID {self.node}: the device is not taking reports (transient; retried)") \
                from None
        except OSError as e:
            raise self._err(e) from None
        if n != len(report):
            raise DeviceBusy(f"HID {self.node}: short write ({n} of {len(report)} bytes); retried")

    def recv(self, timeout_s: float = 0.0) -> bytes | None:
        deadline = time.monotonic() + timeout_s
        empties = 0
        while True:
            try:
                data = os.read(self.fd, READ_SIZE)
            except BlockingIOError:
                data = None
            except OSError as e:
                raise self._err(e) from None
            if data:
                return data
            if data is not None:  # a zero-length packet is not a report
                self.empty_reads += 1
                empties += 1
            left = deadline - time.monotonic()
            ev = self._poll.poll(max(0, int(left * 1000 + 0.999)) if left > 0 else 0)
            if ev and ev[0][1] & (select.POLLHUP | select.POLLERR | select.POLLNVAL):
                raise DeviceGone(f"HID {self.node} went away (hang-up); re-plug it, hostd reconnects")
            if left <= 0 and (not ev or empties > 64):  # (64: an fd that reads empty forever)
                return None

    def fileno(self) -> int:
        return self.fd

    def close(self) -> None:
        fd, self.fd = self.fd, -1
        if fd >= 0:
            try:
                os.close(fd)
            except OSError:
                pass

    def describe(self) -> str:
        return f"hid:{self.node}"


# ------------------------------------------------------------------ elsewhere: hidapi
def _hid():
    try:
        import hid
    except ImportError as e:  # the package or the system library is missing
        from hostd.extras import pip_install

        raise DeviceNotFound(f"HID backend unavailable ({e}); {pip_install('device')}") from None
    return hid


class HidapiTransport(Transport):
    """hidapi's `hid` module, for systems without hidraw (macOS, Windows)."""

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
        self.empty_reads = 0
        self.dev = hid.device()
        try:
            self.dev.open_path(path_b)
        except OSError as e:
            # hidapi raises a bare OSError('open failed'): tell permission from absence
            p = self.path
            if p.startswith("/dev/") and os.path.exists(p) and not os.access(p, os.R_OK | os.W_OK):
                raise permission_error(p) from None
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
        deadline = time.monotonic() + timeout_s
        while True:
            left_ms = max(0, int((deadline - time.monotonic()) * 1000))
            try:
                data = self.dev.read(READ_SIZE, left_ms)
            except OSError as e:
                raise os_error(e, f"HID {self.path}") from None
            if data:
                return bytes(data)
            # nothing within the timeout, or a zero-length packet (not a report): go on waiting
            if left_ms <= 0:
                return None
            self.empty_reads += 1

    def close(self) -> None:
        try:
            self.dev.close()
        except OSError:
            pass

    def describe(self) -> str:
        return f"hid:{self.path}"


def open_hid(path: str | None = None, sysfs: str = SYSFS) -> Transport:
    """The HID transport for this system: hidraw on Linux, hidapi elsewhere."""
    if (path or "").startswith("/dev/") or (path is None and hidraw_present(sysfs)):
        return HidrawTransport(path, sysfs=sysfs)
    return HidapiTransport(path)


# the name the factory and older callers use
HidTransport = open_hid
