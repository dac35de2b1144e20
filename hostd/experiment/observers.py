"""Simulated observers and participants: the statistics of the procedures, checked against
a known truth (tests/test_experiment_stats.py, `hostd experiment bench`).

Threshold observers answer an n-AFC trial correctly with probability P(x), x in dB re 1 µm:
- WeibullObserver: the procedure's own model, P = 1 - δ - (1 - γ - δ) exp(-10^(β (x - t)/20));
- LogisticObserver: another shape, P = γ + (1 - γ - δ) / (1 + exp(-(x - m) / s)), whose
  threshold t is defined as the procedure's is: the level detected with probability 1 - 1/e
  beyond guessing, t = m + s ln(e - 1).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

LN_E_MINUS_1 = math.log(math.e - 1.0)
# The simulated observers' ranges. Steepness at threshold, dP/dx per dB (over 1 - γ - δ):
# Weibull 0.368 β ln10 / 20 = 0.042 β; logistic (1 - 1/e)(1/e) / s = 0.233 / s. So spreads of
# 1.2..2.2 dB are as steep as Weibull shapes 2.5..4.6: the two observers differ in shape (the
# logistic's tails), not in how much a trial can tell.
WEIBULL_SLOPES = (2.5, 5.0)
LOGISTIC_SPREADS_DB = (1.2, 2.2)


@dataclass(frozen=True)
class WeibullObserver:
    threshold_db: float
    slope: float = 3.5
    lapse: float = 0.02
    n_afc: int = 2

    def p_correct(self, x_db: float) -> float:
        g = 1.0 / self.n_afc
        z = 10 ** (self.slope * (x_db - self.threshold_db) / 20)
        return 1 - self.lapse - (1 - g - self.lapse) * math.exp(-z)

    def p_at(self, x_db, threshold_db):
        """P(correct) at x_db of this observer moved to threshold_db (arrays broadcast)."""
        g = 1.0 / self.n_afc
        z = 10 ** (self.slope * (np.asarray(x_db) - threshold_db) / 20)
        return 1 - self.lapse - (1 - g - self.lapse) * np.exp(-z)


@dataclass(frozen=True)
class LogisticObserver:
    threshold_db: float
    spread_db: float = 3.0
    lapse: float = 0.02
    n_afc: int = 2

    def p_correct(self, x_db: float) -> float:
        g = 1.0 / self.n_afc
        m = self.threshold_db - self.spread_db * LN_E_MINUS_1
        return g + (1 - g - self.lapse) / (1 + math.exp(-(x_db - m) / self.spread_db))

    def p_at(self, x_db, threshold_db):
        """P(correct) at x_db of this observer moved to threshold_db (arrays broadcast)."""
        g = 1.0 / self.n_afc
        m = threshold_db - self.spread_db * LN_E_MINUS_1
        return g + (1 - g - self.lapse) / (1 + np.exp(-(np.asarray(x_db) - m) / self.spread_db))


def make_observer(kind: str, rng: np.random.Generator, centre_db: float, n_afc: int):
    """A random observer: its threshold within ±8 dB of the prior's centre, its slope or spread
    and lapse rate drawn too (the procedure knows none of them)."""
    t = centre_db + rng.uniform(-8.0, 8.0)
    lapse = rng.uniform(0.0, 0.04)
    if kind == "weibull":
        return WeibullObserver(t, slope=rng.uniform(*WEIBULL_SLOPES), lapse=lapse, n_afc=n_afc)
    if kind == "logistic":
        return LogisticObserver(t, spread_db=rng.uniform(*LOGISTIC_SPREADS_DB), lapse=lapse, n_afc=n_afc)
    raise ValueError(kind)


def simulate_thresholds(kind: str, n_afc: int, runs: int, max_trials: int = 30, seed: int = 0,
                        centre_um: float = 0.1, reach_um: float = 30.0) -> np.ndarray:
    """Errors (estimate - truth, dB) of `runs` seeded single-frequency QUEST+ runs."""
    from hostd.experiment.threshold import ThresholdConfig, ThresholdRun, db

    errs = np.empty(runs)
    for r in range(runs):
        rng = np.random.default_rng([seed, r])
        obs = make_observer(kind, rng, db(centre_um), n_afc)
        run = ThresholdRun(ThresholdConfig([250.0], [centre_um], [reach_um], n_afc=n_afc,
                                           max_trials=max_trials, seed=int(rng.integers(1 << 31))))
        while (t := run.next_trial()) is not None:
            correct = rng.random() < obs.p_correct(t.level_db)
            run.answer(t.index, t.target if correct else (t.target % n_afc) + 1)
        errs[r] = db(run.results()[0].threshold_um) - obs.threshold_db
    return errs


def simulate_oracle(kind: str, n_afc: int, runs: int, max_trials: int = 30, seed: int = 0,
                    centre_um: float = 0.1, reach_um: float = 30.0, prior: str = "procedure") -> np.ndarray:
    """A practical ceiling for a procedure on simulate_thresholds' observers: errors (dB) of a grid
    Bayes that knows each observer's psychometric function exactly (shape, slope, lapse) and has only
    its threshold to find, with the per-frequency procedure's prior on it (prior="procedure":
    normal, PRIOR_SD_DB about the prior's centre) or the simulation's own draw of it
    (prior="true": uniform ±8 dB), the same levels, the QUEST+ rule (the level of least expected
    posterior entropy) and the posterior mean. The same seeds give the same observers and
    answers' random numbers as simulate_thresholds."""
    from hostd.experiment.threshold import GRID_STEP_DB, PRIOR_SD_DB, PRIOR_SPAN_DB, db

    centre, top = db(centre_um), db(reach_um)
    stim = np.arange(centre - PRIOR_SPAN_DB, top + 1e-9, GRID_STEP_DB)
    ts = np.arange(centre - PRIOR_SPAN_DB, centre + PRIOR_SPAN_DB + 1e-9, 0.25)
    if prior == "procedure":
        p0 = np.exp(-0.5 * ((ts - centre) / PRIOR_SD_DB) ** 2)
    elif prior == "true":
        p0 = (np.abs(ts - centre) <= 8.0).astype(np.float64)
    else:
        raise ValueError(prior)
    errs = np.empty(runs)
    for r in range(runs):
        rng = np.random.default_rng([seed, r])
        obs = make_observer(kind, rng, centre, n_afc)
        rng.integers(1 << 31)  # simulate_thresholds' run seed: the answers' draws stay in step
        pc_table = obs.p_at(stim[:, None], ts[None, :])  # (level, threshold)
        post = p0 / p0.sum()
        for _ in range(max_trials):
            eh = np.zeros(stim.size)
            for m in (post * pc_table, post * (1 - pc_table)):
                tot = m.sum(axis=1)
                with np.errstate(divide="ignore", invalid="ignore"):
                    eh -= np.sum(np.where(m > 0, m * np.log(m / tot[:, None]), 0.0), axis=1)
            i = int(np.argmin(eh))
            correct = rng.random() < obs.p_correct(stim[i])
            post = post * (pc_table[i] if correct else 1 - pc_table[i])
            post /= post.sum()
        errs[r] = float(post @ ts) - obs.threshold_db
    return errs


def simulate_fit(a: float, b: float, noise_sd: float, n_sims: int = 50, reps: int = 4,
                 participants: int = 8, seed: int = 0, n_boot: int = 2000) -> dict:
    """Simulated participants whose scores are a Ip + b Ia plus noise (per answer, on the paper's
    0..3 scale: rounded and clipped like a grade), over the paper's wood design (6 quant + 6 cut
    levels + the control, `reps` repetitions, `participants` people, mean score per stimulus).
    Returns the coverage of the 95 % intervals `hostd fit` states (its residual bootstrap-t) and
    their mean widths, beside those of the t interval of its standard errors."""
    from hostd.perception import fit

    rng0 = np.random.default_rng(seed)
    # (Ip, Ia) of a design like the paper's: quantization raises Ia faster, cut raises Ip
    ip = np.concatenate([np.linspace(0.1, 1.4, 6), np.linspace(0.05, 1.0, 6), [0.0]])
    ia = np.concatenate([np.linspace(0.2, 1.6, 6), np.linspace(0.1, 0.7, 6), [0.0]])
    ip = ip * rng0.uniform(0.9, 1.1, ip.size)
    ia = ia * rng0.uniform(0.9, 1.1, ia.size)
    cover_a = cover_b = both = se_cover = 0
    wa, wb, se_w = [], [], []
    for s in range(n_sims):
        rng = np.random.default_rng([seed, s])
        true = a * ip + b * ia
        noise = rng.normal(0, noise_sd, (participants * reps, ip.size))
        grades = np.clip(np.rint(true[None, :] + noise), 0, 3)
        mean = grades.mean(axis=0)
        stim = [fit.Stimulus("wood", "none" if k == ip.size - 1 else "m", str(k), float(mean[k]),
                             float(ip[k]), float(ia[k])) for k in range(ip.size)]
        res = fit.fit(stim, n_boot=n_boot, scale_max=3.0, scale_min=0.0)
        cover_a += res.ci_a[0] <= a <= res.ci_a[1]
        cover_b += res.ci_b[0] <= b <= res.ci_b[1]
        both += res.ci_a[0] <= a <= res.ci_a[1] and res.ci_b[0] <= b <= res.ci_b[1]
        wa.append(res.ci_a[1] - res.ci_a[0])
        wb.append(res.ci_b[1] - res.ci_b[0])
        ta, tb = res.t_interval_a, res.t_interval_b  # hostd fit's t interval of its standard errors
        se_cover += ta[0] <= a <= ta[1] and tb[0] <= b <= tb[1]
        se_w.append(ta[1] - ta[0])
    return {"coverage_a": cover_a / n_sims, "coverage_b": cover_b / n_sims, "coverage_both": both / n_sims,
            "mean_width_a": float(np.mean(wa)), "mean_width_b": float(np.mean(wb)), "sims": n_sims,
            "stimuli": int(ip.size), "answers_per_stimulus": participants * reps, "noise_sd": noise_sd,
            "se_t_interval_coverage_both": se_cover / n_sims,
            "se_t_interval_mean_width_a": float(np.mean(se_w))}
