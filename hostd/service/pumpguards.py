"""What a display claims, checked before the pump publishes it: bad frames and messages, a flood
of STATUS, counters beyond what the host knows, counters that went back; each named in one log
line per burst, none of it acted on. Loaded by the pump process only (hostd.service.pumpproc)."""

from __future__ import annotations

import math
import time

from hostd.device import protocol as pr
from hostd.device.health import HostBound


class DeviceClaims:
    """The publish-side guards of one pump process over its display's claims. link_up() at each
    new link; then, at each publish, the checks in the order publish() calls them and
    `bounds[name].shown`: the device's counters as shown (status, metrics, the plays rows)."""

    # (name, most per second of the link (None: from the samples sent), how a claim above reads)
    BOUND_RULES = (("samples", None, "{:.0f} samples played"), ("elapsed", 1.0, "{:.1f} s of its clock"),
                   ("underruns", pr.SAMPLE_RATE_HZ / 2, "{:.0f} underruns"),
                   ("rendered", pr.SAMPLE_RATE_HZ, "{:.0f} ticks rendered"),
                   ("faded", pr.SAMPLE_RATE_HZ, "{:.0f} ticks faded"),
                   ("idle", pr.SAMPLE_RATE_HZ, "{:.0f} ticks idle"))

    def __init__(self, log, flood_factor: float) -> None:
        self.log = log
        self.flood_factor = flood_factor
        self.bad_seen = [0, -math.inf]  # bad frames of this link: counted, time of the last one
        self.bad_msgs_seen = [0, -math.inf]  # bad messages (valid frames) of this link: the same
        self.resets_seen = [0, -math.inf]  # the device's counter resets (health.resets), time of the last one
        # a flood of STATUS: a display reports once per status_period_ticks at most (1 ms while it
        # streams, 300 ms while it renders); STATUS counted per second of host time, against that
        # fastest rate. A window ends only when the pump looks (publish()), so a backlog the host
        # reads after its own stall falls in the window that holds the stall: it never looks like a
        # flood. [window start, link.stats.statuses then, flooding]
        self.max_status_hz = pr.SAMPLE_RATE_HZ / pr.P["status_period_ticks"]
        self.flood = [time.monotonic(), 0, False]
        # the device's counters as shown (status, metrics, the plays rows), bounded by what the host
        # knows: samples played at most those this link sent plus a buffer; the device time elapsed
        # and the display's ticks at most the link's time up (+1 %, +0.5 s), underruns one per two
        # ticks. A claim above: one line per burst naming the device (the first after a quiet second)
        self.bounds = {k: HostBound()
                       for k in ("samples", "elapsed", "underruns", "rendered", "faded", "idle")}
        self.impossible_seen = -math.inf

    @staticmethod
    def claimed(h) -> dict:
        return {"samples": h.samples_played, "elapsed": h.elapsed_s, "underruns": h.underruns,
                "rendered": h.rendered_ticks, "faded": h.faded_ticks, "idle": h.idle_ticks}

    def link_up(self, link, health) -> None:
        """A new link (`health`: the pump's DeviceHealth, None before the first one)."""
        # (the old link's counts since the last publish stay the old link's)
        for k, b in self.bounds.items():
            b.link_up(time.clock_gettime(time.CLOCK_BOOTTIME),
                      0.0 if health is None else self.claimed(health)[k])
        self.bad_seen[:] = [0, -math.inf]
        self.bad_msgs_seen[:] = [0, -math.inf]
        self.flood[:] = [time.monotonic(), link.stats.statuses, False]

    def check_messages(self, transport, link, now: float) -> None:
        # a device's garbage, cut, oversized or unknown messages: dropped (bad CRC, bad layout),
        # never acted on; one line per burst (the first bad one after a quiet second), naming it.
        # Bad frames (the framing: garbage, cut, oversized, also a frame the host's own stall
        # cut) and bad messages (valid frames hostd cannot take: an unknown id, a bad layout) are
        # bursts of their own: a cut frame of a stall never hides a message the device made up
        framer = getattr(transport, "deframer", None)
        bad_frames = framer.bad_frames if framer is not None else 0
        for seen, bad, what in (
                (self.bad_seen, bad_frames, "garbage, cut or oversized frames"),
                (self.bad_msgs_seen, link.stats.bad_messages_received,
                 f"messages hostd cannot take, the last: {link.stats.last_bad}")):
            if bad > seen[0]:
                if now - seen[1] >= 1.0:
                    self.log(f"device: {transport.describe()} sent bad frames or messages ({what}; {bad} on "
                             "this link); dropped, the rest of the burst silently")
                seen[:] = [bad, now]

    def check_flood(self, transport, link, now: float) -> None:
        flood = self.flood
        span_s = now - flood[0]
        if span_s >= 1.0:  # one line per flood episode (windows over the rate in a row), naming it
            n_status = link.stats.statuses - flood[1]
            expected = span_s * self.max_status_hz
            flooding = n_status > self.flood_factor * expected
            if flooding and not flood[2]:
                self.log(f"device: {transport.describe()} sent {n_status} status reports in {span_s:.1f} s "
                         f"(expected at most ~{expected:.0f}): flooding; each is checked as usual, the host "
                         "keeps its own pace")
            flood[:] = [now, link.stats.statuses, flooding]

    def check_bounds(self, transport, link, h, now: float) -> None:
        """The device's counters (`h`: the pump's DeviceHealth) taken within what the host knows."""
        sent = link.stats.samples_sent
        boot = time.clock_gettime(time.CLOCK_BOOTTIME)  # a device's clock runs on while the host sleeps
        # (one pass over constant tables: the bounds were ~37 µs of a ~100 µs publish as dicts)
        bounds = self.bounds
        claims = []
        told = self.claimed(h)
        for k, per_s, fmt in self.BOUND_RULES:
            b = bounds[k]
            if per_s is None:  # samples played: at most those sent on this link, plus a buffer
                over = b.take(told[k], b.base + sent + pr.BUFFER_CAPACITY, pr.BUFFER_CAPACITY)
            else:
                over = b.take(told[k], *b.within_time(boot, per_s))
            if over > 0:
                claims.append(fmt.format(over))
        if claims:
            if now - self.impossible_seen >= 1.0:
                up_s = boot - bounds["samples"].t0
                self.log(f"device: {transport.describe()} reported the impossible: {', '.join(claims)} "
                         f"more than {up_s:.1f} s of its link and the {sent} samples sent to it allow; its "
                         "counters are shown within what the host knows")
            self.impossible_seen = now

    def check_resets(self, transport, h) -> None:
        resets_seen = self.resets_seen
        if h.resets > resets_seen[0]:  # counters or clock went back or leapt: one line per burst
            t_reset = time.monotonic()
            if t_reset - resets_seen[1] >= 1.0:
                self.log(f"device: {transport.describe()} reported counters or a clock that went back or "
                         f"leapt (a reset, or a device that lies; {h.resets} in all); counted from a new "
                         "baseline")
            resets_seen[:] = [h.resets, t_reset]
