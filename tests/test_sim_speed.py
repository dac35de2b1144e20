"""The fast paths of the scene simulator compute what the slow ones do: heights planned batch by
batch and evaluated per speed bucket equal the batch-by-batch render (the daemon's path); a
report's shared renders and fits equal fresh runs; the pruned band-limited series and the
NUFFT sums equal direct sums."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hostd.render import pipeline, series
from hostd.render.height import BandLimitConfig, band_edges_hz, band_gains
from hostd.sim import scene

ALL_EFFECTS = """
[effects.encoder]
resolution_um = 0.4
noise_counts = 1.0
missed_count_prob = 0.001
[effects.transport]
latency_ms = 1.0
jitter_ms = 1.5
loss = 0.01
buffer_ms = 4.0
[effects.clock_drift]
ppm = -500.0
[effects.cpu_load]
stall_prob = 0.01
stall_ms = 8.0
[effects.dac]
[effects.actuator]
model = "paper-parametric"
[effects.finger_load]
stiffness_ratio = 0.3
corner_hz = 500.0
"""


def _scene(tmp_path: Path, effects: str, duration: float) -> scene.Scene:
    # a hand at 30 mm/s that is lifted and set down 3 mm further at 0.4 s: the motion
    # estimate re-locks, and the renderer crossfades
    t = np.arange(0.0, duration + 0.05, 0.001)
    x = 30.0 * t + np.where(t >= 0.4, 3.0, 0.0)
    np.savetxt(tmp_path / "hand.csv", np.column_stack([t, x]), delimiter=",")
    p = tmp_path / "s.toml"
    p.write_text(f'name = "t"\nduration_s = {duration}\nseed = 7\n'
                 f'[texture]\nprofile = "synthetic:sandpaper:1"\n'
                 f'[hand]\nmodel = "recorded"\nfile = "hand.csv"\n{effects}')
    return scene.load(p)


def test_vectorized_render_equals_batch_by_batch_with_every_effect(tmp_path, monkeypatch):
    sc = _scene(tmp_path, ALL_EFFECTS, 1.0)
    plans = []
    real_plan = pipeline.Renderer.plan

    def spy(self, t):
        p = real_plan(self, t)
        plans.append(p)
        return p

    monkeypatch.setattr(pipeline.Renderer, "plan", spy)
    fast = scene.run(sc, vectorized=True)
    assert any(p.x_old_mm is not None for p in plans), "the scene must exercise a re-lock crossfade"
    slow = scene.run(sc, vectorized=False)
    assert fast["underruns"] == slow["underruns"] > 0  # cpu_load stalls of 8 ms > the 4 ms buffer
    # the DAC rounds: a height differing in the last bits may land on the next code (1 LSB)
    lsb = pipeline.OutputConfig().um_per_code
    d = np.abs(fast["_trace"]["delivered"] - slow["_trace"]["delivered"])
    assert d.max() <= 1.01 * lsb
    assert abs(fast["Iobj"] - slow["Iobj"]) <= 1e-6 and abs(fast["Ip"] - slow["Ip"]) <= 1e-6
    # without the DAC the two paths agree to float rounding
    closed = ["encoder", "transport", "clock_drift", "cpu_load", "actuator", "finger_load"]
    a, b = scene.run(sc, closed, vectorized=True), scene.run(sc, closed, vectorized=False)
    assert np.allclose(a["_trace"]["delivered"], b["_trace"]["delivered"], rtol=0, atol=1e-9)
    # (the least-squares fit of 1 s of texture amplifies that rounding by its conditioning)
    assert np.abs(a["_trace"]["fit"] - b["_trace"]["fit"]).max() <= 1e-6 * np.abs(b["_trace"]["fit"]).max()
    assert abs(a["Iobj"] - b["Iobj"]) <= 1e-9
    assert a["underruns"] == b["underruns"]


def test_a_report_reuses_renders_and_fits_that_equal_fresh_runs(tmp_path):
    effects = "[effects.encoder]\n[effects.dac]\n[effects.actuator]\n[effects.finger_load]\n"
    sc = _scene(tmp_path, effects, 0.5)
    rep = scene.report(sc, progress=False)
    assert [r["effects"] for r in rep["runs"]] == [[], ["encoder"], ["dac"], ["actuator"], ["finger_load"],
                                                   ["encoder", "dac", "actuator", "finger_load"]]
    for r in rep["runs"]:
        fresh = scene.run(sc, r["effects"])  # its own render and its own fit
        assert np.array_equal(r["_trace"]["delivered"], fresh["_trace"]["delivered"])
        assert np.allclose(r["_trace"]["fit"], fresh["_trace"]["fit"], rtol=0, atol=1e-12)
        assert r["Iobj"] == fresh["Iobj"] or abs(r["Iobj"] - fresh["Iobj"]) <= 1e-12


def test_pruned_band_limited_series_and_nufft_sums_equal_direct_sums():
    rng = np.random.default_rng(11)
    K, length, n = 300, 5.0, 2000
    c = rng.normal(0, 1, K)
    th = series.phase_rad(rng.uniform(-50, 50, 2500), n, length)
    speed = np.concatenate([[0.0, 1e-3], rng.uniform(-120, 120, th.size - 2)])
    cfg = BandLimitConfig()
    k = np.arange(1, K + 1, dtype=np.float64)
    direct = np.einsum("ij,ij->i", np.cos(np.multiply.outer(th, k)), band_gains(k, speed, length, cfg) * c)
    f_pass, f_stop = band_edges_hz(cfg)
    got = series.evaluate_faded(c, th, np.abs(speed) / (2 * length), f_pass, f_stop,
                                lambda kk, s: band_gains(float(kk), s * 2 * length, length, cfg))
    assert np.allclose(got, direct, rtol=0, atol=1e-10)
    # evaluate: the cosine matrix for few terms, the NUFFT for many; both equal the direct sum
    for m in (3, 2500):
        want = np.cos(np.multiply.outer(th[:m], k)) @ c
        assert np.allclose(series.evaluate(c, th[:m]), want, rtol=0, atol=1e-10)
    # one projector, many fits: each equals its own least squares
    pj = series.Projector(th, 40)
    basis = np.cos(np.multiply.outer(th, np.arange(41)))
    for _ in range(2):
        y = rng.normal(0, 1, th.size)
        assert np.allclose(pj.fit(y), np.linalg.lstsq(basis, y, rcond=None)[0], rtol=0, atol=1e-9)


def test_projector_on_phases_that_do_not_cover_the_period_gives_the_least_squares_fit():
    rng = np.random.default_rng(2)
    th = np.repeat(rng.uniform(0, 2 * np.pi, 6), 50)  # 6 distinct phases, 31 unknowns: G singular
    pj = series.Projector(th, 30)
    basis = np.cos(np.multiply.outer(th, np.arange(31)))
    for _ in range(2):
        y = rng.normal(0, 1, th.size)
        want = np.linalg.lstsq(basis, y, rcond=None)[0]  # the minimum-norm least-squares solution
        got = pj.fit(y)
        assert np.allclose(basis @ got, basis @ want, rtol=0, atol=1e-9)
        assert np.allclose(got, want, rtol=0, atol=1e-9)
