"""A refit as statistics that merge and decay: exact against the two-pass fit, and right
against a known POMDP's Bayes filter, also after the world changes."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
from learning_fixtures import POMDP, episodes_from_symbols, example_pomdp
from test_tpsr_known_answer import filtering_errors

from tpsr_ros.core.episodes import Trajectory, make_episodes
from tpsr_ros.core.errors import ConfigError, DataError
from tpsr_ros.core.fit_basis import SKETCH_MARGIN, Sketch
from tpsr_ros.core.fit_statistics import FitStatistics, forgetting_weights
from tpsr_ros.core.learn import fit
from tpsr_ros.core.presets import PRESETS
from tpsr_ros.core.sizing import Sizing
from tpsr_ros.core.tpsr import TPSRConfig, fit_tpsr, fit_tpsr_episodes

SMALL = TPSRConfig(
    center_selection="kmeans", obs_centers=12, ht_centers=20, obs_dim=4, ht_dim=4, rank=4,
    p_th_tests="from-current", normalize_ht_features=True, action_pooling=0.5,
)  # fmt: skip


def _trajectory(steps: int, seed: int = 0) -> Trajectory:
    """4 actions push a slow drift that the observations show through noise."""
    rng = np.random.default_rng(seed)
    actions = rng.integers(0, 4, steps)
    obs = np.empty((steps, 6))
    level = np.zeros(6)
    for k in range(steps):
        level = 0.8 * level + 0.3 * (actions[k] - 1.5)
        obs[k] = level + rng.normal(scale=0.3, size=6)
    return Trajectory.from_arrays(actions, obs)


def _episodes(trajectory: Trajectory):
    return make_episodes(trajectory, 1, 1)


def _parts(episodes, start: int, stop: int) -> SimpleNamespace:
    return SimpleNamespace(**{
        name: getattr(episodes, name)[start:stop]
        for name in ("history", "observation", "action", "test", "history_actions",
                     "test_actions")
    })  # fmt: skip


@pytest.fixture(scope="module")
def first():
    """A first fit of the small config: the basis a refit keeps."""
    episodes = _episodes(_trajectory(2400))
    return fit_tpsr_episodes(episodes, config=SMALL)


def test_a_first_fit_keeps_a_sketch_of_p_th_wider_than_its_rank(first):
    sketch = first.basis.sketch
    assert sketch.width == min(SMALL.rank + SKETCH_MARGIN, SMALL.ht_centers + 1)
    for basis in (sketch.test, sketch.history):  # orthonormal columns
        np.testing.assert_allclose(basis.T @ basis, np.eye(sketch.width), atol=1e-10)


@pytest.mark.parametrize("pooling", [0.5, 1.0])  # per-action sums; their total only
def test_with_a_sketch_of_the_whole_range_the_statistics_solve_to_the_two_pass_fit(first, pooling):
    """An identity sketch keeps every direction: the sums are P_TH and the unprojected
    operator sums, and the solution is run_fit's on the same basis, to rounding."""
    full = np.eye(SMALL.ht_centers + 1)
    config = replace(first.basis.config, action_pooling=pooling)
    basis = replace(first.basis, config=config, sketch=Sketch(full, full))
    episodes = _episodes(_trajectory(6000, seed=3))
    exact = fit_tpsr_episodes(episodes, config=basis.config, basis=basis, sizing=Sizing())
    solved = FitStatistics.empty(basis, 4).partial_fit(episodes).solve()
    assert solved.config.rank == exact.config.rank == SMALL.rank
    for name in ("b_star", "b_inf", "B", "singular_values"):
        got, want = getattr(solved, name), getattr(exact, name)
        np.testing.assert_allclose(
            got, want, rtol=1e-8, atol=1e-10 * np.abs(want).max(), err_msg=name
        )


def test_the_statistics_of_a_first_fits_own_data_on_its_sketch_solve_to_it():
    """The sketch holds the first fit's leading directions of P_TH: its own data's
    statistics give back the same filter, to rounding."""
    data = _trajectory(3000, seed=10)
    model = fit(data, PRESETS["best"].tpsr_config())  # the learner node's refits: spectral
    episodes = make_episodes(data, 1, 1)
    again = FitStatistics.empty(model.basis, 4).partial_fit(episodes).solve()
    assert again.config == model.config
    for name in ("b_star", "b_inf", "B"):
        got, want = getattr(again, name), getattr(model, name)
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12 * np.abs(want).max())
    states = model.track(data.actions, data.observations).states
    np.testing.assert_allclose(
        again.track(data.actions, data.observations).states, states, rtol=0,
        atol=1e-9 * np.abs(states).max(),
    )  # fmt: skip


def test_the_sketch_compresses_the_spectrum_of_more_data(first):
    """On more data the sketch's singular values are those of the whole P_TH compressed:
    none above them (interlacing), the leading ones close."""
    episodes = _episodes(_trajectory(9000, seed=11))
    sketched = FitStatistics.empty(first.basis, 4).partial_fit(episodes).solve()
    whole = fit_tpsr_episodes(
        episodes, config=first.basis.config, basis=replace(first.basis, sketch=None),
        sizing=Sizing(),
    )  # fmt: skip
    r = min(sketched.state_dim, whole.state_dim)
    values, reference = sketched.singular_values[:r], whole.singular_values[:r]
    assert (values <= reference * (1 + 1e-9)).all()
    np.testing.assert_allclose(values[:2], reference[:2], rtol=0.01)


def test_statistics_of_chunks_merge_to_those_of_all_the_data(first, monkeypatch):
    import tpsr_ros.core.fit_statistics as module

    monkeypatch.setattr(module, "BLOCK_ROWS", 300)  # blocks inside one call, too
    episodes = _episodes(_trajectory(4500, seed=4))
    n = len(episodes)
    empty = FitStatistics.empty(first.basis, 4)
    whole = empty.partial_fit(episodes)
    chunks = [empty.partial_fit(_parts(episodes, a, min(n, a + 700))) for a in range(0, n, 700)]
    merged = chunks[0]
    for chunk in chunks[1:]:
        merged = merged.merge(chunk)
    for name in ("weight", "weight_sq", "history_sum", "p_th", "counts", "b_sums"):
        np.testing.assert_allclose(getattr(merged, name), getattr(whole, name), rtol=1e-11,
                                   atol=1e-12, err_msg=name)  # fmt: skip
    assert merged.episodes == n
    np.testing.assert_allclose(merged.solve().B, whole.solve().B, rtol=1e-8, atol=1e-12)
    assert whole.weight == n and empty.weight == 0  # the operands are left as they were


def test_decayed_sums_are_the_sums_weighted_by_age(first):
    episodes = _episodes(_trajectory(3000, seed=5))
    n, split, lam = len(episodes), 600, 0.999
    ages = 3.0 * (n - 1 - np.arange(n))  # three steps an episode
    weights = forgetting_weights(ages, lam)
    empty = FitStatistics.empty(first.basis, 4)
    at_once = empty.partial_fit(episodes, weights)
    old = empty.partial_fit(
        _parts(episodes, 0, split), forgetting_weights(ages[:split] - ages[split - 1], lam)
    )
    new = empty.partial_fit(_parts(episodes, split, n), weights[split:])
    streamed = old.decayed(lam ** ages[split - 1]).merge(new)
    for name in ("weight", "weight_sq", "history_sum", "p_th", "counts", "b_sums"):
        np.testing.assert_allclose(getattr(streamed, name), getattr(at_once, name), rtol=1e-11,
                                   atol=1e-12, err_msg=name)  # fmt: skip
    assert at_once.episodes < n  # forgetting leaves fewer effective episodes


def test_refusals_name_the_problem(first):
    empty = FitStatistics.empty(first.basis, 4)
    with pytest.raises(DataError, match="no episodes"):
        empty.solve()
    with pytest.raises(ConfigError, match="no sketch"):
        FitStatistics.empty(replace(first.basis, sketch=None), 4)
    with pytest.raises(ConfigError, match="forgetting"):
        forgetting_weights(np.arange(3), 1.5)
    episodes = _episodes(_trajectory(300, seed=6))
    with pytest.raises(DataError, match="weights"):
        empty.partial_fit(episodes, -np.ones(len(episodes)))
    with pytest.raises(DataError, match="never occur"):  # an action without samples
        empty.partial_fit(_parts(episodes, 0, 3)).solve()


# -- ground truth: a POMDP of linear dimension 3 (tests/test_tpsr_known_answer.py) ----------

POMDP_CONFIG = TPSRConfig(
    obs_dim=3, ht_dim=3, obs_centers=40, ht_centers=40, sigma_obs=0.05, sigma_ht=0.05, rank=3,
    p_th_tests="from-current", center_selection="kmeans",
)  # fmt: skip


def _pomdp_episodes(pomdp: POMDP, steps: int, seed: int) -> SimpleNamespace:
    obs, actions = pomdp.sample(steps, seed=seed)
    h, o, a, t = episodes_from_symbols(obs, actions, pomdp.n_obs)
    return SimpleNamespace(history=h, observation=o, action=a, test=t, history_actions=None,
                           test_actions=None)  # fmt: skip


def _basis(pomdp: POMDP):
    e = _pomdp_episodes(pomdp, 9000, seed=1)
    return fit_tpsr(e.history, e.observation, e.action, e.test, n_actions=2,
                    config=POMDP_CONFIG).basis  # fmt: skip


@pytest.mark.slow
def test_a_refit_from_the_sums_filters_as_the_bayes_filter_does():
    pomdp = example_pomdp()
    stats = FitStatistics.empty(_basis(pomdp), pomdp.n_actions)
    for seed in range(2, 6):  # 4 x 60000 steps, one chunk at a time
        stats = stats.partial_fit(_pomdp_episodes(pomdp, 60_000, seed))
    errors = filtering_errors(stats.solve(), pomdp)
    assert errors.mean() < 0.03, errors.mean()


@pytest.mark.slow
def test_forgetting_follows_a_world_that_changes():
    """The actions' effects swap halfway; with forgetting the refit filters the new world
    as its Bayes filter does, without it the model of both worlds mixed does not."""
    before = example_pomdp()
    after = POMDP(T=before.T[::-1].copy(), O=before.O)
    basis = _basis(before)
    # the memory 1 / (1 - lam) scaled with the steps: the old world's weight, lam ** ages[0],
    # is what 0.99998 gave it on 300000 steps, with half the sampling and fitting
    lam, steps = 0.99996, 150_000
    old = _pomdp_episodes(before, steps, seed=2)
    new = _pomdp_episodes(after, steps, seed=3)
    ages = 3.0 * (len(new.action) - 1 - np.arange(len(new.action)))
    empty = FitStatistics.empty(basis, 2)
    kept = empty.partial_fit(old).merge(empty.partial_fit(new))
    forgetting = (
        empty.partial_fit(old).decayed(lam ** (ages[0] + 3)).merge(
            empty.partial_fit(new, forgetting_weights(ages, lam))
        )
    )  # fmt: skip
    error_kept = filtering_errors(kept.solve(), after).mean()
    error_forgetting = filtering_errors(forgetting.solve(), after).mean()
    assert error_forgetting < 0.06, (error_forgetting, error_kept)  # 0.046
    assert error_kept > 2 * error_forgetting, (error_forgetting, error_kept)  # 0.144
