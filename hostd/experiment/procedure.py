"""The threshold run a config's `procedure` names (above both procedures, which the session
runner takes from here: threshold.py, the per-frequency QUEST+, does not import the joint fit
built on it)."""

from __future__ import annotations


def make_run(cfg):
    """The run of cfg.procedure: threshold.ThresholdRun (a QUEST+ per frequency) or
    joint.JointRun (one posterior over the whole curve)."""
    if cfg.procedure == "joint":
        from hostd.experiment.joint import JointRun

        return JointRun(cfg)
    from hostd.experiment.threshold import ThresholdRun

    return ThresholdRun(cfg)
