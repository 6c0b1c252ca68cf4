"""A refit's state coordinates rotated to the replaced model's: the same filter, closer states."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from test_fit_basis import _trajectory

from tpsr_ros.core.alignment import align_model, rotated
from tpsr_ros.core.learn import fit
from tpsr_ros.core.presets import PRESETS
from tpsr_ros.core.refit import fit_trajectory

LIVE = PRESETS["best"].tpsr_config()
"""The learner node's preset, whose refits are aligned (spectral: no refinement)."""


@pytest.fixture(scope="module")
def model():
    return fit(_trajectory(3000), LIVE)


def _rotation(r: int, seed: int) -> np.ndarray:
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(r, r)))
    return q


def test_a_rotated_model_is_the_same_filter_in_rotated_coordinates(model):
    data = _trajectory(800, seed=7)
    rotation = _rotation(model.state_dim, 1)
    turned = rotated(model, rotation)
    before = model.track(data.actions, data.observations)
    after = turned.track(data.actions, data.observations)
    np.testing.assert_allclose(after.states, before.states @ rotation, atol=1e-9)
    np.testing.assert_allclose(after.normalizers, before.normalizers, rtol=1e-10)
    np.testing.assert_array_equal(after.recovered, before.recovered)
    with pytest.raises(ValueError, match="orthogonal"):
        rotated(model, 2 * rotation)


def test_aligning_a_rotated_copy_to_the_original_undoes_the_rotation(model):
    data = _trajectory(800, seed=8)
    reference = model.track(data.actions, data.observations).states
    turned = rotated(model, _rotation(model.state_dim, 2))
    states = turned.track(data.actions, data.observations).states
    aligned, rotation, record = align_model(turned, states, reference)
    np.testing.assert_allclose(states @ rotation, reference, atol=1e-8)
    for name in ("b_star", "b_inf", "B"):
        np.testing.assert_allclose(getattr(aligned, name), getattr(model, name), atol=1e-10)
    assert record["distance_before"] > 0.1 and record["distance_after"] < 1e-8


def test_a_model_of_another_rank_or_with_a_state_box_is_left_as_it_is(model):
    data = _trajectory(500, seed=9)
    states = model.track(data.actions, data.observations).states
    same, none, record = align_model(model, states, states[:, :-1])
    assert none is None and same is model and "rank" in record["skipped"]
    clipped = replace(model.config, state_clip_quantile=0.01)
    boxed = replace(model, config=clipped, state_box=np.stack([states.min(0), states.max(0)]))
    same, none, record = align_model(boxed, states, states)
    assert none is None and same is boxed and "box" in record["skipped"]


@pytest.mark.slow
def test_a_refit_aligned_to_the_model_it_replaces_tracks_closer_to_it_and_predicts_the_same():
    model = fit(_trajectory(6000), LIVE)  # enough steps for the rank its refit keeps
    longer = _trajectory(9000, seed=3)
    plain = fit_trajectory(longer, model.basis.config, basis=model.basis)
    aligned = fit_trajectory(longer, model.basis.config, basis=model.basis, align_to=model)
    record = aligned.model.fit_info["aligned"]
    assert record["distance_after"] < record["distance_before"]
    np.testing.assert_allclose(aligned.tracked.normalizers, plain.tracked.normalizers, rtol=1e-9)
    reference = model.track(longer.actions, longer.observations).states
    assert np.linalg.norm(aligned.tracked.states - reference) < np.linalg.norm(
        plain.tracked.states - reference
    )
    again = aligned.model.track(longer.actions, longer.observations).states  # the model's own
    np.testing.assert_allclose(aligned.tracked.states, again, atol=1e-9)
