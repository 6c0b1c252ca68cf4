"""learner.plots.neighbour_position_error: how precisely states locate the robot; and
loop_position_error: how precisely the states a policy acted on locate it among a reference
run's."""

from __future__ import annotations

import numpy as np
import pytest

from learner.plots import affine_r2, loop_position_error, neighbour_position_error
from tpsr_ros.core.errors import DataError


def _walk(steps: int = 8000, seed: int = 0) -> np.ndarray:
    """Positions of a reflected random walk in a 45 m square room."""
    rng = np.random.default_rng(seed)
    position = np.cumsum(rng.normal(0.0, 2.0, size=(steps, 2)), axis=0) + 22.5
    position = np.mod(position, 90.0)
    return np.where(position > 45.0, 90.0 - position, position)


def test_a_nonlinear_state_locates_as_well_as_the_position_itself():
    positions = _walk()
    bent = np.column_stack([np.exp(positions[:, 0] / 8.0), positions[:, 1] ** 3])
    assert affine_r2(bent, positions).min() < 0.85  # the affine fit misses it
    exact = neighbour_position_error(positions, positions)
    assert exact < 1.0
    assert neighbour_position_error(bent, positions) < 1.5 * exact + 0.2


def test_blind_to_invertible_linear_maps_of_the_states():
    positions = _walk(seed=1)
    rng = np.random.default_rng(2)
    states = np.column_stack([positions, np.sin(positions[:, 0] / 5.0)])
    mixed = states @ rng.normal(size=(3, 3)) * np.array([1e-3, 1.0, 1e4]) + 7.0
    assert neighbour_position_error(mixed, positions) == pytest.approx(
        neighbour_position_error(states, positions), rel=1e-6
    )


def test_a_state_that_has_lost_a_coordinate_locates_badly():
    positions = _walk(seed=3)
    noise = np.random.default_rng(4).normal(size=(len(positions), 1))
    only_x = np.column_stack([positions[:, :1], noise])  # y is gone: aliasing
    # about the median distance between two random places of one column: ~ 45 / 4 m
    assert neighbour_position_error(only_x, positions) > 8.0
    assert neighbour_position_error(positions, positions) < 1.0


def test_bad_input_is_refused():
    positions = _walk(steps=100)
    with pytest.raises(DataError, match="need 20 states"):
        neighbour_position_error(positions[:15], positions[:15])
    with pytest.raises(DataError, match="need 20 states"):
        neighbour_position_error(positions, positions[:50])
    broken = positions.copy()
    broken[3, 0] = np.nan
    with pytest.raises(DataError, match="non-finite"):
        neighbour_position_error(broken, positions)
    with pytest.raises(DataError, match="do not vary"):
        neighbour_position_error(np.ones((100, 2)), positions)


def test_the_heading_r2_pools_its_unit_vector_and_is_nan_without_one():
    from learner.experiment import _pose_r2

    positions = _walk(seed=5)
    heading = np.random.default_rng(6).uniform(-np.pi, np.pi, len(positions))
    poses = np.column_stack([positions, np.cos(heading), np.sin(heading)])
    knows_cos = np.column_stack([positions, np.cos(heading)])  # sin is lost
    r2 = _pose_r2(knows_cos, poses)
    assert r2[:2] == pytest.approx([1.0, 1.0])
    # cos explained, sin not at all: their pooled R² is cos's share of their variance
    cos_var, sin_var = np.var(poses[:, 2]), np.var(poses[:, 3])
    assert r2[2] == pytest.approx(cos_var / (cos_var + sin_var), abs=0.01)
    assert _pose_r2(poses, poses)[2] == pytest.approx(1.0)
    assert np.isnan(_pose_r2(positions, positions)[2])


def test_loop_states_that_follow_the_robot_locate_it_and_states_that_drift_do_not():
    """Ground truth: the reference states are the positions (bent, linearly mixed); loop
    states made the same way from other positions locate them as the reference does its
    own, and loop states stuck at the room's middle while the robot stands in a corner
    are off by the corner's distance."""
    reference_positions = _walk(seed=5)
    mix = np.array([[2.0, 0.3], [-0.5, 1.0]])

    def state(p: np.ndarray) -> np.ndarray:
        return np.column_stack([np.exp(p[:, 0] / 8.0), p[:, 1]]) @ mix + 3.0

    reference = state(reference_positions)
    loop_positions = _walk(steps=500, seed=6)
    followed = loop_position_error(reference, reference_positions, state(loop_positions),
                                   loop_positions)  # fmt: skip
    assert followed < 1.5 * neighbour_position_error(reference, reference_positions) + 0.2
    corner = np.full((50, 2), 44.0)
    middle = state(np.full((50, 2), 22.5))
    lost = loop_position_error(reference, reference_positions, middle, corner)
    assert lost == pytest.approx(np.hypot(21.5, 21.5), abs=1.5)


def test_loop_position_error_refuses_bad_input():
    positions = _walk(steps=100)
    with pytest.raises(DataError, match="states of their size"):
        loop_position_error(positions, positions, positions[:, :1], positions)
    with pytest.raises(DataError, match="with a position each"):
        loop_position_error(positions, positions, positions, positions[:10])
    with pytest.raises(DataError, match="non-finite"):
        loop_position_error(positions, positions, np.full((3, 2), np.nan), positions[:3])
