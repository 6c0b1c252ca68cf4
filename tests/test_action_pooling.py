"""Pooling the per-action operators (TPSRConfig.action_pooling, tpsr.pool_actions)."""

from __future__ import annotations

import numpy as np
import pytest
from learning_fixtures import POMDP, one_hot

from tpsr_ros.core.episodes import Trajectory, make_episodes
from tpsr_ros.core.errors import ConfigError
from tpsr_ros.core.filtering import observation_weights, update
from tpsr_ros.core.tpsr import TPSRConfig, fit_tpsr_episodes, pool_actions


def test_pooling_shrinks_each_action_toward_the_count_weighted_mean():
    rng = np.random.default_rng(0)
    operators = rng.standard_normal((3, 4, 2, 2))
    counts = np.array([10, 30, 60])
    kept = operators.copy()
    assert pool_actions(operators, counts, 0.0) is operators
    np.testing.assert_array_equal(operators, kept)  # 0: the guide's operators, bit for bit
    pooled = sum(c * b for c, b in zip(counts, kept, strict=True)) / counts.sum()
    for weight in (0.25, 1.0):
        result = pool_actions(kept.copy(), counts, weight)
        for a in range(3):
            np.testing.assert_allclose(result[a], (1 - weight) * kept[a] + weight * pooled)


@pytest.mark.parametrize("bad", [-0.1, 1.5, float("nan")])
def test_pooling_outside_zero_to_one_is_refused(bad):
    with pytest.raises(ConfigError, match="action_pooling"):
        TPSRConfig(action_pooling=bad)


def fully_observable(n_states: int = 4, n_actions: int = 8, seed: int = 3) -> POMDP:
    """Each observation names its state; the actions move the state differently."""
    rng = np.random.default_rng(seed)
    T = rng.dirichlet(np.full(n_states, 0.5), size=(n_actions, n_states)).transpose(0, 2, 1)
    return POMDP(T=T, O=np.eye(n_states))


def next_observation_given_state(model, pomdp: POMDP, action: int, obs: int) -> np.ndarray:
    """``P(o_2 | a_1, o_1)`` under a uniformly random second action, from the learned model."""
    members = (observation_weights(model, np.eye(pomdp.n_obs)) > 0).astype(float)
    state = update(model, model.initial_state(), action, np.eye(pomdp.n_obs)[obs])[0]
    per_action = [
        members @ (np.einsum("oij,j->oi", model.B[a2], state) @ model.b_inf)
        for a2 in range(pomdp.n_actions)
    ]
    return np.mean(per_action, axis=0) / (model.b_inf @ state)


def test_pooling_recovers_a_fully_observable_state_from_few_samples_per_action():
    """Ground truth: where the observation names the state, the state after an update does
    not depend on the action that led there (its prediction of the next observation is
    ``O T_mean e_s`` whatever the action). Per-action operators, each fitted on an eighth
    of the data, get it wrong by more than pooled ones."""
    pomdp = fully_observable()
    symbols, actions = pomdp.sample(6_000, seed=1)
    trajectory = Trajectory.from_arrays(
        actions, one_hot(symbols, pomdp.n_obs), n_actions=pomdp.n_actions
    )
    episodes = make_episodes(trajectory, 1, 1)
    exact = pomdp.T.mean(axis=0)  # column s: P(o_2 | s_1 = s), O = I
    errors = {}
    for pooling in (0.0, 1.0):
        cfg = TPSRConfig(
            obs_dim=3, ht_dim=3, obs_centers=30, ht_centers=30, sigma_obs=0.05, sigma_ht=0.05,
            rank=4, p_th_tests="from-current", action_pooling=pooling,
        )  # fmt: skip
        model = fit_tpsr_episodes(episodes, config=cfg)
        errors[pooling] = max(
            np.abs(next_observation_given_state(model, pomdp, a, s) - exact[:, s]).max()
            for a in range(pomdp.n_actions)
            for s in range(pomdp.n_states)
        )
    assert errors[1.0] < 0.05 < errors[0.0]

