"""Raw USB backend through pyusb, with libusb-package's bundled libusb (no system libusb).

Interrupt OUT endpoint 0x01 and IN endpoint 0x81 (protocol.toml), 64-byte packets.
"""

from __future__ import annotations

import errno

from hostd.device import protocol as pr
from hostd.device.transport import TRANSIENT_ERRNOS, UDEV_FIX, Transport
from hostd.errors import DeviceBusy, DeviceError, DeviceGone, DeviceNotFound, DevicePermission


def _find(find=None, **kw):
    if find is None:
        try:
            import libusb_package
        except ImportError as e:
            raise DeviceNotFound(f"USB backend unavailable ({e}); pip install 'hostd[device]'") from None
        find = libusb_package.find
    try:
        return find(**kw)
    except Exception as e:  # usb.core.NoBackendError and friends
        raise DeviceNotFound(f"USB backend unavailable ({e})") from None


def enumerate_specs(find=None) -> list[str]:
    devs = _find(find, find_all=True, idVendor=pr.USB_VID, idProduct=pr.USB_PID) or []
    return [f"usb:{d.bus}:{d.address}" for d in devs]


class UsbTransport(Transport):
    name = "usb"

    def __init__(self, find=None) -> None:
        dev = _find(find, idVendor=pr.USB_VID, idProduct=pr.USB_PID)
        if dev is None:
            seen = _find(find, find_all=True) or []
            ids = sorted({f"{d.idVendor:04x}:{d.idProduct:04x}" for d in seen})
            raise DeviceNotFound(f"no USB display {pr.USB_VID:04x}:{pr.USB_PID:04x} "
                                 f"(USB devices seen: {', '.join(ids) or 'none'})")
        self.dev = dev
        self.where = f"usb:{getattr(dev, 'bus', '?')}:{getattr(dev, 'address', '?')}"
        try:
            try:
                if dev.is_kernel_driver_active(0):
                    dev.detach_kernel_driver(0)
            except NotImplementedError:
                pass
            dev.set_configuration()
        except Exception as e:
            raise self._map(e) from None

    def _map(self, e: Exception) -> DeviceError:
        code = getattr(e, "errno", None)
        if code in (errno.EACCES, errno.EPERM):
            return DevicePermission(f"permission denied on {self.where}: {UDEV_FIX}")
        if code in TRANSIENT_ERRNOS or type(e).__name__ == "USBTimeoutError":
            return DeviceBusy(f"{self.where}: {e} (transient; retried)")
        if code in (errno.ENODEV, errno.EIO, errno.EPIPE):
            return DeviceGone(f"{self.where} went away ({e}); re-plug it, hostd reconnects")
        return DeviceError(f"{self.where}: {e}")

    def send(self, msg: bytes) -> None:
        try:
            self.dev.write(pr.P["usb_ep_out"], pr.pad_report(msg), 100)
        except Exception as e:
            raise self._map(e) from None

    def recv(self, timeout_s: float = 0.0) -> bytes | None:
        try:
            data = self.dev.read(pr.P["usb_ep_in"], pr.REPORT_SIZE, max(1, int(timeout_s * 1000)))
        except Exception as e:
            if getattr(e, "errno", None) == errno.ETIMEDOUT or "timeout" in str(e).lower():
                return None
            raise self._map(e) from None
        return bytes(data) if len(data) else None

    def close(self) -> None:
        try:
            import usb.util

            usb.util.dispose_resources(self.dev)
        except Exception:
            pass

    def describe(self) -> str:
        return self.where
