"""The device link: protocol, transports (HID, raw USB, serial, simulated) and flow control.

    transport = open_transport("auto")  # or "hid", "hid:/dev/hidraw0", "usb", "serial:/dev/ttyACM0", "sim"
    link = DeviceLink(transport); link.handshake(); link.start()
"""

from hostd.device.link import DeviceLink, LinkStats
from hostd.device.transport import Transport, find_devices, open_transport

__all__ = ["DeviceLink", "LinkStats", "Transport", "find_devices", "open_transport"]
