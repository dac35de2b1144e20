"""hostd's own SPQI (hostd.perception.spqi) equals vibromaf's spqi() to 1e-12, and keeps working
where vibromaf's float64 arithmetic over- or underflows."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from hostd.errors import QualityError
from hostd.perception import peer
from hostd.perception.spqi import Reference, spqi


def _signals(rng):
    """Reference/distorted pairs of many kinds: noise at every SNR, quantized, scaled, longer
    distorted signals, random walks, sparse spikes, silence, played texture signals."""
    for i in range(160):
        n = int(rng.integers(512, 9000))
        ref = rng.normal(0, 1, n) * 10.0 ** rng.uniform(-4, 4)
        kind = i % 8
        if kind == 0:
            dist = ref + rng.normal(0, 10 ** rng.uniform(-6, 0.5), n) * np.std(ref)
        elif kind == 1:
            step = np.std(ref) * 10 ** rng.uniform(-3, 0.3)
            dist = np.round(ref / step) * step
        elif kind == 2:
            dist = np.concatenate([ref, rng.normal(size=int(rng.integers(1, 700)))]) * rng.uniform(0.5, 1.5)
        elif kind == 3:
            ref, dist = np.cumsum(rng.normal(size=n)), np.cumsum(rng.normal(size=n))
        elif kind == 4:
            dist = ref.copy()
            dist[int(rng.integers(0, n))] += 1e-3 * np.std(ref)
        elif kind == 5:
            ref = np.zeros(n)
            ref[rng.integers(0, n, 3)] = rng.normal(size=3)
            dist = ref * 0.5
        elif kind == 6:
            ref = np.sin(2 * np.pi * rng.uniform(5, 1000) * np.arange(n) / 8000.0)
            dist = ref + 0.01 * np.sin(2 * np.pi * rng.uniform(5, 3000) * np.arange(n) / 8000.0)
        else:
            c = rng.normal(0, 1, 160) / np.arange(1, 161) ** rng.uniform(0.5, 2)
            ref = peer.played_signal(c, 20000, 10.0, 50.0)
            dist = peer.played_signal(np.round(c * 4) / 4, 20000, 10.0, 50.0)
        yield ref, dist


def test_spqi_equals_vibromaf_to_1e12_on_many_signals():
    vm = pytest.importorskip("vibromaf.metrics.spqi")
    rng = np.random.default_rng(23)
    worst, count = 0.0, 0
    for ref, dist in _signals(rng):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            want = float(vm.spqi(dist, ref))
        got = spqi(dist, ref)
        worst = max(worst, abs(got - want))
        count += 1
    assert count == 160
    assert worst <= 1e-12


def test_cached_reference_scores_like_the_one_shot_function():
    rng = np.random.default_rng(1)
    ref = rng.normal(size=8000)
    r = Reference(ref)
    for snr in (0.01, 0.1, 1.0):
        d = ref + snr * rng.normal(size=8000)
        assert r.score(d) == spqi(d, ref)
    assert r.score(ref.copy()) == 1.0


def test_spqi_is_scale_invariant_over_the_float64_range():
    rng = np.random.default_rng(2)
    ref = rng.normal(size=4096)
    dist = ref + 0.05 * rng.normal(size=4096)
    base = spqi(dist, ref)
    assert 0.0 < base < 1.0
    for scale in (2.0 ** -990, 2.0 ** 500):  # powers of two: the signals are exactly scaled
        assert spqi(dist * scale, ref * scale) == pytest.approx(base, abs=1e-12)
    # vibromaf's eps is not scale-invariant (it is added to a power sum); at 1e150 µm the
    # result must still be a number, not NaN from overflowed squares
    assert spqi(dist * 1e150, ref * 1e150) == pytest.approx(base, abs=1e-9)


def test_spqi_refuses_short_or_non_finite_signals_with_a_message():
    with pytest.raises(QualityError, match="at least 512"):
        spqi(np.zeros(100), np.zeros(100))
    with pytest.raises(QualityError, match="shorter"):
        spqi(np.zeros(600), np.ones(700))
    with pytest.raises(QualityError, match="NaN"):
        spqi(np.full(600, np.nan), np.ones(600))


def test_peer_scores_give_spqi_without_the_peer_extra(monkeypatch):
    rng = np.random.default_rng(4)
    c = rng.normal(0, 1, 160) / np.arange(1, 161)
    d = np.round(c * 8) / 8
    with_extra = peer.peer_scores(c, d, 20000, 10.0, 50.0)
    monkeypatch.setattr(peer, "available", lambda: False)
    without = peer.peer_scores(c, d, 20000, 10.0, 50.0)
    assert "st_sim" not in without and without["spqi"] == with_extra["spqi"]
    ref = peer.played_signal(c, 20000, 10.0, 50.0)
    assert without["spqi"] == spqi(peer.played_signal(d, 20000, 10.0, 50.0), ref)
    assert peer.played_spqi(c, d, 20000, 10.0, 50.0) == without["spqi"]
