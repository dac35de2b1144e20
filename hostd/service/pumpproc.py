"""The real-time pump in its own process, isolated from intake and quality work.

A separate process, not a thread: the parent's threads (socket, spool, SQLite, scoring)
cannot hold a GIL that the pump needs, so Python's 5 ms switch interval never reaches it.
The parent sends commands over a Pipe (select a texture, stop, quit); the pump publishes its
counters in shared memory (no pickling per cycle) and log lines over the Pipe. After set-up
it calls gc.freeze(); the steady-state loop allocates only numpy temporaries of a few samples.
"""

from __future__ import annotations

import gc
import math
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
               "device_elapsed_s", "device_overflows",
               "publish_seq")  # odd while publish() writes: readers take a whole snapshot (a seqlock)
PUBLISH_SEQ = len(STAT_FIELDS) - 1
STAT_INDEX = {name: i for i, name in enumerate(STAT_FIELDS)}  # no linear search per put
FLOAT_FIELDS = {"speed_mm_s", "played_fraction", "device_time_s", "longest_stall_ms", "max_late_us",
                "batch_p50_us", "batch_p99_us", "batch_p999_us", "device_rendered_s", "device_faded_s",
                "device_idle_s", "busy_until_s", "device_elapsed_s"}
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


def pump_main(cfg, conn, stats) -> None:
    """Entry point of the pump process. cfg: hostd.service.config.Config."""
    import resource

    import numpy as np

    from hostd.device import devrender
    from hostd.device import protocol as pr
    from hostd.device.devmode import RENDERING, DeviceMode
    from hostd.device.health import HostBound
    from hostd.device.hotplug import watch
    from hostd.device.link import DeviceLink
    from hostd.device.pump import JitterConfig, Pump
    from hostd.device.realtime import SchedPolicy
    from hostd.device.transport import open_transport, present
    from hostd.errors import DeviceBusy, DeviceError, DeviceGone, DeviceNotFound

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent decides when we stop
    parent = os.getppid()
    quit_ = False
    daemon_gone = [False]  # the daemon died (the kernel's notice, or EOF on the pipe): said at exit

    def on_parent_death(*_) -> None:
        nonlocal quit_
        daemon_gone[0] = quit_ = True

    signal.signal(PARENT_DEATH_SIGNAL, on_parent_death)  # before prctl: its default action kills
    _die_with_parent()

    def log(msg: str, warn: bool | None = None) -> None:
        # device loss, refusals and recoveries are warnings; set-up lines are information
        if warn is None:
            warn = msg.startswith(("device lost", "device:", "playback recovered", "device mode: the display",
                                   "pump: ")) and ", protocol v" not in msg and " playing again " not in msg
        try:
            conn.send(("warn" if warn else "log", msg))
        except (OSError, EOFError):
            pass

    def put(name: str, value: float) -> None:
        stats[STAT_INDEX[name]] = value

    _realtime(cfg.realtime, log)
    # hotplug: udev events where udev runs, else a retry every device.reconnect_s
    hot = watch(cfg.device.transport)
    spec_kind = cfg.device.transport.partition(":")[0]
    info = {"transport": None, "hotplug": hot.mode, "last_reconnect_s": None, "reconnected": 0}

    def tell(**kw) -> None:  # strings and timings for `hostd status` (not per cycle: on change)
        info.update(kw)
        try:
            conn.send(("info", dict(info)))
        except (OSError, EOFError):
            pass

    tell()
    log(f"hotplug: {hot.describe()}")
    backlog: list = []  # udev events read but not yet acted on
    hot_fd = hot.fileno()
    hot_poll = None
    if hot_fd is not None:
        import select

        hot_poll = select.poll()
        hot_poll.register(hot_fd, select.POLLIN)
    arrival = [None, None]  # (CLOCK_MONOTONIC of the udev add event, of the link up) until playing
    rcfg = cfg.render_config()
    out = rcfg.output
    limit_code = out.limit_code
    max_step = int(min(out.slew_um_s / pr.SAMPLE_RATE_HZ / out.um_per_code + 1, 32767))
    texture = None  # (name, coeffs, n, length_mm)
    pump: Pump | None = None  # one pump for the process: its counters survive reconnections
    link: DeviceLink | None = None
    connected = playing = False

    def on_sigterm(*_) -> None:  # systemctl kill, or the parent's terminate(): ramp to zero, exit 0
        nonlocal quit_
        quit_ = True

    signal.signal(signal.SIGTERM, on_sigterm)
    reconnects = 0
    put("state", STATE_CODES["starting"])
    gc.collect()
    gc.freeze()

    jitter = JitterConfig(base_fill=cfg.device.target_fill,
                          max_fill=max(cfg.device.target_fill, cfg.device.max_fill))

    where = cfg.render.where  # auto (the default), device or host
    dev_params = None  # devrender.device_params(rcfg): the equalizer's design, for the display
    if where == "host":
        preload_host_rendering(stats)  # before the first connection: a selection plays at once
    else:  # designed now (in a child, ~1 s of scipy), not between a display's arrival and playing
        try:
            dev_params = devrender.device_params_apart(rcfg)
        except ValueError:  # (a setting the display cannot render: said when one connects, as before)
            dev_params = None
    dev = None  # DeviceMode while the display can render (protocol v2 with CAPS)
    logged_choice: list = [None]  # (render_at, reason) last logged: each choice is logged once

    def choose(at_device: bool, reason: int, detail: str = "") -> None:
        """Publish where the texture renders and why; log it once per change."""
        put("render_at", 1 if at_device else 0)
        put("render_reason", reason)
        if logged_choice[0] == (at_device, reason) or reason == 7:  # 7: nothing to render yet
            return
        logged_choice[0] = (at_device, reason)
        if at_device:
            log(f"device mode: {link.t.describe()} renders the texture from its own encoder")
        else:
            log(f"rendering on the host: {detail or RENDER_REASONS[reason]}",
                warn=where == "device" and reason != 7)

    uploading: list = [None]  # the texture whose upload to the display is under way

    def start_device(coeffs) -> bool:
        """Upload to the display and render there when it can hold the texture; False (and
        the reason published) when the host must render it."""
        sos = dev.params["sos"]
        link.await_caps(1.0)  # (asked again if it was lost at the connection)
        why = pr.render_refusal(link.ident or {}, link.caps, len(coeffs), 0 if sos is None else len(sos),
                                who=link.t.describe())
        if why is not None:
            if dev.rendering:
                dev.end()
            choose(False, _REASON_OF_REFUSAL[why[0]], why[1])
            return False
        if pump.renderer is not None:
            pump.end()  # it streamed the previous texture: stop streaming first
        # the selection counts from the display's first report at full gain after START_RENDER
        # (reports arrive during the upload's acknowledgements already)
        pump.health.select(True, device=True)
        uploading[0] = texture[0]  # (a loss meanwhile is said as one: the upload starts again on return)
        try:
            dev.begin(texture)  # upload; the display renders (crossfades on a swap)
        except devrender.UploadAborted:  # stopping: the loop ends, the stop path says STOP_RENDER
            uploading[0] = None
            return True
        except (DeviceGone, DeviceBusy):
            raise
        except DeviceError as e:  # refused (the upload was not applied): the host renders it
            uploading[0] = None
            dev.end()
            choose(False, 6, f"device mode: {e}")
            return False
        uploading[0] = None
        choose(True, 0)
        return True

    def begin() -> None:
        nonlocal playing
        _, coeffs, n, length = texture
        link.poll(0.01)
        if dev is None or not start_device(coeffs):
            preload_host_rendering(stats)  # (a fallback from device mode loads it here: bounded)
            from hostd.render import Renderer  # (host rendering only: device mode never loads it)

            r = Renderer(np.asarray(coeffs), n, length, rcfg)
            r.start()
            pump.begin(r)  # pre-fill, then start the device (soft start)
        playing = True
        put("state", STATE_CODES["playing"])
        put("texture_serial", stats[STAT_INDEX["texture_serial"]] + 1)

    # ---- stimuli (hostd.render.stimulus; the daemon's `stimulus` command): streamed like a
    # host-rendered texture, through the output stage and the firmware's limits, whatever the
    # hand does; answered once the device's own count of samples played covers it
    stim: list = [None]  # the stimulus being played (a dict), else None

    def answer_stimulus(sid: int, error: str | None, retry: bool = True, played: dict | None = None) -> None:
        try:
            conn.send(("stimulus", (sid, error, retry, played)))
        except (OSError, EOFError):
            pass

    def drop_stimulus(error: str, link_up: bool = True) -> None:
        """The stimulus being played was not played whole: say so (the client may ask again);
        the display's host timeout is set back (a new link sets it anyway)."""
        s, stim[0] = stim[0], None
        if s is not None:
            answer_stimulus(s["id"], error)
            if connected and link_up:
                link.set_timeout(cfg.device.host_timeout_ms)

    def stimulus_begin(sid: int, f_hz: float, amplitude_um: float, duration_s: float) -> None:
        nonlocal texture, playing
        drop_stimulus("interrupted by another stimulus")
        if not connected:
            answer_stimulus(sid, "no display is connected (hostd status says why): connect it and ask again")
            return
        from hostd.errors import StimulusRefused
        from hostd.render.stimulus import StimulusRenderer  # (the stimulus path only)

        try:
            r = StimulusRenderer(rcfg, f_hz, amplitude_um, duration_s)
        except StimulusRefused as e:
            answer_stimulus(sid, str(e), retry=False)
            return
        except Exception as e:  # (the daemon checked it: whatever slipped through never stops the pump)
            answer_stimulus(sid, f"stimulus refused: {type(e).__name__}: {e}", retry=False)
            return
        texture = None  # the stimulus ends what played; the display is idle after it
        now = time.monotonic()
        # (kept before any message goes out: a display lost from here on is answered as such)
        stim[0] = s = {"id": sid, "renderer": r, "first_seq": None, "p0": None, "t0": now,
                       "deadline": now + duration_s + 2.0, "duration_s": duration_s,
                       "needed": r.length + STIMULUS_TAIL}
        if dev is not None and dev.rendering:
            dev.end()  # the display stops rendering first; it streams the stimulus
        # the display's host timeout covers the whole buffer while it plays a stimulus: a host
        # stall shorter than what it holds does not cut it (what it holds was all checked; a
        # host gone for longer still ramps the display to zero); set back at the end
        link.set_timeout(max(cfg.device.host_timeout_ms, STIMULUS_TIMEOUT_MS))
        r.start()
        pump.begin(r)  # (STOP if it streamed,) load the compiled cycle, prime, START
        s["first_seq"] = link.next_seq()  # the first SAMPLES after START: once taken, START was too
        s["underruns0"], s["recoveries0"] = pump.health.underruns, pump.stats.recoveries
        s["overflows0"], s["malformed0"] = pump.stats.overflows, malformed_count()
        playing = True
        put("state", STATE_CODES["playing"])

    def stimulus_end() -> None:
        nonlocal playing
        pump.end()  # STOP: the device plays nothing more (the stimulus's tail was silence)
        link.set_timeout(cfg.device.host_timeout_ms)
        pump.health.select(False)
        playing = False
        put("state", STATE_CODES["idle"])

    def malformed_count() -> int | None:
        """The device's own count of messages it dropped as malformed (a cut SAMPLES frame)."""
        st = link.stats.last_status
        return st.get("malformed") if st else None

    def stimulus_check() -> None:
        """Once per cycle while a stimulus plays: played whole (the device's own count of samples
        played since it took the stimulus's first SAMPLES), or not (it ran dry, stopped, or not
        in time)."""
        s = stim[0]
        if s is None:
            return
        h = pump.health
        if s["malformed0"] is None:
            # (no STATUS heard before the stimulus: cannot be on a connected link, whose
            # handshake has one; the first one heard is the baseline, never read as damage)
            s["malformed0"] = malformed_count()
        if s["p0"] is None:
            if link.acked(s["first_seq"]):  # it took STOP (if any), the prime and START: what it
                s["p0"] = h.samples_played  # played before is counted here (what since, at most, later)
        elif pump.recovering or h.underruns != s["underruns0"] or pump.stats.recoveries != s["recoveries0"]:
            stim[0] = None
            ep = pump._episode
            why = ep.cause if ep is not None else "underrun" if h.underruns != s["underruns0"] else "stopped"
            n_played = h.samples_played - s["p0"]
            stimulus_end()
            answer_stimulus(s["id"], f"the display stopped playing the stimulus ({why}: a host stall "
                            f"longer than its buffer) after {n_played} samples: it was not "
                            "played whole; ask again")
            return
        elif pump.stats.overflows != s["overflows0"] or malformed_count() != s["malformed0"]:
            # the device dropped samples it was sent (its buffer full: a display that fell behind
            # the host's estimate of its clock; or a frame cut on the way): it played on, from
            # later in the stimulus, without an underrun; the count of samples played cannot tell
            stim[0] = None
            why = ("its buffer overflowed" if pump.stats.overflows != s["overflows0"]
                   else "a message of it arrived damaged")
            stimulus_end()
            answer_stimulus(s["id"], f"the display dropped samples of the stimulus ({why}): it was not "
                            "played as asked; ask again")
            return
        elif h.samples_played - s["p0"] >= s["needed"]:
            stim[0] = None
            r = s["renderer"]
            played = {"samples": h.samples_played - s["p0"], "stimulus_samples": r.length,
                      "limited": r.limited, "host_s": round(time.monotonic() - s["t0"], 4),
                      "device_time_s": link.device_time_s}
            stimulus_end()  # idle first: the answer says the stimulus is over (a client's status agrees)
            if r.limited:  # (cannot happen after the check; said rather than assumed)
                answer_stimulus(s["id"], f"the output stage limited {r.limited} samples of the stimulus",
                                retry=False, played=played)
            else:
                answer_stimulus(s["id"], None, played=played)
            return
        if time.monotonic() > s["deadline"]:
            stim[0] = None
            stimulus_end()
            answer_stimulus(s["id"], f"the display did not play the {s['duration_s']:g} s stimulus within "
                            f"{s['deadline'] - s['t0']:g} s; ask again")

    def command(cmd) -> None:
        """A command from the parent; while no device is connected only the choice is kept."""
        nonlocal texture, playing, quit_
        if cmd[0] == "quit":
            quit_ = True
        elif cmd[0] == "stimulus":
            stimulus_begin(*cmd[1])
        elif cmd[0] == "select":
            drop_stimulus("interrupted: a texture was selected")
            texture = cmd[1]
            if connected:
                begin()
        elif cmd[0] == "stop":
            drop_stimulus("interrupted by a stop")
            texture = None
            if connected:
                if dev is not None and dev.rendering:
                    dev.end()
                    pump.health.select(False)
                if pump.renderer is not None:
                    pump.end()
                playing = False
                put("state", STATE_CODES["idle"])

    last_pct = [0.0]

    bad_seen = [0, -math.inf]  # bad frames of this link: counted, time of the last one
    bad_msgs_seen = [0, -math.inf]  # bad messages (valid frames) of this link: the same
    resets_seen = [0, -math.inf]  # the device's counter resets (health.resets), time of the last one
    # a flood of STATUS: a display reports once per status_period_ticks at most (1 ms while it
    # streams, 300 ms while it renders); STATUS counted per second of host time, against that
    # fastest rate. A window ends only when the pump looks (publish()), so a backlog the host
    # reads after its own stall falls in the window that holds the stall: it never looks like a
    # flood. [window start, link.stats.statuses then, flooding]
    max_status_hz = pr.SAMPLE_RATE_HZ / pr.P["status_period_ticks"]
    flood = [time.monotonic(), 0, False]
    # the device's counters as shown (status, metrics, the plays rows), bounded by what the host
    # knows: samples played at most those this link sent plus a buffer; the device time elapsed
    # and the display's ticks at most the link's time up (+1 %, +0.5 s), underruns one per two
    # ticks. A claim above: one line per burst naming the device (the first after a quiet second)
    bounds = {k: HostBound() for k in ("samples", "elapsed", "underruns", "rendered", "faded", "idle")}
    # (name, most per second of the link (None: from the samples sent), how a claim above reads)
    BOUND_RULES = (("samples", None, "{:.0f} samples played"), ("elapsed", 1.0, "{:.1f} s of its clock"),
                   ("underruns", pr.SAMPLE_RATE_HZ / 2, "{:.0f} underruns"),
                   ("rendered", pr.SAMPLE_RATE_HZ, "{:.0f} ticks rendered"),
                   ("faded", pr.SAMPLE_RATE_HZ, "{:.0f} ticks faded"),
                   ("idle", pr.SAMPLE_RATE_HZ, "{:.0f} ticks idle"))

    def claimed(h) -> dict:
        return {"samples": h.samples_played, "elapsed": h.elapsed_s, "underruns": h.underruns,
                "rendered": h.rendered_ticks, "faded": h.faded_ticks, "idle": h.idle_ticks}
    impossible_seen = [-math.inf]

    def publish() -> None:
        seq = stats[PUBLISH_SEQ]
        stats[PUBLISH_SEQ] = seq + 1  # odd: a snapshot is being written
        try:
            _publish()
        finally:
            stats[PUBLISH_SEQ] = seq + 2

    def _publish() -> None:
        # a device's garbage, cut, oversized or unknown messages: dropped (bad CRC, bad layout),
        # never acted on; one line per burst (the first bad one after a quiet second), naming it.
        # Bad frames (the framing: garbage, cut, oversized, also a frame the host's own stall
        # cut) and bad messages (valid frames hostd cannot take: an unknown id, a bad layout) are
        # bursts of their own: a cut frame of a stall never hides a message the device made up
        framer = getattr(transport, "deframer", None)
        now = time.monotonic()
        bad_frames = framer.bad_frames if framer is not None else 0
        for seen, bad, what in (
                (bad_seen, bad_frames, "garbage, cut or oversized frames"),
                (bad_msgs_seen, link.stats.bad_messages_received,
                 f"messages hostd cannot take, the last: {link.stats.last_bad}")):
            if bad > seen[0]:
                if now - seen[1] >= 1.0:
                    log(f"device: {transport.describe()} sent bad frames or messages ({what}; {bad} on this "
                        "link); dropped, the rest of the burst silently")
                seen[:] = [bad, now]
        span_s = now - flood[0]
        if span_s >= 1.0:  # one line per flood episode (windows over the rate in a row), naming it
            n_status = link.stats.statuses - flood[1]
            expected = span_s * max_status_hz
            flooding = n_status > FLOOD_FACTOR * expected
            if flooding and not flood[2]:
                log(f"device: {transport.describe()} sent {n_status} status reports in {span_s:.1f} s "
                    f"(expected at most ~{expected:.0f}): flooding; each is checked as usual, the host "
                    "keeps its own pace")
            flood[:] = [now, link.stats.statuses, flooding]
        s = link.stats.last_status
        if s:
            put("fill", s["buffer_fill"])
            put("malformed", s["malformed"])
            put("device_time_s", link.device_time_s)  # the device's clock, unwrapped
        h = pump.health
        rate = pr.SAMPLE_RATE_HZ
        sent = link.stats.samples_sent
        boot = time.clock_gettime(time.CLOCK_BOOTTIME)  # a device's clock runs on while the host sleeps
        # (one pass over constant tables: the bounds were ~37 µs of a ~100 µs publish as dicts)
        claims = []
        told = claimed(h)
        for k, per_s, fmt in BOUND_RULES:
            b = bounds[k]
            if per_s is None:  # samples played: at most those sent on this link, plus a buffer
                over = b.take(told[k], b.base + sent + pr.BUFFER_CAPACITY, pr.BUFFER_CAPACITY)
            else:
                over = b.take(told[k], *b.within_time(boot, per_s))
            if over > 0:
                claims.append(fmt.format(over))
        if claims:
            if now - impossible_seen[0] >= 1.0:
                up_s = boot - bounds["samples"].t0
                log(f"device: {transport.describe()} reported the impossible: {', '.join(claims)} more than "
                    f"{up_s:.1f} s of its link and the {sent} samples sent to it allow; its counters are "
                    "shown within what the host knows")
            impossible_seen[0] = now
        if h.resets > resets_seen[0]:  # counters or clock went back or leapt: one line per burst
            t_reset = time.monotonic()
            if t_reset - resets_seen[1] >= 1.0:
                log(f"device: {transport.describe()} reported counters or a clock that went back or leapt "
                    f"(a reset, or a device that lies; {h.resets} in all); counted from a new baseline")
            resets_seen[:] = [h.resets, t_reset]
        put("device_state", h.state)
        put("device_fault_bits", h.recent_fault_bits())
        put("device_underruns", bounds["underruns"].shown)
        put("device_samples_played", bounds["samples"].shown)
        put("played_fraction", h.played_fraction)
        put("device_resets", h.resets)
        put("device_host_lost", h.host_lost)
        put("device_rendered_s", bounds["rendered"].shown / rate)
        put("device_faded_s", bounds["faded"].shown / rate)
        put("device_idle_s", bounds["idle"].shown / rate)
        put("device_elapsed_s", bounds["elapsed"].shown)
        if dev is not None and dev.rendering:
            rs = link.render_status
            if rs is not None:  # the display's own measure, from its encoder's edge times
                put("speed_mm_s", rs["speed_mm_s"])
            put("state", STATE_CODES["recovering" if s and s["state"] != RENDERING else "playing"])
        elif pump.renderer is not None:
            put("speed_mm_s", pump.renderer.motion.velocity_mm_s)
            put("state", STATE_CODES["recovering" if pump.recovering else "playing"])
        st = pump.stats
        for name in ("cycles", "samples", "late_batches", "deadline_misses", "max_late_us", "stalls",
                     "longest_stall_ms", "implausible_speed", "relocks", "io_retries", "io_dropped"):
            put(name, getattr(st, name))
        put("recoveries", st.recoveries + (dev.recoveries if dev is not None else 0))
        put("device_overflows", st.overflows)  # reports with the display's OVERFLOW flag
        if dev is not None:
            put("device_uploads", dev.uploads)
            put("device_reuploads", dev.recoveries)
            put("wakeups", dev.wakeups)
            # the kernel's count of the pump's sleeps, read at the same instant (bench soak sets
            # the loop's runs against it: a wake-up that is not a run would show here)
            put("voluntary_switches", resource.getrusage(resource.RUSAGE_SELF).ru_nvcsw)
        put("target_fill", pump.target_fill)
        fastpump = sys.modules.get("hostd.device.fastpump")  # loaded by host rendering only
        put("compiled_cycles", fastpump.compiled_cycles() if fastpump is not None else 0)
        if pump.renderer is not None and now - last_pct[0] >= 5.0:
            # percentiles of the host-rendering cycle every 5 s (a sort of 65536 cycles: ~1 ms)
            last_pct[0] = now
            p50, p99, p999 = pump.step_percentiles_us()
            put("batch_p50_us", p50)
            put("batch_p99_us", p99)
            put("batch_p999_us", p999)

    def hotplug_cycle() -> None:
        """Connected: a udev removal of our node ends the link at once; time the reconnection
        from the udev add event to the display playing again (or, with nothing selected, to the
        link being up)."""
        if hot_poll is not None and hot_poll.poll(0):
            for ev in hot.events():
                if ev.action == "remove" and ev.node and ev.node == transport.node:
                    raise DeviceGone(f"{transport.describe()} removed (udev event)")
                if ev.action == "add" and ev.display:
                    backlog.append(ev)  # (another display, or ours back before we saw it go)
        if arrival[0] is None:
            return
        s = link.stats.last_status
        if texture is not None:
            if not s or not playing:
                return
            if dev is not None and dev.rendering:
                if s["state"] != pr.STATES["RENDERING"]:
                    return
            elif pump.renderer is None or pump.recovering:
                return
        t_event, t_up = arrival
        arrival[0] = arrival[1] = None
        now = time.monotonic()
        what = "playing again" if texture is not None else "connected (nothing selected)"
        log(f"device: {transport.describe()} {what} {now - t_event:.3f} s after its udev add event "
            f"(link up at +{t_up - t_event:.3f} s)")
        tell(last_reconnect_s=round(now - t_event, 4), reconnected=info["reconnected"] + 1)

    def commands() -> None:
        """The daemon's commands. EOF: the daemon died (kill -9 outside systemd): stop, with one
        line at exit instead of multiprocessing's traceback of the EOFError."""
        nonlocal quit_
        while True:
            try:  # only the pipe: an error of a command itself is not the daemon's death
                if not conn.poll():
                    return
                msg = conn.recv()
            except (EOFError, OSError):
                daemon_gone[0] = quit_ = True
                return
            command(msg)

    def each_cycle() -> None:
        commands()
        stimulus_check()
        if dev is not None and pump.renderer is None:
            dev.tick()
        hotplug_cycle()
        publish()

    wait_ticks = 0

    def wait_for_display(absent: bool) -> None:
        """Until it is time to try again: the display's udev add event (udev mode, and it was
        not there), else device.reconnect_s (poll mode, or a display that is there but failed).
        In udev mode the display's sysfs entry is also looked at every device.reconnect_s
        (nothing is opened): a missed event (a private network namespace hides udev's events,
        a netlink overflow drops them) costs that long, not forever."""
        nonlocal wait_ticks
        from multiprocessing.connection import wait

        by_event = absent and hot.mode == "udev"
        t_end = time.monotonic() + cfg.device.reconnect_s
        adds: list = []
        listed_usb = False
        while not quit_:
            now = time.monotonic()
            if by_event:
                backlog.extend(hot.events())
                adds += [ev for ev in backlog if ev.action == "add" and ev.display]
                backlog.clear()
                # with "auto", a USB device's own event comes before usbhid made its hidraw node:
                # give that 0.5 s, or auto would take it as raw USB (and detach usbhid)
                if adds and (spec_kind != "auto" or any(ev.subsystem != "usb" for ev in adds)
                             or now - adds[0].t >= 0.5):
                    arrival[0] = adds[0].t
                    return
                if not adds and now >= t_end:
                    t_end = now + cfg.device.reconnect_s
                    listed = (present(cfg.device.transport, cfg.device.serial) if cfg.device.serial
                              else present(cfg.device.transport))
                    usb_only = all(d["spec"].startswith("usb:") for d in listed)
                    if listed and (spec_kind != "auto" or not usb_only or listed_usb):
                        info["missed"] = info.get("missed", 0) + 1
                        log(f"hotplug: {listed[0]['spec']} is there but no udev event said so: udev's "
                            "events do not reach hostd (a private network namespace, e.g. the unit's "
                            "PrivateNetwork=yes, hides them); reconnecting within device.reconnect_s")
                        tell(hotplug_missed=info["missed"])
                        return
                    listed_usb = bool(listed)  # auto: raw USB only if still no hidraw a tick later
            elif now >= t_end:
                return
            # wake at least every 0.25 s: SIGTERM is seen, and the watchdog sees the pump alive
            ready = wait([conn, hot_fd] if by_event else [conn],
                         0.1 if adds else min(0.25, max(0.0, t_end - now)))
            wait_ticks += 1
            put("wait_ticks", wait_ticks)
            if conn in ready:
                commands()

    last_pub = [0.0]

    conn_fd = conn.fileno()

    def upload_progress() -> None:
        """A message arrived during an upload to the display: progress, as a wake-up is (a slow
        display's upload, e.g. an emulated one on a loaded host, outlasted WatchdogSec=5 and
        systemd killed the daemon at every try)."""
        pump.stats.cycles += 1
        put("cycles", pump.stats.cycles)

    def each_wake(ready) -> None:  # device mode: a wake-up of the sleeping loop
        pump.stats.cycles += 1  # progress the daemon's watchdog sees
        if ready is None or conn_fd in ready:  # (conn.poll() builds a selector per call)
            commands()
        if dev is not None and pump.renderer is None:
            dev.tick()
        hotplug_cycle()
        # the counters are read at most a few times a second (`hostd status`, the daemon's
        # STATUS= and watchdog every WatchdogSec / 3, a Prometheus scrape every few seconds):
        # publish every DEVICE_PUBLISH_S, not at every report, unless the display's state changed
        # (a publish is ~90 µs of thread CPU on this VM: a third of a wake-up's)
        now = time.monotonic()
        s = link.stats.last_status
        if now - last_pub[0] >= DEVICE_PUBLISH_S or (s and s["state"] != stats[STAT_INDEX["device_state"]]):
            last_pub[0] = now
            publish()

    def device_loop() -> bool:
        """The display renders (or nothing is selected): sleep, no periodic loop."""
        return dev is not None and pump.renderer is None

    while not quit_:
        # ---- connect
        transport = None
        try:
            transport = (open_transport(cfg.device.transport, serial=cfg.device.serial) if cfg.device.serial
                         else open_transport(cfg.device.transport))
            link = DeviceLink(transport, target_fill=cfg.device.target_fill)
            ident = link.handshake(timeout_s=2.0)
            link.set_limits(min(limit_code, ident["limit_code"]), min(max_step, ident["max_step_code"]))
            link.set_timeout(cfg.device.host_timeout_ms)
        except DeviceError as e:
            if transport is not None:  # opened, then no answer: release it (the fd, the USB claim)
                transport.close()
            put("connected", 0)
            put("state", STATE_CODES["waiting"])
            log(f"device: {e}")
            arrival[0] = None
            wait_for_display(absent=isinstance(e, DeviceNotFound))
            reconnects += 1
            put("reconnects", reconnects)
            continue
        connected = True
        # (the old link's counts since the last publish stay the old link's)
        h = pump.health if pump is not None else None
        for k, b in bounds.items():
            b.link_up(time.clock_gettime(time.CLOCK_BOOTTIME), 0.0 if h is None else claimed(h)[k])
        bad_seen[:] = [0, -math.inf]
        bad_msgs_seen[:] = [0, -math.inf]
        flood[:] = [time.monotonic(), link.stats.statuses, False]
        put("connected", 1)
        if arrival[0] is not None:
            arrival[1] = time.monotonic()
        backlog.clear()
        tell(transport=transport.describe())
        log(f"device: {transport.describe()} firmware {ident['fw_major']}.{ident['fw_minor']}."
            f"{ident['fw_patch']}, protocol v{ident['protocol_version']}")
        if pump is None:
            pump = Pump(link, None, period_s=cfg.device.host_cycle_ms / 1000, jitter=jitter, log=log,
                        cycle=CompiledCycle(), realtime=SchedPolicy(cfg.realtime.sched_fifo_priority, log))
        else:
            pump.attach(link)
        playing = False
        dev = None
        if where == "host":
            choose(False, 1)
        else:
            link.await_caps()  # a v2 display sends CAPS right after IDENT
            why = pr.render_refusal(link.ident, link.caps, 1, 0, who=transport.describe())
            if why is None:
                if dev_params is None:  # designed once per process, scipy kept out of it
                    dev_params = devrender.device_params_apart(rcfg)
                dev = DeviceMode(link, rcfg, log, host_lost_ms=cfg.render.host_lost_ms,
                                 timeout_ms=cfg.device.host_timeout_ms, params=dev_params)
                dev.abort = lambda: quit_  # a stop does not wait out an upload's answers
                dev.alive = upload_progress  # the watchdog sees a slow upload moving
                if texture is None:
                    choose(True, 7)
            else:
                choose(False, _REASON_OF_REFUSAL[why[0]], why[1])
        if dev is None:  # the host renders: its renderer's imports now, not at the first texture
            preload_host_rendering(stats)
        try:
            if texture is not None:
                begin()
            else:
                put("state", STATE_CODES["idle"])
            # commands and udev events wake the sleeping loop at once
            fds = [conn.fileno()] + ([hot_fd] if hot_fd is not None else [])
            while not quit_:
                if device_loop():
                    dev.run(stop=lambda: quit_ or not device_loop(), each_wake=each_wake, fds=fds)
                else:
                    pump._last_cycle_start = None  # the sleeping loop's gaps are not stalls
                    pump.run(stop=lambda: quit_ or device_loop(), each_cycle=each_cycle, wake_fds=fds)
        except DeviceError as e:
            drop_stimulus(f"the display was lost during the stimulus ({e})", link_up=False)
            if uploading[0] is not None:  # mid-upload: nothing it holds is believed; all again on return
                log(f"device lost during the upload of {uploading[0]} (device rendering): {e}; output "
                    "stopped, waiting; identified and uploaded to again when it returns")
                uploading[0] = None
            else:
                log(f"device lost while {'playing' if playing else 'idle'}: {e}; output stopped, waiting")
            put("connected", 0)
            tell(transport=None)
            put("state", STATE_CODES["waiting"])
        finally:
            connected = False
            pump.renderer = None
            # a stop: the display ends what it renders (or may render: an upload in flight) and
            # ramps to zero (STOP also ends a stimulus or a stream); each step on its own, so one
            # failing does not skip the next
            steps = []
            if quit_ and dev is not None:
                steps.append(dev.end)
            if quit_:
                steps.append(link.stop)
            for step in (*steps, transport.close):
                try:
                    step()
                except Exception:
                    pass
    drop_stimulus("hostd is stopping")
    put("state", STATE_CODES["stopped"])
    # a second notice (the daemon's last thread exiting after the one that started us) must not
    # kill the process once Python's finalization has put the default action back
    signal.signal(PARENT_DEATH_SIGNAL, signal.SIG_IGN)
    if daemon_gone[0] or os.getppid() != parent:  # its pipe is closed: the journal hears it from stderr
        sys.stderr.write("hostd-pump: daemon gone; pump exiting\n")
        sys.stderr.flush()
