"""The threshold procedures: their names (declared here once: the config checks them, the CLI
offers them), the interface every one implements (Procedure), and the run a config's
`procedure` names (the session runner takes it from here: threshold.py, the per-frequency
QUEST+, does not import the joint fit built on it). This module imports no procedure at module
level, so the CLI can read PROCEDURES without numpy."""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol, runtime_checkable

if TYPE_CHECKING:
    from hostd.experiment.threshold import ThresholdConfig, ThresholdResult, Trial

# name -> (module, class)
PROCEDURES = {
    "per-frequency": ("hostd.experiment.threshold", "ThresholdRun"),  # one QUEST+ per frequency
    "joint": ("hostd.experiment.joint", "JointRun"),  # one posterior over the whole curve
}


@runtime_checkable
class Procedure(Protocol):
    """A threshold run: next_trial() then answer(trial index, chosen interval), in order, until
    next_trial() is None; a pure function of (config, seed, answers), so resuming replays them."""

    cfg: ThresholdConfig
    index: int  # trials answered

    @property
    def planned_trials(self) -> int: ...  # the budget known now (a stop rule may end sooner)

    @property
    def done(self) -> bool: ...

    def next_trial(self) -> Trial | None: ...  # the same trial again until it is answered

    def answer(self, trial_index: int, chosen: int) -> bool: ...  # whether it was correct

    def results(self) -> list[ThresholdResult]: ...

    def notes(self) -> list[str]: ...  # what the experimenter should know (a misfit, say)


def make_run(cfg) -> Procedure:
    """The run of cfg.procedure (PROCEDURES)."""
    from importlib import import_module

    module, cls = PROCEDURES[cfg.procedure]
    return getattr(import_module(module), cls)(cfg)
