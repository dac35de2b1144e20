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
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import scipy.optimize

from hostd.errors import FitError

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


@dataclass
class FitResult:
    a: float
    b: float
    nonnegative: bool
    n_used: int
    excluded: list[dict] = field(default_factory=list)
    metrics: dict[str, dict[str, float]] = field(default_factory=dict)

    def as_dict(self) -> dict:
        return {
            "a": self.a, "b": self.b, "nonnegative": self.nonnegative, "n_used": self.n_used,
            "excluded": self.excluded, "metrics": self.metrics,
            "legend": {
                "r2_pearson": "squared Pearson correlation of index and scores (the paper's R^2)",
                "r2_fit": "coefficient of determination of the no-intercept least-squares fit",
            },
        }


def pearson_r2(x: np.ndarray, y: np.ndarray) -> float:
    x = x - x.mean()
    y = y - y.mean()
    den = math.sqrt(float(x @ x) * float(y @ y))
    if den == 0:
        return float("nan")
    return (float(x @ y) / den) ** 2


def r2_fit(pred: np.ndarray, y: np.ndarray) -> float:
    ss_tot = float(((y - y.mean()) ** 2).sum())
    return 1.0 - float(((y - pred) ** 2).sum()) / ss_tot


def _solve(X: np.ndarray, y: np.ndarray, nonnegative: bool) -> np.ndarray:
    if nonnegative:
        return scipy.optimize.nnls(X, y)[0]
    return np.linalg.lstsq(X, y, rcond=None)[0]


def fit(stimuli: list[Stimulus], *, nonnegative: bool = False,
        scale_max: float | None = None, exclude_saturated: bool = False) -> FitResult:
    """Fit (a, b); stimuli with a mean score at scale_max are excluded when asked (flagged)."""
    for s in stimuli:
        if exclude_saturated and scale_max is not None and s.score >= scale_max:
            s.excluded = f"saturated: mean score {s.score} at the top of the scale ({scale_max})"
    used = [s for s in stimuli if not s.excluded]
    if len(used) < 2:
        raise FitError(f"need at least 2 stimuli to fit (a, b), have {len(used)}")
    y = np.array([s.score for s in used])
    ip = np.array([s.Ip for s in used])
    ia = np.array([s.Ia for s in used])
    for name, v in (("score", y), ("Ip", ip), ("Ia", ia)):
        if not np.all(np.isfinite(v)):
            raise FitError(f"a {name} value is NaN or Inf")
    if np.ptp(y) == 0:
        raise FitError("every score is equal: nothing to explain; check the scores column")
    X = np.column_stack([ip, ia])
    if np.linalg.matrix_rank(X, tol=1e-12 * max(1.0, float(np.abs(X).max()))) < 2:
        raise FitError("Ip and Ia are collinear (or zero) over these stimuli: (a, b) is not "
                       "identifiable; add stimuli from both methods")
    a, b = (float(v) for v in _solve(X, y, nonnegative))
    metrics = {}
    for name, pred, x in (("Iobj", X @ [a, b], a * ip + b * ia), ("Ip", None, ip), ("Ia", None, ia)):
        if pred is None:
            w = float(_solve(x[:, None], y, nonnegative)[0])
            pred = w * x
        metrics[name] = {"r2_pearson": pearson_r2(x, y), "r2_fit": r2_fit(pred, y)}
    for m in metrics.values():
        for k, v in m.items():
            if not math.isfinite(v):
                m[k] = None  # an index that is constant over the stimuli has no correlation
    excluded = [{"texture": s.texture, "method": s.method, "level": s.level, "why": s.excluded}
                for s in stimuli if s.excluded]
    return FitResult(a, b, nonnegative, len(used), excluded, metrics)


def read_scores(path: str | Path, score_one=None) -> list[Stimulus]:
    """Rows: texture, method, level, score and either Ip, Ia or stream (+ profile) paths.

    score_one(stream_path, profile_path|None) -> (Ip, Ia) scores rows given as streams;
    relative paths are taken from the CSV's folder.
    """
    p = Path(path)
    try:
        fh = p.open(newline="", encoding="utf-8")
    except OSError as exc:
        raise FitError(f"cannot read {p}: {exc.strerror or exc}") from None
    with fh:
        rows = list(csv.DictReader(line for line in fh if not line.lstrip().startswith("#")))
    if not rows:
        raise FitError(f"{p}: no rows")
    cols = set(rows[0].keys())
    missing = [c for c in REQUIRED if c not in cols]
    if missing:
        raise FitError(f"{p}: missing column(s) {', '.join(missing)}; see docs/fitting.md")
    has_idx = {"Ip", "Ia"} <= cols
    if not has_idx and "stream" not in cols:
        raise FitError(f"{p}: give Ip and Ia columns, or a stream column (and profile)")
    out = []
    for i, r in enumerate(rows, start=2):
        try:
            score = float(r["score"])
            if has_idx and r.get("Ip", "") != "":
                ip, ia = float(r["Ip"]), float(r["Ia"])
            else:
                if score_one is None:
                    raise FitError(f"{p}:{i}: no Ip/Ia and no way to score a stream")
                prof = r.get("profile") or None
                ip, ia = score_one(p.parent / r["stream"],
                                   (p.parent / prof) if prof else None)
        except (ValueError, TypeError):
            raise FitError(f"{p}:{i}: score, Ip and Ia must be numbers") from None
        out.append(Stimulus(r["texture"], r["method"], r["level"], score, ip, ia))
    return out
