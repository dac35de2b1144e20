"""Joint mode: the whole threshold curve at once, by the QUEST+ rule over a parametric curve,
estimated with a bump of its own at each frequency, and more trials per frequency where the
answers call for bumps.

Detection thresholds across frequency form a smooth U. Instead of one QUEST+ per frequency,
this estimates one curve over u, log-frequency scaled to [-1, 1] over the measured range:

    t(f) = prior_db(f) + c0 + c1 u + c2 u²          (dB re 1 µm)

the prior curve (the shipped b(f), or the one given) plus a smooth correction (offset, tilt,
curvature: a log-parabola about the prior's shape), with one slope β and lapse δ shared by
all frequencies. The psychometric function is the per-frequency procedure's Weibull
(psychometric.weibull), γ = 1/n. A trial's stimulus is a pair (frequency, level): the frequency
one of those tried least so far (so every frequency has answers of its own, which the check
needs), the level the one of most information about the whole grid (c0, c1, c2, β, δ): the
QUEST+ rule (psychometric.information_flat, the per-frequency procedure's rule with no nuisance
parameter: the curve has trials to spare for β and δ, unlike one frequency's 30). Two matrix
products per trial, for one run or a batch of them (the bench runs hundreds at once through
this code).

The estimates: the curve with a bump per frequency. A lab's curve need not be of this form (a
resonance of the display puts a bump in it); a curve's estimate alone then misses at the bumps
while its intervals, which trust the form, are narrow. So the thresholds and their intervals
come from a hierarchical posterior (bump_posterior): t(f) = the curve + b_f, the bumps b_f
independent normal of an SD σ ∈ BUMP_SD_DB (0, 1, 2, 3 dB; prior BUMP_PRIOR) marginalised with
the curve, β and δ, from every answer. Given (curve, σ, β, δ) the frequencies are independent,
so each bump is integrated out per frequency on a fine grid of t (FINE_STEP_DB) and the grid
over (curve, σ, β, δ) stays the joint grid times 4. The answers then say how far to trust the
curve at each frequency: the intervals hold for a smooth curve and for a bumpy one, whether
or not the check below fires (`hostd experiment bench --joint-runs`, docs/experiments.md).

The check. Once the joint phase's budget (max_trials × the frequencies) is spent, a run whose
posterior gives bumps of SD >= BUMP_FOUND_DB a probability above BUMP_FOUND_P (0.3: chosen on
the bench, smooth curves spend more in 16-28 % of runs, bumps of SD 2 dB in about 70 %) spends
misfit_trials × the frequencies more, one QUEST+ per frequency (threshold.ThresholdGrid, each
frequency's posterior from the per-frequency prior and every answer at that frequency, the
joint phase's included), each trial at the frequency whose 95 % interval is the widest; the
estimates are the same posterior's, from every answer. notes() says whether it fired. (Tried
before and dropped: a likelihood-ratio test against χ², anti-conservative at 15 adaptive
trials per frequency (it fired on half the smooth curves), and its parametric bootstrap,
conservative; both chose between the curve's thresholds and each frequency's own, whose
intervals then missed in the runs the test got wrong.)

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
interval the central 95 % of t(f)'s posterior (both with the bumps). The default budget is
JOINT_TRIALS (15) per frequency, half the per-frequency procedure's 30, and as many again on a
misfit; a stop width ends the joint phase once every frequency's interval on the smooth curve
is that narrow. A run is a pure function of (config, seed, answers): resuming replays the
answers.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from hostd.experiment import psychometric
from hostd.experiment.threshold import (
    JOINT_TRIALS,
    ThresholdConfig,
    ThresholdGrid,
    ThresholdResult,
    Trial,
    answered,
    db,
    um,
)

PRIOR_SPAN_DB = 22.0  # levels this far either side of the prior curve (and never above the reach)
LEVEL_STEP_DB = 2.0
C0_DB = np.arange(-16.0, 16.0 + 1e-9, 1.0)  # offset from the prior curve
C0_PRIOR_SD_DB = 6.0  # as the per-frequency procedure's prior on t
C12_DB = np.arange(-6.0, 6.0 + 1e-9, 2.0)  # tilt and curvature, dB at the range's ends
C12_PRIOR_SD_DB = 4.0
SLOPES = (2.0, 3.5, 6.0)  # β and δ shared by all frequencies
LAPSE = (0.0, 0.04)
# The choice is computed over the grid points within exp(-PRUNE_LOG) of the most probable one (of
# any run of the batch), reselected every PRUNE_EVERY trials: the rest changes the information
# by less than 1e-5 of its value.
PRUNE_EVERY = 8
PRUNE_LOG = 20.0
JOINT, PER_FREQUENCY, DONE = 0, 1, 2  # a run's phase
# The estimates' model: the curve plus a bump per frequency, normal with an SD of its own (one
# of BUMP_SD_DB, prior BUMP_PRIOR), marginalised; on a grid of FINE_STEP_DB.
BUMP_SD_DB = (0.0, 1.0, 2.0, 3.0)
BUMP_PRIOR = (0.4, 0.2, 0.2, 0.2)
FINE_STEP_DB = 0.25
# The check: after the joint phase, P(σ >= BUMP_FOUND_DB | the answers) above BUMP_FOUND_P: spend
# the fallback's trials (calibrated by `hostd experiment bench --joint-runs`: docs/experiments.md)
BUMP_FOUND_DB = 2.0
BUMP_FOUND_P = 0.3


class JointBatch:
    """`runs` joint runs of one config at once (one row each; JointRun is a batch of one): the
    joint grid's log posterior, each frequency's own QUEST+ posterior (for the check's
    fallback) and the answers so far. choose(rows) then record(rows, correct), per trial."""

    def __init__(self, cfg: ThresholdConfig, runs: int = 1, seeds=None) -> None:
        self.cfg = c = cfg
        f = np.asarray(c.frequencies_hz, dtype=np.float64)
        self.n_f = f.size
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
        # stimuli: (frequency index, level) with the level never above that frequency's reach
        fi, lv = [], []
        for i in range(self.n_f):
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
        # P(correct | theta, stimulus) and its binary entropy, (n_theta, n_stim)
        self._curve = self.curve_db_grid()  # (n_freq, n_theta)
        t = self._curve[self.stim_f].T
        self.p_correct = psychometric.weibull(self.stim_db[None, :], t, self.beta[:, None], 1.0 / c.n_afc,
                                              self.lapse[:, None])
        self.p_correct = np.ascontiguousarray(self.p_correct)
        self.h = psychometric.binary_entropy(self.p_correct)
        self.runs = runs
        self.log_prior = lp - lp.max()
        self.log_post = np.repeat(self.log_prior[None], runs, axis=0)  # (runs, n_theta)
        nb, nd = np.meshgrid(np.array(SLOPES), np.array(LAPSE), indexing="ij")
        self._nuisance = (nb.ravel(), nd.ravel())
        self.grids = [ThresholdGrid(p, r, c.n_afc, runs) for p, r in zip(c.prior_um, c.reach_um, strict=True)]
        self.budget = c.max_trials * self.n_f
        self.extra = c.misfit_trials * self.n_f
        cap = self.budget + self.extra
        self.trial_f = np.full((runs, cap), -1)  # per run and trial: frequency index, level, answer
        self.trial_db = np.zeros((runs, cap))
        self.trial_ok = np.zeros((runs, cap), dtype=bool)
        self.trial_s = np.full((runs, cap), -1)  # the joint grid's stimulus (joint phase only)
        self.index = np.zeros(runs, dtype=int)
        self.count = np.zeros((runs, self.n_f), dtype=int)  # trials per frequency
        self.phase = np.full(runs, JOINT)
        self.bump_p = np.full(runs, np.nan)  # P(σ >= BUMP_FOUND_DB) after the joint phase
        self.seeds = [c.seed] * runs if seeds is None else list(seeds)
        self._orders = None
        self._act, self._since = None, 0
        self._bump = None
        self._bump_cache = None

    def curve_db_grid(self) -> np.ndarray:
        """t(f) at every grid point, (n_freq, n_theta)."""
        u = self.u[:, None]
        return self.prior_db[:, None] + self.c[0] + self.c[1] * u + self.c[2] * u * u

    def posterior(self, rows=slice(None)) -> np.ndarray:
        lp = self.log_post[rows]
        # below 1e-30 of the mode: 0 (the mass it drops is < 1e-26; subnormal products are slow)
        p = psychometric.flush(np.exp(lp - lp.max(axis=-1, keepdims=True)), 1e-30)
        return p / p.sum(axis=-1, keepdims=True)

    def planned(self, r: int) -> int:
        return self.budget + (self.extra if self.phase[r] == PER_FREQUENCY or
                              (self.phase[r] == DONE and self.misfit(r)) else 0)

    def misfit(self, r: int) -> bool:
        return bool(self.extra > 0 and self.bump_p[r] > BUMP_FOUND_P)

    # ------------------------------------------------------------------ trials
    def live(self) -> np.ndarray:
        return np.flatnonzero(self.phase != DONE)

    def choose(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(frequency index, level dB) of the next trial of each run in rows (none DONE)."""
        fi = np.empty(rows.size, dtype=int)
        lv = np.empty(rows.size)
        j = self.phase[rows] == JOINT
        if j.any():
            rj = rows[j]
            if self._act is None or self._since >= PRUNE_EVERY:
                lp = self.log_post[rj]
                keep = np.any(lp > lp.max(axis=-1, keepdims=True) - PRUNE_LOG, axis=0)
                self._act = np.flatnonzero(keep)
                self._pa, self._ha = self.p_correct[self._act], self.h[self._act]
                self._since = 0
            self._since += 1
            post = self.posterior(rj)[:, self._act]
            post /= post.sum(axis=-1, keepdims=True)
            info = psychometric.information_flat(post, self._pa, self._ha)
            # only at the frequencies tried least so far: every frequency gets its share of the
            # budget, so that the check can see a bump at any of them
            cnt = self.count[rj][:, self.stim_f]
            info = np.where(cnt == cnt.min(axis=1, keepdims=True), info, -np.inf)
            s = np.argmax(info, axis=-1)
            self.trial_s[rj, self.index[rj]] = s
            fi[j], lv[j] = self.stim_f[s], self.stim_db[s]
        if (~j).any():
            rp = rows[~j]
            widths = np.stack([g.width_db(rows=rp) for g in self.grids], axis=1)  # (rows, n_f)
            fp = np.argmax(widths, axis=1)  # the frequency least known
            lp = np.empty(rp.size)
            for i in np.unique(fp):
                sel = fp == i
                lp[sel] = self.grids[i].stim[self.grids[i].next_index(rp[sel])]
            fi[~j], lv[~j] = fp, lp
        return fi, lv

    def record(self, rows: np.ndarray, fi: np.ndarray, level_db: np.ndarray, correct: np.ndarray) -> None:
        k = self.index[rows]
        self.trial_f[rows, k], self.trial_db[rows, k], self.trial_ok[rows, k] = fi, level_db, correct
        j = self.phase[rows] == JOINT
        if j.any():
            rj = rows[j]
            p = self.p_correct[:, self.trial_s[rj, k[j]]].T  # (rows, n_theta)
            lik = np.where(correct[j][:, None], p, 1.0 - p)
            self.log_post[rj] += np.log(np.clip(lik, 1e-300, None))
            self.log_post[rj] -= self.log_post[rj].max(axis=-1, keepdims=True)
        if (~j).any():  # the fallback's trials inform the joint posterior too (for the final check)
            rp = rows[~j]
            p = psychometric.weibull(level_db[~j][:, None], self._curve[fi[~j]], self.beta,
                                     1.0 / self.cfg.n_afc, self.lapse)
            self.log_post[rp] += np.log(np.clip(np.where(correct[~j][:, None], p, 1.0 - p), 1e-300, None))
            self.log_post[rp] -= self.log_post[rp].max(axis=-1, keepdims=True)
        for i in np.unique(fi):
            sel = fi == i
            self.grids[i].update(rows[sel], level_db[sel], correct[sel])
        self.index[rows] += 1
        np.add.at(self.count, (rows, fi), 1)
        self._advance(rows)

    def _advance(self, rows: np.ndarray) -> None:
        j = rows[self.phase[rows] == JOINT]
        end = j[self.index[j] >= self.budget]
        c = self.cfg
        if c.stop_width_db > 0:
            rest = j[(self.index[j] < self.budget) & (self.index[j] >= 5)]
            if rest.size:
                iv = self.curve_intervals_db(rest)
                narrow = np.all(iv[..., 1] - iv[..., 0] <= c.stop_width_db, axis=1)
                end = np.concatenate([end, rest[narrow]])
        if end.size:  # the check: do the answers call for bumps the curve does not have?
            sds = np.array(BUMP_SD_DB)
            self.bump_p[end] = self.bump_posterior(end)["p_sd"][:, sds >= BUMP_FOUND_DB].sum(axis=1)
            found = (self.bump_p[end] > BUMP_FOUND_P) & (self.extra > 0)
            self.phase[end] = np.where(found, PER_FREQUENCY, DONE)
        p = rows[self.phase[rows] == PER_FREQUENCY]
        self.phase[p[self.index[p] >= self.budget + self.extra]] = DONE

    # ------------------------------------------------------------------ estimates
    def estimates_db(self, rows=slice(None)) -> np.ndarray:
        """Per run and frequency the posterior mean of t(f), the curve with its bumps (runs, n_f)."""
        return self.bump_posterior(rows)["mean_db"]

    def intervals_db(self, rows=slice(None)) -> np.ndarray:
        """(runs, n_f, 2): the central 95 % of t(f)'s posterior, the curve with its bumps."""
        return self.bump_posterior(rows)["interval_db"]

    def curve_intervals_db(self, rows=slice(None), level: float = 0.95) -> np.ndarray:
        """(runs, n_f, 2): the central `level` of the smooth curve's t(f) (the joint grid's posterior,
        no bumps: the stop width's)."""
        if self._orders is None:
            grid = self.curve_db_grid()
            self._orders = [(np.argsort(row), np.sort(row)) for row in grid]
        post = self.posterior(rows)
        q = ((1 - level) / 2, (1 + level) / 2)
        out = np.empty((post.shape[0], self.n_f, 2))
        for i, (o, v) in enumerate(self._orders):
            cdf = np.cumsum(post[:, o], axis=1)
            out[:, i] = [np.interp(q, ci, v) for ci in cdf]
        return out

    # ------------------------------------------------------------------ the bumps' model
    def _bump_tables(self) -> list:
        """Per frequency: the fine grid of t; log P(correct) and log P(wrong) per (level of its
        QUEST+ grid, fine t, nuisance); the bump's kernel per SD; where each joint grid point's
        t(f) falls on the fine grid (the two neighbours and their weights, as a sparse matrix from
        the joint grid to (fine t, nuisance)) and its nuisance (β, δ)."""
        if self._bump is not None:
            return self._bump
        from scipy import sparse

        nb, nd = self._nuisance
        nu = np.array([int(np.flatnonzero((nb == b) & (nd == d))[0]) for b, d in zip(self.beta, self.lapse,
                                                                                       strict=True)])
        n_nu, n_theta = nb.size, nu.size
        out = []
        for i, g in enumerate(self.grids):
            fine = np.arange(g.thresholds[0], g.thresholds[-1] + 1e-9, FINE_STEP_DB)
            p = psychometric.weibull(g.stim[:, None, None], fine[None, :, None], nb, 1.0 / self.cfg.n_afc, nd)
            logp = np.log(np.clip(p, 1e-300, None)), np.log(np.clip(1.0 - p, 1e-300, None))
            d = fine[None, :] - fine[:, None]  # (m, t): t - m
            kern = []
            for sd in BUMP_SD_DB:
                k = np.eye(fine.size) if sd == 0 else np.exp(-0.5 * (d / sd) ** 2)
                kern.append(k / k.sum(axis=1, keepdims=True))
            pos = np.clip((self._curve[i] - fine[0]) / FINE_STEP_DB, 0, fine.size - 1 - 1e-9)
            lo = np.floor(pos).astype(int)
            w = pos - lo
            near = sparse.csr_matrix((np.r_[1.0 - w, w], (np.r_[np.arange(n_theta), np.arange(n_theta)],
                                                        np.r_[lo * n_nu + nu, (lo + 1) * n_nu + nu])),
                                     shape=(n_theta, fine.size * n_nu))
            out.append((fine, logp, np.stack(kern), near))
        self._bump = out
        return out

    def _counts(self, rows: np.ndarray, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Per run of rows, the answers at frequency i: (right, wrong) per level of its QUEST+ grid."""
        g = self.grids[i]
        n = self.trial_f.shape[1]
        f, x, ok = self.trial_f[rows], self.trial_db[rows], self.trial_ok[rows]
        mine = (f == i) & (np.arange(n)[None, :] < self.index[rows][:, None])
        r, k = np.nonzero(mine)
        lv = np.clip(np.rint(x[r, k] - g.stim[0]).astype(int), 0, g.stim.size - 1)
        right = np.zeros((rows.size, g.stim.size))
        wrong = np.zeros((rows.size, g.stim.size))
        np.add.at(right, (r[ok[r, k]], lv[ok[r, k]]), 1.0)
        np.add.at(wrong, (r[~ok[r, k]], lv[~ok[r, k]]), 1.0)
        return right, wrong

    def bump_posterior(self, rows=slice(None)) -> dict:
        """The estimates' posterior: t(f) = the curve (c0, c1, c2) + a bump per frequency, normal of
        SD σ ∈ BUMP_SD_DB (σ marginalised, prior BUMP_PRIOR), one β and δ for all frequencies;
        from every answer. Given the curve, σ, β and δ the frequencies are independent, so the
        grid over (curve, σ, β, δ) takes the bumps integrated out per frequency, on a grid of t
        FINE_STEP_DB fine. Returns per run the posterior of σ (runs, n_sd) and per frequency t's
        mean and central 95 % interval (runs, n_f[, 2])."""
        tables = self._bump_tables()
        rows = np.arange(self.runs)[rows]
        key = (rows.tobytes(), self.index[rows].tobytes())
        if self._bump_cache is not None and self._bump_cache[0] == key:
            return self._bump_cache[1]
        n_r, n_s = rows.size, len(BUMP_SD_DB)
        lj = (self.log_prior[None, None, :] + np.log(np.array(BUMP_PRIOR))[None, :, None]).repeat(n_r, axis=0)
        like, marg = [], []
        for i, (_fine, (logp, logq), kern, near) in enumerate(tables):
            right, wrong = self._counts(rows, i)
            ll = np.einsum("rs,stn->rtn", right, logp) + np.einsum("rs,stn->rtn", wrong, logq)
            lk = np.exp(ll - ll.max(axis=(1, 2), keepdims=True))  # (runs, fine, nuisance): the likelihood
            m = np.matmul(kern[None], lk[:, None])  # (runs, sd, fine, nuisance): the bump integrated
            at = (near @ m.reshape(n_r * n_s, -1).T).T.reshape(n_r, n_s, -1)  # at each grid point's t(f)
            lj += np.log(np.clip(at, 1e-300, None))
            like.append(lk)
            marg.append(m)
        lj -= lj.max(axis=(1, 2), keepdims=True)
        post = np.exp(lj)
        post /= post.sum(axis=(1, 2), keepdims=True)  # (runs, sd, theta)
        mean = np.empty((n_r, self.n_f))
        iv = np.empty((n_r, self.n_f, 2))
        for i, ((fine, _lp, kern, near), lk, m) in enumerate(zip(tables, like, marg, strict=True)):
            w = (near.T @ post.reshape(n_r * n_s, -1).T).T.reshape(m.shape)  # (runs, sd, fine, nuisance)
            with np.errstate(divide="ignore", invalid="ignore"):
                a = np.where(m > 0, w / m, 0.0)
            pt = (np.matmul(np.swapaxes(kern, 1, 2)[None], a).sum(axis=1) * lk).sum(axis=-1)  # (runs, fine)
            pt /= pt.sum(axis=1, keepdims=True)
            mean[:, i] = pt @ fine
            iv[:, i] = psychometric.central_interval(pt, fine, FINE_STEP_DB)  # each t's mass over its cell
        out = {"p_sd": post.sum(axis=2), "mean_db": mean, "interval_db": iv}
        self._bump_cache = (key, out)
        return out

    def trials_per_frequency(self, r: int) -> np.ndarray:
        f = self.trial_f[r, :self.index[r]]
        return np.bincount(f, minlength=self.n_f)


@dataclass
class JointRun:
    """The whole curve at once; next_trial() then answer(trial, chosen interval), in order (the
    Procedure interface, hostd.experiment.procedure)."""

    cfg: ThresholdConfig
    rng: np.random.Generator = field(init=False)
    pending: Trial | None = field(init=False, default=None)

    def __post_init__(self) -> None:
        self.batch = JointBatch(self.cfg)
        self.rng = np.random.default_rng(self.cfg.seed)
        self._rows = np.array([0])
        self._choice = None

    @property
    def index(self) -> int:
        return int(self.batch.index[0])

    @property
    def budget(self) -> int:
        return self.batch.budget

    @property
    def planned_trials(self) -> int:
        return self.batch.planned(0)

    @property
    def done(self) -> bool:
        return self.pending is None and self.batch.phase[0] == DONE

    def next_trial(self) -> Trial | None:
        """The trial to present (the same one again until it is answered)."""
        if self.pending is not None:
            return self.pending
        if self.batch.phase[0] == DONE:
            return None
        fi, lv = self.batch.choose(self._rows)
        i, x = int(fi[0]), float(lv[0])
        self._choice = (fi, lv)
        target = int(self.rng.integers(1, self.cfg.n_afc + 1))
        self.pending = Trial(self.index, self.cfg.frequencies_hz[i], um(x), x, target, self.cfg.n_afc)
        return self.pending

    def answer(self, trial_index: int, chosen: int) -> bool:
        """Record the chosen interval of the pending trial; returns whether it was correct."""
        correct = answered(self.pending, trial_index, chosen)
        fi, lv = self._choice
        self.batch.record(self._rows, fi, lv, np.array([correct]))
        self.pending = None
        return correct

    @property
    def n_per_f(self) -> np.ndarray:
        return self.batch.trials_per_frequency(0)

    def estimates_db(self) -> np.ndarray:
        return self.batch.estimates_db(self._rows)[0]

    def intervals_db(self) -> list[tuple[float, float]]:
        return [(float(lo), float(hi)) for lo, hi in self.batch.intervals_db(self._rows)[0]]

    def results(self) -> list[ThresholdResult]:
        est = self.estimates_db()
        n = self.n_per_f
        out = []
        for i, ((lo, hi), t) in enumerate(zip(self.intervals_db(), est, strict=True)):
            status = "above_reach" if t > self.batch.reach_db[i] else "ok"
            out.append(ThresholdResult(self.cfg.frequencies_hz[i], um(float(t)), um(lo), um(hi),
                                       int(n[i]), self.cfg.reach_um[i], status))
        return out

    def notes(self) -> list[str]:
        p = self.batch.bump_p[0]
        if not np.isfinite(p):
            return []
        fit = (f"P(bumps of SD >= {BUMP_FOUND_DB:g} dB | the joint phase's answers) = {p:.2f}")
        if not self.batch.misfit(0):
            return [f"the answers fit the joint model's smooth curve ({fit}); each threshold is the curve's "
                    "with a bump of its own, and its interval allows for one"]
        extra = self.batch.extra // self.batch.n_f
        return [f"the answers may not fit the joint model's smooth curve ({fit} > {BUMP_FOUND_P:g}): {extra} "
                "more trials per frequency were spent, one QUEST+ per frequency; each threshold is the "
                "curve's with a bump of its own, from every answer"]


def simulate_joint(kind: str, n_afc: int, runs: int, trials_per_frequency: int = JOINT_TRIALS, seed: int = 0,
                   wiggle_db: float = 0.0, reach_um: float = 30.0, misfit_trials: int | None = None) -> dict:
    """`runs` seeded joint runs at once over the shipped b(f)'s frequencies (JointBatch, the
    procedure's own code, one row per run). The observer's curve is the shipped one plus a random
    offset (±8 dB, as the per-frequency bench draws its thresholds), tilt and curvature (±3 dB at
    the range's ends) and, with wiggle_db, an independent normal deviation per frequency (a bump:
    a curve that is not of the model's form); one slope and lapse rate for all frequencies, of
    the observer shape `kind` (observers.SHAPES). Returns per run and frequency the errors
    (estimate - truth, dB) and whether the 95 % interval held the truth; per run the trials and
    whether the check found a misfit."""
    from hostd.experiment.observers import LAPSES, SHAPES, THRESHOLD_SPREAD_DB
    from hostd.perception import thresholds as th

    curve = th.default_curve()
    freqs = [float(f) for f in curve.freq_hz]
    prior = [float(v) for v in curve.threshold_um]
    cfg = ThresholdConfig(freqs, prior, [reach_um] * len(freqs), n_afc=n_afc, max_trials=trials_per_frequency,
                          procedure="joint", misfit_trials=misfit_trials)
    func, (lo, hi) = SHAPES[kind]
    truth = np.empty((runs, len(freqs)))
    slope, lapse, seeds = np.empty(runs), np.empty(runs), np.empty(runs, dtype=np.int64)
    u_f = None
    for r in range(runs):
        rng = np.random.default_rng([seed, r])
        d0 = rng.uniform(-THRESHOLD_SPREAD_DB, THRESHOLD_SPREAD_DB)
        d1, d2 = rng.uniform(-3, 3), rng.uniform(-3, 3)
        if u_f is None:
            lf = np.log10(freqs)
            u_f = (lf - (lf.max() + lf.min()) / 2) / ((lf.max() - lf.min()) / 2)
        truth[r] = np.array([db(p) for p in prior]) + d0 + d1 * u_f + d2 * u_f * u_f
        if wiggle_db > 0:
            truth[r] += rng.normal(0, wiggle_db, len(freqs))
        lapse[r] = rng.uniform(*LAPSES)
        slope[r] = rng.uniform(lo, hi)
        seeds[r] = rng.integers(1 << 31)
    b = JointBatch(cfg, runs, seeds=seeds)
    u = np.random.default_rng(seeds).random((runs, b.budget + b.extra))
    while (rows := b.live()).size:
        fi, lv = b.choose(rows)
        p = psychometric.p_correct(func, lv, truth[rows, fi], slope[rows], 1.0 / n_afc, lapse[rows])
        b.record(rows, fi, lv, u[rows, b.index[rows]] < p)
    bp = b.bump_posterior()
    est, iv = bp["mean_db"], bp["interval_db"]
    return {"errors_db": est - truth, "covered": (iv[..., 0] <= truth) & (truth <= iv[..., 1]),
            "trials": b.index.copy(), "bump_p": b.bump_p.copy(), "p_sd": bp["p_sd"],
            "spent_more": b.index > b.budget,
            "frequencies": len(freqs)}
