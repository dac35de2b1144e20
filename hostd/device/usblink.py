"""Raw USB backend through pyusb, with libusb-package's bundled libusb (no system libusb).

Interface 0's interrupt OUT and IN endpoints as its descriptor gives them (the board port's are 0x01
and 0x81, protocol.toml; a Linux gadget numbers its own), 64-byte packets.

Polite claim: the kernel's HID driver (usbhid) normally has the interface, and a program may
be using the display through it (/dev/hidrawN, e.g. the daemon on `hid`). Detaching usbhid
would pull that node from under it, so when a hidraw node of this device is open in any process
the claim is refused as busy, naming the process. Otherwise usbhid is detached, the interface
claimed, and on close released and usbhid re-attached (the hidraw node comes back). When
another program already claimed the interface through usbfs, the claim fails with EBUSY and the
refusal names what holds /dev/bus/usb/BBB/DDD.
"""

from __future__ import annotations

import errno
import os
import time
from pathlib import Path

from hostd.device import protocol as pr
from hostd.device.backend import GONE_ERRNOS, TRANSIENT_ERRNOS, Transport, permission_error
from hostd.errors import DeviceBusy, DeviceError, DeviceGone, DeviceNotFound

SYSFS = "/sys"
INTERFACE = 0


def _find(find=None, **kw):
    if find is None:
        try:
            import libusb_package
        except ImportError as e:
            from hostd.extras import pip_install

            raise DeviceNotFound(f"USB backend unavailable ({e}); {pip_install('device')}") from None
        find = libusb_package.find
    try:
        return find(**kw)
    except Exception as e:  # usb.core.NoBackendError and friends
        raise DeviceNotFound(f"USB backend unavailable ({e})") from None


def _read(p: Path) -> str:
    try:
        return p.read_text().strip()
    except OSError:
        return ""


def enumerate_usb(sysfs: str = SYSFS) -> list[dict]:
    """Every USB device in sysfs: {"vid", "pid", "bus", "address", "node", "serial", "sysfs"}."""
    out = []
    for d in sorted(Path(sysfs, "bus", "usb", "devices").glob("*")):
        vid, pid = _read(d / "idVendor"), _read(d / "idProduct")
        bus, addr = _read(d / "busnum"), _read(d / "devnum")
        if not (vid and pid and bus and addr):
            continue  # an interface, not a device
        try:
            bus_i, addr_i = int(bus), int(addr)
            out.append({"vid": int(vid, 16), "pid": int(pid, 16), "bus": bus_i, "address": addr_i,
                        "node": f"/dev/bus/usb/{bus_i:03d}/{addr_i:03d}", "serial": _read(d / "serial"),
                        "sysfs": str(d.resolve())})
        except ValueError:
            continue
    return out


def enumerate_displays(find=None, sysfs: str = SYSFS) -> list[dict]:
    """The displays reachable as raw USB devices, as {"spec": "usb:BBB/DDD", "node", ...}."""
    if find is None and Path(sysfs, "bus", "usb", "devices").is_dir():
        devs = [d for d in enumerate_usb(sysfs) if (d["vid"], d["pid"]) == (pr.USB_VID, pr.USB_PID)]
    else:
        devs = [{"bus": d.bus, "address": d.address, "node": f"/dev/bus/usb/{d.bus:03d}/{d.address:03d}"}
                for d in _find(find, find_all=True, idVendor=pr.USB_VID, idProduct=pr.USB_PID) or []]
    return [{"spec": f"usb:{d['bus']:03d}/{d['address']:03d}", **d} for d in devs]


def enumerate_specs(find=None) -> list[str]:
    return [d["spec"] for d in enumerate_displays(find)]


def hidraw_nodes_of(bus: int, address: int, sysfs: str = SYSFS) -> list[str]:
    """The /dev/hidrawN nodes the kernel's HID driver made for this USB device."""
    dev = next((d for d in enumerate_usb(sysfs) if (d["bus"], d["address"]) == (bus, address)), None)
    if dev is None:
        return []
    nodes = []
    for h in Path(sysfs, "class", "hidraw").glob("hidraw*"):
        if str(h.resolve()).startswith(dev["sysfs"] + "/"):
            nodes.append(f"/dev/{h.name}")
    return sorted(nodes)


def holders(nodes: list[str], proc: str = "/proc") -> list[str]:
    """Processes (other than this one) that have one of `nodes` open: "pid 123 (hostd) /dev/x".
    Without root only this user's processes can be seen."""
    want = {os.path.realpath(n) for n in nodes}
    found = []
    for d in Path(proc).glob("[0-9]*"):
        if d.name == str(os.getpid()):
            continue
        try:
            fds = list((d / "fd").iterdir())
        except OSError:
            continue
        for fd in fds:
            try:
                target = os.readlink(fd)
            except OSError:
                continue
            if target in want:
                found.append(f"pid {d.name} ({_read(d / 'comm') or '?'}) {target}")
                break
    return found


class UsbTransport(Transport):
    name = "usb"

    def __init__(self, where: str | None = None, find=None, sysfs: str = SYSFS, proc: str = "/proc",
                 util=None) -> None:
        kw = {"idVendor": pr.USB_VID, "idProduct": pr.USB_PID}
        if where:
            try:
                b, a = where.split("/")
                kw.update(bus=int(b), address=int(a))
            except ValueError:
                raise DeviceError(f"usb:{where}: name the device as usb:BUS/ADDRESS, e.g. usb:001/002 "
                                  "(hostd doctor lists them)") from None
        dev = _find(find, **kw)
        if dev is None:
            seen = _find(find, find_all=True) or []
            ids = sorted({f"{d.idVendor:04x}:{d.idProduct:04x}" for d in seen})
            at = f" at usb:{where}" if where else ""
            raise DeviceNotFound(f"no USB display {pr.USB_VID:04x}:{pr.USB_PID:04x}{at} "
                                 f"(USB devices seen: {', '.join(ids) or 'none'})")
        self.dev = dev
        bus, addr = getattr(dev, "bus", 0) or 0, getattr(dev, "address", 0) or 0
        self.where = f"usb:{bus:03d}/{addr:03d}"
        self.node = f"/dev/bus/usb/{bus:03d}/{addr:03d}"
        self._sysfs, self._proc = sysfs, proc
        if util is None:  # pyusb's usb.util (claim/release/dispose); tests pass a recorder
            import usb.util as util
        self._util = util
        self._detached = self._claimed = False
        self._pending: bytes | None = None  # a packet read by wait(), for recv
        try:
            self._claim()
        except DeviceError:
            self.close()
            raise
        except Exception as e:
            self.close()
            raise self._map(e) from None

    def _claim(self) -> None:
        dev = self.dev
        try:
            active = dev.is_kernel_driver_active(INTERFACE)
        except NotImplementedError:  # not on this OS (Windows, macOS): nothing to detach
            active = False
        if active:
            bus, addr = getattr(dev, "bus", 0), getattr(dev, "address", 0)
            busy = holders(hidraw_nodes_of(bus, addr, self._sysfs), self._proc)
            if busy:
                raise DeviceBusy(f"{self.where} is busy: the kernel's HID driver has it and {busy[0]} is "
                                 "using it; stop that (systemctl stop hostd) or use device.transport = "
                                 "\"hid\"")
            dev.detach_kernel_driver(INTERFACE)
            self._detached = True
        try:
            dev.get_active_configuration()
        except Exception:  # unconfigured: configure it (never re-set an active configuration)
            dev.set_configuration()
        self._util.claim_interface(dev, INTERFACE)
        self._claimed = True
        self.ep_out, self.ep_in = self._endpoints(dev)

    @staticmethod
    def _endpoints(dev) -> tuple[int, int]:
        """The interface's interrupt OUT and IN endpoints, as its descriptor says (a Linux gadget
        numbers them itself, e.g. 0x02 OUT); the board port's (protocol.toml) if it says none."""
        ep_out, ep_in = pr.P["usb_ep_out"], pr.P["usb_ep_in"]
        try:
            intf = dev.get_active_configuration()[(INTERFACE, 0)]
            for e in intf:
                if e.bmAttributes & 0x3 == 0x3:  # interrupt
                    if e.bEndpointAddress & 0x80:
                        ep_in = e.bEndpointAddress
                    else:
                        ep_out = e.bEndpointAddress
        except Exception:  # no descriptor to read: keep the board port's
            pass
        return ep_out, ep_in

    def _map(self, e: Exception) -> DeviceError:
        code = getattr(e, "errno", None)
        if code in (errno.EACCES, errno.EPERM):
            return permission_error(self.node)
        if code == errno.EBUSY:
            who = holders([self.node], self._proc)
            held = f"{who[0]} holds it" if who else "another program holds it (or one of another user)"
            return DeviceBusy(f"{self.where} is busy: {held}; stop it (systemctl stop hostd if it is the "
                              "daemon) or use that program")
        if code in TRANSIENT_ERRNOS or type(e).__name__ == "USBTimeoutError":
            return DeviceBusy(f"{self.where}: {e} (transient; retried)")
        if code in GONE_ERRNOS:
            return DeviceGone(f"{self.where} went away ({e}); re-plug it, hostd reconnects")
        return DeviceError(f"{self.where}: {e}")

    def send(self, msg: bytes) -> None:
        try:
            self.dev.write(self.ep_out, pr.pad_report(msg), 100)
        except Exception as e:
            raise self._map(e) from None

    def _read(self, timeout_s: float) -> bytes | None:
        try:
            data = self.dev.read(self.ep_in, pr.REPORT_SIZE, max(1, int(timeout_s * 1000)))
        except Exception as e:
            if getattr(e, "errno", None) == errno.ETIMEDOUT or type(e).__name__ == "USBTimeoutError":
                return None
            raise self._map(e) from None
        return bytes(data) if len(data) else None  # a zero-length packet is not a report

    def recv(self, timeout_s: float = 0.0) -> bytes | None:
        if self._pending is not None:
            data, self._pending = self._pending, None
            return data
        return self._read(timeout_s)

    def pending(self) -> bool:
        return self._pending is not None

    def wait(self, timeout_s: float, fds=()) -> bool:
        """libusb gives no descriptor per endpoint: wait by reading (the packet is kept for
        recv), in slices of POLL_S when `fds` must be watched too."""
        import select

        if self._pending is not None:
            return True
        deadline = time.monotonic() + timeout_s
        while True:
            left = deadline - time.monotonic()
            self._pending = self._read(min(left, self.POLL_S) if fds else left)
            if self._pending is not None:
                return True
            if fds and select.select(list(fds), [], [], 0)[0]:
                return False
            if deadline - time.monotonic() <= 0:
                return False

    def close(self) -> None:
        dev = getattr(self, "dev", None)
        if dev is None:
            return
        util = self._util
        steps = []
        if self._claimed:
            steps.append(lambda: util.release_interface(dev, INTERFACE))
        if self._detached:  # give the interface back to usbhid: its hidraw node returns
            steps.append(lambda: dev.attach_kernel_driver(INTERFACE))
        steps.append(lambda: util.dispose_resources(dev))
        self._claimed = self._detached = False
        for step in steps:  # each on its own: a failed release must not keep usbhid away
            try:
                step()
            except Exception:
                pass

    def describe(self) -> str:
        return self.where
