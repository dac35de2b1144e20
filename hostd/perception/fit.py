"""Fitting (a, b) of Iobj = a Ip + b Ia to subjective dissimilarity scores (paper eq. 13-15).

Least squares without intercept, as in the paper, optionally constrained to a, b >= 0. For
each of Iobj, Ip and Ia we report two different numbers, named so they are not confused:
  r2_pearson  the squared Pearson correlation between the index and the scores (what the
              paper calls "R^2 between" an index and the subjective dissimilarities);
  r2_fit      the coefficient of determination 1 - SS_res / SS_tot of the no-intercept
              least-squares fit of the scores by that index (Ip, Ia alone: one weight each).
"""

from __future__ import annotations

import csv
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import scipy.optimize

from hostd.errors import FitError, ScoresNotFound
from hostd.texture import synth

REQUIRED = ("texture", "method", "level", "score")


@dataclass
class Stimulus:
    texture: str
    method: str
    level: str
    score: float
    Ip: float
    Ia: float
    excluded: str = ""
    n: int | None = None  # answers averaged into the score (the scores CSV's optional n column)


@dataclass
class FitResult:
    a: float
    b: float
    nonnegative: bool
    n_used: int
    excluded: list[dict] = field(default_factory=list)
    metrics: dict[str, dict[str, float]] = field(default_factory=dict)
    se_a: float | None = None  # standard errors of the unconstrained least-squares fit
    se_b: float | None = None
    ci_a: tuple[float, float] | None = None  # residual bootstrap-t intervals (ci_level)
    ci_b: tuple[float, float] | None = None
    ci_level: float = 0.95
    warnings: list[str] = field(default_factory=list)
    # w ± t(0.975, dof) se, beside the bootstrap's (simulated labs of 13 stimuli: about as
    # calibrated, slightly wider; docs/experiments.md). None without standard errors or with
    # --nonnegative (the se are the unconstrained fit's).
    t_interval_a: tuple[float, float] | None = None
    t_interval_b: tuple[float, float] | None = None
    # the coverage and bias of these intervals on this design, by simulation (design_coverage)
    design: dict | None = None

    def as_dict(self) -> dict:
        return {
            "a": self.a, "b": self.b, "nonnegative": self.nonnegative, "n_used": self.n_used,
            "se_a": self.se_a, "se_b": self.se_b,
            "ci_a": list(self.ci_a) if self.ci_a else None,
            "ci_b": list(self.ci_b) if self.ci_b else None, "ci_level": self.ci_level,
            "t_interval_a": list(self.t_interval_a) if self.t_interval_a else None,
            "t_interval_b": list(self.t_interval_b) if self.t_interval_b else None,
            "warnings": self.warnings, "design": self.design,
            "excluded": self.excluded, "metrics": self.metrics,
            "legend": {
                "r2_pearson": "squared Pearson correlation of index and scores (the paper's R^2)",
                "r2_fit": "coefficient of determination of the no-intercept least-squares fit",
            },
        }


def pearson_r2(x: np.ndarray, y: np.ndarray) -> float:
    """Squared Pearson correlation; x and y are first scaled by their largest magnitude (so
    indices of order 1e-13 or 1e200 give the same r^2 as of order 1). NaN when one is constant."""
    x = _unit_scaled(x)
    y = _unit_scaled(y)
    x = x - x.mean()
    y = y - y.mean()
    den = math.sqrt(float(x @ x) * float(y @ y))
    if den == 0:
        return float("nan")
    return min(1.0, (float(x @ y) / den) ** 2)


def _unit_scaled(v: np.ndarray) -> np.ndarray:
    m = float(np.max(np.abs(v))) if v.size else 0.0
    return v / m if m > 0 else v


def r2_fit(pred: np.ndarray, y: np.ndarray) -> float:
    ss_tot = float(((y - y.mean()) ** 2).sum())
    return 1.0 - float(((y - pred) ** 2).sum()) / ss_tot


MIN_PER_PARAMETER = 5  # fewer stimuli per fitted weight than this: a warning
# Rank and conditioning are judged on the columns scaled to unit size (so only the angle
# between Ip and Ia matters, not their magnitude): Ip and Ia count as collinear when the
# smaller singular value is <= RANK_RTOL times the larger; above COND_WARN the fit is made
# but warned about (its weights are then sensitive to the scores' last digits).
RANK_RTOL = 1e-12
COND_WARN = 1e6


@dataclass(frozen=True)
class _Design:
    """X = [Ip, Ia] with each column divided by its largest magnitude: X = Xs diag(norms)."""

    Xs: np.ndarray
    norms: np.ndarray
    sv: np.ndarray  # singular values of Xs, descending

    @property
    def cond(self) -> float:
        return float(self.sv[0] / self.sv[-1]) if self.sv[-1] > 0 else math.inf

    @property
    def rank(self) -> int:
        return int(np.count_nonzero(self.sv > RANK_RTOL * self.sv[0])) if self.sv[0] > 0 else 0


def _design(X: np.ndarray) -> _Design:
    norms = np.max(np.abs(X), axis=0)  # largest magnitude per column (2-norm within sqrt(n))
    norms = np.where(norms > 0, norms, 1.0)
    Xs = X / norms
    return _Design(Xs, norms, np.linalg.svd(Xs, compute_uv=False))


def _solve(X: np.ndarray, y: np.ndarray, nonnegative: bool) -> np.ndarray:
    """Least squares on the unit-scaled columns (SVD, relative cut-off RANK_RTOL), unscaled."""
    d = _design(X)
    if nonnegative:
        w = scipy.optimize.nnls(d.Xs, y)[0]
    else:
        w = np.linalg.lstsq(d.Xs, y, rcond=RANK_RTOL)[0]
    return w / d.norms


def standard_errors(X: np.ndarray, y: np.ndarray, w: np.ndarray,
                    dof: int | None = None) -> tuple[float, float] | None:
    """Standard errors of the no-intercept least-squares weights w:
    se_j = sqrt(s^2 [(X^T X)^-1]_jj), s^2 = sum (y - X w)^2 / dof (dof = n - p by default).

    (X^T X)^-1 is taken from the SVD of the unit-scaled columns, V S^-2 V^T, whose diagonal is a
    sum of squares (never negative, unlike an explicit inverse of an ill-conditioned X^T X).
    None when dof <= 0 or X is rank-deficient."""
    n, p = X.shape
    dof = n - p if dof is None else dof
    if dof <= 0:
        return None
    d = _design(X)
    if d.rank < p:
        return None
    _, sv, vt = np.linalg.svd(d.Xs, full_matrices=False)
    s2 = float(((y - X @ w) ** 2).sum()) / dof
    diag = np.sum(np.square(vt.T / sv), axis=1)  # diag of (Xs^T Xs)^-1
    se = np.sqrt(s2 * diag) / d.norms
    return float(se[0]), float(se[1])


def bootstrap_intervals(X: np.ndarray, y: np.ndarray, nonnegative: bool, n_boot: int = 2000,
                        level: float = 0.95, seed: int = 0):
    """Intervals of (a, b) from a residual bootstrap: n_boot sets of scores X w + r*, r* drawn with
    replacement from the fit's centred residuals scaled by sqrt(n / (n - 2)), the design X kept.

    Unconstrained: studentized (bootstrap-t), w - q(1 - α/2) se .. w - q(α/2) se, q the quantiles
    of (w* - w) / se* and se the classical standard error; with `nonnegative`, the percentiles of
    the NNLS weights w*. None with fewer than 3 stimuli.

    Why not resample the stimuli (the case bootstrap hostd used before): the scores are means of
    grades rounded and clipped to the scale, so near its bottom (small Ip, Ia, the control) the
    mean is pulled up and the linear model's misfit sits on the low-leverage stimuli. A case
    bootstrap estimates the sandwich variance, which weights each residual by its leverage and so
    misses that misfit; with 13 stimuli it also shrinks by (n - 2) / n and uses normal quantiles.
    In 50 simulated labs per grade noise 0.3 / 0.5 / 0.8 it covered both weights in 94 / 80 / 96 %,
    this one in 98 / 94 / 100 % (docs/experiments.md, `hostd experiment bench --runs 0`)."""
    n = X.shape[0]
    if n < 3:
        return None
    d = _design(X)
    if d.rank < 2:
        return None
    rng = np.random.default_rng(seed)
    w = _solve(X, y, nonnegative) * d.norms  # weights of the unit-scaled columns
    r = y - d.Xs @ w
    r = (r - r.mean()) * math.sqrt(n / (n - 2))
    ystar = d.Xs @ w + r[rng.integers(0, n, (n_boot, n))]  # (n_boot, n)
    lo_q, hi_q = 100 * (1 - level) / 2, 100 * (1 + level) / 2
    if nonnegative:
        e = np.array([scipy.optimize.nnls(d.Xs, yi)[0] for yi in ystar]) / d.norms
        return (tuple(float(v) for v in np.percentile(e[:, 0], [lo_q, hi_q])),
                tuple(float(v) for v in np.percentile(e[:, 1], [lo_q, hi_q])))
    _, sv, vt = np.linalg.svd(d.Xs, full_matrices=False)
    pinv = (vt.T / sv**2) @ vt @ d.Xs.T  # (Xs^T Xs)^-1 Xs^T
    diag = np.sum(np.square(vt.T / sv), axis=1)
    wu = np.linalg.lstsq(d.Xs, y, rcond=RANK_RTOL)[0]
    se = np.sqrt(float(((y - d.Xs @ wu) ** 2).sum()) / (n - 2) * diag)
    wstar = ystar @ pinv.T  # (n_boot, 2)
    res = ystar - wstar @ d.Xs.T
    sestar = np.sqrt(np.sum(res**2, axis=1, keepdims=True) / (n - 2) * diag)
    ok = np.all(sestar > 0, axis=1)
    if np.count_nonzero(ok) < n_boot // 2 or not np.all(se > 0):
        return None
    tstar = (wstar[ok] - wu) / sestar[ok]
    q_lo, q_hi = np.percentile(tstar, [lo_q, hi_q], axis=0)
    lo = (wu - q_hi * se) / d.norms
    hi = (wu - q_lo * se) / d.norms
    return (float(lo[0]), float(hi[0])), (float(lo[1]), float(hi[1]))


COVERAGE_WARN = 0.90  # a design whose simulated 95 % intervals cover both weights less often: a warning
DESIGN_SIMS = 100  # per noise level


def design_coverage(ip, ia, a: float, b: float, noise_sd: float, answers: int | None = None, *,
                    sims: int = DESIGN_SIMS, n_boot: int = 500, seed: int = 0,
                    scale: tuple[float, float] | None = (0.0, 3.0), nonnegative: bool = False) -> dict:
    """The coverage and bias of the intervals fit() states, on this design, by simulation: `sims`
    labs whose scores follow Iobj = a Ip + b Ia exactly, fitted as fit() fits them.

    With `answers`, each stimulus' score is the mean of that many grades a Ip + b Ia + N(0,
    noise_sd), rounded to the scale's integers and clipped to it (the paper's 0..3 grades: near
    the scale's bottom the mean is pulled up, which biases the weights); without, the score is
    a Ip + b Ia + N(0, noise_sd), clipped to the scale when one is given. Lab s draws from the
    generator seeded [seed, s]. Returns the share of labs whose interval held a, b and both,
    the mean estimates' bias, the intervals' mean widths, and the same coverage for the t
    interval of the standard errors."""
    ip = np.asarray(ip, dtype=np.float64)
    ia = np.asarray(ia, dtype=np.float64)
    X = np.column_stack([ip, ia])
    true = a * ip + b * ia
    n = ip.size
    cov = np.zeros(3)
    est, widths = [], []
    t_both, t_width, done = 0, [], 0
    import scipy.stats

    for s in range(sims):
        rng = np.random.default_rng([seed, s])
        if answers:
            y = np.rint(true[None, :] + rng.normal(0, noise_sd, (answers, n)))
            if scale is not None:
                y = np.clip(y, *scale)
            y = y.mean(axis=0)
        else:
            y = true + rng.normal(0, noise_sd, n)
            if scale is not None:
                y = np.clip(y, *scale)
        if np.ptp(y) == 0:
            continue
        w = _solve(X, y, nonnegative)
        ci = bootstrap_intervals(X, y, nonnegative, n_boot)
        if ci is None:
            continue
        done += 1
        ca = ci[0][0] <= a <= ci[0][1]
        cb = ci[1][0] <= b <= ci[1][1]
        cov += (ca, cb, ca and cb)
        est.append(w)
        widths.append((ci[0][1] - ci[0][0], ci[1][1] - ci[1][0]))
        se = standard_errors(X, y, w)
        if se and not nonnegative:
            k = float(scipy.stats.t.ppf(0.975, n - 2))
            t_both += abs(w[0] - a) <= k * se[0] and abs(w[1] - b) <= k * se[1]
            t_width.append(2 * k * se[0])
    if not done:
        return {"sims": 0}
    e = np.mean(est, axis=0)
    wd = np.mean(widths, axis=0)
    return {"sims": done, "coverage_a": cov[0] / done, "coverage_b": cov[1] / done,
            "coverage_both": cov[2] / done, "bias_a": float(e[0] - a), "bias_b": float(e[1] - b),
            "mean_width_a": float(wd[0]), "mean_width_b": float(wd[1]), "stimuli": n,
            "answers_per_stimulus": answers, "noise_sd": noise_sd,
            "se_t_interval_coverage_both": t_both / done,
            "se_t_interval_mean_width_a": float(np.mean(t_width)) if t_width else None}


GRADE_NOISE_SDS = (0.15, 0.3, 0.5, 0.8)  # per answer: what mean scores cannot tell apart


def design_check(ip, ia, a: float, b: float, answers: int | None, noises, *, scale=(0.0, 3.0),
                 sims: int = DESIGN_SIMS, nonnegative: bool = False) -> tuple[dict, str | None]:
    """design_coverage() of this design at (a, b) for each noise SD of `noises`: the worst case
    (with every case under by_noise) and a warning when it covers both weights less often than
    COVERAGE_WARN."""
    cases = [design_coverage(ip, ia, a, b, sd, answers, sims=sims, scale=scale, nonnegative=nonnegative)
             for sd in noises if sd > 0]
    cases = [d for d in cases if d.get("sims")]
    if not cases:
        return {"sims": 0}, None
    d = dict(min(cases, key=lambda c: c["coverage_both"]))
    d["by_noise"] = [{k: c[k] for k in ("noise_sd", "coverage_both", "bias_a", "bias_b")} for c in cases]
    if d["coverage_both"] >= COVERAGE_WARN:
        return d, None
    return d, (f"on this design the 95 % intervals of (a, b) held both true weights in only "
               f"{d['coverage_both']:.0%} of {d['sims']} simulated labs (a {d['coverage_a']:.0%}, "
               f"b {d['coverage_b']:.0%}; bias a {d['bias_a']:+.3f}, b {d['bias_b']:+.3f}; at (a, b) = "
               f"({a:.3g}, {b:.3g}) and noise {d['noise_sd']:.2f}"
               + (f" per answer, {answers} answers per stimulus)" if answers else " per score)")
               + ": trust them less, or add stimuli (levels away from the scale's bottom, both methods)")


def _design_check(used: list[Stimulus], X: np.ndarray, y: np.ndarray, a: float, b: float, nonnegative: bool,
                  scale: tuple[float, float] | None, sims: int) -> tuple[dict, str | None]:
    """design_check() at the fitted (a, b). With every stimulus' answer count known, grades are
    simulated at each per-answer noise of GRADE_NOISE_SDS (mean scores do not tell the per-answer
    noise from the misfit of the rounded grades, and the rounding's bias depends on it); else the
    scores themselves, with this fit's residual SD."""
    counts = [s.n for s in used]
    answers = int(np.median(counts)) if all(c for c in counts) else None
    if answers:
        noises = GRADE_NOISE_SDS
    else:
        noises = (math.sqrt(float(((y - X @ [a, b]) ** 2).sum()) / max(len(used) - 2, 1)),)
    return design_check(X[:, 0], X[:, 1], a, b, answers, noises, scale=scale, sims=sims,
                        nonnegative=nonnegative)


def check_scale(stimuli: list[Stimulus], scale_min: float, scale_max: float) -> None:
    """Scores must lie on the rating scale [scale_min, scale_max]."""
    for s in stimuli:
        if not (scale_min <= s.score <= scale_max):
            raise FitError(f"{s.texture} {s.method} {s.level}: score {s.score} is outside the "
                           f"rating scale {scale_min:g}..{scale_max:g}: fix the score, or set "
                           "--scale-min/--scale-max")


def check_indices(stimuli: list[Stimulus]) -> None:
    """Ip and Ia are relative errors: finite and >= 0 (a negative one is a wrong column)."""
    for s in stimuli:
        for name in ("Ip", "Ia"):
            v = getattr(s, name)
            if not math.isfinite(v):
                raise FitError(f"{s.texture} {s.method} {s.level}: {name} is {v}; give a finite "
                               "number")
            if v < 0:
                raise FitError(f"{s.texture} {s.method} {s.level}: {name} = {v:g} is negative, but "
                               f"{name} is a relative error (>= 0): check the column")


def fit(stimuli: list[Stimulus], *, nonnegative: bool = False,
        scale_max: float | None = None, exclude_saturated: bool = False,
        scale_min: float | None = None, n_boot: int = 2000, design_sims: int = DESIGN_SIMS) -> FitResult:
    """Fit Iobj = a Ip + b Ia to the scores by least squares without intercept (eq. 13-15).

    Stimuli with a mean score at scale_max are excluded when asked (flagged). Scores outside
    [scale_min, scale_max] are refused (when the scale is given); negative or non-finite Ip,
    Ia are refused. The solve is an SVD of the columns scaled to unit size, so Ip or Ia of any
    magnitude fit alike; Ip and Ia collinear within RANK_RTOL are refused, a condition number
    above COND_WARN is warned about. Returns (a, b), their standard errors (unconstrained fit;
    None when the stimuli have no distinct rows to spare) and residual bootstrap-t intervals
    (2000 resamples, seeded: reproducible; bootstrap_intervals says why this bootstrap), and
    warnings (fewer than 5 stimuli per fitted weight, ill-conditioning, repeated stimuli, and
    intervals that cover the weights less than COVERAGE_WARN on this design: with intervals,
    design_sims labs are simulated from the fitted weights on this design, `design`).
    """
    if scale_max is not None:
        check_scale(stimuli, -math.inf if scale_min is None else scale_min, scale_max)
    for s in stimuli:
        if exclude_saturated and scale_max is not None and s.score >= scale_max:
            s.excluded = f"saturated: mean score {s.score} at the top of the scale ({scale_max})"
    used = [s for s in stimuli if not s.excluded]
    if len(used) < 2:
        raise FitError(f"need at least 2 stimuli to fit (a, b), have {len(used)}")
    y = np.array([s.score for s in used])
    if not np.all(np.isfinite(y)):
        raise FitError("a score value is NaN or Inf")
    check_indices(used)
    ip = np.array([s.Ip for s in used])
    ia = np.array([s.Ia for s in used])
    if np.ptp(y) == 0:
        raise FitError("every score is equal: nothing to explain; check the scores column")
    X = np.column_stack([ip, ia])
    design = _design(X)
    if design.rank < 2:
        raise FitError("Ip and Ia are collinear (or zero) over these stimuli: (a, b) is not "
                       "identifiable; add stimuli from both methods")
    a, b = (float(v) for v in _solve(X, y, nonnegative))
    metrics = {}
    for name, pred, x in (("Iobj", X @ [a, b], a * ip + b * ia), ("Ip", None, ip), ("Ia", None, ia)):
        if pred is None:
            w = float(_solve(x[:, None], y, nonnegative)[0]) if np.any(x) else 0.0
            pred = w * x
        metrics[name] = {"r2_pearson": pearson_r2(x, y), "r2_fit": r2_fit(pred, y)}
    for m in metrics.values():
        for k, v in m.items():
            if not math.isfinite(v):
                m[k] = None  # an index that is constant over the stimuli has no correlation
    excluded = [{"texture": s.texture, "method": s.method, "level": s.level, "why": s.excluded}
                for s in stimuli if s.excluded]
    warns = []
    distinct = len({(float(p), float(q)) for p, q in X})
    if distinct < len(used):
        warns.append(f"only {distinct} distinct (Ip, Ia) rows among {len(used)} stimuli: repeats of "
                     "one stimulus are not independent evidence, so the standard errors count "
                     "each distinct row once"
                     + (" and are not available (no degrees of freedom left)" if distinct <= 2
                        else f" ({distinct - 2} degrees of freedom)"))
    se = standard_errors(X, y, np.array([a, b]), dof=distinct - 2)
    if design.cond > COND_WARN:
        warns.append(f"Ip and Ia are nearly collinear over these stimuli (condition number "
                     f"{design.cond:.1e} of the unit-scaled columns): (a, b) are poorly determined; "
                     "add stimuli that separate the two indices (both methods, several levels)")
    ci = bootstrap_intervals(X, y, nonnegative, n_boot) if n_boot else None
    if len(used) < 2 * MIN_PER_PARAMETER:
        warns.append(f"only {len(used)} stimuli for 2 weights (fewer than {MIN_PER_PARAMETER} per "
                     "parameter): (a, b) are poorly determined; see their intervals")
    design_fig = None
    if ci and design_sims > 0:
        scale = (-math.inf if scale_min is None else scale_min, scale_max) if scale_max is not None else None
        design_fig, w = _design_check(used, X, y, a, b, nonnegative, scale, design_sims)
        if w:
            warns.append(w)
    ti = None
    if se and not nonnegative:
        import scipy.stats

        k = float(scipy.stats.t.ppf(0.975, distinct - 2))
        ti = ((a - k * se[0], a + k * se[0]), (b - k * se[1], b + k * se[1]))
    return FitResult(a, b, nonnegative, len(used), excluded, metrics,
                     se_a=se[0] if se else None, se_b=se[1] if se else None,
                     ci_a=ci[0] if ci else None, ci_b=ci[1] if ci else None, warnings=warns,
                     t_interval_a=ti[0] if ti else None, t_interval_b=ti[1] if ti else None,
                     design=design_fig)


CONTROL = "none"  # the uncompressed control: the reference against itself, Ip = Ia = 0
INDEX_NAMES = ("Ip", "Ia", "Iobj")  # the one spelling hostd writes; readers accept any case


def column(cols, name: str) -> str | None:
    """The header of `cols` that spells `name` in any case (Ip, ip, IP), or None."""
    want = name.lower()
    for c in cols:
        if c is not None and c.strip().lower() == want:
            return c
    return None


def _empty(v) -> bool:
    """A cell with nothing in it: None, "", or a NaN float (pandas' missing value)."""
    return v is None or (isinstance(v, str) and not v.strip()) or (isinstance(v, float) and math.isnan(v))


def indices_of(r: Mapping, where: str) -> tuple[float, float] | None:
    """(Ip, Ia) of one record whose columns are spelt Ip/Ia or ip/ia; None when it has neither
    (or both cells are empty); (0, 0) for a control (method none) without them."""
    kp, ka = column(r.keys(), "Ip"), column(r.keys(), "Ia")
    vp = r.get(kp) if kp else None
    va = r.get(ka) if ka else None
    if _empty(vp) and _empty(va):
        return (0.0, 0.0) if str(r.get("method", "")).strip().lower() == CONTROL else None
    if _empty(vp) or _empty(va):
        raise FitError(f"{where}: give both Ip and Ia (one is empty)")
    try:
        return float(vp), float(va)
    except (TypeError, ValueError):
        raise FitError(f"{where}: Ip and Ia must be numbers, not {vp!r:.20} and {va!r:.20}") from None


def read_scores(path: str | Path, score_one=None) -> list[Stimulus]:
    """Rows: texture, method, level, score and either Ip, Ia (any case: ip, ia as `hostd quality
    --csv` wrote them before) or stream (+ profile) paths. A control row (method `none`) with
    no Ip, Ia and an empty stream cell is the reference against itself: Ip = Ia = 0.

    score_one(stream_path, profile_path|None) -> (Ip, Ia) scores rows given as streams;
    relative paths are taken from the CSV's folder.
    """
    p = Path(path)
    try:
        fh = p.open(newline="", encoding="utf-8")
    except FileNotFoundError:
        raise ScoresNotFound(f"no such scores file: {p}") from None
    except OSError as exc:
        raise FitError(f"cannot read {p}: {exc.strerror or exc}") from None
    with fh:
        rows = list(csv.DictReader(line for line in fh if not line.lstrip().startswith("#")))
    if not rows:
        raise FitError(f"{p}: no rows")
    cols = set(rows[0].keys())
    missing = [c for c in REQUIRED if c not in cols]
    if missing:
        raise FitError(f"{p}: missing column(s) {', '.join(missing)}; see hostd fit --help")
    has_idx = column(cols, "Ip") is not None and column(cols, "Ia") is not None
    if not has_idx and "stream" not in cols:
        raise FitError(f"{p}: give Ip and Ia columns, or a stream column (and profile)")
    out = []
    for i, r in enumerate(rows, start=2):
        where = f"{p}:{i}"
        try:
            score = float(r["score"])
        except (ValueError, TypeError):
            raise FitError(f"{where}: score, Ip and Ia must be numbers (score is "
                           f"{r['score']!r:.20})") from None
        idx = indices_of(r, where)
        if idx is None:
            stream = (r.get("stream") or "").strip()
            if not stream:
                raise FitError(f"{where}: no Ip, Ia and no stream: give either (an empty stream cell "
                               f"is only for the uncompressed control, method {CONTROL})")
            if score_one is None:
                raise FitError(f"{where}: no Ip/Ia and no way to score a stream")
            prof = r.get("profile") or None
            if prof and not synth.is_spec(prof):
                prof = str(p.parent / prof)
            idx = score_one(p.parent / stream, prof)
        count = None
        if (r.get("n") or "").strip():
            try:
                count = int(r["n"])
            except ValueError:
                raise FitError(f"{where}: n (answers per score) must be a whole number, "
                               f"not {r['n']!r:.20}") from None
            if count < 1:
                raise FitError(f"{where}: n (answers per score) must be >= 1")
        out.append(Stimulus(r["texture"], r["method"], r["level"], score, *idx, n=count))
    return out
