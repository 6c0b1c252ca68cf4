"""The observation kernel's effective number of centres, and the width that spreads it."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from tpsr_ros import TPSRConfig, fit
from tpsr_ros.core.errors import ConfigError, DataError
from tpsr_ros.core.features import rbf_features
from tpsr_ros.core.filtering import observation_weights
from tpsr_ros.core.kernel_width import (
    effective_centres,
    median_effective_centres,
    widened_sigma,
)
from tpsr_ros.core.presets import get_preset


def test_effective_centres_count_how_many_centres_share_the_weight() -> None:
    weights = np.array([[1.0, 0, 0, 0], [0.5, 0.5, 0, 0], [0.25] * 4])
    assert effective_centres(weights) == pytest.approx([1.0, 2.0, 4.0])


def _cloud(dims: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rows = np.random.default_rng(seed).normal(size=(3000, dims))
    return rows, rows[::30].copy()  # 100 centres among the rows


def test_the_widened_width_is_the_smallest_that_reaches_the_target() -> None:
    rows, centres = _cloud(40)  # 40 dimensions: at width 1 one or two centres take it all
    assert median_effective_centres(rows, centres, 1.0) < 2.0
    width, reached = widened_sigma(rows, centres, 1.0, 5.0)
    assert width > 1.0 and width == float(f"{width:.3g}")  # three significant digits
    assert reached == median_effective_centres(rows, centres, width) >= 5.0
    assert median_effective_centres(rows, centres, 0.99 * width) < 5.0  # tight to rounding
    weights = rbf_features(rows[::2], centres, width, normalize=True)
    assert np.median(effective_centres(weights)) == pytest.approx(5.0, rel=0.05)


def test_a_kernel_that_already_spreads_keeps_its_width_exactly() -> None:
    rows, centres = _cloud(2)  # 2 dimensions: width 1 spreads over dozens of centres
    spread = median_effective_centres(rows, centres, 1.0)
    assert spread > 10
    assert widened_sigma(rows, centres, 1.0, 2.0) == (1.0, spread)


@pytest.mark.parametrize("target", [0.5, 100.0, 250.0])
def test_a_target_the_centres_cannot_reach_is_refused(target: float) -> None:
    rows, centres = _cloud(5)
    with pytest.raises(DataError, match="below the number of observation centres"):
        widened_sigma(rows, centres, 1.0, target)


@pytest.mark.parametrize("value", [-1.0, 0.5, float("nan"), float("inf")])
def test_the_config_refuses_a_target_below_one(value: float) -> None:
    with pytest.raises(ConfigError, match="obs_effective_centres must be 0 or a number >= 1"):
        TPSRConfig(obs_effective_centres=value)


def test_a_fit_widens_its_kernel_and_its_filter_weighs_with_the_width_it_records() -> None:
    """Observations of 6 places in 30 noisy dimensions: whitened to 95 % of the variance, the
    kernel of width 1 gives each image to one or two centres; the rule widens it, and the filter's
    weights (from the model's own sigma_obs) spread as the fit measured."""
    rng = np.random.default_rng(1)
    actions = rng.integers(0, 2, size=1500)
    places = np.cumsum(actions) % 6
    observations = np.eye(6, 30)[places] + 0.3 * rng.normal(size=(1500, 30))
    plain = replace(get_preset("predictive").tpsr_config(), refine_epochs=0, obs_centers=200)
    before = fit(actions, observations, plain)
    assert before.config.sigma_obs == 1.0
    assert before.fit_info["obs_kernel"]["sigma"] == 1.0
    assert before.fit_info["obs_kernel"]["effective_centres"] < 2.0
    widened = fit(actions, observations, replace(plain, obs_effective_centres=4.0))
    kernel = widened.fit_info["obs_kernel"]
    assert kernel["sigma_given"] == 1.0 and kernel["sigma"] == widened.config.sigma_obs > 1.0
    assert kernel["effective_centres"] >= 4.0
    weights = observation_weights(widened, observations)
    assert np.median(effective_centres(weights)) == pytest.approx(4.0, rel=0.15)
    assert widened.config.obs_effective_centres == 4.0  # the target beside the width it gave


def test_only_the_turning_robot_of_the_default_preset_widens_its_kernel() -> None:
    """The rule was chosen in ``drive`` (docs/results.md, "the observation kernel's width");
    every other preset and robot keeps the width given, so their models are unchanged."""
    predictive = get_preset("predictive")
    assert predictive.tpsr_config(turning=True).obs_effective_centres == 2.0
    assert predictive.tpsr_config().obs_effective_centres == 0.0
    for name in ("best", "guide"):
        assert get_preset(name).tpsr_config(turning=True).obs_effective_centres == 0.0
