"""Closed-loop simulation of the render pipeline against a simulated hand and device.

Time is the device's clock. The device reports its encoder count every `status_period_s`;
a report reaches the host `transport_s` later. Every batch period the host feeds the
reports it has received to the renderer and renders one batch, whose first sample the
device plays `transport_s + buffer_s` after the host rendered it. The DAC holds each sample
for one period (zero-order hold) and the actuator (a continuous model, discretized exactly
for that hold) turns commands into displacement.

The reference is the ideal display: the exact band-limited series at the hand's true
position and true speed, at the instant the displacement is delivered.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.signal

from hostd.render import series
from hostd.render.equalizer import ActuatorModel
from hostd.render.height import band_edges_hz, band_gains
from hostd.render.pipeline import Renderer
from hostd.sim.hand import Hand


@dataclass
class LinkConfig:
    status_period_s: float = 0.001
    transport_s: float = 0.001
    buffer_s: float = 0.003  # the device's target buffer fill, as time


@dataclass
class LoopResult:
    t_play_s: np.ndarray  # play instant of each sample (device clock)
    command_um: np.ndarray  # what the DAC output, in µm (codes x µm per code)
    batch_cpu_ns: np.ndarray  # CPU time of the renderer per batch (encoder feed + render)
    batch_wall_ns: np.ndarray

    @property
    def cpu_ms_per_s(self) -> float:
        duration_s = self.t_play_s.size * (self.t_play_s[1] - self.t_play_s[0])
        return float(self.batch_cpu_ns.sum()) * 1e-6 / duration_s


def quantize_counts(x_mm: np.ndarray, um_per_count: float) -> np.ndarray:
    """The encoder count nearest to each position (unbounded, int64)."""
    return np.floor(np.asarray(x_mm) * 1000.0 / um_per_count + 0.5).astype(np.int64)


def encoder_counts(hand: Hand, t_s: np.ndarray, um_per_count: float) -> np.ndarray:
    """Ideal quadrature encoder: the count of the true position, wrapped to 32 bits."""
    return quantize_counts(hand.position_mm(t_s), um_per_count) % (1 << 32)


def run_loop(renderer: Renderer, hand: Hand, duration_s: float, link: LinkConfig | None = None,
             timer=time.thread_time_ns) -> LoopResult:
    link = link or LinkConfig()
    fs = renderer.cfg.sample_rate_hz
    b = renderer.cfg.samples_per_batch
    n_batches = round(duration_s * fs / b)
    n = n_batches * b
    lead_s = link.transport_s + link.buffer_s
    t_play = np.arange(n) / fs + lead_s
    t_status = np.arange(0.0, duration_s + link.status_period_s, link.status_period_s)
    counts = encoder_counts(hand, t_status, renderer.cfg.um_per_count).tolist()
    arrive = (t_status + link.transport_s).tolist()
    t_status_l = t_status.tolist()
    codes = np.empty(n, dtype=np.int64)
    cpu = np.empty(n_batches, dtype=np.int64)
    wall = np.empty(n_batches, dtype=np.int64)
    m = 0
    renderer.start()
    perf = time.perf_counter_ns
    eps = 1e-12
    for j in range(n_batches):
        t_host = j * b / fs
        tp = t_play[j * b : (j + 1) * b]
        c0, w0 = timer(), perf()
        while m < len(arrive) and arrive[m] <= t_host + eps:
            renderer.on_encoder(t_status_l[m], counts[m])
            m += 1
        out = renderer.render_codes(tp)
        c1, w1 = timer(), perf()
        codes[j * b : (j + 1) * b] = out
        cpu[j] = c1 - c0
        wall[j] = w1 - w0
    command = codes * renderer.out.cfg.um_per_code
    return LoopResult(t_play, command, cpu, wall)


def actuate(command_um: np.ndarray, model: ActuatorModel, fs: float) -> np.ndarray:
    """Displacement at each sample's play instant + the model's dead time, for commands
    held by the DAC (the continuous model discretized exactly for a zero-order hold)."""
    b, a = model.analog_ba()
    bd, ad, _dt = scipy.signal.cont2discrete((b, a), 1.0 / fs, method="zoh")
    return scipy.signal.lfilter(np.ravel(bd), ad, command_um)


def ideal(coeffs_um: np.ndarray, n: int, length_mm: float, x_mm: np.ndarray, v_mm_s: np.ndarray,
          band) -> np.ndarray:
    """The ideal display at positions x_mm and speeds v_mm_s: the exact series with the band
    gains of each sample's own speed (hostd.render.height.band_gains, no speed buckets)."""
    f_pass, f_stop = band_edges_hz(band)
    two_l = 2.0 * length_mm
    theta = series.phase_rad(x_mm, n, length_mm)
    scale = np.abs(v_mm_s) / two_l  # component k sounds at k * scale Hz
    return series.evaluate_faded(coeffs_um, theta, scale, f_pass, f_stop,
                                 lambda k, s: band_gains(float(k), s * two_l, length_mm, band))


def reference(coeffs_um: np.ndarray, n: int, length_mm: float, hand: Hand, t_s: np.ndarray,
              renderer: Renderer) -> np.ndarray:
    """The ideal display for the hand at instants t_s, with the renderer's band."""
    return ideal(coeffs_um, n, length_mm, hand.position_mm(t_s), hand.velocity_mm_s(t_s),
                 renderer.height.band)
