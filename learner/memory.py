"""``learner memory MODEL --environment partial -o DIR``: how long a model remembers (guide 4.4).

The guide's experiment. Two fixed action sequences start from one position, differ for a
few steps and then reach positions that look exactly alike; from then on both receive
the same actions and see the same images, so only the state's memory of the differing
past can keep them apart. Both runs are tracked with the model's parameters (Algorithm 4
for a TPSR) from its initial state. Execution noise is switched off so that the paths,
and therefore the identical images, are exact.

Two variants (:data:`EXPERIMENTS`):

- ``paths`` (guide figures 4.15-4.17): from the room's centre one run goes west and the
  other east, then both go north until they stop at the north wall, then stand still.
  In ``partial`` (60 degree camera facing north) both see only the north wall from the
  first step north on.
- ``stand-still`` (guide figure A.5): from near the north wall one run steps west and
  the other east (same image, different actions), then both stand still.

Measure. The distance between the two states at each step, divided by the spread of the
model's states over a random run (root mean square distance from their mean, a scale
every model has). The memory of a variant is the number of consecutive steps, from the
first step whose inputs are identical onwards, during which that relative distance stays
above ``threshold`` (default :data:`THRESHOLD`, 0.1: a tenth of the spread of the whole
state space). A model that forgets at once scores 0; the true position never forgets.
The summary ``memory: N steps`` is the smaller of the two variants' memories; a variant
whose states are still apart when its run ends reports a lower bound (``at least``).

A filter restart (the guarded normaliser of :mod:`tpsr_ros.core.filtering` gave up and
the state was rebuilt from ``b_*``) ends the count: two states apart because one run just
restarted are not remembering anything. The first restart of either run from the first
identical step on is printed and plotted.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from learner.simulated import SimSettings, random_trajectory
from sim_node import Environment, RobotEnv, action_index
from sim_node.options import add_vertical_half_extent_option
from tpsr_ros.cli import positive_int
from tpsr_ros.core.episodes import Trajectory, images_to_observations
from tpsr_ros.core.errors import ConfigError, DataError
from tpsr_ros.core.state_model import StateModel
from tpsr_ros.io.model_io import load_model

__all__ = [
    "EXPERIMENTS",
    "THRESHOLD",
    "MemoryExperiment",
    "MemoryResult",
    "identical_from",
    "measure",
    "memory_steps",
    "register",
    "run",
    "simulate",
    "state_spread",
]

THRESHOLD = 0.1
Velocity = tuple[float, float]


@dataclass(frozen=True)
class MemoryExperiment:
    """Two action sequences from one start: their own first steps, then shared steps."""

    name: str
    start: tuple[float, float]
    first: tuple[Velocity, ...]
    second: tuple[Velocity, ...]
    shared: tuple[Velocity, ...]

    def actions(self, which: int) -> list[int]:
        """Action indices of run 0 or run 1."""
        own = self.first if which == 0 else self.second
        return [action_index(vx, vy) for vx, vy in (*own, *self.shared)]


_WEST, _EAST, _NORTH, _STILL = (-6.0, 0.0), (6.0, 0.0), (0.0, 6.0), (0.0, 0.0)
EXPERIMENTS = (
    MemoryExperiment(
        "paths",
        start=(22.5, 22.5),
        first=(_WEST, _WEST),
        second=(_EAST, _EAST),
        shared=(_NORTH,) * 4 + (_STILL,) * 30,
    ),
    MemoryExperiment(
        "stand-still",
        start=(22.5, 40.0),
        first=(_WEST,),
        second=(_EAST,),
        shared=(_STILL,) * 30,
    ),
)


@dataclass(frozen=True)
class Run:
    """One run of an experiment: actions, observations and true positions per step."""

    actions: np.ndarray  # (T,)
    observations: np.ndarray  # (T, k)
    positions: np.ndarray  # (T + 1, 2), the start first


@dataclass(frozen=True)
class MemoryResult:
    """Both runs of one experiment, their states and the memory measured on them."""

    experiment: MemoryExperiment
    runs: tuple[Run, Run]
    states: tuple[np.ndarray, np.ndarray]  # (T + 1, d) each, the initial state first
    relative_distance: np.ndarray  # (T + 1,)
    identical_from: int  # first step (1-based) from which every input pair is identical
    memory: int
    censored: bool  # the states were still apart when the run ended
    restart: int | None = None  # first step >= identical_from at which a run's filter restarted

    def describe(self) -> str:
        """``<name>: memory N steps`` (``at least N`` when censored)."""
        bound = "at least " if self.censored else ""
        return f"{self.experiment.name}: memory {bound}{self.memory} steps"


def simulate(
    experiment: MemoryExperiment, environment: str, sim: SimSettings | None = None
) -> tuple[Run, Run]:
    """Both runs of ``experiment`` in ``environment`` (camera: ``sim``) without execution
    noise."""
    config = (sim or SimSettings()).config(environment, noise_fraction=0.0)
    runs = []
    for which in (0, 1):
        env = RobotEnv(config, seed=0)
        image, info = env.reset(options={"position": experiment.start})
        actions = experiment.actions(which)
        images, positions = [], [info["position"]]
        for action in actions:
            image, _, _, _, info = env.step(action)
            images.append(image)
            positions.append(info["position"])
        runs.append(
            Run(
                np.array(actions, dtype=np.int64),
                images_to_observations(np.stack(images)),
                np.array(positions, dtype=np.float64),
            )
        )
    return runs[0], runs[1]


def identical_from(first: Run, second: Run) -> int:
    """First step (1-based) from which actions and observations of both runs are equal."""
    same = (first.actions == second.actions) & np.all(
        first.observations == second.observations, axis=1
    )
    differing = np.flatnonzero(~same)
    start = int(differing[-1]) + 2 if differing.size else 1
    if start > len(same):
        raise DataError(
            "the two runs never receive identical inputs here, so there is nothing to "
            "remember: the memory experiment needs a camera that confuses positions (partial)"
        )
    return start


def memory_steps(
    relative_distance: np.ndarray, start: int, threshold: float = THRESHOLD
) -> tuple[int, bool]:
    """Consecutive steps from ``start`` on whose relative distance exceeds ``threshold``.

    ``relative_distance[k]`` belongs to step ``k`` (index 0 is the initial state). Returns
    the count and whether the states were still apart at the last step (a lower bound).
    """
    apart = np.asarray(relative_distance)[start:] > threshold
    closed = np.flatnonzero(~apart)
    if closed.size == 0:
        return int(apart.size), True
    return int(closed[0]), False


@lru_cache(maxsize=2)
def _random_run(environment: str, steps: int, seed: int, sim: SimSettings | None) -> Trajectory:
    """The random run of :func:`state_spread`: the same for every model of an experiment."""
    return random_trajectory(environment, steps, seed, sim)


def state_spread(
    model: StateModel,
    environment: str,
    steps: int = 3000,
    seed: int = 7,
    sim: SimSettings | None = None,
) -> float:
    """Root mean square distance of the model's states from their mean over a random run.

    The first 10 % of the run is dropped so the spread describes the states the filter
    settles into, not its start-up.
    """
    trajectory = _random_run(environment, steps, seed, sim)
    states = model.track(trajectory.actions, trajectory.observations).states[steps // 10 :]
    spread = float(np.sqrt(np.mean(np.sum((states - states.mean(axis=0)) ** 2, axis=1))))
    if not np.isfinite(spread) or spread <= 0:
        raise DataError("the model's states do not vary over a random run: no scale to measure")
    return spread


def _track(model: StateModel, run: Run) -> tuple[np.ndarray, np.ndarray]:
    """States ``(T + 1, d)`` (the initial one first) and restarts ``(T + 1,)`` of one run."""
    track = model.track(run.actions, run.observations)
    states = np.vstack([model.initial_state()[None], track.states])
    return states, np.concatenate([[False], np.asarray(track.recovered, dtype=bool)])


def measure(
    model: StateModel,
    experiment: MemoryExperiment,
    environment: str,
    spread: float,
    threshold: float = THRESHOLD,
    sim: SimSettings | None = None,
) -> MemoryResult:
    """Run ``experiment``, track both runs with ``model`` and measure its memory.

    The count stops at the first filter restart of either run (see the module docstring).
    """
    runs = simulate(experiment, environment, sim)
    (first, restarts_0), (second, restarts_1) = _track(model, runs[0]), _track(model, runs[1])
    relative = np.linalg.norm(first - second, axis=1) / spread
    start = identical_from(*runs)
    memory, censored = memory_steps(relative, start, threshold)
    restarted = np.flatnonzero((restarts_0 | restarts_1)[start:])
    restart = int(restarted[0]) + start if restarted.size else None
    if restart is not None and restart < start + memory + int(censored):
        memory, censored = restart - start, False
    return MemoryResult(
        experiment, runs, (first, second), relative, start, memory, censored, restart
    )


def plot(results: Sequence[MemoryResult], threshold: float, path: Path, title: str) -> None:
    """Per experiment: true paths, the states' first two dimensions, the relative distance."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(results), 3, figsize=(13, 4.2 * len(results)), squeeze=False)
    colours = ("tab:blue", "tab:orange")
    for row, result in zip(axes, results, strict=True):
        start = result.identical_from
        for which, colour in enumerate(colours):
            xy = result.runs[which].positions
            row[0].plot(
                xy[:, 0], xy[:, 1], "-o", color=colour, markersize=3, label=f"run {which + 1}"
            )
            row[0].plot(*xy[start], "s", color=colour, markersize=8, mfc="none")
            states = result.states[which]
            row[1].plot(states[:, 0], states[:, 1], "-o", color=colour, markersize=3)
            row[1].plot(*states[start, :2], "s", color=colour, markersize=8, mfc="none")
        row[0].set(
            xlim=(0, 45),
            ylim=(0, 45),
            aspect="equal",
            xlabel="x (m)",
            ylabel="y (m)",
            title=f"{result.experiment.name}: true paths (square: inputs equal)",
        )
        row[0].legend(fontsize=8, loc="lower right")
        row[1].set(xlabel="state dim 1", ylabel="state dim 2", title="tracked states")
        steps = np.arange(len(result.relative_distance))
        row[2].plot(steps, result.relative_distance, "-o", color="black", markersize=3)
        row[2].axhline(threshold, color="tab:red", linestyle="--", label=f"threshold {threshold}")
        row[2].axvline(start, color="tab:green", label=f"inputs equal from step {start}")
        if result.restart is not None:
            row[2].axvline(
                result.restart, color="tab:purple", linestyle=":", label="filter restart"
            )
        row[2].set(xlabel="step", ylabel="|b1 - b2| / state spread", title=result.describe())
        row[2].set_ylim(bottom=0)
        row[2].legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def register(subparsers: Any) -> None:
    """Add the ``memory`` subcommand."""
    doc = "measure how many steps a model remembers (guide section 4.4)"
    parser = subparsers.add_parser(
        "memory", help=doc, description=doc[0].upper() + doc[1:] + ". " + __doc__.split("\n\n")[1]
    )
    parser.add_argument("model", type=Path, metavar="MODEL")
    parser.add_argument(
        "--environment",
        default="partial",
        choices=[e.value for e in Environment],
        help="(default: %(default)s)",
    )
    add_vertical_half_extent_option(parser, "the camera the model was learned with")
    parser.add_argument(
        "--threshold",
        type=float,
        default=THRESHOLD,
        help="relative distance below which two states count as merged (default: %(default)s)",
    )
    parser.add_argument(
        "--spread-steps",
        type=positive_int,
        default=3000,
        help="random steps over which the state spread is measured (default: %(default)s)",
    )
    parser.add_argument("-o", "--output", type=Path, required=True, help="directory for memory.png")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Measure both variants; print per-step distances, each variant and the summary."""
    if not (np.isfinite(args.threshold) and args.threshold > 0):
        raise ConfigError(f"--threshold must be a positive number, got {args.threshold}")
    model = load_model(args.model)
    sim = SimSettings(args.vertical_half_extent)
    spread = state_spread(model, args.environment, args.spread_steps, sim=sim)
    results = [
        measure(model, e, args.environment, spread, args.threshold, sim) for e in EXPERIMENTS
    ]
    for result in results:
        distances = " ".join(f"{d:.3g}" for d in result.relative_distance)
        restart = "" if result.restart is None else f"; filter restart at step {result.restart}"
        print(
            f"{result.experiment.name}: inputs identical from step {result.identical_from}"
            f"{restart}; relative distance by step: {distances}"
        )
        print(result.describe())
    args.output.mkdir(parents=True, exist_ok=True)
    png = args.output / "memory.png"
    plot(results, args.threshold, png, f"{args.model.name} in {args.environment}")
    print(f"wrote {png}", file=sys.stderr)
    worst = min(results, key=lambda r: r.memory)
    print(f"memory: {'at least ' if worst.censored else ''}{worst.memory} steps")
    return 0
