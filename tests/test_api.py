"""The array front door: Trajectory.from_arrays and fit."""

from __future__ import annotations

import numpy as np
import pytest

from tpsr_ros import PCAConfig, TPSRConfig, Trajectory, fit, make_episodes
from tpsr_ros.core.errors import DataError
from tpsr_ros.core.tpsr import fit_tpsr_episodes

S = 10**9


def test_from_arrays_splits_segments_at_gaps() -> None:
    obs = np.arange(12.0).reshape(6, 2)
    traj = Trajectory.from_arrays(
        np.array([0, 1, 2, 0, 1, 2]), obs, stamps=np.array([1, 2, 3, 5, 6, 7]) * S
    )
    assert traj.segment_bounds() == [(0, 3), (3, 6)]
    assert traj.n_actions == 3 and traj.image_shape == (1, 2)
    assert np.isnan(traj.positions).all() and np.isnan(traj.rewards).all()
    assert len(make_episodes(traj, 1, 1)) == 2  # one episode per segment, none across the gap


def test_from_arrays_refuses_bad_input() -> None:
    with pytest.raises(DataError):
        Trajectory.from_arrays(np.array([0.5, 1.0]), np.zeros((2, 3)))
    with pytest.raises(DataError):
        Trajectory.from_arrays(np.array([0, 3]), np.zeros((2, 3)), n_actions=3)
    with pytest.raises(DataError):
        Trajectory.from_arrays(np.array([0, 1]), np.zeros((2, 3)), stamps=[2, 1])


def test_fit_equals_the_episode_fit_and_fits_pca() -> None:
    rng = np.random.default_rng(3)
    actions = rng.integers(0, 2, size=900)
    observations = np.eye(4)[np.cumsum(actions) % 4] + 0.1 * rng.normal(size=(900, 4))
    traj = Trajectory.from_arrays(actions, observations)
    config = TPSRConfig(obs_dim=4, ht_dim=4, obs_centers=20, ht_centers=40, rank=3)
    model = fit(traj, config)
    reference = fit_tpsr_episodes(make_episodes(traj, 1, 1), config=config)
    np.testing.assert_array_equal(model.B, reference.B)
    np.testing.assert_array_equal(model.b_star, reference.b_star)
    pca = fit(traj, PCAConfig(dim=3))
    assert pca.method == "pca" and pca.track(actions, observations).states.shape == (900, 3)


def test_fit_arrays_with_the_defaults_sizes_them_to_a_small_system() -> None:
    """3000 steps of a ring of 6 cells (stay or move): the default preset, sized to 2997
    overlapping episodes of 6 values, learns states from which the cell can be read off."""
    rng = np.random.default_rng(0)
    actions = rng.integers(0, 2, size=3000)
    cells = np.cumsum(actions) % 6
    observations = np.eye(6)[cells] + 0.1 * rng.normal(size=(3000, 6))
    model = fit(actions, observations)
    assert model.config.center_selection == "kmeans" and model.config.action_pooling == 1.0
    assert model.config.history_length == 2 and model.config.refine_epochs == 30
    assert model.fit_info["episodes"] == 2997 and "refinement" in model.fit_info
    # rank 8 held to the 6 singular values of P_TH the data support (the ring's dimension);
    # the whitening of the shorter of history and test (one image) holds 6 values
    assert model.fit_info["sized"] == {"ht_dim": [10, 6], "rank": [8, 6]}
    states = model.track(actions, observations).states
    design = np.column_stack([states, np.ones(len(states))])
    half = len(states) // 2
    weights, *_ = np.linalg.lstsq(design[:half], np.eye(6)[cells[:half]], rcond=None)
    read = np.argmax(design[half:] @ weights, axis=1)
    assert (read == cells[half:]).mean() > 0.97  # 1.0 (0.946 with --preset best)
    with pytest.raises(Exception, match="actions \\(T,\\) and observations"):
        fit(actions)
    turning = fit(actions, observations, turning=True)  # a robot whose actions turn it
    assert turning.config.action_pooling == 0.5 and turning.fit_info["sized"]["rank"][0] == 16


def test_a_config_given_is_sized_where_it_keeps_the_default_presets_values() -> None:
    """fit(a, o) and fit(a, o, <the default preset's config>) are one model; a field set
    apart from the preset is kept as set, and a rank set above what the data support is
    refused, as `learner fit` treats its options."""
    from dataclasses import replace

    from tpsr_ros.core.presets import DEFAULT_PRESET, get_preset
    from tpsr_ros.io.model_io import model_fingerprint

    rng = np.random.default_rng(0)
    actions = rng.integers(0, 2, size=1500)
    observations = np.eye(6)[np.cumsum(actions) % 6] + 0.1 * rng.normal(size=(1500, 6))
    preset = get_preset(DEFAULT_PRESET).tpsr_config()
    default = fit(actions, observations)
    assert model_fingerprint(fit(actions, observations, preset)) == model_fingerprint(default)
    assert default.fit_info["sized"]["ht_centers"] == [1000, 748]  # half of 1497 episodes
    chosen = fit(actions, observations, replace(preset, ht_centers=100))
    assert chosen.config.ht_centers == 100 and "ht_centers" not in chosen.fit_info["sized"]
    with pytest.raises(DataError, match="rank 12 is above"):
        fit(actions, observations, replace(preset, rank=12))


def test_the_predictive_preset_carries_no_state_forward_for_a_robot_that_turns() -> None:
    """A carried start loses a turning robot's heading (docs/results.md, "the carried
    start"): the preset's turning changes set the carry to 0 and keep the rest."""
    from learner.experiment import default_config
    from tpsr_ros.core.presets import get_preset

    predictive = get_preset("predictive")
    turning = predictive.tpsr_config(turning=True)
    assert turning.refine_carry == 0.0 and predictive.tpsr_config().refine_carry == 0.3
    assert turning.refine_epochs == 30 and turning.p_th_tests == "from-current"
    assert turning.history_length == predictive.tpsr_config().history_length == 2
    assert (turning.rank, turning.action_pooling) == (16, 0.5)  # the turning robot's best
    assert default_config("drive", "predictive").tpsr.refine_carry == 0.0
    assert default_config("partial-strip", "predictive").tpsr.refine_carry == 0.3
