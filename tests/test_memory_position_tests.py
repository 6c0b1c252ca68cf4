"""The position-test diagnostic of the memory section (benchmarks/memory_position_tests.py)."""

from __future__ import annotations

import numpy as np

from benchmarks.memory_position_tests import position_codes, with_position_tests
from tpsr_ros.core.episodes import Trajectory, make_episodes


def test_position_codes_approximate_a_gaussian_kernel_of_the_given_width():
    rng = np.random.default_rng(1)
    points = rng.uniform(0, 10, size=(30, 2))
    codes = position_codes(points, 20_000, width=2.5, seed=3)
    squared = np.sum((points[:, None] - points[None]) ** 2, axis=2)
    kernel = np.exp(-squared / (2 * 2.5**2))
    assert np.abs(codes @ codes.T - kernel).max() < 0.05


def test_each_test_step_gets_the_code_of_its_own_position():
    steps, k = 23, 6
    rng = np.random.default_rng(2)
    positions = rng.uniform(0, 45, size=(steps, 2))
    stamps = np.arange(steps, dtype=np.int64) * 10**9
    stamps[12:] += 10**9  # a gap: the second segment starts at row 12
    trajectory = Trajectory.from_arrays(
        rng.integers(0, 3, steps), rng.normal(size=(steps, k)), stamps=stamps,
        n_actions=3, positions=positions,
    )
    episodes = make_episodes(trajectory, history_length=2, test_length=2)
    replaced = with_position_tests(trajectory, episodes, width=2.5)
    # spans of 5 rows from each segment's start: 0-4, 5-9 | 12-16, 17-21; tests are the last 2
    rows = np.array([[3, 4], [8, 9], [15, 16], [20, 21]])
    expected = position_codes(positions[rows], k, 2.5).reshape(4, 2 * k)
    np.testing.assert_array_equal(replaced.test, expected)
    np.testing.assert_array_equal(replaced.history, episodes.history)
    np.testing.assert_array_equal(replaced.observation, episodes.observation)
