"""The host-rendering pump's steady-state cycle, compiled (hostd/device/_fastpump.c), with
hostd.device.pump.Pump.step as its reference.

(Stub while the compiled cycle is written: `step` runs the reference.)
"""

from __future__ import annotations

IMPLEMENTATION = "python"


def step(pump, now_s: float | None = None) -> int:
    """pump.step(), compiled where the cycle is in its steady state. now_s: the host clock the
    cycle reads (tests; it must equal what pump.link.t.now() returns during the call); None:
    CLOCK_MONOTONIC. Returns the number of samples sent."""
    return pump.step()
