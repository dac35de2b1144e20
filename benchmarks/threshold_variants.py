"""Variants of the per-frequency threshold procedure on the bench's simulated observers
(docs/experiments.md, "What changed and what was tried").

    python -m benchmarks.threshold_variants [--runs N] [--seed S] [--afc 2] [VARIANT ...]

A numpy copy of hostd.experiment.threshold.Staircase (questplus' Weibull on the dB scale, the
same grids and prior) whose rule, grids and estimator can be varied; with the shipped settings
it gives the same estimates as the procedure (`--check`: the largest difference over 10 runs
per case, ~1e-14 dB), a hundred times faster, so that thousands of runs can tell variants
apart. Same seeds, same observers and answers' random numbers as `hostd experiment bench`."""

from __future__ import annotations

import argparse

import numpy as np

from hostd.experiment.observers import observers
from hostd.experiment.threshold import GRID_STEP_DB, PRIOR_SD_DB, PRIOR_SPAN_DB, db

M = {"slopes": (2.0, 3.5, 6.0), "lapses": (0.0, 0.04)}
VARIANTS = {
    "shipped": dict(M, rule="threshold"),  # the procedure today
    "questplus-rule": dict(M, rule="all"),  # questplus' next_stim: entropy of (t, β, δ)
    "fixed-b3-d.02": dict(slopes=(3.0,), lapses=(0.02,), rule="all"),  # 2AFC before the change
    "fixed-b3-d.04": dict(slopes=(3.0,), lapses=(0.04,), rule="all"),
    "fixed-b3-d.02-prior10": dict(slopes=(3.0,), lapses=(0.02,), rule="all", prior_sd=10.0),
    "fixed-b3-d.02-flat": dict(slopes=(3.0,), lapses=(0.02,), rule="all", prior_sd=0.0),
    "variance": dict(M, rule="variance"),
    "lapse-0-.02-.05": dict(M, rule="threshold", lapses=(0.0, 0.02, 0.05)),
    "window-estimate": dict(M, rule="threshold", estimate="window"),
}


def _entropy(m: np.ndarray) -> np.ndarray:
    """Σ over the last axis of -m log(m / Σ m): P(answer) H(t | answer) from joint masses."""
    tot = m.sum(axis=-1, keepdims=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        return -np.sum(np.where(m > 0, m * np.log(m / tot), 0.0), axis=-1)


class Copy:
    def __init__(self, centre_db: float, top_db: float, n_afc: int, slopes=M["slopes"], lapses=M["lapses"],
                 rule: str = "threshold", prior_sd: float = PRIOR_SD_DB, estimate: str = "mean") -> None:
        lo = centre_db - PRIOR_SPAN_DB
        self.stim = np.arange(lo, top_db + 1e-9, GRID_STEP_DB)
        self.t = np.arange(lo, max(centre_db + PRIOR_SPAN_DB, top_db + 6.0) + 1e-9, GRID_STEP_DB)
        b, d = np.array(slopes)[None, None, :, None], np.array(lapses)[None, None, None, :]
        g = 1.0 / n_afc
        self.p = 1 - d - (1 - g - d) * np.exp(-(10 ** (b * (self.stim[:, None, None, None]
                                                              - self.t[None, :, None, None]) / 20)))
        pt = np.exp(-0.5 * ((self.t - centre_db) / prior_sd) ** 2) if prior_sd > 0 else np.ones(self.t.size)
        post = np.broadcast_to(pt[:, None, None], self.p.shape[1:]).copy()
        self.post = post / post.sum()
        self.rule, self.estimate_kind = rule, estimate

    def next_db(self) -> float:
        jc = self.post[None] * self.p
        ji = self.post[None] - jc
        if self.rule == "all":
            eh = _entropy(jc.reshape(len(self.stim), -1)) + _entropy(ji.reshape(len(self.stim), -1))
        else:
            mc, mi = jc.sum(axis=(2, 3)), ji.sum(axis=(2, 3))
            if self.rule == "threshold":
                eh = _entropy(mc) + _entropy(mi)
            else:  # expected variance of t's marginal
                eh = np.zeros(len(self.stim))
                for m in (mc, mi):
                    tot = m.sum(axis=1)
                    mean = m @ self.t / tot
                    eh += m @ self.t ** 2 - tot * mean ** 2
        return float(self.stim[int(np.argmin(eh))])

    def update(self, x_db: float, correct: bool) -> None:
        p = self.p[int(np.argmin(np.abs(self.stim - x_db)))]
        self.post = self.post * (p if correct else 1 - p)
        self.post /= self.post.sum()

    def estimate_db(self) -> float:
        m = self.post.sum(axis=(1, 2))
        if self.estimate_kind == "mean":
            return float(m @ self.t)
        # the level that maximises the posterior mass within ±2 dB
        edges = np.concatenate([self.t - GRID_STEP_DB / 2, [self.t[-1] + GRID_STEP_DB / 2]])
        cdf = np.concatenate([[0.0], np.cumsum(m)])
        fine = np.arange(self.t[0], self.t[-1], 0.1)
        mass = np.interp(fine + 2, edges, cdf) - np.interp(fine - 2, edges, cdf)
        return float(fine[mass >= mass.max() - 1e-12].mean())


def simulate(kind: str, n_afc: int, runs: int, seed: int, max_trials: int = 30, centre_um: float = 0.1,
             reach_um: float = 30.0, **variant) -> np.ndarray:
    """observers.simulate_thresholds with the copy in place of the procedure."""
    obs, seeds = observers(kind, runs, seed, db(centre_um), n_afc)
    u = np.random.default_rng(seeds).random((runs, max_trials))  # simulate_threshold_runs' numbers
    errs = np.empty(runs)
    for r, o in enumerate(obs):
        s = Copy(db(centre_um), db(reach_um), n_afc, **variant)
        for k in range(max_trials):
            x = s.next_db()
            s.update(x, u[r, k] < o.p_correct(x))
        errs[r] = s.estimate_db() - o.threshold_db
    return errs


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("variants", nargs="*", default=["shipped"], metavar="VARIANT",
                    help=f"of: {', '.join(VARIANTS)} (default shipped)")
    ap.add_argument("--runs", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=99)
    ap.add_argument("--afc", type=int, choices=[2, 3], default=2)
    ap.add_argument("--check", action="store_true", help="compare the copy with the procedure first")
    a = ap.parse_args()
    for v in a.variants:
        if v not in VARIANTS:
            ap.error(f"{v}: a variant of {', '.join(VARIANTS)}")
    if a.check:
        from hostd.experiment.observers import simulate_thresholds

        for kind in ("weibull", "logistic"):
            for n in (2, 3):
                d = np.max(np.abs(simulate(kind, n, 10, 2026, **VARIANTS["shipped"])
                                  - simulate_thresholds(kind, n, 10, 30, seed=2026)))
                print(f"copy vs procedure, {n}AFC {kind}: largest difference {d:.1e} dB")
                if not d < 1e-9:
                    return 1
    for v in a.variants:
        for kind in ("weibull", "logistic"):
            e = simulate(kind, a.afc, a.runs, a.seed, **VARIANTS[v])
            print(f"{v:<22} {a.afc}AFC {kind:<8} within ±2 dB: {np.mean(np.abs(e) <= 2):.1%}  "
                  f"bias {np.mean(e):+.2f} dB  90th pct |error| {np.percentile(np.abs(e), 90):.2f} dB  "
                  f"({a.runs} runs, seed {a.seed})", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
