"""Device-side rendering driven by the daemon: upload once, start, then only supervise.

In device mode (`[render] where = "device"`) the display renders the texture from its own
encoder (protocol v2, firmware/src/render.c); the host uploads the texture and the render
parameters (equalizer, band, scale, chain delay, all from the same RenderConfig the host
renderer uses), starts rendering, and then:
  - keeps the link alive: any valid message at least every host_lost_ms / 2 (a same-value
    SET_TIMEOUT), so the display never counts its host as lost while the daemon runs;
  - watches every STATUS: a display that is not rendering while a texture is selected (a
    reset, a stop on its own) gets the upload and START_RENDER again, logged once;
  - swaps textures by uploading into the other slot: the display crossfades (no click).
A host stall does not interrupt the texture: the display keeps rendering; after host_lost_ms
it flags the host as lost and still renders while the hand moves (docs/protocol.md).

The host sleeps meanwhile (`run`): no periodic loop, it blocks on the transport until the
display reports (STATUS and RENDER_STATUS every 300 ms while it renders, firmware 0.5; 150 ms in
0.4, 50 ms in 0.3), a command arrives (the daemon's pipe, a hotplug monitor: any descriptor in `fds`) or
the next keep-alive is due. Each report pair wakes the loop once (over serial: one read,
deframed, Transport.gather with a count of REPORTS_PER_WAKE pairs, so a 0.3 display's 50 ms
pairs also wake it once each); the counters are cumulative and every STATUS's fault bits
count, so the slower report loses no tick; a display that stops rendering sends its 1 ms
STATUS again at once. Every wake-up is a run of the loop (`wakeups`, the figure `hostd bench
soak` sets against the process's own count of wake-ups). A keep-alive that falls due before the
next wake-up goes out with it, so the keep-alive adds no wake-up of its own.
"""

from __future__ import annotations

import math
import select
import time

import numpy as np

from hostd.device import devrender
from hostd.device import protocol as pr
from hostd.device.link import DeviceLink
from hostd.errors import DeviceTimeout

RENDERING = pr.STATES["RENDERING"]


class DeviceMode:
    IDLE_WAIT_S = 0.05  # nothing to render: read the display's 1 ms statuses in batches
    RETRY_ACK_S = 3.0  # an upload not answered within 1 s is sent once more with this long to wait
    REPORTS_PER_WAKE = 1  # report pairs taken in at once while rendering (one per 300 ms, firmware 0.5)

    def __init__(self, link: DeviceLink, cfg, log, host_lost_ms: int = 1000,
                 timeout_ms: int = 50, params: dict | None = None) -> None:
        self.link = link
        self.cfg = cfg  # RenderConfig
        self._params = params  # devrender.device_params(cfg), designed on first use if not given
        self.log = log
        self.host_lost_ms = int(host_lost_ms)
        self.timeout_ms = int(timeout_ms)
        self.texture = None  # (name, coeffs, n, length_mm)
        self.rendering = False  # START_RENDER acknowledged for the current texture
        # START_RENDER sent, its answer not (yet) in: the display may render, so a stop says
        # STOP_RENDER all the same (a slow display, or a stop while the upload waits)
        self.start_sent = False
        self._taken_over = False  # take_over() done on this connection
        self.abort = None  # a callable, true when the process stops: an upload in flight gives way
        self.alive = None  # a callable, called for each message arriving during an upload (progress)
        self.slot = 1
        self.recoveries = 0
        self.uploads = 0
        # any valid message at least this often: well within host_lost_ms (the v1 host timeout
        # applies only while streaming, never while the display renders or idles)
        self._keepalive_s = self.host_lost_ms / 3000.0
        # take the messages in once per REPORTS_PER_WAKE report pairs (STATUS + RENDER_STATUS)
        # where the transport gathers them (serial); a display that stops rendering sends its
        # 1 ms STATUS, which fills the same count within a few ms: supervision stays prompt
        self._wake_count = 2 * self.REPORTS_PER_WAKE  # messages (STATUS + RENDER_STATUS each)
        # a keep-alive due within this much of a wake-up goes out with it (the wake-up period)
        self._early_s = min(self.REPORTS_PER_WAKE * pr.R["status_period_ticks"] / pr.SAMPLE_RATE_HZ,
                            self._keepalive_s / 2)
        self._last_keepalive = time.monotonic()
        self._keepalive_msg = pr.encode("SET_TIMEOUT", timeout_ms=self.timeout_ms)  # a same-value one
        self.wakeups = 0  # runs of the sleeping loop: one per wake-up (gathered arrivals included)
        self._started_at = 0.0
        self._statuses_at_start = -1

    @property
    def params(self) -> dict:
        """What the display needs besides the texture (devrender.device_params), once."""
        if self._params is None:
            self._params = devrender.device_params(self.cfg)
        return self._params

    def check(self, coeffs) -> None:
        """Raise DeviceVersion (what to do) unless this display can render this texture."""
        sos = self.params["sos"]
        pr.require_render(self.link.ident or {}, self.link.caps, len(coeffs),
                          0 if sos is None else len(sos), who=self.link.t.describe())

    def begin(self, texture) -> None:
        """Render `texture` (name, coeffs, n, length_mm): the first one with every parameter,
        later ones into the other slot (the display crossfades)."""
        _name, coeffs, n, length_mm = texture
        c = np.asarray(coeffs, dtype=np.float64)
        self.check(c)
        if self.rendering:
            self.slot = 2 if self.slot == 1 else 1
            msgs = pr.texture_messages(self.slot, c, n, length_mm)
        else:
            # a host back from a pause finds the display's reports of it waiting, up to what the
            # line holds: the display then drops what it sends, the upload's answers too (the
            # retry below would cover that, a second later)
            self.link.catch_up()
            self.take_over()
            msgs = devrender.setup_messages(c, n, length_mm, self.cfg, slot=self.slot, params=self.params)
            msgs.append(pr.encode("START_RENDER", host_lost_ms=self.host_lost_ms))
            self.start_sent = True
        try:
            devrender.send_and_confirm(self.link.t, msgs, on_other=self.link._take, abort=self.abort,
                                       alive=self.alive)
        except DeviceTimeout:
            # no answer is not a refusal: a starved or emulated host can miss the 1 s (the VM
            # rig under load); the whole upload once more, waiting longer, before the host renders
            devrender.send_and_confirm(self.link.t, msgs, timeout_s=self.RETRY_ACK_S,
                                       on_other=self.link._take, abort=self.abort,
                                       alive=self.alive)
        self.texture = texture
        self.rendering = True
        self.uploads += 1
        self._started_at = time.monotonic()
        self._statuses_at_start = self.link.stats.statuses

    TAKE_OVER_S = 1.0  # a display told to stop a previous host's texture: fade (50 ms) and STATUS

    def take_over(self) -> None:
        """Once per connection, before the first upload: STOP_RENDER (answered ACK whatever the
        display does), then its first STATUS of a state other than RENDERING. A display may
        still render what a previous host gave it (that host was killed: a lost host's texture
        plays on while the hand moves), and says so only every 300 ms, so the host cannot know
        from what it has heard; this upload starts from idle (its SET_EQ would be refused BUSY
        while the display renders: the VM rig after SIGKILL rendered on the host with the old
        texture still under it)."""
        if self._taken_over:
            return
        self._taken_over = True
        link = self.link
        try:
            devrender.send_and_confirm(link.t, [pr.encode("STOP_RENDER")], on_other=link._take,
                                       abort=self.abort, alive=self.alive)
        except DeviceTimeout:
            return  # (the upload waits longer and says what the display does)
        deadline = time.monotonic() + self.TAKE_OVER_S
        n0 = link.stats.statuses
        while time.monotonic() < deadline:
            if self.abort is not None and self.abort():
                raise devrender.UploadAborted("stopping")
            if link.poll(0.01) and self.alive is not None:
                self.alive()
            s = link.stats.last_status
            if link.stats.statuses != n0 and s and s["state"] != RENDERING:
                return

    def end(self) -> None:
        if self.rendering or self.start_sent:
            self.link._send(pr.encode("STOP_RENDER"), must=True)  # retried like STOP
        self.texture = None
        self.rendering = self.start_sent = False

    def tick(self) -> None:
        """Once per pump cycle: keep alive, and bring the texture back if the display is not
        rendering it."""
        now = time.monotonic()
        if now - self._last_keepalive >= self._keepalive_s - self._early_s:
            self.link._send(self._keepalive_msg, must=True)  # set_timeout's message, encoded once
            self._last_keepalive = now
        s = self.link.stats.last_status
        # (only a STATUS sent after START_RENDER's answer says what the display does now: the
        # display reports every 300 ms while rendering, so the last one heard may predate it)
        if (self.texture is None or not s or now - self._started_at < 0.1
                or self.link.stats.statuses == self._statuses_at_start):
            return
        if s["state"] != RENDERING:
            self.log(f"device mode: the display stopped rendering (state {s['state']}); uploading "
                     f"{self.texture[0]} again")
            self.rendering = False
            self.recoveries += 1
            try:
                self.begin(self.texture)
            except devrender.UploadAborted:
                return  # stopping: the stop path says STOP_RENDER

    def run(self, stop, each_wake, fds=()) -> None:
        """Device mode's loop, until stop() is true: sleep until the display reports, a
        descriptor in `fds` is readable (commands, hotplug) or the keep-alive is due; then take
        in what arrived and call each_wake(ready): `ready` is the set of descriptors in `fds`
        that woke it (None when the transport cannot say: check them all). With no texture to
        render the display's 1 ms statuses are read in batches every IDLE_WAIT_S.

        One poll() on the transport's descriptor and `fds` per wake-up, set up once: the
        transport is read only when its descriptor is readable (once: Transport.drain or
        Transport.gather), the commands only when theirs is."""
        link = self.link
        t = link.t
        tfd = t.fileno()
        cmd_poll = select.poll()
        for fd in fds:
            cmd_poll.register(fd, select.POLLIN)
        all_poll = None
        if tfd is not None:
            all_poll = select.poll()
            for fd in (tfd, *fds):
                all_poll.register(fd, select.POLLIN)
        while not stop():
            timeout = max(0.0, self._last_keepalive + self._keepalive_s - time.monotonic())
            s = link.stats.last_status
            if self.texture is None and s and s["state"] != RENDERING:
                # nothing to supervise: only commands wake us before the batch
                ready = {fd for fd, _ in cmd_poll.poll(_ms(min(timeout, self.IDLE_WAIT_S)))}
                link.poll()
            elif all_poll is not None and t.gathers:
                # a byte stream (serial): each arrival is read as it wakes the loop, the messages
                # are taken (decoded, acted on) once REPORTS_PER_WAKE pairs are in
                ready, runs = t.gather(fds, _ms(timeout), self._wake_count)
                self.wakeups += runs - 1
                link.poll(read=False)
            elif all_poll is not None and not t.pending():
                ready = {fd for fd, _ in all_poll.poll(_ms(timeout))}
                if tfd in ready:  # (a hang-up too: the read raises DeviceGone)
                    ready.discard(tfd)
                    link.poll()
            else:  # a transport without a descriptor (or with messages already queued)
                t.wait(timeout, fds)
                link.poll()
                ready = None
            self.wakeups += 1
            each_wake(ready)


def _ms(timeout_s: float) -> int:
    """poll()'s timeout: whole milliseconds, rounded up (never a busy early wake-up)."""
    return math.ceil(timeout_s * 1000.0)
