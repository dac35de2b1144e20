"""The pump's scheduling policy: real-time while it streams, an ordinary process while it supervises.

A pump that streams samples (host rendering, a stimulus) must write every millisecond, and the
display's buffer covers only a few: a SCHED_OTHER pump waited 4-6 ms behind a busier neighbour
on a quiet machine, and the display ran dry (docs/benchmarks.md, "Link latency"). SCHED_FIFO
removes those waits. A pump that supervises a display rendering itself (device mode) sleeps
between reports 300 ms apart and needs none of it; at SCHED_FIFO it woke while the kernel still
handed the display's report over, and its read (TIOCINQ takes the line discipline's lock) waited
again: 1.8 sleeps per run of its loop instead of 1.0 (`hostd bench soak --render device --check
ci`, 2026-11-27). So the pump asks for SCHED_FIFO when it begins to stream and gives it back when
it stops (`Pump(realtime=...)`).

SCHED_RESET_ON_FORK: nothing the pump starts (its equalizer's design, for one) is real-time.
Not permitted (no LimitRTPRIO, not root): one line says what to do, once, and the pump streams
SCHED_OTHER as before; it does not ask again.
"""

from __future__ import annotations

import os


class SchedPolicy:
    """SCHED_FIFO at `priority` while streaming(True), SCHED_OTHER otherwise; priority 0: never
    real-time. `policy` says what the calling thread runs now (and why not real-time)."""

    def __init__(self, priority: int, log=None) -> None:
        self.priority = priority
        self.log = log
        self.policy = "SCHED_OTHER"
        self._denied = priority <= 0
        self._fifo = False
        self._said = False

    def streaming(self, on: bool) -> None:
        if on == self._fifo or (on and self._denied):
            return
        flags = getattr(os, "SCHED_RESET_ON_FORK", 0)
        try:
            if on:
                os.sched_setscheduler(0, os.SCHED_FIFO | flags, os.sched_param(self.priority))
            else:  # (always permitted; an unprivileged thread keeps RESET_ON_FORK once set)
                os.sched_setscheduler(0, os.SCHED_OTHER | flags, os.sched_param(0))
        except (OSError, AttributeError) as e:
            if on:
                self._denied = True
                why = getattr(e, "strerror", None) or str(e)
                self.policy = f"SCHED_OTHER (SCHED_FIFO {self.priority} not permitted: {why})"
                self._say(f"pump: SCHED_FIFO {self.priority} not permitted ({why}); it streams SCHED_OTHER: "
                          "grant LimitRTPRIO/CAP_SYS_NICE (systemd/hostd.service does), or set [realtime] "
                          "sched_fifo_priority = 0 not to ask")
            return
        self._fifo = on
        self.policy = f"SCHED_FIFO {self.priority}" if on else "SCHED_OTHER"
        if on and not self._said:
            self._said = True
            self._say(f"pump streams SCHED_FIFO priority {self.priority} (supervises SCHED_OTHER)")

    def _say(self, msg: str) -> None:
        if self.log is not None:
            self.log(msg)
