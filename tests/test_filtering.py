"""State tracking (guide Algorithm 4): batch equals streaming, the normaliser guard, errors."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from test_tpsr import SMALL, structured_episodes

from tpsr_ros.core import filtering
from tpsr_ros.core.errors import DataError
from tpsr_ros.core.features import rbf_features
from tpsr_ros.core.state_model import StateModel, UpdateInfo
from tpsr_ros.core.tpsr import TPSRModel, fit_tpsr


@pytest.fixture(scope="module")
def episodes():
    return structured_episodes(500, seed=7)


@pytest.fixture(scope="module")
def model(episodes) -> TPSRModel:
    h, o, a, t = (x[:400] for x in episodes)
    return fit_tpsr(h, o, a, t, n_actions=3, config=SMALL)


@pytest.fixture(scope="module")
def run(episodes):
    """300 steps of the same system that the model did not see."""
    h, o, _, t = (x[400:] for x in episodes)
    obs = np.stack([h, o, t], axis=1).reshape(-1, h.shape[1])
    actions = np.random.default_rng(9).integers(3, size=obs.shape[0])
    return actions, obs


def loop(model, actions, obs, initial=None):
    state = model.initial_state() if initial is None else initial
    states, infos = [], []
    for a, o in zip(actions, obs, strict=True):
        state, info = filtering.update(model, state, int(a), o)
        states.append(state)
        infos.append(info)
    return np.array(states), infos


def assert_same(track, states, infos):
    np.testing.assert_array_equal(track.states, states)
    np.testing.assert_array_equal(track.normalizers, [i.normalizer for i in infos])
    np.testing.assert_array_equal(track.recovered, [i.recovered for i in infos])


def test_model_satisfies_the_state_model_interface(model):
    assert isinstance(model, StateModel)
    assert model.state_dim == 3 and model.n_actions == 3 and model.obs_size == 12


def test_batch_tracking_equals_a_loop_of_updates_bit_for_bit(model, run):
    actions, obs = run
    track = filtering.track(model, actions, obs)
    states, infos = loop(model, actions, obs)
    assert_same(track, states, infos)
    assert track.states.shape == (300, 3)
    assert not track.recovered.any()
    # and through the model's methods
    np.testing.assert_array_equal(model.track(actions, obs).states, states)
    np.testing.assert_array_equal(model.update(model.b_star, int(actions[0]), obs[0])[0], states[0])


def test_update_is_algorithm_4(model, run):
    actions, obs = run
    state = model.b_star * 1.3
    new, info = filtering.update(model, state, int(actions[0]), obs[0])
    white = (obs[0] - model.obs_mean) @ model.obs_whitening
    phi = rbf_features(white[None], model.obs_centers, model.config.sigma_obs, normalize=True)[0]
    b_ao = np.einsum("o,oij->ij", phi, model.B[actions[0]])  # eq. 3.9
    expected = b_ao @ state / (model.b_inf @ b_ao @ state)  # eq. 3.8
    np.testing.assert_allclose(new, expected, rtol=1e-12)
    assert info == UpdateInfo(
        normalizer=pytest.approx(model.b_inf @ b_ao @ state, rel=1e-12), recovered=False
    )
    assert model.b_inf @ new == pytest.approx(1.0, rel=1e-12)


def test_track_from_a_given_state(model, run):
    actions, obs = run
    initial = model.b_star * 0.5 + 0.1
    states, infos = loop(model, actions[:20], obs[:20], initial)
    assert_same(model.track(actions[:20], obs[:20], initial), states, infos)


def test_guard_restarts_from_b_star_when_the_normaliser_vanishes(model, run):
    actions, obs = run
    weights = filtering.observation_weights(model, obs[:1])
    b_ao = filtering.update_matrices(model, actions[:1], weights)[0]
    w = b_ao.T @ model.b_inf
    initial = model.b_star - (model.b_star @ w) / (w @ w) * w  # b_inf^T B_ao initial = 0
    new, info = filtering.update(model, initial, int(actions[0]), obs[0])
    assert info.recovered and abs(info.normalizer) < 1e-12
    np.testing.assert_array_equal(
        new, filtering.update(model, model.b_star, int(actions[0]), obs[0])[0]
    )
    states, infos = loop(model, actions[:5], obs[:5], initial)
    assert_same(model.track(actions[:5], obs[:5], initial), states, infos)


def test_guard_falls_back_to_b_star_when_even_a_restart_fails(model, run):
    actions, obs = run
    broken = dataclasses.replace(model, B=model.B * np.array([1.0, -1.0, 1.0])[:, None, None, None])
    track = broken.track(actions, obs)
    states, infos = loop(broken, actions, obs)
    assert_same(track, states, infos)
    hit = actions == 1
    assert (track.recovered == hit).all()  # negative normalisers exactly on action 1
    assert (track.normalizers[hit] < 0).all()
    np.testing.assert_array_equal(track.states[hit], np.broadcast_to(model.b_star, (hit.sum(), 3)))


def test_derived_arrays_belong_to_the_model_they_were_derived_from(model, run):
    actions, obs = run
    model.update(model.b_star, int(actions[0]), obs[0])  # derives model.derived once
    moved = dataclasses.replace(model, obs_centers=model.obs_centers + 0.5, b_inf=model.b_inf * 2)
    assert moved.derived is not model.derived
    np.testing.assert_array_equal(
        moved.derived.centers_sq, np.einsum("ij,ij->i", moved.obs_centers, moved.obs_centers)
    )
    assert moved.derived.b_inf_norm == np.linalg.norm(moved.b_inf)
    states, infos = loop(moved, actions[:20], obs[:20])
    assert_same(moved.track(actions[:20], obs[:20]), states, infos)
    assert model.derived.operator_of == (0, 1, 2)


def test_pooled_operators_stored_per_action_are_read_from_one_copy(model, run):
    actions, obs = run
    pooled = dataclasses.replace(model, B=np.repeat(model.B[1:2], 3, axis=0))
    assert pooled.derived.operator_of == (0, 0, 0)
    states, infos = loop(pooled, actions, obs)
    assert_same(pooled.track(actions, obs), states, infos)
    one = dataclasses.replace(model, B=pooled.B[:1].copy())  # the same operators, once
    np.testing.assert_array_equal(states, loop(one, np.zeros_like(actions), obs)[0])


def test_guard_catches_overflow(model, run):
    actions, obs = run
    new, info = filtering.update(model, np.full(3, 1e308), int(actions[0]), obs[0])
    assert info.recovered  # B_ao b overflows: its norm is not finite
    assert np.isfinite(new).all()


def test_bad_input(model, run):
    actions, obs = run
    with pytest.raises(DataError, match="observation size 12"):
        filtering.update(model, model.b_star, 0, np.zeros(11))
    bad = obs[:3].copy()
    bad[1, 0] = np.nan
    with pytest.raises(DataError, match="non-finite"):
        filtering.track(model, actions[:3], bad)
    with pytest.raises(DataError, match=r"0\.\.2"):
        filtering.update(model, model.b_star, 3, obs[0])
    with pytest.raises(DataError, match="integer"):
        filtering.track(model, actions[:3].astype(float), obs[:3])
    with pytest.raises(DataError, match="state of shape"):
        filtering.update(model, np.zeros(4), 0, obs[0])
