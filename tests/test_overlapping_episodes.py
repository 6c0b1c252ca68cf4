"""Overlapping episodes: every window of m + 1 + n steps a sample, within segments."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from tpsr_ros.core.episode_stream import EpisodeCutter
from tpsr_ros.core.episodes import Trajectory, make_episodes
from tpsr_ros.core.errors import ConfigError
from tpsr_ros.core.learn import fit_tpsr_trajectory
from tpsr_ros.core.tpsr import TPSRConfig


def trajectory_with_a_gap() -> Trajectory:
    rng = np.random.default_rng(3)
    stamps = np.concatenate([np.arange(1, 11), np.arange(20, 27)]) * 1_000_000_000
    obs = rng.normal(size=(17, 4))
    return Trajectory.from_arrays(rng.integers(0, 2, size=17), obs, stamps=stamps, n_actions=2)


def test_every_window_inside_each_segment_is_an_episode() -> None:
    data = trajectory_with_a_gap()  # segments of 10 and 7 steps
    episodes = make_episodes(data, 2, 1, stride=1)
    assert len(episodes) == (10 - 4 + 1) + (7 - 4 + 1)
    first = np.concatenate([np.arange(0, 7), np.arange(10, 14)])
    np.testing.assert_array_equal(episodes.observation, data.observations[first + 2])
    np.testing.assert_array_equal(episodes.history[:, :4], data.observations[first])
    np.testing.assert_array_equal(episodes.test, data.observations[first + 3])
    guide = make_episodes(data, 2, 1)  # the guide's: one every 4 steps
    np.testing.assert_array_equal(
        guide.observation, make_episodes(data, 2, 1, stride=4).observation
    )
    assert len(guide) == 2 + 1


def test_the_config_sets_the_stride_and_the_fit_uses_it() -> None:
    assert TPSRConfig().episode_stride == 3
    assert TPSRConfig(history_length=2, test_length=3).episode_stride == 6
    assert TPSRConfig(overlapping_episodes=True).episode_stride == 1
    rng = np.random.default_rng(0)
    actions = rng.integers(0, 2, size=1500)
    obs = np.eye(6)[np.cumsum(actions) % 6] + 0.1 * rng.normal(size=(1500, 6))
    data = Trajectory.from_arrays(actions, obs)
    cfg = TPSRConfig(obs_dim=5, ht_dim=5, obs_centers=50, ht_centers=50, rank=4)
    model = fit_tpsr_trajectory(data, replace(cfg, overlapping_episodes=True))
    assert model.fit_info["episodes"] == 1500 - 2
    assert fit_tpsr_trajectory(data, cfg).fit_info["episodes"] == 500


def test_bad_strides_are_refused() -> None:
    data = trajectory_with_a_gap()
    with pytest.raises(ConfigError, match="stride"):
        make_episodes(data, 1, 1, stride=0)
    with pytest.raises(ConfigError, match="stride"):
        EpisodeCutter(1, 1, stride=4)
    with pytest.raises(ConfigError, match="overlapping_episodes"):
        TPSRConfig(overlapping_episodes=1)  # type: ignore[arg-type]


def test_kernel_centres_come_from_every_fourth_window_or_as_many_as_short_data_need() -> None:
    """Overlapping windows of two images of history: centres are chosen from one window in
    every m + 1 + n = 4, and from more where that would leave fewer rows than centres."""
    from tpsr_ros.core.tpsr_stages import centre_stride, kernel_centres

    cfg = TPSRConfig(history_length=2, overlapping_episodes=True, ht_centers=1000,
                     obs_centers=500, center_selection="first")  # fmt: skip
    assert [centre_stride(cfg, rows) for rows in (24000, 4000, 3999, 2997, 1999)] == [
        4, 4, 3, 2, 1,
    ]
    assert centre_stride(replace(cfg, overlapping_episodes=False), 24000) == 1
    rows = np.arange(2997 * 2, dtype=np.float64).reshape(2997, 2)
    history, test, observation = kernel_centres(rows, rows, rows, cfg)
    np.testing.assert_array_equal(history, rows[::2][:1000])  # every second window's
    assert test.shape == (1000, 2) and observation.shape == (500, 2)
