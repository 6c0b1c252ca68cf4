"""Aligning a refit's state coordinates to the model it replaces (orthogonal Procrustes).

A TPSR is defined only up to an invertible change of its state coordinates: with ``T``
invertible, ``b -> T b``, ``B_ao -> T B_ao T^-1``, ``b_inf^T -> b_inf^T T^-1`` and
``b_* -> T b_*`` filter the same predictions, and every tracked state moves by ``T``. A
refit's SVD picks its coordinates afresh (a sign, a rotation among close singular values),
so the state a filter node publishes would jump at every swap and a planner learned on the
old states would read the new ones wrongly. :func:`align_model` chooses the rotation ``R``
that brings the refit's states over the steps both models tracked closest to the old
model's (``min ||S_new R - S_old||``, :func:`scipy.linalg.orthogonal_procrustes`) and applies
it: an orthogonal ``T = R^T`` changes neither the predictions nor the normaliser's guard
(``||b_inf||`` is kept). A refit whose rank differs from the old model's (the rank rule
kept more or fewer directions), or whose states are clipped to a box (its box lies along its
own axes), is left as it is, and its ``fit_info`` says why.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import scipy.linalg

from tpsr_ros.core.tpsr_model import TPSRModel

__all__ = ["ALIGN_STEPS", "align_model", "rotated"]

ALIGN_STEPS = 2000
"""The last steps of the training data whose states the rotation matches."""


def rotated(model: TPSRModel, rotation: np.ndarray) -> TPSRModel:
    """The same filter in the coordinates ``b' = R^T b`` (``rotation`` ``R``: orthogonal)."""
    r = model.state_dim
    if rotation.shape != (r, r) or not np.allclose(rotation.T @ rotation, np.eye(r), atol=1e-9):
        raise ValueError(f"a rotation of {r} state coordinates is an orthogonal {r}x{r} matrix")
    big_b = np.einsum("ki,aoij,jl->aokl", rotation.T, model.B, rotation, optimize=True)
    return replace(model, b_star=rotation.T @ model.b_star, b_inf=rotation.T @ model.b_inf,
                   B=big_b)  # fmt: skip


def align_model(
    model: TPSRModel, states: np.ndarray, reference: np.ndarray
) -> tuple[TPSRModel, np.ndarray | None, dict[str, Any]]:
    """``model`` rotated so that its ``states`` ``(t, r)`` come closest to ``reference``
    ``(t, r_ref)`` (the replaced model's states over the same steps); returns the model, the
    rotation ``R`` (a state ``s`` becomes ``s @ R``; None: left as it was) and a record of
    what was done, for ``fit_info``."""
    r, r_ref = model.state_dim, reference.shape[1]
    if model.state_box is not None:
        return model, None, {"skipped": "the states are clipped to a box along their axes"}
    if r != r_ref:
        return model, None, {"skipped": f"rank {r}, the replaced model's {r_ref}"}
    target = reference
    rotation, _ = scipy.linalg.orthogonal_procrustes(states, target)
    scale = float(np.linalg.norm(target)) or 1.0
    record = {
        "steps": int(states.shape[0]),
        "distance_before": round(float(np.linalg.norm(states - target)) / scale, 6),
        "distance_after": round(float(np.linalg.norm(states @ rotation - target)) / scale, 6),
    }
    return rotated(model, rotation), rotation, record
