"""The perceptual model: detection-threshold curves, the quality indices, fitting, peer metrics."""

from hostd.perception.indices import DEFAULT_AB, PRESETS, Scores, score, scores_from_sums
from hostd.perception.thresholds import ThresholdCurve, default_curve, load_csv

__all__ = [
    "DEFAULT_AB",
    "PRESETS",
    "Scores",
    "ThresholdCurve",
    "default_curve",
    "load_csv",
    "score",
    "scores_from_sums",
]
