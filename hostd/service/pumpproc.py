"""The real-time pump in its own process, isolated from intake and quality work.

A separate process, not a thread: the parent's threads (socket, spool, SQLite, scoring)
cannot hold a GIL that the pump needs, so Python's 5 ms switch interval never reaches it.
The parent sends commands over a Pipe (select a texture, stop, quit); the pump publishes its
counters in shared memory (no pickling per cycle) and log lines over the Pipe. After set-up
it calls gc.freeze(); the steady-state loop allocates only numpy temporaries of a few samples.
pump_main runs a PumpProcess, whose Phase names where its lifecycle is. Its parts: pumpstate (the
counters, the Phase), pumpsetup (its set-up), pumpstimulus (stimuli), pumpguards (display claims).
"""

from __future__ import annotations

import gc
import importlib
import os
import signal
import sys
import time

from hostd.service.pumpsetup import (  # noqa: F401 (LOADING_ALLOWANCE_S: tests read it here)
    DEVICE_SIDE,
    LOADING_ALLOWANCE_S,
    PARENT_DEATH_SIGNAL,
    CompiledCycle,
    _die_with_parent,
    _realtime,
    poll_of,
    preload_host_rendering,
    prepare_rendering,
)
from hostd.service.pumpstate import (  # noqa: F401 (STAT_FIELDS: tests read it here)
    RENDER_REASONS,
    STAT_FIELDS,
    STAT_INDEX,
    Phase,
    PumpCounters,
)
from hostd.service.pumpstimulus import StimulusPlayer

_REASON_OF_REFUSAL = {"v1": 2, "no_caps": 3, "components": 4, "sections": 5}
# more STATUS per second than this many times the protocol's fastest report rate: a flood
FLOOD_FACTOR = 3
DEVICE_PUBLISH_S = 0.5  # device mode: the counters published at most this often (state changes at once)


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
        # what it publishes (the kernel's count of the pump's sleeps among them)
        self.counters = PumpCounters(stats, SAMPLE_RATE_HZ, RENDERING,
                                     lambda: resource.getrusage(resource.RUSAGE_SELF).ru_nvcsw)
        self.phase = Phase.STARTING
        self.stopping = False  # asked to stop: SIGTERM, the daemon's death, "quit", EOF on the pipe
        self.daemon_gone = False  # the daemon died (the kernel's notice, or EOF on the pipe): said at exit
        self.parent = None
        self.texture = None  # (name, coeffs, n, length_mm): the selection, kept while no display is there
        self.stimuli = StimulusPlayer(conn, cfg.device.host_timeout_ms)  # the stimulus being played
        self.uploading = None  # the texture whose upload to the display is under way
        self.pump = None  # one Pump for the process: its counters survive reconnections
        self.link = None  # DeviceLink, this connection's
        self.transport = None
        self.dev = None  # DeviceMode while the display can render (protocol v2 with CAPS)
        self.logged_choice = None  # (render_at, reason) last logged: each choice is logged once
        self.reconnects = 0
        self.wait_ticks = 0
        self.last_pub = 0.0  # device mode: the last publish
        self.claims = None  # DeviceClaims: the guards over what the display claims

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
        self.hot_poll = poll_of(self.hot_fd)
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
        # devrender.device_params(rcfg): the equalizer's design, for the display (None: not yet)
        self.dev_params = prepare_rendering(self.where, rcfg, self.stats)
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
                if self.dev_params is None:  # designed once per process (no scipy.signal)
                    self.dev_params = devrender.device_params(self.rcfg)
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

    # ---- stimuli (pumpstimulus.StimulusPlayer holds the one being played and its answers)
    def drop_stimulus(self, error: str, link_up: bool = True) -> None:
        """The stimulus being played (if any) was not played whole: said (StimulusPlayer)."""
        self.stimuli.drop_stimulus(error, self.link if self.phase.connected and link_up else None)

    def stimulus_begin(self, sid: int, f_hz: float, amplitude_um: float, duration_s: float) -> None:
        self.drop_stimulus("interrupted by another stimulus")
        if not self.phase.connected:
            self.stimuli.answer_stimulus(sid, "no display is connected (hostd status says why): connect it "
                                         "and ask again")
            return
        s = self.stimuli.make_stimulus(self.rcfg, sid, f_hz, amplitude_um, duration_s)
        if s is None:
            return
        self.texture = None  # the stimulus ends what played; the display is idle after it
        self.stimuli.start_stimulus(s, self.pump, self.link, self.dev)
        self.enter(Phase.STIMULUS)

    def stimulus_end(self) -> None:
        self.pump.end()  # STOP: the device plays nothing more (the stimulus's tail was silence)
        self.link.set_timeout(self.cfg.device.host_timeout_ms)
        self.pump.health.select(False)
        self.enter(Phase.IDLE)

    def stimulus_check(self) -> None:
        """Once per cycle while a stimulus plays: answered once played whole, or not (Stimulus.verdict)."""
        done = self.stimuli.verdict(self.pump, self.link)
        if done is not None:
            self.stimulus_end()  # idle first: the answer says the stimulus is over (a client's status agrees)
            self.stimuli.answer_stimulus(done[0], *done[1])

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
        """One snapshot of the counters (PumpCounters.publish)."""
        self.counters.publish(self.phase, self.link, self.pump, self.dev, self.transport, self.claims)

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
