"""Serial-bridge backend through pyserial: COBS frames with a CRC-16 (protocol.frame)."""

from __future__ import annotations

import time

from hostd.device import protocol as pr
from hostd.device.transport import Transport, os_error
from hostd.errors import DeviceGone, DeviceNotFound


def enumerate_specs() -> list[str]:
    from serial.tools import list_ports

    return [f"serial:{p.device}" for p in list_ports.comports()
            if p.vid == pr.USB_VID and p.pid == pr.USB_PID]


class SerialTransport(Transport):
    name = "serial"

    def __init__(self, port: str | None = None, baudrate: int = 2_000_000) -> None:
        import serial

        if port is None:
            specs = enumerate_specs()
            if not specs:
                from serial.tools import list_ports

                seen = [p.device for p in list_ports.comports()]
                raise DeviceNotFound(f"no serial display {pr.USB_VID:04x}:{pr.USB_PID:04x} "
                                     f"(serial ports seen: {', '.join(seen) or 'none'}); "
                                     "name one with serial:/dev/ttyACM0")
            port = specs[0].split(":", 1)[1]
        self.port = port
        try:
            self.ser = serial.Serial(port, baudrate=baudrate, timeout=0, write_timeout=0.5)
        except serial.SerialException as e:
            inner = e.__context__ if isinstance(e.__context__, OSError) else None
            if inner is None and e.errno is not None:
                inner = OSError(e.errno, str(e))
            if inner is not None:
                err = os_error(inner, f"serial port {port}")
                if isinstance(err, DeviceGone):  # ENOENT at open: not there
                    raise DeviceNotFound(f"serial port {port} does not exist") from None
                raise err from None
            raise DeviceNotFound(f"cannot open serial port {port} ({e})") from None
        self.deframer = pr.Deframer()
        self._queue: list[bytes] = []

    def _gone(self, e: Exception) -> DeviceGone:
        return DeviceGone(f"serial port {self.port} went away ({e}); hostd reconnects when it returns")

    def send(self, msg: bytes) -> None:
        self.send_raw(pr.frame(msg))

    def send_raw(self, data: bytes) -> None:
        import serial

        try:
            self.ser.write(data)
        except (OSError, serial.SerialException) as e:
            raise self._gone(e) from None

    def recv(self, timeout_s: float = 0.0) -> bytes | None:
        import serial

        deadline = time.monotonic() + timeout_s
        while not self._queue:
            try:
                data = self.ser.read(4096)
            except (OSError, serial.SerialException) as e:
                raise self._gone(e) from None
            if data:
                self._queue += self.deframer.feed(data)
                continue
            if time.monotonic() >= deadline:
                return None
            time.sleep(0.0002)
        return self._queue.pop(0)

    def close(self) -> None:
        try:
            self.ser.close()
        except Exception:
            pass

    def describe(self) -> str:
        return f"serial:{self.port}"
