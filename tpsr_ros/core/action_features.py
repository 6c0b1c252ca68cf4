"""Action-aware history and test vectors: each step's action code joined to its observations.

The guide's histories and tests are observations only (section 3.1). In ``partial`` that
loses what a robot needs to remember: standing still at the north wall and arriving there
from the west or from the east give the same images, so every training sample of the
operator ``B_(stand still, wall)`` has the same history, the regression of eq. 3.3 sees one
history column only, and the learned operator contracts every other direction of the state
(measured: all 148 such samples of a 60000-step run share one history; the operator's
eigenvalues beyond the first are 20x smaller). The guide's chapter 5 suggests integrating
actions into the features; this module does it for the RBF kernel.

A history of ``m`` steps ``(a_1, o_1), ..., (a_m, o_m)`` (``a_j`` is the action that led to
``o_j``) becomes the whitened observations followed by ``weight * c(a_1), ..., weight *
c(a_m)``, where ``c`` are the action codes (commands; the simulator's 25 velocity pairs by
default) centred and scaled to unit root-mean-square per component over the actions. The
Gaussian kernel of the joined vector is the product of an observation kernel and an action
kernel, i.e. the Kronecker product of the two feature spaces, without forming it: the
feature dimension stays ``l^H``. Tests get the same treatment (their actions are the
exploration policy's, so the state becomes a prediction of observations *given* actions).
``weight = 0`` leaves the vectors untouched (the guide's algorithm).
"""

from __future__ import annotations

import numpy as np

from tpsr_ros.core.actions import ACTIONS, NUM_ACTIONS
from tpsr_ros.core.errors import ConfigError, DataError

__all__ = ["join_actions", "standardised_codes"]


def standardised_codes(codes: np.ndarray | None, n_actions: int) -> np.ndarray:
    """Action codes ``(n_actions, d)`` centred and scaled to unit RMS per component.

    ``codes=None`` means the simulator's 25 velocity pairs (refused for another action count).
    A component that is the same for every action carries nothing and is dropped.
    """
    if codes is None:
        if n_actions != NUM_ACTIONS:
            raise ConfigError(
                f"action-aware features need the command of each of the {n_actions} actions "
                f"(the default codes are the simulator's {NUM_ACTIONS} velocity pairs)"
            )
        codes = ACTIONS
    arr = np.asarray(codes, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[0] != n_actions or not np.isfinite(arr).all():
        raise DataError(
            f"action codes must be a finite ({n_actions}, d) array, got shape {arr.shape}"
        )
    centred = arr - arr.mean(axis=0)
    rms = np.sqrt(np.mean(centred**2, axis=0))
    keep = rms > 0
    if not keep.any():
        raise DataError("every action has the same code: action-aware features carry nothing")
    return np.ascontiguousarray(centred[:, keep] / rms[keep])


def join_actions(
    white: np.ndarray, actions: np.ndarray | None, codes: np.ndarray, weight: float, what: str
) -> np.ndarray:
    """``[white, weight * codes[actions]]``: whitened rows ``(E, d)`` with ``(E, m)`` actions.

    Returns ``white`` itself when ``weight`` is 0 (the guide's features, bit for bit).
    """
    if weight == 0:
        return white
    if actions is None:
        raise ConfigError(f"action-aware {what} features need the actions of the {what} steps")
    acts = np.asarray(actions)
    if acts.ndim != 2 or acts.shape[0] != white.shape[0] or acts.dtype.kind not in "iu":
        raise DataError(
            f"{what} actions must be ({white.shape[0]}, steps) integers, got {acts.dtype} "
            f"{acts.shape}"
        )
    if acts.size and (acts.min() < 0 or acts.max() >= codes.shape[0]):
        raise DataError(f"{what} action indices must lie in 0..{codes.shape[0] - 1}")
    joined = codes[acts].reshape(white.shape[0], -1)
    joined *= weight
    return np.concatenate([white, joined], axis=1)
