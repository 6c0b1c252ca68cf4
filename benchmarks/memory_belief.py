"""What an exact filter remembers in ``learner memory``'s two variants.

``python -m benchmarks.memory_belief [--environment partial-strip] [--rollouts 30]``

``learner memory`` starts both runs of a variant from the filter's initial state: the filter
has seen nothing. This script filters the same runs with the exact belief over the robot's
position (a grid Bayes filter that knows the simulator: the image of every 0.5 m cell,
each action's displacement with the training data's execution noise, walls that stop the
robot) from the uniform belief, and maps each belief to a predictive state that depends on
no learned model: the belief-weighted mean, over the places, of the next 10 images' top 10
principal components under random actions from that place (Monte Carlo, ``--rollouts``
continuations per place). It prints the two runs' distance step by step, divided by the
spread of such states over a random run's places, and the memory ``learner memory``'s rule
gives it (steps above 0.1 from the first identical step).

A variant whose exact belief stays under the threshold asks of a filter what no filter can
know from that start: the states of a filter that did remember would be wrong. Monte Carlo
noise adds to every distance (the states of the two runs are estimated apart). Not a timed
benchmark (not run by ``make bench``).
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy.ndimage import gaussian_filter1d

from learner import memory
from learner.simulated import SimSettings, random_trajectory
from sim_node import RobotEnv
from tpsr_ros.cli import positive_int
from tpsr_ros.core.actions import ACTIONS, NUM_ACTIONS
from tpsr_ros.core.episodes import images_to_observations

CELL = 0.5
"""Grid spacing of the belief (m)."""
HORIZON = 10
COMPONENTS = 10
MASS = 0.999
"""Share of a belief's mass whose places enter its predictive state (the rest is noise)."""


class PlaceGrid:
    """The room's cells, the image seen from each, and a belief's filter step."""

    def __init__(self, environment: str) -> None:
        self.config = SimSettings().config(environment, noise_fraction=0.0)  # the runs'
        self.noise = SimSettings().config(environment).noise_fraction  # the training data's
        margin = self.config.robot_radius
        self.centres = np.arange(margin, self.config.room_size - margin + 1e-9, CELL)
        n = self.centres.size
        env = RobotEnv(self.config, seed=0)
        images = []
        for x in self.centres:
            for y in self.centres:
                image, _ = env.reset(options={"position": (float(x), float(y))})
                images.append(image)
        self.images = images_to_observations(np.stack(images))  # (n * n, k), x-major
        steps = np.linalg.norm(np.diff(self.images.reshape(n, n, -1), axis=0), axis=2)
        self.sigma = 0.5 * float(np.median(steps[steps > 0]))  # a cell's worth of change

    @property
    def size(self) -> int:
        return self.centres.size

    def uniform(self) -> np.ndarray:
        return np.full((self.size, self.size), 1.0 / self.size**2)

    def step(self, belief: np.ndarray, action: int, observation: np.ndarray) -> np.ndarray:
        """The belief after ``action`` and then ``observation``."""
        for axis, velocity in enumerate(ACTIONS[action]):
            if velocity:
                belief = _moved(belief, int(round(velocity / CELL)), axis)
                noise = self.noise * abs(velocity) / CELL
                belief = gaussian_filter1d(belief, noise, axis=axis, mode="nearest")
        distance = np.sum((self.images - observation) ** 2, axis=1)
        likelihood = np.exp(-(distance - distance.min()) / (2 * self.sigma**2))
        belief = belief * likelihood.reshape(belief.shape)
        return belief / belief.sum()


def _moved(belief: np.ndarray, cells: int, axis: int) -> np.ndarray:
    """``belief`` moved ``cells`` along ``axis``; what would cross a wall stops at it."""
    moved = np.roll(belief, cells, axis=axis)
    edge, spill = (-1, slice(-cells, None)) if cells > 0 else (0, slice(None, -cells))
    index = [slice(None), slice(None)]
    index[axis] = spill
    stopped = belief[tuple(index)].sum(axis=axis)
    keep = [slice(None), slice(None)]
    keep[axis] = slice(None, cells) if cells > 0 else slice(cells, None)
    moved[tuple(keep)] = 0.0
    index[axis] = edge
    moved[tuple(index)] += stopped
    return moved


class PlaceStates:
    """Each place's predictive state, estimated on demand and kept."""

    def __init__(self, environment: str, grid: PlaceGrid, rollouts: int) -> None:
        run = random_trajectory(environment, 6000, seed=3)
        self.mean = run.observations.mean(axis=0)
        _, _, vt = np.linalg.svd(run.observations[::3] - self.mean, full_matrices=False)
        self.basis = vt[:COMPONENTS].T
        self.grid, self.rollouts = grid, rollouts
        self.env = RobotEnv(SimSettings().config(environment), seed=1)
        self.rng = np.random.default_rng(2)
        self.known: dict[int, np.ndarray] = {}
        self.run_places = run.positions[::30, :2]

    def of_cell(self, cell: int) -> np.ndarray:
        """E[the next images' components | the robot at ``cell``] (random actions)."""
        if cell not in self.known:
            x, y = divmod(cell, self.grid.size)
            place = (float(self.grid.centres[x]), float(self.grid.centres[y]))
            total = np.zeros(HORIZON * COMPONENTS)
            for actions in self.rng.integers(0, NUM_ACTIONS, (self.rollouts, HORIZON)):
                self.env.reset(options={"position": place})
                images = np.stack([self.env.step(int(a))[0] for a in actions])
                total += ((images_to_observations(images) - self.mean) @ self.basis).ravel()
            self.known[cell] = total / self.rollouts
        return self.known[cell]

    def of_belief(self, belief: np.ndarray) -> np.ndarray:
        """The belief-weighted mean of its places' states (the places holding ``MASS``)."""
        flat = belief.ravel()
        order = np.argsort(flat)[::-1]
        kept = order[: int(np.searchsorted(np.cumsum(flat[order]), MASS)) + 1]
        weights = flat[kept] / flat[kept].sum()
        return weights @ np.array([self.of_cell(int(c)) for c in kept])

    def spread(self) -> float:
        """RMS distance from their mean of the states of a random run's places."""
        cells = np.clip(np.rint((self.run_places - self.grid.centres[0]) / CELL), 0,
                        self.grid.size - 1).astype(int)  # fmt: skip
        states = np.array([self.of_cell(int(x * self.grid.size + y)) for x, y in cells])
        return float(np.sqrt(np.mean(np.sum((states - states.mean(axis=0)) ** 2, axis=1))))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.memory_belief")
    parser.add_argument("--environment", choices=["partial", "partial-strip"],
                        default="partial-strip")  # fmt: skip
    parser.add_argument("--rollouts", type=positive_int, default=30)
    parser.add_argument("--steps", type=positive_int, default=8,
                        help="steps measured from the first identical one")
    args = parser.parse_args(argv)
    grid = PlaceGrid(args.environment)
    places = PlaceStates(args.environment, grid, args.rollouts)
    spread = places.spread()
    print(f"{args.environment}: {grid.size}x{grid.size} places, image tolerance "
          f"{grid.sigma:.3f}; spread of the places' states {spread:.3f}", flush=True)  # fmt: skip
    for experiment in memory.EXPERIMENTS:
        runs = memory.simulate(experiment, args.environment)
        start = memory.identical_from(*runs)
        states = []
        for run in runs:
            belief, trace = grid.uniform(), []
            for step, (action, observation) in enumerate(zip(run.actions, run.observations)):
                if step >= start + args.steps - 1:
                    break
                belief = grid.step(belief, int(action), observation)
                trace.append(places.of_belief(belief))
            states.append(np.array(trace))
        relative = np.linalg.norm(states[0] - states[1], axis=1) / spread
        remembered, _ = memory.memory_steps(np.concatenate([[0.0], relative]), start)
        print(f"{experiment.name}: inputs identical from step {start}; relative distance by "
              f"step: {' '.join(f'{v:.3f}' for v in relative)}; memory {remembered} steps "
              f"(of {args.steps} measured)", flush=True)


if __name__ == "__main__":
    main()
