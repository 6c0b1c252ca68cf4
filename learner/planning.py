"""``learner policy MODEL BAG... -o POLICY``: fitted Q-iteration on states tracked over an RL bag.

States come from the model's parameters tracked over a separate random RL trajectory
(guide 4.2: never embedded histories); ``MODEL`` may also be ``true-position``, the
ground-truth baseline. Transitions ``(s_k, a_{k+1}, r_{k+1}, s_{k+1})`` never cross a gap
in the bag. The policy file names the model's fingerprint. Rewards come from the
simulator's ``/reward``, a robot's ``--reward-topic`` or a ``--goal-region`` on its poses
(:mod:`learner.rewards`).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path
from typing import Any

from learner.fit import add_topic_options, topics_from_args
from learner.inputs import (
    read_for_model,
    recorded_topic,
    require_camera,
    require_given_topics,
)
from learner.options import (
    add_config_options,
    add_preset_option,
    config_from_args,
    preset_from_args,
)
from learner.representations import Tracker, load_tracker
from learner.rewards import (
    REWARD_WAYS,
    RewardSource,
    add_reward_options,
    apply_rewards,
    check_reward_topic,
    reward_source_from_args,
)
from tpsr_ros.cli import positive_int
from tpsr_ros.core.episodes import Trajectory
from tpsr_ros.core.errors import DataError
from tpsr_ros.core.fqi import FQIConfig
from tpsr_ros.core.planning import MissingRewards
from tpsr_ros.core.presets import departures
from tpsr_ros.io.model_io import ModelFile, open_model
from tpsr_ros.io.npz_archive import check_output_path
from tpsr_ros.io.policy import TRUE_POSITION, Policy, policy_from_states, save_policy
from tpsr_ros.io.trajectory import Topics, read_trajectory

__all__ = ["fit_policy", "register", "run"]


def fit_policy(
    tracker: Tracker,
    trajectory: Trajectory,
    config: FQIConfig,
    *,
    environment: str | None,
    model_path: str | None = None,
    preset: dict[str, Any] | None = None,
    rewards: dict[str, Any] | None = None,
    skip_unknown: bool = False,
) -> Policy:
    """Track states over ``trajectory``, fit Q on its transitions, return the greedy policy.

    The metadata record the fitted-Q configuration used (a larger ridge than ``config``'s
    if the fit diverged: :func:`fit_q_on`), ``preset``, the named settings it started
    from and what changed in them, and ``rewards``, where the rewards came from.
    ``skip_unknown``: see :func:`transitions`.
    """
    start = time.perf_counter()
    states = tracker.track(trajectory)
    try:
        return policy_from_states(
            states,
            trajectory,
            config,
            representation=tracker.representation,
            fingerprint=tracker.fingerprint,
            environment=environment,
            metadata={
                "model_path": model_path,
                **({"preset": preset} if preset is not None else {}),
                **({"rewards": rewards} if rewards is not None else {}),
            },
            skip_unknown=skip_unknown,
            tracking_s=time.perf_counter() - start,
        )
    except MissingRewards as exc:
        raise DataError(f"{exc}: {REWARD_WAYS}") from None


def register(subparsers: Any) -> None:
    """Add the ``policy`` subcommand."""
    doc = "fit a greedy fitted-Q policy on states tracked with a model over an RL bag"
    parser = subparsers.add_parser("policy", help=doc, description=doc[0].upper() + doc[1:] + ".")
    parser.add_argument("model", metavar="MODEL", help="model file, or 'true-position'")
    parser.add_argument("bags", nargs="+", type=Path, metavar="BAG", help="RL bag(s)")
    parser.add_argument("-o", "--output", type=Path, required=True, metavar="POLICY")
    parser.add_argument(
        "--steps",
        type=positive_int,
        default=None,
        metavar="N",
        help="use the first N RL steps and refuse a shorter bag (guide: 15000 full, "
        "20000 partial and distractors; default: all)",
    )
    parser.add_argument("--force", action="store_true", help="overwrite an existing POLICY")
    planner = parser.add_argument_group("fitted Q-iteration")
    add_preset_option(planner, "fitted-Q")
    add_config_options(planner, FQIConfig)
    add_topic_options(parser.add_argument_group("topics"))
    add_reward_options(parser.add_argument_group("rewards of a robot's bag (docs/robot_bags.md)"))
    parser.set_defaults(run=run)


def _first_steps(trajectory: Trajectory, steps: int | None) -> Trajectory:
    if steps is None:
        return trajectory
    if len(trajectory) < steps:
        raise DataError(f"the RL bag has {len(trajectory)} steps, fewer than the {steps} requested")
    per_step = (
        "stamps", "observations", "actions", "velocities", "positions", "rewards", "segments"
    )
    return dataclasses.replace(
        trajectory, **{name: getattr(trajectory, name)[:steps] for name in per_step}
    )


def _reward_source(
    args: argparse.Namespace, model_file: ModelFile | None
) -> tuple[RewardSource, str]:
    """The run's reward source and the pose topic a goal region reads (the options', else
    the model's training bags', else the defaults)."""
    defaults = Topics()
    if model_file is not None and model_file.spec is not None:  # its training bags' topics
        metadata = model_file.metadata
        defaults = Topics(
            pose=recorded_topic(metadata, "pose") or defaults.pose,
            reward=recorded_topic(metadata, "reward") or defaults.reward,
        )
    source = reward_source_from_args(args, defaults.reward)
    return source, args.pose_topic or defaults.pose


def run(args: argparse.Namespace) -> int:
    """Fit and save a policy."""
    output = check_output_path(args.output, force=args.force)
    preset = preset_from_args(args)
    config = config_from_args(FQIConfig, args, preset.fqi_config())
    model_file = None if str(args.model) == TRUE_POSITION else open_model(args.model)
    source, pose_topic = _reward_source(args, model_file)
    require_given_topics(args.bags, args)
    if source.region is not None:  # the bags are read with these topics
        args.pose_topic = pose_topic
    else:
        args.reward_topic = source.topic
    check_reward_topic(
        args.bags, source, resampled=model_file is not None and model_file.spec is not None
    )
    if model_file is None:
        tracker = load_tracker(TRUE_POSITION)
        read = read_trajectory(args.bags, topics=topics_from_args(args))
    else:  # a model reads bags as its training bags were read (its input spec, if any)
        tracker = load_tracker(model_file)
        read = read_for_model(model_file, args.bags, args)
    trajectory, said = apply_rewards(_first_steps(read, args.steps), source, pose_topic)
    print(f"learner policy: {said}", file=sys.stderr)
    if model_file is not None:  # the RL bags must show the model's camera
        camera = trajectory.summary()["vertical_half_extent"]
        if isinstance(camera, float):
            require_camera(model_file, camera, "the RL bags' camera")
    environment = trajectory.summary()["environment"]
    if not isinstance(environment, str):
        environment = None  # unknown or mixed: evaluation will not check it
    record = {"name": preset.name, "changed": departures(config, preset.fqi_config())}
    policy = fit_policy(
        tracker,
        trajectory,
        config,
        environment=environment,
        model_path=str(args.model),
        preset=record,
        rewards=source.as_dict(pose_topic),
        skip_unknown=source.region is not None,
    )
    save_policy(policy, output, force=args.force)
    timing = policy.metadata["timing_s"]
    ridges = policy.metadata["fqi"]["member_ridges"]
    if raised := [r for r in ridges if r != config.ridge]:
        which = (
            f"refitted at ridge {raised[0]:g}"
            if raised == [raised[0]] * len(ridges)
            else f"refitted {len(raised)} of {len(ridges)} members, at ridges up to {max(raised):g}"
        )
        print(f"fitted Q diverged at ridge {config.ridge:g}; {which}", file=sys.stderr)
    print(
        f"wrote {output}: {policy.representation} policy over {policy.state_dim}-d states, "
        f"{policy.metadata['data']['transitions']} transitions "
        f"(tracking {timing['tracking']:.1f} s, fitted Q {timing['fitted_q']:.1f} s); "
        f"environment {environment}",
        file=sys.stderr,
    )
    return 0
