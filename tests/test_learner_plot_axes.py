"""``learner plot``'s axes follow the bulk of the states: a few outliers are drawn on the
edge and counted instead of squashing every other state into a dot."""

from __future__ import annotations

import numpy as np

from learner.plots import AXIS_QUANTILE, robust_limits


def test_axes_cover_the_bulk_and_leave_outliers_out() -> None:
    rng = np.random.default_rng(0)
    values = np.concatenate([rng.normal(0, 1, 10_000), [1e6, -1e6, 5e5]])
    low, high = robust_limits(values)
    inside = np.mean((values >= low) & (values <= high))
    assert -5 < low < -2 and 2 < high < 5  # the normal bulk, not the outliers' range
    assert inside >= 1 - 2 * AXIS_QUANTILE
    assert robust_limits(np.full(5, 3.0)) == (2.85, 3.15)  # constant: padded around it
    assert robust_limits(np.array([np.nan, np.inf])) == (-1.0, 1.0)
