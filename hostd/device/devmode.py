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
"""

from __future__ import annotations

import time

import numpy as np

from hostd.device import devrender
from hostd.device import protocol as pr
from hostd.device.link import DeviceLink

RENDERING = pr.STATES["RENDERING"]


class DeviceMode:
    def __init__(self, link: DeviceLink, cfg, log, host_lost_ms: int = 1000,
                 timeout_ms: int = 50) -> None:
        self.link = link
        self.cfg = cfg  # RenderConfig
        self.log = log
        self.host_lost_ms = int(host_lost_ms)
        self.timeout_ms = int(timeout_ms)
        self.texture = None  # (name, coeffs, n, length_mm)
        self.rendering = False  # START_RENDER acknowledged for the current texture
        self.slot = 1
        self.recoveries = 0
        self.uploads = 0
        # any valid message at least this often: within both the host timeout and host_lost_ms
        self._keepalive_s = min(self.host_lost_ms, self.timeout_ms) / 2000.0
        self._last_keepalive = time.monotonic()
        self._started_at = 0.0

    def check(self, coeffs) -> None:
        """Raise DeviceVersion (what to do) unless this display can render this texture."""
        sos = devrender.device_params(self.cfg)["sos"]
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
            msgs = devrender.setup_messages(c, n, length_mm, self.cfg, slot=self.slot)
            msgs.append(pr.encode("START_RENDER", host_lost_ms=self.host_lost_ms))
        devrender.send_and_confirm(self.link.t, msgs, on_other=self.link._take)
        self.texture = texture
        self.rendering = True
        self.uploads += 1
        self._started_at = time.monotonic()

    def end(self) -> None:
        if self.rendering:
            self.link._send(pr.encode("STOP_RENDER"), must=True)  # retried like STOP
        self.texture = None
        self.rendering = False

    def tick(self) -> None:
        """Once per pump cycle: keep alive, and bring the texture back if the display is not
        rendering it."""
        now = time.monotonic()
        if now - self._last_keepalive >= self._keepalive_s:
            self.link.set_timeout(self.timeout_ms)
            self._last_keepalive = now
        s = self.link.stats.last_status
        if self.texture is None or not s or now - self._started_at < 0.1:
            return
        if s["state"] != RENDERING:
            self.log(f"device mode: the display stopped rendering (state {s['state']}); uploading "
                     f"{self.texture[0]} again")
            self.rendering = False
            self.recoveries += 1
            self.begin(self.texture)
