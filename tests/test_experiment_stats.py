"""The statistics of the procedures, on simulated observers and participants with a known truth.

A subset of the bench (`hostd experiment bench`, docs/experiments.md has its full figures: 200
seeded runs per procedure, 2AFC and 3AFC, both observers): 10 seeded runs per case here, whose
bound fails for a procedure that is biased or on the wrong scale (errors of several dB), while
the ≥ 90 % within ±2 dB figure is measured by the bench."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("questplus")

from hostd.experiment.observers import LogisticObserver, WeibullObserver, simulate_fit, simulate_thresholds


def test_the_observers_threshold_is_the_procedures_threshold():
    # both observers detect their threshold with probability 1 - 1/e beyond guessing
    for obs in (WeibullObserver(-20.0, 3.0, 0.02, 2), LogisticObserver(-20.0, 1.7, 0.02, 2),
                WeibullObserver(5.0, 4.0, 0.0, 3), LogisticObserver(5.0, 2.0, 0.0, 3)):
        g = 1 / obs.n_afc
        assert (obs.p_correct(obs.threshold_db) - g) / (1 - g - obs.lapse) == pytest.approx(1 - np.exp(-1))


@pytest.mark.parametrize("kind", ["weibull", "logistic"])
@pytest.mark.parametrize("n_afc", [2, 3])
def test_quest_plus_finds_a_known_threshold_within_30_trials(kind, n_afc):
    e = simulate_thresholds(kind, n_afc, runs=10, max_trials=30, seed=7)
    # 10 runs cannot pin a 90 % rate; they do catch a biased or mis-scaled procedure
    assert np.median(np.abs(e)) <= 2.5 and abs(np.mean(e)) <= 1.5 and np.max(np.abs(e)) <= 6.0, e


def test_fit_recovers_known_weights_inside_its_interval():
    r = simulate_fit(0.581, 0.464, 0.5, n_sims=50, n_boot=200)
    # the standard errors' t interval covers (a, b) jointly as a 95 % interval should
    assert r["se_t_interval_coverage_both"] >= 0.9
    # the bootstrap percentile interval of 13 stimuli is too narrow (docs/experiments.md)
    assert min(r["coverage_a"], r["coverage_b"]) >= 0.75
    assert r["mean_width_a"] < r["se_t_interval_mean_width_a"]
