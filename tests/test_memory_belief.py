"""The exact-belief diagnostic of the memory section (benchmarks/memory_belief.py)."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.memory_belief import _moved


@pytest.mark.parametrize("axis", [0, 1])
@pytest.mark.parametrize("cells", [3, -2])
def test_a_moved_belief_keeps_its_mass_and_stops_at_the_walls(axis: int, cells: int) -> None:
    belief = np.random.default_rng(0).random((6, 5))
    belief /= belief.sum()
    moved = _moved(belief, cells, axis)
    assert moved.sum() == pytest.approx(1.0)
    along = np.moveaxis(belief, axis, 0)
    got = np.moveaxis(moved, axis, 0)
    n = along.shape[0]
    for row in range(n):  # a row lands ``cells`` on, or at the wall it would cross; with
        # the mass kept, every row that nothing lands on is empty
        target = min(max(row + cells, 0), n - 1)
        inflow = sum(along[r] for r in range(n) if min(max(r + cells, 0), n - 1) == target)
        np.testing.assert_allclose(got[target], inflow, rtol=1e-12)
