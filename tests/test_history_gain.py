"""Whether the previous image helps to predict the future (tpsr_ros.core.history_gain), and
the carry the refinement starts from where it does and where it does not."""

from __future__ import annotations

from dataclasses import replace

import pytest
from test_refine import CONFIG, ring, visible_ring

from tpsr_ros.core.errors import ConfigError, DataError
from tpsr_ros.core.history_gain import history_gain
from tpsr_ros.core.learn import fit_tpsr_trajectory
from tpsr_ros.core.refine import chosen_carry
from tpsr_ros.core.tpsr import TPSRConfig


def test_the_previous_image_adds_nothing_where_each_place_looks_its_own() -> None:
    """Ground truth: on a ring of 6 cells each seen as itself, the current image is the place."""
    for seed in (0, 1):
        data = visible_ring(6000, seed=seed)
        assert history_gain(data.actions, data.observations, 2) <= 0.0


def test_the_previous_image_adds_where_two_places_look_alike() -> None:
    """Ground truth: on the 4-cell ring cells 0 and 2 look alike and only the past tells
    which one the robot is in, so which image comes next."""
    for seed in (1, 2):
        data = ring(6000, seed=seed)
        assert history_gain(data.actions, data.observations, 2) > 0.003  # visible: <= 0


def test_segments_keep_each_row_inside_its_own() -> None:
    """Rows whose previous step or futures lie in another segment are not used: a gap
    between two runs of a visible ring changes nothing at its edges (gain still <= 0), and
    the bounds given are honoured (fewer rows: a different value)."""
    data = visible_ring(6000, seed=0)
    whole = history_gain(data.actions, data.observations, 2)
    cut = history_gain(data.actions, data.observations, 2, [(0, 3000), (3000, 6000)])
    assert cut <= 0.0 and cut != whole


def test_too_few_steps_are_refused_and_keep_the_carry() -> None:
    """A short run cannot tell: the gain is refused, and the aliased rule keeps the carry
    it was given (the fit does not fail for it)."""
    data = ring(300, seed=0)
    with pytest.raises(DataError, match="too few"):
        history_gain(data.actions, data.observations, 2)
    cfg = replace(CONFIG, refine_epochs=2, refine_carry=0.3, refine_carry_rule="aliased")
    model = fit_tpsr_trajectory(data, cfg)
    assert model.fit_info["refinement"]["carry"] == 0.3
    assert "history_gain" not in model.fit_info["refinement"]


def test_the_aliased_rule_carries_only_where_the_previous_image_helps() -> None:
    cfg = replace(CONFIG, refine_epochs=0, refine_carry=0.3, refine_carry_rule="aliased")
    for data, carried in ((ring(6000, seed=1), True), (visible_ring(6000, seed=0), False)):
        model = fit_tpsr_trajectory(data, cfg)
        carry, gain = chosen_carry(model, data.actions, data.observations)
        assert gain is not None and (gain > 0.0) == carried
        assert carry == (0.3 if carried else 0.0)
        always = replace(model, config=replace(cfg, refine_carry_rule="always"))
        assert chosen_carry(always, data.actions, data.observations) == (0.3, None)


def test_a_refined_model_records_the_carry_it_started_from() -> None:
    data = visible_ring(6000, seed=0)
    cfg = replace(CONFIG, refine_epochs=3, refine_carry=0.3, refine_carry_rule="aliased")
    info = fit_tpsr_trajectory(data, cfg).fit_info["refinement"]
    assert info["carry"] == 0.0 and info["history_gain"] <= 0.0
    plain = fit_tpsr_trajectory(data, replace(cfg, refine_carry=0.0))
    assert "history_gain" not in plain.fit_info["refinement"]  # nothing to choose


def test_an_unknown_rule_is_refused() -> None:
    with pytest.raises(ConfigError, match="refine_carry_rule"):
        TPSRConfig(refine_carry_rule="sometimes")  # type: ignore[arg-type]
