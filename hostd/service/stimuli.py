"""Stimuli on the control socket ([experiment] stimuli): one sinusoid at a time, checked against the
display's reach, played by the pump in place of the texture, answered once the device played it."""

from __future__ import annotations

import itertools
import logging
import math
import threading
from collections.abc import Callable

from hostd.errors import HostdError
from hostd.service.control import BadRequest

log = logging.getLogger("hostd")

class StimulusFailed(HostdError):
    """A stimulus that was not played whole (no display, the display lost or running dry
    mid-stimulus, interrupted): the client may ask again (its reply says "retry": true)."""

    retry = True


STIMULUS_SLACK_S = 5.0  # beyond its duration, how long a stimulus may take before hostd gives up
MAX_REACH_FREQUENCIES = 256  # per `reach` request


class Stimuli:
    """The daemon's `stimulus` and `reach` requests and the pump's answers. `refuse` counts and
    raises a refusal (the daemon's); `take_over(msg)` ends the texture being played and sends msg
    to the pump in its place, returning the name it stopped; `lock` is the daemon's."""

    def __init__(self, cfg, lock: threading.Lock, refuse: Callable[[str], None],
                 take_over: Callable[[tuple], str | None]) -> None:
        self.cfg = cfg
        self.lock = lock
        self.refuse = refuse
        self.take_over = take_over
        # stimuli ([experiment] stimuli): one at a time; the pump's answers by stimulus id
        self.stimulus_lock = threading.Lock()
        self.stimulus_ids = itertools.count(1)
        self.stimulus_answers: dict[int, list] = {}  # id -> [Event, answer], under self.lock
        self._stimulus_bound = None

    def stimulus_bound(self):
        """The bound every stimulus is checked against (hostd.render.stimulus, from this
        daemon's config: output.travel_um, output.slew_um_s, render.actuator)."""
        if not self.cfg.experiment.stimuli:
            self.refuse(f"this hostd does not play stimuli: set [experiment] stimuli = true in "
                        f"{self.cfg.path} and restart hostd (`hostd experiment threshold --help`)")
        if self._stimulus_bound is None:
            from hostd.render.stimulus import StimulusBound

            self._stimulus_bound = StimulusBound(self.cfg.render_config())
        return self._stimulus_bound

    def reach(self, req: dict) -> dict:
        """The largest stimulus (µm peak at the finger) at each frequency asked."""
        from hostd.render.stimulus import MAX_DURATION_S, MAX_FREQUENCY_HZ

        bound = self.stimulus_bound()
        fs = req.get("frequencies_hz")
        if not (isinstance(fs, list) and 0 < len(fs) <= MAX_REACH_FREQUENCIES
                and all(isinstance(f, int | float) and not isinstance(f, bool) and math.isfinite(f)
                        and 0 < f <= MAX_FREQUENCY_HZ for f in fs)):
            raise BadRequest(f"bad request: frequencies_hz must be a list of 1..{MAX_REACH_FREQUENCIES} "
                             f"frequencies in (0, {MAX_FREQUENCY_HZ:g}] Hz")
        return {"reach_um": [bound.reach_um(float(f)) for f in fs], "max_duration_s": MAX_DURATION_S,
                "max_frequency_hz": MAX_FREQUENCY_HZ}

    def play_stimulus(self, req: dict) -> dict:
        """Play one sinusoid (frequency_hz, amplitude_um at the finger, duration_s) on the display
        and answer once the device has played it (its own count of samples played), then the
        display is idle. Checked here against the display's reach (StimulusRefused: nothing is
        played), and again by the pump; it stops a texture being played. One at a time."""
        bound = self.stimulus_bound()
        f, a, d = (req.get(k) for k in ("frequency_hz", "amplitude_um", "duration_s"))
        try:
            bound.check(f, a, d)
        except HostdError as e:
            log.warning("control socket: %s", e)
            self.refuse(str(e))
        if not self.stimulus_lock.acquire(blocking=False):
            raise StimulusFailed("another stimulus is being played: one at a time")
        sid = None
        try:
            sid = next(self.stimulus_ids)
            waiting = [threading.Event(), None]
            with self.lock:
                self.stimulus_answers[sid] = waiting
            # the texture being played (if any) ends here
            stopped = self.take_over(("stimulus", (sid, float(f), float(a), float(d))))
            if not waiting[0].wait(d + STIMULUS_SLACK_S) or waiting[1] is None:
                raise StimulusFailed(f"the pump did not report the stimulus played within "
                                     f"{d + STIMULUS_SLACK_S:g} s")
            _sid, error, retry, played = waiting[1]
            if error:
                if retry:
                    raise StimulusFailed(error)
                self.refuse(error)
            return {"played": played, "stopped": stopped}
        finally:
            with self.lock:
                self.stimulus_answers.pop(sid, None)
            self.stimulus_lock.release()

    def answered(self, msg: tuple) -> None:
        """The pump's answer to a stimulus: (id, error or None, retry, what the device played)."""
        with self.lock:
            waiting = self.stimulus_answers.get(msg[0])
        if waiting is not None:
            waiting[1] = msg
            waiting[0].set()
