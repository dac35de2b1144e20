"""What the pump process publishes and where its lifecycle is: the counters' layout in shared memory
(a seqlock), the states and render reasons, the Phase, and the publishing of one snapshot."""

from __future__ import annotations

import enum
import sys
import time

# Counters published in shared memory (float64 each). The device_* fields and
# played_fraction come from the device's own STATUS counters (hostd.device.health), never
# from what the host sent; stalls/recoveries/target_fill describe the host's side.
STAT_FIELDS = ("cycles", "deadline_misses", "late_batches", "samples", "fill",
               "speed_mm_s", "state", "connected", "malformed", "max_late_us", "reconnects",
               "texture_serial", "device_state", "device_fault_bits", "device_underruns",
               "device_samples_played", "played_fraction", "device_resets", "stalls",
               "longest_stall_ms", "recoveries", "target_fill", "implausible_speed", "relocks",
               "io_retries", "io_dropped", "batch_p50_us", "batch_p99_us", "batch_p999_us",
               "device_time_s", "render_at", "device_uploads", "wait_ticks", "render_reason",
               "device_host_lost", "device_reuploads", "device_rendered_s", "device_faded_s",
               "device_idle_s", "wakeups", "compiled_cycles", "voluntary_switches", "busy_until_s",
               "device_elapsed_s", "device_overflows", "device_report_host_s",
               "publish_seq")  # odd while publish() writes: readers take a whole snapshot (a seqlock)
PUBLISH_SEQ = len(STAT_FIELDS) - 1
STAT_INDEX = {name: i for i, name in enumerate(STAT_FIELDS)}  # no linear search per put
FLOAT_FIELDS = {"speed_mm_s", "played_fraction", "device_time_s", "longest_stall_ms", "max_late_us",
                "batch_p50_us", "batch_p99_us", "batch_p999_us", "device_rendered_s", "device_faded_s",
                "device_idle_s", "busy_until_s", "device_elapsed_s", "device_report_host_s"}
# why the texture renders where it does (`render_reason`, published as the index)
RENDER_REASONS = ("the display renders it (protocol v2, its CAPS hold the texture)",
                  "configured: [render] where = \"host\"",
                  "the display runs protocol v1 firmware (no device rendering)",
                  "the display reported no render capability (CAPS)",
                  "the texture has more components than the display holds (CAPS max_components)",
                  "the equalizer has more sections than the display runs (CAPS max_sections)",
                  "the display refused the upload (see the log)",
                  "no texture selected")
STATE_CODES = {"starting": 0, "waiting": 1, "idle": 2, "playing": 3, "stopped": 4, "recovering": 5}
STATE_NAMES = {v: k for k, v in STATE_CODES.items()}


class Phase(enum.Enum):
    """The pump process's lifecycle, one named state at a time. Each says what the published
    `state` becomes on entering it (STATE_CODES; None: the last one stands), whether a display is
    connected, whether something plays, and whether the host streams it (the periodic loop:
    pump.run) or the display only needs supervising (the sleeping loop: DeviceMode.run, where the
    display can render). While something plays, publish() refines "playing" to "recovering" when
    the display is not (yet, or no longer) playing it.

    A stop is asked at any moment (SIGTERM, the daemon's death, "quit": PumpProcess.stopping) and
    is not a phase of its own until the loops have ended: until then the phase says what the
    display does, which the stop steps and the last publishes need."""

    #             (what it is,                       state on entry, connected, playing, host streams)
    STARTING = ("starting: no display tried yet", "starting", False, False, False)
    WAITING = ("waiting for a display", "waiting", False, False, False)
    CONNECTING = ("connected, being set up", None, True, False, False)
    IDLE = ("connected, nothing plays", "idle", True, False, False)
    HOST = ("playing the texture, rendered on the host", "playing", True, True, True)
    DEVICE = ("playing the texture, rendered by the display", "playing", True, True, False)
    STIMULUS = ("playing a stimulus, streamed by the host", "playing", True, True, True)
    STOPPING = ("stopping: the display told to stop, the link closed", None, False, False, False)
    STOPPED = ("stopped", "stopped", False, False, False)

    def __init__(self, what: str, state: str | None, connected: bool, playing: bool, streams: bool) -> None:
        self.what = what
        self.code = None if state is None else STATE_CODES[state]
        self.connected = connected
        self.playing = playing
        self.streams = streams  # the pump streams a renderer (pump.renderer is not None)



class PumpCounters:
    """The counters the pump publishes in `stats` (shared memory, STAT_FIELDS): each publish one
    snapshot, from what the process passes it (its phase, link, pump, display and guards)."""

    def __init__(self, stats, rate_hz: int, rendering_state: int, voluntary_switches) -> None:
        self.stats = stats
        self.rate_hz = rate_hz
        self.rendering_state = rendering_state  # the display's state while it renders its texture
        # the kernel's count of the pump's sleeps
        self.voluntary_switches = voluntary_switches
        self.last_pct = 0.0  # host rendering: the last percentiles published
        # CLOCK_MONOTONIC when the host received the latest report (on any link) that
        # device_elapsed_s counts up to: the host's time of the same report (0.0: none yet)
        self.report_host_s = 0.0

    def put(self, name: str, value: float) -> None:
        self.stats[STAT_INDEX[name]] = value

    def publish(self, phase, link, pump, dev, transport, claims) -> None:
        stats = self.stats
        seq = stats[PUBLISH_SEQ]
        stats[PUBLISH_SEQ] = seq + 1  # odd: a snapshot is being written
        try:
            self._publish(phase, link, pump, dev, transport, claims)
        finally:
            stats[PUBLISH_SEQ] = seq + 2

    def _publish(self, phase, link, pump, dev, transport, claims) -> None:
        now = time.monotonic()
        claims.check_messages(transport, link, now)
        claims.check_flood(transport, link, now)
        s = link.stats.last_status
        if s:
            self.put("fill", s["buffer_fill"])
            self.put("malformed", s["malformed"])
            self.put("device_time_s", link.device_time_s)  # the device's clock, unwrapped
        h = pump.health
        claims.check_bounds(transport, link, h, now)
        claims.check_resets(transport, h)
        bounds = claims.bounds
        rate = self.rate_hz
        self.put("device_state", h.state)
        self.put("device_fault_bits", h.recent_fault_bits())
        self.put("device_underruns", bounds["underruns"].shown)
        self.put("device_samples_played", bounds["samples"].shown)
        self.put("played_fraction", h.played_fraction)
        self.put("device_resets", h.resets)
        self.put("device_host_lost", h.host_lost)
        self.put("device_rendered_s", bounds["rendered"].shown / rate)
        self.put("device_faded_s", bounds["faded"].shown / rate)
        self.put("device_idle_s", bounds["idle"].shown / rate)
        self.put("device_elapsed_s", bounds["elapsed"].shown)
        # (a new link's 0.0 before its first report: the old link's latest stands)
        self.report_host_s = max(self.report_host_s, link.status_host_time)
        self.put("device_report_host_s", self.report_host_s)
        # the state while something plays: "recovering" while the display is not (yet, or no
        # longer) playing it. (A texture whose upload gave way to a stop is not rendering: the
        # state put when it began stands, as while nothing plays)
        if phase is Phase.DEVICE:
            if dev.rendering:
                rs = link.render_status
                if rs is not None:  # the display's own measure, from its encoder's edge times
                    self.put("speed_mm_s", rs["speed_mm_s"])
                self.put("state", STATE_CODES["recovering" if s and s["state"] != self.rendering_state
                                              else "playing"])
        elif phase.streams:
            self.put("speed_mm_s", pump.renderer.motion.velocity_mm_s)
            self.put("state", STATE_CODES["recovering" if pump.recovering else "playing"])
        st = pump.stats
        for name in ("cycles", "samples", "late_batches", "deadline_misses", "max_late_us", "stalls",
                     "longest_stall_ms", "implausible_speed", "relocks", "io_retries", "io_dropped"):
            self.put(name, getattr(st, name))
        self.put("recoveries", st.recoveries + (dev.recoveries if dev is not None else 0))
        self.put("device_overflows", st.overflows)  # reports with the display's OVERFLOW flag
        if dev is not None:
            self.put("device_uploads", dev.uploads)
            self.put("device_reuploads", dev.recoveries)
            self.put("wakeups", dev.wakeups)
            # the kernel's count of the pump's sleeps, read at the same instant (bench soak sets
            # the loop's runs against it: a wake-up that is not a run would show here)
            self.put("voluntary_switches", self.voluntary_switches())
        self.put("target_fill", pump.target_fill)
        fastpump = sys.modules.get("hostd.device.fastpump")  # loaded by host rendering only
        self.put("compiled_cycles", fastpump.compiled_cycles() if fastpump is not None else 0)
        if phase.streams and now - self.last_pct >= 5.0:
            # percentiles of the host-rendering cycle every 5 s (a sort of 65536 cycles: ~1 ms)
            self.last_pct = now
            p50, p99, p999 = pump.step_percentiles_us()
            self.put("batch_p50_us", p50)
            self.put("batch_p99_us", p99)
            self.put("batch_p999_us", p999)
