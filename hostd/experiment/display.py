"""What a stimulus is, how far the display can reach, and the displays that play stimuli.

Safety, host side: the bound is hostd.render.stimulus.StimulusBound (the daemon applies the
same one to its clients' stimuli): a sinusoid of amplitude A µm at f Hz needs a command of
A / |H(f)| (the actuator's response, config render.actuator) that must stay inside the output
stage's limits (output.travel_um: |x| <= travel/2 at its code limit; output.slew_um_s:
2 pi f A_cmd <= slew). `reach_um(f)` is that bound times SAFETY_MARGIN; `check()` refuses
(StimulusRefused, an ExperimentError) any stimulus above it before anything is played, or one
the output stage would have to limit. SimDisplay renders through the real output stage and
refuses again if the stage had to clip or slew-limit a single sample; DaemonDisplay's daemon
checks again and streams through its output stage and the firmware's limits. The firmware's
own limits (firmware/src/core.c: |code| <= limit_code, slew <= max_step_code, whatever the host
sends) are tested by firmware/tests/test_fw.c (test_limits_only_tighten plays codes
32767/-32768 over the limit; test_random_bytes_never_break_safety) and, for stimuli, by
tests/test_stimulus_daemon.py on the firmware's host port. A procedure never asks beyond the
reach: its stimulus grid stops there, and a threshold estimated above it is reported as such
(ThresholdResult.status "above_reach").
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np

from hostd.errors import DeviceGone, ExperimentError
from hostd.render.stimulus import RAMP_S, SAFETY_MARGIN, SAMPLE_RATE_HZ, StimulusBound, sinusoid_um

__all__ = ["RAMP_S", "SAFETY_MARGIN", "SAMPLE_RATE_HZ", "DaemonDisplay", "DaemonReach", "Reach", "SimDisplay",
           "Sinusoid"]


@dataclass(frozen=True)
class Sinusoid:
    """A sinusoidal displacement (µm peak) at frequency_hz for duration_s, raised-cosine ramps."""

    frequency_hz: float
    amplitude_um: float
    duration_s: float = 0.5

    def samples_um(self, gain: float = 1.0) -> np.ndarray:
        return sinusoid_um(self.frequency_hz, self.amplitude_um, self.duration_s, gain)


class Reach(StimulusBound):
    """The largest sinusoid (µm peak at the finger) the display can play at f, from the config's
    output stage and actuator model (hostd.render.stimulus: the bound the daemon applies too)."""

    def __init__(self, render_config=None) -> None:
        if render_config is None:
            from hostd.service.config import load

            render_config = load(None).render_config()
        super().__init__(render_config)

    def check(self, s: Sinusoid) -> None:  # type: ignore[override]
        """Refuse a stimulus beyond the reach (or not a finite positive one): nothing is played
        (StimulusRefused, an ExperimentError)."""
        super().check(*(float(v) if isinstance(v, np.number) else v
                        for v in (s.frequency_hz, s.amplitude_um, s.duration_s)))


class SimDisplay:
    """The simulated display: each stimulus is checked, rendered through the real output stage
    at 3 kHz (refused if the stage had to limit a sample) and kept as the last samples played.
    `fail_on` lists play numbers (0-based) at which the display 'disconnects' (DeviceGone),
    as a real one may mid-trial; `realtime` sleeps for the stimulus' duration."""

    def __init__(self, reach: Reach | None = None, realtime: bool = False,
                 fail_on: set[int] | None = None) -> None:
        self.reach = reach or Reach()
        self.realtime = realtime
        self.fail_on = set(fail_on or ())
        self.plays = 0
        self.last_um: np.ndarray | None = None
        self.lock = threading.Lock()

    def play(self, s: Sinusoid) -> None:
        from hostd.render.output import OutputStage

        self.reach.check(s)
        with self.lock:
            n = self.plays
            self.plays += 1
            if n in self.fail_on:
                raise DeviceGone("the display disconnected during the stimulus")
            stage = OutputStage(self.reach.stage.cfg)
            stage.start()
            stage.envelope = 1.0  # the stimulus has its own ramps
            cmd = s.samples_um(self.reach.gain(s.frequency_hz))
            out = stage.process(cmd)
            if stage.clipped or not np.allclose(out, cmd, rtol=0, atol=1e-12):
                raise ExperimentError(f"stimulus {s} refused: the output stage had to limit it")
            self.last_um = out
        if self.realtime:
            time.sleep(s.duration_s)

    def play_silence(self, duration_s: float) -> None:
        """An interval without the stimulus."""
        if self.realtime:
            time.sleep(duration_s)

    def wait(self, duration_s: float) -> None:
        """Between intervals: nothing is played."""
        if self.realtime:
            time.sleep(duration_s)

    def play_stream(self, path: str, seconds: float) -> None:
        """A texture stream: decoded (a corrupt one is refused) and, on this display, not felt."""
        from hostd.codec import stream as vtx

        with self.lock:
            n = self.plays
            self.plays += 1
            if n in self.fail_on:
                raise DeviceGone("the display disconnected during the texture")
        vtx.decode(open(path, "rb").read())
        if self.realtime:
            time.sleep(seconds)


SILENCE_HZ = 100.0  # the frequency of a silent interval's stimulus (amplitude 0: the value is moot)


class DaemonReach:
    """The running daemon's reach (its `reach` command: the bound it applies to every stimulus,
    from its own config), asked once per frequency."""

    def __init__(self, display: DaemonDisplay) -> None:
        self.display = display
        self.cache: dict[float, float] = {}

    def reach_um(self, f_hz: float) -> float:
        f = float(f_hz)
        if f not in self.cache:
            rep = self.display._request({"cmd": "reach", "frequencies_hz": [f]}, refusal=ExperimentError)
            self.cache[f] = float(rep["reach_um"][0])
        return self.cache[f]


class DaemonDisplay:
    """The running daemon's display, through its control socket.

    A sinusoid is the daemon's `stimulus` command: the daemon checks it against the display's
    reach (from its own config; refused: ExperimentError), its pump streams it through the
    output stage and the firmware's limits, and it answers once the display has played it (the
    device's own count of samples played). A silent interval is the same command at amplitude 0,
    so the display does exactly the same in every interval but the one that holds the stimulus
    (no cue from the display starting or stopping). No display, a display lost or running dry
    mid-stimulus, a daemon not answering: DeviceGone (the trial is repeated, nothing recorded).
    The daemon plays stimuli only with `[experiment] stimuli = true` in its config.

    A texture (the similarity experiment) is sent once, selected for `seconds` while the
    participant strokes it, then stopped."""

    def __init__(self, socket_path: str) -> None:
        self.socket_path = socket_path
        self.sent: dict[str, str] = {}
        self.reach = DaemonReach(self)

    def play(self, s: Sinusoid) -> None:
        self._stimulus(float(s.frequency_hz), float(s.amplitude_um), float(s.duration_s))

    def play_silence(self, duration_s: float) -> None:
        """An interval without the stimulus: the same command at amplitude 0."""
        self._stimulus(SILENCE_HZ, 0.0, float(duration_s))

    def wait(self, duration_s: float) -> None:
        """Between intervals: nothing is played."""
        time.sleep(duration_s)

    def _stimulus(self, f_hz: float, amplitude_um: float, duration_s: float) -> None:
        self._request({"cmd": "stimulus", "frequency_hz": f_hz, "amplitude_um": amplitude_um,
                       "duration_s": duration_s}, refusal=ExperimentError, timeout_s=duration_s + 15.0)

    def _request(self, req: dict, payload: bytes = b"", refusal=DeviceGone, timeout_s: float = 30.0) -> dict:
        """One request; a daemon not answering or a failure worth a retry (the reply's `retry`)
        is DeviceGone, another refusal is `refusal`."""
        from hostd.service.client import ClientError, request

        try:
            return request(self.socket_path, req, payload, timeout_s=timeout_s)
        except ClientError as e:
            reply = getattr(e, "reply", None)
            if reply is None or reply.get("retry"):
                raise DeviceGone(f"the daemon: {e}") from None
            raise refusal(f"the daemon refused: {e}") from None
        except OSError as e:
            raise DeviceGone(f"the daemon is not answering: {e}") from None

    def play_stream(self, path: str, seconds: float) -> None:
        import hashlib
        from pathlib import Path

        data = Path(path).read_bytes()
        name = "exp-" + hashlib.sha256(data).hexdigest()[:16]
        if name not in self.sent:
            self._request({"cmd": "send", "name": name, "size": len(data)}, data)
            self.sent[name] = path
        self._request({"cmd": "select", "name": name})
        time.sleep(seconds)
        self._request({"cmd": "stop"})
