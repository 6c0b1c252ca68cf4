"""learner memory: the guide's memory experiment (section 4.4), checked on known memories."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import dataclass

import numpy as np
import pytest

from learner.memory import (
    EXPERIMENTS,
    identical_from,
    measure,
    memory_steps,
    simulate,
    state_spread,
)
from learner.simulated import random_trajectory
from tpsr_ros.core.errors import DataError
from tpsr_ros.core.pca_baseline import PCAConfig, fit_pca
from tpsr_ros.core.state_model import Track


@dataclass(frozen=True)
class ShiftRegister:
    """A planted model that remembers exactly ``memory`` past steps besides the current one.

    Its state is the current input and the ``memory`` previous ones (action one-hot and the
    mean of the observation), so two runs whose inputs become equal at step s have states
    that differ at steps s .. s + memory - 1 and are equal from s + memory on.
    """

    memory: int
    n_actions: int = 25

    @property
    def slot_size(self) -> int:
        return self.n_actions + 1

    def _slot(self, action: int, observation: np.ndarray) -> np.ndarray:
        return np.concatenate([np.eye(self.n_actions)[action], [observation.mean()]])

    def initial_state(self) -> np.ndarray:
        return np.zeros((self.memory + 1) * self.slot_size)

    def track(self, actions, observations, initial=None) -> Track:
        window = [np.zeros(self.slot_size)] * (self.memory + 1)
        states = []
        for action, observation in zip(actions, observations, strict=True):
            window = [*window[1:], self._slot(int(action), observation)]
            states.append(np.concatenate(window))
        n = len(states)
        return Track(np.array(states), np.full(n, np.nan), np.zeros(n, dtype=bool))


@pytest.mark.parametrize("memory", [0, 1, 3, 10, 25])
def test_the_measure_finds_a_planted_memory(memory):
    model = ShiftRegister(memory)
    spread = state_spread(model, "partial", steps=500)
    for experiment in EXPERIMENTS:
        result = measure(model, experiment, "partial", spread)
        assert result.memory == memory and not result.censored, result.describe()


@dataclass(frozen=True)
class ImageRegister(ShiftRegister):
    """A shift register of whole observations: blind to the actions, so the stand-still
    variant (the same image after different actions) finds nothing to remember."""

    @property
    def slot_size(self) -> int:
        return 16 * 16 * 3  # the simulator's camera

    def _slot(self, action: int, observation: np.ndarray) -> np.ndarray:
        return np.asarray(observation, dtype=float)


def test_experiments_record_the_smaller_memory_and_the_paths_variants_own():
    from learner.measures import memory_of
    from learner.representations import ModelTracker

    figures = memory_of(ModelTracker(ImageRegister(3), "planted"), "partial")
    assert (figures.steps, figures.paths_steps) == (0.0, 3.0) and figures.paths_distance > 0.1
    both = memory_of(ModelTracker(ShiftRegister(2), "planted"), "partial")
    assert (both.steps, both.paths_steps) == (2.0, 2.0)


def test_a_memory_longer_than_the_run_is_reported_as_a_lower_bound():
    model = ShiftRegister(100)
    spread = state_spread(model, "partial", steps=500)
    result = measure(model, EXPERIMENTS[1], "partial", spread)
    shared = len(EXPERIMENTS[1].shared)
    assert result.censored and result.memory == shared
    assert result.describe() == f"stand-still: memory at least {shared} steps"


@dataclass(frozen=True)
class RestartingRegister(ShiftRegister):
    """A shift register whose filter reports a restart at step ``restart`` (1-based)."""

    restart: int = 1

    def track(self, actions, observations, initial=None) -> Track:
        states, normalizers, recovered = super().track(actions, observations, initial)
        recovered = recovered.copy()
        if len(recovered) >= self.restart:
            recovered[self.restart - 1] = True
        return Track(states, normalizers, recovered)


def test_a_filter_restart_ends_the_memory():
    experiment = EXPERIMENTS[1]
    start = identical_from(*simulate(experiment, "partial"))
    model = RestartingRegister(100, restart=start + 4)
    spread = state_spread(model, "partial", steps=500)
    result = measure(model, experiment, "partial", spread)
    assert (result.memory, result.censored, result.restart) == (4, False, start + 4)
    early = RestartingRegister(100, restart=start - 1)  # before the inputs are equal: ignored
    assert measure(early, experiment, "partial", spread).restart is None


def test_pca_has_no_memory():
    train = random_trajectory("partial", 3000, seed=1)
    model = fit_pca(train.observations, n_actions=train.n_actions, config=PCAConfig(dim=3))
    spread = state_spread(model, "partial", steps=1000)
    for experiment in EXPERIMENTS:
        result = measure(model, experiment, "partial", spread)
        assert result.memory == 0
        # a state of the current image only: the states are equal exactly where images are
        same_image = np.all(result.runs[0].observations == result.runs[1].observations, axis=1)
        assert np.array_equal(result.relative_distance[1:] == 0, same_image)


def test_the_runs_reach_look_alike_positions_in_partial_only():
    for experiment in EXPERIMENTS:
        first, second = simulate(experiment, "partial")
        start = identical_from(first, second)
        # different places, same inputs: only memory can tell them apart
        assert np.all(np.abs(first.positions[start:, 0] - second.positions[start:, 0]) >= 12)
        assert np.all(first.observations[start - 1 :] == second.observations[start - 1 :])
        assert first.actions[start - 2] != second.actions[start - 2] or not np.array_equal(
            first.observations[start - 2], second.observations[start - 2]
        )
        with pytest.raises(DataError, match="needs a camera that confuses positions"):
            identical_from(*simulate(experiment, "full"))


def test_memory_steps_counts_from_the_first_identical_step():
    distance = np.array([0.0, 0.5, 0.9, 0.3, 0.2, 0.05, 0.4])
    assert memory_steps(distance, 3) == (2, False)  # steps 3 and 4; merged at 5
    assert memory_steps(distance, 5) == (0, False)
    assert memory_steps(distance, 6) == (1, True)


@pytest.mark.slow
def test_memory_command(tmp_path, capsys):
    from cli_support import run_entry

    from sim_node import SimConfig
    from sim_node.generate import generate_bag

    generate_bag(tmp_path / "train", SimConfig(environment="partial"), 3000, seed=2)
    fit = ["fit", str(tmp_path / "train"), "-o", str(tmp_path / "model.npz"),
           "--ht-centers", "200", "--obs-centers", "100"]
    assert run_entry(fit, capsys)[0] == 0
    command = [sys.executable, "-m", "learner", "memory", str(tmp_path / "model.npz"),
               "--spread-steps", "500", "-o", str(tmp_path / "out")]
    result = subprocess.run(command, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    lines = result.stdout.strip().splitlines()
    assert lines[-1].startswith("memory: ") and lines[-1].endswith(" steps")
    assert any(line.startswith("paths: memory") for line in lines)
    assert any(line.startswith("stand-still: memory") for line in lines)
    assert (tmp_path / "out" / "memory.png").stat().st_size > 20_000
    code, _, err = run_entry([*command[3:5], "--environment", "full", "-o", str(tmp_path / "o2")],
                             capsys)
    assert code != 0 and err.count("\n") == 1
    assert "confuses positions" in err
