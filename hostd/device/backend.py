"""What every transport backend is: the Transport interface and the error mapping they share.

Backends (hidlink, usblink, seriallink, simdev) import this module and nothing of the
factory; the factory (hostd.device.transport) maps names to backends lazily, so no module
imports back and a backend's optional library (hidapi, pyusb, pyserial) loads only when used.

A transport moves whole protocol messages. Besides send/recv it gives the pump something to
block on: `wait_readable(timeout_s)` returns as soon as a message may be waiting (or the
device went away), and `fileno()` is the descriptor it waits on where there is one (hidraw,
serial), so the pump can sleep in select/poll with other descriptors (the command pipe, the
udev monitor) instead of spinning.
"""

from __future__ import annotations

import errno
import grp
import os
import pwd
import select
import stat
import time

from hostd.errors import DeviceBusy, DeviceError, DeviceGone, DevicePermission

UDEV_RULE = "systemd/70-hostd.rules"
GROUP = "hostd"
UDEV_FIX = (f"install the udev rule: sudo cp {UDEV_RULE} /etc/udev/rules.d/ && "
            "sudo udevadm control --reload && sudo udevadm trigger, then re-plug the display "
            f"(or add your user to the '{GROUP}' group)")


class Transport:
    name = "transport"
    node: str | None = None  # the device node it holds open (/dev/hidraw0, /dev/ttyACM0, ...)

    def send(self, msg: bytes) -> None:
        raise NotImplementedError

    def recv(self, timeout_s: float = 0.0) -> bytes | None:
        """One message, or None if none arrived within timeout_s. Raises DeviceGone."""
        raise NotImplementedError

    def fileno(self) -> int | None:
        """The descriptor that becomes readable when a message arrives (None: there is none,
        use wait_readable)."""
        return None

    def wait_readable(self, timeout_s: float) -> bool:
        """Block until a message may be waiting (True) or timeout_s passed (False). A device
        that went away counts as readable: the next recv() raises DeviceGone."""
        fd = self.fileno()
        if fd is None:
            time.sleep(max(0.0, timeout_s))
            return True
        return wait_fd(fd, timeout_s)

    def close(self) -> None:
        pass

    def now(self) -> float:
        """The host clock the link measures against (a simulation on a manual clock gives its
        own, so that the device's clock and the host's advance together)."""
        return time.monotonic()

    def describe(self) -> str:
        """The transport spec of this open device: hid:/dev/hidraw0, usb:001/002, serial:PORT."""
        return self.name

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def wait_fd(fd: int, timeout_s: float) -> bool:
    """poll() one descriptor for input (or hang-up/error, which the next read reports)."""
    p = select.poll()
    p.register(fd, select.POLLIN | select.POLLPRI)
    while True:
        try:
            return bool(p.poll(max(0, int(timeout_s * 1000 + 0.999))))
        except InterruptedError:  # pragma: no cover - PEP 475 retries already
            continue


TRANSIENT_ERRNOS = (errno.EAGAIN, errno.EWOULDBLOCK, errno.ETIMEDOUT, errno.EINTR, errno.ENOBUFS)
GONE_ERRNOS = (errno.EIO, errno.ENODEV, errno.ENXIO, errno.EPIPE, errno.ENOENT, errno.ESHUTDOWN)


def node_owner(path: str) -> dict:
    """owner, group and mode of a device node (for `hostd doctor` and permission messages)."""
    try:
        st = os.stat(path)
    except OSError as e:
        return {"node": path, "error": e.strerror}

    def name(fn, i):
        try:
            return fn(i)[0]
        except KeyError:
            return str(i)

    return {"node": path, "owner": name(pwd.getpwuid, st.st_uid), "group": name(grp.getgrgid, st.st_gid),
            "mode": f"{stat.S_IMODE(st.st_mode):04o}",
            "access": os.access(path, os.R_OK | os.W_OK)}


def permission_error(node: str) -> DevicePermission:
    """The one-line refusal for a node this user may not open: who may, and how to get there."""
    o = node_owner(node)
    have = f" ({o['owner']}:{o['group']} {o['mode']})" if "mode" in o else ""
    return DevicePermission(f"permission denied opening {node}{have}: {UDEV_FIX}")


def os_error(e: OSError, what: str, node: str | None = None) -> DeviceError:
    """Map an OS error on open/read/write to the error that says what to do."""
    if e.errno in (errno.EACCES, errno.EPERM):
        if node:
            return permission_error(node)
        return DevicePermission(f"permission denied opening {what}: {UDEV_FIX}")
    if e.errno in TRANSIENT_ERRNOS:
        return DeviceBusy(f"{what}: {e.strerror or e} (transient; retried)")
    if e.errno in GONE_ERRNOS:
        return DeviceGone(f"{what} went away ({e.strerror or e}); re-plug it, hostd reconnects")
    if e.errno == errno.EBUSY:
        return DeviceBusy(f"{what} is busy ({e.strerror}): another program holds it")
    return DeviceError(f"{what}: {e}")
