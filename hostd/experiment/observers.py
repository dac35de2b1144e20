"""Simulated observers and participants: the statistics of the procedures, checked against
a known truth (tests/test_experiment_stats.py, `hostd experiment bench`).

Threshold observers answer an n-AFC trial correctly with probability P(x), x in dB re 1 µm, a
psychometric function named as the procedures name theirs (hostd.experiment.psychometric):
- weibull: the procedure's own model, P = 1 - δ - (1 - γ - δ) exp(-10^(β (x - t)/20));
- logistic: another shape, P = γ + (1 - γ - δ) / (1 + exp(-(x - m) / s)), whose threshold t is
  defined as the procedure's is: the level detected with probability 1 - 1/e beyond guessing,
  t = m + s ln(e - 1).
The bench's observers (SHAPES) draw their slope or spread from a range, their threshold within
±8 dB of the prior's centre and their lapse rate in 0..0.04; the procedure knows none of them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hostd.experiment import psychometric

LN_E_MINUS_1 = psychometric.LN_E_MINUS_1
# The simulated observers' ranges. Steepness at threshold, dP/dx per dB (over 1 - γ - δ):
# Weibull 0.368 β ln10 / 20 = 0.042 β; logistic (1 - 1/e)(1/e) / s = 0.233 / s. So spreads of
# 1.2..2.2 dB are as steep as Weibull shapes 2.5..4.6: the two observers differ in shape (the
# logistic's tails), not in how much a trial can tell. β = 2 is the model's shallowest Weibull
# (threshold.SLOPES): half as steep as the middle of the first range.
WEIBULL_SLOPES = (2.5, 5.0)
LOGISTIC_SPREADS_DB = (1.2, 2.2)
# name -> (psychometric function, range of its slope or spread): the bench's observer shapes
SHAPES = {
    "weibull": ("weibull", WEIBULL_SLOPES),
    "logistic": ("logistic", LOGISTIC_SPREADS_DB),
    "weibull-beta2": ("weibull", (2.0, 2.0)),
}
THRESHOLD_SPREAD_DB = 8.0  # an observer's threshold: uniform within this of the prior's centre
LAPSES = (0.0, 0.04)


@dataclass(frozen=True)
class Observer:
    threshold_db: float
    slope: float  # the Weibull's β, or the logistic's spread in dB
    lapse: float = 0.02
    n_afc: int = 2
    func: str = "weibull"

    def p_correct(self, x_db: float) -> float:
        return float(self.p_at(x_db, self.threshold_db))

    def p_at(self, x_db, threshold_db):
        """P(correct) at x_db of this observer moved to threshold_db (arrays broadcast)."""
        return psychometric.p_correct(self.func, x_db, threshold_db, self.slope, 1.0 / self.n_afc, self.lapse)


def WeibullObserver(threshold_db: float, slope: float = 3.5, lapse: float = 0.02, n_afc: int = 2) -> Observer:
    return Observer(threshold_db, slope, lapse, n_afc, "weibull")


def LogisticObserver(threshold_db: float, spread_db: float = 3.0, lapse: float = 0.02,
                     n_afc: int = 2) -> Observer:
    return Observer(threshold_db, spread_db, lapse, n_afc, "logistic")


def make_observer(kind: str, rng: np.random.Generator, centre_db: float, n_afc: int) -> Observer:
    """A random observer of shape `kind` (SHAPES): its threshold within ±8 dB of the prior's
    centre, its slope or spread and lapse rate drawn too (the procedure knows none of them)."""
    if kind not in SHAPES:
        raise ValueError(f"observer {kind!r}: one of {', '.join(SHAPES)}")
    func, (lo, hi) = SHAPES[kind]
    t = centre_db + rng.uniform(-THRESHOLD_SPREAD_DB, THRESHOLD_SPREAD_DB)
    lapse = rng.uniform(*LAPSES)
    return Observer(t, rng.uniform(lo, hi), lapse, n_afc, func)


def observers(kind: str, runs: int, seed: int, centre_db: float,
              n_afc: int) -> tuple[list[Observer], np.ndarray]:
    """The bench's observers of runs 0..runs-1 (each from its own seeded generator, so run r is
    the same observer whatever the number of runs) and a seed per run for what follows."""
    obs, seeds = [], np.empty(runs, dtype=np.int64)
    for r in range(runs):
        rng = np.random.default_rng([seed, r])
        obs.append(make_observer(kind, rng, centre_db, n_afc))
        seeds[r] = rng.integers(1 << 31)
    return obs, seeds


def simulate_threshold_runs(kind: str, n_afc: int, runs: int, max_trials: int = 30, seed: int = 0,
                            centre_um: float = 0.1, reach_um: float = 30.0, stop_width_db: float = 0.0,
                            min_trials_width: int | None = None) -> dict:
    """`runs` seeded single-frequency QUEST+ runs at once (threshold.ThresholdGrid, the procedure's
    own posterior and rule, one row per run), stopping as ThresholdRun does: at max_trials, or
    once the 95 % interval is narrower than stop_width_db after min_trials_width trials (None:
    the procedure's default, threshold.MIN_TRIALS_WIDTH).
    Returns the errors (estimate - truth, dB), the trials each took and whether its 95 %
    interval held the truth."""
    from hostd.experiment import threshold as thr

    min_w = thr.MIN_TRIALS_WIDTH[n_afc] if min_trials_width is None else min_trials_width
    centre = thr.db(centre_um)
    obs, seeds = observers(kind, runs, seed, centre, n_afc)
    func = obs[0].func
    t_true = np.array([o.threshold_db for o in obs])
    slope = np.array([o.slope for o in obs])
    lapse = np.array([o.lapse for o in obs])
    u = np.random.default_rng(seeds).random((runs, max_trials))  # the answers' random numbers
    grid = thr.ThresholdGrid(centre_um, reach_um, n_afc, runs)
    live = np.ones(runs, dtype=bool)
    for k in range(max_trials):
        rows = np.flatnonzero(live)
        if rows.size == 0:
            break
        x = grid.stim[grid.next_index(rows)]
        p = psychometric.p_correct(func, x, t_true[rows], slope[rows], 1.0 / n_afc, lapse[rows])
        grid.update(rows, x, u[rows, k] < p)
        if stop_width_db > 0 and k + 1 >= min_w:
            live[rows] = grid.width_db(rows=rows) > stop_width_db
    iv = grid.interval_db()
    return {"errors_db": grid.estimate_db() - t_true, "trials": grid.n.copy(),
            "covered": (iv[:, 0] <= t_true) & (t_true <= iv[:, 1])}


def simulate_thresholds(kind: str, n_afc: int, runs: int, max_trials: int = 30, seed: int = 0,
                        centre_um: float = 0.1, reach_um: float = 30.0) -> np.ndarray:
    """Errors (estimate - truth, dB) of `runs` seeded single-frequency QUEST+ runs of max_trials."""
    return simulate_threshold_runs(kind, n_afc, runs, max_trials, seed, centre_um, reach_um)["errors_db"]


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
    obs, seeds = observers(kind, runs, seed, centre, n_afc)
    u = np.random.default_rng(seeds).random((runs, max_trials))  # simulate_threshold_runs' numbers
    errs = np.empty(runs)
    for r, o in enumerate(obs):
        table = o.p_at(stim[:, None], ts[None, :])[..., None]  # (level, threshold, no nuisance)
        post = (p0 / p0.sum())[:, None]
        for k in range(max_trials):
            i = int(np.argmax(psychometric.information(post, table)))
            lik = table[i] if u[r, k] < o.p_correct(stim[i]) else 1 - table[i]
            post = post * lik
            post /= post.sum()
        errs[r] = float(post[:, 0] @ ts) - o.threshold_db
    return errs


def wood_design(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(Ip, Ia) of a design like the paper's wood test: 6 quant + 6 cut levels + the control
    (quantization raises Ia faster, cut raises Ip), jittered ±10 % with the seed."""
    rng0 = np.random.default_rng(seed)
    ip = np.concatenate([np.linspace(0.1, 1.4, 6), np.linspace(0.05, 1.0, 6), [0.0]])
    ia = np.concatenate([np.linspace(0.2, 1.6, 6), np.linspace(0.1, 0.7, 6), [0.0]])
    return ip * rng0.uniform(0.9, 1.1, ip.size), ia * rng0.uniform(0.9, 1.1, ia.size)


def simulate_fit(a: float, b: float, noise_sd: float, n_sims: int = 50, reps: int = 4,
                 participants: int = 8, seed: int = 0, n_boot: int = 2000) -> dict:
    """Simulated participants whose scores are a Ip + b Ia plus noise (per answer, on the paper's
    0..3 scale: rounded and clipped like a grade), over the paper's wood design (wood_design,
    `reps` repetitions, `participants` people, mean score per stimulus): fit.design_coverage,
    the coverage of the 95 % intervals `hostd fit` states (its residual bootstrap-t) and their
    mean widths, beside those of the t interval of its standard errors."""
    from hostd.perception import fit

    ip, ia = wood_design(seed)
    return fit.design_coverage(ip, ia, a, b, noise_sd, participants * reps, sims=n_sims, n_boot=n_boot,
                               seed=seed)
