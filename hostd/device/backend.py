"""What every transport backend is: the Transport interface and the error mapping they share.

Backends (hidlink, usblink, seriallink, simdev) import this module and nothing of the
factory; the factory (hostd.device.transport) maps names to backends lazily, so no module
imports back and a backend's optional library (hidapi, pyusb, pyserial) loads only when used.

A transport moves whole protocol messages. Besides send/recv it gives the pump something to
block on (the interface i22's sleeping device-mode loop uses): `wait(timeout_s, fds)` returns as
soon as a message may be waiting (or the device went away), or one of `fds` (the command pipe)
is readable; `fileno()` is the descriptor it waits on where there is one (hidraw, serial), and
`pending()` says a message was already read and is queued in the object.
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

    def drain(self) -> list[bytes]:
        """Every message waiting now (none: an empty list). Raises DeviceGone. A backend that
        reads a byte stream overrides this to take them all with one read."""
        out = []
        while (m := self.recv(0.0)) is not None:
            out.append(m)
        return out

    gathers = False  # a byte stream: gather() takes each arrival in and counts its messages

    def take(self) -> list[bytes]:
        """The messages read already (gather), without reading."""
        return []

    def gather(self, fds: tuple[int, ...], timeout_ms: int, count: int) -> tuple[set[int], int]:
        """Sleep on fileno() and `fds` until `count` messages wait here, one of `fds` is readable
        or timeout_ms passed; every arrival that wakes it is read at once. Returns the
        descriptors of `fds` that are readable and how many wake-ups it took. Only where
        `gathers` (a byte stream, whose reader the kernel wakes at each arrival: a tty's VMIN
        spares the read, not the wake-up); HID and raw USB deliver one report per read and the
        loop runs per report."""
        raise NotImplementedError

    POLL_S = 0.001  # the fallback's poll period (a backend without a descriptor)

    def fileno(self) -> int | None:
        """A descriptor that becomes readable when the device has sent something, or None."""
        return None

    def pending(self) -> bool:
        """Messages already read from the device and waiting in this object."""
        return False

    def wait(self, timeout_s: float, fds=()) -> bool:
        """Block until the device may have sent a message, one of `fds` is readable, or
        timeout_s has passed. True when recv() may have something (a device that went away
        counts: the next recv() raises DeviceGone). Without a descriptor: the fallback wakes
        every POLL_S and reports True (recv finds out)."""
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
    """The one-line refusal for a node this user may not open: who may, and how to get there.
    A node of group hostd means the udev rule worked and this user is not in the group; any other
    group means the rule did not apply (not installed, or the group did not exist yet when the
    display appeared)."""
    o = node_owner(node)
    have = f" ({o['owner']}:{o['group']} {o['mode']})" if "mode" in o else ""
    if o.get("group") == GROUP:
        fix = (f"the udev rule ({UDEV_RULE}) gave it to group '{GROUP}': add your user to it "
               f"(sudo usermod -aG {GROUP} $USER, then log in again) or run hostd as the service")
    else:
        fix = (f"{UDEV_FIX}; the '{GROUP}' group must exist before the display appears "
               "(sudo hostd install-service does both)")
    return DevicePermission(f"permission denied opening {node}{have}: {fix}")


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
