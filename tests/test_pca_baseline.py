"""The PCA baseline (guide 4.2): principal-component projection behind the StateModel interface."""

from __future__ import annotations

import numpy as np
import pytest

from tpsr_ros.core.errors import ConfigError, DataError
from tpsr_ros.core.pca_baseline import PCAConfig, PCAModel, fit_pca
from tpsr_ros.core.state_model import StateModel


@pytest.fixture(scope="module")
def data():
    rng = np.random.default_rng(0)
    latent = rng.standard_normal((500, 2)) * [5.0, 2.0]
    mixing = rng.standard_normal((2, 20))
    obs = latent @ mixing + rng.normal(0, 0.01, (500, 20)) + 0.5
    return obs, rng.integers(25, size=500)


def test_projection_matches_numpy_svd(data):
    obs, actions = data
    model = fit_pca(obs, n_actions=25)
    assert isinstance(model, StateModel)
    assert (model.state_dim, model.n_actions, model.obs_size) == (2, 25, 20)
    centred = obs - obs.mean(axis=0)
    _, s, vt = np.linalg.svd(centred, full_matrices=False)
    scores = centred @ vt[:2].T
    states = model.track(actions, obs).states
    np.testing.assert_allclose(np.abs(states), np.abs(scores), rtol=1e-8, atol=1e-9)
    np.testing.assert_allclose(model.eigenvalues, s[:2] ** 2 / 499, rtol=1e-10)
    assert model.explained_variance_ratio.sum() > 0.99


def test_update_ignores_state_and_action_and_equals_track(data):
    obs, actions = data
    model = fit_pca(obs, n_actions=25, config=PCAConfig(dim=3))
    track = model.track(actions, obs)
    assert track.states.shape == (500, 3)
    assert np.isnan(track.normalizers).all() and not track.recovered.any()
    for i in (0, 17, 499):
        new, info = model.update(np.full(3, 123.0), int(actions[i]), obs[i])
        np.testing.assert_array_equal(new, track.states[i])
        assert not info.recovered
    np.testing.assert_array_equal(model.initial_state(), np.zeros(3))


def test_round_trip_through_arrays(data):
    obs, _ = data
    model = fit_pca(obs, n_actions=25)
    again = PCAModel.from_arrays(model.to_arrays(), model.parameters(), model.summary())
    np.testing.assert_array_equal(again.components, model.components)
    assert again.n_actions == 25


def test_bad_input(data):
    obs, _ = data
    with pytest.raises(ConfigError):
        PCAConfig(dim=0)
    model = fit_pca(obs, n_actions=25)
    with pytest.raises(DataError, match="observation size 20"):
        model.update(model.initial_state(), 0, np.zeros(21))
    with pytest.raises(DataError, match=r"0\.\.24"):
        model.track(np.full(500, 25), obs)
    with pytest.raises(ConfigError, match="cannot keep 21"):
        fit_pca(obs, n_actions=25, config=PCAConfig(dim=21))
