"""The real-time pump: every cycle, read the device's status, render what the device's
buffer is missing for the instants it will play it, and send it; and whenever a texture is
selected but the device is not playing it, bring it back.

Absolute-deadline scheduling (the next cycle is due at start + k x period, not "now +
period"), so a late cycle does not shift the ones after it; lateness past half a period is
counted as a deadline miss, a pause longer than the device's buffer as a stall.

Recovery. Machines stall a process for 100 ms and more (even under SCHED_FIFO). The device
then runs dry (underrun: it ramps to zero and keeps running) or, after its host timeout,
ramps to zero and goes idle. The pump watches every STATUS and, as soon as it runs again:
  - device idle while a texture is selected (host timeout, a reset, idle after a stall):
    STOP (clears what the device buffered while idle), re-prime the buffer, START; a device
    still ramping down (a host timeout, at most 50 ms) is let finish first, so the soft start
    begins where the device is, at zero;
  - device running but dry (underrun): refill at once;
and in both cases the output restarts with a soft start from zero (the device's own ramp
took it there), and the jitter buffer's fill target rises. Each episode is logged once when
it ends, with its cause and how long the device played nothing from its buffer.

The raised target comes back down on evidence from the device's own counters, not on a clock:
after a quiet period (JitterConfig.quiet_s without a fault or an underrun episode) it drops by
what the device's buffer never used in that period, its lowest reported fill less a margin
(LOW_WATER_MARGIN). A host that kept the buffer well filled gets its latency back at once; one
whose buffer dipped keeps the part it needed.
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from hostd.cyclestate import record
from hostd.device import protocol as pr
from hostd.device.health import (
    CLOCK_TOLERANCE,
    HOST_TIMEOUT_BIT,
    OVERFLOW_BIT,
    REPORT_SLACK_S,
    RUNNING,
    UNDERRUN_BIT,
    DeviceHealth,
)
from hostd.device.link import DeviceLink
from hostd.errors import DeviceBusy

# The device reports its fill every HP_STATUS_PERIOD_TICKS (3) ticks and plays one sample a tick,
# so its true lowest fill can be 2 below the lowest it reported: the raised target comes down to
# leave this much, one more than that, at the lowest point of the quiet period.
LOW_WATER_MARGIN = 3  # samples


# A host pause counts as a stall (PumpStats.stalls, stall_log) when it left the device's buffer
# less than this many cycles: the cycle after a pause needs its own time to read the reports and
# write, and its estimate of the fill counts samples in flight (a tty read blocked 9 ms in the
# kernel's buffer work, then a 2.6 ms cycle, emptied a 10 ms buffer; compiled: _fastpump.c).
STALL_MARGIN_CYCLES = 2

@dataclass
class JitterConfig:
    """The device buffer's fill target adapts: up after an underrun, down on the device's evidence."""

    base_fill: int = 12  # samples (4 ms at 3 kHz): the configured target
    max_fill: int = 90  # samples (30 ms): the most it rises to
    rise_factor: float = 2.0  # after an underrun: target = min(max, target x factor)
    # a raised target comes down after this long without an underrun or a fault: by what the
    # device's buffer never used meanwhile (its lowest reported fill less LOW_WATER_MARGIN)
    quiet_s: float = 1.0

    def __post_init__(self) -> None:
        hi = pr.BUFFER_CAPACITY - pr.MAX_SAMPLES
        if not 1 <= self.base_fill <= self.max_fill <= hi:
            raise ValueError(f"jitter buffer: need 1 <= base_fill <= max_fill <= {hi} samples")
        if not (self.rise_factor >= 1.0 and self.quiet_s > 0):
            raise ValueError("jitter buffer: rise_factor >= 1 and quiet_s > 0")


@dataclass
class PumpStats(record("pump_stats")):
    # in the record (hostd/device/cycle_state.toml): cycles, deadline_misses, late_batches (a batch
    # sent when the device had less than one batch queued), max_late_us, samples (sent: host side;
    # what was PLAYED comes from the device), relocks, implausible_speed
    stalls: int = 0  # host pauses that left the device's buffer < STALL_MARGIN_CYCLES cycles
    longest_stall_ms: float = 0.0
    recoveries: int = 0  # episodes where the device stopped playing and was brought back
    io_retries: int = 0  # transient write errors retried within the cycle
    io_dropped: int = 0  # messages given up after retries (the device's host timeout covers it)
    # STATUS reports flagging OVERFLOW: the device's buffer was full and it dropped samples it was
    # sent (the device's own flag; it has no counter): what it played next was not what followed
    overflows: int = 0
    # stall intervals in host monotonic time (start, end), the latest 4096, for tests/benches
    stall_log: deque = field(default_factory=lambda: deque(maxlen=4096))
    # step durations (µs, thread CPU) for percentiles, a ring of the latest 65536 cycles
    step_us: np.ndarray = field(default_factory=lambda: np.zeros(65536))


@dataclass
class _Episode:
    cause: str
    silent_since_s: float  # device time of the last sample played from the buffer before it
    host_start: float  # host time it was noticed


RAMP_DOWN = pr.STATES["RAMP_DOWN"]


def _log_nothing(_msg: str) -> None:
    pass


_NO_LOW = 1 << 16  # above any fill the device can report (u16)


class Pump(record("pump")):
    """One device link, one renderer (None = nothing selected), the recovery state machine.

    cycle: what runs the ordinary cycles in Pump.run, an object with usable(pump) -> bool and
    run(pump, start_s, k, duration_s, wake_fds) -> (k, why, due_s): the compiled cycle,
    hostd.device.fastpump, which its owner passes (the daemon's pump process, the benches);
    None, every cycle is this module's reference. The pump does not import it: the compiled
    cycle mirrors this class (COMPILED_MIRROR), not the other way round."""

    # the compiled cycle (hostd/device/_fastpump.c) does what this class's methods do: it takes
    # a pump only when it is exactly this class (a subclass, or an instance with a method
    # replaced, goes through the reference)
    COMPILED_MIRROR = True

    def __init__(self, link: DeviceLink, renderer, period_s: float = 0.001,
                 jitter: JitterConfig | None = None, log=None, cycle=None, realtime=None) -> None:
        self.renderer = renderer
        self.cycle = cycle
        # the scheduling policy (hostd.device.realtime.SchedPolicy): real-time while it streams
        self.realtime = realtime
        if realtime is not None:
            realtime.streaming(renderer is not None)
        if not 0.001 <= period_s <= 0.010 + 1e-12:
            raise ValueError("pump period must be 1..10 ms")
        self.period_s = period_s
        # A cycle longer than 1 ms sends that many ms of samples per wake-up; the fill target
        # rises by the extra samples so the buffer's margin just before the next wake-up (what
        # covers a late host) stays target_fill - 1 ms, as with a 1 ms cycle.
        self._extra = round((period_s - 0.001) * pr.SAMPLE_RATE_HZ)
        self.stats = PumpStats()
        self.health = DeviceHealth()
        self.jitter = jitter or JitterConfig(base_fill=link.target_fill,
                                             max_fill=max(link.target_fill, JitterConfig.max_fill))
        self.log = log or _log_nothing
        self.sent_codes: list[np.ndarray] = []  # kept when record=True (tests, demo summary)
        self.record = False
        self._episode: _Episode | None = None
        self._started = False  # START sent for the current selection
        self._guard_seq: int | None = None  # state is judged once this SAMPLES seq is acked
        self._guard_host_t = 0.0
        self._last_played_dev_s: float | None = None
        self._last_samples_played: int | None = None
        self._flags_seen = 0  # fault bits in the statuses taken since the last step
        self._under_seen = 0  # device underrun episodes counted at the last step
        self._last_decay = link.t.now()  # start of the quiet period the target may come down after
        self._low_fill = _NO_LOW  # the device's lowest reported fill in it (while the target is raised)
        self._last_cycle_start: float | None = None
        # counts of renderers and links already replaced (a new one per selection / reconnection)
        self._relocks_base = self._implausible_base = 0  # re-locks, implausible speeds
        self._retries_base = 0
        self._fill = self.jitter.base_fill
        self._base_fill, self._quiet_s = self.jitter.base_fill, self.jitter.quiet_s  # (for the C)
        self.attach(link)

    # ------------------------------------------------------------------ wiring
    def attach(self, link: DeviceLink) -> None:
        """Stream to `link` from now on (after a reconnection); the counters carry on."""
        old = getattr(self, "link", None)
        if old is not None and old is not link:
            self._retries_base += old.stats.io_retries
        self.link = link
        link.on_status = self._on_status
        link.on_render_status = self.health.update_render
        link.target_fill = self._link_fill()
        self.health.new_device()
        self._last_samples_played = None
        self._last_played_dev_s = None  # (another device, or the same one reset: another clock)
        self._started = False
        self._episode = None

    def _on_status(self, f: dict, device_time_s: float, fresh: bool = True) -> None:
        self.health.update(f)
        self._flags_seen |= f["fault_flags"]
        if f["fault_flags"] & OVERFLOW_BIT:
            self.stats.overflows += 1
        sp = f["samples_played"]
        if self._last_played_dev_s is not None and device_time_s < self._last_played_dev_s:
            # the device's clock went back (it was reset behind the same port): what it played
            # before is on another clock; an open episode counts its silence from now
            self._last_played_dev_s = None
            if self._episode is not None:
                self._episode.silent_since_s = device_time_s
        if (self._last_samples_played is not None and sp != self._last_samples_played
                and f["state"] == RUNNING):
            self._last_played_dev_s = device_time_s
        self._last_samples_played = sp
        if self._fill > self.jitter.base_fill and self._episode is None and f["state"] == RUNNING:
            # the evidence the raised target comes down on: how low the device's buffer went
            # (every STATUS, stale ones too: the compiled cycle hands a raised target's cycles here)
            self._low_fill = min(self._low_fill, f["buffer_fill"])
        r = self.renderer
        if r is not None and fresh:
            r.on_encoder(device_time_s, f["encoder_count"])

    @property
    def recovering(self) -> bool:
        """A texture is selected and the device is not (yet, or no longer) playing it."""
        if self.renderer is None:
            return False
        s = self.link.stats.last_status
        return self._episode is not None or not s or s["state"] != RUNNING

    @property
    def target_fill(self) -> int:
        return self._fill

    def _set_fill(self, n: int) -> None:
        self._fill = max(self.jitter.base_fill, min(self.jitter.max_fill, int(n)))
        self.link.target_fill = self._link_fill()
        self._quiet_from(self.link.t.now())

    def _quiet_from(self, now: float) -> None:
        """A new quiet period starts: the evidence gathered so far is spent."""
        self._last_decay = now
        self._low_fill = _NO_LOW

    def _link_fill(self) -> int:
        """What the link keeps queued: the fill target plus the samples of a cycle beyond 1 ms,
        or more for a renderer that does not follow the hand (a stimulus, hostd.render.stimulus:
        its `fill_samples`, latency being no matter there, buys margin against host stalls)."""
        deep = getattr(self.renderer, "fill_samples", 0) if self.renderer is not None else 0
        return min(max(self._fill + self._extra, deep), pr.BUFFER_CAPACITY - pr.MAX_SAMPLES)

    # ------------------------------------------------------------------ playback control
    def begin(self, renderer) -> None:
        """Play `renderer` from now: stop what plays, prime the buffer, start (soft start)."""
        old = self.renderer
        if old is not None and old is not renderer:
            self._relocks_base += old.motion.relocks
            self._implausible_base += old.motion.implausible
        self.renderer = renderer
        if self.realtime is not None:
            self.realtime.streaming(renderer is not None)  # (before the prime and START)
        self.link.target_fill = self._link_fill()
        self.health.select(renderer is not None)
        self._episode = None
        if renderer is None:
            if self._started:
                self.link.stop()
            self._started = False
            return
        self._ready()
        self._restart(first=True)
        # from START the device plays the prime: the next cycle's pause counts from here (a
        # first cycle held up past the prime was an underrun with no stall to explain it; the
        # link's clock: time.monotonic() for every transport the compiled cycle drives)
        self._last_cycle_start = self.link.t.now()

    def _ready(self) -> None:
        """Load what the cycles after START need, before START: from START on the device plays
        the primed buffer (the fill target, 4 ms by default) and the next cycle must come before
        it runs dry. The compiled cycle's modules (hostd.device.fastpump and the transports it
        tells apart) were imported by the first run() after begin(): 20-60 ms, measured, so
        every stream began with an underrun (and a doubled fill target)."""
        if self.cycle is not None:
            self.cycle.usable(self)  # (imports the transports it checks for)

    def end(self) -> None:
        """Stop playing (the device ramps to zero)."""
        self.begin(None)

    def _restart(self, first: bool = False) -> None:
        link = self.link
        r = self.renderer
        if not first or self._started:
            link.reset_stream()  # STOP: the device drops what it buffered while not playing
        # the device's present state, not a backlog: a link left unread for a while (a texture
        # built between the handshake and the start) holds ~0.7 s of old STATUS, on which the
        # primed samples stay "in flight" until they are read through, so nothing more was sent
        # and the device played its primed buffer dry (DAC log: the prime, then an underrun)
        link.catch_up()
        # the device ramped to zero; fade in from there, from the prime's first play instant
        r.restart(link.next_play_time_s())
        self._send(link.wanted_to_prime())  # pre-fill, then start
        link.start()
        self._started = True
        self._guard_seq = link.next_seq()  # the first SAMPLES after START
        self._guard_host_t = link.t.now()
        self._under_seen = self.health.underruns
        self._flags_seen = 0

    def _state_known(self) -> bool:
        """Do the statuses reflect our latest START? (messages are handled in order: once the
        device acknowledges a SAMPLES message sent after START, it has taken START too)"""
        if self._guard_seq is None:
            return True
        if self.link.acked(self._guard_seq) or self.link.t.now() - self._guard_host_t > 0.1:
            self._guard_seq = None
            return True
        return False

    def _supervise(self) -> None:
        """Compare what the device does with what it should do; act on a difference."""
        s = self.link.stats.last_status
        if not s or self.renderer is None or not self._state_known():
            self._flags_seen = 0
            return
        flags, self._flags_seen = self._flags_seen, 0
        under = self.health.underruns
        new_underrun = under != self._under_seen
        self._under_seen = under
        if self._episode is None:
            cause = None
            if s["state"] != RUNNING:
                cause = "host timeout" if flags & HOST_TIMEOUT_BIT else "device idle"
            elif new_underrun or flags & UNDERRUN_BIT:
                cause = "underrun"
            if cause is None:
                return
            since = self._last_played_dev_s
            if since is None:
                since = self.link.device_time_s
            self._episode = _Episode(cause, since, self.link.t.now())
            if cause == "underrun":
                self._set_fill(self._fill * self.jitter.rise_factor)
                self.renderer.restart(self.link.next_play_time_s())
            else:
                if flags & UNDERRUN_BIT or new_underrun:
                    self._set_fill(self._fill * self.jitter.rise_factor)
                if s["state"] != RAMP_DOWN:
                    self._restart()
            return
        # an episode is open: is the device playing again?
        if s["state"] != RUNNING:
            if self._episode.cause == "underrun":  # the underrun outlasted the host timeout
                self._episode.cause = "host timeout" if flags & HOST_TIMEOUT_BIT else "device idle"
            if s["state"] != RAMP_DOWN:
                self._restart()
            # (else the device is still ramping its output to zero after a host timeout, for at
            # most HP_RAMP_TICKS: the soft start begins once it is there, from zero as it assumes)
            return
        if flags & UNDERRUN_BIT or self._last_played_dev_s is None \
                or self._last_played_dev_s <= self._episode.silent_since_s:
            return
        ep, self._episode = self._episode, None
        self.stats.recoveries += 1
        silent_ms = (self._last_played_dev_s - ep.silent_since_s) * 1e3
        pause = ""
        paused_s = 0.0
        if self.stats.stall_log:
            a, b = self.stats.stall_log[-1]
            if ep.host_start - b < 0.05:
                paused_s = b - a
                pause = f" (the host paused {paused_s * 1e3:.0f} ms)"
        # the device's figure within what the host knows: the silence began at most the host's pause
        # before it was noticed, and ended by now (its clock 1 % fast, a report late)
        host_s = self.link.t.now() - ep.host_start + paused_s
        most_ms = (host_s * (1 + CLOCK_TOLERANCE) + REPORT_SLACK_S) * 1e3
        silent = f"{silent_ms:.0f} ms" if silent_ms <= most_ms else f"at most {most_ms:.0f} ms"
        claimed = "" if silent_ms <= most_ms else " (its clock claimed more than the host allows)"
        self.log(f"playback recovered after {ep.cause}{pause}: {silent} without samples from the buffer"
                 f"{claimed}; fill target now {self._fill / pr.SAMPLE_RATE_HZ * 1e3:.1f} ms")

    def _decay(self) -> None:
        """A raised target comes down after a quiet period by what the device's buffer never
        used in it (its lowest reported fill less LOW_WATER_MARGIN), at once; a buffer that
        dipped that low keeps its target and a new quiet period starts."""
        now = self.link.t.now()
        if self._fill <= self.jitter.base_fill:
            self._last_decay = now  # (at base: nothing gathered, _low_fill stays unset)
        elif self._episode is not None:
            self._quiet_from(now)
        elif now - self._last_decay >= self.jitter.quiet_s:
            spare = self._low_fill - LOW_WATER_MARGIN if self._low_fill != _NO_LOW else 0
            if spare > 0:
                self._set_fill(self._fill - spare)
            else:
                self._quiet_from(now)

    # ------------------------------------------------------------------ one cycle
    def _send(self, n: int) -> int:
        if n <= 0 or self.renderer is None:
            return 0
        link = self.link
        t0 = link.next_play_time_s()
        t_play = t0 + np.arange(n) / pr.SAMPLE_RATE_HZ
        r = self.renderer
        codes = r.render_codes(t_play)
        sent = self._send_codes(codes)
        if sent < len(codes) and hasattr(r, "unsent"):
            r.unsent(len(codes) - sent)  # (a stimulus goes on where the device's samples end)
        return sent

    def _send_codes(self, codes: np.ndarray, first: int = 0) -> int:
        """SAMPLES for `codes`, of which `first` went out already (the compiled cycle hands a
        write that did not go through over here, with what it sent before it)."""
        try:
            sent = first + self.link.send_samples(codes[first:]) if first < len(codes) else first
        except DeviceBusy:
            if first == 0:
                self.stats.io_dropped += 1
                return 0
            sent = first  # (send_samples stops at a busy write once something went out)
        if self.record:
            self.sent_codes.append(codes[:sent])
        self.stats.samples += sent
        return sent

    def step(self) -> int:
        """One cycle: poll, supervise, render, send. Returns the number of samples sent."""
        self.link.poll()
        return self.after_poll()

    def after_poll(self) -> int:
        """The cycle after its messages are in: supervise, render, send (the compiled cycle,
        hostd.device.fastpump, hands over here when a cycle leaves its steady state)."""
        link = self.link
        if self.renderer is None:
            return 0
        self._supervise()
        self._decay()
        fill = link.fill_estimate()
        n = link.wanted(fill)
        if n == 0:
            return 0
        if fill < self.renderer.cfg.samples_per_batch:
            self.stats.late_batches += 1
        sent = self._send(n)
        self._motion_stats()
        return sent

    def _motion_stats(self) -> None:
        m = self.renderer.motion
        self.stats.relocks = self._relocks_base + m.relocks
        self.stats.implausible_speed = self._implausible_base + m.implausible

    def run(self, duration_s: float | None = None, stop=None, each_cycle=None, wake_fds=(),
            compiled: bool = True) -> PumpStats:
        """Cycle until duration_s has passed or stop() returns True; each_cycle() runs at the
        start of every cycle the reference loop runs (the daemon's pump takes its commands and
        publishes counters).

        With the compiled cycle (hostd.device.fastpump, compiled=True, where it applies) a
        cycle and the ordinary ones after it run compiled, for at most fastpump.BUDGET_S or until
        one of wake_fds is readable (a command, a udev event): each_cycle() and stop() are then
        asked at least that often, and at the next deadline after a command."""
        cycle = self.cycle
        fast = compiled and cycle is not None and cycle.usable(self)
        start = time.monotonic()
        k = 0
        st = self.stats
        while True:
            now = time.monotonic()
            if duration_s is not None and now - start >= duration_s:
                break
            last = self._last_cycle_start
            margin_s = self._link_fill() / pr.SAMPLE_RATE_HZ - STALL_MARGIN_CYCLES * self.period_s
            if last is not None and now - last > margin_s:
                # a host pause that left the buffer less than STALL_MARGIN_CYCLES cycles: the device
                # may have run dry before this cycle's samples reach it
                if now - last > max(2 * self.period_s, 0.004):
                    st.stalls += 1
                    st.longest_stall_ms = max(st.longest_stall_ms, (now - last) * 1e3)
                    st.stall_log.append((last, now))
            self._last_cycle_start = now
            if each_cycle is not None:
                each_cycle()
            if stop is not None and stop():
                break
            if fast:  # this cycle and the ordinary ones after it, compiled
                k, why, due = cycle.run(self, start, k, duration_s, wake_fds)
                if why != "reference":
                    if due:
                        time.sleep(max(0.0, due - time.monotonic()))
                    continue
            c0 = time.thread_time()
            try:
                self.step()
            except DeviceBusy:
                st.io_dropped += 1
            k, due = self._end_cycle(c0, start, k)
            if due:
                time.sleep(max(0.0, due - time.monotonic()))
        return st

    def _end_cycle(self, c0: float, start: float, k: int) -> tuple[int, float]:
        """The end of one cycle of run(): its CPU time, counters, the next deadline on the grid
        start + k x period. Returns (k, the deadline to sleep until, or 0.0 when late: a late
        cycle skips the missed ones and keeps the grid)."""
        st = self.stats
        ring = st.step_us
        ring[st.cycles % ring.size] = (time.thread_time() - c0) * 1e6
        st.cycles += 1
        st.io_retries = self._retries_base + self.link.stats.io_retries
        k += 1
        due = start + k * self.period_s
        now = time.monotonic()
        if now > due:
            late = (now - due) * 1e6
            st.max_late_us = max(st.max_late_us, late)
            if late > self.period_s * 0.5e6:
                st.deadline_misses += 1
            return int((now - start) / self.period_s), 0.0
        return k, due

    def step_percentiles_us(self) -> tuple[float, float, float]:
        """p50, p99, p99.9 of the CPU time of one cycle (the latest 65536 cycles)."""
        n = min(self.stats.cycles, self.stats.step_us.size)
        if n == 0:
            return (0.0, 0.0, 0.0)
        p = np.percentile(self.stats.step_us[:n], [50, 99, 99.9])
        return (float(p[0]), float(p[1]), float(p[2]))
