"""Serial-bridge backend through pyserial: COBS frames with a CRC-16 (protocol.frame).

Reads wait in select() on the port's descriptor (`wait`, `fileno`), so the pump can block
on it; a port that hangs up (a CDC-ACM display unplugged) reads as gone.

A read never asks a tty that has nothing: `drain`, `recv` and `gather` read only the bytes the
line discipline holds (TIOCINQ, which does not wait). A `read()` that finds the line discipline
empty first waits for the kernel's buffer work (n_tty_read -> tty_buffer_flush_work: a kworker
that moves bytes the other side wrote from the tty's flip buffer into the line discipline), and
on a busy machine that kworker waits for a core: the pump's 1 ms cycle was held 9-14 ms
(DEVELOPMENT.md, "Link latency"). Bytes still in the flip buffer are read by the next
cycle instead. A port that hung up answers TIOCINQ with EIO: gone.
"""

from __future__ import annotations

import fcntl
import os
import termios
import time

from hostd.device import fastlink
from hostd.device import protocol as pr
from hostd.device.backend import Transport, os_error, permission_error
from hostd.errors import DeviceBusy, DeviceGone, DeviceNotFound, DevicePermission


def enumerate_displays() -> list[dict]:
    """Serial ports of displays (by the USB VID:PID pyserial reads from sysfs)."""
    from serial.tools import list_ports

    return [{"spec": f"serial:{p.device}", "node": p.device, "serial": p.serial_number or ""}
            for p in list_ports.comports() if p.vid == pr.USB_VID and p.pid == pr.USB_PID]


def enumerate_specs() -> list[str]:
    return [d["spec"] for d in enumerate_displays()]


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
        self.node = port
        try:
            self.ser = serial.Serial(port, baudrate=baudrate, timeout=0, write_timeout=0)
        except serial.SerialException as e:
            inner = e.__context__ if isinstance(e.__context__, OSError) else None
            if inner is None and e.errno is not None:
                inner = OSError(e.errno, str(e))
            if inner is not None:
                err = os_error(inner, f"serial port {port}")
                if isinstance(err, DeviceGone):  # ENOENT at open: not there
                    raise DeviceNotFound(f"serial port {port} does not exist") from None
                if isinstance(err, DevicePermission):
                    raise permission_error(port) from None
                raise err from None
            raise DeviceNotFound(f"cannot open serial port {port} ({e})") from None
        self.deframer = fastlink.deframer()
        self._queue: list[bytes] = []
        # Writes go straight to the non-blocking fd (one layer less on the real-time path, and
        # pyserial's write() can report a timeout after writing everything): what the port
        # does not take now waits here, in order, and goes out first on the next call.
        fcntl.fcntl(self.ser.fd, fcntl.F_SETFL, fcntl.fcntl(self.ser.fd, fcntl.F_GETFL) | os.O_NONBLOCK)
        self._pending = b""
        import select

        # a poll() that said the port hung up or failed, while its line discipline still answers
        # (made once, not per call; a poll of an empty tty waits for the buffer work too, so
        # only a wake-up that read nothing asks it)
        self._hup_poll = select.poll()
        self._hup_poll.register(self.ser.fd, select.POLLIN)
        self._vmin = 0  # the line discipline's VMIN: left at 0 (the compiled cycle checks it)

    def _gone(self, e: Exception) -> DeviceGone:
        return DeviceGone(f"serial port {self.port} went away ({e}); hostd reconnects when it returns")

    def send(self, msg: bytes) -> None:
        self.send_raw(pr.frame(msg))

    MAX_PENDING = 4096  # bytes (about 60 ms of SAMPLES): past this the port is stuck

    def send_raw(self, data: bytes) -> None:
        if self._pending:
            data = self._pending + data
            self._pending = b""
        self._pending = data[self._write(data):]
        if len(self._pending) > self.MAX_PENDING:
            # the device has not read for a long while: drop what waits, resynchronize its
            # deframer with a delimiter (the cut frame fails its CRC and is counted), retry later
            self._pending = b"\x00"
            raise DeviceBusy(f"serial port {self.port}: the device is not reading; output dropped")

    def _write(self, data: bytes) -> int:
        try:
            return os.write(self.ser.fd, data)
        except BlockingIOError:
            return 0
        except OSError as e:
            err = os_error(e, f"serial port {self.port}")
            if isinstance(err, DeviceBusy):
                return 0
            raise self._gone(e) from None

    def flush_pending(self) -> None:
        if self._pending:
            self._pending = self._pending[self._write(self._pending):]

    def _hung_up(self) -> bool:
        """The port reports a hang-up or an error (poll)."""
        import select

        return any(ev & (select.POLLHUP | select.POLLERR) for _, ev in self._hup_poll.poll(0))

    def fileno(self) -> int | None:
        return self.ser.fd

    def pending(self) -> bool:
        return bool(self._queue)

    def waiting(self) -> int:
        """Bytes the line discipline holds now (TIOCINQ: it does not wait for the kernel's
        buffer work, as a read that finds nothing does). DeviceGone when the port hung up."""
        try:
            return int.from_bytes(fcntl.ioctl(self.ser.fd, termios.FIONREAD, b"\0\0\0\0"), "little")
        except OSError as e:
            raise self._gone(e) from None

    def _read_waiting(self) -> bytes:
        """One read of what the line discipline holds (at most READ_SIZE bytes), b"" when it holds
        nothing: never a read of an empty tty."""
        n = self.waiting()
        if n <= 0:
            return b""
        try:
            data = os.read(self.ser.fd, min(n, self.READ_SIZE))
        except BlockingIOError:  # (TIOCINQ said they were there: another reader took them)
            return b""
        except OSError as e:
            raise self._gone(e) from None
        if not data:  # bytes were there and the read ended: the other end hung up
            raise self._gone(OSError("end of file"))
        return data

    def recv(self, timeout_s: float = 0.0) -> bytes | None:
        self.flush_pending()
        deadline = time.monotonic() + timeout_s
        while not self._queue:
            data = self._read_waiting()  # (the non-blocking fd itself: pyserial's read() adds a select())
            if data:
                self._queue += self.deframer.feed(data)
                continue
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            # sleeps in select() until bytes arrive (or the port hangs up: the next TIOCINQ
            # says so), not in a polling loop
            self.wait(left)
        return self._queue.pop(0)

    gathers = True

    def take(self) -> list[bytes]:
        out, self._queue = self._queue, []
        return out

    def gather(self, fds: tuple[int, ...], timeout_ms: int, count: int) -> tuple[set[int], int]:
        """Transport.gather: asleep in poll(); each wake-up by the port reads what arrived, until
        `count` messages wait, a descriptor of `fds` is readable, or timeout_ms has passed. The
        compiled loop (hostd/device/_fastlink.c: a wake-up costs a poll() and a read, no Python)
        collects the bytes, which are deframed once at the end; else the same loop in Python."""
        want = count - len(self._queue)
        if want <= 0:  # (a run of the loop that need not sleep)
            return set(), 1
        if fastlink.GATHER is not None:
            raw = bytearray()
            ready, runs, hung_up = fastlink.GATHER(self.ser.fd, tuple(fds), timeout_ms, want, raw)
            if raw:
                self._queue += self.deframer.feed(raw)
            if hung_up:  # (or a read error): the read says which, DeviceGone when it is gone
                n0 = len(self._queue)
                self._queue = self.drain()
                if len(self._queue) == n0 and self._hung_up():
                    raise self._gone(OSError("hang-up"))
            return set(ready), runs
        return self._gather_py(fds, timeout_ms, count)

    def _gather_py(self, fds, timeout_ms: int, count: int) -> tuple[set[int], int]:
        import math
        import select

        key = tuple(fds)
        if getattr(self, "_gather_key", None) != key:
            self._gather_poll = select.poll()
            for f in (self.ser.fd, *key):
                self._gather_poll.register(f, select.POLLIN)
            self._gather_key = key
        fd = self.ser.fd
        deadline = time.monotonic() + timeout_ms / 1000.0
        runs = 0
        while True:
            events = self._gather_poll.poll(timeout_ms)
            runs += 1
            others = set()
            port = False
            hup = False
            for f, ev in events:
                if f == fd:
                    port = True
                    hup = bool(ev & (select.POLLHUP | select.POLLERR))
                else:
                    others.add(f)
            if port:  # readable or hung up: TIOCINQ and the read say which
                n0 = len(self._queue)
                self._queue = self.drain()  # (what was queued, then what arrived)
                if hup and len(self._queue) == n0:
                    raise self._gone(OSError("hang-up"))
            if others or not events or len(self._queue) >= count:
                return others, runs
            timeout_ms = max(0, math.ceil((deadline - time.monotonic()) * 1000.0))
            if timeout_ms == 0:
                return others, runs

    READ_SIZE = 4096

    def drain(self) -> list[bytes]:
        """Every message waiting, with one read of what the line discipline holds (another only
        if the first filled its buffer), none when it holds nothing: bytes the kernel's buffer
        work has not handed over yet wait for the next call (the next cycle, or the next
        wake-up of the sleeping device-mode loop), the caller is never held up for them."""
        self.flush_pending()
        out, self._queue = self._queue, []
        while True:
            data = self._read_waiting()
            if not data:
                return out
            out += self.deframer.feed(data)
            if len(data) < self.READ_SIZE:
                return out

    def close(self) -> None:
        try:
            self.ser.close()
        except Exception:
            pass

    def describe(self) -> str:
        return f"serial:{self.port}"
