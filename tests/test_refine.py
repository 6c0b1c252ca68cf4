"""Refinement of a spectral TPSR through its filter (tpsr_ros.core.refine).

The gradient is checked against central finite differences, on pooled and unpooled
operators; a refined model starts exactly at the spectral one and is tracked by the usual
filter; refinement lowers the held-out error it optimises on a system with memory; a start
that carries half of the state tells apart, after the refinement, two places that look
alike where the spectral start cannot; a past target makes the refined state tell the
previous observation; and the options are refused where they cannot apply.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from tpsr_ros.core.episodes import Trajectory, make_episodes
from tpsr_ros.core.errors import ConfigError, DataError
from tpsr_ros.core.learn import fit, fit_tpsr_trajectory
from tpsr_ros.core.refine import (
    Factors,
    RefineProblem,
    carried,
    factor_model,
    group_scales,
    refine_tpsr,
)
from tpsr_ros.core.tpsr import TPSRConfig


def ring(steps: int, seed: int) -> Trajectory:
    """A robot on a ring of 4 cells: action 0 stays, 1 moves one cell on. Cells 0 and 2 look
    alike (symbols 0, 1, 0, 2) but are followed by different symbols: only the past tells
    which one the robot is in. Observations: the symbol one-hot, with noise."""
    rng = np.random.default_rng(seed)
    actions = rng.integers(0, 2, size=steps)
    cell = np.cumsum(actions) % 4
    shown = np.array([0, 1, 0, 2])[cell]
    obs = np.eye(3)[shown] + 0.1 * rng.normal(size=(steps, 3))
    return Trajectory.from_arrays(actions, obs, n_actions=2)


CONFIG = TPSRConfig(
    obs_dim=2,
    ht_dim=2,
    obs_centers=30,
    ht_centers=60,
    rank=4,
    normalize_ht_features=True,
    p_th_tests="from-current",
    refine_epochs=40,
    refine_window=6,
    refine_horizon=3,
)


@pytest.fixture(scope="module")
def aliased() -> Trajectory:
    return ring(6000, seed=1)


@pytest.fixture(scope="module")
def refined(aliased: Trajectory):
    """The aliased ring's model refined with CONFIG (no carry): fitted once, read by two tests."""
    return fit_tpsr_trajectory(aliased, CONFIG)


def visible_ring(steps: int, seed: int) -> Trajectory:
    """The README's ring of 6 cells, each seen as itself with noise: a well-fitted model whose
    objective is smooth where the finite differences probe it."""
    rng = np.random.default_rng(seed)
    actions = rng.integers(0, 2, size=steps)
    obs = np.eye(6)[np.cumsum(actions) % 6] + 0.1 * rng.normal(size=(steps, 6))
    return Trajectory.from_arrays(actions, obs, n_actions=2)


@pytest.mark.parametrize(
    ("pooling", "barrier", "past"), [(1.0, 1.0, 0), (0.0, 1.0, 0), (1.0, 20.0, 0), (1.0, 1.0, 2)]
)
def test_gradient_matches_finite_differences(pooling: float, barrier: float, past: int) -> None:
    """``barrier`` raises the normaliser barrier's floor so that it bites at most steps;
    ``past``: the states also predict the last observations."""
    data = visible_ring(2000, seed=0)
    cfg = replace(
        CONFIG, obs_dim=5, ht_dim=5, rank=6, action_pooling=pooling, refine_past=past
    )
    model = fit_tpsr_trajectory(data, replace(cfg, refine_epochs=0))
    model = replace(model, config=cfg)
    start = factor_model(model)
    problem = RefineProblem(model, start, data.actions, data.observations, [(0, len(data))])
    assert problem.z_floor > 0
    problem.z_floor *= barrier
    if barrier > 1:
        assert problem.loss_and_grad(start.vector())[0] > 0.5  # the barrier dominates
    rng = np.random.default_rng(0)
    theta = start.vector() * (1 + 0.001 * rng.normal(size=start.vector().size))
    _, grad = problem.loss_and_grad(theta)
    n = theta.size
    r = model.state_dim
    picks = np.concatenate([
        rng.choice(start.shared.size, 6, replace=False),  # B_o'
        start.shared.size + rng.choice(start.action.size, 6, replace=False),  # A_a
        np.arange(n - r, n),  # b_inf
    ])  # fmt: skip
    for i in picks:
        step = 1e-6 * max(1.0, abs(theta[i]))
        e = np.zeros(n)
        e[i] = step
        numeric = (problem.loss_and_grad(theta + e)[0] - problem.loss_and_grad(theta - e)[0]) / (
            2 * step
        )
        assert grad[i] == pytest.approx(numeric, rel=1e-4, abs=1e-8), i


@pytest.mark.parametrize("pooling", [1.0, 0.5, 0.0])
def test_start_is_the_spectral_model(aliased: Trajectory, pooling: float) -> None:
    """The factors plus their fixed rest reproduce every operator, pooled or not."""
    model = fit_tpsr_trajectory(aliased, replace(CONFIG, refine_epochs=0, action_pooling=pooling))
    start = factor_model(model)
    problem = RefineProblem(
        replace(model, config=CONFIG), start, aliased.actions, aliased.observations,
        [(0, len(aliased))],
    )  # fmt: skip
    if pooling == 1.0:
        np.testing.assert_allclose(start.action, np.broadcast_to(np.eye(4), start.action.shape),
                                   atol=1e-8)  # fmt: skip
    # the windows' states under the start equal the filter's own from b_*
    first = int(problem.train_starts[3])
    span = 2 * problem.window
    expected = model.track(
        aliased.actions[first : first + span], aliased.observations[first : first + span]
    ).states[problem.window :]
    got = problem.states(start, problem.train_starts[3:4])
    np.testing.assert_allclose(got, expected, rtol=1e-9, atol=1e-12)


def test_refinement_lowers_the_heldout_error_on_an_aliased_ring(
    aliased: Trajectory, refined
) -> None:
    model = refined
    info = model.fit_info["refinement"]
    assert info["best_iteration"] >= 1
    assert info["heldout_unexplained"] < info["heldout_unexplained_spectral"] - 0.01
    # the refined operators are what the usual filter tracks with: track equals updates
    track = model.track(aliased.actions[:50], aliased.observations[:50])
    state = model.initial_state()
    for s in range(50):
        state, _ = model.update(state, int(aliased.actions[s]), aliased.observations[s])
        np.testing.assert_array_equal(state, track.states[s])


def test_a_past_target_adds_the_last_observations_after_the_next_ones(
    aliased: Trajectory,
) -> None:
    """Each scored step's targets: the next ``horizon`` observations' features, then those
    of the last ``refine_past`` before the current one, centred over the scored steps."""
    from tpsr_ros.core.refine import _targets

    model = fit_tpsr_trajectory(aliased, replace(CONFIG, refine_epochs=0))
    bounds = [(0, len(aliased))]
    problems = {
        past: RefineProblem(
            replace(model, config=replace(CONFIG, refine_past=past)), factor_model(model),
            aliased.actions, aliased.observations, bounds,
        )  # fmt: skip
        for past in (0, 2)
    }
    features = _targets(model, aliased.observations)
    problem = problems[2]
    w, h, p = problem.window, problem.horizon, features.shape[1]
    scored = (problem.train_starts[:, None] + w + np.arange(w)).ravel()
    offsets = [1, 2, 3, -1, -2]  # horizon 3, then the last two
    expected = np.concatenate([features[scored + k] for k in offsets], axis=1)
    expected -= expected.mean(axis=0)
    got = problem._targets["train"]
    assert got.shape == (scored.size, (h + 2) * p)
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12)
    # without a past target, the same futures, bit for bit
    np.testing.assert_array_equal(problems[0]._targets["train"], got[:, : h * p])
    with pytest.raises(ConfigError, match="refine_past 7 exceeds refine_window 6"):
        replace(CONFIG, refine_past=7)
    with pytest.raises(ConfigError, match="refine_past must be a non-negative integer"):
        replace(CONFIG, refine_past=-1)


@pytest.mark.slow
def test_a_past_target_makes_the_state_tell_the_last_observation(
    aliased: Trajectory, refined
) -> None:
    """Ground truth: on the aliased ring, an affine read-out of the refined state recovers
    the previous observation, held out, far better when the refinement also asked the
    states for it (``refine_past`` 1) than when it asked for the next ones alone."""
    test = ring(4000, seed=7)  # trained on ring(6000, seed=1)
    with_past = fit_tpsr_trajectory(aliased, replace(CONFIG, refine_past=1))
    assert with_past.fit_info["refinement"]["past"] == 1
    assert "past" not in refined.fit_info["refinement"]
    previous = test.observations[:-1]
    half = previous.shape[0] // 2
    r2 = {}
    for past, model in ((0, refined), (1, with_past)):
        states = model.track(test.actions, test.observations).states[1:]
        x = np.column_stack([states, np.ones(states.shape[0])])
        w = np.linalg.lstsq(x[:half], previous[:half], rcond=None)[0]
        residual = previous[half:] - x[half:] @ w
        spread = previous[half:] - previous[:half].mean(axis=0)
        r2[past] = 1.0 - float((residual**2).sum()) / float((spread**2).sum())
    assert r2[1] >= 0.55 and r2[1] > r2[0] + 0.2, r2


def test_a_carried_step_mixes_the_update_with_the_previous_state(aliased: Trajectory) -> None:
    """mu I on every operator: each step is (B_ao b + mu b) / (z + mu) for pooled operators,
    and at the spectral filter's median normaliser the previous state weighs the carry."""
    model = fit_tpsr_trajectory(aliased, replace(CONFIG, refine_epochs=0, refine_carry=0.4))
    spectral = model.track(aliased.actions, aliased.observations)
    median_z = float(np.median(spectral.normalizers[~spectral.recovered]))
    start, mu = carried(model, aliased.actions, aliased.observations)
    assert mu / (median_z + mu) == pytest.approx(0.4, rel=1e-12)
    b = spectral.states[99]
    a, o = int(aliased.actions[100]), aliased.observations[100]
    got, _ = start.update(b, a, o)
    plain, info = model.update(b, a, o)
    assert not info.recovered
    z = info.normalizer
    np.testing.assert_allclose(got, (z * plain + mu * b) / (z + mu), rtol=1e-10, atol=1e-12)
    plain_config = replace(model, config=CONFIG)
    itself, none = carried(plain_config, aliased.actions, aliased.observations)
    assert itself is plain_config and none == 0.0


@pytest.mark.slow
def test_carry_lets_the_refined_filter_remember_which_lookalike_it_stands_in(
    aliased: Trajectory, refined
) -> None:
    """Ground truth: on the ring, cells 0 and 2 look alike. After two steps standing still
    in one of them, the past alone tells which; an affine read-out of the state must say.
    The spectral start forgets within a step and its refinement cannot find the past (the
    gradient through a contracting filter vanishes); starting from half the state carried
    forward, the refinement keeps it."""
    test = ring(4000, seed=7)  # trained on the aliased ring, ring(6000, seed=1)
    cell = np.cumsum(np.random.default_rng(7).integers(0, 2, size=4000)) % 4  # as ring()
    acts = test.actions
    stood = np.flatnonzero(
        np.isin(cell, (0, 2)) & (acts == 0) & (np.roll(acts, 1) == 0) & (np.arange(4000) > 2)
    )
    half = stood.size // 2
    accuracy, heldout = {}, {}
    for carry in (0.0, 0.5):
        if carry == 0.0:
            model = refined
        else:
            model = fit_tpsr_trajectory(aliased, replace(CONFIG, refine_carry=carry))
        states = model.track(test.actions, test.observations).states[stood]
        x = np.column_stack([states, np.ones(stood.size)])
        y = (cell[stood] == 0).astype(float)
        w = np.linalg.lstsq(x[:half], y[:half], rcond=None)[0]
        accuracy[carry] = float(np.mean((x[half:] @ w > 0.5) == (y[half:] > 0.5)))
        heldout[carry] = model.fit_info["refinement"]["heldout_unexplained"]
        assert model.fit_info["refinement"]["carry"] == carry
    assert accuracy[0.5] >= 0.95 > 0.8 >= accuracy[0.0]
    assert heldout[0.5] < heldout[0.0]


@pytest.mark.slow
def test_a_carried_start_is_never_returned_as_the_model(
    aliased: Trajectory, monkeypatch: pytest.MonkeyPatch
) -> None:
    """When no iterate qualifies (here: no restart allowed at all), the result is the
    spectral model's operators, not the carried start the search began from."""
    import tpsr_ros.core.refine as refine

    spectral = fit_tpsr_trajectory(aliased, replace(CONFIG, refine_epochs=0))
    monkeypatch.setattr(refine, "restart_allowance", lambda count: -1)
    kept = refine_tpsr(replace(spectral, config=replace(CONFIG, refine_carry=0.5)),
                       aliased.actions, aliased.observations)  # fmt: skip
    assert kept.fit_info["refinement"]["kept"] == "spectral"
    assert kept.fit_info["refinement"]["best_iteration"] == 0
    np.testing.assert_array_equal(kept.B, spectral.B)
    np.testing.assert_array_equal(kept.b_inf, spectral.b_inf)


def test_group_scaling_divides_each_group_by_its_root_mean_square() -> None:
    """B_o' entries ~0.004 and A_a ~0.35 (a real model's): the search's variables are the
    parameters over their group's size, a group of zeros keeps 1, and ``none`` is 1."""
    start = Factors(
        shared=np.full((3, 2, 2), 0.004), action=np.stack([np.eye(2)] * 2), b_inf=np.zeros(2)
    )
    scales = group_scales(start, "groups")
    n_s, n_a = start.shared.size, start.action.size
    np.testing.assert_allclose(scales[:n_s], 0.004)
    np.testing.assert_allclose(scales[n_s : n_s + n_a], np.sqrt(0.5))
    np.testing.assert_array_equal(scales[n_s + n_a :], 1.0)
    assert (start.vector() / scales)[:n_s] == pytest.approx(1.0)
    np.testing.assert_array_equal(group_scales(start, "none"), np.ones(n_s + n_a + 2))


def test_a_scaled_search_is_recorded_and_tracked_by_the_usual_filter(aliased: Trajectory) -> None:
    model = fit_tpsr_trajectory(aliased, replace(CONFIG, refine_scaling="groups"))
    assert model.fit_info["refinement"]["scaling"] == "groups"
    track = model.track(aliased.actions[:30], aliased.observations[:30])
    state = model.initial_state()
    for s in range(30):
        state, _ = model.update(state, int(aliased.actions[s]), aliased.observations[s])
        np.testing.assert_array_equal(state, track.states[s])
    with pytest.raises(ConfigError, match="refine_scaling must be one of"):
        replace(CONFIG, refine_scaling="diagonal")


def test_the_restart_allowance_is_the_count_within_its_noise() -> None:
    from tpsr_ros.core.refine import restart_allowance

    assert [restart_allowance(n) for n in (0, 3, 4, 72)] == [2, 7, 9, 90]


def test_no_epochs_is_the_spectral_model_bit_for_bit(aliased: Trajectory) -> None:
    spectral = fit_tpsr_trajectory(aliased, replace(CONFIG, refine_epochs=0))
    assert refine_tpsr(spectral, aliased.actions, aliased.observations) is spectral
    assert "refinement" not in spectral.fit_info


def test_refinement_refused_where_it_cannot_apply(aliased: Trajectory) -> None:
    episodes = make_episodes(aliased, 1, 1)
    with pytest.raises(ConfigError, match="trajectory"):
        fit(episodes, CONFIG)
    with pytest.raises(ConfigError, match="state box"):  # refused before any fit
        replace(CONFIG, state_clip_quantile=0.01)
    with pytest.raises(ConfigError, match="refine_epochs"):
        replace(CONFIG, refine_epochs=-1)
    with pytest.raises(ConfigError, match="refine_pull"):
        replace(CONFIG, refine_pull=float("nan"))
    for carry in (1.0, -0.1, float("nan")):
        with pytest.raises(ConfigError, match="refine_carry"):
            replace(CONFIG, refine_carry=carry)


def test_data_too_short_to_refine_are_fitted_spectral_unless_the_refinement_was_asked_for() -> None:
    """Like the kernel centres, the default preset's refinement follows the data: a log too
    short for two windows gives the spectral model, says so, and records refine_epochs 0;
    refinement set on purpose is refused with the reason instead."""
    from tpsr_ros.core.presets import DEFAULT_PRESET, get_preset

    short = visible_ring(50, seed=4)  # two windows of 2 x 16 + 10 steps need 58
    default = fit(short)
    spectral = fit(short, get_preset(DEFAULT_PRESET).tpsr_config(refine_epochs=0))
    assert default.config.refine_epochs == 0 and "refinement" not in default.fit_info
    assert default.fit_info["sized"]["refine_epochs"] == [30, 0]
    assert "two windows of 42 steps" in default.fit_info["refinement_skipped"]
    np.testing.assert_array_equal(default.B, spectral.B)
    asked = get_preset(DEFAULT_PRESET).tpsr_config(refine_epochs=20)
    with pytest.raises(DataError, match="two windows of 42 steps in one segment; the data has 1"):
        fit(short, asked)
    longer = fit(visible_ring(600, seed=4))  # long enough: refined as configured
    assert longer.config.refine_epochs == 30 and "refinement" in longer.fit_info


def test_learner_fit_says_what_the_refinement_did() -> None:
    from learner.fit import refinement_line

    base = {"iterations": 12, "best_iteration": 7, "heldout_unexplained_spectral": 0.6,
            "heldout_unexplained": 0.5, "seconds": 5.0}  # fmt: skip
    older = refinement_line(base, 10.0)  # a model file written before the carry
    assert older == (
        "refinement: 12 iteration(s), best after iteration 7; held-out unexplained variance "
        "of the next images 0.6000 -> 0.5000; 5.0 s (50 % of the fit)"
    )
    line = refinement_line(
        {**base, "best_iteration": 0, "carry": 0.3, "heldout_restarts": 4,
         "heldout_restarts_allowed": 9}, 20.0,
    )  # fmt: skip
    assert line.startswith("refinement from a start carrying 0.3 of the state: 12 iteration(s)")
    assert "the spectral model kept" in line and "held-out restarts 4 (allowed 9)" in line
    assert line.endswith("5.0 s (25 % of the fit)")
    past = refinement_line({**base, "past": 2}, 10.0)
    assert "held-out unexplained variance of the next images and the last 2 0.6000" in past
    chose = refinement_line({**base, "carry": 0.0, "history_gain": -0.0004}, 10.0)
    assert chose.startswith(
        "refinement (the previous image's held-out gain in predicting the next ones -0.0004: "
        "no carry): 12 iteration(s)"
    )
