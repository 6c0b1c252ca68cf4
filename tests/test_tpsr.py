"""TPSR batch learning (guide Algorithm 3): fast path vs the literal algorithm, SVD, errors."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from learning_fixtures import literal_algorithm3

from tpsr_ros.core.errors import ConfigError, DataError
from tpsr_ros.core.features import constant_vector, rbf_features
from tpsr_ros.core.tpsr import TPSRConfig, fit_tpsr
from tpsr_ros.core.tpsr_stages import (
    p_th_test_window,
    top_singular_triplets,
    whiten_test_window,
)
from tpsr_ros.core.whitening import Whitening


def structured_episodes(n_episodes: int, k: int = 12, n_actions: int = 3, seed: int = 0):
    """Observations that are smooth functions of a 2-D random walk, plus noise."""
    rng = np.random.default_rng(seed)
    steps = 3 * n_episodes
    actions = rng.integers(n_actions, size=steps)
    moves = np.array([[1.0, 0.0], [0.0, 1.0], [-0.7, -0.7], [0.3, -1.0]])[:n_actions]
    pos = np.clip(np.cumsum(moves[actions] + rng.normal(0, 0.3, (steps, 2)), axis=0), -5, 5)
    freqs = rng.normal(0, 0.6, (2, k))
    obs = np.sin(pos @ freqs + rng.uniform(0, 6, k)) + rng.normal(0, 0.05, (steps, k))
    o = obs.reshape(n_episodes, 3, k)
    return o[:, 0], o[:, 1], actions.reshape(n_episodes, 3)[:, 1], o[:, 2]


SMALL = TPSRConfig(
    obs_dim=5, ht_dim=6, obs_centers=15, ht_centers=25, sigma_obs=1.0, sigma_ht=2.0, rank=3
)


def literal_fit(h, o, a, t, cfg: TPSRConfig, n_actions: int):
    """Algorithms 1-3 with the guide's loops (features through the library's Algorithm 2)."""
    n_c = max(cfg.obs_centers, cfg.ht_centers)
    wh, wt, wo = (
        Whitening.fit(x, d) for x, d in ((h, cfg.ht_dim), (t, cfg.ht_dim), (o, cfg.obs_dim))
    )
    hw, tw, ow = wh.transform(h), wt.transform(t), wo.transform(o)
    phi_h = rbf_features(hw[n_c:], hw[: cfg.ht_centers], cfg.sigma_ht, add_constant=True).T
    phi_t = rbf_features(tw[n_c:], tw[: cfg.ht_centers], cfg.sigma_ht, add_constant=True).T
    phi_o = rbf_features(ow[n_c:], ow[: cfg.obs_centers], cfg.sigma_obs, normalize=True).T
    phi_t_th = None
    if cfg.p_th_tests == "from-current":
        k = o.shape[1]
        window = np.concatenate([o, t[:, : (cfg.test_length - 1) * k]], axis=1)
        phi_t_th = rbf_features(
            wt.transform(window)[n_c:], tw[: cfg.ht_centers], cfg.sigma_ht, add_constant=True
        ).T
    return literal_algorithm3(
        phi_h,
        phi_t,
        phi_o,
        constant_vector(phi_h.shape[0]),
        cfg.rank,
        a[n_c:],
        range(n_actions),
        phi_t_th=phi_t_th,
    )


@pytest.mark.parametrize("variant", ["after-current", "from-current"])
def test_fast_path_equals_literal_algorithm3(variant):
    h, o, a, t = structured_episodes(160)
    cfg = dataclasses.replace(SMALL, p_th_tests=variant)
    model = fit_tpsr(h, o, a, t, n_actions=3, config=cfg)
    _, s, _, b_star, b_inf, B = literal_fit(h, o, a, t, cfg, 3)
    np.testing.assert_allclose(model.singular_values[:3], s, rtol=1e-12)
    np.testing.assert_allclose(model.b_star, b_star, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(model.b_inf, b_inf, rtol=1e-10, atol=1e-12)
    literal_b = np.array([np.array(B[act]) for act in range(3)])
    assert model.B.shape == literal_b.shape == (3, 15, 3, 3)
    scale = np.abs(literal_b).max()
    np.testing.assert_allclose(model.B, literal_b, rtol=0, atol=1e-10 * scale)


@pytest.mark.parametrize("block_bytes", [8 * 4 * 3, 8 * 4 * 40, 1 << 25])
def test_test_window_is_whitened_block_by_block_as_in_one_shot(monkeypatch, block_bytes):
    """The P_TH window, whitened in blocks of rows, equals the whole window whitened at once."""
    rng = np.random.default_rng(3)
    observation, test = rng.normal(size=(101, 4)), rng.normal(size=(101, 12))
    whitening = Whitening.fit(test, 5)
    one_shot = whitening.transform(p_th_test_window(observation, test, 3))
    # blocks of 1, 13 or all 101 rows
    monkeypatch.setattr("tpsr_ros.core.tpsr_stages.WINDOW_BLOCK_BYTES", block_bytes)
    blocks = whiten_test_window(whitening, observation, test, 3)
    np.testing.assert_allclose(blocks, one_shot, rtol=1e-13, atol=1e-13)
    assert blocks.shape == (101, 5)


@pytest.mark.slow
def test_fast_path_equals_literal_algorithm3_through_arpack():
    h, o, a, t = structured_episodes(330, seed=1)
    cfg = dataclasses.replace(SMALL, ht_centers=210, obs_centers=4, rank=4)
    model = fit_tpsr(h, o, a, t, n_actions=3, config=cfg)
    _, s, _, b_star, b_inf, B = literal_fit(h, o, a, t, cfg, 3)
    np.testing.assert_allclose(model.singular_values[:4], s, rtol=1e-10)
    np.testing.assert_allclose(model.b_star, b_star, rtol=1e-9)
    np.testing.assert_allclose(model.b_inf, b_inf, rtol=1e-9)
    literal_b = np.array([np.array(B[act]) for act in range(3)])
    np.testing.assert_allclose(model.B, literal_b, rtol=0, atol=1e-10 * np.abs(literal_b).max())


@pytest.mark.slow
@pytest.mark.parametrize("shape", [(60, 40), (420, 380)])
def test_truncated_svd_is_exact(shape):
    rng = np.random.default_rng(2)
    q1, _ = np.linalg.qr(rng.standard_normal((shape[0], shape[0])))
    q2, _ = np.linalg.qr(rng.standard_normal((shape[1], shape[1])))
    spectrum = 10.0 * 0.8 ** np.arange(min(shape))
    m = (q1[:, : len(spectrum)] * spectrum) @ q2[:, : len(spectrum)].T
    u, s, v = top_singular_triplets(m, 8, seed=0)
    uf, sf, vft = np.linalg.svd(m)
    np.testing.assert_allclose(s, sf[:8], rtol=1e-12)
    signs = np.sign(np.sum(u * uf[:, :8], axis=0))
    np.testing.assert_allclose(u, uf[:, :8] * signs, atol=1e-10)
    np.testing.assert_allclose(v, vft[:8].T * signs, atol=1e-10)
    idx = np.argmax(np.abs(u), axis=0)
    assert (u[idx, range(8)] > 0).all()


def test_fit_is_deterministic_and_reports_its_stages():
    h, o, a, t = structured_episodes(200, seed=3)
    stages: list[str] = []
    m1 = fit_tpsr(h, o, a, t, n_actions=3, config=SMALL, progress=stages.append)
    m2 = fit_tpsr(h, o, a, t, n_actions=3, config=SMALL)
    for name in ("b_star", "b_inf", "B", "obs_whitening", "obs_centers", "singular_values"):
        np.testing.assert_array_equal(getattr(m1, name), getattr(m2, name))
    assert stages == [
        "checking data",
        "whitening",
        "kernel centres",
        "features",
        "P-statistics",
        "SVD",
        "parameters",
    ]
    assert set(m1.fit_info["timings"]) == set(stages)
    assert m1.fit_info["training_episodes"] == 200 - 25
    assert sum(m1.fit_info["samples_per_action"]) == 175
    assert m1.singular_values.shape == (8,)  # rank + 5 reported
    assert np.all(np.diff(m1.singular_values) <= 0)


def test_kmeans_centres_keep_every_episode_for_training():
    h, o, a, t = structured_episodes(120, seed=4)
    cfg = dataclasses.replace(SMALL, center_selection="kmeans", seed=5)
    m1 = fit_tpsr(h, o, a, t, n_actions=3, config=cfg)
    m2 = fit_tpsr(h, o, a, t, n_actions=3, config=cfg)
    assert m1.fit_info["training_episodes"] == 120
    np.testing.assert_array_equal(m1.B, m2.B)


def test_longer_histories_and_tests():
    rng = np.random.default_rng(6)
    h2, o, a, t3 = (
        rng.standard_normal((150, 2 * 8)),
        rng.standard_normal((150, 8)),
        rng.integers(2, size=150),
        rng.standard_normal((150, 3 * 8)),
    )
    cfg = TPSRConfig(
        history_length=2,
        test_length=3,
        obs_dim=4,
        ht_dim=6,
        obs_centers=10,
        ht_centers=20,
        rank=2,
        p_th_tests="from-current",
    )
    model = fit_tpsr(h2, o, a, t3, n_actions=2, config=cfg)
    assert model.B.shape == (2, 10, 2, 2)
    with pytest.raises(DataError, match="history_length 1"):
        fit_tpsr(h2, o, a, t3, n_actions=2, config=dataclasses.replace(cfg, history_length=1))


def test_too_few_episodes():
    h, o, a, t = structured_episodes(100)
    with pytest.raises(DataError, match="100 episodes are too few for 500 kernel centres"):
        fit_tpsr(h, o, a, t, n_actions=3, config=dataclasses.replace(SMALL, obs_centers=500))


def test_rank_above_usable_singular_values():
    h, o, a, t = structured_episodes(100)
    # kernels so wide that every activation is exactly 1: P_TH has rank 1
    cfg = dataclasses.replace(SMALL, sigma_ht=1e9, rank=2)
    with pytest.raises(DataError, match="rank 2 exceeds the 1 usable singular values"):
        fit_tpsr(h, o, a, t, n_actions=3, config=cfg)


def test_action_without_samples():
    h, o, a, t = structured_episodes(100)
    with pytest.raises(DataError, match=r"action\(s\) \[3\] never occur"):
        fit_tpsr(h, o, a, t, n_actions=4, config=SMALL)
    with pytest.raises(DataError, match=r"0\.\.1"):
        fit_tpsr(h, o, a, t, n_actions=2, config=SMALL)


def test_non_finite_data():
    h, o, a, t = structured_episodes(100)
    t = t.copy()
    t[5, 3] = np.inf
    with pytest.raises(DataError, match=r"1 non-finite values \(NaN or infinity\) in the tests"):
        fit_tpsr(h, o, a, t, n_actions=3, config=SMALL)


@pytest.mark.parametrize(
    "changes",
    [
        {"rank": 0},
        {"sigma_obs": -1.0},
        {"sigma_ht": float("nan")},
        {"center_selection": "random"},
        {"obs_centers": True},
        {"history_length": 1.5},
        {"p_th_tests": "x"},
        {"seed": -1},
        {"rank": 2000},
        {"normalize_ht_features": 1},
        {"obs_variance": 1.0},
        {"obs_variance": -0.5},
    ],
)
def test_config_validation(changes):
    with pytest.raises(ConfigError):
        TPSRConfig(**changes)


def test_config_defaults_are_the_guides():
    cfg = TPSRConfig()
    assert (cfg.history_length, cfg.test_length, cfg.obs_dim, cfg.ht_dim) == (1, 1, 10, 10)
    assert (cfg.obs_centers, cfg.ht_centers, cfg.sigma_obs, cfg.sigma_ht, cfg.rank) == (
        500,
        1000,
        1.0,
        2.0,
        5,
    )
    assert cfg.center_selection == "first" and not cfg.normalize_ht_features
    assert TPSRConfig.from_dict(cfg.to_dict()) == cfg
    with pytest.raises(ConfigError, match="unknown"):
        TPSRConfig.from_dict({"bogus": 1})


def test_a_variance_fraction_chooses_the_observation_dimensions_and_the_model_records_them(
    tmp_path,
):
    from tpsr_ros.io.model_io import load_model, save_model

    h, o, a, t = structured_episodes(200, seed=5)
    centred = o - o.mean(axis=0)
    values = np.linalg.eigvalsh(centred.T @ centred)[::-1]
    kept = int(np.searchsorted(np.cumsum(values) / values.sum(), 0.9)) + 1
    assert 1 < kept < o.shape[1]
    by_variance = dataclasses.replace(SMALL, obs_variance=0.9, state_clip_quantile=0.1)
    model = fit_tpsr(
        h, o, a, t, n_actions=3, config=by_variance, history_actions=np.zeros((200, 1), int)
    )
    assert model.config.obs_dim == kept and model.obs_whitening.shape == (12, kept)
    assert model.config.obs_variance == 0.9 and model.state_box is not None
    same_dims = dataclasses.replace(by_variance, obs_variance=0.0, obs_dim=kept)
    fixed = fit_tpsr(
        h, o, a, t, n_actions=3, config=same_dims, history_actions=np.zeros((200, 1), int)
    )
    np.testing.assert_array_equal(model.B, fixed.B)
    again = load_model(save_model(model, tmp_path / "m.npz"))
    assert again.config == model.config
    np.testing.assert_array_equal(again.obs_whitening, model.obs_whitening)
