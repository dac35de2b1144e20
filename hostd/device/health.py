"""Playback health from the device's own counters, never from the host's bookkeeping.

Every STATUS carries the device's state, its sticky fault flags, and wrapping counters
(samples played from the buffer: u32; underrun episodes: u16) stamped with the device's own
clock (u32 µs). `DeviceHealth` unwraps them into totals since the daemon started, and keeps
the played fraction of the current selection: samples the device played from its buffer
over the samples due (device time elapsed x 3 kHz) since the texture was selected.

In device mode (protocol v2, the display renders itself) nothing is played from the buffer:
the display's RENDER_STATUS counts its own ticks, rendered at full gain, faded (fading in or
out) and idle, and the episodes of a lost host. The played fraction of a selection rendered on
the device is then rendered-at-full-gain ticks over ticks due (device time x 3 kHz) since the
texture first reached full gain: a display that faded out (its host lost and the hand still)
or went idle does not count as playing.

Counters are accumulated as wrap-aware deltas between consecutive STATUS (RENDER_STATUS)
messages, so a lost message (a host stall overflows the link's buffer) loses nothing, and a
new device or a device reset (its counters go back, or its clock does) starts a new baseline
instead of a negative count. Nothing here allocates per STATUS beyond a few Python floats.
"""

from __future__ import annotations

from hostd.cyclestate import record
from hostd.device import protocol as pr

STATE_NAMES = {v: k.lower() for k, v in pr.STATES.items()}  # 0 idle, 1 running, 2 ramp_down
FAULT_NAMES = tuple((name.lower(), bit) for name, bit in pr.FAULTS.items())
RUNNING = pr.STATES["RUNNING"]
RENDERING = pr.STATES.get("RENDERING", -1)  # protocol v2: the device renders itself
UNDERRUN_BIT = pr.FAULTS["UNDERRUN"]
HOST_TIMEOUT_BIT = pr.FAULTS["HOST_TIMEOUT"]
OVERFLOW_BIT = pr.FAULTS["OVERFLOW"]
# a gap in device time between two STATUS messages longer than this is not a gap: the
# device clock went back or jumped (a reset, another device); the counters re-baseline
MAX_GAP_US = 600_000_000
M32 = 0xFFFFFFFF
FULL_GAIN_STATES = (pr.RENDER_STATES["ON"], pr.RENDER_STATES["CROSSFADE"])
# a device's clock may run this much faster than the host's, and a report arrive this late
CLOCK_TOLERANCE = 0.01
REPORT_SLACK_S = 0.5


class HostBound:
    """One of a device's counters (a total since the daemon started) as the host shows it: never
    above what the host can vouch for. A device's clock may leap forward by up to MAX_GAP_US
    between two reports (the host may have stalled that long), and its counters with it, so a
    device that lies is believed by DeviceHealth; its total is checked here against the host's
    own knowledge (`most`, which holds `slack` of tolerance), and what is above it is set aside
    for good: the count goes on from the bound less the slack, so honest counting after a lie
    (a buffer draining, a late report) is not called impossible again. link_up(now): a new link;
    its counts may grow from what is shown now."""

    def __init__(self) -> None:
        self.excess = 0.0  # claimed but not vouched for, since the daemon started
        self.shown = 0.0
        self.base = 0.0  # shown when the link came up
        self.t0 = 0.0

    def link_up(self, now_s: float, claimed: float) -> None:
        """A new link at now_s; `claimed`: the device's total now (what the old link counted
        after the last look, too: none of it is the new link's)."""
        self.base, self.t0 = claimed - self.excess, now_s

    def within_time(self, now_s: float, per_s: float) -> tuple[float, float]:
        """(most, slack): the count grown at per_s a second since the link came up (the device's
        clock 1 % fast, a report 0.5 s late)."""
        slack = REPORT_SLACK_S * per_s
        return self.base + (now_s - self.t0) * (1 + CLOCK_TOLERANCE) * per_s + slack, slack

    def take(self, claimed: float, most: float, slack: float) -> float:
        """The device's total `claimed`, at most `most`: sets .shown; returns by how much this
        claim passed the bound (0 when it holds)."""
        v = claimed - self.excess
        over = v - most
        if over > 0:
            self.excess += v - (most - slack)
            v = most - slack
        self.shown = v
        return max(over, 0.0)


def fault_names(flags: int) -> list[str]:
    return [name for name, bit in FAULT_NAMES if flags & bit]


class DeviceHealth(record("health")):
    """Feed every STATUS (in arrival order); read totals and the current selection's figures."""

    def __init__(self, fault_window_s: float = 1.0) -> None:
        self.fault_window_s = fault_window_s
        self.underruns = 0  # episodes since the daemon started (all devices, wrap-aware)
        self.samples_played = 0  # from the buffer, since the daemon started
        self.resets = 0  # counters or clock went back: a device reset or another device
        self.state = -1
        self._recent_flags: dict[int, float] = {}  # fault bit -> device time (s) last seen
        self._last: dict | None = None
        self._time_s = 0.0  # unwrapped device time of the latest STATUS (this device)
        # the current selection
        self._sel_active = False
        self._sel_due = 0.0  # ticks due since selection (device time x rate)
        self._sel_played = 0
        self._sel_started = False
        self._sel_device = False  # the selection renders on the device: RENDER_STATUS counts
        # device mode, from RENDER_STATUS (totals since the daemon started, wrap-aware)
        self.rendered_ticks = 0  # ticks the display rendered the texture at full gain
        self.faded_ticks = 0  # ticks it rendered below full gain (fading in or out)
        self.idle_ticks = 0  # ticks it neither rendered nor played
        self.host_lost = 0  # episodes in which the display counted its host as lost
        self._last_rs: dict | None = None

    # ------------------------------------------------------------ input
    def new_device(self) -> None:
        """A (re)connected device: its counters start a new baseline."""
        self._last = None
        self._last_rs = None

    def select(self, active: bool, device: bool = False) -> None:
        """A texture was selected (True) or playback stopped (False): restart the fraction.
        device: the display renders it (the fraction comes from RENDER_STATUS)."""
        self._sel_active = active
        self._sel_device = device and active
        self._sel_due = 0.0
        self._sel_played = 0
        self._sel_started = False

    def update(self, f: dict) -> None:
        last = self._last
        self._last = f
        self.state = f["state"]
        if last is None:
            return
        dt_us = (f["device_time_us"] - last["device_time_us"]) & 0xFFFFFFFF
        d_played = (f["samples_played"] - last["samples_played"]) & 0xFFFFFFFF
        d_under = (f["underruns"] - last["underruns"]) & 0xFFFF
        if dt_us > MAX_GAP_US or d_played > dt_us * pr.SAMPLE_RATE_HZ // 1_000_000 + 3:
            # the clock or a counter went back (it wrapped "forwards" by nearly 2^32): a reset
            self.resets += 1
            return
        self._time_s += dt_us * 1e-6
        self.samples_played += d_played
        self.underruns += d_under
        for bit in (b for _, b in FAULT_NAMES if f["fault_flags"] & b):
            self._recent_flags[bit] = self._time_s
        if self._sel_active and not self._sel_device:
            if not self._sel_started and f["state"] == RUNNING:
                self._sel_started = True  # count from the first STATUS that shows it playing
            if self._sel_started:
                self._sel_due += dt_us * 1e-6 * pr.SAMPLE_RATE_HZ
                self._sel_played += d_played

    def update_render(self, rs: dict) -> None:
        """A RENDER_STATUS (device mode): the display's own tick counters."""
        last = self._last_rs
        self._last_rs = rs
        if last is None:  # a new baseline; counting may start from it
            if self._sel_device and not self._sel_started:
                self._sel_started = rs["render_state"] in FULL_GAIN_STATES
            return
        dt_us = (rs["device_time_us"] - last["device_time_us"]) & M32
        d_rend = (rs["rendered_ticks"] - last["rendered_ticks"]) & M32
        d_fade = (rs["faded_ticks"] - last["faded_ticks"]) & M32
        d_idle = (rs["idle_ticks"] - last["idle_ticks"]) & M32
        if dt_us > MAX_GAP_US or d_rend + d_fade + d_idle > dt_us * pr.SAMPLE_RATE_HZ // 1_000_000 + 3:
            self.resets += 1  # the clock or a counter went back: a reset, a new baseline
            return
        self.rendered_ticks += d_rend
        self.faded_ticks += d_fade
        self.idle_ticks += d_idle
        self.host_lost += (rs["host_lost_count"] - last["host_lost_count"]) & 0xFFFF
        if not self._sel_device:
            return
        if not self._sel_started:
            # count from the first report that shows the texture at full gain (the selection's
            # own fade-in is not due, as a host-rendered selection counts from its first run)
            self._sel_started = rs["render_state"] in FULL_GAIN_STATES
            return
        self._sel_due += dt_us * 1e-6 * pr.SAMPLE_RATE_HZ
        self._sel_played += d_rend

    # ------------------------------------------------------------ output
    @property
    def elapsed_s(self) -> float:
        """Device time elapsed between consecutive reports, summed over every link since the
        daemon started (a reset, a new device or a clock that went back adds nothing): never goes
        back, unlike a device's clock."""
        return self._time_s

    @property
    def state_name(self) -> str:
        return STATE_NAMES.get(self.state, "unknown")

    def recent_fault_bits(self) -> int:
        """Fault bits the device reported within the last fault_window_s of device time."""
        t0 = self._time_s - self.fault_window_s
        return sum(bit for bit, t in self._recent_flags.items() if t >= t0)

    def recent_faults(self) -> list[str]:
        return fault_names(self.recent_fault_bits())

    @property
    def played_fraction(self) -> float:
        """Samples played from the buffer (device mode: ticks rendered at full gain) over
        samples due since the selection first played (1.0 until the device has run for a full
        STATUS period; NaN-free)."""
        if self._sel_due < 1.0:
            return 1.0 if self._sel_active else 0.0
        return min(1.0, self._sel_played / self._sel_due)

