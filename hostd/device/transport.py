"""One interface, four backends. A transport moves whole protocol messages.

Backends: "hid" (hidapi), "usb" (pyusb + libusb-package), "serial[:PORT]" (pyserial, COBS
frames), "sim" (an in-process simulated device). "auto" tries hid, usb, serial, in that order.
"""

from __future__ import annotations

import errno
import time

from hostd.device import protocol as pr
from hostd.errors import DeviceBusy, DeviceError, DeviceGone, DeviceNotFound, DevicePermission

UDEV_RULE = "systemd/70-hostd.rules"
UDEV_FIX = (f"install the udev rule: sudo cp {UDEV_RULE} /etc/udev/rules.d/ && "
            "sudo udevadm control --reload && sudo udevadm trigger, then re-plug the display "
            "(or add your user to the 'hostd' group)")


class Transport:
    name = "transport"

    def send(self, msg: bytes) -> None:
        raise NotImplementedError

    def recv(self, timeout_s: float = 0.0) -> bytes | None:
        """One message, or None if none arrived within timeout_s. Raises DeviceGone."""
        raise NotImplementedError

    def close(self) -> None:
        pass

    # Blocking with a timeout, so that a host with nothing to do sleeps (device mode) instead of
    # polling every millisecond. A backend with a descriptor that turns readable when the device
    # has sent something (a pty or serial port, hidraw) returns it from fileno(); one that has
    # already read and queued messages says so in pending(). Others get the polling fallback.
    POLL_S = 0.001  # the fallback's poll period (a backend without a descriptor)

    def fileno(self) -> int | None:
        """A descriptor that becomes readable when the device has sent something, or None."""
        return None

    def pending(self) -> bool:
        """Messages already read from the device and waiting in this object."""
        return False

    def wait(self, timeout_s: float, fds=()) -> bool:
        """Block until the device may have sent a message, one of `fds` is readable, or
        timeout_s has passed. True when recv() may have something. Without a descriptor:
        the fallback wakes every POLL_S and reports True (recv finds out)."""
        import select

        if self.pending():
            return True
        fd = self.fileno()
        if fd is None:
            ready, _, _ = select.select(list(fds), [], [], max(0.0, min(timeout_s, self.POLL_S)))
            return not ready
        try:
            ready, _, _ = select.select([fd, *fds], [], [], max(0.0, timeout_s))
        except (OSError, ValueError):  # the descriptor closed under us: let recv() report it
            return True
        return fd in ready

    def now(self) -> float:
        """The host clock the link measures against (a simulation on a manual clock gives its
        own, so that the device's clock and the host's advance together)."""
        return time.monotonic()

    def describe(self) -> str:
        return self.name

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


TRANSIENT_ERRNOS = (errno.EAGAIN, errno.EWOULDBLOCK, errno.ETIMEDOUT, errno.EINTR, errno.ENOBUFS)


def os_error(e: OSError, what: str) -> DeviceError:
    """Map an OS error on open/read/write to the error that says what to do."""
    if e.errno in (errno.EACCES, errno.EPERM):
        return DevicePermission(f"permission denied opening {what}: {UDEV_FIX}")
    if e.errno in TRANSIENT_ERRNOS:
        return DeviceBusy(f"{what}: {e.strerror or e} (transient; retried)")
    if e.errno in (errno.EIO, errno.ENODEV, errno.ENXIO, errno.EPIPE, errno.ENOENT):
        return DeviceGone(f"{what} went away ({e.strerror or e}); re-plug it, hostd reconnects")
    return DeviceError(f"{what}: {e}")


def find_devices() -> list[str]:
    """Everything that looks like a display, as transport specs (for `hostd doctor`)."""
    from hostd.device import hidlink, seriallink, usblink

    found: list[str] = []
    for mod in (hidlink, usblink, seriallink):
        try:
            found += mod.enumerate_specs()
        except DeviceError:
            pass
    return found


def open_transport(spec: str = "auto", **kw) -> Transport:
    """Open a transport from a spec: auto | hid[:PATH] | usb | serial[:PORT] | sim."""
    from hostd.device import hidlink, seriallink, simdev, usblink

    kind, _, arg = spec.partition(":")
    if kind == "sim":
        return simdev.SimTransport(**kw)
    if kind == "hid":
        return hidlink.HidTransport(arg or None)
    if kind == "usb":
        return usblink.UsbTransport()
    if kind == "serial":
        return seriallink.SerialTransport(arg or None)
    if kind != "auto":
        raise DeviceError(f"unknown device {spec!r}: use auto, hid[:PATH], usb, serial[:PORT] or sim")
    seen: list[str] = []
    for opener in (hidlink.HidTransport, usblink.UsbTransport, seriallink.SerialTransport):
        try:
            return opener()
        except DevicePermission:
            raise
        except DeviceNotFound as e:
            seen.append(str(e))
    raise DeviceNotFound(f"no display {pr.USB_VID:04x}:{pr.USB_PID:04x} found on HID, USB or serial "
                         f"({'; '.join(seen)}); plug it in, or use device = \"sim\" to run without one")
