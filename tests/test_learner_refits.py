"""The learner node's refits continue their statistics, forget old steps when asked, fit a
new basis when due, and equal `learner fit --init-from --forgetting` on a recording of the
same steps."""

from __future__ import annotations

import numpy as np
import pytest
from cli_support import run_entry

from sim_node import SimConfig
from sim_node.generate import generate_bag
from tpsr_ros.core.errors import ConfigError
from tpsr_ros.core.presets import PRESETS
from tpsr_ros.core.refit import fit_trajectory
from tpsr_ros.core.sizing import Sizing
from tpsr_ros.io.model_io import open_model
from tpsr_ros.io.policy import load_policy
from tpsr_ros.io.trajectory import LiveSteps
from tpsr_ros.learner_node.refits import RefitRequest, new_basis_due, policy_horizon, refit

STEPS, FORGETTING = 1200, 0.995


@pytest.fixture(scope="module")
def bag(tmp_path_factory):
    path = tmp_path_factory.mktemp("refits") / "run"
    generate_bag(path, SimConfig(environment="full"), STEPS, seed=12)
    return path


@pytest.fixture(scope="module")
def versions(bag, tmp_path_factory):
    """Three versions of the run, at 600, 900 and 1200 steps, forgetting as the node does."""
    live, out = LiveSteps.of_bag(bag, "full"), tmp_path_factory.mktemp("out")
    first = refit(RefitRequest(live.chunk(600), 1, out, "best"))
    results = [first]
    for version, steps in ((2, 900), (3, STEPS)):
        results.append(refit(RefitRequest(
            live.chunk(steps), version, out, "best", basis_model=first.model,
            forgetting=FORGETTING, previous=results[-1].summed,
        )))  # fmt: skip
    return live, out, results


@pytest.mark.slow
def test_each_refit_sums_only_the_steps_since_the_last(versions):
    live, out, (first, second, third) = versions
    assert first.summed is None  # a first fit: two passes, no statistics
    assert (second.summed.steps, third.summed.steps) == (900, STEPS)
    # continued from the second's sums or summed anew from every step: the same model
    anew = refit(RefitRequest(
        live.chunk(STEPS), 4, out, "best", basis_model=first.model, forgetting=FORGETTING,
    ))  # fmt: skip
    continued, whole = open_model(third.model).model, open_model(anew.model).model
    for name, array in whole.to_arrays().items():
        np.testing.assert_allclose(continued.to_arrays()[name], array, rtol=0, atol=1e-9)


@pytest.mark.slow
def test_a_forgetting_refit_is_learner_fit_init_from_with_forgetting(
    bag, versions, tmp_path, capsys
):
    _, _, (first, _, third) = versions
    out = tmp_path / "offline.npz"
    args = ["fit", str(bag), "--init-from", str(first.model), "--forgetting", str(FORGETTING)]
    code, _, stderr = run_entry([*args, "-o", str(out)], capsys)
    assert code == 0, stderr
    offline, live = open_model(out).model, open_model(third.model).model
    assert offline.fit_info["forgetting"] == live.fit_info["forgetting"] == FORGETTING
    for name, array in offline.to_arrays().items():
        np.testing.assert_allclose(live.to_arrays()[name], array, rtol=0, atol=1e-9)
    # forgetting moved the model: the same steps without it give another
    code, _, stderr = run_entry(
        ["fit", str(bag), "--init-from", str(first.model), "-o", str(tmp_path / "kept.npz")], capsys
    )
    assert code == 0, stderr
    kept = open_model(tmp_path / "kept.npz").model
    assert np.abs(kept.B - live.B).max() > 1e-3 * np.abs(kept.B).max()


@pytest.mark.slow
def test_the_policy_learns_from_the_steps_forgetting_keeps(versions):
    _, _, (first, _, third) = versions
    assert first.policy_steps == 600  # no forgetting in a first fit
    assert policy_horizon(STEPS, FORGETTING) == third.policy_steps == 600  # 3 / (1 - 0.995)
    assert policy_horizon(STEPS, 1.0) == STEPS
    assert load_policy(third.policy).model_fingerprint == third.fingerprint


def test_forgetting_is_refused_out_of_range_and_without_a_model_to_refit(bag, capsys):
    for value in ("0", "1.5"):
        code, _, stderr = run_entry(
            ["fit", str(bag), "--init-from", str(bag), "--forgetting", value, "-o", "x.npz"],
            capsys,
        )  # fmt: skip
        assert code != 0 and "--forgetting must lie in (0, 1]" in stderr
    code, _, stderr = run_entry(["fit", str(bag), "--forgetting", "0.99", "-o", "x.npz"], capsys)
    assert code != 0 and "give the model to refit with --init-from" in stderr
    first_steps = LiveSteps.of_bag(bag, "full").chunk(600).trajectory()
    with pytest.raises(ConfigError, match="forgetting and continued statistics refit on the basis"):
        fit_trajectory(first_steps, PRESETS["best"].tpsr_config(), forgetting=0.9)


def test_a_new_basis_is_due_so_many_steps_after_the_one_in_use():
    assert not new_basis_due(5000, 1000, 0)  # 0: never
    assert not new_basis_due(1000, None, 2000)  # no basis yet: the first fit makes one
    assert not new_basis_due(2999, 1000, 2000)
    assert new_basis_due(3000, 1000, 2000)


@pytest.mark.slow
def test_a_new_basis_fits_the_steps_the_policy_plans_on_and_the_next_refit_keeps_it(
    versions, tmp_path
):
    live, _, (_, _, third) = versions
    horizon = policy_horizon(STEPS, FORGETTING)
    new = refit(RefitRequest(
        live.chunk(STEPS), 5, tmp_path, "best", basis_model=third.model,
        forgetting=FORGETTING, previous=third.summed, new_basis=True,
    ))  # fmt: skip
    assert new.basis_steps == new.policy_steps == horizon < STEPS and new.summed is None
    # learner fit of the last `horizon` steps, in the coordinates of the model it replaces
    recent = live.chunk(STEPS).trajectory().rows(STEPS - horizon, STEPS)
    expected = fit_trajectory(
        recent, PRESETS["best"].tpsr_config(), sizing=Sizing(),
        align_to=open_model(third.model).model,
    ).model  # fmt: skip
    model = open_model(new.model).model
    for name, array in expected.to_arrays().items():
        np.testing.assert_allclose(model.to_arrays()[name], array, rtol=0, atol=1e-9)
    # the next refit keeps the new basis and sums every step on it anew
    after = refit(RefitRequest(
        live.chunk(STEPS), 6, tmp_path, "best", basis_model=new.model, forgetting=FORGETTING,
    ))  # fmt: skip
    assert after.basis_steps == 0 and after.summed.steps == STEPS
    np.testing.assert_array_equal(
        open_model(after.model).model.basis.obs.components_, model.basis.obs.components_
    )


def test_a_new_basis_needs_a_model_to_replace(bag, tmp_path):
    live = LiveSteps.of_bag(bag, "full")
    with pytest.raises(ConfigError, match="a new basis replaces a model"):
        refit(RefitRequest(live.chunk(600), 1, tmp_path, "best", new_basis=True))
