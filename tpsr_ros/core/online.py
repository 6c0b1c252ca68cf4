"""Algorithm 4 over a live stream of steps: the ROS-free core of the filter node.

:class:`OnlineTracker` holds the current predictive state and applies the model's
stateless update (:meth:`tpsr_ros.core.state_model.StateModel.update`, i.e.
:func:`tpsr_ros.core.filtering.update` for a TPSR) to one ``(stamp, action, observation)``
step at a time, with the same rules as offline tracking
(:func:`tpsr_ros.core.episodes.track_trajectory`), so the states it produces are bit for
bit the offline ones for the same steps:

- the first step of a *segment* starts from the model's initial state ``b_*``;
- a new segment starts after :meth:`OnlineTracker.reinit` (a reset, a backwards jump of
  time) and at every *gap*: a step whose stamp is not exactly one step period after the
  previous step's (a step was lost, or the robot was reset in between);
- the normaliser guard of :mod:`tpsr_ros.core.filtering` restarts from ``b_*`` when an update
  cannot be normalised; :attr:`OnlineTracker.recoveries` counts those steps.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from tpsr_ros.core.errors import ConfigError
from tpsr_ros.core.state_model import StateModel, Track
from tpsr_ros.core.units import STEP_NS

__all__ = ["SWAP_STATES", "OnlineTracker", "Step", "StepInfo", "track_with_swap"]


@dataclass(frozen=True)
class StepInfo:
    """What one step did.

    Attributes:
        state: the state after the step, ``(state_dim,)``.
        started: the step started a segment from ``b_*`` (first step, after a re-init or a gap).
        gap: the segment started because of a gap in the stamps.
        recovered: the normaliser guard restarted the update from ``b_*``.
        normalizer: ``b_inf^T B_ao b`` (NaN for models without one).

    """

    state: np.ndarray
    started: bool
    gap: bool
    recovered: bool
    normalizer: float


class OnlineTracker:
    """The predictive state of one robot, updated step by step."""

    def __init__(self, model: StateModel, step_ns: int = STEP_NS) -> None:
        if step_ns <= 0:
            raise ConfigError(f"the step period must be positive, not {step_ns} ns")
        self.model = model
        self.step_ns = int(step_ns)
        self.state = model.initial_state()
        self.last_stamp: int | None = None
        """Stamp of the last step of the current segment; None before its first step."""
        self.steps = 0
        self.recoveries = 0
        self.gaps = 0
        self.reinits = 0

    def reinit(self) -> None:
        """Start a new segment: the state is ``b_*`` and the next step starts from it."""
        self.state = self.model.initial_state()
        self.last_stamp = None
        self.reinits += 1

    def swap(self, model: StateModel, replay: Sequence[Step] = ()) -> None:
        """Track with ``model`` from the next step on, its state ``b_*`` re-filtered through
        ``replay``, the last steps ``(stamp, action, observation)`` oldest first (none: the
        next step starts from ``b_*``). The replayed steps are not counted again."""
        self.model = model
        self.state = model.initial_state()
        self.last_stamp = None
        counts = (self.steps, self.gaps, self.recoveries)
        for stamp, action, observation in replay:
            self.step(stamp, action, observation)
        self.steps, self.gaps, self.recoveries = counts

    def step(self, stamp_ns: int, action: int, observation: np.ndarray) -> StepInfo:
        """Incorporate step ``(a_k, o_k)`` stamped ``stamp_ns``; return the new state."""
        started = self.last_stamp is None
        gap = not started and stamp_ns - self.last_stamp != self.step_ns  # type: ignore[operator]
        state = self.model.initial_state() if (started or gap) else self.state
        new, info = self.model.update(state, int(action), observation)
        self.state = new
        self.last_stamp = int(stamp_ns)
        self.steps += 1
        self.gaps += int(gap)
        self.recoveries += int(info.recovered)
        return StepInfo(new, started or gap, gap, info.recovered, info.normalizer)


Step = tuple[int, int, np.ndarray]
"""One step as the tracker takes it: stamp (ns), action index, observation."""

SWAP_STATES = ("replay", "restart")
"""What the state becomes at a model swap: the last steps re-filtered, or ``b_*``."""


def track_with_swap(
    first: StateModel,
    second: StateModel,
    steps: Sequence[Step],
    swap_at_ns: int,
    *,
    step_ns: int = STEP_NS,
    replay_steps: int = 20,
) -> Track:
    """The states of ``steps`` tracked with ``first`` and, from the first step stamped
    at or after ``swap_at_ns``, with ``second`` after :meth:`OnlineTracker.swap` re-filtered
    its last ``replay_steps`` steps (0: from ``b_*``): what the filter node publishes when
    the swap comes between those two steps (the offline reference of a live swap)."""
    tracker = OnlineTracker(first, step_ns)
    recent: deque[Step] = deque(maxlen=max(replay_steps, 0))  # 0 keeps nothing: b_*
    states, normalizers, recovered = [], [], []
    swapped = False
    for stamp, action, observation in steps:
        if not swapped and stamp >= swap_at_ns:
            tracker.swap(second, list(recent))
            swapped = True
        info = tracker.step(stamp, action, observation)
        states.append(info.state)
        normalizers.append(info.normalizer)
        recovered.append(info.recovered)
        recent.append((stamp, action, observation))
    return Track(np.array(states), np.array(normalizers), np.array(recovered, dtype=bool))
