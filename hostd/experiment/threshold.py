"""Detection thresholds by QUEST+, nAFC, frequencies interleaved.

Intensities are in dB re 1 µm peak displacement, x = 20 log10(A / 1 µm). The model is
questplus' Weibull on that scale (hostd.experiment.psychometric; slope and lapse per n-AFC:
SLOPES, LAPSE), P(correct) = 1 - δ - (1 - γ - δ) exp(-10^(β (x - t) / 20)),
with γ = 1/n (n-AFC), δ the lapse rate and t the threshold: the displacement at which the
observer detects the stimulus with probability 1 - 1/e (63 %) beyond guessing. Per frequency
the stimulus grid runs from PRIOR_SPAN_DB below the prior (the shipped b(f), or a curve given)
up to the display's reach and never beyond it (hostd.experiment.display: the host refuses
anything above); the threshold grid runs PRIOR_SPAN_DB either side of the prior, so a threshold
above the reach is estimated as such and reported with status "above_reach", never clipped.

A frequency's next level is the one of least expected entropy of t's marginal posterior (the
QUEST+ rule with β and δ as nuisance parameters: psychometric.information). The posterior is a
grid Bayes in numpy (ThresholdGrid: the one questplus.QuestPlus keeps, equal to it to rounding,
which tests/test_experiment_stats.py checks; in numpy so that the bench runs hundreds of runs
at once through the same code). The estimate is the posterior mean of t; its interval the
central 95 % of t's marginal posterior. A frequency stops at its trial budget or, after
min_trials (MIN_TRIALS_WIDTH per n-AFC), when that interval is narrower than stop_width_db. By
default (no budget given) the stop is that width, STOP_WIDTH_DB, within at most MAX_TRIALS
trials: a steep observer's frequency ends at its minimum, a shallow one's takes more (2AFC at a
fixed 30 trials put 75 % of a β = 2 observer's thresholds within ±2 dB; `hostd experiment bench`).
Trials of the frequencies still running are interleaved at random (seeded).
A run is a pure function of (config, seed, answers): resuming replays the answers recorded.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import asdict, dataclass, field

import numpy as np

from hostd.errors import ExperimentError
from hostd.experiment import psychometric
from hostd.experiment.procedure import PROCEDURES

PRIOR_SPAN_DB = 30.0
GRID_STEP_DB = 1.0
# β (dB form, = the Weibull shape in amplitude) and the lapse rate δ of the model: marginalised
# over, as nuisance parameters. The next level minimises the expected entropy of the threshold's
# marginal posterior, not of the whole (t, β, δ) posterior as questplus' next_stim does (that
# spent 2AFC trials on the slope: with it, fixing β = 3 and δ = 0.02 had been the better 2AFC
# model). docs/experiments.md has the figures (`hostd experiment bench`).
SLOPES = {2: (2.0, 3.5, 6.0), 3: (2.0, 3.5, 6.0)}
LAPSE = {2: (0.0, 0.04), 3: (0.0, 0.04)}
PRIOR_SD_DB = 6.0  # the prior on t: normal about the prior curve, 6 dB (0: flat)
# The default stop (no budget given): the 95 % interval this narrow, after at least
# MIN_TRIALS_WIDTH trials and within MAX_TRIALS (docs/experiments.md: `hostd experiment bench`).
STOP_WIDTH_DB = {2: 5.25, 3: 4.5}  # per n-AFC: medians of 38 and 40 trials on the bench's observers
# 3AFC: at least 40, the goal's median, which a narrower width would spend less well (a β = 2
# observer within ±2 dB: 89.5 % at a median of 40 trials, against 88.3 % at 41 with 12 and a
# 4.25-dB width; 1000 runs). 2AFC: 12 (its medians are 38 already).
MIN_TRIALS_WIDTH = {2: 12, 3: 40}
STORED_MIN_TRIALS = 12  # what a session stored without min_trials (an older hostd) stopped after
MAX_TRIALS = 60
JOINT_TRIALS = 15  # the joint procedure's default budget per frequency: half of per-frequency's 30


def db(um: float) -> float:
    return 20.0 * math.log10(um)


def um(x_db: float) -> float:
    return 10.0 ** (x_db / 20.0)


@dataclass
class ThresholdConfig:
    frequencies_hz: list[float]
    prior_um: list[float]  # the prior's centre per frequency (the shipped b(f) by default)
    reach_um: list[float]  # the display's reach per frequency (hostd.experiment.display.Reach)
    n_afc: int = 2
    # per frequency (joint: the joint phase's budget is this x the frequencies). None: the
    # procedure's default, per-frequency MAX_TRIALS with the stop width STOP_WIDTH_DB, joint
    # JOINT_TRIALS (and as many again per frequency when its curve does not fit: joint.py)
    max_trials: int | None = None
    # stop a frequency when its 95 % interval is narrower (0: never; None: STOP_WIDTH_DB when
    # max_trials is None too, else 0), once it has had min_trials (None: MIN_TRIALS_WIDTH)
    stop_width_db: float | None = None
    seed: int = 0
    duration_s: float = 0.5  # each interval's stimulus
    gap_s: float = 0.4  # silence between the intervals
    procedure: str = "per-frequency"  # or "joint": the whole curve at once (hostd.experiment.joint)
    # joint: trials per frequency to spend per frequency when the curve does not fit the joint
    # model (a posterior predictive check; None: max_trials, so the two phases together spend at
    # most the per-frequency budget; 0: never)
    misfit_trials: int | None = None
    min_trials: int | None = None

    @classmethod
    def stored(cls, d: dict) -> ThresholdConfig:
        """The config a session stored (dataclasses.asdict); one stored before min_trials existed
        stopped after STORED_MIN_TRIALS, and replays so."""
        return cls(**{"min_trials": STORED_MIN_TRIALS, **d})

    def __post_init__(self) -> None:
        if self.procedure not in PROCEDURES:
            raise ExperimentError(f"--procedure {self.procedure}: one of {', '.join(PROCEDURES)}")
        if self.n_afc not in (2, 3):
            raise ExperimentError(f"--afc {self.n_afc}: 2 or 3 intervals")
        joint = self.procedure == "joint"
        if self.max_trials is None:
            self.max_trials = JOINT_TRIALS if joint else MAX_TRIALS
            if self.stop_width_db is None:
                self.stop_width_db = 0.0 if joint else STOP_WIDTH_DB.get(self.n_afc, 0.0)
        if self.stop_width_db is None:
            self.stop_width_db = 0.0
        if self.misfit_trials is None:
            self.misfit_trials = self.max_trials if joint else 0
        if self.min_trials is None:
            self.min_trials = MIN_TRIALS_WIDTH[self.n_afc]
        if not 1 <= self.min_trials <= 1000:
            raise ExperimentError(f"--min-trials {self.min_trials}: 1..1000 per frequency")
        if not (math.isfinite(self.stop_width_db) and self.stop_width_db >= 0):
            raise ExperimentError(f"--stop-width-db {self.stop_width_db}: a width in dB >= 0")
        if not 0 <= self.misfit_trials <= 1000:
            raise ExperimentError("misfit trials: 0..1000 per frequency")
        if not self.frequencies_hz:
            raise ExperimentError("no frequencies to measure")
        if len({len(self.frequencies_hz), len(self.prior_um), len(self.reach_um)}) != 1:
            raise ExperimentError("one prior and one reach per frequency")
        for f, p, r in zip(self.frequencies_hz, self.prior_um, self.reach_um, strict=True):
            if not (math.isfinite(f) and f > 0 and math.isfinite(p) and p > 0 and math.isfinite(r) and r > 0):
                raise ExperimentError(f"{f} Hz: frequency, prior and reach must be finite and > 0")
        if not 1 <= self.max_trials <= 1000:
            raise ExperimentError("--trials: 1..1000 per frequency")
        if self.procedure == "joint" and len(self.frequencies_hz) < 3:
            raise ExperimentError("--procedure joint fits a curve over frequency: give at least 3 "
                                  "frequencies")


@dataclass
class ThresholdResult:
    frequency_hz: float
    threshold_um: float
    ci_low_um: float
    ci_high_um: float
    trials: int
    reach_um: float
    status: str  # "ok", or "above_reach": the estimate is above what the display can play

    def as_dict(self) -> dict:
        return asdict(self)


class ThresholdGrid:
    """A batch of per-frequency QUEST+ posteriors over (t, β, δ) on one stimulus grid: one run per
    row (a live frequency is a batch of one; the bench runs hundreds at once). The model is
    psychometric.weibull (questplus' Weibull on the dB scale, as questplus computes it: tests
    check the posterior against questplus'), the rule psychometric.information with β and δ
    as nuisance parameters."""

    def __init__(self, prior_um: float, reach_um: float, n_afc: int, runs: int = 1) -> None:
        centre = db(prior_um)
        top = db(reach_um)
        lo = centre - PRIOR_SPAN_DB
        stim = np.arange(lo, top + 1e-9, GRID_STEP_DB)  # never above the reach
        if stim.size < 2:
            stim = np.array([top - GRID_STEP_DB, top])
        self.stim = stim
        self.thresholds = np.arange(lo, max(centre + PRIOR_SPAN_DB, top + 6.0) + 1e-9, GRID_STEP_DB)
        b, d = np.meshgrid(np.array(SLOPES[n_afc]), np.array(LAPSE[n_afc]), indexing="ij")
        self.slope, self.lapse, self.guess = b.ravel(), d.ravel(), 1.0 / n_afc  # (n_nuisance,)
        self.table = self.likelihood(stim)  # P(correct) per (stimulus, threshold, nuisance)
        prior = np.ones(self.thresholds.size)
        if PRIOR_SD_DB > 0:
            prior = np.exp(-0.5 * ((self.thresholds - centre) / PRIOR_SD_DB) ** 2)
        p0 = np.repeat(prior[:, None], self.slope.size, axis=1)
        self.post = np.repeat((p0 / p0.sum())[None], runs, axis=0)  # (runs, threshold, nuisance)
        self.n = np.zeros(runs, dtype=int)

    def likelihood(self, x_db) -> np.ndarray:
        """P(correct) at the levels x_db (any shape) per (threshold, nuisance): x's shape + 2 axes."""
        x = np.asarray(x_db, dtype=np.float64)[..., None, None]
        return psychometric.weibull(x, self.thresholds[:, None], self.slope, self.guess, self.lapse)

    def next_index(self, rows=slice(None)) -> np.ndarray:
        """Per run of `rows`, the index into stim of the level of most information about t."""
        return np.argmax(psychometric.information(self.post[rows], self.table), axis=-1)

    def update(self, rows, x_db, correct) -> None:
        lik = self.likelihood(x_db)
        p = self.post[rows] * np.where(np.asarray(correct)[..., None, None], lik, 1.0 - lik)
        self.post[rows] = psychometric.flush(p / p.sum(axis=(-2, -1), keepdims=True))
        self.n[rows] += 1

    def marginal(self) -> np.ndarray:
        return self.post.sum(axis=-1)  # (runs, threshold)

    def estimate_db(self) -> np.ndarray:
        m = self.marginal()
        return (m @ self.thresholds) / m.sum(axis=-1)

    def interval_db(self, level: float = 0.95, rows=slice(None)) -> np.ndarray:
        """The central `level` of t's marginal posterior, (runs, 2), each threshold's mass spread
        over its GRID_STEP_DB cell (psychometric.central_interval)."""
        m = self.post[rows].sum(axis=-1)
        return psychometric.central_interval(m, self.thresholds, GRID_STEP_DB, level)

    def width_db(self, level: float = 0.95, rows=slice(None)) -> np.ndarray:
        iv = self.interval_db(level, rows)
        return iv[:, 1] - iv[:, 0]


class Staircase:
    """One frequency's QUEST+: a ThresholdGrid of one run."""

    def __init__(self, frequency_hz: float, prior_um: float, reach_um: float, n_afc: int) -> None:
        self.frequency_hz = frequency_hz
        self.reach_um = reach_um
        self.grid = ThresholdGrid(prior_um, reach_um, n_afc)
        self.stim = self.grid.stim
        self.thresholds = self.grid.thresholds

    @property
    def n(self) -> int:
        return int(self.grid.n[0])

    def next_db(self) -> float:
        """The level that minimises the expected entropy of the threshold's marginal posterior
        (questplus' own rule, `qp.next_stim`, minimises that of the whole (t, β, δ) posterior and
        so spends trials on the slope and lapse, which only the threshold's estimate needs as
        nuisance parameters)."""
        return float(self.stim[int(self.grid.next_index()[0])])

    def update(self, x_db: float, correct: bool) -> None:
        self.grid.update(slice(None), np.array([float(x_db)]), np.array([bool(correct)]))

    def marginal(self) -> np.ndarray:
        return self.grid.marginal()[0]

    def estimate_db(self) -> float:
        return float(self.grid.estimate_db()[0])

    def interval_db(self, level: float = 0.95) -> tuple[float, float]:
        lo, hi = self.grid.interval_db(level)[0]
        return float(lo), float(hi)

    def result(self) -> ThresholdResult:
        t = self.estimate_db()
        lo, hi = self.interval_db()
        status = "above_reach" if t > db(self.reach_um) else "ok"
        return ThresholdResult(self.frequency_hz, um(t), um(lo), um(hi), self.n, self.reach_um, status)


@dataclass
class Trial:
    """One nAFC trial: the frequency, the level, the interval (1..n) holding the stimulus."""

    index: int
    frequency_hz: float
    amplitude_um: float
    level_db: float
    target: int  # 1..n_afc
    n_afc: int

    def as_dict(self) -> dict:
        return asdict(self)


def answered(t: Trial | None, trial_index: int, chosen: int) -> bool:
    """Whether `chosen` is the pending trial `t`'s target: ExperimentError (one line) for an answer
    to another trial than the one presented or an interval outside 1..n_afc."""
    if t is None or t.index != trial_index:
        raise ExperimentError(f"answer to trial {trial_index}, but trial "
                              f"{'none' if t is None else t.index} is the one presented")
    if not 1 <= chosen <= t.n_afc:
        raise ExperimentError(f"answer {chosen}: choose an interval 1..{t.n_afc}")
    return chosen == t.target


@dataclass
class ThresholdRun:
    """Interleaved staircases; next_trial() then answer(trial, chosen interval), in order."""

    cfg: ThresholdConfig
    stairs: list[Staircase] = field(init=False)
    rng: np.random.Generator = field(init=False)
    index: int = field(init=False, default=0)
    pending: Trial | None = field(init=False, default=None)

    def __post_init__(self) -> None:
        c = self.cfg
        self.stairs = [Staircase(f, p, r, c.n_afc)
                       for f, p, r in zip(c.frequencies_hz, c.prior_um, c.reach_um, strict=True)]
        self.rng = np.random.default_rng(c.seed)

    def running(self) -> list[int]:
        out = []
        for i, s in enumerate(self.stairs):
            if s.n >= self.cfg.max_trials:
                continue
            if self.cfg.stop_width_db > 0 and s.n >= self.cfg.min_trials:
                lo, hi = s.interval_db()
                if hi - lo <= self.cfg.stop_width_db:
                    continue
            out.append(i)
        return out

    @property
    def done(self) -> bool:
        return self.pending is None and not self.running()

    @property
    def planned_trials(self) -> int:
        return self.cfg.max_trials * len(self.stairs)

    def next_trial(self) -> Trial | None:
        """The trial to present (the same one again until it is answered)."""
        if self.pending is not None:
            return self.pending
        live = self.running()
        if not live:
            return None
        i = live[int(self.rng.integers(len(live)))]
        x = self.stairs[i].next_db()
        target = int(self.rng.integers(1, self.cfg.n_afc + 1))
        self.pending = Trial(self.index, self.stairs[i].frequency_hz, um(x), x, target, self.cfg.n_afc)
        return self.pending

    def answer(self, trial_index: int, chosen: int) -> bool:
        """Record the chosen interval of the pending trial; returns whether it was correct."""
        t = self.pending
        correct = answered(t, trial_index, chosen)
        i = self.cfg.frequencies_hz.index(t.frequency_hz)
        self.stairs[i].update(t.level_db, correct)
        self.pending = None
        self.index += 1
        return correct

    def results(self) -> list[ThresholdResult]:
        return [s.result() for s in self.stairs]

    def notes(self) -> list[str]:
        return []


def thresholds_csv(results: list[ThresholdResult], provenance: str = "") -> str:
    """The thresholds CSV every `--thresholds` reads as-is (columns by name; the interval and
    the counts are extra columns). A frequency whose threshold is above the display's reach is
    a comment line saying so, not a row: it is not clipped into the curve."""
    out = io.StringIO()
    out.write("# Detection thresholds measured with hostd experiment threshold (QUEST+, Weibull):\n")
    out.write("# threshold_um = posterior mean, ci_*_um = central 95 % of the posterior, µm peak.\n")
    if provenance:
        for line in provenance.splitlines():
            out.write(f"# {line}\n")
    for r in results:
        if r.status != "ok":
            out.write(f"# {r.frequency_hz:g} Hz: ABOVE THE DISPLAY'S REACH: estimate {r.threshold_um:.4g} µm "
                      f"(95 % {r.ci_low_um:.4g}..{r.ci_high_um:.4g}) > reach {r.reach_um:.4g} µm; "
                      "not in the curve\n")
    w = csv.writer(out, lineterminator="\n")
    w.writerow(["frequency_hz", "threshold_um", "ci_low_um", "ci_high_um", "trials", "reach_um"])
    for r in results:
        if r.status == "ok":
            w.writerow([f"{r.frequency_hz:g}", f"{r.threshold_um:.6g}", f"{r.ci_low_um:.6g}",
                        f"{r.ci_high_um:.6g}", r.trials, f"{r.reach_um:.6g}"])
    return out.getvalue()
