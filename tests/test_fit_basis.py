"""The frozen fit basis: a refit keeps its whitenings and centres; `learner fit --init-from`."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from cli_support import run_entry

from sim_node import SimConfig
from sim_node.generate import generate_bag
from tpsr_ros.core.episodes import Trajectory, make_episodes
from tpsr_ros.core.errors import ConfigError, DataError, ModelFormatError
from tpsr_ros.core.fit_basis import FitBasis
from tpsr_ros.core.learn import fit
from tpsr_ros.core.presets import PRESETS
from tpsr_ros.core.refit import fit_trajectory
from tpsr_ros.core.sizing import Sizing
from tpsr_ros.core.tpsr import fit_tpsr_episodes
from tpsr_ros.io.model_io import model_fingerprint, open_model, save_model
from tpsr_ros.io.trajectory import read_trajectory


def _trajectory(steps: int, seed: int = 0) -> Trajectory:
    """A 4-action system whose observation follows its action and its last observation."""
    rng = np.random.default_rng(seed)
    actions = rng.integers(0, 4, steps)
    obs = np.empty((steps, 6))
    level = np.zeros(6)
    for k in range(steps):  # a slow drift the actions push: the past matters
        level = 0.8 * level + 0.3 * (actions[k] - 1.5)
        obs[k] = level + rng.normal(scale=0.3, size=6)
    return Trajectory.from_arrays(actions, obs)


def test_a_refit_on_the_same_data_with_the_fits_own_basis_is_the_same_model():
    data = _trajectory(3000)
    model = fit(data)
    assert model.basis is not None
    again = fit_trajectory(data, model.basis.config, basis=model.basis).model
    assert model_fingerprint(again) == model_fingerprint(model)


def test_a_refit_keeps_the_whitenings_and_centres_and_refits_the_operators():
    first, longer = _trajectory(1500), _trajectory(4500, seed=1)
    spectral = PRESETS["best"].tpsr_config()  # no refinement: the solution by hand below
    basis = fit(first, spectral).basis
    refit = fit_trajectory(longer, basis.config, basis=basis).model
    assert refit.basis is basis
    np.testing.assert_array_equal(refit.obs_centers, basis.centres.observation)
    np.testing.assert_array_equal(refit.obs_mean, basis.obs.mean_)
    # the operators are the spectral solution of the longer data in that basis: the same
    # fit by hand, whitening with the basis and choosing no centres, agrees exactly
    cfg = basis.config
    by_hand = fit_tpsr_episodes(
        make_episodes(longer, cfg.history_length, cfg.test_length), config=cfg, basis=basis,
        sizing=Sizing(),
    )  # fmt: skip
    np.testing.assert_array_equal(refit.B, by_hand.B)
    fresh = fit(longer, spectral)  # a fit of its own chooses other centres: another model
    assert not np.array_equal(fresh.obs_centers, refit.obs_centers)


def test_the_rank_follows_the_rank_rule_from_the_rank_asked(tmp_path):
    few = _trajectory(300)
    basis = fit(few).basis
    assert basis.config.rank == 8  # the preset's, before the rule lowered it for 100 episodes
    refit = fit_trajectory(_trajectory(9000, seed=2), basis.config, basis=basis).model
    assert refit.state_dim <= 8
    assert refit.fit_info["supported_rank"] >= refit.state_dim


def test_a_refit_refuses_observations_of_another_size():
    basis = fit(_trajectory(1500)).basis
    other = Trajectory.from_arrays(np.arange(600) % 4, np.zeros((600, 5)) + np.arange(5))
    with pytest.raises(DataError, match="observations hold 5 values, the basis whitens 6"):
        fit_trajectory(other, basis.config, basis=basis)


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    """A default model of 2000 steps and its file: fitted once for the tests that read it."""
    model = fit(_trajectory(2000))
    return model, save_model(model, tmp_path_factory.mktemp("basis") / "m.npz")


def test_the_basis_round_trips_through_the_model_file_outside_the_fingerprint(saved):
    model, path = saved
    opened = open_model(path)
    assert opened.fingerprint == model_fingerprint(model)
    loaded = opened.model.basis
    assert isinstance(loaded, FitBasis) and loaded.config == model.basis.config
    for name, array in model.basis.to_arrays().items():
        np.testing.assert_array_equal(loaded.to_arrays()[name], array)
    stripped = replace(model, basis=None)  # the same filter without it: the same fingerprint
    assert model_fingerprint(stripped) == opened.fingerprint


def _rewritten(src, dst, change):
    """A copy of a model file with its metadata changed by ``change``."""
    with np.load(src, allow_pickle=False) as npz:
        content = {name: npz[name] for name in npz.files}
    metadata = json.loads(str(content["metadata"]))
    change(metadata)
    content["metadata"] = np.array(json.dumps(metadata))
    with open(dst, "wb") as handle:
        np.savez(handle, **content)
    return dst


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda m: m["basis"].update(history_width=-1), "history_width"),
        (lambda m: m["basis"].update(rank=10**6), "rank above its centres"),
        (lambda m: m.update(basis=[1]), "invalid 'basis' entry"),
        (lambda m: m["basis"].update(test_width=m["basis"]["test_width"] + 1), "shape"),
    ],
)
def test_a_file_whose_basis_entry_is_broken_is_refused(saved, tmp_path, change, message):
    with pytest.raises(ModelFormatError, match=message):
        open_model(_rewritten(saved[1], tmp_path / "bad.npz", change))


def test_a_basis_that_does_not_fit_its_config_is_refused(saved):
    basis = saved[0].basis
    with pytest.raises(DataError, match="centres"):
        replace(basis, config=replace(basis.config, ht_centers=basis.config.ht_centers + 1))
    with pytest.raises(ConfigError, match="above the basis's"):
        basis.fit_config(basis.config.ht_centers + 1)


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    root = tmp_path_factory.mktemp("init_from")
    generate_bag(root / "short", SimConfig(environment="full"), 900, seed=5)
    generate_bag(root / "long", SimConfig(environment="full"), 2100, seed=6)
    return root


@pytest.mark.slow
def test_learner_fit_init_from_is_the_refit_of_the_bag_on_the_models_basis(bags, capsys):
    first = bags / "first.npz"
    code, _, stderr = run_entry(["fit", str(bags / "short"), "-o", str(first)], capsys)
    assert code == 0, stderr
    out = bags / "refit.npz"
    code, _, stderr = run_entry(
        ["fit", str(bags / "long"), "--init-from", str(first), "-o", str(out)], capsys
    )
    assert code == 0, stderr
    replaced = open_model(first).model
    basis = replaced.basis
    expected = fit_trajectory(
        read_trajectory([bags / "long"]), basis.config, basis=basis, align_to=replaced
    )
    refit = open_model(out)
    for name, array in expected.model.to_arrays().items():
        np.testing.assert_allclose(refit.model.to_arrays()[name], array, rtol=0, atol=1e-12)
    assert refit.training["init_from"]["fingerprint"] == open_model(first).fingerprint
    assert refit.metadata["preset"]["name"] == "predictive"  # the first fit's, the default
    assert refit.view is not None


@pytest.mark.parametrize(
    ("options", "named"),
    [
        (["--rank", "4"], "--rank"),
        (["--method", "pca"], "--method pca"),
        (["--stream"], "--stream/--workers/--scheduler"),
        (["--step-period", "0.5"], "--step-period"),
    ],
)
def test_learner_fit_init_from_refuses_options_that_would_change_the_basis(
    bags, capsys, options, named
):
    first = bags / "first_refuse.npz"
    if not first.exists():
        assert run_entry(["fit", str(bags / "short"), "-o", str(first)], capsys)[0] == 0
    code, _, stderr = run_entry(
        ["fit", str(bags / "long"), "--init-from", str(first), "-o", str(bags / "x.npz"),
         *options],
        capsys,
    )  # fmt: skip
    assert code != 0 and named in stderr and "--init-from refits" in stderr


def test_learner_fit_init_from_a_model_without_a_basis_says_so(bags, tmp_path, capsys):
    model = fit(read_trajectory([bags / "short"]))
    path = save_model(replace(model, basis=None), tmp_path / "old.npz")
    code, _, stderr = run_entry(
        ["fit", str(bags / "long"), "--init-from", str(path), "-o", str(tmp_path / "m.npz")],
        capsys,
    )
    assert code != 0 and "holds no fit basis" in stderr
