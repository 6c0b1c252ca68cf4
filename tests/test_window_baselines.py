"""Baselines that carry the past: stacked PCA frames and the finite-window predictive state."""

from __future__ import annotations

import csv
import json
import re

import numpy as np
import pytest
from cli_support import run_entry

from learner.overrides import apply_overrides
from tpsr_ros.core.errors import ConfigError, DataError, ModelFormatError
from tpsr_ros.core.fqi import FQIConfig, fit_q, ignore_trailing
from tpsr_ros.core.pca_baseline import PCAConfig
from tpsr_ros.core.state_model import StateModel, planner_dim
from tpsr_ros.core.tpsr import TPSRConfig
from tpsr_ros.core.window_baselines import (
    StackedPCAConfig,
    WindowConfig,
    fit_stacked_pca,
    fit_window,
    window_rows,
)
from tpsr_ros.io.model_io import save_model

STAY, FORWARD = 0, 1
CODES = np.array([[0.0, 0.0], [3.0, 0.0]])  # the commands' codes: stand still, move on


def ring(steps: int = 4000, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A ring of 4 cells seen as A, B, A, C (cells 0 and 2 look alike); actions stay or
    move one cell on, uniformly at random. Returns observations, actions and cells."""
    rng = np.random.default_rng(seed)
    templates = rng.uniform(0.0, 1.0, (3, 6))  # A, B, C
    seen = np.array([0, 1, 0, 2])
    actions = rng.integers(2, size=steps)
    cells = np.cumsum(actions) % 4
    obs = templates[seen[cells]] + rng.normal(0.0, 0.01, (steps, 6))
    return obs, actions, cells


def separation(states: np.ndarray, cells: np.ndarray, actions: np.ndarray) -> float:
    """How well the states tell 'cell 0 entered moving on' from 'cell 2 entered moving on'
    (alike now; C lies before cell 0, B before cell 2): the Fisher discriminant's
    distance between the groups' means in pooled within-group standard deviations."""
    moved = actions == FORWARD
    groups = [states[moved & (cells == c)] for c in (0, 2)]
    gap = groups[0].mean(axis=0) - groups[1].mean(axis=0)
    within = sum(np.cov(g, rowvar=False) * (len(g) - 1) for g in groups)
    within = within / (sum(len(g) for g in groups) - 2)
    within += 1e-12 * np.trace(within) * np.eye(len(gap))
    return float(np.sqrt(gap @ np.linalg.solve(within, gap)))


def test_known_answer_k2_tells_apart_the_alike_cells_that_k1_cannot():
    obs, actions, cells = ring()
    for fit in (
        lambda k: fit_stacked_pca(obs, actions, n_actions=2, action_codes=CODES,
                                  config=StackedPCAConfig(k=k, dim=2)),
        lambda k: fit_window(obs, actions, n_actions=2,
                             config=WindowConfig(k=k, dim=2, components=2)),
    ):
        one, two = fit(1), fit(2)
        assert isinstance(one, StateModel) and isinstance(two, StateModel)
        s1 = one.track(actions, obs).states[:, : planner_dim(one)]
        s2 = two.track(actions, obs).states[:, : planner_dim(two)]
        # k = 1 sees only the same image and action: the groups differ by noise alone
        assert separation(s1, cells, actions) < 0.5
        assert separation(s2, cells, actions) > 5.0


def test_window_state_carries_its_buffer_and_predicts_more_with_a_longer_window():
    """The state is ``[p, x_t]`` for k = 2, its buffer the current step's features exactly;
    and seeing one step further back explains more of the future images (the alike cells
    have different futures: B or A after cell 0, C or A after cell 2)."""
    obs, actions, cells = ring(8000)
    fits = {k: fit_window(obs, actions, n_actions=2,
                          config=WindowConfig(k=k, dim=2, components=2)) for k in (1, 2)}
    model = fits[2]
    states = model.track(actions, obs).states
    assert states.shape[1] == 2 + 4  # p, then one step's buffer: 2 components + 2 actions
    codes = np.matmul((obs - model.obs_mean)[:, None, :], model.obs_components)[:, 0, :]
    np.testing.assert_array_equal(states[:, 2:4], codes)
    np.testing.assert_array_equal(states[:, 4:], np.eye(2)[actions])
    r2 = {k: m.fit_info["future_r2"] for k, m in fits.items()}
    assert 0 < r2[1] < r2[2] < 1
    assert 0 < model.fit_info["future_r2_top_dim"] <= r2[2] + 1e-9


@pytest.mark.parametrize("k", [1, 2, 3])
def test_track_equals_a_loop_of_updates_bit_for_bit(k):
    obs, actions, _ = ring(300, seed=k)
    models = [
        fit_stacked_pca(obs, actions, n_actions=2, action_codes=CODES,
                        config=StackedPCAConfig(k=k, dim=2)),
        fit_stacked_pca(obs, actions, n_actions=2,
                        config=StackedPCAConfig(k=k, dim=3, actions="one-hot")),
        fit_window(obs, actions, n_actions=2, config=WindowConfig(k=k, dim=2, components=2)),
        fit_window(obs, actions, n_actions=2, action_codes=CODES,
                   config=WindowConfig(k=k, dim=2, components=3, actions="code")),
    ]
    rng = np.random.default_rng(k)
    for model in models:
        for initial in (None, rng.normal(size=model.state_dim)):
            state = model.initial_state() if initial is None else initial
            loop = []
            for a, o in zip(actions, obs, strict=True):
                state, info = model.update(state, int(a), o)
                assert not info.recovered and np.isnan(info.normalizer)
                loop.append(state)
            track = model.track(actions, obs, initial)
            assert track.states.shape == (300, model.state_dim)
            assert np.array_equal(track.states, np.array(loop))  # bit for bit
            assert not track.recovered.any()


def test_stacked_state_is_the_window_of_step_features():
    obs, actions, _ = ring(50)
    model = fit_stacked_pca(obs, actions, n_actions=2, action_codes=CODES,
                            config=StackedPCAConfig(k=3))
    states = model.track(actions, obs).states
    codes = np.matmul((obs - model.obs_mean)[:, None, :], model.obs_components)[:, 0, :]
    x = np.concatenate([codes, CODES[actions]], axis=1)  # (T, 5)
    assert model.state_dim == planner_dim(model) == 15
    np.testing.assert_array_equal(states[10], np.concatenate([x[10], x[9], x[8]]))
    # steps before the first hold the training mean of the step features
    np.testing.assert_allclose(model.padding, x.mean(axis=0), rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(states[1], np.concatenate([x[1], x[0], model.padding]))
    assert np.array_equal(model.initial_state(), np.tile(model.padding, 3))
    assert np.array_equal(window_rows(x, 1), x)


def test_window_starts_from_the_mean_step():
    obs, actions, _ = ring(300)
    model = fit_window(obs, actions, n_actions=2, config=WindowConfig(k=3, dim=2, components=2))
    np.testing.assert_allclose(model.padding[2:], np.bincount(actions) / 300, rtol=1e-12)
    start = model.initial_state()
    empty = np.tile(model.padding, 3)
    np.testing.assert_allclose(start[:2], (empty - model.window_mean) @ model.projection,
                               rtol=1e-10, atol=1e-12)
    assert np.array_equal(start[2:], empty[:8])


def test_window_k1_update_ignores_the_previous_state():
    obs, actions, _ = ring(200)
    model = fit_window(obs, actions, n_actions=2, config=WindowConfig(k=1, dim=2, components=2))
    assert model.state_dim == planner_dim(model) == 2
    a = model.update(np.zeros(2), 1, obs[5])[0]
    b = model.update(np.full(2, 7.0), 1, obs[5])[0]
    assert np.array_equal(a, b)


def test_windows_restart_empty_at_every_segment():
    x = np.arange(12, dtype=float).reshape(6, 2)
    rows = window_rows(x, 2, history=np.array([-1.0, -2.0]))
    np.testing.assert_array_equal(rows[0], [0, 1, -1, -2])
    np.testing.assert_array_equal(rows[3], [6, 7, 4, 5])
    obs, actions, _ = ring(400)
    segments = np.repeat([0, 1], 200)
    model = fit_window(obs, actions, n_actions=2, segments=segments,
                       config=WindowConfig(k=2, dim=2, components=2))
    assert model.fit_info["regression_steps"] == 400 - 2 * 10


def test_q_function_ignores_the_trailing_buffer():
    rng = np.random.default_rng(1)
    states, nxt = rng.normal(size=(400, 2)), rng.normal(size=(400, 2))
    actions, rewards = rng.integers(2, size=400), rng.normal(size=400)
    q = fit_q(states, actions, rewards, nxt, 2, FQIConfig(centers=10, ridge=1.0))
    wide = ignore_trailing(q, 5)
    assert wide.state_dim == 5 and ignore_trailing(q, 2) is q
    padded = np.concatenate([states, rng.normal(size=(400, 3)) * 100], axis=1)
    np.testing.assert_allclose(wide.values(padded), q.values(states), rtol=1e-12, atol=1e-12)
    with pytest.raises(DataError, match="cannot hold"):
        ignore_trailing(q, 1)


def test_bad_configs_are_refused_with_clear_errors():
    cases = [
        (lambda: StackedPCAConfig(k=0), "stacked PCA k (steps in the window) must be a positive"),
        (lambda: StackedPCAConfig(k=True), "must be a positive integer, not True"),
        (lambda: StackedPCAConfig(dim=1.5), "stacked PCA dim (components of each image)"),
        (lambda: StackedPCAConfig(actions="both"), "actions must be one of ['code', 'one-hot']"),
        (lambda: WindowConfig(k=-1), "window k (steps in the window)"),
        (lambda: WindowConfig(dim=0), "window dim (state dimension)"),
        (lambda: WindowConfig(components=0), "window components (of each image)"),
        (lambda: WindowConfig(ridge=0.0), "window ridge must be a positive finite number"),
        (lambda: WindowConfig(ridge=float("nan")), "window ridge must be a positive finite"),
        (lambda: WindowConfig(ridge="big"), "window ridge must be a positive number"),
        (lambda: WindowConfig.from_dict({"k": 2, "width": 3}), "unknown window parameters"),
    ]
    for make, message in cases:
        with pytest.raises(ConfigError, match=re.escape(message)):
            make()
    obs, actions, _ = ring(200)
    with pytest.raises(ConfigError, match="needs the commands' codes"):
        fit_stacked_pca(obs, actions, n_actions=2, config=StackedPCAConfig(dim=2))
    with pytest.raises(DataError, match="window dim 9 exceeds what the regression can span"):
        fit_window(obs, actions, n_actions=2, config=WindowConfig(k=2, dim=9, components=2))
    with pytest.raises(DataError, match="codes must be a finite"):
        fit_window(obs, actions, n_actions=2, action_codes=np.zeros((3, 2)),
                   config=WindowConfig(dim=2, components=2, actions="code"))


def test_set_reaches_the_baselines_and_refuses_bad_values():
    configs = {"tpsr": TPSRConfig(), "pca": PCAConfig(), "fqi": FQIConfig(),
               "stacked": StackedPCAConfig(), "window": WindowConfig()}
    changed = apply_overrides(
        configs, ["stacked.k=4", "stacked.actions=one-hot", "window.k=3", "window.ridge=0.01"]
    )
    assert changed["stacked"] == StackedPCAConfig(k=4, actions="one-hot")
    assert changed["window"] == WindowConfig(k=3, ridge=0.01)
    with pytest.raises(ConfigError, match=re.escape("--set window.k=0: window k")):
        apply_overrides(configs, ["window.k=0"])
    with pytest.raises(ConfigError, match="ambiguous; use one of"):
        apply_overrides(configs, ["k=2"])


def test_saving_a_baseline_is_refused_in_one_line(tmp_path):
    obs, actions, _ = ring(200)
    model = fit_window(obs, actions, n_actions=2, config=WindowConfig(k=2, dim=2, components=2))
    with pytest.raises(ModelFormatError) as caught:
        save_model(model, tmp_path / "window.npz")
    assert "\n" not in str(caught.value) and "cannot be saved" in str(caught.value)
    assert not (tmp_path / "window.npz").exists()


def test_experiment_help_lists_the_baselines(capsys):
    code, out, _ = run_entry(["experiment", "--help"], capsys)
    assert code == 0
    for text in ("stacked-pca", "window", "stacked.k=K", "window.<field>"):
        assert text in " ".join(out.split())


def test_experiment_refuses_a_bad_baseline_setting(capsys):
    code, _, err = run_entry(
        ["experiment", "--environment", "partial-strip", "--methods", "window", "--set",
         "window.ridge=-1", "--workers", "1"], capsys)
    assert code != 0 and "window ridge must be a positive finite number" in err


@pytest.mark.slow
def test_experiment_rows_of_the_baselines(tmp_path, capsys):
    out = tmp_path / "results"
    args = ["experiment", "--environment", "partial-strip", "--episodes", "300",
            "--repetitions", "1", "--methods", "stacked-pca", "window", "--set",
            "stacked.k=3", "--set", "window.k=3", "--set", "fqi.ensemble=1",
            "--rl-steps", "2000", "--workers", "1", "-o", str(out)]
    code, _, err = run_entry(args, capsys)
    assert code == 0, err
    with (out / "experiment_partial-strip.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    assert [r["method"] for r in rows] == ["stacked-pca", "window"]
    for row in rows:
        assert row["status"] == "ok" and row["recoveries"] == "0"
        assert np.isfinite(float(row["score"])) and 0 < float(row["r2_y"]) <= 1
        assert float(row["position_error"]) > 0
        assert "--set stacked.k=3 --set window.k=3" in row["command"]
    parameters = [json.loads(r["parameters"]) for r in rows]
    assert parameters[0]["stacked-pca"] == {"k": 3, "dim": 3, "actions": "code"}
    assert parameters[1]["window"] == {"k": 3, "dim": 8, "components": 3,
                                       "actions": "one-hot", "ridge": 0.001}
