"""``learner evaluate POLICY --environment E``: the standard evaluation (guide 4.1-4.2).

Protocol, fixed and documented so that every score is comparable and the closed loop over
the nodes reproduces it exactly: one simulator seeded with ``EVALUATION_SEED``; its
start-up reset (a random start, as ``sim_node`` does); then for each of the ten
``START_POSITIONS`` a reset to that position and ``STEPS`` greedy steps, the state
starting from the representation's initial state (``b_*`` for a TPSR); in ``drive`` each
start also has a heading (``START_HEADINGS_DEG``: east, north, west, south in turn). A
trial's reward
is the sum over its steps; the score is the mean over the ten trials (at most about 470:
no start lies in the goal zone). Execution noise continues from trial to trial, exactly
as in a ``sim_node`` that is reset ten times. A model learned from robot bags sees the
simulator's camera at its robot camera's size through its own preprocessing, and each code
its policy chooses is executed as the simulator's action nearest to the code's command
(:mod:`learner.sim_robot`), as over the nodes.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from learner.inputs import require_camera
from learner.representations import ModelTracker, Tracker, load_tracker
from learner.sim_robot import is_robot_model, simulated_robot
from sim_node import Environment, RobotEnv, SimConfig
from sim_node.options import add_vertical_half_extent_option
from tpsr_ros.cli import positive_int
from tpsr_ros.core.errors import ModelFormatError
from tpsr_ros.io.model_io import open_model
from tpsr_ros.io.policy import TRUE_POSITION, Policy, load_policy

__all__ = [
    "EVALUATION_SEED",
    "STANDING_METRES",
    "START_HEADINGS_DEG",
    "START_POSITIONS",
    "STEPS",
    "Evaluation",
    "Trial",
    "add_camera_size_option",
    "evaluate",
    "path_end",
    "register",
    "robot_setup",
    "run",
    "run_protocol",
    "start_heading",
]

EVALUATION_SEED = 2026
STEPS = 50
STANDING_METRES = 0.01
"""A step that moves the robot this far or less left it in its place."""
START_POSITIONS: tuple[tuple[float, float], ...] = (
    (5.0, 5.0),
    (5.0, 22.5),
    (5.0, 40.0),
    (22.5, 5.0),
    (40.0, 5.0),
    (15.0, 15.0),
    (30.0, 10.0),
    (10.0, 30.0),
    (22.5, 22.5),
    (28.0, 28.0),
)
START_HEADINGS_DEG: tuple[float, ...] = tuple(90.0 * (i % 4) for i in range(len(START_POSITIONS)))
"""The heading of each start in ``drive`` (degrees from east, counter-clockwise)."""


def start_heading(drives: bool, index: int) -> float | None:
    """The heading (rad) of start ``index`` for a robot that turns, else None."""
    if not drives:
        return None
    return float(np.radians(START_HEADINGS_DEG[index % len(START_HEADINGS_DEG)]))


def start_options(config: SimConfig, index: int, start: tuple[float, float]) -> dict[str, Any]:
    """The reset options of trial ``index`` from ``start``: its position, and in ``drive``
    its heading from :data:`START_HEADINGS_DEG`."""
    heading = start_heading(config.drives, index)
    return {"position": start} | ({} if heading is None else {"heading": heading})


@dataclass(frozen=True)
class Trial:
    """One trial: where it started, its summed reward, when (if) it reached the goal zone;
    where it ended and for how many of its last steps it had not left its place (stood,
    turned on the spot or pushed into a wall): where a policy that fails gets stuck."""

    start: tuple[float, float]
    reward: float
    goal_step: int | None
    wall_contacts: int
    end: tuple[float, float] | None = field(default=None, compare=False)
    """Not compared: the closed loop reads it from pose messages, which can differ from the
    simulator's own pose in the last bit."""
    standing: int = 0


@dataclass(frozen=True)
class Evaluation:
    """The trials of one evaluation and their mean reward (the score)."""

    trials: tuple[Trial, ...]
    states: np.ndarray | None = field(default=None, compare=False, repr=False)
    """``(N, r)``: the state each action was chosen from, trial after trial (not compared:
    the closed loop's own record is the states it published)."""
    positions: np.ndarray | None = field(default=None, compare=False, repr=False)
    """``(N, 2)``: where the robot stood when each action was chosen."""

    @property
    def score(self) -> float:
        """Mean summed reward over the trials."""
        return float(np.mean([t.reward for t in self.trials]))


def path_end(path: np.ndarray) -> tuple[tuple[float, float], int]:
    """Where a trial's path ``(N + 1, 2)`` (its start, then the position after each step)
    ended, and for how many of its last steps the robot moved :data:`STANDING_METRES` or
    less."""
    moved = np.hypot(*np.diff(path, axis=0).T) > STANDING_METRES
    standing = len(moved) - (int(np.flatnonzero(moved)[-1]) + 1) if moved.any() else len(moved)
    return (float(path[-1, 0]), float(path[-1, 1])), standing


def evaluate(
    policy: Policy, tracker: Tracker, environment: Environment | str | SimConfig, **protocol: Any
) -> Evaluation:
    """Run the standard protocol with ``policy`` choosing from ``tracker``'s states.

    ``protocol`` takes the keyword options of :func:`run_protocol` (seed, starts, steps,
    on_trial); the policy must belong to the tracker's model.
    """
    policy.check_model(tracker.fingerprint)
    return run_protocol(policy.action, tracker, environment, **protocol)


def run_protocol(
    choose: Callable[[np.ndarray], int],
    tracker: Tracker,
    environment: Environment | str | SimConfig,
    *,
    seed: int = EVALUATION_SEED,
    starts: Sequence[tuple[float, float]] = START_POSITIONS,
    steps: int = STEPS,
    on_trial: Callable[[int, Trial], None] | None = None,
    execute: Callable[[int], int] | None = None,
) -> Evaluation:
    """The standard protocol for any controller ``choose(state) -> action index``.

    :func:`evaluate` runs it for a fitted-Q policy, the floor baselines
    (:mod:`learner.floors`) for state-blind controllers. ``environment`` is a name (the
    default camera) or the simulator's whole configuration. ``execute`` maps the
    controller's action to the simulator's (a robot model's code to the action its command
    snaps to); the tracker is updated with the controller's own action. A tracker whose
    ``sees_images`` is False (the floors, the true position) gets no camera images: the
    simulator skips rendering them.
    """
    config = (
        environment if isinstance(environment, SimConfig) else SimConfig(environment=environment)
    )
    env = RobotEnv(config, seed=seed, render=getattr(tracker, "sees_images", True))
    env.reset()  # the start-up reset of a freshly started sim_node
    trials = []
    chosen_from: list[np.ndarray] = []
    stood_at: list[np.ndarray] = []
    for index, start in enumerate(starts):
        image, info = env.reset(options=start_options(config, index, start))
        state = tracker.start(image, info["pose"])
        total, goal_step, contacts = 0.0, None, 0
        path = [np.asarray(info["pose"], dtype=np.float64)[:2]]
        for k in range(1, steps + 1):
            chosen_from.append(np.asarray(state, dtype=np.float64))
            stood_at.append(path[-1])
            action = choose(state)
            image, reward, _, _, info = env.step(action if execute is None else execute(action))
            total += reward
            contacts += info["wall_contact"]
            if goal_step is None and info["goal_zone"]:
                goal_step = k
            state = tracker.step(state, action, image, info["pose"])
            path.append(np.asarray(info["pose"], dtype=np.float64)[:2])
        trial = Trial(tuple(start), total, goal_step, contacts, *path_end(np.array(path)))
        trials.append(trial)
        if on_trial is not None:
            on_trial(index, trial)
    return Evaluation(tuple(trials), np.array(chosen_from), np.array(stood_at))


def register(subparsers: Any) -> None:
    """Add the ``evaluate`` subcommand."""
    doc = "score a policy with the standard protocol (10 fixed starts, 50 greedy steps)"
    parser = subparsers.add_parser(
        "evaluate", help=doc, description=doc[0].upper() + doc[1:] + ". " + __doc__.split("\n\n")[1]
    )
    parser.add_argument("policy", type=Path, metavar="POLICY")
    parser.add_argument("--environment", required=True, choices=[e.value for e in Environment])
    add_vertical_half_extent_option(parser, "the simulator's camera (the model's must match)")
    add_camera_size_option(parser)
    parser.add_argument(
        "--model",
        default=None,
        metavar="MODEL",
        help="the policy's model file (default: the path recorded in the policy)",
    )
    parser.add_argument(
        "--seed", type=int, default=EVALUATION_SEED, help="simulator seed (default: %(default)s)"
    )
    parser.set_defaults(run=run)


def add_camera_size_option(parser: argparse.ArgumentParser) -> None:
    """``--camera-size N``: the simulator's camera for a model learned from robot bags."""
    parser.add_argument(
        "--camera-size",
        type=positive_int,
        default=None,
        metavar="N",
        help="for a model learned from robot bags: the simulator's camera pixels on each side "
        "(default: its robot's camera, as the model records it)",
    )


def robot_setup(
    policy: Policy, model: str | None, sim: SimConfig, camera_size: int | None
) -> tuple[Tracker, SimConfig, Callable[[int], int] | None]:
    """The tracker, the simulator's configuration and the code-to-action map of the policy's
    model: a robot model's camera size, preprocessing and codebook (:mod:`learner.sim_robot`),
    else the simulator's own (no map)."""
    if policy.representation == TRUE_POSITION:
        return load_tracker(TRUE_POSITION), sim, None
    model_file = open_model(policy.model_path(model))
    if not is_robot_model(model_file):
        require_camera(model_file, sim.vertical_extent)
        return load_tracker(model_file), sim, None
    robot = simulated_robot(model_file, sim, camera_size)
    assert model_file.spec is not None
    tracker = ModelTracker(model_file.model, model_file.fingerprint, model_file.spec.preprocessing)
    return tracker, replace(sim, image_size=robot.camera_size), robot.execute



def run(args: argparse.Namespace) -> int:
    """Evaluate; print each trial, then ``score: <mean>`` as the last line."""
    if args.seed < 0:
        raise ModelFormatError(f"--seed must be >= 0, got {args.seed}")
    policy = load_policy(args.policy)
    policy.check_environment(args.environment)
    sim = SimConfig(
        environment=args.environment, vertical_half_extent=args.vertical_half_extent
    )
    tracker, sim, execute = robot_setup(policy, args.model, sim, args.camera_size)

    def show(index: int, trial: Trial) -> None:
        goal = (
            f"goal zone at step {trial.goal_step}" if trial.goal_step else "goal zone not reached"
        )
        print(
            f"trial {index + 1:2d}: start ({trial.start[0]:4.1f}, {trial.start[1]:4.1f})  "
            f"reward {trial.reward:7.1f}  {goal}, {trial.wall_contacts} wall contacts",
            flush=True,
        )

    result = evaluate(policy, tracker, sim, seed=args.seed, on_trial=show, execute=execute)
    print(f"score: {result.score:.1f}")
    return 0
