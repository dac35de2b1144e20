"""The render pipeline: encoder counts -> position -> predicted x at play time -> band-limited
height -> equalizer -> output limits -> DAC codes, in batches (frames) for the device link."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from hostd.cyclestate import record
from hostd.render import fastrender, series
from hostd.render.equalizer import ActuatorModel, Equalizer, EqualizerConfig
from hostd.render.height import BandLimitConfig, HeightEvaluator
from hostd.render.motion import MotionConfig, MotionEstimator
from hostd.render.output import OutputConfig, OutputStage
from hostd.render.position import EncoderPosition


@dataclass
class RenderConfig:
    sample_rate_hz: float = 3000.0
    samples_per_batch: int = 3  # 3 samples per 1 ms report at 3 kHz
    um_per_count: float = 0.4
    height_method: str = "series"
    table_oversample: int = 16  # table methods: table points per period of the top component
    dtype: str = "float64"
    # Extra look-ahead beyond the play instants: the delay between a sample's play instant and
    # the actuator's displacement (DAC hold + actuator x equalizer + actuator dead time).
    # None = measure it from the models (chain group delay at 100 Hz).
    latency_s: float | None = None
    predict: bool = True
    motion: MotionConfig = field(default_factory=MotionConfig)  # see the accuracy bench
    band: BandLimitConfig = field(default_factory=BandLimitConfig)
    equalizer: EqualizerConfig = field(default_factory=EqualizerConfig)
    actuator: ActuatorModel = field(default_factory=ActuatorModel)
    output: OutputConfig = field(default_factory=OutputConfig)
    relock_fade_s: float = 0.01  # crossfade across a re-lock of the motion estimate


@dataclass
class BatchPlan:
    """One batch's motion, decided when it is rendered (Renderer.plan)."""
    x_mm: np.ndarray  # predicted positions at the play instants (+ latency)
    speed_mm_s: float  # the estimate's speed: selects the band limit
    x_old_mm: np.ndarray | None = None  # the estimate before a re-lock, while crossfading
    fade_in: np.ndarray | None = None  # weight of the new estimate per sample (crossfade)


class Renderer(record("renderer")):
    """Stateful: feed encoder readings, ask for batches of samples at their play times. Its
    scalar state is the "renderer" record of hostd/device/cycle_state.toml."""

    def __init__(self, coeffs_um: np.ndarray, n: int, length_mm: float,
                 cfg: RenderConfig | None = None) -> None:
        self.cfg = cfg = cfg or RenderConfig()
        if cfg.samples_per_batch < 1:
            raise ValueError("samples_per_batch must be >= 1")
        self._samples_per_batch = cfg.samples_per_batch
        # The pipeline's rate is the one source of truth; stage configs get copies with it,
        # and the caller's objects are left untouched.
        fs = cfg.sample_rate_hz
        eq_cfg = replace(cfg.equalizer, sample_rate_hz=fs)
        out_cfg = replace(cfg.output, sample_rate_hz=fs)
        band_cfg = replace(cfg.band, sample_rate_hz=fs)
        self.position = EncoderPosition(cfg.um_per_count)
        self.motion = MotionEstimator(cfg.motion if cfg.predict else MotionConfig(order=0, window=2))
        if cfg.dtype not in ("float32", "float64"):
            raise ValueError("dtype must be float32 or float64")
        self.height = HeightEvaluator(coeffs_um, n, length_mm, cfg.height_method, band_cfg,
                                      dtype=np.float32 if cfg.dtype == "float32" else np.float64,
                                      table_oversample=cfg.table_oversample)
        self.eq = Equalizer(cfg.actuator, eq_cfg)
        self.out = OutputStage(out_cfg)
        self.period_s = 1.0 / cfg.sample_rate_hz
        self.latency_s = (self.eq.chain_delay_ms() * 1e-3 if cfg.latency_s is None
                          else float(cfg.latency_s))
        if not (np.isfinite(self.latency_s) and abs(self.latency_s) < 0.05):
            raise ValueError("latency_s must be finite and within ±50 ms")
        self._xfade_n = max(1, round(cfg.relock_fade_s * fs))
        self._xfade_left = 0

    def on_encoder(self, t_s: float, raw_count: int) -> None:
        m = self.motion
        before = m.relocks + m.implausible
        m.update(t_s, self.position.update(raw_count))
        if m.relocks + m.implausible != before:
            # the position estimate restarted (a real jump, or after a gap): fade from the
            # old estimate's texture to the new one instead of jumping
            self._xfade_left = self._xfade_n

    def start(self) -> None:
        self.out.start()

    def stop(self) -> None:
        self.out.stop()

    def restart(self, t_play_s: float) -> None:
        """Soft start again from zero with the sample played at t_play_s (the device ramped to
        zero: a stall, an underrun). The envelope starts from zero (OutputStage.restart_from),
        and the equalizer's state is the texture's just before t_play_s, as if it had played on:
        its state from before the pause belonged to the texture where the hand was then, and the
        jump from it rang near the Nyquist rate through the envelope's first samples (up to
        7.4x the envelope times the texture's peak on the firmware's DAC log, tests/test_playback).
        No crossfade from an estimate before a re-lock: the envelope is the fade."""
        self.out.restart_from(0.0)
        self._xfade_left = 0
        n = self.eq.settle_samples
        if n:
            t = float(t_play_s) - np.arange(n, 0, -1) / self.cfg.sample_rate_hz
            # in real-time batches: the pump's own arithmetic (Clenshaw), never the bulk
            # evaluation's NUFFT (finufft: an import of 16 ms and its memory, in the pump)
            b = series.SMALL_BATCH
            self.eq.warm(np.concatenate([self.heights_um(self.plan(t[i : i + b])) for i in range(0, n, b)]))

    def plan(self, t_play_s: np.ndarray) -> BatchPlan:
        """The motion part of rendering one batch: where the hand will be at the play instants
        (+ the chain's latency), at what speed, and the crossfade from the estimate before a
        re-lock (advances the crossfade). render_um = plan, then heights, then the filters."""
        t = np.asarray(t_play_s, dtype=np.float64) + self.latency_s
        x = self.motion.predict(t)
        # the band limit is the speed the hand will have when the batch plays (its middle), not
        # the speed at the newest reading ~6 ms before: at the paper's strokes that lag alone
        # was 0.08 % of the 1.31 % RMS error on sandpaper (hostd bench accuracy)
        v = (self.motion.velocity_at(0.5 * (float(t[0]) + float(t[-1]))) if t.ndim == 1 and t.size
             else self.motion.velocity_mm_s)
        if self._xfade_left <= 0:
            return BatchPlan(x, v)
        # linear crossfade, old estimate -> new, over relock_fade_s
        k = np.arange(self._xfade_n - self._xfade_left, self._xfade_n - self._xfade_left + t.size)
        w = np.minimum(1.0, (k + 1) / self._xfade_n)
        self._xfade_left = max(0, self._xfade_left - t.size)
        return BatchPlan(x, v, self.motion.predict_previous(t), w)

    def heights_um(self, plan: BatchPlan) -> np.ndarray:
        """Band-limited heights (before the equalizer) of one planned batch."""
        h = self.height(plan.x_mm, plan.speed_mm_s)
        if plan.x_old_mm is not None:
            h = plan.fade_in * h + (1.0 - plan.fade_in) * self.height(plan.x_old_mm, plan.speed_mm_s)
        return h

    def heights_many_um(self, plans: list[BatchPlan], chunk: int = 2048) -> np.ndarray:
        """heights_um of many planned batches, concatenated: the same height evaluator, called
        once per speed bucket (the evaluator's weights or table depend only on the bucket)
        with every position planned at a speed in that bucket, instead of once per batch.
        Equal to the batch-by-batch heights to float rounding. For offline use, where the
        hand's readings are known ahead (the scene simulator): on the real-time path each
        batch is planned only when its readings have arrived."""
        sizes = np.array([p.x_mm.size for p in plans], dtype=np.int64)
        fading = [i for i, p in enumerate(plans) if p.x_old_mm is not None]
        x = np.concatenate([p.x_mm for p in plans] + [plans[i].x_old_mm for i in fading])
        speed = np.array([p.speed_mm_s for p in plans])
        bucket = np.array([self.height._bucket(v) for v in speed], dtype=np.int64)
        pt_batch = np.concatenate([np.repeat(np.arange(len(plans)), sizes),
                                   np.repeat(np.array(fading, dtype=np.int64), sizes[fading])])
        pt_bucket = bucket[pt_batch]
        order = np.argsort(pt_bucket, kind="stable")
        edges = np.flatnonzero(np.diff(pt_bucket[order])) + 1
        h = np.empty(x.size, dtype=np.float64)
        for grp in np.split(order, edges):
            if grp.size == 0:
                continue
            v = float(speed[pt_batch[grp[0]]])
            for i in range(0, grp.size, chunk):
                g = grp[i : i + chunk]
                h[g] = self.height(x[g], v)
        n = int(sizes.sum())
        out = h[:n]
        if fading:
            starts = np.concatenate([[0], np.cumsum(sizes)])
            o = n
            for i in fading:
                a, b, w = starts[i], starts[i + 1], plans[i].fade_in
                out[a:b] = w * out[a:b] + (1.0 - w) * h[o : o + (b - a)]
                o += b - a
        return out

    def finish_um(self, h_um: np.ndarray) -> np.ndarray:
        """Equalizer and output limits (stateful): heights -> limited displacement (µm)."""
        return self.out.process(self.eq(h_um))

    def render_um(self, t_play_s: np.ndarray) -> np.ndarray:
        """Limited displacement (µm) for samples that will be played at t_play_s."""
        return self.finish_um(self.heights_um(self.plan(t_play_s)))

    def render_codes(self, t_play_s: np.ndarray) -> np.ndarray:
        """DAC codes for samples played at t_play_s: out.to_codes(render_um(t_play_s)), with
        the equalizer/output/codes tail compiled for small batches when it is built."""
        return fastrender.tail(self.eq, self.out, self.heights_um(self.plan(t_play_s)))


def frames(codes: np.ndarray, samples_per_batch: int) -> list[np.ndarray]:
    """Split a run of codes into the batches the device link sends (last one may be short)."""
    c = np.asarray(codes)
    return [c[i : i + samples_per_batch] for i in range(0, c.size, samples_per_batch)]
