"""Algorithm 1's output as rows: a fit's three whitenings and the whitened episodes they give.

:class:`Whitenings` holds the whitenings of histories, tests (``d^H = d^T``) and current
observations (``d^O``), fitted on the data in memory or from merged moments, and the
standardised action codes of action-aware features. :meth:`Whitenings.rows` turns episodes
into :class:`WhitenedRows`, the only form of the data the later stages read: whitened
histories, tests and observations, the tests ``P_TH`` correlates (Boots et al.'s window,
when asked) and the current actions, with the steps' action codes joined where the config
asks for them (:mod:`tpsr_ros.core.action_features`). Every fit whitens through here, so
in-memory, streamed and distributed fits give the same rows.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from tpsr_ros.core.action_features import join_actions
from tpsr_ros.core.moments import Moments
from tpsr_ros.core.tpsr_config import TPSRConfig
from tpsr_ros.core.tpsr_stages import p_th_window_actions, whiten_test_window
from tpsr_ros.core.whitening import Whitening

__all__ = [
    "WHITENED_FIELDS",
    "ActionSums",
    "Centres",
    "EpisodeRows",
    "WhitenedRows",
    "Whitenings",
]


class EpisodeRows(Protocol):
    """Cut episodes as the whitening reads them (e.g. :class:`tpsr_ros.core.episodes.Episodes`)."""

    @property
    def history(self) -> np.ndarray: ...
    @property
    def observation(self) -> np.ndarray: ...
    @property
    def action(self) -> np.ndarray: ...
    @property
    def test(self) -> np.ndarray: ...
    @property
    def history_actions(self) -> np.ndarray | None: ...
    @property
    def test_actions(self) -> np.ndarray | None: ...


@dataclass(frozen=True, eq=False)
class WhitenedRows:
    """Whitened episodes: histories, tests, current observations, ``P_TH`` tests, actions."""

    history: np.ndarray
    test: np.ndarray
    observation: np.ndarray
    test0: np.ndarray | None
    """Tests of ``P_TH`` (None: ``test`` itself, the guide's ``after-current``)."""
    actions: np.ndarray

    def __len__(self) -> int:
        return int(self.actions.shape[0])

    @classmethod
    def concatenate(cls, parts: Sequence[WhitenedRows]) -> WhitenedRows:
        """The rows of ``parts``, one after the other."""
        return cls(**{
            name: None if getattr(parts[0], name) is None
            else np.concatenate([getattr(part, name) for part in parts])
            for name in WHITENED_FIELDS
        })  # fmt: skip

    def rows(self, start: int, stop: int) -> WhitenedRows:
        """Rows ``start:stop`` (views)."""
        return self._map(lambda array: array[start:stop])

    def copy(self) -> WhitenedRows:
        """In-memory copy (e.g. to send a block of a memory map to a worker)."""
        return self._map(np.array)

    def _map(self, function: Callable[[np.ndarray], np.ndarray]) -> WhitenedRows:
        """``function`` of every array (a missing ``test0`` stays missing)."""
        return WhitenedRows(**{
            name: None if (array := getattr(self, name)) is None else function(array)
            for name in WHITENED_FIELDS
        })  # fmt: skip


WHITENED_FIELDS = tuple(f.name for f in dataclasses.fields(WhitenedRows))
"""The arrays of :class:`WhitenedRows`, in order."""


@dataclass(frozen=True, eq=False)
class Whitenings:
    """Algorithm 1's three whitenings, and the action codes of action-aware features."""

    history: Whitening
    test: Whitening
    obs: Whitening
    codes: np.ndarray | None = None
    """Standardised action codes ``(n_actions, d)`` (None: no action-aware features)."""

    @classmethod
    def from_moments(
        cls,
        history: Moments,
        test: Moments,
        observation: Moments,
        cfg: TPSRConfig,
        codes: np.ndarray | None = None,
    ) -> Whitenings:
        """Whitenings of the data whose moments are given (a streamed fit's pass 1)."""
        return cls(
            Whitening.from_moments(history, cfg.ht_dim, what="histories"),
            Whitening.from_moments(test, cfg.ht_dim, what="tests"),
            Whitening.from_moments(
                observation, cfg.obs_dim, what="current observations", variance=cfg.obs_variance
            ),
            codes,
        )

    @classmethod
    def fit(
        cls, episodes: EpisodeRows, cfg: TPSRConfig, codes: np.ndarray | None = None
    ) -> tuple[Whitenings, WhitenedRows]:
        """Whitenings fitted on episodes in memory, and those episodes' rows."""
        wh_h, h_white = Whitening.fit_transform(episodes.history, cfg.ht_dim, what="histories")
        wh_t, t_white = Whitening.fit_transform(episodes.test, cfg.ht_dim, what="tests")
        wh_o, o_white = Whitening.fit_transform(
            episodes.observation, cfg.obs_dim, what="current observations",
            variance=cfg.obs_variance,
        )  # fmt: skip
        whitenings = cls(wh_h, wh_t, wh_o, codes)
        return whitenings, whitenings.rows(episodes, cfg, (h_white, t_white, o_white))

    def rows(
        self,
        episodes: EpisodeRows,
        cfg: TPSRConfig,
        whitened: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    ) -> WhitenedRows:
        """The rows of ``episodes`` (``whitened``: their histories, tests and observations,
        already whitened by these whitenings).

        With ``p_th_tests="from-current"`` the test window of ``P_TH`` (the current
        observation and the first ``n - 1`` test observations) is whitened with the tests'
        whitening; with action weights the steps' action codes are joined.
        """
        if whitened is None:
            whitened = (
                self.history.transform(episodes.history),
                self.test.transform(episodes.test),
                self.obs.transform(episodes.observation),
            )
        h_white, t_white, o_white = whitened
        t0_white = None
        if cfg.p_th_tests == "from-current":
            t0_white = whiten_test_window(
                self.test, episodes.observation, episodes.test, cfg.test_length
            )
        action = np.asarray(episodes.action, dtype=np.int64)
        if cfg.uses_actions:
            assert self.codes is not None, "action-aware features need the action codes"
            codes, w_h, w_t = self.codes, cfg.history_action_weight, cfg.test_action_weight
            h_white = join_actions(h_white, episodes.history_actions, codes, w_h, "history")
            t_white = join_actions(t_white, episodes.test_actions, codes, w_t, "test")
            if t0_white is not None:
                window = p_th_window_actions(action, episodes.test_actions, cfg.test_length)
                t0_white = join_actions(t0_white, window, codes, w_t, "test")
        return WhitenedRows(h_white, t_white, o_white, t0_white, action)

    def widths(self, cfg: TPSRConfig) -> dict[str, int]:
        """Columns of each array of :class:`WhitenedRows` (action codes included)."""
        code = 0 if self.codes is None else int(self.codes.shape[1])
        history = self.history.n_components + (
            cfg.history_length * code if cfg.history_action_weight > 0 else 0
        )
        test = self.test.n_components + (
            cfg.test_length * code if cfg.test_action_weight > 0 else 0
        )
        widths = {"history": history, "test": test, "observation": self.obs.n_components}
        if cfg.p_th_tests == "from-current":
            widths["test0"] = test
        return widths


@dataclass(frozen=True, eq=False)
class Centres:
    """Kernel centres (whitened): histories ``(l_H, d_H)``, tests, observations ``(l_O, d_O)``."""

    history: np.ndarray
    test: np.ndarray
    observation: np.ndarray


@dataclass(eq=False)
class ActionSums:
    """Per action: training samples and ``sum phi_O[i, o'] outer(A_T[i], A_H[i])``."""

    counts: np.ndarray
    sums: np.ndarray

    @classmethod
    def zeros(cls, n_actions: int, n_obs_centres: int, rank: int) -> ActionSums:
        """Empty sums ``(n_actions, l_O, r^2)``."""
        counts = np.zeros(n_actions, dtype=np.int64)
        return cls(counts, np.zeros((n_actions, n_obs_centres, rank**2)))

    def merged(self, other: ActionSums) -> ActionSums:
        """Return a new :class:`ActionSums` of both."""
        return ActionSums(self.counts + other.counts, self.sums + other.sums)
