"""Does the previous image tell the future better than the current one alone?

A robot whose camera shows where it is (one image, one place) needs no memory; one whose
image looks alike in several places does, and only there does a refinement that starts
from a carried state (:mod:`tpsr_ros.core.refine`, ``refine_carry``) pay: the carry costs a
step's lag where the image alone suffices (docs/results.md, "A predictive state: the carry
with two images of history").

:func:`history_gain` measures it without reward or ground truth, on the training steps: two
ridge regressions from the current image's top principal components and action (one) and
from those and the previous step's (two) to the top components of the next ``horizon``
images, fitted on the first three quarters of the steps and scored on the last quarter (the
fraction of the futures' variance explained). The gain is the second's score minus the
first's: where the current image suffices the previous one only adds variance (a gain at or
below 0), where places look alike it adds what the current image cannot say. On the ten
training runs (24000 steps) of each simulated room on the results page's fresh seeds the
gain lay between -0.0009 and -0.0003 where one image tells the place (``full``) and between
0.0006 and 0.0037 where it does not (``partial``, ``distractors``, ``partial-strip``).
"""

from __future__ import annotations

import numpy as np

from tpsr_ros.core.errors import DataError

__all__ = ["COMPONENTS", "HORIZON", "RIDGE", "TARGETS", "history_gain"]

COMPONENTS = 20
"""Principal components of an image the regressions read."""

TARGETS = 10
"""Principal components of each future image they predict."""

HORIZON = 10
"""Future images predicted."""

RIDGE = 1e-3
"""Ridge of both regressions."""

_FIT_FRACTION = 0.75
_PCA_STRIDE = 3  # the components come from every third fitted step: a third of the cost


def history_gain(
    actions: np.ndarray,
    observations: np.ndarray,
    n_actions: int,
    bounds: list[tuple[int, int]] | None = None,
) -> float:
    """Held-out variance of the next images explained from the last two steps minus that
    from the last one (module docstring): ``actions (T,)``, ``observations (T, k)``,
    ``bounds`` the ``[start, stop)`` rows of gap-free segments (default: one)."""
    obs = np.asarray(observations, dtype=np.float64)
    steps = obs.shape[0]
    split = int(_FIT_FRACTION * steps)
    rows = np.concatenate([
        np.arange(a + 1, b - HORIZON, dtype=np.int64) for a, b in (bounds or [(0, steps)])
    ])  # fmt: skip
    is_train, is_held = rows + HORIZON < split, rows >= split
    if is_train.sum() < 10 * (2 * COMPONENTS + 2 * n_actions) or is_held.sum() < 10:
        raise DataError(
            f"{steps} steps are too few to tell whether the previous image predicts the "
            "future (refine_carry_rule aliased)"
        )
    mean = obs[:split].mean(axis=0)
    _, _, vt = np.linalg.svd(obs[:split:_PCA_STRIDE] - mean, full_matrices=False)
    z = (obs - mean) @ vt[:COMPONENTS].T
    onehot = np.eye(n_actions)[np.asarray(actions)]
    futures = np.concatenate([z[rows + h, :TARGETS] for h in range(1, HORIZON + 1)], axis=1)
    one = np.concatenate([z[rows], onehot[rows], np.ones((rows.size, 1))], axis=1)
    two = np.concatenate([one, z[rows - 1], onehot[rows - 1]], axis=1)
    scores = []
    for inputs in (one, two):
        x, y = inputs[is_train], futures[is_train]
        weights = np.linalg.solve(x.T @ x + RIDGE * np.eye(x.shape[1]), x.T @ y)
        residual = futures[is_held] - inputs[is_held] @ weights
        spread = futures[is_held] - y.mean(axis=0)
        scores.append(1.0 - float((residual**2).sum()) / float((spread**2).sum()))
    return scores[1] - scores[0]
