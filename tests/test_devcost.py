"""The device-mode sleeping loop's cheap receive path over serial (issue 22, ≤ 0.5 % of a core):
the port wakes once per few report pairs (Transport.wake_after: the line discipline's VMIN),
one read takes every message waiting (Transport.drain), and everything else still wakes at the
first byte. The CPU figure itself is `hostd bench soak --render auto` (docs/benchmarks.md)."""

from __future__ import annotations

import os
import pty
import select

import pytest

from hostd.device import protocol as pr
from hostd.device.devmode import DeviceMode
from hostd.device.seriallink import SerialTransport


@pytest.fixture
def port():
    master, slave = pty.openpty()
    t = SerialTransport(os.ttyname(slave))
    yield master, t
    t.close()
    os.close(master)
    os.close(slave)


def _pair() -> bytes:
    return (pr.frame(pr.encode("STATUS", state=pr.STATES["RENDERING"]))
            + pr.frame(pr.encode("RENDER_STATUS", render_state=2)))


def _readable(t) -> bool:
    p = select.poll()
    p.register(t.fileno(), select.POLLIN)
    return bool(p.poll(50))


def test_wakes_once_per_report_pairs_and_drains_them_in_one_pass(port):
    master, t = port
    sizes = (pr.LAYOUTS["STATUS"].size, pr.LAYOUTS["RENDER_STATUS"].size) * DeviceMode.REPORTS_PER_WAKE
    t.wake_after(sizes)
    for _ in range(DeviceMode.REPORTS_PER_WAKE - 1):
        os.write(master, _pair())
        assert not _readable(t)  # the kernel counts the bytes: no wake-up per report
    os.write(master, _pair())
    assert _readable(t)
    t.wake_after(None)
    msgs = t.drain()
    assert [pr.decode(m)[0] for m in msgs] == ["STATUS", "RENDER_STATUS"] * DeviceMode.REPORTS_PER_WAKE
    assert t.drain() == []


def test_a_stopped_display_s_1ms_statuses_fill_the_count_within_a_few_ms(port):
    master, t = port
    pair = (pr.LAYOUTS["STATUS"].size, pr.LAYOUTS["RENDER_STATUS"].size)
    t.wake_after(pair * DeviceMode.REPORTS_PER_WAKE)
    status = pr.frame(pr.encode("STATUS", state=pr.STATES["IDLE"]))
    n = 0
    while not _readable(t):
        os.write(master, status)  # one per ms from a display that is not rendering
        n += 1
        assert n <= 8
    t.wake_after(None)
    assert len(t.drain()) == n


def test_outside_the_sleep_every_byte_wakes_as_before(port):
    master, t = port
    t.wake_after((200,))
    t.wake_after(None)  # the loop resets it after its poll(): acknowledgements, stream mode
    os.write(master, pr.frame(pr.encode("ACK", for_id=pr.IDS["LOAD_END"])))
    assert _readable(t)
    m = t.recv(0.1)
    assert m is not None and pr.decode(m)[0] == "ACK"
