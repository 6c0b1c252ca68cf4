"""Refinement of a spectral TPSR through its own filter: truncated backpropagation through time.

The spectral fit (Algorithm 3) is consistent, but with one-image histories and tests and
one pooled operator for all actions its filter is an action-blind smoother of the current
image: the regression that defines ``B_ao`` only ever sees ``(o_{t-1}, a_t, o_t, o_{t+1})``.
The successors of the spectral method (Hefny et al., NIPS 2015, and their RFF-PSR code;
Downey et al., "Predictive State Recurrent Neural Networks", NIPS 2017) take the spectral
model as the *initialisation* and refine it by backpropagation through the filter on
multi-step prediction. This module does that with numpy and scipy's L-BFGS-B.

The parameterisation gives each action back its own small factor::

    B_{a o'} = B_{o'} A_a        b_t = B_{a_t o_t} b_{t-1} / (b_inf^T B_{a_t o_t} b_{t-1})

with ``B_{o'}`` ``(l_O, r, r)`` shared by the actions, ``A_a`` ``(r, r)`` per action (the
state propagated by the action before the observation weighs it) and ``b_inf``. It starts at
the spectral model: ``B_{o'}`` the mean of the actions' operators and ``A_a`` the least-squares
factor of action ``a`` (exactly the identity for pooled operators); what the factors leave
of unpooled operators, ``R_{a o'} = B_{a o'} - B_{o'} A_a``, is kept fixed and added, so the
start is the spectral model exactly (with ``refine_carry``, the spectral model with its
carry, below). The refined model stores the operators
``B[a, o'] = B_{o'} A_a + R_{a o'}``, so the model file,
:func:`~tpsr_ros.core.filtering.track`, the filter node and their equality bit for bit are
unchanged.

The objective, over windows of the training trajectory: each window starts at ``b_*`` and runs
the filter (with its normaliser guard and restart) for ``window`` burn-in steps, then
``window`` scored steps. The state ``b_t`` of a scored step should predict the next
``horizon`` observations' features ``y_{t+1} .. y_{t+h}`` (the top principal components of
the model's own observation whitening, weighted by their variance, as ``learner tune``'s
criterion): an affine read-out ``W`` is solved in closed form by ridge regression for the
current states (variable projection), so the loss is ``min_W ||Y - [X 1] W||^2 / SST``, the
fraction of the futures' variance the states leave unexplained, plus a pull toward the
spectral values, ``pull * sum_g ||theta_g - theta_g0||^2 / ||theta_g0||^2``, plus a barrier
that keeps the filter from its restarts: the mean over the windows' steps of
``max(0, 1 - z / z_floor)^2``, ``z`` each step's normaliser and ``z_floor``
:data:`BARRIER_FRACTION` of the start's median one. A restart cuts the past off, so the
prediction error alone cannot see what a restart costs; a planner's filter, run without end,
restarts wherever the refined operators let the normaliser fall below zero. Its gradient
is exact (the read-out is at its optimum, so only the states' dependence on the parameters
counts) and checked against finite differences in the tests.

The past as a target (``refine_past`` ``q > 0``). The states of the scored steps also
predict the features of the last ``q`` observations before the current one,
``y_{t-1} .. y_{t-q}``, in the same read-out and loss. A filter that forgets within a step
cannot: the target asks the state to carry what it saw forward, which the future alone
asks for only where places look alike, a small part of a random run.

Memory to start from (``refine_carry`` ``c > 0``). The spectral filter contracts: a change
of the previous state shrinks to about a tenth in one step, so the gradient through the
recursion vanishes within a step or two and the refinement cannot find a use for the past
it never sees. Before refining, ``mu I`` is added to every ``B_{a o'}``; the observation
weights sum to one and a state's ``b_inf^T b`` is one, so a step becomes
``b_t = (B_{a o} b + mu A_a b) / (z + mu)``: the observation's update mixed with the
previous state propagated by the action, the latter weighing ``mu / (z + mu)``. ``mu`` is
``c / (1 - c)`` times the median normaliser ``z`` of the spectral filter over the training
steps, so a typical step carries the fraction ``c`` of its previous state forward. The
refinement starts there (and its pull draws toward there): the same model class, stored as
operators like any other. With ``refine_carry_rule`` ``aliased`` the carry applies only
where the previous image helps to predict the next ones (:mod:`tpsr_ros.core.history_gain`):
where one image tells the place the refinement starts from the spectral filter, without the
carry's lag.

The search's variables (``refine_scaling``): the parameters themselves (``none``), or each
group (``B_{o'}``, the factors ``A_a``, ``b_inf``) divided by its root mean square at the
start (``groups``, :func:`group_scales`). The groups' sizes differ by orders of magnitude,
so unscaled the search barely moves the actions' factors; scaled, it does, but on the
selection seeds of ``partial-strip`` it planned far worse (docs/results.md, "A predictive
state: scaling the refinement's search"), and ``none`` stays the default.

Early stopping: the last :data:`HOLDOUT` of the windows (in time) are held out; after every
iteration their loss is measured with the training read-out, and the parameters of the best
held-out loss are returned among those whose filter, tracked continuously over the held-out
steps, restarts no more often than the spectral filter or the start, ``n`` restarts, within
the noise of such a count: at most ``n + ceil(2 sqrt(n + 1))`` (:func:`restart_allowance`).
The objective cuts the past at a restart, so it cannot see what restarts cost a planner:
one refinement of ``partial-strip`` that predicted better restarted at 3 % of the steps.
The search stops when the held-out loss, restarts or not, has not improved for
:data:`PATIENCE` iterations (the first iterations of the search wander, and may restart
where later ones do not). When no iterate qualifies, the spectral model itself is returned:
a carried start is a place to begin the search, not a model.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from scipy.optimize import minimize

from tpsr_ros.core.errors import DataError
from tpsr_ros.core.filtering import (
    NORMALIZER_RTOL,
    observation_weights,
    track,
    update_matrices,
)
from tpsr_ros.core.history_gain import history_gain
from tpsr_ros.core.sizing import Sizing
from tpsr_ros.core.tpsr_config import TPSRConfig
from tpsr_ros.core.tpsr_model import TPSRModel
from tpsr_ros.core.tpsr_stages import Progress
from tpsr_ros.core.whitening import single_blas_thread

__all__ = [
    "HOLDOUT",
    "PATIENCE",
    "Factors",
    "RefineProblem",
    "carried",
    "chosen_carry",
    "factor_model",
    "group_scales",
    "refine_tpsr",
    "restart_allowance",
]

HOLDOUT = 0.1
"""Fraction of the windows (the last in time) held out for early stopping."""

PATIENCE = 5
"""Iterations without a better held-out loss before the search stops."""

BARRIER_FRACTION = 0.2
"""The barrier's floor: this fraction of the start's median normaliser."""

BARRIER_WEIGHT = 1.0
"""Weight of the normaliser barrier in the objective."""

TARGET_COMPONENTS = 10
"""Principal components of the observations the states must predict."""

CLIP_SPREADS = 3.0
"""The read-out sees each state coordinate pulled smoothly (tanh) into its spectral median
+- this many robust spreads: a state blown up near the normaliser guard costs a bounded
error instead of swamping the loss."""

READOUT_RIDGE = 1e-6
"""Ridge of the read-out, relative to the mean squared size of the spectral states."""


@dataclass(frozen=True)
class Factors:
    """``B_{a o'} = B_{o'} A_a`` and the normaliser: the refined parameters."""

    shared: np.ndarray  # (l_O, r, r): B_{o'}
    action: np.ndarray  # (n_actions, r, r): A_a
    b_inf: np.ndarray  # (r,)

    def vector(self) -> np.ndarray:
        """All parameters as one vector (the optimiser's)."""
        return np.concatenate([self.shared.ravel(), self.action.ravel(), self.b_inf])

    def like(self, theta: np.ndarray) -> Factors:
        """Factors of these shapes holding ``theta``."""
        n_s, n_a = self.shared.size, self.action.size
        return Factors(
            theta[:n_s].reshape(self.shared.shape),
            theta[n_s : n_s + n_a].reshape(self.action.shape),
            theta[n_s + n_a :].copy(),
        )

    def operators(self) -> np.ndarray:
        """``B`` ``(n_actions, l_O, r, r)``: every ``B_{o'} A_a``."""
        return np.einsum("oij,ajk->aoik", self.shared, self.action)


def factor_model(model: TPSRModel) -> Factors:
    """The factors closest to ``model``'s operators: ``B_{o'}`` their mean over actions and
    ``A_a = argmin sum_o' ||B_{o'} A_a - B_{a o'}||^2`` (the identity for pooled operators)."""
    big_b = model.B
    shared = big_b.mean(axis=0)
    r = shared.shape[-1]
    gram = np.einsum("oji,ojk->ik", shared, shared)  # sum_o' B_o'^T B_o'
    cross = np.einsum("oji,aojk->aik", shared, big_b)  # per action: sum_o' B_o'^T B_ao'
    ridge = 1e-12 * np.trace(gram) / r
    action = np.linalg.solve(gram + ridge * np.eye(r), cross)
    return Factors(shared, action, np.array(model.b_inf, dtype=np.float64))


def group_scales(start: Factors, how: str) -> np.ndarray:
    """Per parameter, what the search's variable is multiplied by to give it (``how``
    ``"groups"``: its group's root mean square at the start, 1 for a group of zeros;
    ``"none"``: 1).

    Unscaled, the groups differ by orders of magnitude: on ``partial-strip`` the entries of
    ``B_{o'}`` are ~0.004 and those of ``A_a`` ~0.35, so a step of the search changes
    ``B_{o'}`` by a fraction some 600 times larger than it changes ``A_a``, and the
    actions' factors stay at the start (0.1 % apart after a refinement). Divided by their
    groups' sizes, every group moves by a like fraction.
    """
    groups = (start.shared, start.action, start.b_inf)
    if how == "none":
        return np.ones(sum(g.size for g in groups))
    sizes = []
    for group in groups:
        rms = float(np.sqrt(np.mean(group**2))) if group.size else 0.0
        sizes.append(np.full(group.size, rms if rms > 0 and np.isfinite(rms) else 1.0))
    return np.concatenate(sizes)


def restart_allowance(count: int) -> int:
    """Restarts a refined filter may make on the held-out steps where its references made
    ``count``: as many, plus two standard deviations of a Poisson count."""
    return count + math.ceil(2.0 * math.sqrt(count + 1.0))


def carried(
    model: TPSRModel,
    actions: np.ndarray,
    observations: np.ndarray,
    carry: float | None = None,
) -> tuple[TPSRModel, float]:
    """``model`` whose typical step carries ``carry`` (default ``config.refine_carry``) of
    the previous state forward (module docstring), and ``mu``: ``mu I`` added to every
    operator (at 0 the model itself and 0)."""
    carry = float(model.config.refine_carry if carry is None else carry)
    if carry == 0.0:
        return model, 0.0
    tracked = track(model, actions, observations)
    z = tracked.normalizers[~tracked.recovered]
    z = z[np.isfinite(z) & (z > 0)]
    if z.size == 0:
        raise DataError("no step of the spectral filter has a valid normaliser to carry from")
    mu = carry / (1.0 - carry) * float(np.median(z))
    return replace(model, B=model.B + mu * np.eye(model.state_dim)), mu


def chosen_carry(
    model: TPSRModel,
    actions: np.ndarray,
    observations: np.ndarray,
    bounds: list[tuple[int, int]] | None = None,
) -> tuple[float, float | None]:
    """The carry the refinement starts from, and the history gain that chose it (None when
    not measured): ``refine_carry``, but with ``refine_carry_rule`` ``aliased`` 0 where
    the previous image does not help to predict the next ones
    (:func:`~tpsr_ros.core.history_gain.history_gain` at or below 0). Steps too few to
    tell keep ``refine_carry``: the carry was chosen where places look alike, and a short
    run cannot show that they do not."""
    cfg = model.config
    if cfg.refine_carry == 0.0 or cfg.refine_carry_rule == "always":
        return float(cfg.refine_carry), None
    try:
        gain = history_gain(actions, observations, model.n_actions, bounds)
    except DataError:
        return float(cfg.refine_carry), None
    return (float(cfg.refine_carry) if gain > 0.0 else 0.0), gain


def _targets(model: TPSRModel, observations: np.ndarray) -> np.ndarray:
    """``(T, p)`` top principal components of the observations, weighted by their variance."""
    white = (observations - model.obs_mean) @ model.obs_whitening
    ratio = np.asarray(model.explained_variance["obs"], dtype=np.float64)
    p = min(TARGET_COMPONENTS, white.shape[1], ratio.shape[0])
    return white[:, :p] * np.sqrt(np.maximum(ratio[:p], 0.0))


def _window_starts(bounds: list[tuple[int, int]], window: int, horizon: int) -> np.ndarray:
    """First rows of the windows: ``window`` burn-in then ``window`` scored steps, every
    scored step with ``horizon`` future steps, all inside one segment."""
    span = 2 * window + horizon
    starts = [np.arange(a, b - span + 1, window, dtype=np.int64) for a, b in bounds]
    return np.concatenate(starts) if starts else np.zeros(0, dtype=np.int64)


def _shortfall(windows: int, cfg: TPSRConfig) -> str | None:
    """Why ``windows`` windows cannot carry the refinement, or None."""
    if windows >= 2:
        return None
    span = 2 * int(cfg.refine_window) + int(cfg.refine_horizon)
    return (
        f"refinement needs at least two windows of {span} steps in one segment; the data "
        f"has {windows}"
    )


@dataclass(frozen=True)
class _Operators:
    """Operators ``B`` alone, as :func:`~tpsr_ros.core.filtering.update_matrices` reads them."""

    B: np.ndarray

    @property
    def state_dim(self) -> int:
        return int(self.B.shape[-1])

    @property
    def n_actions(self) -> int:
        return int(self.B.shape[0])


@dataclass
class _Tape:
    """What the forward pass keeps for the backward one, per step of the windows."""

    b_in: np.ndarray  # (2w, C, r) the state each step updated (b_{t-1}, or b_* on restart)
    u: np.ndarray  # (2w, C, r) A_a b_in
    v: np.ndarray  # (2w, C, r) M u
    z: np.ndarray  # (2w, C) normaliser
    mode: np.ndarray  # (2w, C) 0: normal step, 1: restarted from b_*, 2: set to b_*
    m: np.ndarray  # (rows, r, r) sum_o' phi_o'(o_t) B_o' of the rows first .. first + rows
    first: int


class RefineProblem:
    """The refinement objective on one trajectory: loss and gradient of a parameter vector.

    ``observations`` ``(T, k)`` and ``actions`` ``(T,)`` are the training trajectory with its
    segments' ``bounds``; ``start`` gives the shapes, the pull's centre and ``b_*``.
    """

    def __init__(
        self,
        model: TPSRModel,
        start: Factors,
        actions: np.ndarray,
        observations: np.ndarray,
        bounds: list[tuple[int, int]],
    ) -> None:
        cfg = model.config
        self.window, self.horizon, self.past, self.pull = (
            int(cfg.refine_window),
            int(cfg.refine_horizon),
            int(cfg.refine_past),
            float(cfg.refine_pull),
        )
        self.start = start
        self._model = model
        self.b_star = np.array(model.b_star, dtype=np.float64)
        self.actions = np.asarray(actions, dtype=np.int64)
        self._observations = observations
        self.weights = observation_weights(model, observations)  # (T, l_O), fixed
        # what the factors leave of the spectral operators, kept fixed: the start is the
        # spectral model exactly, pooled or not
        self.rest = model.B - start.operators()
        self._rest = update_matrices(_Operators(self.rest), self.actions, self.weights)
        targets = _targets(model, observations)
        starts = _window_starts(bounds, self.window, self.horizon)
        if (shortfall := _shortfall(starts.size, cfg)) is not None:
            raise DataError(shortfall)
        n_held = max(1, round(HOLDOUT * starts.size))
        self.train_starts, self.held_starts = starts[:-n_held], starts[-n_held:]
        # scored rows of every window, and their targets' features (rows x (horizon+past)*p)
        self._targets = {
            name: self._future(targets, s)
            for name, s in (("train", self.train_starts), ("held", self.held_starts))
        }
        self._norms = [max(float(np.sum(g**2)), 1e-300) for g in self._groups(start)]
        walked, tape, _ = self._forward(start, self.train_starts)
        typical = np.median(tape.z[tape.mode == 0]) if (tape.mode == 0).any() else 0.0
        self.z_floor = BARRIER_FRACTION * float(typical) if typical > 0 else 0.0
        states = walked[self.window :].transpose(1, 0, 2).reshape(-1, walked.shape[-1])
        centre = np.median(states, axis=0)
        spread = 1.4826 * np.median(np.abs(states - centre), axis=0)
        self._centre = centre
        self._reach = CLIP_SPREADS * np.maximum(spread, 1e-12 * max(float(spread.max()), 1e-300))
        states = self._squash(states)[0]
        self.ridge = READOUT_RIDGE * max(float(np.mean(np.sum(states**2, axis=1))), 1e-300)
        self.readout = self._readout(states, self._targets["train"])

    # --- data --------------------------------------------------------------------------
    def _future(self, targets: np.ndarray, starts: np.ndarray) -> np.ndarray:
        """Centred features of what the scored steps' states predict: the next ``horizon``
        observations, then the last ``past`` before the current one (all in the window)."""
        w = self.window
        scored = (starts[:, None] + w + np.arange(w)).ravel()  # window-major, then step
        offsets = np.concatenate([1 + np.arange(self.horizon), -1 - np.arange(self.past)])
        future = targets[scored[:, None] + offsets]  # (rows, horizon + past, p)
        future = future.reshape(scored.size, -1)
        return future - future.mean(axis=0)

    @staticmethod
    def _groups(f: Factors) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return f.shared, f.action, f.b_inf

    # --- the filter over windows ---------------------------------------------------------
    def _forward(self, f: Factors, starts: np.ndarray) -> tuple[np.ndarray, _Tape, np.ndarray]:
        """States ``(2w, C, r)`` of the windows, the tape, and the rows ``(2w, C)``."""
        w2, c, r = 2 * self.window, starts.size, self.b_star.shape[0]
        rows = starts[None, :] + np.arange(w2)[:, None]
        flat = f.shared.reshape(f.shared.shape[0], r * r)
        first, last = int(rows.min()), int(rows.max()) + 1  # windows are contiguous in time
        m_rows = (self.weights[first:last] @ flat).reshape(-1, r, r)  # each row once
        tape = _Tape(*(np.empty((w2, c, r)) for _ in range(3)), np.empty((w2, c)),
                     np.zeros((w2, c), dtype=np.int8), m_rows, first)  # fmt: skip
        states = np.empty((w2, c, r))
        b = np.broadcast_to(self.b_star, (c, r)).copy()
        norm_inf = float(np.linalg.norm(f.b_inf))
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            for k in range(w2):
                m = m_rows[rows[k] - first]
                a = f.action[self.actions[rows[k]]]
                b_in, mode, u, v, z = self._step(m, a, self._rest[rows[k]], b, f.b_inf, norm_inf)
                tape.b_in[k], tape.u[k], tape.v[k], tape.z[k], tape.mode[k] = b_in, u, v, z, mode
                b = np.where(
                    (mode == 2)[:, None], self.b_star, v / np.where(mode == 2, 1.0, z)[:, None]
                )
                states[k] = b
        return states, tape, rows

    def _step(
        self,
        m: np.ndarray,
        a: np.ndarray,
        rest: np.ndarray,
        b: np.ndarray,
        b_inf: np.ndarray,
        norm_inf: float,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """One guarded update of every window (filtering._step, vectorised):
        ``v = M A b + R b`` with ``R`` the fixed part of the step's operator."""
        u = np.einsum("cij,cj->ci", a, b)
        v = np.einsum("cij,cj->ci", m, u) + np.einsum("cij,cj->ci", rest, b)
        z = v @ b_inf
        bad = ~(np.isfinite(z) & (z > NORMALIZER_RTOL * norm_inf * np.linalg.norm(v, axis=1)))
        mode = np.zeros(b.shape[0], dtype=np.int8)
        b_in = b
        if bad.any():
            b_in = b.copy()
            b_in[bad] = self.b_star
            u[bad] = a[bad] @ self.b_star
            v[bad] = np.einsum("cij,cj->ci", m[bad], u[bad]) + rest[bad] @ self.b_star
            z[bad] = v[bad] @ b_inf
            still = bad & ~(
                np.isfinite(z) & (z > NORMALIZER_RTOL * norm_inf * np.linalg.norm(v, axis=1))
            )
            mode[bad] = 1
            mode[still] = 2
        return b_in, mode, u, v, z

    def states(self, f: Factors, starts: np.ndarray) -> np.ndarray:
        """The scored states ``(C w, r)`` of the windows ``starts`` (window-major)."""
        states, _, _ = self._forward(f, starts)
        return states[self.window :].transpose(1, 0, 2).reshape(-1, states.shape[-1])

    # --- read-out ------------------------------------------------------------------------
    def _squash(self, states: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """States pulled smoothly into ``centre +- reach`` and the derivative of the pull."""
        t = np.tanh((states - self._centre) / self._reach)
        return self._centre + self._reach * t, 1.0 - t**2

    def _design(self, states: np.ndarray) -> np.ndarray:
        return np.column_stack([states, np.ones(states.shape[0])])

    def _readout(self, states: np.ndarray, targets: np.ndarray) -> np.ndarray:
        return self._solve(self._design(states), targets)

    def _solve(self, x: np.ndarray, targets: np.ndarray) -> np.ndarray:
        """The ridge read-out of the design ``x`` (``[states, 1]``)."""
        gram = x.T @ x
        gram[np.diag_indices(x.shape[1] - 1)] += self.ridge * x.shape[0]
        return np.linalg.solve(gram, x.T @ targets)

    def unexplained(
        self, f: Factors, which: str = "held", readout: np.ndarray | None = None
    ) -> float:
        """Fraction of the futures' variance unexplained on ``which`` windows (1 - R^2),
        with the training read-out of ``f`` (or ``readout``)."""
        starts = self.held_starts if which == "held" else self.train_starts
        y = self._targets[which]
        if readout is None:
            train = self._squash(self.states(f, self.train_starts))[0]
            readout = self._readout(train, self._targets["train"])
        resid = y - self._design(self._squash(self.states(f, starts))[0]) @ readout
        return float(np.sum(resid**2) / max(np.sum(y**2), 1e-300))

    def model_of(self, f: Factors) -> TPSRModel:
        """The model whose operators are ``f``'s plus the fixed rest."""
        return replace(self._model, B=f.operators() + self.rest, b_inf=f.b_inf)

    @property
    def held_steps(self) -> int:
        """Steps of the held-out stretch :meth:`restarts` tracks."""
        return int(self.held_starts[-1]) + 2 * self.window - int(self.held_starts[0])

    def restarts(self, f: Factors | TPSRModel) -> int:
        """Restarts of the filter of ``f`` (or of a model) tracked continuously over the
        held-out stretch (the held-out windows' steps, as a planner's filter runs)."""
        if isinstance(f, Factors):
            f = self.model_of(f)
        first = int(self.held_starts[0])
        stop = first + self.held_steps
        tracked = track(f, self.actions[first:stop], self._observations[first:stop])
        return int(tracked.recovered.sum())

    # --- loss and gradient -----------------------------------------------------------------
    def loss_and_grad(self, theta: np.ndarray) -> tuple[float, np.ndarray]:
        """The objective (module docstring) and its exact gradient."""
        f = self.start.like(theta)
        states, tape, rows = self._forward(f, self.train_starts)
        w, r = self.window, states.shape[-1]
        c = self.train_starts.size
        scored = states[w:].transpose(1, 0, 2).reshape(-1, r)
        y = self._targets["train"]
        sst = max(float(np.sum(y**2)), 1e-300)
        if not np.isfinite(scored).all():
            return float("inf"), np.zeros_like(theta)
        squashed, slope = self._squash(scored)
        x = self._design(squashed)
        readout = self._solve(x, y)  # at its optimum: only the states carry gradient
        resid = y - x @ readout
        loss = (
            float(np.sum(resid**2)) + self.ridge * x.shape[0] * float(np.sum(readout[:r] ** 2))
        ) / sst
        g_scored = (-2.0 / sst) * (resid @ readout[:r].T) * slope  # (C w, r)
        g_states = np.zeros_like(states)
        g_states[w:] = g_scored.reshape(c, w, r).transpose(1, 0, 2)
        barrier, g_z = self._barrier(tape)
        loss += barrier
        grads = self._backward(f, tape, rows, g_states, g_z)
        for g, (cur, ini, norm) in zip(
            grads,
            zip(self._groups(f), self._groups(self.start), self._norms, strict=True),
            strict=True,
        ):
            diff = cur - ini
            loss += self.pull * float(np.sum(diff**2)) / norm
            g += (2.0 * self.pull / norm) * diff
        return loss, np.concatenate([g.ravel() for g in grads])

    def _barrier(self, tape: _Tape) -> tuple[float, np.ndarray]:
        """The normaliser barrier (module docstring) and its derivative by every step's ``z``
        ``(2w, C)``; a step set to ``b_*`` has no normaliser and costs nothing."""
        if self.z_floor <= 0:
            return 0.0, np.zeros_like(tape.z)
        with np.errstate(invalid="ignore"):
            short = np.where(tape.mode != 2, np.maximum(1.0 - tape.z / self.z_floor, 0.0), 0.0)
        scale = BARRIER_WEIGHT / short.size
        return scale * float(np.sum(short**2)), (-2.0 * scale / self.z_floor) * short

    def _backward(
        self,
        f: Factors,
        tape: _Tape,
        rows: np.ndarray,
        g_states: np.ndarray,
        g_z: np.ndarray,
    ) -> list[np.ndarray]:
        """Gradients of the states' loss (and of the barrier, by each step's normaliser
        ``g_z``) with respect to ``B_{o'}``, ``A_a`` and ``b_inf``."""
        w2, c, r = g_states.shape
        n_obs = f.shared.shape[0]
        g_m_rows = np.zeros((tape.m.shape[0], r * r))
        g_action = np.zeros_like(f.action)
        g_inf = np.zeros(r)
        carry = np.zeros((c, r))
        for k in range(w2 - 1, -1, -1):
            g = g_states[k] + carry
            mode, z, u, v, b_in = tape.mode[k], tape.z[k], tape.u[k], tape.v[k], tape.b_in[k]
            live = mode != 2
            g = np.where(live[:, None], g, 0.0)
            zz = np.where(live, z, 1.0)
            b_new = v / zz[:, None]
            gb = np.einsum("ci,ci->c", g, b_new)
            g_v = (g - gb[:, None] * f.b_inf) / zz[:, None] + g_z[k][:, None] * f.b_inf
            g_inf += (g_z[k] - gb / zz) @ v
            m = tape.m[rows[k] - tape.first]
            g_m_rows[rows[k] - tape.first] += np.einsum("ci,cj->cij", g_v, u).reshape(c, r * r)
            g_u = np.einsum("cji,cj->ci", m, g_v)
            acts = self.actions[rows[k]]
            np.add.at(g_action, acts, np.einsum("ci,cj->cij", g_u, b_in))
            carry = np.einsum("cji,cj->ci", f.action[acts], g_u)
            carry += np.einsum("cji,cj->ci", self._rest[rows[k]], g_v)
            carry[mode != 0] = 0.0  # a restart cuts the past off
        weights = self.weights[tape.first : tape.first + tape.m.shape[0]]
        g_shared = (weights.T @ g_m_rows).reshape(n_obs, r, r)
        return [g_shared, g_action, g_inf]


def refine_tpsr(
    model: TPSRModel,
    actions: np.ndarray,
    observations: np.ndarray,
    bounds: list[tuple[int, int]] | None = None,
    *,
    progress: Progress | None = None,
    sizing: Sizing | None = None,
) -> TPSRModel:
    """``model`` refined through its filter on a trajectory (module docstring).

    Args:
        model: a spectral TPSR whose ``config.refine_epochs`` (iterations of L-BFGS, one
            pass over the data each), ``refine_window``, ``refine_horizon`` and
            ``refine_pull`` say how.
        actions: ``(T,)`` action indices of the training trajectory.
        observations: ``(T, k)`` its observations.
        bounds: ``[start, stop)`` rows of its gap-free segments (default: one segment).
        progress: called with a line per iteration.
        sizing: the fit's sizing (:mod:`tpsr_ros.core.sizing`); where it sizes
            ``refine_epochs``, data too short for two windows give the model unrefined,
            with ``refine_epochs`` 0 in its config and ``fit_info["sized"]``, instead of a
            ``DataError``.

    Returns the refined model, whose ``fit_info["refinement"]`` records the held-out loss
    of the start (``..._spectral``: the spectral model with its carry) and of the result,
    the carry and its ``mu``, the iterations and the seconds taken; with ``refine_epochs``
    0, the model itself. BLAS runs on one thread: the search amplifies rounding, so the
    refined model would otherwise depend on the machine's thread count.

    """
    cfg = model.config
    if cfg.refine_epochs == 0:
        return model
    obs = np.asarray(observations, dtype=np.float64)
    acts = np.asarray(actions)
    if obs.ndim != 2 or acts.shape != (obs.shape[0],):
        raise DataError(
            "refinement needs actions (T,) and observations (T, k), not "
            f"{acts.shape} and {obs.shape}"
        )
    if sizing is not None and sizing.sizes("refine_epochs"):
        whole = bounds or [(0, obs.shape[0])]
        starts = _window_starts(whole, cfg.refine_window, cfg.refine_horizon)
        if (shortfall := _shortfall(starts.size, cfg)) is not None:
            info = dict(model.fit_info)
            info["sized"] = {**info.get("sized", {}), "refine_epochs": [cfg.refine_epochs, 0]}
            info["refinement_skipped"] = shortfall
            return replace(model, config=replace(cfg, refine_epochs=0), fit_info=info)
    with single_blas_thread():  # the search amplifies rounding: one thread, one result
        return _refine(model, acts, obs, bounds, progress)


def _refine(
    model: TPSRModel,
    acts: np.ndarray,
    obs: np.ndarray,
    bounds: list[tuple[int, int]] | None,
    progress: Progress | None,
) -> TPSRModel:
    """The search of :func:`refine_tpsr` on its validated arrays."""
    cfg = model.config
    begin = time.perf_counter()
    spectral = model
    carry, gain = chosen_carry(model, acts, obs, bounds)
    model, mu = carried(model, acts, obs, carry)
    start = factor_model(model)
    problem = RefineProblem(model, start, acts, obs, bounds or [(0, obs.shape[0])])
    before = problem.unexplained(start)
    start_restarts = problem.restarts(start)
    allowed = restart_allowance(max(problem.restarts(spectral), start_restarts))
    scales = group_scales(start, cfg.refine_scaling)
    best = {"theta": start.vector(), "held": before, "iteration": 0, "restarts": start_restarts}
    lowest = {"held": before, "iteration": 0}  # restarts or not: what patience counts from
    since = [0]

    def watch(intermediate_result: Any) -> None:
        theta = np.asarray(intermediate_result.x) * scales
        candidate = start.like(theta)
        held = problem.unexplained(candidate)
        since[0] += 1
        if np.isfinite(held) and held < lowest["held"]:
            lowest.update(held=held, iteration=since[0])
        if np.isfinite(held) and held < best["held"]:
            restarts = problem.restarts(candidate)
            if restarts <= allowed:  # a better prediction must not cost the filter restarts
                best.update(theta=theta.copy(), held=held, iteration=since[0], restarts=restarts)
        if progress is not None:
            progress(
                f"refinement {since[0]}/{cfg.refine_epochs}: held-out unexplained {held:.4f} "
                f"(start {before:.4f})"
            )
        if since[0] - int(lowest["iteration"]) >= PATIENCE:
            raise StopIteration

    def scaled_loss(u: np.ndarray) -> tuple[float, np.ndarray]:
        loss, grad = problem.loss_and_grad(u * scales)
        return loss, grad * scales

    minimize(
        scaled_loss,
        start.vector() / scales,
        jac=True,
        method="L-BFGS-B",
        callback=watch,
        options={"maxiter": int(cfg.refine_epochs), "maxcor": 20},
    )
    refined = start.like(np.asarray(best["theta"]))
    seconds = time.perf_counter() - begin
    info = dict(model.fit_info)
    info["refinement"] = {
        "iterations": since[0],
        "best_iteration": int(best["iteration"]),
        "carry": carry,
        **({"history_gain": round(gain, 6)} if gain is not None else {}),
        "carry_mu": mu,
        "scaling": cfg.refine_scaling,
        **({"past": problem.past} if problem.past else {}),
        "heldout_unexplained_spectral": round(before, 6),
        "heldout_unexplained": round(float(best["held"]), 6),
        "heldout_restarts_allowed": allowed,
        "heldout_restarts": int(best["restarts"]),
        "windows": int(problem.train_starts.size + problem.held_starts.size),
        "seconds": round(seconds, 3),
    }
    info["timings"] = {**info.get("timings", {}), "refinement": round(seconds, 6)}
    if best["iteration"] == 0:  # nothing qualified: the spectral model, not the start
        info["refinement"]["kept"] = "spectral"
        return replace(spectral, fit_info=info)
    return replace(problem.model_of(refined), fit_info=info)
