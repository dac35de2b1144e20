"""The display's arrival and removal from udev events, with a 1 s poll only where udev is absent.

The daemon's pump opens the display; when it is not there it waits. With udev running
(`/run/udev/control`) and pyudev installed, it waits on a udev monitor (netlink, the events udev
sends once its rules ran, so the node already has its group and mode), filtered in the kernel to
the subsystems of the configured transport (its backend's, hostd.device.transport.BACKENDS: hidraw
for hid, usb for usb, tty for serial; all three for auto), as Solaar does: a display that appears
is opened at once, one that goes away is dropped at once. Without udev (a container, a minimal
system) or without pyudev it falls back to trying every `device.reconnect_s`, and says so
(`hostd status --json` `hotplug`, `hostd doctor`).

Each event carries the instant it happened on CLOCK_MONOTONIC (udev's USEC_INITIALIZED for an
arrival, else when it was read), so the time from the event to playing again can be reported
(`last_reconnect_s`).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass

from hostd.device import protocol as pr

UDEV_CONTROL = "/run/udev/control"
ACTIONS = ("add", "remove")


@dataclass(frozen=True)
class Event:
    action: str  # "add" or "remove"
    subsystem: str
    node: str | None  # /dev/hidraw0, /dev/bus/usb/001/002, /dev/ttyACM0
    t: float  # CLOCK_MONOTONIC of the event
    display: bool  # the device (or a parent) has the display's VID:PID


def _ids_of(props) -> tuple[int, int] | None:
    """(vid, pid) from one device's udev properties, if they say."""
    hid_id = props.get("HID_ID")
    if hid_id:
        try:
            _bus, vid, pid = (int(x, 16) for x in hid_id.split(":"))
            return vid, pid
        except ValueError:
            pass
    product = props.get("PRODUCT")  # usb device and interface: "1209/7470/100" (hex)
    if product and product.count("/") == 2:
        try:
            vid, pid, _ = (int(x, 16) for x in product.split("/"))
            return vid, pid
        except ValueError:
            pass
    if props.get("ID_VENDOR_ID") and props.get("ID_MODEL_ID"):
        try:
            return int(props["ID_VENDOR_ID"], 16), int(props["ID_MODEL_ID"], 16)
        except ValueError:
            pass
    return None


def is_display(device) -> bool:
    """Does this udev device, or one of its parents, have the display's VID:PID?"""
    chain = [device]
    try:
        chain += list(device.ancestors)
    except Exception:  # a removed device has no sysfs to walk
        pass
    for d in chain:
        try:
            ids = _ids_of(d.properties)
        except Exception:
            ids = None
        if ids is not None:
            return ids == (pr.USB_VID, pr.USB_PID)
    return False


def _event_time(device, now: float) -> float:
    """udev stamps a device when it first handles it (USEC_INITIALIZED, CLOCK_MONOTONIC µs); use it
    for an arrival when it is plausible, else the time we read the event."""
    try:
        us = int(device.properties.get("USEC_INITIALIZED", "0"))
    except (ValueError, AttributeError):
        us = 0
    t = us * 1e-6
    return t if us and 0.0 <= now - t < 10.0 else now


class Hotplug:
    """A udev monitor for the transport's subsystems, or nothing (poll mode)."""

    def __init__(self, monitor=None, subsystems: tuple[str, ...] = (), why_poll: str = "",
                 clock=time.monotonic, plugged: bool = True) -> None:
        self.monitor = monitor
        self.plugged = plugged  # False: a simulated display, nothing to plug
        self.subsystems = subsystems
        self.why_poll = why_poll
        self.clock = clock
        self.events_seen = 0

    @property
    def mode(self) -> str:
        """"udev" (events), "poll" (retry every device.reconnect_s) or "none" (simulated)."""
        if not self.plugged:
            return "none"
        return "udev" if self.monitor is not None else "poll"

    def describe(self) -> str:
        if not self.plugged:
            return "none (a simulated display)"
        if self.monitor is not None:
            return f"udev events ({', '.join(self.subsystems)})"
        return f"polling every device.reconnect_s: {self.why_poll}"

    def fileno(self) -> int | None:
        return self.monitor.fileno() if self.monitor is not None else None

    def events(self) -> list[Event]:
        """The add/remove events waiting (never blocks)."""
        out: list[Event] = []
        if self.monitor is None:
            return out
        while True:
            try:
                d = self.monitor.poll(timeout=0)
            except OSError:
                break
            if d is None:
                break
            action = d.action
            if action not in ACTIONS:
                continue
            sub = d.subsystem
            if sub == "usb" and d.device_type != "usb_device":
                continue  # interfaces: the device's own event is enough
            now = self.clock()
            t = _event_time(d, now) if action == "add" else now
            self.events_seen += 1
            out.append(Event(action, sub, d.device_node, t, is_display(d)))
        return out

    def close(self) -> None:
        self.monitor = None  # libudev closes the netlink socket with the last reference


def watch(spec: str, source: str = "udev", control: str = UDEV_CONTROL) -> Hotplug:
    """The hotplug source for a transport spec: udev events where possible, else poll mode."""
    from hostd.device.transport import subsystems  # the backends' table: each kind's subsystems

    kind, _, arg = spec.partition(":")
    subs = subsystems(spec)
    if not subs:
        return Hotplug(why_poll=f"a {kind} display is not plugged", plugged=False)
    if kind == "serial" and arg.startswith("/dev/pts/"):
        return Hotplug(why_poll="a pseudo-terminal has no udev events")
    if source == "udev" and not os.path.exists(control):
        return Hotplug(why_poll=f"udev is not running here (no {control})")
    try:
        import pyudev
    except ImportError:
        from hostd.extras import pip_install

        return Hotplug(why_poll=f"pyudev is not installed ({pip_install('device')})")
    try:
        monitor = pyudev.Monitor.from_netlink(pyudev.Context(), source=source)
        for s in subs:  # (filtered in the kernel: other devices' events never wake us)
            monitor.filter_by(s, "usb_device" if s == "usb" else None)
        monitor.start()
    except Exception as e:  # no libudev, no netlink socket (a sandbox)
        return Hotplug(why_poll=f"no udev monitor ({e})")
    return Hotplug(monitor, subs)
