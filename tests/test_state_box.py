"""The state box (``state_clip_quantile``): its bounds, clipping, saving and online tracking."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from test_model_io import rewrite
from test_tpsr import SMALL

from tpsr_ros.core import filtering
from tpsr_ros.core.errors import ConfigError, DataError
from tpsr_ros.core.online import OnlineTracker
from tpsr_ros.core.state_box import BOX_EPISODES, box_episodes, episode_states
from tpsr_ros.core.tpsr import TPSRConfig, TPSRModel, fit_tpsr
from tpsr_ros.core.units import STEP_NS
from tpsr_ros.io.model_io import ModelFormatError, load_model, save_model

QUANTILE = 0.05


def walk(n_episodes: int, seed: int, k: int = 12):
    """Episodes (history of 1, current pair, test of 1) of a noisy 2-D walk seen through sines,
    with the history step's action, and the flat run they were cut from."""
    rng = np.random.default_rng(seed)
    steps = 3 * n_episodes
    actions = rng.integers(3, size=steps)
    moves = np.array([[1.0, 0.0], [0.0, 1.0], [-0.7, -0.7]])
    pos = np.clip(np.cumsum(moves[actions] + rng.normal(0, 0.3, (steps, 2)), axis=0), -5, 5)
    freqs = rng.normal(0, 0.6, (2, k))
    obs = np.sin(pos @ freqs + rng.uniform(0, 6, k)) + rng.normal(0, 0.05, (steps, k))
    o, a = obs.reshape(n_episodes, 3, k), actions.reshape(n_episodes, 3)
    return (o[:, 0], o[:, 1], a[:, 1], o[:, 2], a[:, :1]), (actions, obs)


@pytest.fixture(scope="module")
def fitted():
    (h, o, a, t, ha), run = walk(400, seed=3)
    cfg = dataclasses.replace(SMALL, state_clip_quantile=QUANTILE)
    model = fit_tpsr(h, o, a, t, n_actions=3, config=cfg, history_actions=ha)
    return model, (h, o, a, t, ha), run


def unclipped(model: TPSRModel) -> TPSRModel:
    return dataclasses.replace(
        model, config=dataclasses.replace(model.config, state_clip_quantile=0.0), state_box=None
    )


def test_box_bounds_the_states_of_the_training_episodes_under_the_filter(fitted):
    model, (h, o, a, _, ha), _ = fitted
    plain = unclipped(model)
    states = episode_states(plain, h, ha, a, o)
    # ground truth: Algorithm 4 over each episode's history and current pair, from b_*
    for e in range(0, 400, 37):
        truth = filtering.track(plain, np.array([ha[e, 0], a[e]]), np.stack([h[e], o[e]]))
        np.testing.assert_allclose(states[e], truth.states[-1], rtol=1e-10, atol=1e-12)
    np.testing.assert_array_equal(model.state_box, np.quantile(states, [0.05, 0.95], axis=0))
    assert (model.state_box[0] < model.state_box[1]).all()
    # the unclipped fit is the same model apart from the box
    no_box = fit_tpsr(h, o, a, fitted[1][3], n_actions=3, config=SMALL, history_actions=ha)
    np.testing.assert_array_equal(no_box.B, model.B)
    assert no_box.state_box is None and "state_box" not in no_box.to_arrays()


def test_every_tracked_state_is_clipped_into_the_box(fitted):
    model, _, (actions, obs) = fitted
    track = model.track(actions, obs)
    low, high = model.state_box
    assert ((track.states >= low) & (track.states <= high)).all()
    free = unclipped(model).track(actions, obs)
    outside = ((free.states < low) | (free.states > high)).any(axis=1)
    assert 0.02 < outside.mean() < 0.9  # the box binds on this run, so clipping is exercised
    # the first step from b_* is the unclipped state, clipped
    np.testing.assert_array_equal(track.states[0], np.clip(free.states[0], low, high))
    # step by step equals the batch, bit for bit (the filter node's path)
    state = model.initial_state()
    for s in range(60):
        state, info = model.update(state, int(actions[s]), obs[s])
        np.testing.assert_array_equal(state, track.states[s])
        assert info.recovered == track.recovered[s]


def test_a_saved_clipped_model_loads_and_tracks_identically_offline_and_online(tmp_path, fitted):
    model, _, (actions, obs) = fitted
    path = save_model(model, tmp_path / "m.npz")
    loaded = load_model(path)
    assert loaded.config == model.config
    np.testing.assert_array_equal(loaded.state_box, model.state_box)
    expected = model.track(actions[:200], obs[:200]).states
    np.testing.assert_array_equal(loaded.track(actions[:200], obs[:200]).states, expected)
    online = OnlineTracker(loaded)
    for s in range(200):
        info = online.step(s * STEP_NS, int(actions[s]), obs[s])
        np.testing.assert_array_equal(info.state, expected[s])
    # a file whose parameters ask for the box but that lacks it is refused, and vice versa
    rewrite(path, tmp_path / "no_box.npz", drop=("state_box",))
    with pytest.raises(ModelFormatError, match="state_box"):
        load_model(tmp_path / "no_box.npz")
    no_clip = {"parameters": {**model.parameters(), "state_clip_quantile": 0.0}}
    rewrite(path, tmp_path / "extra_box.npz", metadata=no_clip)
    with pytest.raises(ModelFormatError, match="state_box"):
        load_model(tmp_path / "extra_box.npz")


def test_bad_settings_are_refused(fitted):
    for bad in (0.5, -0.1, True, float("nan")):
        with pytest.raises(ConfigError, match="state_clip_quantile must be 0 or in"):
            TPSRConfig(state_clip_quantile=bad)
    _, (h, o, a, t, _), _ = fitted
    cfg = dataclasses.replace(SMALL, state_clip_quantile=QUANTILE)
    with pytest.raises(ConfigError, match="needs the history actions"):
        fit_tpsr(h, o, a, t, n_actions=3, config=cfg)
    with pytest.raises(DataError, match=r"must lie in 0 \.\. 2"):
        fit_tpsr(h, o, a, t, n_actions=3, config=cfg, history_actions=np.full((400, 1), 3))
    with pytest.raises(DataError, match="not integer indices of 400 episodes of 1"):
        fit_tpsr(h, o, a, t, n_actions=3, config=cfg, history_actions=np.zeros((400, 2), int))


def test_large_training_sets_set_the_box_from_evenly_spread_episodes():
    np.testing.assert_array_equal(box_episodes(7), np.arange(7))
    rows = box_episodes(11538)
    assert len(np.unique(rows)) == BOX_EPISODES and rows[0] == 0 and rows[-1] == 11537
    gaps = np.diff(rows)
    assert gaps.min() >= 2 and gaps.max() <= 3  # 11538 / 4000 = 2.9 apart
