"""A figure a log line takes from the device is bounded by what the host knows: a display that
forges its clock (a report 3,000 s on; the next honest one then reads as a wrap, 2^32 µs on)
while the pump recovers from a display it starved does not make the journal say "4294973 ms without
samples"; an honest recovery's silence is said as the device measured it."""

from __future__ import annotations

import re

from hostd.device import protocol as pr
from hostd.device.link import DeviceLink
from hostd.device.pump import Pump
from hostd.device.simdev import SimTransport
from tests.test_device import _renderer


def _recovery(forge: bool) -> str:
    """Stream on a simulated display (manual clock), starve it 50 ms (an underrun), then let it
    play again; forge: its first report after the starving is forged as said above. The pump's
    recovery line."""
    lines: list[str] = []
    t = SimTransport(realtime=False)
    link = DeviceLink(t, target_fill=12)
    t.advance(3)
    link.handshake(timeout_s=0.1)
    pump = Pump(link, None, log=lines.append)
    pump.begin(_renderer())
    for _ in range(300):  # 0.3 s of streaming
        t.advance(3)
        pump.step()
    t.advance(150)  # the host away for 50 ms: the display runs dry
    for _ in range(500):
        if forge and pump._episode is not None:
            f = {k: v for k, v in pr.decode(t.device.status())[1].items() if k != "id"}
            f.update(device_time_us=(f["device_time_us"] + 3_000_000_000) & 0xFFFFFFFF, fault_flags=0,
                     state=pr.STATES["RUNNING"], samples_played=(f["samples_played"] + 3) & 0xFFFFFFFF)
            t.device.outbox.append(pr.encode("STATUS", **f))
            forge = False
        t.advance(3)
        pump.step()
    said = [ln for ln in lines if ln.startswith("playback recovered")]
    assert said, lines
    return said[0]


def test_a_forged_clock_does_not_reach_the_recovery_line():
    honest = _recovery(forge=False)
    silent_ms = float(re.search(r": (\d+) ms without samples", honest).group(1))
    assert 40 <= silent_ms < 500, honest
    forged = _recovery(forge=True)
    ms = [float(x) for x in re.findall(r"(\d+) ms", forged)]
    assert "ms without samples" in forged and max(ms) < 1000, forged
    assert "its clock claimed more than the host allows" in forged and "claimed" not in honest
