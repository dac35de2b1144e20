"""What a stimulus is, how far the display can reach, and the displays that play stimuli.

Safety, host side: a sinusoid of amplitude A µm at f Hz needs a command of A / |H(f)| (the
actuator's response, config render.actuator) that must stay inside the output stage's limits
(output.travel_um: |x| <= travel/2 at its code limit; output.slew_um_s: 2 pi f A_cmd <= slew).
`reach_um(f)` is that bound times SAFETY_MARGIN; `check()` refuses (ExperimentError) any
stimulus above it before anything is played, and SimDisplay renders through the real output
stage (hostd.render.output.OutputStage) and refuses again if the stage had to clip or slew-
limit a single sample. The firmware's own limits (firmware/src/core.c: |code| <= limit_code,
slew <= max_step_code, whatever the host sends) are tested by firmware/tests/test_fw.c
(test_limits_only_tighten plays codes 32767/-32768 over the limit; test_random_bytes_never_
break_safety). A procedure never asks beyond the reach: its stimulus grid stops there, and a
threshold estimated above it is reported as such (ThresholdResult.status "above_reach").
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass

import numpy as np

from hostd.errors import DeviceGone, ExperimentError

SAFETY_MARGIN = 0.9  # the procedures stay 10 % (0.9 dB) inside the output stage's limits
SAMPLE_RATE_HZ = 3000.0
RAMP_S = 0.05  # raised-cosine onset and offset: no click at the ends of a stimulus


@dataclass(frozen=True)
class Sinusoid:
    """A sinusoidal displacement (µm peak) at frequency_hz for duration_s, raised-cosine ramps."""

    frequency_hz: float
    amplitude_um: float
    duration_s: float = 0.5

    def samples_um(self, gain: float = 1.0) -> np.ndarray:
        n = round(self.duration_s * SAMPLE_RATE_HZ)
        t = np.arange(n) / SAMPLE_RATE_HZ
        env = np.ones(n)
        r = min(int(RAMP_S * SAMPLE_RATE_HZ), n // 2)
        if r:
            ramp = 0.5 - 0.5 * np.cos(np.pi * np.arange(r) / r)
            env[:r], env[n - r:] = ramp, ramp[::-1]
        return (self.amplitude_um / gain) * env * np.sin(2 * np.pi * self.frequency_hz * t)


class Reach:
    """The largest sinusoid (µm peak at the finger) the display can play at f, from the config's
    output stage and actuator model."""

    def __init__(self, render_config=None) -> None:
        from hostd.render.output import OutputStage

        if render_config is None:
            from hostd.service.config import load

            render_config = load(None).render_config()
        self.render_config = render_config
        self.stage = OutputStage(render_config.output)
        self.actuator = render_config.actuator

    def gain(self, f_hz: float) -> float:
        return float(abs(self.actuator.measured(np.array([float(f_hz)]))[0]))

    def command_limit_um(self, f_hz: float) -> float:
        """Largest command amplitude: the displacement limit, and the slew limit at f."""
        return min(self.stage.limit_um, self.stage.cfg.slew_um_s / (2 * math.pi * f_hz))

    def reach_um(self, f_hz: float) -> float:
        return SAFETY_MARGIN * self.gain(f_hz) * self.command_limit_um(f_hz)

    def check(self, s: Sinusoid) -> None:
        """Refuse a stimulus beyond the reach (or not a finite positive one): nothing is played."""
        if not (math.isfinite(s.frequency_hz) and s.frequency_hz > 0 and math.isfinite(s.amplitude_um)
                and s.amplitude_um >= 0 and math.isfinite(s.duration_s) and 0 < s.duration_s <= 10):
            raise ExperimentError(f"stimulus {s} refused: frequency > 0, amplitude >= 0 and a duration "
                                  "of at most 10 s expected")
        r = self.reach_um(s.frequency_hz)
        if s.amplitude_um > r:
            raise ExperimentError(f"stimulus of {s.amplitude_um:.4g} µm at {s.frequency_hz:g} Hz refused: "
                                  f"the display reaches {r:.4g} µm there (output.travel_um, "
                                  "output.slew_um_s, render.actuator, with a 10 % margin)")


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


class DaemonDisplay:
    """The running daemon's display, through its control socket: a texture is sent (once),
    selected for `seconds` while the participant strokes it, then stopped. Sinusoids are not
    streams the daemon plays (it renders textures at the hand's position): the threshold
    experiment uses the simulated display or a display driven by the lab's own stimulus
    player, and says so."""

    def __init__(self, socket_path: str) -> None:
        self.socket_path = socket_path
        self.sent: dict[str, str] = {}

    def play(self, s: Sinusoid) -> None:
        raise ExperimentError("the daemon plays texture streams, not sinusoids: run the threshold "
                              "experiment with --display sim")

    def play_silence(self, duration_s: float) -> None:
        time.sleep(duration_s)

    def _request(self, req: dict, payload: bytes = b"") -> dict:
        from hostd.service.client import ClientError, request

        try:
            rep = request(self.socket_path, req, payload)
        except (ClientError, OSError) as e:
            raise DeviceGone(f"the daemon is not answering: {e}") from None
        if not rep.get("ok", False):
            raise DeviceGone(f"the daemon refused: {rep.get('error')}")
        return rep

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
