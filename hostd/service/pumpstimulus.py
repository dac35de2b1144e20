"""A stimulus played by the pump process (hostd.render.stimulus; the daemon's `stimulus` command):
the verdict on it by the device's own count (Stimulus), and the one being played (StimulusPlayer)."""

from __future__ import annotations

import time

# samples of silence the device plays after a stimulus before it is answered and STOPped
STIMULUS_TAIL = 6
# the display's host timeout while it plays a stimulus: what its buffer holds (the pump keeps it
# full for a stimulus: 227 samples, 76 ms) and a little more
STIMULUS_TIMEOUT_MS = 85


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



class StimulusPlayer:
    """The pump process's stimuli (the daemon's `stimulus` command): streamed like a host-rendered
    texture, through the output stage and the firmware's limits, whatever the hand does; answered
    (over `conn`) once the device's own count of samples played covers it. `stim`: the one being
    played. The process moves its phases; this holds the stimulus and its answers."""

    def __init__(self, conn, host_timeout_ms: int) -> None:
        self.conn = conn
        self.host_timeout_ms = host_timeout_ms  # the display's own, set back after a stimulus
        self.stim: Stimulus | None = None  # the stimulus being played

    def answer_stimulus(self, sid: int, error: str | None, retry: bool = True,
                        played: dict | None = None) -> None:
        try:
            self.conn.send(("stimulus", (sid, error, retry, played)))
        except (OSError, EOFError):
            pass

    def drop_stimulus(self, error: str, link=None) -> None:
        """The stimulus being played was not played whole: say so (the client may ask again);
        the display's host timeout is set back on `link` (when it is up; a new link sets it anyway)."""
        s, self.stim = self.stim, None
        if s is not None:
            self.answer_stimulus(s.id, error)
            if link is not None:
                link.set_timeout(self.host_timeout_ms)

    def make_stimulus(self, rcfg, sid: int, f_hz: float, amplitude_um: float,
                      duration_s: float) -> Stimulus | None:
        """The stimulus to play, now the one being played; None when it is refused (answered)."""
        from hostd.errors import StimulusRefused
        from hostd.render.stimulus import StimulusRenderer  # (the stimulus path only)

        try:
            r = StimulusRenderer(rcfg, f_hz, amplitude_um, duration_s)
        except StimulusRefused as e:
            self.answer_stimulus(sid, str(e), retry=False)
            return None
        except Exception as e:  # (the daemon checked it: whatever slipped through never stops the pump)
            self.answer_stimulus(sid, f"stimulus refused: {type(e).__name__}: {e}", retry=False)
            return None
        # (kept before any message goes out: a display lost from here on is answered as such)
        self.stim = s = Stimulus(sid, r, duration_s, time.monotonic())
        return s

    def start_stimulus(self, s: Stimulus, pump, link, dev) -> None:
        """The display streams the stimulus `s` from here (pump.begin)."""
        r = s.renderer
        if dev is not None and dev.rendering:
            dev.end()  # the display stops rendering first; it streams the stimulus
        # the display's host timeout covers the whole buffer while it plays a stimulus: a host
        # stall shorter than what it holds does not cut it (what it holds was all checked; a
        # host gone for longer still ramps the display to zero); set back at the end
        link.set_timeout(max(self.host_timeout_ms, STIMULUS_TIMEOUT_MS))
        r.start()
        pump.begin(r)  # (STOP if it streamed,) load the compiled cycle, prime, START
        s.started(pump, link)

    def verdict(self, pump, link) -> tuple | None:
        """Once per cycle while a stimulus plays (Stimulus.verdict): None while it plays on (or
        none plays), else (its id, its answer), and none is being played any more."""
        s = self.stim
        if s is None:
            return None
        answer = s.verdict(pump, link)
        if answer is None:
            return None
        self.stim = None
        return s.id, answer
