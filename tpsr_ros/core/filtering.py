"""TPSR state tracking: guide Algorithm 4 (section 3.3), eqs. 3.8 and 3.9.

One update incorporates the pair ``(a, o)``:

1. whiten the observation with the model's ``mean^O`` and ``W^O``,
2. normalised RBF features ``phi(o)`` over the observation kernel centres,
3. ``B_ao = sum_o' phi_o'(o) B_ao'`` (eq. 3.9),
4. ``b' = B_ao b / (b_inf^T B_ao b)`` (eq. 3.8).

:func:`update` is stateless (model and state in, state and diagnostics out), so the offline
tracker and the filter node share it. :func:`track` does the same for a whole trajectory:
steps 1-3 for all observations at once (one call per stage, one per action group), then a
loop over the tiny ``r x r`` products of step 4. All per-observation products are computed
row by row inside single stacked matmuls, so every step is bitwise what :func:`update`
computes: batch tracking *equals* a loop of updates.

The normaliser guard
--------------------
``z = b_inf^T B_ao b`` is the model's (unnormalised) probability of the observation given the
state. A learned TPSR is not constrained to keep it positive; when it is not finite, or
``z <= NORMALIZER_RTOL * ||b_inf|| * ||B_ao b||`` (zero, negative, or so small relative to
the largest value the two vectors allow that dividing would blow the state up by more than
``1 / NORMALIZER_RTOL``), or ``||B_ao b||`` itself overflows, the state has left the region
where the model means anything.
On the full environment the cosine ``z / (||b_inf|| ||B_ao b||)`` of valid steps was above
0.2 and the few failures were negative, so any threshold between ``1e-6`` and ``0.1``
behaves the same; ``1e-3`` caps the blow-up of a step at a thousandfold.
The filter then *restarts*: it treats the step as the first one after a reset, i.e. applies
the same update to ``b_*`` (the guide's base case); if even that cannot be normalised the
state becomes ``b_*``. ``UpdateInfo.recovered`` is set either way.

Why restart rather than keep the previous state: the previous state is what produced the
degenerate prediction, so keeping it would ignore the new observation and fail again on the
next step; restarting from the stationary state ``b_*`` and applying the current pair
re-localises at once when observations are informative, and otherwise forgets a past that
the guide found TPSRs remember for only a few steps anyway (section 4.4).

The state box (optional)
------------------------
A model fitted with ``state_clip_quantile > 0`` carries ``state_box`` (``(2, r)``: low and
high bounds per state coordinate, quantiles of the states of its training episodes; see
:mod:`tpsr_ros.core.state_box`). Every new state is then clipped into that box. Measured on
``partial`` (rank 10, action-aware histories and tests of 4 and 8): every restart had a
*negative* normaliser (cosine -0.86 to -0.002), and half of the states just before a restart
lay outside the 1-99 % box of the valid states (8 % of all states), i.e. the filter drifts
out of the region where its operators were fitted before it fails. The update is invariant
to the scale of the state, so clipping changes the direction of the next update only where
the state had left the box. Without ``state_box`` (the default) nothing is clipped.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from tpsr_ros.core.errors import DataError
from tpsr_ros.core.features import rbf_features, squared_norms
from tpsr_ros.core.state_model import Track, UpdateInfo, check_actions, check_observations

__all__ = [
    "NORMALIZER_RTOL",
    "Derived",
    "FilterParameters",
    "derive",
    "observation_weights",
    "track",
    "update",
    "update_matrices",
]

NORMALIZER_RTOL = 1e-3
"""Relative threshold of the normaliser guard (see the module docstring)."""


class _KernelWidth(Protocol):
    @property
    def sigma_obs(self) -> float: ...


class FilterParameters(Protocol):
    """What Algorithm 4 reads of a TPSR (guide table 3.4), e.g. a
    :class:`tpsr_ros.core.tpsr.TPSRModel`; this module does not depend on how it was fitted.
    """

    @property
    def config(self) -> _KernelWidth: ...
    @property
    def obs_mean(self) -> np.ndarray: ...
    @property
    def obs_whitening(self) -> np.ndarray: ...
    @property
    def obs_centers(self) -> np.ndarray: ...
    @property
    def b_star(self) -> np.ndarray: ...
    @property
    def b_inf(self) -> np.ndarray: ...
    @property
    def B(self) -> np.ndarray: ...
    @property
    def state_box(self) -> np.ndarray | None: ...
    @property
    def state_dim(self) -> int: ...
    @property
    def n_actions(self) -> int: ...
    @property
    def obs_size(self) -> int: ...
    @property
    def derived(self) -> Derived: ...
    def initial_state(self) -> np.ndarray: ...


@dataclass(frozen=True, eq=False)
class Derived:
    """What every update reads that follows from a model's parameters: computed once per
    model (:func:`derive`; a model keeps it as ``derived``) instead of at every step.

    Attributes:
        centers_sq: ``(l_O,)`` squared norms of the observation kernel centres.
        b_inf_norm: ``||b_inf||``, the scale of the normaliser guard.
        operator_of: for every action, the first action whose operators ``B_a`` are bit
            for bit its own: pooled operators (``action_pooling`` 1) are stored once per
            action, and an update reading always the same copy finds it in the cache.

    """

    centers_sq: np.ndarray
    b_inf_norm: float
    operator_of: tuple[int, ...]


def derive(model: FilterParameters) -> Derived:
    """The :class:`Derived` arrays of ``model``, computed as every update computed them."""
    return Derived(
        centers_sq=squared_norms(model.obs_centers),
        b_inf_norm=float(np.linalg.norm(model.b_inf)),
        operator_of=_first_equal(model.B),
    )


def _first_equal(operators: np.ndarray) -> tuple[int, ...]:
    """For every action, the first action whose operators equal its own bit for bit."""
    firsts: list[int] = []
    distinct: list[int] = []
    for a in range(len(operators)):
        first = next((b for b in distinct if np.array_equal(operators[b], operators[a])), a)
        if first == a:
            distinct.append(a)
        firsts.append(first)
    return tuple(firsts)


def _operators(model: FilterParameters) -> np.ndarray:
    """``B`` as ``(n_actions, l_O, r * r)`` (a view): each ``B_ao'`` flattened."""
    r = model.state_dim
    return model.B.reshape(model.n_actions, -1, r * r)


def observation_weights(model: FilterParameters, observations: np.ndarray) -> np.ndarray:
    """Compute steps 1-2: normalised kernel weights ``(T, l_O)`` of observations ``(T, k)``."""
    obs = check_observations(observations, model.obs_size)
    white = np.matmul((obs - model.obs_mean)[:, None, :], model.obs_whitening)[:, 0, :]
    return rbf_features(
        white,
        model.obs_centers,
        model.config.sigma_obs,
        normalize=True,
        rowwise=True,
        centers_sq=model.derived.centers_sq,
    )


def update_matrices(
    model: FilterParameters, actions: np.ndarray, weights: np.ndarray
) -> np.ndarray:
    """Compute step 3 (eq. 3.9): ``B_{a_s o_s}`` of all steps ``(T, r, r)``, a matmul per action."""
    r = model.state_dim
    n_steps = weights.shape[0]
    out = np.empty((n_steps, r * r))
    flat = _operators(model)
    for a in np.unique(actions):
        rows = np.flatnonzero(actions == a)
        out[rows] = np.matmul(weights[rows, None, :], flat[a])[:, 0, :]
    return out.reshape(n_steps, r, r)


def _normalise(
    b_ao: np.ndarray, state: np.ndarray, b_inf: np.ndarray, b_inf_norm: float
) -> tuple[np.ndarray | None, float]:
    """Eq. 3.8 with the guard: ``(new state or None if degenerate, normaliser)``.

    ``||B_ao b||`` is ``sqrt(v . v)``, what ``np.linalg.norm`` computes for a vector.
    """
    with np.errstate(over="ignore", invalid="ignore"):
        v = b_ao @ state
        z = float(b_inf @ v)
        scale = b_inf_norm * math.sqrt(float(v.dot(v)))
    if not (math.isfinite(z) and math.isfinite(scale)) or z <= NORMALIZER_RTOL * scale:
        return None, z
    return v / z, z


def _step(
    b_ao: np.ndarray, state: np.ndarray, model: FilterParameters
) -> tuple[np.ndarray, float, bool]:
    """Eq. 3.8 with the guard's restart from ``b_*`` and the state box."""
    b_inf, b_inf_norm = model.b_inf, model.derived.b_inf_norm
    new, z = _normalise(b_ao, state, b_inf, b_inf_norm)
    recovered = new is None
    if new is None:
        new, _ = _normalise(b_ao, model.b_star, b_inf, b_inf_norm)
        if new is None:
            new = model.b_star.copy()
    box = model.state_box
    if box is not None:
        new = np.clip(new, box[0], box[1])
    return new, z, recovered


def _check_state(model: FilterParameters, state: np.ndarray) -> np.ndarray:
    arr = np.asarray(state, dtype=np.float64)
    if arr.shape != (model.state_dim,):
        raise DataError(f"state of shape {arr.shape} is not ({model.state_dim},)")
    if not np.isfinite(arr).all():
        raise DataError("state contains non-finite values")
    return arr


def _check_action(action: int, n_actions: int) -> int:
    """One action index, checked as :func:`check_actions` checks a batch (and by it, with
    its message, when it is not a plain index in range)."""
    if isinstance(action, int | np.integer) and not isinstance(action, bool):
        if 0 <= action < n_actions:
            return int(action)
    return int(check_actions(np.asarray([action]), n_actions, 1)[0])


def update(
    model: FilterParameters, state: np.ndarray, action: int, observation: np.ndarray
) -> tuple[np.ndarray, UpdateInfo]:
    """Algorithm 4: incorporate action ``action`` and observation ``(k,)`` into ``state (r,)``.

    Returns the new state ``(r,)`` and its :class:`UpdateInfo`.
    """
    state = _check_state(model, state)
    a = _check_action(action, model.n_actions)
    weights = observation_weights(model, np.asarray(observation, dtype=np.float64)[None, :])
    # the product update_matrices computes for a one-step group of action a (on the same
    # operators, maybe another copy)
    r, flat = model.state_dim, _operators(model)[model.derived.operator_of[a]]
    b_ao = np.matmul(weights[:, None, :], flat)[0, 0].reshape(r, r)
    new, z, recovered = _step(b_ao, state, model)
    return new, UpdateInfo(normalizer=z, recovered=recovered)


def track(
    model: FilterParameters,
    actions: np.ndarray,
    observations: np.ndarray,
    initial: np.ndarray | None = None,
) -> Track:
    """Algorithm 4 over ``T`` steps: ``actions (T,)``, ``observations (T, k)`` -> :class:`Track`.

    Starts at ``initial`` (default ``b_*``); row ``s`` of the states is the state after step
    ``s``. Equal, bit for bit, to a loop of :func:`update`.
    """
    obs = check_observations(observations, model.obs_size)
    acts = check_actions(actions, model.n_actions, obs.shape[0])
    state = model.initial_state() if initial is None else _check_state(model, initial)
    weights = observation_weights(model, obs)
    b_aos = update_matrices(model, acts, weights)
    n_steps, r = obs.shape[0], model.state_dim
    states = np.empty((n_steps, r))
    normalizers = np.empty(n_steps)
    recovered = np.zeros(n_steps, dtype=bool)
    for s in range(n_steps):
        state, normalizers[s], recovered[s] = _step(b_aos[s], state, model)
        states[s] = state
    return Track(states=states, normalizers=normalizers, recovered=recovered)
