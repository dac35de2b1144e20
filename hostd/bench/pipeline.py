"""Real-time cost of the render pipeline at its default settings.

Runs the closed-loop simulation (hostd.sim.chain) for `duration_s` of 3 kHz output in
1 ms batches and reports the renderer's time per batch (thread CPU time and wall time):
p50, p99, p99.9 and max, and the share of one core it needs.

host_cycle_ms > 1 models the pump's longer host cycle ([device] host_cycle_ms): one batch of
host_cycle_ms x 3 samples per wake-up, the oldest of them played as soon after the wake-up
as with a 1 ms cycle (the same margin; the newest host_cycle_ms - 1 ms later), and reports the
accuracy it costs (RMS error against the ideal display, as `hostd bench accuracy` scores it).
"""

from __future__ import annotations

import gc
from dataclasses import replace

import numpy as np

from hostd.bench.accuracy import _score, link_for, texture_coeffs
from hostd.render.pipeline import RenderConfig, Renderer
from hostd.sim import chain
from hostd.sim.hand import Metronome
from hostd.texture import synth


def run(duration_s: float = 60.0, texture: str = "wood", cfg: RenderConfig | None = None,
        host_cycle_ms: int = 1) -> dict:
    cfg = cfg or RenderConfig()
    link = link_for(cfg)  # 1 ms batches: 1 ms transport + 3 ms of buffer before the oldest sample
    if host_cycle_ms != 1:
        cfg = replace(cfg, samples_per_batch=cfg.samples_per_batch * int(host_cycle_ms))
    coeffs, n, length = texture_coeffs(synth.make(texture, seed=1))
    r = Renderer(coeffs, n, length, cfg)
    hand = Metronome()
    gc.collect()
    gc.freeze()  # as the daemon's pump does: no collection pauses from old objects
    try:
        res = chain.run_loop(r, hand, duration_s, link)
    finally:
        gc.unfreeze()
    delivered = chain.actuate(res.command_um, r.eq.model, cfg.sample_rate_hz)
    acc = _score(coeffs, n, length, hand, r, res.t_play_s, delivered, {})
    cpu_us = res.batch_cpu_ns / 1e3
    wall_us = res.batch_wall_ns / 1e3
    batch_ms = cfg.samples_per_batch / cfg.sample_rate_hz * 1e3
    row = {"bench": "pipeline", "texture": texture, "height_method": cfg.height_method,
           "samples_per_batch": cfg.samples_per_batch, "batch_ms": batch_ms,
           "duration_s": duration_s, "batches": int(cpu_us.size),
           "host_cycle_ms": int(host_cycle_ms), "rms_error_pct": acc["rms_error_pct"],
           "core_pct": res.cpu_ms_per_s / 10.0, "cpu_ms_per_s": res.cpu_ms_per_s}
    for name, v in (("cpu", cpu_us), ("wall", wall_us)):
        p50, p99, p999 = np.percentile(v, [50, 99, 99.9])
        row.update({f"{name}_p50_us": float(p50), f"{name}_p99_us": float(p99),
                    f"{name}_p999_us": float(p999), f"{name}_max_us": float(v.max())})
    return row
