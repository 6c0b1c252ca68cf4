"""Action-aware history and test features: checked on a planted bit of memory."""

from __future__ import annotations

import numpy as np
import pytest

from learner.memory import memory_steps
from tpsr_ros.core.action_features import join_actions, standardised_codes
from tpsr_ros.core.episodes import Trajectory, make_episodes
from tpsr_ros.core.errors import ConfigError, DataError
from tpsr_ros.core.tpsr import TPSRConfig, fit_tpsr, fit_tpsr_episodes
from tpsr_ros.io.model_io import load_model, save_model

LEFT, RIGHT, STILL, PROBE = range(4)
BLANK = np.array([1.0, 0.0, 0.0])


def hidden_bit(steps: int, seed: int) -> tuple[Trajectory, np.ndarray]:
    """A bit set by 'left' (0) and 'right' (1), kept by 'still', read and re-drawn by 'probe'.

    Every action but 'probe' shows the same blank observation; 'probe' shows the bit and
    then replaces it by a fresh random one. So no observation, however long the history,
    tells the current bit: only the actions since the last probe do. Uniformly random
    actions. Returns the trajectory and the bit after every step.
    """
    rng = np.random.default_rng(seed)
    actions = rng.integers(0, 4, size=steps)
    draws = rng.integers(0, 2, size=steps)
    sets = actions != STILL
    value = np.where(actions == LEFT, 0, np.where(actions == RIGHT, 1, draws))
    last_set = np.maximum.accumulate(np.where(sets, np.arange(steps), -1))
    start = rng.integers(0, 2)
    bit = np.where(last_set >= 0, value[np.maximum(last_set, 0)], start)
    before = np.concatenate([[start], bit[:-1]])  # the bit a probe reads
    observations = np.tile(BLANK, (steps, 1))
    probes = actions == PROBE
    observations[probes] = np.eye(3)[1 + before[probes]]
    return Trajectory.from_arrays(actions, observations, n_actions=4), bit


# Boots' P_TH window: only with it do repeated updates stay exact (with the guide's window
# the stand-still operator of this system grows the bit direction until the filter restarts)
SMALL = {
    "obs_dim": 2,
    "ht_dim": 2,
    "obs_centers": 20,
    "ht_centers": 40,
    "rank": 2,
    "p_th_tests": "from-current",
}
CODES = np.eye(4)  # one code per action: an indicator kernel


def fit(steps: int = 30000, **settings) -> object:
    train, _ = hidden_bit(steps, seed=1)
    cfg = TPSRConfig(**{**SMALL, **settings})
    episodes = make_episodes(train, cfg.history_length, cfg.test_length)
    return fit_tpsr_episodes(episodes, config=cfg, action_codes=CODES)


def bit_memory(model) -> tuple[int, bool]:
    """The memory experiment on the planted system: 'left' vs 'right', then standing still.

    The true bit is remembered for ever; relative distance as in ``learner memory``.
    """
    still = [STILL] * 20
    blank = np.tile(BLANK, (21, 1))
    runs = [model.track(np.array([first, *still]), blank).states for first in (LEFT, RIGHT)]
    train, _ = hidden_bit(3000, seed=7)
    states = model.track(train.actions, train.observations).states[300:]
    spread = np.sqrt(np.mean(np.sum((states - states.mean(axis=0)) ** 2, axis=1)))
    relative = np.linalg.norm(runs[0] - runs[1], axis=1) / spread
    return memory_steps(np.concatenate([[0.0], relative]), start=2)


def test_the_planted_system_hides_the_bit_from_observations():
    train, bit = hidden_bit(5000, seed=0)
    probes = np.flatnonzero(train.actions == PROBE)
    probes = probes[probes > 0]
    assert np.array_equal(train.observations[probes].argmax(axis=1) - 1, bit[probes - 1])
    blank = np.all(train.observations == BLANK, axis=1)
    assert blank[train.actions != PROBE].all()
    # the bit after a step is the one its action set, or the one before for 'still'
    assert (bit[1:][train.actions[1:] == LEFT] == 0).all()
    assert (bit[1:][train.actions[1:] == RIGHT] == 1).all()
    still = np.flatnonzero(train.actions[1:] == STILL) + 1
    assert np.array_equal(bit[still], bit[still - 1])


def bit_accuracy(model) -> tuple[float, int]:
    """How well the states tell the bit (affine read-out) over a random run; restarts."""
    run, bit = hidden_bit(4000, seed=3)
    track = model.track(run.actions, run.observations)
    last_set = np.maximum.accumulate(np.where(run.actions != STILL, np.arange(len(run)), 0))
    # the bit is known where the last action that was not 'still' set it (not a probe's coin)
    known = np.flatnonzero(run.actions[last_set] != PROBE)[100:]
    x = np.column_stack([track.states[known], np.ones(known.size)])
    coef, *_ = np.linalg.lstsq(x, bit[known], rcond=None)
    return float(np.mean((x @ coef > 0.5) == bit[known])), int(track.recovered.sum())


def test_action_aware_histories_remember_what_observation_histories_cannot():
    guide = fit()
    # no history of observations tells the bit: P_TH has rank 1 up to sampling noise
    assert guide.singular_values[1] < 0.005 * guide.singular_values[0]
    accuracy, _ = bit_accuracy(guide)
    assert accuracy < 0.75
    assert bit_memory(guide)[0] < 10

    aware = fit(history_action_weight=1.0)
    assert aware.singular_values[1] > 0.01 * aware.singular_values[0]
    accuracy, restarts = bit_accuracy(aware)
    assert accuracy > 0.97 and restarts == 0
    memory, censored = bit_memory(aware)
    assert memory == 20 and censored  # the true system remembers for ever


def test_zero_weights_are_the_guides_fit_bit_for_bit():
    train, _ = hidden_bit(6000, seed=2)
    cfg = TPSRConfig(**SMALL)
    e = make_episodes(train, 2, 2)
    cfg = TPSRConfig(**{**SMALL, "history_length": 2, "test_length": 2})
    plain = fit_tpsr(e.history, e.observation, e.action, e.test, n_actions=4, config=cfg)
    with_actions = fit_tpsr_episodes(e, config=cfg, action_codes=CODES)
    for name, array in plain.to_arrays().items():
        np.testing.assert_array_equal(array, with_actions.to_arrays()[name])


def test_a_saved_action_aware_model_loads_and_tracks_the_same(tmp_path):
    model = fit(history_action_weight=1.0, test_action_weight=0.5, p_th_tests="from-current")
    path = tmp_path / "aware.npz"
    save_model(model, path)
    loaded = load_model(path)
    assert loaded.config == model.config
    run, _ = hidden_bit(200, seed=5)
    np.testing.assert_array_equal(
        loaded.track(run.actions, run.observations).states,
        model.track(run.actions, run.observations).states,
    )
    state = loaded.initial_state()
    for action, observation in zip(run.actions[:20], run.observations[:20], strict=True):
        state, _ = loaded.update(state, int(action), observation)
    np.testing.assert_array_equal(state, model.track(run.actions, run.observations).states[19])


def test_bad_action_settings_are_refused():
    with pytest.raises(ConfigError, match="history_action_weight must be a non-negative"):
        TPSRConfig(history_action_weight=-1.0)
    with pytest.raises(ConfigError, match="test_action_weight"):
        TPSRConfig(test_action_weight=float("nan"))
    train, _ = hidden_bit(3000, seed=2)
    e = make_episodes(train, 1, 1)
    cfg = TPSRConfig(**SMALL, history_action_weight=1.0)
    with pytest.raises(ConfigError, match="need the actions of the history steps"):
        fit_tpsr(e.history, e.observation, e.action, e.test, n_actions=4, config=cfg,
                 action_codes=CODES)
    with pytest.raises(ConfigError, match="command of each of the 4 actions"):
        fit_tpsr_episodes(e, config=cfg)  # the default codes are the simulator's 25
    with pytest.raises(DataError, match="action codes must be a finite"):
        standardised_codes(np.eye(3), 4)
    with pytest.raises(DataError, match="same code"):
        standardised_codes(np.ones((4, 2)), 4)
    with pytest.raises(DataError, match="history action indices"):
        join_actions(np.zeros((2, 1)), np.array([[0], [9]]), np.eye(4), 1.0, "history")
