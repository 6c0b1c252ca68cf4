"""The streamed fit (tpsr_ros.core.streamed_fit) learns the in-memory fit's model from chunks."""

from __future__ import annotations

import re
from dataclasses import replace

import numpy as np
import pytest
from learning_fixtures import example_pomdp, one_hot

from tpsr_ros.core.episodes import Trajectory, make_episodes
from tpsr_ros.core.episode_stream import refinement_steps
from tpsr_ros.core.errors import ConfigError, DataError
from tpsr_ros.core.learn import fit_tpsr_trajectory
from tpsr_ros.core.filtering import observation_weights
from tpsr_ros.core.moments import Moments
from tpsr_ros.core.pca_baseline import PCAConfig
from tpsr_ros.core.streamed_fit import (
    ChunkEngine,
    EpisodeCutter,
    fit_pca_streamed,
    fit_tpsr_streamed,
)
from tpsr_ros.core.tpsr import TPSRConfig, TPSRModel, fit_tpsr_episodes
from tpsr_ros.core.whitening import Whitening

ARRAYS = ("obs_mean", "obs_whitening", "obs_centers", "b_star", "b_inf", "B", "singular_values")


def smooth_trajectory(steps: int, k: int = 12, n_actions: int = 3, seed: int = 0) -> Trajectory:
    """A random walk seen through a fixed nonlinear map, with gaps (several segments)."""
    rng = np.random.default_rng(seed)
    actions = rng.integers(n_actions, size=steps)
    moves = np.array([[-0.3, 0.0], [0.3, 0.1], [0.0, -0.3]])[actions]
    position = np.cumsum(moves + 0.05 * rng.standard_normal((steps, 2)), axis=0)
    basis = rng.standard_normal((2, k))
    obs = 5.0 + np.tanh(np.sin(position) @ basis) + 0.01 * rng.standard_normal((steps, k))
    stamps = np.arange(1, steps + 1, dtype=np.int64) * 10**9
    for cut in (steps // 3, steps // 3 + 17, 2 * steps // 3 + 1):  # three gaps, one tiny run
        stamps[cut:] += 5 * 10**9
    return Trajectory.from_arrays(actions, obs, stamps=stamps, n_actions=n_actions)


def chunks_of(trajectory: Trajectory, size: int):
    """A chunk source: slices of ``size`` steps (segments continue across them)."""

    def source():
        for start in range(0, len(trajectory), size):
            yield trajectory.rows(start, start + size)

    return source


def relative(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(a - b).max() / max(np.abs(b).max(), 1e-300))


def assert_same_model(streamed: TPSRModel, reference: TPSRModel, tol: float = 1e-9) -> None:
    for name in ARRAYS:
        a, b = getattr(streamed, name), getattr(reference, name)
        assert a.shape == b.shape, name
        assert relative(a, b) <= tol, (name, relative(a, b))
    for key, ratio in reference.explained_variance.items():
        assert relative(streamed.explained_variance[key], ratio) <= tol, key
    assert streamed.fit_info["training_episodes"] == reference.fit_info["training_episodes"]
    assert streamed.fit_info["samples_per_action"] == reference.fit_info["samples_per_action"]


@pytest.fixture(scope="module")
def trajectory() -> Trajectory:
    return smooth_trajectory(2400)


SMALL = {"obs_dim": 4, "ht_dim": 5, "obs_centers": 30, "ht_centers": 60, "rank": 3}


CUTS = [
    *((size, lengths, limit, None) for size in (1, 7, 100, 1000, 5000)
      for lengths in ((1, 1), (2, 2), (2, 1)) for limit in (None, 1, 311)),
    *((size, lengths, limit, stride) for size in (7, 100) for lengths in ((1, 1), (2, 1))
      for limit in (None, 311) for stride in (1, 2)),
]  # fmt: skip
"""Chunk sizes, lengths, limits and strides cut: the guide's episodes (stride None) in every
combination, overlapping ones (1) and a stride between (2) across chunk boundaries."""


@pytest.mark.parametrize(("size", "lengths", "max_episodes", "stride"), CUTS)
def test_cutter_cuts_the_episodes_of_the_whole(trajectory, size, lengths, max_episodes, stride):
    m, n = lengths
    whole = make_episodes(trajectory, m, n, max_episodes=max_episodes, stride=stride)
    cutter = EpisodeCutter(m, n, max_episodes, stride)
    parts = [e for e in map(cutter.cut, chunks_of(trajectory, size)()) if e is not None]
    for name in ("history", "observation", "action", "test", "stamps"):
        joined = np.concatenate([getattr(p, name) for p in parts])
        np.testing.assert_array_equal(joined, getattr(whole, name), err_msg=name)
    last = int(np.searchsorted(trajectory.stamps, whole.stamps[-1])) + 1 + n
    assert cutter.used == last  # the steps the episodes use, as the fit in memory counts them


@pytest.mark.parametrize(
    ("changes", "size", "max_episodes"),
    [
        ({}, 97, None),  # chunk boundaries inside episodes
        ({}, 2400, 500),
        ({"center_selection": "kmeans"}, 250, None),
        ({"center_selection": "kmeans"}, 64, 400),
        ({"history_length": 2, "test_length": 2}, 301, None),
        ({"history_length": 2, "test_length": 2, "p_th_tests": "from-current"}, 55, None),
        ({"normalize_ht_features": True, "p_th_tests": "from-current"}, 1000, 650),
        ({"action_pooling": 0.6}, 301, None),
        ({"obs_variance": 0.9}, 301, None),
        ({"overlapping_episodes": True}, 97, None),
        ({"overlapping_episodes": True, "history_length": 2, "center_selection": "kmeans"},
         64, 700),  # fmt: skip
    ],
)
def test_streamed_fit_equals_the_in_memory_fit(trajectory, changes, size, max_episodes):
    cfg = TPSRConfig(**SMALL, **changes)
    m, n = cfg.history_length, cfg.test_length
    episodes = make_episodes(
        trajectory, m, n, max_episodes=max_episodes, stride=cfg.episode_stride
    )
    reference = fit_tpsr_episodes(episodes, config=cfg)
    stages: list[str] = []
    streamed = fit_tpsr_streamed(
        chunks_of(trajectory, size), config=cfg, max_episodes=max_episodes, progress=stages.append
    )
    assert_same_model(streamed, reference)
    assert streamed.fit_info["episodes"] == len(episodes)
    if max_episodes is None:
        assert streamed.fit_info["steps"] == len(trajectory)
        assert streamed.fit_info["segments"] == len(trajectory.segment_bounds()) == 4
        assert streamed.fit_info["stamps_ns"] == [trajectory.stamps[0], trajectory.stamps[-1]]
    assert stages[0].startswith("pass 1") and "SVD" in stages
    assert set(streamed.fit_info["timings"]) == set(stages)


@pytest.mark.parametrize(
    ("refine_steps", "max_episodes"), [(50_000, None), (50_000, 400), (700, None)]
)
def test_streamed_refinement_equals_the_in_memory_one(trajectory, refine_steps, max_episodes):
    """The steps refined on are read once more: all of them, those the episodes use, or the
    first ``refine_steps``; on this small system the refined model is the fit in memory's
    to 1e-6 (the search follows the spectral start's last bits, which agree to 1e-9)."""
    cfg = TPSRConfig(**SMALL, overlapping_episodes=True, p_th_tests="from-current",
                     refine_epochs=3, refine_window=8, refine_carry=0.3,
                     refine_steps=refine_steps)  # fmt: skip
    reference = fit_tpsr_trajectory(trajectory, cfg, max_episodes=max_episodes)
    lines: list[str] = []
    streamed = fit_tpsr_streamed(
        chunks_of(trajectory, 97), config=cfg, max_episodes=max_episodes, progress=lines.append
    )
    spectral = replace(cfg, refine_epochs=0)
    unrefined = fit_tpsr_trajectory(trajectory, spectral, max_episodes=max_episodes)
    assert relative(streamed.B, unrefined.B) > 1e-3  # the refinement moved the operators
    assert_same_model(streamed, reference, tol=1e-6)
    assert "refinement through the filter" in lines
    used = refinement_steps(chunks_of(trajectory, 97)(), cfg, max_episodes)
    expected = {(50_000, None): len(trajectory), (700, None): 700}.get(
        (refine_steps, max_episodes), 399 + 3  # overlapping: episode k starts at step k
    )
    assert len(used) == expected
    np.testing.assert_array_equal(used.observations, trajectory.observations[:expected])


def test_an_engine_refines_only_with_a_source_of_steps(trajectory):
    cfg = TPSRConfig(**SMALL, refine_epochs=2)
    engine = ChunkEngine(chunks_of(trajectory, 500))
    with pytest.raises(ConfigError, match="refine_source"):
        fit_tpsr_streamed(engine, config=cfg)
    refined = fit_tpsr_streamed(engine, config=cfg, refine_source=chunks_of(trajectory, 500))
    assert refined.fit_info["refinement"]["iterations"] >= 1


def test_large_blocks_and_small_blocks_agree(trajectory, monkeypatch):
    """Features are summed block by block: many small blocks give the same sums."""
    import tpsr_ros.core.streamed_fit as streamed_fit

    cfg = TPSRConfig(**SMALL)
    one_block = fit_tpsr_streamed(chunks_of(trajectory, 500), config=cfg)
    monkeypatch.setattr(streamed_fit, "block_rows", lambda n_features: 13)
    many_blocks = fit_tpsr_streamed(chunks_of(trajectory, 500), config=cfg)
    assert_same_model(many_blocks, one_block, tol=1e-12)


def test_merged_moments_whiten_like_the_whole_data():
    rng = np.random.default_rng(3)
    x = 1e4 + rng.standard_normal((1000, 6)) @ rng.standard_normal((6, 6))  # large mean
    merged = Moments.empty(6)
    for part in np.array_split(x, [1, 2, 300, 301, 700]):
        merged = merged.merge(Moments.of(part))
    assert merged.count == 1000
    np.testing.assert_allclose(merged.mean, x.mean(axis=0), rtol=1e-14)
    np.testing.assert_allclose(merged.scatter / 999, np.cov(x.T), rtol=1e-9)
    whole = Whitening.fit(x, 4)
    pieces = Whitening.from_moments(merged, 4)
    np.testing.assert_allclose(pieces.matrix_, whole.matrix_, rtol=1e-9, atol=1e-12)


def test_data_that_change_between_the_passes_are_refused(trajectory):
    calls = []

    def source():
        calls.append(1)
        steps = len(trajectory) if len(calls) == 1 else len(trajectory) // 2
        return chunks_of(trajectory, 500)() if steps == len(trajectory) else iter(
            [chunks_of(trajectory, steps)().__next__()]
        )

    with pytest.raises(DataError, match=r"second pass .* gave .* episodes, the first"):
        fit_tpsr_streamed(source, config=TPSRConfig(**SMALL))


def test_too_little_data_is_refused_before_the_second_pass(trajectory):
    calls = []

    def source():
        calls.append(1)
        return chunks_of(trajectory, 500)()

    with pytest.raises(DataError, match="too few for 1000 kernel centres"):
        fit_tpsr_streamed(source, config=TPSRConfig(ht_centers=1000, rank=2), max_episodes=900)
    assert len(calls) == 1


def test_data_without_one_whole_episode_are_refused_like_the_in_memory_fit(trajectory):
    short = chunks_of(trajectory.rows(0, 2), 1)  # 2 steps: no history + current + test run
    message = re.escape(
        "no usable episodes: no run of 3 consecutive steps (history 1 + current + test 1)"
    )
    with pytest.raises(DataError, match=message + " in 2 steps"):
        make_episodes(trajectory.rows(0, 2), 1, 1)
    with pytest.raises(DataError, match=message + " in the data"):
        fit_tpsr_streamed(short, config=TPSRConfig(**SMALL))
    with pytest.raises(DataError, match=message + " in the data"):
        fit_pca_streamed(short, config=PCAConfig(dim=2))


def test_streamed_fit_of_a_known_pomdp_predicts_its_observations():
    """Ground truth: on the small POMDP the streamed model's one-step predictions from b_*
    match the exact ones (as tests/test_tpsr_known_answer.py checks the in-memory fit)."""
    pomdp = example_pomdp()
    symbols, actions = pomdp.sample(30_000, seed=1)
    trajectory = Trajectory.from_arrays(actions, one_hot(symbols, pomdp.n_obs), n_actions=2)
    cfg = TPSRConfig(
        obs_dim=3, ht_dim=3, obs_centers=40, ht_centers=40, sigma_obs=0.05, sigma_ht=0.05,
        rank=3, p_th_tests="from-current",
    )  # fmt: skip
    model = fit_tpsr_streamed(chunks_of(trajectory, 4001), config=cfg)
    weights = observation_weights(model, np.eye(pomdp.n_obs))
    members = (weights > 0).astype(float)
    state = model.initial_state()
    for action in range(pomdp.n_actions):
        per_centre = np.einsum("oij,j->oi", model.B[action], state) @ model.b_inf
        predicted = members @ per_centre / (model.b_inf @ state)
        exact = pomdp.predict(pomdp.stationary(), action)
        assert np.abs(predicted - exact).max() < 0.02


@pytest.mark.parametrize(
    "options",
    [
        {"center_selection": "kmeans", "normalize_ht_features": True, "rank": 4,
         "action_pooling": 1.0, "obs_variance": 0.95},  # the default preset's switches
        {"history_length": 2, "test_length": 2, "history_action_weight": 1.0,
         "test_action_weight": 0.5, "p_th_tests": "from-current", "state_clip_quantile": 0.05},
        {"state_clip_quantile": 0.1, "action_pooling": 0.5, "test_action_weight": 1.0},
    ],
    ids=["preset-best", "actions-window-box", "box-pooling"],
)
def test_every_option_streams_to_the_in_memory_model(trajectory, options):
    """One driver: the options the in-memory fit has, streamed in chunks, give its model."""
    codes = np.array([[-1.0, 0.0], [1.0, 0.5], [0.0, -1.0]])
    config = TPSRConfig(**{**SMALL, **options})
    episodes = make_episodes(trajectory, config.history_length, config.test_length)
    reference = fit_tpsr_episodes(episodes, config=config, action_codes=codes)
    streamed = fit_tpsr_streamed(chunks_of(trajectory, 97), config=config, action_codes=codes)
    assert_same_model(streamed, reference)
    assert streamed.config == reference.config
    if config.state_clip_quantile > 0:
        assert relative(streamed.state_box, reference.state_box) <= 1e-9
        assert "state box" in streamed.fit_info["timings"]
