"""What a learning-planning run measures beside its score: tuning, memory and the criterion.

``learner experiment --tune`` chooses each run's TPSR parameters on its own training data
(:func:`tuned`), ``--memory`` measures each learned model's memory (:func:`memory_of`) and
``--criterion`` scores each TPSR configuration by ``learner tune``'s held-out criterion
(:func:`criterion_of`), the columns the results page's appendix reads.
"""

from __future__ import annotations

from typing import Any, NamedTuple

from learner.representations import ModelTracker, Tracker
from learner.simulated import SimSettings
from tpsr_ros.core.episodes import Trajectory
from tpsr_ros.core.tpsr import TPSRConfig

__all__ = ["NOT_MEASURED", "MemoryFigures", "criterion_of", "memory_of", "tuned"]


def tuned(
    base: TPSRConfig, train: Trajectory, budget: float | None, candidates: int | None
) -> tuple[TPSRConfig, dict[str, Any]]:
    """``base``, or with a ``budget`` what ``learner tune`` picks from ``train`` starting there
    (at most ``candidates`` candidates)."""
    if budget is None:
        return base, {}
    from learner.tune import tune

    result = tune(train, budget=budget, candidates=candidates, seed=base.seed, base=base)
    return result.best.config, {
        "tune": {
            "criterion": round(result.best.score.value, 6),
            "se": round(result.best.score.se, 6),
            "highest": round(result.top.score.value, 6),
            "candidates": len(result.trials),
            "seconds": round(result.seconds, 1),
            "budget": budget,
            "candidate_limit": candidates,
        }
    }


def criterion_of(tpsr: TPSRConfig, train: Trajectory) -> float:
    """``learner tune``'s held-out criterion of ``tpsr`` on ``train`` (-inf if it fails)."""
    from learner.criterion import CriterionConfig, ObservationFeatures, score_tpsr, split_trajectory

    settings = CriterionConfig()
    fitted, heldout = split_trajectory(train, settings.holdout)
    features = ObservationFeatures.fit(fitted.observations, settings.feature_dim)
    score, _ = score_tpsr(tpsr, fitted, heldout, features, settings)
    return float(score.value)


class MemoryFigures(NamedTuple):
    """What ``--memory`` records of one model (:mod:`learner.memory`)."""

    steps: float
    """Steps remembered: the smaller of both variants."""
    paths_distance: float
    """The ``paths`` variant's relative distance at its first identical step."""
    paths_steps: float
    """Steps the ``paths`` variant alone remembers."""


NOT_MEASURED = MemoryFigures(float("nan"), float("nan"), float("nan"))
"""The figures of a run that did not measure its memory."""


def memory_of(
    tracker: Tracker, environment: str = "partial", sim: SimSettings | None = None
) -> MemoryFigures:
    """How long a learned model remembers in ``environment`` (camera: ``sim``;
    :mod:`learner.memory`); not measured for the true position."""
    if not isinstance(tracker, ModelTracker):
        return NOT_MEASURED
    from learner.memory import EXPERIMENTS, measure, state_spread

    spread = state_spread(tracker.model, environment, sim=sim)
    results = [measure(tracker.model, e, environment, spread, sim=sim) for e in EXPERIMENTS]
    paths = results[0]
    return MemoryFigures(
        steps=float(min(r.memory for r in results)),
        paths_distance=float(paths.relative_distance[paths.identical_from]),
        paths_steps=float(paths.memory),
    )
