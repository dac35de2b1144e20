"""Open a transport from its spec, and list the displays plugged in: the backend registry.

Specs: "hid[:PATH]" (Linux: /dev/hidrawN directly; elsewhere hidapi), "usb[:BUS/ADDR]" (pyusb +
libusb-package), "serial[:PORT]" (pyserial, COBS frames), "sim" (an in-process simulated
device). "auto" tries hid, usb, serial, in that order.

BACKENDS is the one table of transport kinds: each backend's descriptor names its module, opener
and enumerator, the udev subsystems its displays arrive on, and the grammar of its spec's
argument. The config's validation, the hotplug filter, `hostd doctor` and the messages below all
read it, so a new transport is its module plus one entry here (Solaar's habit). The backend is
imported only when it is used: the backends import hostd.device.backend (the interface), never
this module, so there is no import circle, and a missing optional library (hidapi, pyusb) costs
only its own backend.
"""

from __future__ import annotations

import importlib
import re
from dataclasses import dataclass

from hostd.device import protocol as pr
from hostd.device.backend import UDEV_FIX, UDEV_RULE, Transport, os_error  # noqa: F401  (re-exported)
from hostd.errors import DeviceError, DeviceNotFound, DevicePermission


@dataclass(frozen=True)
class Backend:
    """One transport kind. The opener takes the spec's argument (None if absent) and the
    enumerator lists the displays plugged in (None: nothing to enumerate, e.g. the simulation)."""
    name: str
    module: str
    opener: str
    enumerator: str | None
    subsystems: tuple[str, ...]  # udev subsystems its displays arrive on (hotplug's kernel filter)
    arg: str = ""           # what may follow "name:" in a spec, for messages ("" = nothing)
    arg_re: str = ""        # the argument's grammar (a full match)
    arg_is_node: bool = False  # the argument is the display's device node (checked as a path)
    auto: bool = True       # tried, in table order, by "auto"

    def spec_forms(self) -> str:
        return f"{self.name}[:{self.arg}]" if self.arg else self.name


BACKENDS: dict[str, Backend] = {b.name: b for b in (
    Backend("hid", "hostd.device.hidlink", "open_hid", "enumerate_displays", ("hidraw",),
            arg="PATH", arg_re=r".+", arg_is_node=True),
    Backend("usb", "hostd.device.usblink", "UsbTransport", "enumerate_displays", ("usb",),
            arg="BUS/ADDR", arg_re=r"\d+/\d+"),
    Backend("serial", "hostd.device.seriallink", "SerialTransport", "enumerate_displays", ("tty",),
            arg="PORT", arg_re=r".+", arg_is_node=True),
    Backend("sim", "hostd.device.simdev", "SimTransport", None, (), auto=False),
)}
AUTO_ORDER = tuple(b.name for b in BACKENDS.values() if b.auto)
_FORMS = ["auto", *(b.spec_forms() for b in BACKENDS.values())]
SPEC_FORMS = f"{', '.join(_FORMS[:-1])} or {_FORMS[-1]}"  # auto, hid[:PATH], ... or sim


def parse_spec(spec: str) -> tuple[str, str]:
    """(kind, argument) of a transport spec; ValueError naming the forms when it is none of them."""
    kind, colon, arg = spec.partition(":")
    b = BACKENDS.get(kind)
    ok = (kind == "auto" and not colon) or (
        b is not None and (not colon or bool(b.arg_re and re.fullmatch(b.arg_re, arg))))
    if not ok:
        raise ValueError(f"must be {SPEC_FORMS}, not {spec!r}")
    return kind, arg


def subsystems(spec: str) -> tuple[str, ...]:
    """The udev subsystems a display of this spec arrives on (auto: every auto backend's)."""
    kind = spec.partition(":")[0]
    names = AUTO_ORDER if kind == "auto" else (kind,)
    return tuple(s for n in names if n in BACKENDS for s in BACKENDS[n].subsystems)


def _attr(kind: str, which: str):
    b = BACKENDS[kind]
    return getattr(importlib.import_module(b.module), getattr(b, which))


def find_displays() -> list[dict]:
    """Every display plugged in, as {"spec", "node", ...} (for `hostd doctor` and auto)."""
    found: list[dict] = []
    for kind in AUTO_ORDER:
        try:
            found += _attr(kind, "enumerator")()
        except (DeviceError, ImportError):
            pass
    return found


def present(spec: str, serial: str | None = None) -> list[dict]:
    """The displays a spec could open, listed without opening anything (sysfs on Linux): the
    daemon's check, once per device.reconnect_s while it waits, that no udev event was missed.
    serial: only the display with this USB serial number (config device.serial)."""
    if serial:
        return [d for d in present(spec) if d.get("serial") == serial]
    import os

    kind, _, arg = spec.partition(":")
    b = BACKENDS.get(kind)
    if b is not None and b.enumerator is None:
        return []
    if arg and b is not None and b.arg_is_node:
        return [{"spec": spec, "node": arg}] if os.path.exists(arg) else []
    found = []
    for name in AUTO_ORDER if kind == "auto" else (kind,):
        try:
            found += _attr(name, "enumerator")()
        except (DeviceError, ImportError, OSError):
            pass
    return [d for d in found if not arg or d["spec"] == spec]


def find_devices() -> list[str]:
    """The transport specs of every display plugged in."""
    return [d["spec"] for d in find_displays()]


def by_serial(spec: str, serial: str) -> str:
    """The spec of the display whose USB serial number is `serial` among those `spec` could open
    (two displays on one PC: config device.serial picks one, as udev's /dev/hostd/by-serial/ names)."""
    found = present(spec)
    for d in found:
        if d.get("serial") == serial:
            return d["spec"]
    seen = ", ".join(f"{d['spec']} (serial {d.get('serial') or 'none'})" for d in found) or "none"
    raise DeviceNotFound(f"no display with serial number {serial!r} (device.serial) among {spec}: seen "
                         f"{seen}; hostd doctor lists the displays and their serial numbers")


def open_transport(spec: str = "auto", serial: str | None = None, **kw) -> Transport:
    """Open a transport from a spec (SPEC_FORMS); with serial, the display of that USB serial
    number (auto, or a kind that enumerates, without an argument)."""
    kind, _, arg = spec.partition(":")
    b = BACKENDS.get(kind)
    if serial and (b is None or b.enumerator is not None):
        spec = by_serial(spec, serial)
        kind, _, arg = spec.partition(":")
        b = BACKENDS.get(kind)
    if b is not None and b.enumerator is None:  # nothing to find: built in-process
        return _attr(kind, "opener")(**kw)
    if b is not None:
        return _attr(kind, "opener")(arg or None)
    if kind != "auto":
        raise DeviceError(f"unknown device {spec!r}: use {SPEC_FORMS}")
    seen: list[str] = []
    for name in AUTO_ORDER:
        try:
            return _attr(name, "opener")(None)
        except DevicePermission:
            raise
        except DeviceNotFound as e:
            seen.append(str(e))
        except ImportError as e:
            seen.append(f"{name}: {e}")
    raise DeviceNotFound(f"no display {pr.USB_VID:04x}:{pr.USB_PID:04x} found on HID, USB or serial "
                         f"({'; '.join(seen)}); plug it in, or set [device] transport = \"sim\" in the "
                         "config to run without one")
