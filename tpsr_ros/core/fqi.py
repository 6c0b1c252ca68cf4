"""Fitted Q-iteration with RBF features over continuous states (guide 4.1).

The planner of Jonschkowski & Brock (2015), as the guide uses it, with these choices
(published details verified where available, the rest ours and documented):

- states are standardised per dimension (zero mean, unit variance on the samples), so
  one kernel width suits every dimension of any representation; beyond the guide,
  ``state_scaling`` can instead whiten them on their principal axes, or weight those axes
  by how much of the coming observations they predict (``predictive``: a direction that
  predicts nothing, which whitening would blow up to unit variance, shrinks to zero);
- ``centers`` (100) RBF centres from k-means (scipy ``kmeans2``, k-means++ init,
  seeded) on the standardised states; the width is the mean distance from each centre
  to its nearest other centre;
- features are normalised RBF activations (they sum to 1, so a state far from every
  centre takes the value of the nearest one instead of decaying to 0);
- one block of weights per action: Q(s, a) = phi(s) . w_a; each iteration regresses
  r + gamma * max_a' Q(s', a') on phi(s) by ridge regression, separately per action,
  with discount gamma = 0.9, until the weights change by less than ``tolerance``;
- ridge 1e-2: with 1e-3 the values of standing still (+10) and pushing into a wall (-1)
  in the goal corner blur, and the true-position baseline scores 425-448 instead of
  ~470 (measured over RL seeds);
- a fit that does not converge is refused, never returned: ridge regression on RBF
  features is not a contraction, and some fits oscillate or grow. Converging fits took
  93-122 iterations on the experiments' states (one 262); one that still moves after
  ``iterations``, or whose values pass ten times the largest |Q| any policy can have
  (max|r| / (1 - gamma)), diverged. One diverging member of an ensemble, left in, decided
  the average and scored 40-70 instead of ~450. A diverged fit is refitted at ten times
  the ridge (:func:`ridge_ladder`, up to ``MAX_RIDGE``): the whole ensemble (``refit
  ensemble``, the guide's single fit), or only the members that diverged (``refit
  member``): two members that diverged in a ``partial-strip`` run took the other three to
  ridge 0.1 with them and the run scored 5.6; refitted alone, 201.1.

Transitions are ``(s_k, a_{k+1}, r_{k+1}, s_{k+1})`` from states tracked with a model's
parameters over one long random trajectory (never embedded histories; guide 4.2).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import asdict, dataclass
from functools import cached_property
from typing import Any, Literal

import numpy as np
from scipy.cluster.vq import kmeans2
from scipy.spatial.distance import cdist

from tpsr_ros.core.errors import ConfigError, DataError, DivergenceError
from tpsr_ros.core.fields import option as _param

__all__ = ["MAX_RIDGE", "FQIConfig", "QFunction", "fit_q", "ignore_trailing", "ridge_ladder"]

REFITS = ("ensemble", "member")
"""What a diverged fit refits at a larger ridge (``FQIConfig.refit``)."""

MAX_RIDGE = 1.0
"""Largest ridge a diverging fitted Q is refitted at before the fit gives up."""

SCALINGS = ("standardise", "whiten", "predictive")
"""Planner units (``FQIConfig.state_scaling``); ``predictive`` needs ``fit_q(futures=...)``."""

PREDICTIVE_RIDGE = 1e-3
"""Ridge of the predictive scaling's regression, per sample, in whitened state units."""

DIVERGENCE_FACTOR = 10.0
"""Fitted values beyond this multiple of max|r| / (1 - gamma), the bound of every policy's |Q|,
stop the iteration early as diverged."""


@dataclass(frozen=True)
class FQIConfig:
    """Parameters of fitted Q-iteration."""

    centers: int = _param(100, "RBF centres (k-means on the standardised states)")
    discount: float = _param(0.9, "discount factor gamma")
    ridge: float = _param(1e-2, "ridge penalty of each action's regression")
    iterations: int = _param(
        300, "Q-iterations allowed; a fit still changing after them is refused as diverged"
    )
    tolerance: float = _param(1e-6, "stop when the weights change less than this (relative)")
    kmeans_samples: int = _param(5000, "states sampled for k-means")
    seed: int = _param(0, "seed of the k-means sample and initialisation")
    width_scale: float = _param(
        1.0, "RBF width as a multiple of the mean nearest-centre distance"
    )
    state_scaling: Literal["standardise", "whiten", "predictive"] = _param(
        "standardise",
        "planner units: per-dimension z-scores, whitened principal axes, or axes weighted "
        "by how much of the next observations they predict",
        choices=SCALINGS,
    )
    ensemble: int = _param(1, "fitted-Q members averaged, each with its own k-means centres")
    refit: Literal["ensemble", "member"] = _param(
        "ensemble",
        "when a member's Q-iteration diverges, refit at ten times the ridge every member "
        "or that member alone",
        choices=REFITS,
    )

    def __post_init__(self) -> None:
        if self.centers < 2:
            raise ConfigError("fitted Q needs at least 2 RBF centres")
        if not 0.0 <= self.discount < 1.0:
            raise ConfigError(f"discount {self.discount} must be in [0, 1)")
        if self.ridge < 0 or self.iterations < 1 or self.tolerance <= 0:
            raise ConfigError("ridge >= 0, iterations >= 1 and tolerance > 0 are required")
        if self.state_scaling not in SCALINGS:
            raise ConfigError(
                f"state_scaling {self.state_scaling!r}: one of {', '.join(SCALINGS)}"
            )
        if self.ensemble < 1:
            raise ConfigError("the fitted-Q ensemble needs at least one member")
        if self.refit not in REFITS:
            raise ConfigError(f"refit {self.refit!r}: one of {', '.join(REFITS)}")
        if not self.width_scale > 0:
            raise ConfigError(f"width_scale {self.width_scale} must be positive")
        if self.kmeans_samples < self.centers or self.seed < 0:
            raise ConfigError("kmeans_samples must be >= centers and seed >= 0")

    def to_dict(self) -> dict[str, Any]:
        """Parameters as a JSON-serialisable dict."""
        return asdict(self)


@dataclass(frozen=True)
class QFunction:
    """A fitted Q-function: the mean of ``M`` members' normalised-RBF regressions.

    ``z = ((s - mean) @ rotation) / scale`` maps a state to planner units (``rotation`` is
    the identity when states are standardised, the principal axes when whitened, the axes
    of the state-to-future map when predictive); member
    ``m`` owns ``group_sizes[m]`` consecutive rows of ``centers`` with width ``width[m]``,
    and Q(s, a) = mean_m phi_m(z) . w_m[:, a]. One member is the guide's planner.
    ``ridges`` records the ridge each member was fitted at (None: not recorded, as for a
    Q-function read from a file); it plays no part in the values.
    """

    mean: np.ndarray  # (r,)
    scale: np.ndarray  # (r,)
    centers: np.ndarray  # (c, r), in planner units
    width: np.ndarray  # (M,), one per member (a float for one member)
    weights: np.ndarray  # (c, n_actions)
    rotation: np.ndarray | None = None  # (r, r); None: the identity
    group_sizes: np.ndarray | None = None  # (M,) centres per member; None: one member
    ridges: tuple[float, ...] | None = None  # (M,) each member's ridge; None: not recorded

    def __post_init__(self) -> None:
        width = np.atleast_1d(np.asarray(self.width, dtype=np.float64))
        sizes = np.array([len(self.centers)] if self.group_sizes is None else self.group_sizes)
        if width.ndim != 1 or sizes.shape != width.shape or sizes.min() < 1:
            raise DataError("one width and a positive centre count per ensemble member")
        if int(sizes.sum()) != len(self.centers):
            raise DataError(f"group sizes sum to {sizes.sum()}, not {len(self.centers)} centres")
        if self.ridges is not None and len(self.ridges) != len(width):
            raise DataError(f"{len(self.ridges)} ridges for {len(width)} ensemble members")
        object.__setattr__(self, "width", width)
        object.__setattr__(self, "group_sizes", sizes.astype(np.int64))

    @property
    def state_dim(self) -> int:
        """Dimension r of the states this Q-function takes."""
        return int(self.mean.shape[0])

    @property
    def n_actions(self) -> int:
        """Number of actions."""
        return int(self.weights.shape[1])

    @property
    def members(self) -> int:
        """Number M of averaged members."""
        return len(self.width)

    def planner_units(self, states: np.ndarray) -> np.ndarray:
        """States ``(T, r)`` centred, rotated and scaled as the centres are."""
        return _to_units(states, self.mean, self.scale, self.rotation)

    def features(self, states: np.ndarray) -> np.ndarray:
        """Normalised RBF features ``(T, c)`` of states ``(T, r)``, each member's summing to 1/M."""
        return self.unit_features(self.planner_units(states))

    @cached_property
    def _denominators(self) -> np.ndarray:
        """``2 width^2`` of every centre (fixed by the fit; computed once, not per step)."""
        widths = np.repeat(self.width, self.group_sizes)
        return 2.0 * widths**2

    @cached_property
    def _group_starts(self) -> np.ndarray:
        """First centre of each ensemble member."""
        return np.concatenate([[0], np.cumsum(self.group_sizes)[:-1]])

    @cached_property
    def _member_of(self) -> np.ndarray:
        """Ensemble member of every centre: spreads a per-member value over its centres."""
        return np.repeat(np.arange(self.members), self.group_sizes)

    def unit_features(self, units: np.ndarray) -> np.ndarray:
        """:meth:`features` of states already in planner units (:meth:`planner_units`)."""
        sq = cdist(units, self.centers, "sqeuclidean") / self._denominators
        if self.members == 1:  # the guide's planner, summed exactly as it always was
            sq -= sq.min(axis=1, keepdims=True)  # exact nearest-centre limit, never 0/0
            activation = np.exp(-sq)
            return activation / activation.sum(axis=1, keepdims=True)
        starts, member_of = self._group_starts, self._member_of
        sq -= np.minimum.reduceat(sq, starts, axis=1)[:, member_of]
        activation = np.exp(np.negative(sq, out=sq), out=sq)
        totals = np.add.reduceat(activation, starts, axis=1) * self.members
        return activation / totals[:, member_of]

    def values(self, states: np.ndarray) -> np.ndarray:
        """Q-values ``(T, n_actions)`` of states ``(T, r)``."""
        return self.features(np.atleast_2d(states)) @ self.weights

    def greedy(self, states: np.ndarray) -> np.ndarray:
        """Greedy action indices ``(T,)``; a non-finite state is refused (``DataError``)."""
        states = np.atleast_2d(states)
        if not np.isfinite(states).all():
            raise DataError("greedy policy called with a non-finite state")
        return np.argmax(self.values(states), axis=1)


def _to_units(
    states: np.ndarray, mean: np.ndarray, scale: np.ndarray, rotation: np.ndarray | None
) -> np.ndarray:
    """``((states - mean) @ rotation) / scale`` (no product for the identity rotation)."""
    centred = np.asarray(states, dtype=np.float64) - mean
    if rotation is not None:
        centred = centred @ rotation
    return centred / scale


def _scaling(
    states: np.ndarray, how: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """``(mean, scale, rotation)``: per-dimension standardising, or whitening on principal axes.

    A (near-)constant direction keeps scale 1, so it stays (near) 0 instead of blowing up.
    """
    mean = states.mean(axis=0)
    rotation = None
    if how == "whiten":
        variances, rotation = np.linalg.eigh(np.cov(states, rowvar=False).reshape(len(mean), -1))
        scale = np.sqrt(np.clip(variances, 0.0, None))
        floor = 1e-9 * max(float(scale.max()), 1e-300)
    else:
        scale = states.std(axis=0)
        floor = 1e-12 * max(1.0, float(np.abs(mean).max()))
    scale[scale < floor] = 1.0  # constant direction
    return mean, scale, rotation


def _predictive_scaling(
    states: np.ndarray, futures: tuple[np.ndarray, np.ndarray]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(mean, scale, rotation)`` in which distances are distances between predicted futures.

    ``futures = (past, future)`` pairs states ``(n, r)`` with features of what followed
    them ``(n, q)`` (e.g. principal components of the next observations). An affine ridge
    regression on the whitened states gives the linear map ``P (r, q)`` from centred states
    to predicted futures; with ``P = V diag(g) W^T`` the units ``(s - mean) V diag(g)`` keep
    every distance between predictions. The map, like whitening, is blind to invertible
    linear maps of the states, but a direction that predicts nothing (noise, a constant)
    shrinks to zero instead of being blown up to unit variance. One overall factor gives
    the units a mean square of 1 per dimension.
    """
    past, future = (np.asarray(x, dtype=np.float64) for x in futures)
    r = states.shape[1]
    if past.ndim != 2 or past.shape[1] != r or future.ndim != 2 or len(future) != len(past):
        raise DataError(
            f"futures must pair states (n, {r}) with features (n, q); got {past.shape} and "
            f"{future.shape}"
        )
    if len(past) <= r or not (np.all(np.isfinite(past)) and np.all(np.isfinite(future))):
        raise DataError(f"the predictive scaling needs more than {r} finite (state, future) pairs")
    mean = states.mean(axis=0)
    variances, axes = np.linalg.eigh(np.cov(past, rowvar=False).reshape(r, r))
    keep = variances > 1e-10 * max(float(variances.max()), 0.0)
    if not keep.any():
        raise DataError("the states do not vary: cannot scale them by what they predict")
    whitener = axes[:, keep] / np.sqrt(variances[keep])
    white = (past - past.mean(axis=0)) @ whitener
    gram = white.T @ white + PREDICTIVE_RIDGE * len(white) * np.eye(white.shape[1])
    weights = np.linalg.solve(gram, white.T @ (future - future.mean(axis=0)))
    rotation, gains, _ = np.linalg.svd(whitener @ weights)  # (r, r), (min(r, q),)
    gains = np.concatenate([gains, np.zeros(r - len(gains))])
    if not gains[0] > 0:
        raise DataError("the states predict nothing of the future observations")
    gains = np.maximum(gains, 1e-9 * gains[0])  # a direction that predicts nothing stays ~0
    units = (states - mean) @ rotation * gains
    overall = np.sqrt(np.mean(np.sum(units**2, axis=1)) / r)
    return mean, overall / gains, rotation


def _centres(z: np.ndarray, config: FQIConfig, seed: int) -> tuple[np.ndarray, float]:
    """k-means centres of a seeded sample of ``z`` and their RBF width."""
    rng = np.random.default_rng(seed)
    sample = z[rng.choice(len(z), size=min(len(z), config.kmeans_samples), replace=False)]
    centers, _ = kmeans2(sample, config.centers, minit="++", seed=rng)
    centers = np.unique(centers, axis=0)  # k-means can merge centres on degenerate data
    if len(centers) < 2:
        raise DataError("the states do not vary: cannot place RBF centres")
    gaps = cdist(centers, centers)
    np.fill_diagonal(gaps, np.inf)
    return centers, config.width_scale * float(gaps.min(axis=1).mean())


def _iterate(
    phi: np.ndarray,
    phi_next: np.ndarray,
    actions: np.ndarray,
    rewards: np.ndarray,
    n_actions: int,
    config: FQIConfig,
) -> np.ndarray:
    """Q-iteration weights ``(c, n_actions)`` on fixed features (one ridge system per action).

    Raises ``DivergenceError`` when the iteration diverges: its values leave
    ``DIVERGENCE_FACTOR`` times the bound of every policy's |Q|, or its weights still
    change after ``config.iterations`` iterations.
    """
    eye = config.ridge * np.eye(phi.shape[1])
    groups = [np.flatnonzero(actions == a) for a in range(n_actions)]
    # ridge solution operator of each action's block, computed once: (c, n_a)
    solvers = [np.linalg.solve(phi[g].T @ phi[g] + eye, phi[g].T) for g in groups]
    bound = DIVERGENCE_FACTOR * float(np.abs(rewards).max()) / (1.0 - config.discount)
    weights = np.zeros((phi.shape[1], n_actions))
    change = 0.0
    for _ in range(config.iterations):
        best_next = (phi_next @ weights).max(axis=1)
        if not np.abs(best_next).max() <= bound:  # NaN fails the comparison too
            raise DivergenceError(
                f"fitted Q-iteration diverged at ridge {config.ridge:g}: values passed "
                f"{bound:g}, {DIVERGENCE_FACTOR:g} times the largest |Q| of any policy; "
                "increase the ridge"
            )
        target = rewards + config.discount * best_next
        new = np.column_stack([solvers[a] @ target[g] for a, g in enumerate(groups)])
        change = float(np.abs(new - weights).max())
        weights = new
        if change < config.tolerance * max(1.0, float(np.abs(weights).max())):
            return weights
    raise DivergenceError(
        f"fitted Q-iteration did not converge in {config.iterations} iterations at ridge "
        f"{config.ridge:g} (the weights still change by {change:.3g}); increase the ridge"
    )


def ridge_ladder(ridge: float, max_ridge: float = MAX_RIDGE) -> list[float]:
    """Ridges a diverging fit tries in turn: ``ridge``, ten times it, ... up to ``max_ridge``."""
    ladder = [ridge]
    while ridge * 10.0 ** len(ladder) <= max_ridge:
        ladder.append(ridge * 10.0 ** len(ladder))
    return ladder


def fit_q(
    states: np.ndarray,
    actions: np.ndarray,
    rewards: np.ndarray,
    next_states: np.ndarray,
    n_actions: int,
    config: FQIConfig | None = None,
    *,
    futures: tuple[np.ndarray, np.ndarray] | None = None,
    max_ridge: float | None = None,
) -> QFunction:
    """Fit Q from ``states (T, r)``, ``actions (T,)``, ``rewards (T,)``, ``next_states (T, r)``.

    Each of the ``config.ensemble`` members has its own k-means centres (seed ``seed + m``)
    and its own Q-iteration at ``config.ridge``; the returned Q-function averages them.
    A member that diverges raises ``DivergenceError``; with ``max_ridge``, the fit is first
    refitted at the larger ridges of :func:`ridge_ladder`: every member, or with
    ``config.refit == "member"`` that member alone (the others keep theirs).
    ``futures`` (states paired with features of what followed them) is needed by, and only
    used for, ``state_scaling="predictive"`` (:func:`_predictive_scaling`).
    """
    config = config or FQIConfig()
    states = np.asarray(states, dtype=np.float64)
    next_states = np.asarray(next_states, dtype=np.float64)
    actions = np.asarray(actions)
    rewards = np.asarray(rewards, dtype=np.float64)
    if states.ndim != 2 or next_states.shape != states.shape:
        raise DataError(f"states {states.shape} and next states {next_states.shape} differ")
    if actions.shape != (len(states),) or rewards.shape != (len(states),):
        raise DataError("actions and rewards need one entry per transition")
    if len(states) < config.centers:
        raise DataError(f"{len(states)} transitions are fewer than {config.centers} RBF centres")
    for name, array in (("states", states), ("next states", next_states), ("rewards", rewards)):
        if not np.all(np.isfinite(array)):
            raise DataError(f"{name} contain non-finite values")
    if actions.min() < 0 or actions.max() >= n_actions:
        raise DataError(f"actions must lie in [0, {n_actions})")
    missing = sorted(set(range(n_actions)) - set(np.unique(actions).tolist()))
    if missing:
        raise DataError(f"actions {missing} never occur in the transitions")

    if config.state_scaling == "predictive":
        if futures is None:
            raise ConfigError(
                "state_scaling 'predictive' needs the features of what followed the states "
                "(fit_q(futures=...))"
            )
        mean, scale, rotation = _predictive_scaling(np.vstack([states, next_states]), futures)
    else:
        mean, scale, rotation = _scaling(np.vstack([states, next_states]), config.state_scaling)
    z, z_next = (_to_units(s, mean, scale, rotation) for s in (states, next_states))
    members = [_centres(z, config, config.seed + m) for m in range(config.ensemble)]
    ladder = [config.ridge] if max_ridge is None else ridge_ladder(config.ridge, max_ridge)

    def fit_member(index: int, ridges: list[float]) -> tuple[np.ndarray, float]:
        """Member ``index``'s weights at the first of ``ridges`` that converges."""
        centers, width = members[index]
        member = QFunction(mean, scale, centers, width, np.zeros((len(centers), 1)), rotation)
        phi, phi_next = member.unit_features(z), member.unit_features(z_next)
        for ridge in ridges:
            attempt = dataclasses.replace(config, ridge=ridge)
            try:
                return _iterate(phi, phi_next, actions, rewards, n_actions, attempt), ridge
            except DivergenceError as exc:
                failure = exc
        named = f"member {index + 1} of {len(members)}: " if len(members) > 1 else ""
        raise DivergenceError(f"{named}{failure}") from failure

    try:
        fitted = (
            [fit_member(m, ladder) for m in range(len(members))]
            if config.refit == "member"  # each member climbs the ladder alone
            else _at_lowest_rung(fit_member, len(members), ladder)
        )
    except DivergenceError as exc:
        if max_ridge is None:
            raise
        tried = (
            f"ridges {ladder[0]:g} to {ladder[-1]:g}" if len(ladder) > 1 else f"ridge {ladder[0]:g}"
        )
        raise DivergenceError(f"{exc} ({tried} tried)") from exc
    weights, ridges = [w for w, _ in fitted], [r for _, r in fitted]
    return QFunction(
        mean,
        scale,
        np.vstack([c for c, _ in members]),
        np.array([w for _, w in members]),
        np.vstack(weights),
        rotation,
        np.array([len(c) for c, _ in members]),
        tuple(ridges),
    )


def _at_lowest_rung(
    fit_member: Callable[[int, list[float]], tuple[np.ndarray, float]],
    members: int,
    ladder: list[float],
) -> list[tuple[np.ndarray, float]]:
    """Every member fitted at the lowest ridge of ``ladder`` at which all of them converge."""
    for ridge in ladder:
        try:
            return [fit_member(m, [ridge]) for m in range(members)]
        except DivergenceError as exc:
            failure = exc
    raise failure


def ignore_trailing(q: QFunction, state_dim: int) -> QFunction:
    """``q``, fitted on the leading ``q.state_dim`` coordinates, over states of ``state_dim``.

    The trailing coordinates get zero planner units (zero rows in the rotation, scale 1,
    centres 0 there), so values and greedy actions are those of ``q`` on the leading part.
    For states that carry memory the planner should not see: the buffer of
    :class:`tpsr_ros.core.window_baselines.WindowModel`.
    """
    r = q.state_dim
    if state_dim < r:
        raise DataError(f"states of {state_dim} coordinates cannot hold the Q-function's {r}")
    if state_dim == r:
        return q
    extra = state_dim - r
    rotation = np.zeros((state_dim, state_dim))
    rotation[:r, :r] = np.eye(r) if q.rotation is None else q.rotation
    return QFunction(
        np.concatenate([q.mean, np.zeros(extra)]),
        np.concatenate([q.scale, np.ones(extra)]),
        np.concatenate([q.centers, np.zeros((len(q.centers), extra))], axis=1),
        q.width,
        q.weights,
        rotation,
        q.group_sizes,
        q.ridges,
    )
