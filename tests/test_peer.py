"""The peer metrics: ST-SIM with the reference's side cached equals vibromaf's own st_sim()."""

from __future__ import annotations

import numpy as np
import pytest

from hostd.perception import peer

pytestmark = pytest.mark.skipif(not peer.available(), reason="vibromaf (hostd[peer]) not installed")


def test_cached_st_sim_equals_vibromafs_for_every_variant():
    from vibromaf.metrics.spqi import spqi
    from vibromaf.metrics.stsim import st_sim

    rng = np.random.default_rng(3)
    n, length, speed = 2000, 10.0, 50.0
    ref_c = rng.normal(0, 1, 160) / np.arange(1, 161)
    variants = [ref_c, ref_c * 0.9, np.where(np.arange(160) < 80, ref_c, 0.0),
                np.round(ref_c * 8) / 8]
    ref = peer.played_signal(ref_c, n, length, speed)
    for c in variants:
        got = peer.peer_scores(ref_c, c, n, length, speed)
        dist = peer.played_signal(c, n, length, speed)
        assert got["st_sim"] == pytest.approx(float(st_sim(dist, ref)), rel=0, abs=1e-15)
        assert got["spqi"] == pytest.approx(float(spqi(dist, ref)), rel=0, abs=1e-15)
    assert peer.peer_scores(ref_c, ref_c, n, length, speed)["st_sim"] == 1.0
