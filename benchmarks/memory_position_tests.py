"""Which limit binds the TPSR's memory in ``partial``: its tests or its estimator.

``python -m benchmarks.memory_position_tests [--steps 150000] [--width 2.5] [--set NAME=VALUE]``

Fits two TPSRs on the same random run with the same histories, centres, rank and
operator estimator, and runs ``learner memory``'s measure on both:

- ``images``: the usual tests, the next ``n`` images;
- ``positions``: tests replaced by a smooth code of the robot's true next ``n`` positions
  (random Fourier features, ``k`` of them per step like an image's ``k`` values: a
  Gaussian kernel of ``--width`` metres; Rahimi & Recht 2007).

The true position is used for training only: both models filter from images and actions,
so the measure tracks them exactly as it tracks any model. If the position-test model
remembers much longer, what the tests can tell apart limits the memory, not how the
operators are estimated from the histories. A diagnostic, not a timed benchmark (not run
by ``make bench``); docs/results.md, Memory, reports its figures.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np

from learner import memory
from learner.overrides import apply_overrides
from learner.simulated import random_trajectory
from tpsr_ros.core.episodes import Episodes, Trajectory, episode_starts, make_episodes
from tpsr_ros.core.tpsr import TPSRConfig, fit_tpsr_episodes

ENVIRONMENT = "partial"
BASE = TPSRConfig(history_length=4, rank=10, history_action_weight=1.0, state_clip_quantile=0.05)
"""Histories of 4 with their actions (the memory section's estimator), tests of 1."""


def position_codes(positions: np.ndarray, size: int, width: float, seed: int = 0) -> np.ndarray:
    """``size`` random Fourier features of ``(..., 2)`` positions: ``z(p) . z(q)`` approximates
    ``exp(-|p - q|^2 / (2 width^2))``."""
    rng = np.random.default_rng(seed)
    frequencies = rng.standard_normal((2, size)) / width
    phases = rng.uniform(0.0, 2.0 * np.pi, size)
    return np.sqrt(2.0 / size) * np.cos(positions @ frequencies + phases)


def with_position_tests(trajectory: Trajectory, episodes: Episodes, width: float) -> Episodes:
    """``episodes`` with each test step's image replaced by the code of its true position."""
    m, n = episodes.history_length, episodes.test_length
    first = episode_starts(trajectory, m + 1 + n)[: len(episodes)]
    test_rows = (first + m)[:, None] + 1 + np.arange(n)
    size = trajectory.observations.shape[1]
    codes = position_codes(trajectory.positions[test_rows], size, width)
    return dataclasses.replace(episodes, test=codes.reshape(len(episodes), n * size))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.memory_position_tests")
    parser.add_argument("--steps", type=int, default=150_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--width", type=float, default=2.5, help="position kernel width, m")
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE")
    args = parser.parse_args(argv)
    cfg = apply_overrides({"tpsr": BASE}, args.set)["tpsr"]
    trajectory = random_trajectory(ENVIRONMENT, args.steps, args.seed)
    episodes = make_episodes(trajectory, cfg.history_length, cfg.test_length)
    print(f"{args.steps} steps of {ENVIRONMENT}, seed {args.seed}, {len(episodes)} episodes; {cfg}")
    for name, tests in (
        ("images", episodes),
        (f"positions ({args.width:g} m)", with_position_tests(trajectory, episodes, args.width)),
    ):
        start = time.perf_counter()
        model = fit_tpsr_episodes(tests, config=cfg)
        seconds = time.perf_counter() - start
        spread = memory.state_spread(model, ENVIRONMENT)
        parts = []
        for experiment in memory.EXPERIMENTS:
            result = memory.measure(model, experiment, ENVIRONMENT, spread)
            first = result.relative_distance[result.identical_from :][:6]
            restart = f", filter restart at step {result.restart}" if result.restart else ""
            distances = ", ".join(f"{d:.3f}" for d in first)
            parts.append(f"{result.describe()}{restart} (distance {distances}, ...)")
        print(f"tests of {name} (fit {seconds:.1f} s):", flush=True)
        for part in parts:
            print(f"  {part}", flush=True)


if __name__ == "__main__":
    main()
