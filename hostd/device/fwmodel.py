"""A model of the firmware's renderer (firmware/src/render.c, protocol v2) in float32 numpy.

The simulated display (hostd.device.simdev) renders with it, so device mode runs where there is
no C compiler. It follows render.c step for step: the same validation and replies, the same
position and speed from edge times, the same float32 arithmetic in the same order where it
matters (the rotation recurrence is numpy's sequential cumprod of complex64). Sums and
transcendental functions may round differently from the C library, so its DAC codes match the
C firmware's within 1 code, not bit for bit: tests/test_device_render.py runs shared scenarios
through both (the C side through firmware/build/fw-replay).
"""

from __future__ import annotations

import math
import struct
import zlib

import numpy as np

from hostd.device import protocol as pr

F32 = np.float32
M32 = 0xFFFFFFFF
M64 = (1 << 64) - 1
R = pr.R
EDGE_HZ: int = R["edge_clock_hz"]
EDGE_PER_TICK = EDGE_HZ // pr.SAMPLE_RATE_HZ
RING = 64
WINDOW = EDGE_HZ // 1000  # speed from the edges of the last 1 ms
STALE = EDGE_HZ // 10  # 100 ms without an edge: at rest
XF = R["xfade_ticks"]
RAMP = pr.P["ramp_ticks"]
Q_NM: int = pr.P["um_per_count_nm"]
MM_S_PER_HALF = F32(Q_NM * 1e-6 / 2.0 * EDGE_HZ)
TWO_PI = F32(6.28318530717958647692)
PI = F32(3.14159265358979323846)
RES = pr.RESULTS
F = pr.FAULTS


class Texture:
    def __init__(self) -> None:
        self.c = np.zeros(R["max_components"], dtype=F32)
        self.n = self.n_samples = self.length_nm = self.dphase_half = self.slot = 0
        self.turns_per_half = self.offset_turns = self.hz_per_mm_s = F32(0)
        self.valid = False


def phase_step(length_nm: int) -> int:
    """q / (4 L) turns per half count in 0.64 fixed point (render.c's long division)."""
    return (Q_NM << 64) // (4 * length_nm)


def hand_edges(t_s: np.ndarray, x_mm: np.ndarray, um_per_count: float = Q_NM * 1e-3):
    """Encoder edges of a hand sampled at times t_s (fine enough that it moves monotonically
    between samples): (edge times s, count after each edge), boundaries at (c ± 1/2) counts,
    crossing times interpolated linearly between samples."""
    q = um_per_count * 1e-3
    x = np.asarray(x_mm, dtype=np.float64)
    t = np.asarray(t_s, dtype=np.float64)
    c = np.floor(x / q + 0.5).astype(np.int64)
    dc = np.diff(c)
    idx = np.nonzero(dc)[0]
    n = np.abs(dc[idx])
    rep = np.repeat(idx, n)
    j = np.arange(rep.size) - np.repeat(np.cumsum(n) - n, n)
    s = np.sign(dc[rep])
    after = c[rep] + s * (j + 1)
    xb = (c[rep] + s * (j + 0.5)) * q
    frac = (xb - x[rep]) / (x[rep + 1] - x[rep])
    return t[rep] + frac * (t[rep + 1] - t[rep]), after


class RenderModel:
    """render.c's state; `dev` is the SimDevice around it (faults, state, ring, replies)."""

    def __init__(self, count: int = 0) -> None:
        self.tex = [Texture(), Texture(), Texture()]
        self.active, self.next, self.staging = 0, 1, 2
        self.loading = False
        self.received = 0
        self.crc = self.crc_want = 0
        self.load_scale = F32(1)
        self.eq: list[list] = []  # [b0, b1, b2, a1, a2, z0, z1] as float32
        self.eq_stage: list[list] = []
        self.n_eq_want = 0
        self.f_stop_hz = F32(400.0)
        self.f_pass_hz = F32(0.8) * F32(400.0)
        self.codes_per_um = F32(pr.LIMIT_CODE) / F32(40.0)
        self.delay_edge = F32(0)
        self.host_lost_ms = R["default_host_lost_ms"]
        self.on = False
        self.env = self.env_target = F32(0)
        self.xfade = 0
        self.host_lost = False
        self.pos = count
        self.eb = np.zeros(RING, dtype=np.int64)  # boundary positions of the edges, half counts
        self.et = np.zeros(RING, dtype=np.int64)  # their edge-clock times (32-bit values)
        self.e_head = 0
        self.e_n = 0
        self.still_anchor = 0
        self.still_since_us = 0
        self.speed_mm_s = F32(0)
        self.last_um = F32(0)
        self.refused = 0
        self.loads = 0
        self.host_lost_count = 0  # episodes (RENDER_STATUS, u16)
        self.rendered_ticks = 0  # ticks at full gain (u32)
        self.faded_ticks = 0  # ticks below full gain: fading in or out (u32)

    # ------------------------------------------------------------ encoder
    def edge(self, count: int, t_edge: int) -> None:
        """The encoder's (unbounded) count after an edge at edge-clock time t_edge."""
        d = count - self.pos
        if d == 0:
            return
        self.pos = count
        self.e_head = (self.e_head + 1) % RING
        self.eb[self.e_head] = 2 * count - (1 if d > 0 else -1)
        self.et[self.e_head] = t_edge & M32
        self.e_n = min(self.e_n + 1, RING)

    def edges(self, counts: np.ndarray, times: np.ndarray) -> None:
        """Many edges at once (counts after each, edge-clock times), as edge() one by one."""
        counts = np.asarray(counts, dtype=np.int64)
        if counts.size == 0:
            return
        d = np.diff(counts, prepend=self.pos)
        keep = d != 0
        counts, d, times = counts[keep], d[keep], np.asarray(times, dtype=np.int64)[keep]
        if counts.size == 0:
            return
        counts, d, times = counts[-RING:], d[-RING:], times[-RING:]
        slots = (self.e_head + 1 + np.arange(counts.size)) % RING
        self.eb[slots] = 2 * counts - np.sign(d)
        self.et[slots] = times & M32
        self.e_head = int(slots[-1])
        self.e_n = min(self.e_n + int(keep.sum()), RING)
        self.pos = int(counts[-1])

    def _estimate(self, now: int) -> tuple[int, np.float32, np.float32]:
        v = F32(0)
        if self.e_n == 0:
            return 2 * self.pos, F32(0), v
        h = self.e_head
        b0 = int(self.eb[h])
        direction = F32(1) if 2 * self.pos > b0 else F32(-1)
        t0 = int(self.et[h])
        since = (now - t0) & M32
        if STALE < since < 0x80000000:
            self.e_n = 1
            return b0, direction, v
        if self.e_n >= 2:
            # render.c: k = 1, then k + 1 while the edge k + 1 back is within the window
            back = (h - np.arange(2, self.e_n)) % RING
            within = ((t0 - self.et[back]) & M32) <= WINDOW
            k = 1 + (int(np.argmin(within)) if not within.all() else within.size)
            i = (h - k) % RING
            dt = (t0 - int(self.et[i])) & M32
            if 0 < dt < 0x80000000:
                v = F32(b0 - int(self.eb[i])) / F32(dt)
        s = F32(since) if since < 0x80000000 else F32(0)
        if abs(v) * s > F32(2):
            v = (F32(2) if v > 0 else F32(-2)) / s
        q = v * s
        q = min(max(q, F32(0)), F32(2)) if direction > 0 else min(max(q, F32(-2)), F32(0))
        return b0, F32(q), v

    # ------------------------------------------------------------ series
    @staticmethod
    def _phase(t: Texture, b0: int, pf) -> np.float32:
        ph = (b0 * t.dphase_half) & M64
        hi = F32(ph >> 32) * F32(2.3283064365386963e-10)
        phi = hi + pf * t.turns_per_half + t.offset_turns
        return phi - np.floor(phi)

    @staticmethod
    def _series(t: Texture, phi, vabs, f_pass, f_stop) -> np.float32:
        th = TWO_PI * phi
        w = np.complex64(complex(np.cos(th), np.sin(th)))
        n = t.n
        n_pass = n_end = n
        f1 = vabs * t.hz_per_mm_s
        if f1 > 0:
            kp, ks = f_pass / f1, f_stop / f1
            if kp < F32(n):
                n_pass = int(kp)
            if ks < F32(n) + F32(1):
                n_end = math.ceil(ks) - 1
            n_pass = min(n_pass, n_end)
        if n_end <= 0:
            return F32(0)
        z = np.cumprod(np.full(n_end, w, dtype=np.complex64))
        zr = z.real
        c = t.c
        acc = F32(0)
        if n_pass > 0:
            acc = F32(np.dot(c[:n_pass], zr[:n_pass]))
        if n_end > n_pass:
            span = f_stop - f_pass
            a0 = PI * (F32(n_pass + 1) * f1 - f_pass) / span
            b = PI * f1 / span
            g = np.full(n_end - n_pass, np.complex64(complex(np.cos(b), np.sin(b))), dtype=np.complex64)
            g[0] = np.complex64(complex(np.cos(a0), np.sin(a0)))
            g = np.cumprod(g)
            gain = F32(0.5) + F32(0.5) * g.real
            acc = acc + F32(np.dot(c[n_pass:n_end] * gain, zr[n_pass:n_end]))
        return F32(acc)

    def _equalize(self, x):
        for s in self.eq:
            b0, b1, b2, a1, a2, z0, z1 = s
            y = b0 * x + z0
            z0 = b1 * x - a1 * y + z1
            z1 = b2 * x - a2 * y
            s[5] = z0 if abs(z0) >= F32(1e-30) else F32(0)
            s[6] = z1 if abs(z1) >= F32(1e-30) else F32(0)
            x = y
        return x

    def halt(self) -> None:
        if self.xfade:
            self.active, self.next = self.next, self.active
            self.xfade = 0
        self.on = False
        self.env = self.env_target = F32(0)
        self.host_lost = False

    def tick(self, dev) -> int:
        """One tick of rendering (dev.ticks already incremented): the target code."""
        now = ((dev.ticks - 1) * EDGE_PER_TICK) & M32
        now_us = ((dev.ticks - 1) * 1_000_000 // pr.SAMPLE_RATE_HZ) & M32
        if abs(self.pos - self.still_anchor) > 2:
            self.still_anchor = self.pos
            self.still_since_us = now_us
        lost = ((now_us - dev.last_rx_us) & M32) > self.host_lost_ms * 1000
        if lost and not self.host_lost:
            self.host_lost_count += 1
        self.host_lost = lost
        if self.host_lost:
            dev.faults |= F["HOST_LOST"]
            if ((now_us - self.still_since_us) & M32) >= R["still_ms"] * 1000 and self.env_target > 0:
                self.env_target = F32(0)
                dev.faults |= F["HOST_TIMEOUT"]
        b0, p, v = self._estimate(now)
        pf = p + v * self.delay_edge
        vabs = abs(v) * MM_S_PER_HALF
        self.speed_mm_s = v * MM_S_PER_HALF
        ta = self.tex[self.active]
        with np.errstate(over="ignore", invalid="ignore"):
            h = self._series(ta, self._phase(ta, b0, pf), vabs, self.f_pass_hz, self.f_stop_hz)
            if self.xfade:
                tn = self.tex[self.next]
                h2 = self._series(tn, self._phase(tn, b0, pf), vabs, self.f_pass_hz, self.f_stop_hz)
                a = F32(self.xfade) / F32(XF)
                h = h + a * (h2 - h)
                self.xfade += 1
                if self.xfade > XF:
                    self.active, self.next = self.next, self.active
                    self.xfade = 0
            y = self._equalize(h)
            step = F32(1) / F32(RAMP)
            if self.env < self.env_target:
                self.env = min(self.env + step, self.env_target)
            elif self.env > self.env_target:
                self.env = max(self.env - step, self.env_target)
            y = y * self.env
            code = y * self.codes_per_um
        if self.env >= 1:
            self.rendered_ticks += 1
        else:
            self.faded_ticks += 1
        if dev.ticks % R["status_period_ticks"] == 0:
            dev.outbox.append(self.status(dev, now_us))
        if self.env == 0 and self.env_target == 0:
            self.halt()
            dev.state = pr.STATES["IDLE"]
        if not np.isfinite(code):
            for s in self.eq:
                s[5] = s[6] = F32(0)
            self.last_um = F32(0)
            return dev.out
        self.last_um = y
        return int(np.rint(min(max(code, F32(-32768)), F32(32767))))

    def status(self, dev, now_us: int) -> bytes:
        rs = pr.RENDER_STATES
        state = (rs["FADE_OUT"] if self.env_target == 0 else rs["CROSSFADE"] if self.xfade
                 else rs["FADE_IN"] if self.env < 1 else rs["ON"])
        return pr.encode("RENDER_STATUS", render_state=state, active_slot=self.tex[self.active].slot,
                         host_lost=int(self.host_lost), speed_mm_s=float(self.speed_mm_s),
                         refused=self.refused & 0xFFFF, loads=self.loads & 0xFFFF,
                         host_silent_ms=min(((now_us - dev.last_rx_us) & M32) // 1000, 0xFFFF),
                         host_lost_count=self.host_lost_count & 0xFFFF, device_time_us=now_us,
                         rendered_ticks=self.rendered_ticks & M32, faded_ticks=self.faded_ticks & M32,
                         idle_ticks=dev.idle_ticks & M32)

    # ------------------------------------------------------------ messages
    def _reply(self, dev, name: str, slot: int, result: str, detail: int = 0) -> None:
        if result != "OK":
            self.refused += 1
            dev.faults |= F["REFUSED"]
        dev.outbox.append(pr.encode("ACK", for_id=pr.IDS[name], slot=slot, result=RES[result],
                                    detail=detail & 0xFFFF, refused=self.refused & 0xFFFF))

    def on_message(self, dev, name: str, f: dict) -> None:
        """A well-formed render message (pr.decode accepted it)."""
        getattr(self, "_" + name.lower())(dev, f)

    def _load_texture(self, dev, f) -> None:
        self.loading = False
        nc, ns, ln = f["n_coeffs"], f["n_samples"], f["length_nm"]
        if nc == 0 or nc > R["max_components"] or ns == 0 or ln < Q_NM or ln > R["max_length_nm"]:
            return self._reply(dev, "LOAD_TEXTURE", f["slot"], "TOO_LARGE", nc)
        if not math.isfinite(f["scale"]):
            return self._reply(dev, "LOAD_TEXTURE", f["slot"], "NONFINITE")
        t = self.tex[self.staging]
        t.valid = False
        t.n, t.n_samples, t.length_nm, t.slot = nc, ns, ln, f["slot"]
        self.loading = True
        self.received = 0
        self.crc = 0
        self.crc_want = f["crc32"]
        self.load_scale = F32(f["scale"])

    def _load_chunk(self, dev, f) -> None:
        t = self.tex[self.staging]
        vals = f["coeffs"]
        first = f["first"]
        if not self.loading or f["slot"] != t.slot or first != self.received or first + len(vals) > t.n:
            self._reply(dev, "LOAD_CHUNK", f["slot"], "OUT_OF_ORDER", self.received)
            self.loading = False
            return
        for i, v in enumerate(vals):
            if not math.isfinite(v):
                self._reply(dev, "LOAD_CHUNK", f["slot"], "NONFINITE", first + i)
                self.loading = False
                return
        t.c[first : first + len(vals)] = vals
        self.crc = zlib.crc32(struct.pack(f"<{len(vals)}f", *vals), self.crc)
        self.received += len(vals)

    def _load_end(self, dev, f) -> None:
        t = self.tex[self.staging]
        slot = f["slot"]
        if not self.loading or slot != t.slot or self.received != t.n:
            self._reply(dev, "LOAD_END", slot, "TRUNCATED", self.received)
            self.loading = False
            return
        if self.crc != self.crc_want:
            self._reply(dev, "LOAD_END", slot, "BAD_CRC", self.received)
            self.loading = False
            return
        if self.on and self.xfade:
            return self._reply(dev, "LOAD_END", slot, "BUSY", self.received)
        with np.errstate(over="ignore"):
            scaled = t.c[: t.n] * self.load_scale
        bad = np.nonzero(~np.isfinite(scaled))[0]
        if bad.size:
            self._reply(dev, "LOAD_END", slot, "NONFINITE", int(bad[0]))
            self.loading = False
            return
        t.c[: t.n] = scaled
        t.dphase_half = phase_step(t.length_nm)
        t.turns_per_half = F32(float(t.dphase_half) * 2.0**-64)
        t.offset_turns = F32(0.25) / F32(t.n_samples)
        t.hz_per_mm_s = F32(1e6) / (F32(2) * F32(t.length_nm))
        t.valid = True
        self.loading = False
        self.loads += 1
        if self.on:
            self.next, self.staging = self.staging, self.next
            self.xfade = 1
        else:
            self.active, self.staging = self.staging, self.active
        self._reply(dev, "LOAD_END", slot, "OK", t.n)

    def _set_eq(self, dev, f) -> None:
        idx, ns = f["index"], f["n_sections"]
        b0, b1, b2, a1, a2 = (F32(f[k]) for k in ("b0", "b1", "b2", "a1", "a2"))
        if self.on:
            return self._reply(dev, "SET_EQ", idx, "BUSY")
        if ns == 0:
            self.eq, self.eq_stage = [], []
            return self._reply(dev, "SET_EQ", idx, "OK")
        if not all(np.isfinite(v) for v in (b0, b1, b2, a1, a2)):
            self.eq_stage = []
            return self._reply(dev, "SET_EQ", idx, "NONFINITE", idx)
        if ns > R["max_sections"] or idx >= ns or not (abs(a2) < 1 and abs(a1) < F32(1) + a2):
            self.eq_stage = []
            return self._reply(dev, "SET_EQ", idx, "BAD_PARAM", idx)
        if idx == 0:
            self.eq_stage = []
            self.n_eq_want = ns
        if idx != len(self.eq_stage) or ns != self.n_eq_want:
            n = len(self.eq_stage)
            self.eq_stage = []
            return self._reply(dev, "SET_EQ", idx, "OUT_OF_ORDER", n)
        self.eq_stage.append([b0, b1, b2, a1, a2, F32(0), F32(0)])
        if len(self.eq_stage) == ns:
            self.eq, self.eq_stage = self.eq_stage, []
            self._reply(dev, "SET_EQ", idx, "OK", ns)

    def _set_band(self, dev, f) -> None:
        fs, fr = F32(f["f_stop_hz"]), F32(f["fade_start"])
        if not (np.isfinite(fs) and np.isfinite(fr)):
            return self._reply(dev, "SET_BAND", 0, "NONFINITE")
        if not (0 < fs <= F32(0.5) * F32(pr.SAMPLE_RATE_HZ) and 0 <= fr < 1):
            return self._reply(dev, "SET_BAND", 0, "BAD_PARAM")
        self.f_stop_hz, self.f_pass_hz = fs, fr * fs
        self._reply(dev, "SET_BAND", 0, "OK")

    def _set_scale(self, dev, f) -> None:
        s = F32(f["codes_per_um"])
        if not np.isfinite(s):
            return self._reply(dev, "SET_SCALE", 0, "NONFINITE")
        if not (0 < s <= F32(1e6)):
            return self._reply(dev, "SET_SCALE", 0, "BAD_PARAM")
        self.codes_per_um = s
        self._reply(dev, "SET_SCALE", 0, "OK")

    def _set_delay(self, dev, f) -> None:
        d = f["delay_us"]
        if abs(d) > 20000:
            return self._reply(dev, "SET_DELAY", 0, "BAD_PARAM")
        self.delay_edge = F32(d) * F32(EDGE_HZ // 1_000_000)
        self._reply(dev, "SET_DELAY", 0, "OK")

    def _start_render(self, dev, f) -> None:
        if not self.tex[self.active].valid:
            return self._reply(dev, "START_RENDER", 0, "NO_TEXTURE")
        self.host_lost_ms = f["host_lost_ms"] or R["default_host_lost_ms"]
        if not self.on:
            for s in self.eq:
                s[5] = s[6] = F32(0)
            self.env = F32(0)
        self.on = True
        self.env_target = F32(1)
        self.host_lost = False
        dev.ring.clear()
        dev.in_underrun = False
        dev.state = pr.STATES["RENDERING"]
        self._reply(dev, "START_RENDER", self.tex[self.active].slot, "OK")

    def _stop_render(self, dev, f) -> None:
        if self.on:
            self.env_target = F32(0)
        self._reply(dev, "STOP_RENDER", 0, "OK")
