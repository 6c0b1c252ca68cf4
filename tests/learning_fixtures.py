"""Shared helpers for the learning tests: a small POMDP, its exact filter, a literal Algorithm 3.

Imported by the test modules (``from learning_fixtures import ...``; pytest puts ``tests/``
on ``sys.path``). Nothing here is a fixture registered with pytest, so it cannot clash with
other engineers' ``conftest.py``.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class POMDP:
    """Discrete POMDP: ``T[a]`` is ``(S, S)`` column-stochastic (``T[a][s', s]``),
    ``O`` is ``(n_obs, S)`` column-stochastic (``O[o, s]``); actions are uniform."""

    T: np.ndarray
    O: np.ndarray  # noqa: E741 - the textbook name

    @property
    def n_actions(self) -> int:
        return int(self.T.shape[0])

    @property
    def n_obs(self) -> int:
        return int(self.O.shape[0])

    @property
    def n_states(self) -> int:
        return int(self.O.shape[1])

    def stationary(self) -> np.ndarray:
        """Stationary state distribution under uniformly random actions."""
        tbar = self.T.mean(axis=0)
        w, v = np.linalg.eig(tbar)
        pi = np.real(v[:, np.argmax(np.real(w))])
        return pi / pi.sum()

    def sample(self, steps: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """A stationary random-action run: observation symbols and actions, both ``(steps,)``."""
        rng = np.random.default_rng(seed)
        actions = rng.integers(self.n_actions, size=steps)
        cum_t = np.cumsum(self.T, axis=1)  # (A, S', S): cumulative over s'
        cum_o = np.cumsum(self.O, axis=0)
        u_t, u_o = rng.random(steps), rng.random(steps)
        s = int(rng.choice(self.n_states, p=self.stationary()))
        # np.searchsorted's left side on each (a, s) column, as bisect on plain floats: the same
        # states, without numpy's per-call cost in this step-by-step loop
        columns = [[cum_t[a, :, j].tolist() for j in range(self.n_states)]
                   for a in range(self.n_actions)]
        chain = []
        for a, u in zip(actions.tolist(), u_t.tolist(), strict=True):
            s = min(bisect.bisect_left(columns[a][s], u), self.n_states - 1)
            chain.append(s)
        states = np.array(chain, dtype=np.int64)
        obs = np.minimum((u_o[:, None] > cum_o[:, states].T).sum(axis=1), self.n_obs - 1)
        return obs, actions

    def predict(self, belief: np.ndarray, action: int) -> np.ndarray:
        """``P(o | belief, a)`` for every observation, ``(n_obs,)``."""
        return self.O @ (self.T[action] @ belief)

    def condition(self, belief: np.ndarray, action: int, obs: int) -> np.ndarray:
        """Exact Bayes filter step."""
        new = self.O[obs] * (self.T[action] @ belief)
        return new / new.sum()


def example_pomdp() -> POMDP:
    """3 hidden states, 2 actions, 4 observations; linear dimension 3."""
    T = np.array(
        [
            [[0.8, 0.1, 0.1], [0.1, 0.8, 0.1], [0.1, 0.1, 0.8]],  # a=0 mostly stays
            [[0.1, 0.1, 0.8], [0.8, 0.1, 0.1], [0.1, 0.8, 0.1]],  # a=1 rotates s -> s+1
        ]
    )  # T[a][s', s]: each column sums to 1
    O = np.array(  # noqa: E741
        [
            [0.7, 0.1, 0.1],
            [0.1, 0.7, 0.1],
            [0.1, 0.1, 0.6],
            [0.1, 0.1, 0.2],
        ]
    )
    return POMDP(T=T, O=O)


def one_hot(symbols: np.ndarray, n: int) -> np.ndarray:
    return np.eye(n)[symbols]


def episodes_from_symbols(obs: np.ndarray, actions: np.ndarray, n_obs: int):
    """Non-overlapping (history 1, current, test 1) episodes as one-hot arrays."""
    E = obs.shape[0] // 3
    o = one_hot(obs[: 3 * E], n_obs).reshape(E, 3, n_obs)
    return o[:, 0], o[:, 1], actions[: 3 * E].reshape(E, 3)[:, 1], o[:, 2]


def literal_algorithm3(phi_h, phi_t, phi_o, e, r, actions, action_list, phi_t_th=None):
    """Algorithm 3 of the guide as printed: columns are samples, line 14 per (a, o', i).

    phi_h: (l_H + 1, t), phi_t: (l_T + 1, t), phi_o: (l_O, t); returns U, s, V, b_star, b_inf, B
    with B[a][o'] (r, r). Signs follow the same svd_flip rule as the library so results match.
    ``phi_t_th`` (default ``phi_t``) are the test features used for P_TH in line 2.
    """
    phi_t_th = phi_t if phi_t_th is None else phi_t_th
    t = phi_h.shape[1]
    p_h = np.zeros(phi_h.shape[0])
    for i in range(t):  # line 1
        p_h += phi_h[:, i]
    p_h /= t
    p_th = np.zeros((phi_t.shape[0], phi_h.shape[0]))
    for i in range(t):
        p_th += np.outer(phi_t_th[:, i], phi_h[:, i])
    p_th /= t
    U, s, Vt = np.linalg.svd(p_th)  # line 2
    U, s, V = U[:, :r], s[:r], Vt[:r].T  # lines 3-6
    idx = np.argmax(np.abs(U), axis=0)
    signs = np.sign(U[idx, np.arange(r)])
    U, V = U * signs, V * signs
    S, S_inv = np.diag(s), np.diag(1.0 / s)  # lines 7-8
    b_star = S @ V.T @ e  # line 9
    b_inf = p_h @ V @ S_inv  # line 10
    B = {}
    for a in action_list:  # line 11
        Y = np.flatnonzero(actions == a)  # line 12
        B[a] = []
        for o in range(phi_o.shape[0]):  # line 13
            acc = np.zeros((r, r))
            for i in Y:  # line 14
                acc += U.T @ (np.outer(phi_t[:, i], phi_h[:, i]) * phi_o[o, i]) @ V @ S_inv
            B[a].append(acc / len(Y))
    return U, s, V, b_star, b_inf, B
