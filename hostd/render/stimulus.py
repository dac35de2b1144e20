"""A stimulus played on the display regardless of the hand: a temporal sinusoid, its safety
bound (the display's reach), and the renderer the pump streams it with.

One implementation for the daemon (which checks every stimulus a client asks for, and whose
pump streams it: `hostd experiment threshold --display daemon`) and for hostd.experiment (its
Reach and SimDisplay), so the host and the daemon refuse the same stimuli.

The bound: a sinusoid of A µm peak at the finger at f Hz needs a command of A / |H(f)| (H: the
actuator model, config render.actuator) that must stay inside the output stage's limits
(output.travel_um: |x| <= the code limit; output.slew_um_s: 2π f A_cmd <= slew). The reach is
that bound times SAFETY_MARGIN. `StimulusBound.check` refuses anything above it, anything not
finite, a frequency outside (0, MAX_FREQUENCY_HZ], a negative amplitude and a duration outside
(0, MAX_DURATION_S]; then the whole command is run through a fresh output stage and refused if
the stage would have to limit a single sample. What is played goes, sample by sample, through
the output stage again (hostd.render.output: limit, slew) and then through the firmware's own
limits (SET_LIMITS), like every host-rendered sample.

numpy and hostd.render.output only: the daemon checks stimuli without scipy (|H(f)| of the
parametric model is its rational function evaluated with numpy, as scipy.signal.freqs does).
"""

from __future__ import annotations

import math

import numpy as np

from hostd.errors import StimulusRefused
from hostd.render.output import OutputStage

SAFETY_MARGIN = 0.9  # stimuli stay 10 % (0.9 dB) inside the output stage's limits
SAMPLE_RATE_HZ = 3000.0
RAMP_S = 0.05  # raised-cosine onset and offset: no click at the ends of a stimulus
MAX_DURATION_S = 10.0
MAX_FREQUENCY_HZ = 1000.0
LEAD_SAMPLES = 3  # silence streamed before the stimulus (the device starts from zero)


def sinusoid_um(frequency_hz: float, amplitude_um: float, duration_s: float, gain: float = 1.0,
                rate_hz: float = SAMPLE_RATE_HZ) -> np.ndarray:
    """amplitude_um / gain · envelope · sin(2π f t) at rate_hz, the envelope's raised-cosine
    ramps RAMP_S long (at most half the stimulus)."""
    n = round(duration_s * rate_hz)
    t = np.arange(n) / rate_hz
    env = np.ones(n)
    r = min(int(RAMP_S * rate_hz), n // 2)
    if r:
        ramp = 0.5 - 0.5 * np.cos(np.pi * np.arange(r) / r)
        env[:r], env[n - r:] = ramp, ramp[::-1]
    return (amplitude_um / gain) * env * np.sin(2 * np.pi * frequency_hz * t)


def actuator_gain(actuator, f_hz: float) -> float:
    """|H(f)|, displacement at the finger per command (the measured table where there is one)."""
    f = float(f_hz)
    if actuator.table_hz is not None:
        return float(abs(actuator.measured(np.array([f]))[0]))
    b, a = actuator.analog_ba()  # the delay has unit magnitude
    s = 2j * np.pi * f
    return float(abs(np.polyval(b, s) / np.polyval(a, s)))


def _number(v) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


class StimulusBound:
    """The largest sinusoid (µm peak at the finger) the display can play at f, from a
    RenderConfig's output stage and actuator model; `check` refuses anything beyond it."""

    def __init__(self, render_config) -> None:
        self.render_config = render_config
        self.stage = OutputStage(render_config.output)
        self.actuator = render_config.actuator

    def gain(self, f_hz: float) -> float:
        return actuator_gain(self.actuator, f_hz)

    def command_limit_um(self, f_hz: float) -> float:
        """Largest command amplitude: the displacement limit, and the slew limit at f."""
        return min(self.stage.limit_um, self.stage.cfg.slew_um_s / (2 * math.pi * f_hz))

    def reach_um(self, f_hz: float) -> float:
        return SAFETY_MARGIN * self.gain(f_hz) * self.command_limit_um(f_hz)

    def check(self, frequency_hz, amplitude_um, duration_s) -> None:
        """Refuse (StimulusRefused, one line) before anything is played."""
        if not (_number(frequency_hz) and 0 < frequency_hz <= MAX_FREQUENCY_HZ and _number(amplitude_um)
                and amplitude_um >= 0 and _number(duration_s) and 0 < duration_s <= MAX_DURATION_S):
            raise StimulusRefused(
                f"stimulus ({frequency_hz!r:.20} Hz, {amplitude_um!r:.20} µm, {duration_s!r:.20} s) refused: "
                f"a frequency in (0, {MAX_FREQUENCY_HZ:g}] Hz, an amplitude >= 0 µm and a duration in "
                f"(0, {MAX_DURATION_S:g}] s, finite numbers, expected")
        r = self.reach_um(frequency_hz)
        if amplitude_um > r:
            raise StimulusRefused(
                f"stimulus of {amplitude_um:.4g} µm at {frequency_hz:g} Hz refused: the display reaches "
                f"{r:.4g} µm there (output.travel_um, output.slew_um_s, render.actuator, with a 10 % "
                "margin)")
        cmd = self.command_um(frequency_hz, amplitude_um, duration_s)
        stage = OutputStage(self.stage.cfg)
        stage.start()
        stage.envelope = 1.0  # the stimulus has its own ramps
        out = stage.process(cmd)
        if stage.clipped or not np.array_equal(out, cmd):
            raise StimulusRefused(f"stimulus of {amplitude_um:.4g} µm at {frequency_hz:g} Hz refused: the "
                                  "output stage would have to limit it")

    def command_um(self, frequency_hz: float, amplitude_um: float, duration_s: float) -> np.ndarray:
        """The command (µm at the actuator's input) that plays the sinusoid at the finger."""
        return sinusoid_um(frequency_hz, amplitude_um, duration_s, self.gain(frequency_hz),
                           self.stage.cfg.sample_rate_hz)


class _Still:
    """The motion a stimulus renderer reports: none (the hand's position is not used)."""

    relocks = 0
    implausible = 0
    velocity_mm_s = 0.0


class _StimulusStage(OutputStage):
    """The output stage (process(): the same limits as every host-rendered sample) whose first
    start is at full envelope: the stimulus begins at zero with its own raised-cosine ramp, and
    a soft start on top would change its onset. A later restart (the device ran dry or stopped:
    the stimulus is reported as not played) aborts it: silence from then on."""

    started = False
    aborted = False

    def restart_from(self, um: float = 0.0) -> None:
        super().restart_from(um)
        if not self.started and um == 0.0:
            self.envelope = 1.0
        elif self.started:
            self.aborted = True
        self.started = True


class StimulusRenderer:
    """What the pump streams for a stimulus, in place of a texture's renderer: LEAD_SAMPLES of
    silence, the command samples, then silence for as long as the pump asks (until the device
    has played the stimulus), each batch through the output stage and to DAC codes. The
    encoder's reports are ignored. Checked again here (the pump's own refusal)."""

    def __init__(self, render_config, frequency_hz: float, amplitude_um: float, duration_s: float) -> None:
        bound = StimulusBound(render_config)
        bound.check(frequency_hz, amplitude_um, duration_s)
        self.cfg = render_config
        self.out = _StimulusStage(render_config.output)
        self.motion = _Still()
        cmd = bound.command_um(frequency_hz, amplitude_um, duration_s)
        self.samples = np.concatenate([np.zeros(LEAD_SAMPLES), cmd])
        self.pos = 0
        self.limited = 0  # samples the output stage changed (none, after the check)
        self._last_before = 0.0  # the stage's last output before the latest batch
        self._last_y = np.zeros(0)
        # the pump keeps the device's buffer this full (clamped to all it can hold): nothing
        # follows the hand, so latency is no matter, and a host stall up to the device's host
        # timeout is covered
        self.fill_samples = 1 << 16

    @property
    def length(self) -> int:
        """Samples of silence and stimulus, before the trailing silence."""
        return int(self.samples.size)

    def on_encoder(self, t_s: float, raw_count: int) -> None:
        pass

    def start(self) -> None:
        self.out.start()

    def restart(self, _t_play_s: float) -> None:
        """The device ran dry or stopped (Renderer.restart): _StimulusStage.restart_from."""
        self.out.restart_from(0.0)

    def render_codes(self, t_play_s: np.ndarray) -> np.ndarray:
        """The next len(t_play_s) samples (the play times do not matter: nothing follows the hand)."""
        n = len(t_play_s)
        x = np.zeros(n)
        if not self.out.aborted:
            part = self.samples[self.pos : self.pos + n]
            x[: part.size] = part
        self._last_before = self.out.last_um
        self.pos += n
        y = self.out.process(x)
        self._last_y = y
        self.limited += int(np.count_nonzero(y != x))
        return self.out.to_codes(y)

    def unsent(self, k: int) -> None:
        """The last k samples rendered did not go out (the link was busy): they come again next,
        from the output stage's state after the last sample that did."""
        n = self._last_y.size
        k = min(max(int(k), 0), n)
        self.pos -= k
        self.out.last_um = float(self._last_y[n - k - 1]) if k < n else self._last_before
