"""Is there enough data for a good model? Episodes per action and the recovery rate.

Two figures tell, without a pose, that a fit had too little data:

- **training episodes per action**: each action's operators ``B_ao`` are averages over the
  training episodes whose current action it is; with a handful of them they are noise.
  Fewer than :data:`MIN_EPISODES_PER_ACTION` per action (on average) is too few.
- **the recovery rate**: tracking the training data itself with the model, the share of
  steps whose predicted observation probability was not positive, so the state restarted
  from ``b_*`` (the normaliser guard of the state update, guide 3.3). A model that cannot
  follow the very steps it was fitted on restarts often; more than
  :data:`MAX_RECOVERY_RATE` of the steps is too often.

``learner fit`` says when either is crossed, with the figures and how many more seconds
to record (at the rate the bags were recorded: the seconds that bring the episodes per
action up to the minimum); the model's training metadata keeps them (``adequacy``) for
``learner info`` and ``learner plot``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from tpsr_ros.core.episodes import Trajectory, track_trajectory
from tpsr_ros.core.state_model import Track
from tpsr_ros.core.tpsr import TPSRModel

__all__ = [
    "MAX_RECOVERY_RATE",
    "MIN_EPISODES_PER_ACTION",
    "Adequacy",
    "assess",
    "recovery_text",
]

MIN_EPISODES_PER_ACTION = 20
"""Fewest training episodes per action (on average) for operators that are not noise."""
MAX_RECOVERY_RATE = 0.2
"""Largest share of the training steps whose tracking may restart from ``b_*``."""


@dataclass(frozen=True)
class Adequacy:
    """The figures of one fit: its training episodes and actions, and the training data
    tracked (``steps``, of which ``recoveries`` restarted), over ``seconds`` recorded."""

    training_episodes: int
    n_actions: int
    steps: int
    recoveries: int
    seconds: float

    @property
    def per_action(self) -> float:
        """Training episodes per action, on average."""
        return self.training_episodes / max(self.n_actions, 1)

    @property
    def recovery_rate(self) -> float:
        """Restarts per tracked step."""
        return self.recoveries / max(self.steps, 1)

    @property
    def too_few_episodes(self) -> bool:
        """Fewer than :data:`MIN_EPISODES_PER_ACTION` per action."""
        return self.per_action < MIN_EPISODES_PER_ACTION

    @property
    def too_many_recoveries(self) -> bool:
        """A recovery rate above :data:`MAX_RECOVERY_RATE`."""
        return self.recovery_rate > MAX_RECOVERY_RATE

    @property
    def too_little(self) -> bool:
        """Too little data for a good model, by either figure."""
        return self.too_few_episodes or self.too_many_recoveries

    def more_seconds(self) -> float:
        """Seconds more to record, at the same rate, for the minimum episodes per action
        (when the episodes suffice but tracking restarts: as much again as recorded)."""
        if not self.too_few_episodes:
            return self.seconds
        needed = MIN_EPISODES_PER_ACTION * self.n_actions
        factor = needed / max(self.training_episodes, 1)
        return self.seconds * (factor - 1.0)

    def judgement(self) -> str | None:
        """One line saying the data are too little, with the figures and what to record;
        None when they are not."""
        if not self.too_little:
            return None
        more = math.ceil(self.more_seconds())
        return (
            f"too little data for a good model: {self.training_episodes} training episodes, "
            f"{self.per_action:.1f} per action over {self.n_actions} actions (at least "
            f"{MIN_EPISODES_PER_ACTION} wanted), and {recovery_text(self.recoveries, self.steps)}"
            f" when tracking the training data: record at least {more} more seconds "
            f"(now {self.seconds:.0f} s) of the same exploration"
        )

    def as_dict(self) -> dict[str, Any]:
        """For the model's training metadata (``adequacy``)."""
        return {
            "training_episodes": self.training_episodes,
            "n_actions": self.n_actions,
            "episodes_per_action": round(self.per_action, 3),
            "tracked_steps": self.steps,
            "recoveries": self.recoveries,
            "recovery_rate": round(self.recovery_rate, 6),
            "seconds": round(self.seconds, 3),
            "too_little": self.too_little,
        }


def recovery_text(recoveries: int, steps: int) -> str:
    """``restarts at 32 of 84 steps (38 %)``."""
    share = 100.0 * recoveries / max(steps, 1)
    return f"restarts at {recoveries} of {steps} steps ({share:.0f} %)"


def recorded_seconds(trajectory: Trajectory) -> float:
    """Seconds the trajectory's steps cover: their segments' spans plus one step each."""
    stamps = np.asarray(trajectory.stamps, dtype=np.int64)
    if stamps.size == 0:
        return 0.0
    step = float(np.median(np.diff(stamps))) if stamps.size > 1 else 1e9
    spans = [float(stamps[b - 1] - stamps[a]) + step for a, b in trajectory.segment_bounds()]
    return sum(spans) * 1e-9


def assess(model: TPSRModel, trajectory: Trajectory, tracked: Track | None = None) -> Adequacy:
    """Gather the figures of ``trajectory`` (the training data) tracked with ``model``
    (``tracked``: those states when already tracked)."""
    if tracked is None:
        tracked = track_trajectory(model, trajectory)
    return Adequacy(
        training_episodes=int(  # overlapping windows: those sharing no step
            model.fit_info.get("independent_episodes", model.fit_info.get("training_episodes", 0))
        ),
        n_actions=int(model.n_actions),
        steps=int(len(trajectory)),
        recoveries=int(np.count_nonzero(tracked.recovered)),
        seconds=recorded_seconds(trajectory),
    )
