"""Fitted Q-iteration against a small continuous MDP whose optimal values are known."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from tpsr_ros.core.errors import ConfigError, DataError, DivergenceError
from tpsr_ros.core.fqi import FQIConfig, fit_q

LEFT, STAY, RIGHT = 0, 1, 2


def _line_world(n: int = 6000, seed: int = 0):
    """States on [0, 10]; actions move -1, 0, +1; reward 1 for ending beyond 8."""
    rng = np.random.default_rng(seed)
    states = rng.uniform(0, 10, size=(n, 1))
    actions = rng.integers(0, 3, size=n)
    moved = np.clip(states[:, 0] + (actions - 1.0), 0, 10)
    rewards = (moved > 8).astype(float)
    return states, actions, rewards, moved[:, None]


def _optimal_values(x: np.ndarray, gamma: float) -> np.ndarray:
    """V*(x): walk right; steps needed to end beyond 8, then reward 1 forever."""
    steps = np.maximum(np.ceil(8 - x + 1e-12), 1)  # at least one step to collect a reward
    steps = np.where(x > 8, 1, steps)
    return gamma ** (steps - 1) / (1 - gamma)


def test_recovers_the_optimal_policy_and_values_of_a_line_world():
    q = fit_q(*_line_world(), n_actions=3, config=FQIConfig(centers=40))
    grid = np.linspace(0.5, 7.5, 15)[:, None]
    assert np.all(q.greedy(grid) == RIGHT)  # left of the goal: always walk right
    values = q.values(grid).max(axis=1)
    truth = _optimal_values(grid[:, 0], 0.9)
    assert np.abs(values - truth).max() < 0.1 * truth.max()
    assert np.all(np.diff(values) > 0)  # closer to the goal is worth more


def test_features_are_normalised_and_fall_back_to_the_nearest_centre():
    q = fit_q(*_line_world(2000), n_actions=3, config=FQIConfig(centers=20))
    phi = q.features(np.array([[3.0], [5.0], [1e6]]))
    assert np.allclose(phi.sum(axis=1), 1.0)
    far = phi[2]
    nearest = np.argmax(q.centers[:, 0])  # a state far to the right is the rightmost centre
    assert far[nearest] == pytest.approx(1.0)


def test_bad_inputs_are_refused():
    s, a, r, s2 = _line_world(500)
    with pytest.raises(DataError, match="fewer than 100 RBF centres"):
        fit_q(s[:50], a[:50], r[:50], s2[:50], n_actions=3)
    bad = s.copy()
    bad[3] = np.nan
    with pytest.raises(DataError, match="non-finite"):
        fit_q(bad, a, r, s2, n_actions=3, config=FQIConfig(centers=20))
    with pytest.raises(DataError, match=r"actions \[3\] never occur"):
        fit_q(s, a, r, s2, n_actions=4, config=FQIConfig(centers=20))
    with pytest.raises(DataError, match="one entry per transition"):
        fit_q(s, a[:-1], r, s2, n_actions=3, config=FQIConfig(centers=20))
    with pytest.raises(ConfigError, match="discount"):
        FQIConfig(discount=1.0)
    q = fit_q(s, a, r, s2, n_actions=3, config=FQIConfig(centers=20))
    with pytest.raises(DataError, match="non-finite state"):
        q.greedy(np.array([[np.inf]]))


def test_divergence_is_detected_not_returned():
    # 200 samples on 40 centres with almost no ridge: the regression extrapolates and the
    # iteration grows without bound; a little ridge settles the same data
    data = _line_world(200)
    with pytest.raises(DivergenceError, match="diverged at ridge 1e-08"):
        fit_q(*data, n_actions=3, config=FQIConfig(centers=40, ridge=1e-8))
    q = fit_q(*data, n_actions=3, config=FQIConfig(centers=40, ridge=1e-4))
    assert np.abs(q.values(data[0])).max() <= 1.0 / (1 - 0.9) * 1.5


def test_a_diverging_member_is_refitted_alone():
    # 200 samples on 40 centres at ridge 1e-4: the member with k-means seed 2 diverges,
    # those with seeds 0, 1 and 3 converge
    data = _line_world(200)
    config = FQIConfig(centers=40, ridge=1e-4, ensemble=4, refit="member")
    with pytest.raises(DivergenceError, match=r"member 3 of 4: .* at ridge 0\.0001"):
        fit_q(*data, n_actions=3, config=config)
    q = fit_q(*data, n_actions=3, config=config, max_ridge=1.0)
    assert q.ridges is not None and q.ridges[2] > 1e-4
    assert [q.ridges[m] for m in (0, 1, 3)] == [1e-4] * 3
    bounds = np.cumsum([0, *q.group_sizes])
    for m, ridge in enumerate(q.ridges):  # each member is its own fit at its own ridge
        alone = fit_q(*data, n_actions=3, config=FQIConfig(centers=40, ridge=ridge, seed=m))
        np.testing.assert_array_equal(q.weights[bounds[m] : bounds[m + 1]], alone.weights)
    with pytest.raises(DivergenceError):  # the member's ridge is the first that converged
        fit_q(*data, n_actions=3, config=FQIConfig(centers=40, ridge=q.ridges[2] / 10, seed=2))
    with pytest.raises(DivergenceError, match=r"ridges 1e-08 to 1e-07 tried"):
        fit_q(*data, n_actions=3, config=FQIConfig(centers=40, ridge=1e-8), max_ridge=1e-7)


def test_a_fit_that_has_not_converged_is_refused():
    # the values need ~130 iterations to settle to 1e-6 at gamma 0.9; five leave them moving
    with pytest.raises(DivergenceError, match="did not converge in 5 iterations"):
        fit_q(*_line_world(500), n_actions=3, config=FQIConfig(centers=20, iterations=5))
    assert issubclass(DivergenceError, DataError)  # callers that catch DataError still do


def test_fit_is_deterministic_for_a_seed():
    data = _line_world(1500)
    a = fit_q(*data, n_actions=3, config=FQIConfig(centers=20, seed=3))
    b = fit_q(*data, n_actions=3, config=FQIConfig(centers=20, seed=3))
    assert np.array_equal(a.weights, b.weights) and np.array_equal(a.centers, b.centers)


def _plane_world(n: int = 3000, seed: int = 3):
    """A 2-d state mixed by a fixed linear map; reward for ending with x0 + x1 > 1."""
    rng = np.random.default_rng(seed)
    states = rng.uniform(-2, 2, size=(n, 2))
    actions = rng.integers(0, 3, size=n)
    moved = states + 0.5 * (actions[:, None] - 1.0)
    rewards = (moved.sum(axis=1) > 1).astype(float)
    return states, actions, rewards, moved


def test_an_ensemble_is_the_mean_of_its_members():
    s, a, r, s_next = _plane_world()
    config = FQIConfig(centers=15, ensemble=3, seed=4)
    ensemble = fit_q(s, a, r, s_next, 3, config)
    members = [
        fit_q(s, a, r, s_next, 3, FQIConfig(centers=15, seed=4 + m)) for m in range(3)
    ]
    probe = np.random.default_rng(5).uniform(-2, 2, size=(40, 2))
    mean = np.mean([q.values(probe) for q in members], axis=0)
    assert ensemble.members == 3 and len(ensemble.centers) == sum(len(q.centers) for q in members)
    assert np.allclose(ensemble.values(probe), mean, rtol=1e-12, atol=1e-12)
    assert np.allclose(ensemble.features(probe).sum(axis=1), 1.0)


def test_whitened_planner_units_are_white_and_invariant_to_a_linear_map():
    """Whitening makes fitted Q blind to an invertible linear map of the states."""
    s, a, r, s_next = _plane_world()
    mix = np.array([[3.0, 0.2], [-1.0, 0.05]])  # scales differing 60-fold, correlated
    config = FQIConfig(centers=15, ridge=0.1, state_scaling="whiten")
    plain = fit_q(s, a, r, s_next, 3, config)
    mixed = fit_q(s @ mix, a, r, s_next @ mix, 3, config)
    units = mixed.planner_units(np.vstack([s, s_next]) @ mix)
    assert np.allclose(np.cov(units, rowvar=False), np.eye(2), atol=1e-9)
    probe = np.random.default_rng(6).uniform(-2, 2, size=(40, 2))
    assert np.allclose(mixed.values(probe @ mix), plain.values(probe), atol=1e-6)
    standardised = fit_q(s @ mix, a, r, s_next @ mix, 3, FQIConfig(centers=15, ridge=0.1))
    assert not np.allclose(standardised.values(probe @ mix), plain.values(probe), atol=1e-6)


def test_predictive_units_shrink_a_direction_that_predicts_nothing():
    """Distances in predictive units are distances between predicted futures."""
    s, a, r, s_next = _plane_world()
    noise = np.random.default_rng(7).normal(0.0, 5.0, size=(len(s), 1))  # widest, predicts nothing
    noisy, noisy_next = np.hstack([s, noise]), np.hstack([s_next, np.roll(noise, 1)])
    futures = (noisy, s_next)  # what followed each state: where it moved
    config = FQIConfig(centers=15, ridge=0.1, state_scaling="predictive")
    q = fit_q(noisy, a, r, noisy_next, 3, config, futures=futures)
    probe = np.random.default_rng(6).uniform(-2, 2, size=(40, 2))
    low, high = (np.hstack([probe, np.full((40, 1), v)]) for v in (-10.0, 10.0))
    spread = np.linalg.norm(q.planner_units(noisy) - q.planner_units(noisy).mean(axis=0), axis=1)
    shift = np.linalg.norm(q.planner_units(high) - q.planner_units(low), axis=1)
    assert shift.max() < 0.05 * np.median(spread)  # four noise SDs apart: the same units
    assert np.allclose(q.values(high), q.values(low), atol=0.05 * np.abs(q.values(low)).max())
    whiten = dataclasses.replace(config, state_scaling="whiten")
    whitened = fit_q(noisy, a, r, noisy_next, 3, whiten)
    apart = whitened.planner_units(high) - whitened.planner_units(low)
    assert np.linalg.norm(apart, axis=1).min() > 3  # whitening: as far apart as any two states
    # like whitening, blind to an invertible linear map of the states
    mix = np.array([[3.0, 0.2, 0.0], [-1.0, 0.05, 0.0], [0.0, 1.0, 10.0]])
    mixed = fit_q(noisy @ mix, a, r, noisy_next @ mix, 3, config, futures=(noisy @ mix, s_next))
    assert np.allclose(mixed.values(low @ mix), q.values(low), atol=1e-6)


def test_the_predictive_scaling_needs_what_followed_the_states():
    s, a, r, s_next = _plane_world()
    config = FQIConfig(centers=15, state_scaling="predictive")
    with pytest.raises(ConfigError, match="needs the features of what followed the states"):
        fit_q(s, a, r, s_next, 3, config)
    with pytest.raises(DataError, match=r"futures must pair states \(n, 2\)"):
        fit_q(s, a, r, s_next, 3, config, futures=(s[:, :1], s_next))
    with pytest.raises(DataError, match="predict nothing"):
        fit_q(s, a, r, s_next, 3, config, futures=(s, np.ones((len(s), 2))))


def test_new_planner_options_are_checked():
    with pytest.raises(ConfigError, match="state_scaling"):
        FQIConfig(state_scaling="sphere")
    with pytest.raises(ConfigError, match="at least one member"):
        FQIConfig(ensemble=0)
    with pytest.raises(ConfigError, match="width_scale"):
        FQIConfig(width_scale=0.0)
