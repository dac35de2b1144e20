"""The real-time pump in its own process, isolated from intake and quality work.

A separate process, not a thread: the parent's threads (socket, spool, SQLite, scoring)
cannot hold a GIL that the pump needs, so Python's 5 ms switch interval never reaches it.
The parent sends commands over a Pipe (select a texture, stop, quit); the pump publishes its
counters in shared memory (no pickling per cycle) and log lines over the Pipe. After set-up
it calls gc.freeze(); the steady-state loop allocates only numpy temporaries of a few samples.
pump_main runs a PumpProcess, whose Phase names where its lifecycle is.
"""

from __future__ import annotations

import enum
import gc
import importlib
import os
import signal
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
_REASON_OF_REFUSAL = {"v1": 2, "no_caps": 3, "components": 4, "sections": 5}
# more STATUS per second than this many times the protocol's fastest report rate: a flood
FLOOD_FACTOR = 3
STATE_CODES = {"starting": 0, "waiting": 1, "idle": 2, "playing": 3, "stopped": 4, "recovering": 5}
STATE_NAMES = {v: k for k, v in STATE_CODES.items()}
# samples of silence the device plays after a stimulus before it is answered and STOPped
STIMULUS_TAIL = 6
# the display's host timeout while it plays a stimulus: what its buffer holds (the pump keeps it
# full for a stimulus: 227 samples, 76 ms) and a little more
STIMULUS_TIMEOUT_MS = 85
# the kernel's notice of the daemon's death (PR_SET_PDEATHSIG): a signal of its own, not SIGTERM
PARENT_DEATH_SIGNAL = signal.SIGUSR2


def _realtime(rt, log) -> None:
    if rt.cpu >= 0:
        try:
            os.sched_setaffinity(0, {rt.cpu})
            log(f"pump pinned to CPU {rt.cpu}")
        except OSError as e:
            log(f"pump: cannot pin to CPU {rt.cpu} ({e.strerror}); running unpinned")
    # (rt.sched_fifo_priority: the pump takes it while it streams, hostd.device.realtime)
    if rt.mlockall:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        if libc.mlockall(3) != 0:  # MCL_CURRENT | MCL_FUTURE
            log(f"pump: mlockall failed ({os.strerror(ctypes.get_errno())}); memory may page: "
                "raise LimitMEMLOCK")
        else:
            log("pump memory locked (mlockall)")


def _die_with_parent() -> None:
    """Linux: the pump gets PARENT_DEATH_SIGNAL (it ramps to zero, says "daemon gone" and exits)
    when the daemon dies, even by SIGKILL outside systemd, so no orphaned pump keeps driving the
    display. Not SIGTERM: the kernel sends it when the daemon's thread that started the pump
    exits, and under SIGKILL that can come before the daemon's other threads are gone; the pump's
    parent is then one of them (getppid() still the daemon's pid) and its pipe not yet at EOF, so
    a SIGTERM would look like a stop (systemctl kill, terminate()) and the line would be lost."""
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, int(PARENT_DEATH_SIGNAL))  # PR_SET_PDEATHSIG
        # PR_SET_NAME: `ps` and a refused raw-USB claim ("busy: pid N (hostd-pump) ...") name it
        libc.prctl(15, ctypes.c_char_p(b"hostd-pump"))
        if os.getppid() == 1:  # the parent died before prctl took effect
            os.kill(os.getpid(), PARENT_DEATH_SIGNAL)
    except (OSError, AttributeError):
        pass


DEVICE_PUBLISH_S = 0.5  # device mode: the counters published at most this often (state changes at once)
LOADING_ALLOWANCE_S = 120.0  # the daemon's watchdog allowance while the pump loads the host renderer


def preload_host_rendering(stats=None) -> None:
    """Import the host renderer and scipy.signal (its equalizer) now: a pump that will render on
    the host loads them before it plays; device mode never does. Seconds on a slow or emulated
    CPU with no progress to show: `stats` (the shared counters) carries a deadline meanwhile,
    busy_until_s (CLOCK_MONOTONIC), that the daemon's watchdog takes as liveness (bounded)."""
    if "hostd.render.pipeline" in sys.modules and "scipy.signal" in sys.modules:
        return
    if stats is not None:
        stats[STAT_INDEX["busy_until_s"]] = time.monotonic() + LOADING_ALLOWANCE_S
    try:
        from hostd.render import equalizer, pipeline  # noqa: F401

        equalizer.preload()
    finally:
        if stats is not None:
            stats[STAT_INDEX["busy_until_s"]] = 0.0


class CompiledCycle:
    """The pump's compiled cycle (hostd.device.fastpump), imported at its first use: host
    rendering and stimuli load it, device rendering never does (the supervisor stays lean)."""

    def usable(self, pump) -> bool:
        from hostd.device import fastpump

        return fastpump.usable(pump)

    def run(self, pump, start_s: float, k: int, duration_s, fds=()):
        from hostd.device import fastpump

        return fastpump.run(pump, start_s, k, duration_s, fds)


# what the pump process runs on, imported first thing (PumpProcess): before its signals, and
# frozen by gc.freeze() with the rest of the set-up; never at this module's import, which the
# daemon does for its constants. (The renderer, scipy and hostd.device.fastpump are host
# rendering's and the stimuli's, imported where they start: device mode never loads them)
DEVICE_SIDE = ("resource", "numpy", "hostd.device.devrender", "hostd.device.protocol", "hostd.device.devmode",
               "hostd.device.health", "hostd.device.hotplug", "hostd.device.link", "hostd.device.pump",
               "hostd.device.realtime", "hostd.device.transport", "hostd.errors", "hostd.service.pumpguards")


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


class Stimulus:
    """A stimulus being played (hostd.render.stimulus; the daemon's `stimulus` command): streamed
    like a host-rendered texture, through the output stage and the firmware's limits, whatever the
    hand does; answered once the device's own count of samples played covers it."""

    __slots__ = ("deadline", "duration_s", "first_seq", "id", "malformed0", "needed", "overflows0", "p0",
                 "recoveries0", "renderer", "t0", "underruns0")

    def __init__(self, sid: int, renderer, duration_s: float, now: float) -> None:
        self.id = sid
        self.renderer = renderer
        self.first_seq = None
        self.p0 = None
        self.t0 = now
        self.deadline = now + duration_s + 2.0
        self.duration_s = duration_s
        self.needed = renderer.length + STIMULUS_TAIL
        # the device's counts when it started (started()): its underruns, the pump's recoveries,
        # the reports of an overflow, the messages it dropped as malformed
        self.underruns0 = self.recoveries0 = self.overflows0 = self.malformed0 = None

    @staticmethod
    def malformed_count(link) -> int | None:
        """The device's own count of messages it dropped as malformed (a cut SAMPLES frame)."""
        st = link.stats.last_status
        return st.get("malformed") if st else None

    def started(self, pump, link) -> None:
        """START went out (pump.begin): what the stimulus is judged against from here."""
        self.first_seq = link.next_seq()  # the first SAMPLES after START: once taken, START was too
        self.underruns0, self.recoveries0 = pump.health.underruns, pump.stats.recoveries
        self.overflows0, self.malformed0 = pump.stats.overflows, self.malformed_count(link)

    def verdict(self, pump, link) -> tuple | None:
        """Once per cycle while it plays: played whole (the device's own count of samples played
        since it took the stimulus's first SAMPLES), or not (it ran dry, stopped, or not in
        time). None while it plays on; else the answer, (error or None, retry, played)."""
        h = pump.health
        if self.malformed0 is None:
            # (no STATUS heard before the stimulus: cannot be on a connected link, whose
            # handshake has one; the first one heard is the baseline, never read as damage)
            self.malformed0 = self.malformed_count(link)
        if self.p0 is None:
            if link.acked(self.first_seq):  # it took STOP (if any), the prime and START: what it
                self.p0 = h.samples_played  # played before is counted here (what since, at most, later)
        elif pump.recovering or h.underruns != self.underruns0 or pump.stats.recoveries != self.recoveries0:
            ep = pump._episode
            why = ep.cause if ep is not None else "underrun" if h.underruns != self.underruns0 else "stopped"
            n_played = h.samples_played - self.p0
            return (f"the display stopped playing the stimulus ({why}: a host stall longer than its "
                    f"buffer) after {n_played} samples: it was not played whole; ask again", True, None)
        elif pump.stats.overflows != self.overflows0 or self.malformed_count(link) != self.malformed0:
            # the device dropped samples it was sent (its buffer full: a display that fell behind
            # the host's estimate of its clock; or a frame cut on the way): it played on, from
            # later in the stimulus, without an underrun; the count of samples played cannot tell
            why = ("its buffer overflowed" if pump.stats.overflows != self.overflows0
                   else "a message of it arrived damaged")
            return (f"the display dropped samples of the stimulus ({why}): it was not played as asked; "
                    "ask again", True, None)
        elif h.samples_played - self.p0 >= self.needed:
            r = self.renderer
            played = {"samples": h.samples_played - self.p0, "stimulus_samples": r.length,
                      "limited": r.limited, "host_s": round(time.monotonic() - self.t0, 4),
                      "device_time_s": link.device_time_s}
            if r.limited:  # (cannot happen after the check; said rather than assumed)
                return f"the output stage limited {r.limited} samples of the stimulus", False, played
            return None, True, played
        if time.monotonic() > self.deadline:
            return (f"the display did not play the {self.duration_s:g} s stimulus within "
                    f"{self.deadline - self.t0:g} s; ask again", True, None)
        return None


class PumpProcess:
    """The pump process: one display link at a time (connect, play, lose it, wait for the next),
    the daemon's commands, the counters it publishes. `phase` (a Phase) is where its lifecycle
    is: the published `state` and the loop it runs follow from it."""

    def __init__(self, cfg, conn, stats) -> None:
        for name in DEVICE_SIDE:  # (loaded once: sys.modules)
            importlib.import_module(name)
        import resource

        from hostd.device.devmode import RENDERING
        from hostd.device.protocol import SAMPLE_RATE_HZ

        self.cfg, self.conn, self.stats = cfg, conn, stats
        self.rendering_state = RENDERING  # the display's state while it renders its texture
        self.rate_hz = SAMPLE_RATE_HZ
        # the kernel's count of the pump's sleeps
        self.voluntary_switches = lambda: resource.getrusage(resource.RUSAGE_SELF).ru_nvcsw
        self.phase = Phase.STARTING
        self.stopping = False  # asked to stop: SIGTERM, the daemon's death, "quit", EOF on the pipe
        self.daemon_gone = False  # the daemon died (the kernel's notice, or EOF on the pipe): said at exit
        self.parent = None
        self.texture = None  # (name, coeffs, n, length_mm): the selection, kept while no display is there
        self.stim: Stimulus | None = None  # the stimulus being played
        self.uploading = None  # the texture whose upload to the display is under way
        self.pump = None  # one Pump for the process: its counters survive reconnections
        self.link = None  # DeviceLink, this connection's
        self.transport = None
        self.dev = None  # DeviceMode while the display can render (protocol v2 with CAPS)
        self.logged_choice = None  # (render_at, reason) last logged: each choice is logged once
        self.reconnects = 0
        self.wait_ticks = 0
        self.last_pub = 0.0  # device mode: the last publish
        self.last_pct = 0.0  # host rendering: the last percentiles published
        self.claims = None  # DeviceClaims: the guards over what the display claims
        # CLOCK_MONOTONIC when the host received the latest report (on any link) that
        # device_elapsed_s counts up to: the host's time of the same report (0.0: none yet)
        self.report_host_s = 0.0

    # ------------------------------------------------------------------ the daemon's side
    def log(self, msg: str, warn: bool | None = None) -> None:
        # device loss, refusals and recoveries are warnings; set-up lines are information
        if warn is None:
            warn = msg.startswith(("device lost", "device:", "playback recovered", "device mode: the display",
                                   "pump: ")) and ", protocol v" not in msg and " playing again " not in msg
        try:
            self.conn.send(("warn" if warn else "log", msg))
        except (OSError, EOFError):
            pass

    def put(self, name: str, value: float) -> None:
        self.stats[STAT_INDEX[name]] = value

    def tell(self, **kw) -> None:  # strings and timings for `hostd status` (not per cycle: on change)
        self.info.update(kw)
        try:
            self.conn.send(("info", dict(self.info)))
        except (OSError, EOFError):
            pass

    def enter(self, phase: Phase) -> None:
        """The lifecycle moves on: the published state with it (unless the phase keeps the last)."""
        self.phase = phase
        if phase.code is not None:
            self.put("state", phase.code)

    def on_parent_death(self, *_) -> None:
        self.daemon_gone = self.stopping = True

    def on_sigterm(self, *_) -> None:  # systemctl kill, or the parent's terminate(): ramp to zero, exit 0
        self.stopping = True

    # ------------------------------------------------------------------ the process's life
    def run(self) -> None:
        self.start()
        while not self.stopping:
            if self.connect():
                self.serve()
        self.finish()

    def start(self) -> None:
        """Set-up, before the first connection."""
        from hostd.device import devrender
        from hostd.device import protocol as pr
        from hostd.device.hotplug import watch
        from hostd.device.pump import JitterConfig
        from hostd.service.pumpguards import DeviceClaims

        cfg = self.cfg
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent decides when we stop
        self.parent = os.getppid()
        signal.signal(PARENT_DEATH_SIGNAL, self.on_parent_death)  # before prctl: its default action kills
        _die_with_parent()
        _realtime(cfg.realtime, self.log)
        # hotplug: udev events where udev runs, else a retry every device.reconnect_s
        self.hot = hot = watch(cfg.device.transport)
        self.spec_kind = cfg.device.transport.partition(":")[0]
        self.info = {"transport": None, "hotplug": hot.mode, "last_reconnect_s": None, "reconnected": 0}
        self.tell()
        self.log(f"hotplug: {hot.describe()}")
        self.backlog: list = []  # udev events read but not yet acted on
        self.hot_fd = hot.fileno()
        self.hot_poll = None
        if self.hot_fd is not None:
            import select

            self.hot_poll = select.poll()
            self.hot_poll.register(self.hot_fd, select.POLLIN)
        self.arrival = [None, None]  # (CLOCK_MONOTONIC of the udev add event, of the link up) until playing
        self.rcfg = rcfg = cfg.render_config()
        out = rcfg.output
        self.limit_code = out.limit_code
        self.max_step = int(min(out.slew_um_s / pr.SAMPLE_RATE_HZ / out.um_per_code + 1, 32767))
        signal.signal(signal.SIGTERM, self.on_sigterm)
        self.enter(Phase.STARTING)
        gc.collect()
        gc.freeze()

        self.jitter = JitterConfig(base_fill=cfg.device.target_fill,
                                   max_fill=max(cfg.device.target_fill, cfg.device.max_fill))

        self.where = cfg.render.where  # auto (the default), device or host
        self.dev_params = None  # devrender.device_params(rcfg): the equalizer's design, for the display
        if self.where == "host":
            preload_host_rendering(self.stats)  # before the first connection: a selection plays at once
        else:  # designed now (in a child, ~1 s of scipy), not between a display's arrival and playing
            try:
                self.dev_params = devrender.device_params_apart(rcfg)
            except ValueError:  # (a setting the display cannot render: said when one connects, as before)
                self.dev_params = None
        self.claims = DeviceClaims(self.log, FLOOD_FACTOR)
        self.conn_fd = self.conn.fileno()

    def connect(self) -> bool:
        """Open the display, shake hands, set its limits. False when there is none (yet): after
        waiting for it. What plays on it is serve()'s (set_up(): where it renders, the selection
        again), where a display lost meanwhile is a loss like any other."""
        from hostd.device.link import DeviceLink
        from hostd.device.pump import Pump
        from hostd.device.realtime import SchedPolicy
        from hostd.device.transport import open_transport
        from hostd.errors import DeviceError, DeviceNotFound

        cfg, put = self.cfg, self.put
        self.transport = transport = None
        try:
            self.transport = transport = (open_transport(cfg.device.transport, serial=cfg.device.serial)
                                          if cfg.device.serial else open_transport(cfg.device.transport))
            self.link = link = DeviceLink(transport, target_fill=cfg.device.target_fill)
            ident = link.handshake(timeout_s=2.0)
            link.set_limits(min(self.limit_code, ident["limit_code"]),
                            min(self.max_step, ident["max_step_code"]))
            link.set_timeout(cfg.device.host_timeout_ms)
        except DeviceError as e:
            if transport is not None:  # opened, then no answer: release it (the fd, the USB claim)
                transport.close()
            put("connected", 0)
            self.enter(Phase.WAITING)
            self.log(f"device: {e}")
            self.arrival[0] = None
            self.wait_for_display(absent=isinstance(e, DeviceNotFound))
            self.reconnects += 1
            put("reconnects", self.reconnects)
            return False
        self.enter(Phase.CONNECTING)
        self.claims.link_up(link, self.pump.health if self.pump is not None else None)
        put("connected", 1)
        if self.arrival[0] is not None:
            self.arrival[1] = time.monotonic()
        self.backlog.clear()
        self.tell(transport=transport.describe(),
                  firmware=f"{ident['fw_major']}.{ident['fw_minor']}.{ident['fw_patch']}")
        self.log(f"device: {transport.describe()} firmware {ident['fw_major']}.{ident['fw_minor']}."
                 f"{ident['fw_patch']}, protocol v{ident['protocol_version']}")
        if self.pump is None:
            self.pump = Pump(link, None, period_s=cfg.device.host_cycle_ms / 1000, jitter=self.jitter,
                             log=self.log, cycle=CompiledCycle(),
                             realtime=SchedPolicy(cfg.realtime.sched_fifo_priority, self.log))
        else:
            self.pump.attach(link)
        self.dev = None
        return True

    def set_up(self) -> None:
        """Where the texture renders on this display: the display itself when it can (a v2
        display's CAPS, waited for), else the host. A display lost while its CAPS are waited
        for (unplugged within a second of its arrival) raises DeviceError to serve(): a loss,
        as during play, not the end of the pump."""
        from hostd.device import devrender
        from hostd.device import protocol as pr
        from hostd.device.devmode import DeviceMode

        cfg, link, transport = self.cfg, self.link, self.transport
        if self.where == "host":
            self.choose(False, 1)
        else:
            link.await_caps()  # a v2 display sends CAPS right after IDENT
            why = pr.render_refusal(link.ident, link.caps, 1, 0, who=transport.describe())
            if why is None:
                if self.dev_params is None:  # designed once per process, scipy kept out of it
                    self.dev_params = devrender.device_params_apart(self.rcfg)
                self.dev = dev = DeviceMode(link, self.rcfg, self.log, host_lost_ms=cfg.render.host_lost_ms,
                                            timeout_ms=cfg.device.host_timeout_ms, params=self.dev_params)
                dev.abort = lambda: self.stopping  # a stop does not wait out an upload's answers
                dev.alive = self.upload_progress  # the watchdog sees a slow upload moving
                if self.texture is None:
                    self.choose(True, 7)
            else:
                self.choose(False, _REASON_OF_REFUSAL[why[0]], why[1])
        if self.dev is None:  # the host renders: its renderer's imports now, not at the first texture
            preload_host_rendering(self.stats)

    def serve(self) -> None:
        """Connected: play until the display is lost or the process stops; then the link is
        closed (on a stop, the display told to stop first)."""
        from hostd.errors import DeviceError

        pump = self.pump
        try:
            self.set_up()
            if self.texture is not None:
                self.begin()
            else:
                self.enter(Phase.IDLE)
            # commands and udev events wake the sleeping loop at once
            fds = [self.conn.fileno()] + ([self.hot_fd] if self.hot_fd is not None else [])
            while not self.stopping:
                if self.sleeps():
                    self.dev.run(stop=self.sleeping_ends, each_wake=self.each_wake, fds=fds)
                else:
                    pump._last_cycle_start = None  # the sleeping loop's gaps are not stalls
                    pump.run(stop=self.streaming_ends, each_cycle=self.each_cycle, wake_fds=fds)
        except DeviceError as e:
            self.lost(e)
        finally:
            self.close_link()

    def sleeps(self) -> bool:
        """The display renders (or nothing is selected): sleep, no periodic loop."""
        return self.dev is not None and not self.phase.streams

    def sleeping_ends(self) -> bool:
        return self.stopping or not self.sleeps()

    def streaming_ends(self) -> bool:
        return self.stopping or self.sleeps()

    def lost(self, e) -> None:
        """The display was lost (or refused what it must take): output stopped, waiting."""
        self.drop_stimulus(f"the display was lost during the stimulus ({e})", link_up=False)
        if self.uploading is not None:  # mid-upload: nothing it holds is believed; all again on return
            self.log(f"device lost during the upload of {self.uploading} (device rendering): {e}; output "
                     "stopped, waiting; identified and uploaded to again when it returns")
            self.uploading = None
        else:
            self.log(f"device lost while {'playing' if self.phase.playing else 'idle'}: {e}; output stopped, "
                     "waiting")
        self.put("connected", 0)
        self.tell(transport=None)
        self.enter(Phase.WAITING)

    def close_link(self) -> None:
        """The link's end, lost or stopping."""
        try:  # its last counts checked now: the next link's baseline starts from what was vouched for
            self.publish()
        except Exception:
            pass
        if self.phase.connected:  # (lost: WAITING already)
            self.enter(Phase.STOPPING)
        self.pump.renderer = None
        # a stop: the display ends what it renders (or may render: an upload in flight) and
        # ramps to zero (STOP also ends a stimulus or a stream); each step on its own, so one
        # failing does not skip the next
        steps = []
        if self.stopping and self.dev is not None:
            steps.append(self.dev.end)
        if self.stopping:
            steps.append(self.link.stop)
        for step in (*steps, self.transport.close):
            try:
                step()
            except Exception:
                pass

    def finish(self) -> None:
        self.drop_stimulus("hostd is stopping")
        self.enter(Phase.STOPPED)
        # a second notice (the daemon's last thread exiting after the one that started us) must not
        # kill the process once Python's finalization has put the default action back
        signal.signal(PARENT_DEATH_SIGNAL, signal.SIG_IGN)
        # (its pipe is closed: the journal hears it from stderr)
        if self.daemon_gone or os.getppid() != self.parent:
            sys.stderr.write("hostd-pump: daemon gone; pump exiting\n")
            sys.stderr.flush()

    # ------------------------------------------------------------------ what plays
    def choose(self, at_device: bool, reason: int, detail: str = "") -> None:
        """Publish where the texture renders and why; log it once per change."""
        self.put("render_at", 1 if at_device else 0)
        self.put("render_reason", reason)
        if self.logged_choice == (at_device, reason) or reason == 7:  # 7: nothing to render yet
            return
        self.logged_choice = (at_device, reason)
        if at_device:
            self.log(f"device mode: {self.link.t.describe()} renders the texture from its own encoder")
        else:
            self.log(f"rendering on the host: {detail or RENDER_REASONS[reason]}",
                     warn=self.where == "device" and reason != 7)

    def start_device(self, coeffs) -> bool:
        """Upload to the display and render there when it can hold the texture; False (and
        the reason published) when the host must render it."""
        from hostd.device import devrender
        from hostd.device import protocol as pr
        from hostd.errors import DeviceBusy, DeviceError, DeviceGone

        dev, link, pump = self.dev, self.link, self.pump
        sos = dev.params["sos"]
        link.await_caps(1.0)  # (asked again if it was lost at the connection)
        why = pr.render_refusal(link.ident or {}, link.caps, len(coeffs), 0 if sos is None else len(sos),
                                who=link.t.describe())
        if why is not None:
            if dev.rendering:
                dev.end()
            self.choose(False, _REASON_OF_REFUSAL[why[0]], why[1])
            return False
        if self.phase.streams:
            pump.end()  # it streamed the previous texture: stop streaming first
        # the selection counts from the display's first report at full gain after START_RENDER
        # (reports arrive during the upload's acknowledgements already)
        pump.health.select(True, device=True)
        # (a loss meanwhile is said as one: the upload starts again on return)
        self.uploading = self.texture[0]
        try:
            dev.begin(self.texture)  # upload; the display renders (crossfades on a swap)
        except devrender.UploadAborted:  # stopping: the loop ends, the stop path says STOP_RENDER
            self.uploading = None
            return True
        except (DeviceGone, DeviceBusy):
            raise
        except DeviceError as e:  # refused (the upload was not applied): the host renders it
            self.uploading = None
            dev.end()
            self.choose(False, 6, f"device mode: {e}")
            return False
        self.uploading = None
        self.choose(True, 0)
        return True

    def begin(self) -> None:
        """Play the selected texture: on the display when it can render it, else on the host."""
        import numpy as np

        _, coeffs, n, length = self.texture
        self.link.poll(0.01)
        if self.dev is not None and self.start_device(coeffs):
            phase = Phase.DEVICE
        else:
            preload_host_rendering(self.stats)  # (a fallback from device mode loads it here: bounded)
            from hostd.render import Renderer  # (host rendering only: device mode never loads it)

            r = Renderer(np.asarray(coeffs), n, length, self.rcfg)
            r.start()
            self.pump.begin(r)  # pre-fill, then start the device (soft start)
            phase = Phase.HOST
        self.enter(phase)
        self.put("texture_serial", self.stats[STAT_INDEX["texture_serial"]] + 1)

    # ---- stimuli (hostd.render.stimulus; the daemon's `stimulus` command): streamed like a
    # host-rendered texture, through the output stage and the firmware's limits, whatever the
    # hand does; answered once the device's own count of samples played covers it
    def answer_stimulus(self, sid: int, error: str | None, retry: bool = True,
                        played: dict | None = None) -> None:
        try:
            self.conn.send(("stimulus", (sid, error, retry, played)))
        except (OSError, EOFError):
            pass

    def drop_stimulus(self, error: str, link_up: bool = True) -> None:
        """The stimulus being played was not played whole: say so (the client may ask again);
        the display's host timeout is set back (a new link sets it anyway)."""
        s, self.stim = self.stim, None
        if s is not None:
            self.answer_stimulus(s.id, error)
            if self.phase.connected and link_up:
                self.link.set_timeout(self.cfg.device.host_timeout_ms)

    def stimulus_begin(self, sid: int, f_hz: float, amplitude_um: float, duration_s: float) -> None:
        self.drop_stimulus("interrupted by another stimulus")
        if not self.phase.connected:
            self.answer_stimulus(sid, "no display is connected (hostd status says why): connect it and ask "
                                 "again")
            return
        from hostd.errors import StimulusRefused
        from hostd.render.stimulus import StimulusRenderer  # (the stimulus path only)

        try:
            r = StimulusRenderer(self.rcfg, f_hz, amplitude_um, duration_s)
        except StimulusRefused as e:
            self.answer_stimulus(sid, str(e), retry=False)
            return
        except Exception as e:  # (the daemon checked it: whatever slipped through never stops the pump)
            self.answer_stimulus(sid, f"stimulus refused: {type(e).__name__}: {e}", retry=False)
            return
        self.texture = None  # the stimulus ends what played; the display is idle after it
        # (kept before any message goes out: a display lost from here on is answered as such)
        self.stim = s = Stimulus(sid, r, duration_s, time.monotonic())
        dev, link = self.dev, self.link
        if dev is not None and dev.rendering:
            dev.end()  # the display stops rendering first; it streams the stimulus
        # the display's host timeout covers the whole buffer while it plays a stimulus: a host
        # stall shorter than what it holds does not cut it (what it holds was all checked; a
        # host gone for longer still ramps the display to zero); set back at the end
        link.set_timeout(max(self.cfg.device.host_timeout_ms, STIMULUS_TIMEOUT_MS))
        r.start()
        self.pump.begin(r)  # (STOP if it streamed,) load the compiled cycle, prime, START
        s.started(self.pump, link)
        self.enter(Phase.STIMULUS)

    def stimulus_end(self) -> None:
        self.pump.end()  # STOP: the device plays nothing more (the stimulus's tail was silence)
        self.link.set_timeout(self.cfg.device.host_timeout_ms)
        self.pump.health.select(False)
        self.enter(Phase.IDLE)

    def stimulus_check(self) -> None:
        """Once per cycle while a stimulus plays: answered once played whole, or not (Stimulus.verdict)."""
        s = self.stim
        if s is None:
            return
        answer = s.verdict(self.pump, self.link)
        if answer is not None:
            self.stim = None
            self.stimulus_end()  # idle first: the answer says the stimulus is over (a client's status agrees)
            self.answer_stimulus(s.id, *answer)

    # ------------------------------------------------------------------ commands
    def command(self, cmd) -> None:
        """A command from the parent; while no device is connected only the choice is kept."""
        if cmd[0] == "quit":
            self.stopping = True
        elif cmd[0] == "stimulus":
            self.stimulus_begin(*cmd[1])
        elif cmd[0] == "select":
            self.drop_stimulus("interrupted: a texture was selected")
            self.texture = cmd[1]
            if self.phase.connected:
                self.begin()
        elif cmd[0] == "stop":
            self.drop_stimulus("interrupted by a stop")
            self.texture = None
            if self.phase.connected:
                dev = self.dev
                if dev is not None and dev.rendering:
                    dev.end()
                    self.pump.health.select(False)
                if self.phase.streams:
                    self.pump.end()
                self.enter(Phase.IDLE)

    def commands(self) -> None:
        """The daemon's commands. EOF: the daemon died (kill -9 outside systemd): stop, with one
        line at exit instead of multiprocessing's traceback of the EOFError."""
        conn = self.conn
        while True:
            try:  # only the pipe: an error of a command itself is not the daemon's death
                if not conn.poll():
                    return
                msg = conn.recv()
            except (EOFError, OSError):
                self.daemon_gone = self.stopping = True
                return
            self.command(msg)

    # ------------------------------------------------------------------ counters
    def publish(self) -> None:
        stats = self.stats
        seq = stats[PUBLISH_SEQ]
        stats[PUBLISH_SEQ] = seq + 1  # odd: a snapshot is being written
        try:
            self._publish()
        finally:
            stats[PUBLISH_SEQ] = seq + 2

    def _publish(self) -> None:
        link, pump, dev, transport, claims = self.link, self.pump, self.dev, self.transport, self.claims
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
        phase = self.phase
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

    # ------------------------------------------------------------------ hotplug
    def hotplug_cycle(self) -> None:
        """Connected: a udev removal of our node ends the link at once; time the reconnection
        from the udev add event to the display playing again (or, with nothing selected, to the
        link being up)."""
        if self.hot_poll is not None and self.hot_poll.poll(0):
            transport = self.transport
            for ev in self.hot.events():
                if ev.action == "remove" and ev.node and ev.node == transport.node:
                    from hostd.errors import DeviceGone

                    raise DeviceGone(f"{transport.describe()} removed (udev event)")
                if ev.action == "add" and ev.display:
                    self.backlog.append(ev)  # (another display, or ours back before we saw it go)
        arrival = self.arrival
        if arrival[0] is None:
            return
        link = self.link
        s = link.stats.last_status
        if self.texture is not None:  # timed to the display playing it again
            phase = self.phase
            if not s or not phase.playing:
                return
            if phase is Phase.DEVICE:
                if not self.dev.rendering or s["state"] != self.rendering_state:
                    return
            elif self.pump.recovering:
                return
        t_event, t_up = arrival
        arrival[0] = arrival[1] = None
        now = time.monotonic()
        what = "playing again" if self.texture is not None else "connected (nothing selected)"
        self.log(f"device: {self.transport.describe()} {what} {now - t_event:.3f} s after its udev add event "
                 f"(link up at +{t_up - t_event:.3f} s)")
        self.tell(last_reconnect_s=round(now - t_event, 4), reconnected=self.info["reconnected"] + 1)

    def wait_for_display(self, absent: bool) -> None:
        """Until it is time to try again: the display's udev add event (udev mode, and it was
        not there), else device.reconnect_s (poll mode, or a display that is there but failed).
        In udev mode the display's sysfs entry is also looked at every device.reconnect_s
        (nothing is opened): a missed event (a private network namespace hides udev's events,
        a netlink overflow drops them) costs that long, not forever."""
        from multiprocessing.connection import wait

        from hostd.device.transport import present

        cfg, conn, hot, backlog, spec_kind = self.cfg, self.conn, self.hot, self.backlog, self.spec_kind
        by_event = absent and hot.mode == "udev"
        t_end = time.monotonic() + cfg.device.reconnect_s
        adds: list = []
        listed_usb = False
        while not self.stopping:
            now = time.monotonic()
            if by_event:
                backlog.extend(hot.events())
                adds += [ev for ev in backlog if ev.action == "add" and ev.display]
                backlog.clear()
                # with "auto", a USB device's own event comes before usbhid made its hidraw node:
                # give that 0.5 s, or auto would take it as raw USB (and detach usbhid)
                if adds and (spec_kind != "auto" or any(ev.subsystem != "usb" for ev in adds)
                             or now - adds[0].t >= 0.5):
                    self.arrival[0] = adds[0].t
                    return
                if not adds and now >= t_end:
                    t_end = now + cfg.device.reconnect_s
                    listed = (present(cfg.device.transport, cfg.device.serial) if cfg.device.serial
                              else present(cfg.device.transport))
                    usb_only = all(d["spec"].startswith("usb:") for d in listed)
                    if listed and (spec_kind != "auto" or not usb_only or listed_usb):
                        info = self.info
                        info["missed"] = info.get("missed", 0) + 1
                        self.log(f"hotplug: {listed[0]['spec']} is there but no udev event said so: udev's "
                                 "events do not reach hostd (a private network namespace, e.g. the unit's "
                                 "PrivateNetwork=yes, hides them); reconnecting within device.reconnect_s")
                        self.tell(hotplug_missed=info["missed"])
                        return
                    listed_usb = bool(listed)  # auto: raw USB only if still no hidraw a tick later
            elif now >= t_end:
                return
            # wake at least every 0.25 s: SIGTERM is seen, and the watchdog sees the pump alive
            ready = wait([conn, self.hot_fd] if by_event else [conn],
                         0.1 if adds else min(0.25, max(0.0, t_end - now)))
            self.wait_ticks += 1
            self.put("wait_ticks", self.wait_ticks)
            if conn in ready:
                self.commands()

    # ------------------------------------------------------------------ the loops' calls
    def each_cycle(self) -> None:  # the periodic loop (pump.run): each cycle the reference loop runs
        self.commands()
        self.stimulus_check()
        if self.dev is not None and not self.phase.streams:
            self.dev.tick()
        self.hotplug_cycle()
        self.publish()

    def upload_progress(self) -> None:
        """A message arrived during an upload to the display: progress, as a wake-up is (a slow
        display's upload, e.g. an emulated one on a loaded host, outlasted WatchdogSec=5 and
        systemd killed the daemon at every try)."""
        self.pump.stats.cycles += 1
        self.put("cycles", self.pump.stats.cycles)

    def each_wake(self, ready) -> None:  # device mode: a wake-up of the sleeping loop
        self.pump.stats.cycles += 1  # progress the daemon's watchdog sees
        if ready is None or self.conn_fd in ready:  # (conn.poll() builds a selector per call)
            self.commands()
        if self.dev is not None and not self.phase.streams:
            self.dev.tick()
        self.hotplug_cycle()
        # the counters are read at most a few times a second (`hostd status`, the daemon's
        # STATUS= and watchdog every WatchdogSec / 3, a Prometheus scrape every few seconds):
        # publish every DEVICE_PUBLISH_S, not at every report, unless the display's state changed
        # (a publish is ~90 µs of thread CPU on this VM: a third of a wake-up's)
        now = time.monotonic()
        s = self.link.stats.last_status
        if (now - self.last_pub >= DEVICE_PUBLISH_S
                or (s and s["state"] != self.stats[STAT_INDEX["device_state"]])):
            self.last_pub = now
            self.publish()


def pump_main(cfg, conn, stats) -> None:
    """Entry point of the pump process. cfg: hostd.service.config.Config."""
    PumpProcess(cfg, conn, stats).run()
