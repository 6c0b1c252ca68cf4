"""Where ``learner policy`` takes the rewards of its RL bags.

Three sources, one per run:

- the simulator's ``/reward`` (or the model's training bags' reward topic), read as before
  when no option names another source;
- ``--reward-topic TOPIC``: a robot's own rewards, ``std_msgs/msg/Float32``,
  ``std_msgs/msg/Float64``, ``std_msgs/msg/Bool`` (1.0 when true) or the simulator's
  ``sensor_msgs/msg/JointState``; on a model's step grid a step earns the sum of the
  rewards timed within it (:mod:`tpsr_ros.core.rewards`), so event-like rewards lose
  nothing. Models that pair steps by identical stamp (simulator models) take only the
  stamped ``JointState``;
- ``--goal-region X,Y,R`` with the poses of ``--pose-topic``: ``+10`` for a step whose end
  pose lies within ``R`` m of ``(X, Y)``, as the simulator's goal zone. Its -1 for a step
  blocked by a wall cannot be told from a pose, so it has no counterpart.

A bag with none of them is refused in one line that names these options.
"""

from __future__ import annotations

import argparse
import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from tpsr_ros.core.episodes import Trajectory
from tpsr_ros.core.errors import ConfigError, DataError
from tpsr_ros.core.rewards import GoalRegion
from tpsr_ros.io.bag import BagReader
from tpsr_ros.io.messages import REWARD_TYPE
from tpsr_ros.io.reward_messages import REWARD_TYPES

__all__ = [
    "REWARD_WAYS",
    "RewardSource",
    "add_reward_options",
    "apply_rewards",
    "check_reward_topic",
    "goal_region",
    "reward_source_from_args",
]

REWARD_WAYS = (
    "give --reward-topic TOPIC (std_msgs/msg/Float32, std_msgs/msg/Float64, std_msgs/msg/Bool "
    "or the simulator's sensor_msgs/msg/JointState) or --goal-region X,Y,R --pose-topic TOPIC "
    "(+10 for a step ending within R m of X,Y); see docs/robot_bags.md, 'Rewards'"
)
"""The ways to give rewards, as the refusal names them."""


def goal_region(text: str) -> GoalRegion:
    """argparse type: ``X,Y,R`` in metres."""
    try:
        return GoalRegion.parse(text)
    except ConfigError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def add_reward_options(parser: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """``--goal-region`` (``--reward-topic`` and ``--pose-topic`` are topic options)."""
    parser.add_argument(
        "--goal-region",
        type=goal_region,
        default=None,
        metavar="X,Y,R",
        help="rewards from poses instead of a reward topic: +10 for a step whose end pose "
        "(on --pose-topic, default the model's) lies within R m of (X, Y), as the "
        "simulator's goal zone (its -1 for a blocked step cannot be known from a pose)",
    )


@dataclass(frozen=True)
class RewardSource:
    """The rewards of one ``learner policy`` run.

    Attributes:
        topic: the reward topic read (given, or the default one).
        given: whether ``--reward-topic`` named it.
        region: the goal region (then poses give the rewards and ``topic`` is unused).

    """

    topic: str
    given: bool = False
    region: GoalRegion | None = None

    def as_dict(self, pose_topic: str | None = None) -> dict[str, Any]:
        """JSON form for the policy's metadata."""
        if self.region is not None:
            return {"goal_region": dataclasses.asdict(self.region), "pose_topic": pose_topic}
        return {"topic": self.topic}


def reward_source_from_args(args: argparse.Namespace, default_topic: str) -> RewardSource:
    """The source the options name; both ``--reward-topic`` and ``--goal-region`` refused."""
    topic = getattr(args, "reward_topic", None)
    region = getattr(args, "goal_region", None)
    if topic and region is not None:
        raise ConfigError(
            "--reward-topic and --goal-region are two sources of rewards: give one of them"
        )
    if region is not None:
        return RewardSource(topic=default_topic, region=region)
    return RewardSource(topic=topic or default_topic, given=bool(topic))


def check_reward_topic(bags: Sequence[Path], source: RewardSource, *, resampled: bool) -> None:
    """Refuse, before any bag is read: bags none of which has the reward topic (the ways
    to give rewards named), a reward topic of a type that carries no reward, or
    (``resampled`` False: the simulator's exact-stamp pairing) one without a stamp."""
    if source.region is not None:
        return
    found = False
    for bag in bags:
        with BagReader(bag) as reader:
            msgtype = reader.topics_with_messages.get(source.topic)
        if msgtype is None:
            continue
        found = True
        if msgtype not in REWARD_TYPES:
            raise ConfigError(
                f"reward topic {source.topic} of bag {str(bag)!r} carries {msgtype}, not one "
                f"of {', '.join(REWARD_TYPES)}"
            )
        if not resampled and msgtype != REWARD_TYPE:
            raise ConfigError(
                f"reward topic {source.topic} of bag {str(bag)!r} carries {msgtype}, which has "
                "no stamp, but this model pairs steps by identical stamp (simulator bags): "
                "fit the model with --step-period so that rewards are summed over its steps"
            )
    if not found:
        raise DataError(_no_rewards(bags, source.topic))


def _no_rewards(bags: Sequence[Path], topic: str) -> str:
    names = ", ".join(repr(str(b)) for b in bags)
    return f"no rewards: the RL bag(s) {names} have no messages on {topic}; {REWARD_WAYS}"


def apply_rewards(
    trajectory: Trajectory, source: RewardSource, pose_topic: str | None
) -> tuple[Trajectory, str]:
    """The trajectory with the source's rewards and one line saying what they are.

    A reward topic's rewards are the trajectory's own (read with the bags); a step without
    one (NaN) is refused here, with the ways to give rewards. A goal region's rewards come
    from the step's poses; steps without a pose keep NaN (their transitions are left out),
    and a trajectory with no pose at all is refused.
    """
    steps = len(trajectory)
    if source.region is not None:
        rewards = source.region.rewards(trajectory.positions[:, :2])
        known = np.isfinite(rewards)
        if not known.any():
            raise DataError(
                f"--goal-region needs the pose at each step's end, but the RL bags have no pose "
                f"on {pose_topic} at any step: give --pose-topic TOPIC (PoseStamped, Odometry, "
                "TransformStamped, PoseWithCovarianceStamped or /tf)"
            )
        inside = int(np.count_nonzero(rewards[known]))
        unknown = steps - int(known.sum())
        line = (
            f"rewards: {source.region.describe()} on {pose_topic}: {inside} of {steps} steps "
            "end inside"
            + (f"; {unknown} steps without a pose (their transitions left out)" if unknown else "")
        )
        return dataclasses.replace(trajectory, rewards=rewards), line
    rewards = trajectory.rewards
    missing = ~np.isfinite(rewards)
    if missing.any():
        raise DataError(
            f"{int(missing.sum())} of {steps} steps of the RL bags have no reward on "
            f"{source.topic}; {REWARD_WAYS}"
        )
    nonzero = int(np.count_nonzero(rewards))
    line = (
        f"rewards: {source.topic}: {nonzero} of {steps} steps non-zero, total {rewards.sum():g}"
    )
    return trajectory, line
