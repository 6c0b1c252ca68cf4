"""How many kernel centres an observation's weights spread over, and a width that spreads them.

The filter weighs the operators of the observation kernel's centres by an observation's
normalised RBF weights ``phi(o)`` (eq. 3.9). Their *effective number*, ``1 / sum_i phi_i^2``,
is 1 when one centre takes all the weight and ``l_O`` when all weigh alike. The width
``sigma^O`` is in whitened units, where squared distances grow with the whitened dimension
``d^O``: at the guide's ``sigma^O = 1`` a camera whitened to 10 or 17 dimensions spreads an
image over 6 to 12 centres, but one whitened to 50 (the ``drive`` and ``distractors`` rooms
at 95 % of the variance) over 1.0 to 1.2. Each step then applies the operator of a single
centre, estimated from the few dozen training steps nearest to it.

:func:`widened_sigma` is the rule ``obs_effective_centres`` applies: the smallest width, at
least the one given, at which the median observation's weights spread over a target number
of centres. It only widens: where images already spread over more centres, the width stays
as given, bit for bit.
"""

from __future__ import annotations

import math

import numpy as np

from tpsr_ros.core.errors import DataError
from tpsr_ros.core.features import rbf_features

__all__ = ["SAMPLE_ROWS", "effective_centres", "median_effective_centres", "widened_sigma"]

SAMPLE_ROWS = 2000
"""Observations (evenly spaced over the rows given) whose median the rule measures."""

_DIGITS = 3
"""Significant digits of a widened width (rounded up, so the target still holds)."""


def effective_centres(weights: np.ndarray) -> np.ndarray:
    """``1 / sum_i w_i^2`` of each row of normalised weights ``(t, l)``: from 1 (one centre)
    to ``l`` (all alike)."""
    w = np.asarray(weights, dtype=np.float64)
    return 1.0 / np.einsum("ti,ti->t", w, w)


def median_effective_centres(rows: np.ndarray, centres: np.ndarray, sigma: float) -> float:
    """The median effective number of centres of whitened observations ``rows`` ``(t, d)``
    under the kernel ``(centres, sigma)`` (of at most :data:`SAMPLE_ROWS` of them), with the
    filter's own weights (:func:`~tpsr_ros.core.features.rbf_features`)."""
    sample = np.asarray(rows, dtype=np.float64)[:: max(1, len(rows) // SAMPLE_ROWS)]
    weights = rbf_features(sample, centres, float(sigma), normalize=True)
    return float(np.median(effective_centres(weights)))


def widened_sigma(
    rows: np.ndarray, centres: np.ndarray, sigma: float, target: float
) -> tuple[float, float]:
    """The smallest width ``>= sigma`` at which the median observation of ``rows`` spreads
    over at least ``target`` effective centres, to 3 significant digits (rounded up), and
    that median: ``(width, median)``. ``sigma`` itself where it already does."""
    n_centres = np.asarray(centres).shape[0]
    if not 1 <= target < n_centres:
        raise DataError(
            f"observations cannot spread over {target:g} effective centres of {n_centres}: "
            "the target must be at least 1 and below the number of observation centres "
            "(lower obs_effective_centres or raise obs_centers)"
        )

    def spread(width: float) -> float:
        return median_effective_centres(rows, centres, width)

    low = float(sigma)
    reached = spread(low)
    if reached >= target:
        return low, reached
    high = 2.0 * low
    while spread(high) < target:  # the spread tends to n_centres > target
        low, high = high, 2.0 * high
    while high / low > 1.0 + 10.0 ** -(_DIGITS + 1):  # bisect in the logarithm
        middle = math.sqrt(low * high)
        low, high = (middle, high) if spread(middle) < target else (low, middle)
    scale = 10.0 ** (math.floor(math.log10(high)) - _DIGITS + 1)
    width = math.ceil(high / scale - 1e-9) * scale
    width = float(f"{width:.{_DIGITS}g}")  # the decimal the config shows
    return width, spread(width)
