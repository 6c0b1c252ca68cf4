"""One TPSR fit of a whole trajectory as ``learner fit`` makes it, for a first fit and a refit.

``learner fit BAG`` (in memory), ``learner fit BAG --init-from MODEL`` and the learner node
all fit through :func:`fit_trajectory`, so the node's model after ``T`` live steps equals the
command's on a recording of those steps: the episodes cut from every step, the preset
sized to the data (a first fit) or the frozen basis of an earlier fit (a refit:
:mod:`tpsr_ros.core.fit_basis`), the refinement the config asks for, then the training
states tracked once for the viewer's read-outs.

A refit that forgets (``forgetting`` below 1) sums its episodes' statistics on the basis's
sketch of ``P_TH`` (every first fit keeps one; :class:`SummedSteps`,
:mod:`tpsr_ros.core.fit_statistics`), each weighted by ``forgetting ** age``, and solves
them. Given the statistics of an earlier refit of the same run, it sums only the episodes
that are new since, after decaying the old sums: the learner node's refits then cost the
new steps, and equal one pass over the whole recording. A refit that keeps every step
alike runs the two passes of the first fit on the basis, the whole ``P_TH`` and no sketch:
in ``partial-strip`` the sketch's refits scored below the two-pass refits of the same
steps (:data:`~tpsr_ros.core.fit_basis.SKETCH_MARGIN`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from tpsr_ros.core.alignment import ALIGN_STEPS, align_model
from tpsr_ros.core.episodes import Episodes, Trajectory, make_episodes, track_trajectory
from tpsr_ros.core.errors import ConfigError
from tpsr_ros.core.fit_basis import FitBasis
from tpsr_ros.core.fit_statistics import FitStatistics, forgetting_weights
from tpsr_ros.core.learn import fit_tpsr_trajectory, refined_on_trajectory
from tpsr_ros.core.sizing import Sizing
from tpsr_ros.core.state_box import box_episodes, episode_states, state_box
from tpsr_ros.core.state_model import Track
from tpsr_ros.core.tpsr import Progress, TPSRConfig, TPSRModel
from tpsr_ros.core.view_readout import ViewReadout, fit_view_readout

__all__ = ["SummedSteps", "TrajectoryFit", "fit_trajectory", "view_of_track"]


@dataclass(frozen=True, eq=False)
class SummedSteps:
    """A refit's statistics and what they hold: the first ``steps`` steps of a run, aged at
    its last one, up to the episode whose current step has the stamp ``last_stamp``."""

    statistics: FitStatistics
    steps: int
    last_stamp: int | None
    forgetting: float = 1.0

    @classmethod
    def of(
        cls,
        trajectory: Trajectory,
        episodes: Episodes,
        basis: FitBasis,
        *,
        forgetting: float = 1.0,
        previous: SummedSteps | None = None,
        action_codes: np.ndarray | None = None,
    ) -> SummedSteps:
        """The statistics of ``episodes`` (cut from ``trajectory``) on ``basis``, each weighted
        by ``forgetting ** age``; with ``previous`` (of a shorter start of the same run) only
        the episodes after it are summed, and its sums aged to the trajectory's end."""
        steps = len(trajectory)
        if previous is None:
            stats = FitStatistics.empty(basis, episodes.n_actions, action_codes)
            new = np.ones(len(episodes), dtype=bool)
        else:
            if previous.steps > steps or previous.forgetting != forgetting:
                raise ConfigError(
                    f"statistics of {previous.steps} steps (forgetting {previous.forgetting}) "
                    f"do not continue into {steps} steps with forgetting {forgetting}"
                )
            stats = previous.statistics.decayed(forgetting ** (steps - previous.steps))
            new = (
                np.ones(len(episodes), dtype=bool) if previous.last_stamp is None
                else episodes.stamps > previous.last_stamp
            )  # fmt: skip
        added = episodes.take(new)
        ages = (steps - 1) - np.searchsorted(trajectory.stamps, added.stamps)
        stats = stats.partial_fit(added, forgetting_weights(ages, forgetting))
        if len(added):
            last: int | None = int(added.stamps[-1])
        else:  # no episode completed since
            last = None if previous is None else previous.last_stamp
        return cls(stats, steps, last, forgetting)

    def model(self, episodes: Episodes) -> TPSRModel:
        """The solved TPSR, with the state box its config asks for (from ``episodes``)."""
        model = self.statistics.solve()
        if self.forgetting != 1.0:
            model.fit_info["forgetting"] = self.forgetting
        quantile = self.statistics.basis.config.state_clip_quantile
        if quantile == 0:
            return model
        chosen = box_episodes(len(episodes))
        states = episode_states(
            model, episodes.history[chosen], episodes.history_actions[chosen],
            episodes.action[chosen], episodes.observation[chosen],
        )  # fmt: skip
        config = replace(model.config, state_clip_quantile=quantile)
        return replace(model, config=config, state_box=state_box(states, quantile))


@dataclass(frozen=True, eq=False)
class TrajectoryFit:
    """A fitted model, its training states, the viewer's read-outs and what the fit took."""

    model: TPSRModel
    tracked: Track
    view: ViewReadout
    episodes: int
    seconds: float
    summed: SummedSteps | None = None
    """A refit's statistics, to continue with more steps (None: a two-pass fit)."""

    def training(self, trajectory: Trajectory) -> dict[str, Any]:
        """The model file's description of its training data (as ``learner fit`` writes it)."""
        cfg = self.model.config
        return {
            **trajectory.summary(),
            "episodes": self.episodes,
            "history_length": cfg.history_length,
            "test_length": cfg.test_length,
            "fit_seconds": round(self.seconds, 6),
        }


def fit_trajectory(
    trajectory: Trajectory,
    config: TPSRConfig,
    *,
    basis: FitBasis | None = None,
    sizing: Sizing | None = None,
    action_codes: np.ndarray | None = None,
    pose_frame: str = "map",
    progress: Progress | None = None,
    episodes: Episodes | None = None,
    max_episodes: int | None = None,
    forgetting: float = 1.0,
    previous: SummedSteps | None = None,
    align_to: TPSRModel | None = None,
) -> TrajectoryFit:
    """Fit ``trajectory`` with ``config`` (sized by ``sizing``), or refit it on ``basis``
    (then ``config`` is the basis's and only the rank rule applies); track its steps once.

    ``action_codes``: a robot model's codebook commands (action-aware features);
    ``pose_frame``: the frame of the training poses, for the decoded pose; ``episodes``:
    the trajectory's episodes when already cut (at most ``max_episodes`` of them). A refit
    with ``forgetting`` below 1 solves statistics on the basis's sketch
    (:class:`SummedSteps`), each episode weighted by ``forgetting ** age``; ``previous``
    continues an earlier such refit's statistics of the same run. ``align_to``: the model
    the fit replaces, whose state coordinates the fit's are rotated to
    (:mod:`tpsr_ros.core.alignment`, over the last
    :data:`~tpsr_ros.core.alignment.ALIGN_STEPS` steps both track).
    """
    start = time.perf_counter()
    cfg = basis.config if basis is not None else config
    from_statistics = forgetting != 1.0 or previous is not None
    if from_statistics and (basis is None or basis.sketch is None):
        raise ConfigError(
            "forgetting and continued statistics refit on the basis of a first fit, with its "
            "sketch of P_TH (a model written before sketches were kept has none: fit it anew)"
        )
    if episodes is None:
        episodes = make_episodes(
            trajectory, cfg.history_length, cfg.test_length, max_episodes=max_episodes,
            stride=cfg.episode_stride,
        )  # fmt: skip
    summed = None
    if from_statistics:
        assert basis is not None
        if progress is not None:
            progress("statistics")
        summed = SummedSteps.of(
            trajectory, episodes, basis, forgetting=forgetting, previous=previous,
            action_codes=action_codes,
        )  # fmt: skip
        model = refined_on_trajectory(
            summed.model(episodes), trajectory, episodes, max_episodes, progress
        )
    else:
        model = fit_tpsr_trajectory(
            trajectory, cfg, episodes=episodes, max_episodes=max_episodes, progress=progress,
            sizing=Sizing() if basis is not None else sizing,
            action_codes=action_codes, basis=basis,
        )  # fmt: skip
    seconds = time.perf_counter() - start
    tracked = track_trajectory(model, trajectory)
    if align_to is not None:
        model, tracked = _aligned(model, tracked, align_to, trajectory)
    view = view_of_track(tracked, trajectory, pose_frame)
    return TrajectoryFit(model, tracked, view, len(episodes), seconds, summed)


def _aligned(
    model: TPSRModel, tracked: Track, reference: TPSRModel, trajectory: Trajectory
) -> tuple[TPSRModel, Track]:
    """``model`` and its tracked states in the coordinates closest to ``reference``'s."""
    window = slice(max(0, len(trajectory) - ALIGN_STEPS), len(trajectory))
    old = track_trajectory(reference, trajectory).states[window]
    model, rotation, record = align_model(model, tracked.states[window], old)
    model.fit_info["aligned"] = record
    if rotation is None:
        return model, tracked
    return model, tracked._replace(states=tracked.states @ rotation)


def view_of_track(tracked: Track, trajectory: Trajectory, pose_frame: str) -> ViewReadout:
    """The viewer's read-outs (next image, pose, state map) on a trajectory's tracked states."""
    positions = trajectory.positions
    return fit_view_readout(
        tracked.states,
        trajectory.actions,
        trajectory.observations,
        trajectory.segments,
        trajectory.n_actions,
        positions=positions if np.isfinite(positions).any() else None,
        pose_frame=pose_frame,
    )
