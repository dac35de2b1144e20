"""Joint mode: the whole threshold curve at once, by the QUEST+ rule over a parametric curve.

Detection thresholds across frequency form a smooth U. Instead of one QUEST+ per frequency,
this estimates one curve over u, log-frequency scaled to [-1, 1] over the measured range:

    t(f) = prior_db(f) + c0 + c1 u + c2 u²          (dB re 1 µm)

the prior curve (the shipped b(f), or the one given) plus a smooth correction (offset, tilt,
curvature: a log-parabola about the prior's shape), with one slope β and lapse δ shared by
all frequencies. The psychometric function is the per-frequency procedure's Weibull,
P = 1 - δ - (1 - γ - δ) exp(-10^(β (x - t(f)) / 20)), γ = 1/n. A trial's stimulus is a pair
(frequency, level); the next is the one that minimises the expected entropy of the posterior
over the joint grid (c0, c1, c2, β, δ), the QUEST+ rule (Watson 2017), computed as the one that
maximises the mutual information h(Σ p P) - Σ p h(P) (h the binary entropy; equal, since the
current entropy is the same for every stimulus). Two matrix-vector products per trial.

Why not questplus: its QuestPlus accepts only its built-in functions; the one over frequency,
`csf`, makes the threshold a linear function max(min_thresh, c0 + cf·f + cw·w) of two stimulus
coordinates over their full product grid, so a quadratic in log f would need w = u² as a second
coordinate that it would choose independently of f (stimuli that are no frequency at all), and
it has no way to add the prior curve per frequency. Hence this small grid-Bayes of the same
rule, on numpy alone.

Safety as in the per-frequency procedure: each frequency's levels run PRIOR_SPAN_DB either side
of the prior and never above the display's reach (the host refuses anything above it:
hostd.experiment.display); the curve's grid extends above the reach, so a threshold above it is
reported as "above_reach", never clipped. The estimate at f is the posterior mean of t(f), its
interval the central 95 % of t(f)'s posterior. The budget is max_trials × the number of
frequencies in all (so `--trials 15` is half of 30 per frequency); a stop width ends the run
once every frequency's interval is that narrow. A run is a pure function of (config, seed,
answers): resuming replays the answers.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from hostd.experiment.threshold import ThresholdConfig, ThresholdResult, Trial, answered, db, um

PRIOR_SPAN_DB = 22.0  # levels this far either side of the prior curve (and never above the reach)
LEVEL_STEP_DB = 2.0
C0_DB = np.arange(-16.0, 16.0 + 1e-9, 1.0)  # offset from the prior curve
C0_PRIOR_SD_DB = 6.0  # as the per-frequency procedure's prior on t
C12_DB = np.arange(-6.0, 6.0 + 1e-9, 2.0)  # tilt and curvature, dB at the range's ends
C12_PRIOR_SD_DB = 4.0
SLOPES = (2.0, 3.5, 6.0)  # β and δ shared by all frequencies, marginalised over (the curve has
LAPSE = (0.0, 0.04)  # trials to spare for them, unlike one frequency's 30)
PRUNE_EVERY = 8  # trials between re-selections of the grid points the choice is computed over
PRUNE_LOG = 20.0


def _binary_entropy(p: np.ndarray) -> np.ndarray:
    p = np.clip(p, 1e-12, 1 - 1e-12)
    return -(p * np.log(p) + (1 - p) * np.log1p(-p))


@dataclass
class JointRun:
    """The whole curve at once; next_trial() then answer(trial, chosen interval), in order (the
    interface of threshold.ThresholdRun)."""

    cfg: ThresholdConfig
    rng: np.random.Generator = field(init=False)
    index: int = field(init=False, default=0)
    pending: Trial | None = field(init=False, default=None)

    def __post_init__(self) -> None:
        c = self.cfg
        f = np.asarray(c.frequencies_hz, dtype=np.float64)
        lf = np.log10(f)
        half = (lf.max() - lf.min()) / 2
        self.u = (lf - (lf.max() + lf.min()) / 2) / half if half > 0 else np.zeros_like(lf)
        self.prior_db = np.array([db(p) for p in c.prior_um])
        self.reach_db = np.array([db(r) for r in c.reach_um])
        c0, c1, c2, beta, lapse = np.meshgrid(C0_DB, C12_DB, C12_DB, np.array(SLOPES), np.array(LAPSE),
                                              indexing="ij")
        self.c = np.stack([c0.ravel(), c1.ravel(), c2.ravel()])  # (3, n_theta)
        self.beta, self.lapse = beta.ravel(), lapse.ravel()
        lp = (-0.5 * (c0 / C0_PRIOR_SD_DB) ** 2 - 0.5 * ((c1 ** 2 + c2 ** 2) / C12_PRIOR_SD_DB ** 2)).ravel()
        self.log_post = lp - lp.max()
        # stimuli: (frequency index, level) with the level never above that frequency's reach
        fi, lv = [], []
        for i in range(f.size):
            top = self.reach_db[i]
            levels = np.arange(self.prior_db[i] - PRIOR_SPAN_DB,
                               min(top, self.prior_db[i] + PRIOR_SPAN_DB) + 1e-9, LEVEL_STEP_DB)
            if levels.size < 2:
                levels = np.array([top - LEVEL_STEP_DB, top])
            levels = levels[levels <= top]
            fi.extend([i] * levels.size)
            lv.extend(levels)
        self.stim_f = np.array(fi)
        self.stim_db = np.array(lv)
        # P(correct | theta, stimulus) and its binary entropy, (n_theta, n_stim): a row per grid point
        t = self.curve_db_grid()[self.stim_f].T  # (n_theta, n_stim)
        g = 1.0 / c.n_afc
        b, d = self.beta[:, None], self.lapse[:, None]
        z = 10.0 ** (np.clip(b * (self.stim_db[None, :] - t) / 20.0, -30, 5))
        self.p_correct = 1 - d - (1 - g - d) * np.exp(-z)
        self.h = _binary_entropy(self.p_correct)
        self.n_per_f = np.zeros(f.size, dtype=int)
        self._act = None
        self.rng = np.random.default_rng(c.seed)

    def curve_db_grid(self) -> np.ndarray:
        """t(f) at every grid point, (n_freq, n_theta)."""
        u = self.u[:, None]
        return self.prior_db[:, None] + self.c[0] + self.c[1] * u + self.c[2] * u * u

    def posterior(self) -> np.ndarray:
        p = np.exp(self.log_post - self.log_post.max())
        return p / p.sum()

    @property
    def budget(self) -> int:
        return self.cfg.max_trials * len(self.cfg.frequencies_hz)

    @property
    def planned_trials(self) -> int:
        return self.budget

    def _stopped(self) -> bool:
        if self.index >= self.budget:
            return True
        if self.cfg.stop_width_db > 0 and self.index >= 5:
            return all(hi - lo <= self.cfg.stop_width_db for lo, hi in self.intervals_db())
        return False

    @property
    def done(self) -> bool:
        return self.pending is None and self._stopped()

    def next_trial(self) -> Trial | None:
        """The trial to present (the same one again until it is answered)."""
        if self.pending is not None:
            return self.pending
        if self._stopped():
            return None
        if self.index % PRUNE_EVERY == 0 or self._act is None:
            # the grid points that still matter (posterior above e^-PRUNE_LOG of its peak): the
            # choice is made over them alone (the posterior itself keeps every point)
            act = np.flatnonzero(self.log_post > self.log_post.max() - PRUNE_LOG)
            self._act, self._pa, self._ha = act, self.p_correct[act], self.h[act]
        post = np.exp(self.log_post[self._act] - self.log_post.max())
        post /= post.sum()
        pc = post @ self._pa
        info = _binary_entropy(pc) - post @ self._ha  # mutual information = entropy reduction
        best = np.flatnonzero(info >= info.max() - 1e-12)
        s = int(best[int(self.rng.integers(best.size))])
        i = int(self.stim_f[s])
        x = float(self.stim_db[s])
        target = int(self.rng.integers(1, self.cfg.n_afc + 1))
        self.pending = Trial(self.index, self.cfg.frequencies_hz[i], um(x), x, target, self.cfg.n_afc)
        self._stim = s
        return self.pending

    def answer(self, trial_index: int, chosen: int) -> bool:
        """Record the chosen interval of the pending trial; returns whether it was correct."""
        t = self.pending
        correct = answered(t, trial_index, chosen)
        p = self.p_correct[:, self._stim]
        self.log_post = self.log_post + np.log(np.clip(p if correct else 1 - p, 1e-300, None))
        self.log_post -= self.log_post.max()
        self.n_per_f[self.stim_f[self._stim]] += 1
        self.pending = None
        self.index += 1
        return correct

    def estimates_db(self) -> np.ndarray:
        """Posterior mean of t(f) per frequency (t is linear in c: the mean of c plugged in)."""
        m = self.c @ self.posterior()
        return self.prior_db + m[0] + m[1] * self.u + m[2] * self.u ** 2

    def intervals_db(self, level: float = 0.95) -> list[tuple[float, float]]:
        post = self.posterior()
        out = []
        for row in self.curve_db_grid():
            o = np.argsort(row)
            cdf = np.cumsum(post[o])
            out.append((float(np.interp((1 - level) / 2, cdf, row[o])),
                        float(np.interp((1 + level) / 2, cdf, row[o]))))
        return out

    def results(self) -> list[ThresholdResult]:
        est = self.estimates_db()
        out = []
        for i, ((lo, hi), t) in enumerate(zip(self.intervals_db(), est, strict=True)):
            status = "above_reach" if t > self.reach_db[i] else "ok"
            out.append(ThresholdResult(self.cfg.frequencies_hz[i], um(float(t)), um(lo), um(hi),
                                       int(self.n_per_f[i]), self.cfg.reach_um[i], status))
        return out


def simulate_joint(kind: str, n_afc: int, runs: int, trials_per_frequency: int = 15, seed: int = 0,
                   wiggle_db: float = 0.0, reach_um: float = 30.0) -> np.ndarray:
    """Errors (estimate - truth, dB), (runs, n_freq), of seeded joint runs over the shipped
    b(f)'s frequencies. The observer's curve is the shipped one plus a random offset (±8 dB, as
    the per-frequency bench draws its thresholds), tilt and curvature (±3 dB at the range's
    ends) and, with wiggle_db, an independent normal deviation per frequency (a curve that is
    not of the model's form); one slope and lapse rate for all frequencies."""
    from hostd.experiment.observers import (
        LOGISTIC_SPREADS_DB,
        WEIBULL_SLOPES,
        LogisticObserver,
        WeibullObserver,
    )
    from hostd.perception import thresholds as th

    curve = th.default_curve()
    freqs = [float(f) for f in curve.freq_hz]
    prior = [float(v) for v in curve.threshold_um]
    lf = np.log10(freqs)
    u = (lf - (lf.max() + lf.min()) / 2) / ((lf.max() - lf.min()) / 2)
    errs = np.empty((runs, len(freqs)))
    for r in range(runs):
        rng = np.random.default_rng([seed, r])
        d0, d1, d2 = rng.uniform(-8, 8), rng.uniform(-3, 3), rng.uniform(-3, 3)
        truth = np.array([db(p) for p in prior]) + d0 + d1 * u + d2 * u * u
        truth = truth + (rng.normal(0, wiggle_db, truth.size) if wiggle_db > 0 else 0.0)
        lapse = rng.uniform(0.0, 0.04)
        if kind == "weibull":
            beta = rng.uniform(*WEIBULL_SLOPES)
            obs = [WeibullObserver(t, slope=beta, lapse=lapse, n_afc=n_afc) for t in truth]
        elif kind == "logistic":
            s = rng.uniform(*LOGISTIC_SPREADS_DB)
            obs = [LogisticObserver(t, spread_db=s, lapse=lapse, n_afc=n_afc) for t in truth]
        else:
            raise ValueError(kind)
        run = JointRun(ThresholdConfig(freqs, prior, [reach_um] * len(freqs), n_afc=n_afc,
                                       max_trials=trials_per_frequency, seed=int(rng.integers(1 << 31)),
                                       procedure="joint"))
        while (t := run.next_trial()) is not None:
            o = obs[freqs.index(t.frequency_hz)]
            correct = rng.random() < o.p_correct(t.level_db)
            run.answer(t.index, t.target if correct else (t.target % n_afc) + 1)
        errs[r] = run.estimates_db() - truth
    return errs

