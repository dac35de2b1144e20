"""Open a transport from its spec, and list the displays plugged in: the backend registry.

Specs: "hid[:PATH]" (Linux: /dev/hidrawN directly; elsewhere hidapi), "usb[:BUS/ADDR]" (pyusb +
libusb-package), "serial[:PORT]" (pyserial, COBS frames), "sim" (an in-process simulated
device). "auto" tries hid, usb, serial, in that order.

The registry maps each name to "module:attribute" and imports the backend only when it is
used: the backends import hostd.device.backend (the interface), never this module, so there is
no import circle, and a missing optional library (hidapi, pyusb) costs only its own backend.
"""

from __future__ import annotations

import importlib

from hostd.device import protocol as pr
from hostd.device.backend import UDEV_FIX, UDEV_RULE, Transport, os_error  # noqa: F401  (re-exported)
from hostd.errors import DeviceError, DeviceNotFound, DevicePermission

# name -> (module, opener, enumerator); the opener takes the spec's argument (None if absent)
BACKENDS: dict[str, tuple[str, str, str | None]] = {
    "hid": ("hostd.device.hidlink", "open_hid", "enumerate_displays"),
    "usb": ("hostd.device.usblink", "UsbTransport", "enumerate_displays"),
    "serial": ("hostd.device.seriallink", "SerialTransport", "enumerate_displays"),
    "sim": ("hostd.device.simdev", "SimTransport", None),
}
AUTO_ORDER = ("hid", "usb", "serial")


def _attr(kind: str, which: int):
    mod = importlib.import_module(BACKENDS[kind][0])
    return getattr(mod, BACKENDS[kind][which])


def find_displays() -> list[dict]:
    """Every display plugged in, as {"spec", "node", ...} (for `hostd doctor` and auto)."""
    found: list[dict] = []
    for kind in AUTO_ORDER:
        try:
            found += _attr(kind, 2)()
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
    if kind == "sim":
        return []
    if arg and kind in ("hid", "serial"):
        return [{"spec": spec, "node": arg}] if os.path.exists(arg) else []
    found = []
    for name in AUTO_ORDER if kind == "auto" else (kind,):
        try:
            found += _attr(name, 2)()
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
    """Open a transport from a spec: auto | hid[:PATH] | usb[:BUS/ADDR] | serial[:PORT] | sim;
    with serial, the display of that USB serial number (auto, hid, usb or serial without a path)."""
    if serial and not spec.startswith("sim"):
        spec = by_serial(spec, serial)
    kind, _, arg = spec.partition(":")
    if kind == "sim":
        return _attr("sim", 1)(**kw)
    if kind in BACKENDS:
        return _attr(kind, 1)(arg or None)
    if kind != "auto":
        raise DeviceError(f"unknown device {spec!r}: use auto, hid[:PATH], usb[:BUS/ADDR], serial[:PORT] "
                          "or sim")
    seen: list[str] = []
    for name in AUTO_ORDER:
        try:
            return _attr(name, 1)(None)
        except DevicePermission:
            raise
        except DeviceNotFound as e:
            seen.append(str(e))
        except ImportError as e:
            seen.append(f"{name}: {e}")
    raise DeviceNotFound(f"no display {pr.USB_VID:04x}:{pr.USB_PID:04x} found on HID, USB or serial "
                         f"({'; '.join(seen)}); plug it in, or set [device] transport = \"sim\" in the "
                         "config to run without one")
