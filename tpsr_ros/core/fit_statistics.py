"""A TPSR refit as statistics that merge: one pass over the data, ``merge``, decay, ``solve``.

On a frozen :class:`~tpsr_ros.core.fit_basis.FitBasis` (whitenings, kernel centres and the
:class:`~tpsr_ros.core.fit_basis.Sketch` of a first fit's ``P_TH``) every quantity
Algorithm 3 needs is a sum over training episodes of a fixed size, once the features are
projected on the sketch (``Q_T``, ``Q_H``: its test and history bases):

- ``sum w``, ``sum w^2`` (the weight and the effective number of episodes),
- ``sum w phi_H`` (eq. 3.1, ``l_H + 1``),
- ``sum w Q_T^T phi_T0 phi_H^T Q_H`` (eq. 3.2 on the sketch, ``w x w``),
- per action ``a``: ``sum w`` and ``sum w phi_O[o'] outer(Q_T^T phi_T, Q_H^T phi_H)`` (eq. 3.3
  on the sketch, ``l_O x w x w``); with every action's operators pooled (``action_pooling``
  1, the default preset) only their total, which is all the pooled operators need.

Sums of disjoint data add (:meth:`FitStatistics.merge`), so a stream, chunks or a cluster
reduce to ``reduce(merge, map(partial_fit, chunks))``; multiplying every sum by ``lambda``
(:meth:`FitStatistics.decayed`) forgets old data exponentially, so the sums follow a world
that changes. :meth:`FitStatistics.solve` then runs the rest of Algorithm 3 on the sums
alone: the SVD of the projected ``P_TH`` (``U = Q_T U~``, ``V = Q_H V~``), ``b_*``, ``b_inf``
and every ``B_ao'``, pooled as the config says, with the rank rule of the first fit on the
effective number of episodes. When the sketch spans ``P_TH``'s whole range the model is
exactly the two-pass fit's (``tests/test_fit_statistics.py``); with the default margin
(:data:`~tpsr_ros.core.fit_basis.SKETCH_MARGIN`) its directions are the first fit's leading
ones, refined.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from tpsr_ros.core.action_features import standardised_codes
from tpsr_ros.core.errors import ConfigError, DataError
from tpsr_ros.core.fit_basis import FitBasis
from tpsr_ros.core.tpsr_config import TPSRConfig
from tpsr_ros.core.tpsr_model import TPSRModel, assemble_model
from tpsr_ros.core.tpsr_stages import (
    EXTRA_SINGULAR_VALUES,
    action_operators,
    action_sums,
    as_actions,
    check_action_counts,
    ht_features,
    independent_episodes,
    obs_features,
    start_and_normaliser,
    supported_rank,
    top_singular_triplets,
)
from tpsr_ros.core.whitened import EpisodeRows

__all__ = ["FitStatistics", "forgetting_weights"]

BLOCK_ROWS = 2048
"""Episodes whose features are held at once (``BLOCK_ROWS x l`` floats per feature)."""


def forgetting_weights(ages: np.ndarray, forgetting: float) -> np.ndarray:
    """``forgetting ** age`` per episode (``age``: steps since the newest; 1: no forgetting)."""
    if not 0.0 < forgetting <= 1.0:
        raise ConfigError(f"forgetting must lie in (0, 1], not {forgetting}")
    return np.power(float(forgetting), np.asarray(ages, dtype=np.float64))


@dataclass(frozen=True, eq=False)
class FitStatistics:
    """The sums of a refit on ``basis`` (module docstring), for ``n_actions`` actions.

    ``codes``: the standardised action codes of action-aware features (None without them).
    Create with :meth:`empty`, add data with :meth:`partial_fit`; every method returns a
    new object and leaves its operands as they were.
    """

    basis: FitBasis
    n_actions: int
    codes: np.ndarray | None
    weight: float
    weight_sq: float
    history_sum: np.ndarray
    p_th: np.ndarray
    counts: np.ndarray
    b_sums: np.ndarray

    @classmethod
    def empty(
        cls, basis: FitBasis, n_actions: int, action_codes: np.ndarray | None = None
    ) -> FitStatistics:
        """No data yet (``action_codes``: the actions' commands, as in ``run_fit``)."""
        if basis.sketch is None:
            raise ConfigError(
                "the basis keeps no sketch of P_TH (a model saved before sketches were "
                "kept): refit it from its steps, or fit it anew"
            )
        if int(n_actions) < 1:
            raise ConfigError(f"n_actions must be at least 1, not {n_actions}")
        cfg = basis.config
        codes = standardised_codes(action_codes, n_actions) if cfg.uses_actions else None
        w, l_h, l_o = basis.sketch.width, cfg.ht_centers + 1, cfg.obs_centers
        groups = 1 if cfg.action_pooling == 1 else n_actions
        return cls(
            basis, int(n_actions), codes, 0.0, 0.0, np.zeros(l_h), np.zeros((w, w)),
            np.zeros(n_actions), np.zeros((groups, l_o, w, w)),
        )  # fmt: skip

    @property
    def episodes(self) -> float:
        """The effective number of episodes summed, ``(sum w)^2 / sum w^2`` (their count
        without forgetting)."""
        return self.weight**2 / self.weight_sq if self.weight_sq > 0 else 0.0

    def partial_fit(
        self, episodes: EpisodeRows, weights: np.ndarray | None = None
    ) -> FitStatistics:
        """These sums and those of ``episodes`` (each weighted by ``weights``, default 1)."""
        cfg, sketch, centres = self.basis.config, self.basis.sketch, self.basis.centres
        assert sketch is not None  # checked by empty()
        n = len(np.asarray(episodes.action))
        observation = np.asarray(episodes.observation)
        if observation.ndim != 2 or observation.shape[1] != self.basis.obs_size:
            size = observation.shape[1] if observation.ndim == 2 else observation.shape
            raise DataError(
                f"the data's observations hold {size} values, the basis whitens "
                f"{self.basis.obs_size}: refit only on data of the same camera and preprocessing"
            )
        action = as_actions(episodes.action, n, self.n_actions)
        weights = np.ones(n) if weights is None else np.asarray(weights, dtype=np.float64)
        if weights.shape != (n,) or not np.isfinite(weights).all() or (weights < 0).any():
            raise DataError(f"weights must be {n} finite non-negative values")
        rows = self.basis.whitenings(self.codes).rows(episodes, cfg)
        history_sum, p_th = self.history_sum.copy(), self.p_th.copy()
        counts, b_sums = self.counts.copy(), self.b_sums.copy()
        w = sketch.width
        for start in range(0, n, BLOCK_ROWS):
            block = rows.rows(start, min(n, start + BLOCK_ROWS))
            wt = weights[start : start + len(block)]
            phi_h = ht_features(block.history, centres.history, cfg)
            a_h = phi_h @ sketch.history
            a_t = ht_features(block.test, centres.test, cfg) @ sketch.test
            a_t0 = a_t if block.test0 is None else (
                ht_features(block.test0, centres.test, cfg) @ sketch.test
            )  # fmt: skip
            history_sum += wt @ phi_h
            p_th += (a_t0 * wt[:, None]).T @ a_h
            outer = (a_t[:, :, None] * a_h[:, None, :]).reshape(len(block), w * w)
            outer *= wt[:, None]
            acts = action[start : start + len(block)]
            phi_o = obs_features(block.observation, centres.observation, cfg)
            if self.b_sums.shape[0] == 1:  # pooled: every action's sum at once
                b_sums[0] += (phi_o.T @ outer).reshape(b_sums.shape[1:])
            else:
                sums = action_sums(phi_o, outer, acts, np.bincount(acts, minlength=self.n_actions))
                b_sums += sums.reshape(b_sums.shape)
            counts += np.bincount(acts, weights=wt, minlength=self.n_actions)
        return replace(
            self,
            weight=self.weight + float(weights.sum()),
            weight_sq=self.weight_sq + float(weights @ weights),
            history_sum=history_sum, p_th=p_th, counts=counts, b_sums=b_sums,
        )  # fmt: skip

    def merge(self, other: FitStatistics) -> FitStatistics:
        """The sums of both (statistics of disjoint data on the same basis)."""
        if other.basis is not self.basis and not _same_basis(self.basis, other.basis):
            raise ConfigError("statistics on different bases do not merge")
        if other.n_actions != self.n_actions:
            raise ConfigError(f"statistics of {self.n_actions} and {other.n_actions} actions")
        return replace(
            self,
            weight=self.weight + other.weight,
            weight_sq=self.weight_sq + other.weight_sq,
            history_sum=self.history_sum + other.history_sum,
            p_th=self.p_th + other.p_th,
            counts=self.counts + other.counts,
            b_sums=self.b_sums + other.b_sums,
        )

    def decayed(self, factor: float) -> FitStatistics:
        """Every sum times ``factor`` (``factor = lambda ** steps``: data that many steps older)."""
        if not 0.0 <= factor <= 1.0:
            raise ConfigError(f"a decay factor lies in [0, 1], not {factor}")
        return replace(
            self,
            weight=self.weight * factor,
            weight_sq=self.weight_sq * factor**2,
            history_sum=self.history_sum * factor,
            p_th=self.p_th * factor,
            counts=self.counts * factor,
            b_sums=self.b_sums * factor,
        )

    def solve(self, rank: int | None = None) -> TPSRModel:
        """The TPSR of the sums (Algorithm 3's SVD and parameters; no pass over data).

        ``rank``: the state dimension asked (default the basis's), lowered to what the
        effective number of episodes supports by the first fit's rank rule.
        """
        cfg: TPSRConfig = self.basis.fit_config(rank)
        if self.weight <= 0:
            raise DataError("the statistics hold no episodes to solve")
        check_action_counts(self.counts)
        sketch = self.basis.sketch
        assert sketch is not None  # checked by empty()
        p_th = self.p_th / self.weight
        n_sv = min(cfg.rank + EXTRA_SINGULAR_VALUES, sketch.width)
        u_s, s_all, v_s = top_singular_triplets(p_th, n_sv, seed=cfg.seed)
        tol = max(p_th.shape) * np.finfo(np.float64).eps * float(s_all[0])
        usable = int(np.count_nonzero(s_all > tol))
        episodes = self.episodes
        independent = independent_episodes(round(episodes), cfg)  # what the rank rule counts
        supported = supported_rank(s_all, independent, usable)
        r = min(cfg.rank, supported)
        cfg = replace(cfg, rank=r)
        u_s, s, v_s = u_s[:, :r], s_all[:r].copy(), v_s[:, :r]
        v = sketch.history @ v_s
        b_star, b_inf = start_and_normaliser(self.history_sum / self.weight, s, v)
        # B_ao' = U~^T (sum on the sketch) V~ S^-1, every action and observation centre at once
        sums = np.einsum("aoij,ik,jl->aokl", self.b_sums, u_s, v_s / s, optimize=True)
        n_obs = self.basis.centres.observation.shape[0]
        if sums.shape[0] == 1:  # pooled: the total over the total count, for every action
            pooled = sums[0] / self.counts.sum()
            big_b = np.repeat(pooled[None], self.n_actions, axis=0)
        else:
            big_b = action_operators(
                sums.reshape(self.n_actions, n_obs, r * r), self.counts.copy(), cfg.action_pooling
            ).reshape(self.n_actions, n_obs, r, r)
        basis = self.basis
        fit_info: dict[str, Any] = {
            "episodes": round(episodes),  # effective: their count without forgetting
            "training_episodes": round(episodes),
            "independent_episodes": independent,
            "samples_per_action": [round(float(c), 6) for c in self.counts],
            "usable_singular_values": usable,
            "supported_rank": supported,
            "from_statistics": {"sketch_width": sketch.width, "weight": round(self.weight, 6)},
        }
        model = assemble_model(
            replace(cfg, state_clip_quantile=0.0),
            (basis.history, basis.test, basis.obs),
            basis.centres.observation,
            (b_star, b_inf, big_b),
            s_all,
            fit_info,
        )
        return replace(model, basis=basis)


def _same_basis(first: FitBasis, second: FitBasis) -> bool:
    """Whether two bases hold the same arrays (statistics of both then merge)."""
    a, b = first.to_arrays(), second.to_arrays()
    return a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)
