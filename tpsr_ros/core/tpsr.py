"""TPSR batch learning with RBF features: guide Algorithm 3 (section 3.2), eqs. 3.1-3.7.

From episodes (history, current action-observation pair, test; guide section 3.1) the fit

1. whitens histories, tests and current observations (Algorithm 1, :mod:`tpsr_ros.core.whitened`),
2. chooses kernel centres and computes the feature matrices (Algorithm 2,
   :mod:`tpsr_ros.core.features`): ``phi_H`` and ``phi_T`` with the constant feature, ``phi_O``
   normalised (with ``obs_effective_centres``, ``sigma^O`` widened first until the median
   observation's weights spread over that many centres: :mod:`tpsr_ros.core.kernel_width`),
3. estimates ``P_H`` (eq. 3.1) and ``P_TH`` (eq. 3.2), normalised by ``1/t``,
4. takes the compact rank-``r`` SVD ``P_TH ~ U S V^T``,
5. computes ``b_* = S V^T e`` (eq. 3.5), ``b_inf^T = P_H^T V S^-1`` (eq. 3.6) and every
   ``B_ao' = U^T P_{T,ao',H} V S^-1`` (eqs. 3.3 and 3.7),

and, with ``state_clip_quantile > 0``, bounds the states of its training episodes
(:mod:`tpsr_ros.core.state_box`).

**One driver.** :func:`run_fit` runs these stages, in this order, for every fit; where the
data live is an *engine* (:class:`FitEngine`): :class:`MemoryEngine` holds the episodes'
arrays (:func:`fit_tpsr`), :class:`~tpsr_ros.core.streamed_fit.ChunkEngine` reads chunks of
data twice in bounded memory, and ``learner.distributed.DaskEngine`` runs the passes on a
Dask cluster. Every option works with every engine, and the models agree to rounding; the
in-memory engine computes each stage over all rows at once, exactly as this module always
has, so its models are bit for bit those of earlier versions.

Step 5 never forms a ``(l_T + 1) x (l_H + 1)`` matrix per sample as line 14 of the literal
Algorithm 3 does. Since ``U^T phi_T phi_H^T V S^-1`` factorises, each sample is projected
first: ``A_T = phi_T U`` (``t x r``) and ``A_H = phi_H V S^-1`` (``t x r``), and for each
action ``a`` with samples ``Y_a``::

    B_a[o', :, :] = 1/t_a * sum_{i in Y_a} phi_O[i, o'] * outer(A_T[i], A_H[i])

is one ``(l_O x t_a) @ (t_a x r^2)`` matrix product. The cost is ``O(t (l_T + l_H) r +
t l_O r^2)`` instead of ``O(t l_T l_H l_O)``.

The SVD: only ``P_TH``'s top singular triplets are needed, so for matrices larger than
:data:`~tpsr_ros.core.tpsr_stages.DENSE_SVD_LIMIT` they come from Lanczos iteration (ARPACK,
tolerance 0, fixed start vector); signs follow ``svd_flip``, so fits are reproducible.

One choice the guide leaves implicit is exposed as :attr:`TPSRConfig.p_th_tests`: which
test window ``P_TH`` correlates with the history. The guide (eq. 3.2 with the same
``phi_T`` as eq. 3.3) uses the test *after* the current pair (``"after-current"``); Boots et
al. (2011) use the test *starting at* the current pair (``"from-current"``). Only the latter
makes ``B_ao`` map a state to the state one step later under the same definition, so that
repeated updates stay exact (``tests/test_tpsr_known_answer.py`` shows both).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

import numpy as np

from tpsr_ros.core.action_features import standardised_codes
from tpsr_ros.core.errors import ConfigError, DataError
from tpsr_ros.core.fit_basis import FitBasis, Sketch
from tpsr_ros.core.kernel_width import median_effective_centres, widened_sigma
from tpsr_ros.core.sizing import Sizing, size_to_data
from tpsr_ros.core.state_box import box_episodes, episode_states, state_box
from tpsr_ros.core.tpsr_config import TPSRConfig
from tpsr_ros.core.tpsr_model import TPSRModel, assemble_model
from tpsr_ros.core.tpsr_stages import (
    Progress,
    Stopwatch,
    action_operators,
    action_sums,
    as_actions,
    check_action_counts,
    check_enough_episodes,
    ht_features,
    independent_episodes,
    kernel_centres,
    obs_features,
    pool_actions,
    projected_outer,
    rank_rule_refusal,
    start_and_normaliser,
    supported_rank,
    top_singular_triplets,
    training_start,
    truncated_svd,
)
from tpsr_ros.core.whitened import ActionSums, Centres, EpisodeRows, WhitenedRows, Whitenings
from tpsr_ros.core.whitening import check_finite_matrix

__all__ = [
    "BoxData",
    "EpisodeArrays",
    "FitEngine",
    "MemoryEngine",
    "Progress",
    "Survey",
    "TPSRConfig",
    "TPSRModel",
    "action_sums",
    "fit_tpsr",
    "fit_tpsr_episodes",
    "pool_actions",
    "run_fit",
    "top_singular_triplets",
]

BoxData = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
"""Episodes whose states set the state box: histories, history actions, actions, observations."""


@dataclass(frozen=True)
class Survey:
    """What an engine learnt of its data before the fit: sizes and descriptive counts."""

    episodes: int
    n_actions: int
    obs_size: int
    info: dict[str, Any] = field(default_factory=dict)
    """Entries for the model's ``fit_info`` (e.g. steps, segments, stamps of a stream)."""


class FitEngine(Protocol):
    """Where a fit's data live: the stages of :func:`run_fit` ask it for what they need.

    ``stages`` names the stages the engine times besides the shared ones: ``survey``
    (reading the data's sizes and, streamed, the whitening moments), ``rows`` (whitening
    every episode, when apart from fitting the whitenings) and ``features`` (computing
    features of every training row ahead of the sums); None: not a stage of its own.
    """

    stages: Mapping[str, str | None]

    def survey(self, cfg: TPSRConfig) -> Survey:
        """Check and count the data (a streamed engine's pass 1)."""

    def whitenings(self, cfg: TPSRConfig, codes: np.ndarray | None) -> Whitenings:
        """Fit Algorithm 1's whitenings (``codes``: standardised action codes, or None)."""

    def whiten(self, whitenings: Whitenings, cfg: TPSRConfig) -> None:
        """Whiten every episode (a streamed engine's pass 2)."""

    def centre_rows(self) -> WhitenedRows:
        """The whitened rows the kernel centres are chosen from (all, or the first)."""

    def action_counts(self, start: int, n_actions: int) -> np.ndarray:
        """Training episodes per current action over the rows ``start:``."""

    def features(self, start: int, centres: Centres, cfg: TPSRConfig) -> None:
        """Prepare the features of the rows ``start:`` (an engine may compute them later)."""

    def p_statistics(
        self, start: int, centres: Centres, cfg: TPSRConfig
    ) -> tuple[np.ndarray, np.ndarray, int]:
        """``P_H``, ``P_TH`` (eqs. 3.1, 3.2, normalised) and the training rows' count."""

    def parameter_sums(
        self,
        start: int,
        centres: Centres,
        svd: tuple[np.ndarray, np.ndarray, np.ndarray],
        cfg: TPSRConfig,
        n_actions: int,
    ) -> ActionSums:
        """The per-action sums of eqs. 3.3 and 3.7 over the rows ``start:``."""

    def box_data(self, indices: np.ndarray, cfg: TPSRConfig) -> BoxData:
        """The raw episodes ``indices`` (sorted), for the state box."""

    def info(self) -> dict[str, Any]:
        """Entries for ``fit_info`` once the fit is done."""


def run_fit(
    engine: FitEngine,
    config: TPSRConfig | None = None,
    *,
    progress: Progress | None = None,
    sizing: Sizing | None = None,
    action_codes: np.ndarray | None = None,
    basis: FitBasis | None = None,
) -> TPSRModel:
    """Algorithms 1-3 (and the state box) on the data of ``engine``, stage by stage.

    ``sizing`` sizes the centres, whitening dimensions and rank to the data
    (:mod:`tpsr_ros.core.sizing`; ``fit_info["sized"]`` records what changed), and holds
    the rank to the singular values of ``P_TH`` the training episodes support
    (:func:`~tpsr_ros.core.tpsr_stages.supported_rank`): a rank the sizing may change is
    lowered to them, a rank it keeps (set on purpose) above them is refused; without
    ``sizing`` the config is used as given;
    ``action_codes`` are the commands of the actions for action-aware features (default:
    the simulator's 25 velocity pairs);
    ``basis`` whitenings and kernel centres to keep (:mod:`tpsr_ros.core.fit_basis`; a
    refit): the fit runs with the basis's config (its sizes); a ``config`` given only
    says the rank, which ``sizing`` may lower by the rank rule. Every model carries the
    basis it was fitted with (``model.basis``).
    """
    cfg = config if config is not None else TPSRConfig()
    if basis is not None:
        cfg = basis.config if config is None else basis.fit_config(cfg.rank)
    watch = Stopwatch(progress)
    watch.stage(str(engine.stages["survey"]))
    survey = engine.survey(cfg)
    sized: dict[str, tuple[int, int]] = {}
    if basis is not None and survey.obs_size != basis.obs_size:
        raise DataError(
            f"the data's observations hold {survey.obs_size} values, the basis whitens "
            f"{basis.obs_size}: refit only on data of the same camera and preprocessing"
        )
    if sizing is not None and basis is None:
        cfg, sized = size_to_data(cfg, survey.episodes, survey.obs_size, sizing)
    check_enough_episodes(survey.episodes, cfg)
    n_actions = survey.n_actions
    codes = standardised_codes(action_codes, n_actions) if cfg.uses_actions else None
    watch.stage("whitening")
    if basis is None:
        whitenings = engine.whitenings(cfg, codes)
    else:
        whitenings = basis.whitenings(codes)
    if engine.stages.get("rows"):
        watch.stage(str(engine.stages["rows"]))
    engine.whiten(whitenings, cfg)
    watch.stage("kernel centres")
    first_fit = basis is None
    if basis is None:
        rows = engine.centre_rows()
        centres = Centres(*kernel_centres(rows.history, rows.test, rows.observation, cfg))
        cfg, kernel = _observation_kernel(cfg, rows.observation, centres.observation)
        chosen = replace(cfg, obs_dim=whitenings.obs.n_components)  # obs_variance's choice
        basis = FitBasis(chosen, whitenings.history, whitenings.test, whitenings.obs, centres)
    else:
        centres = basis.centres
    start = training_start(cfg)
    check_action_counts(engine.action_counts(start, n_actions))
    if engine.stages.get("features"):
        watch.stage(str(engine.stages["features"]))
    engine.features(start, centres, cfg)
    watch.stage("P-statistics")
    p_h, p_th, n_train = engine.p_statistics(start, centres, cfg)
    watch.stage("SVD")
    free_rank = sizing is not None and sizing.sizes("rank")
    u, s, v, s_all, usable = truncated_svd(p_th, cfg, refuse=not free_rank)
    if basis.sketch is None and first_fit:  # what a refit from sums projects on
        basis = replace(basis, sketch=Sketch.of(p_th, basis.config.rank, seed=cfg.seed))
    del p_th
    independent = independent_episodes(n_train, cfg)  # what the rank rule counts
    supported = supported_rank(s_all, independent, usable)
    if sizing is not None and cfg.rank > supported:  # the rank rule (tpsr_stages)
        if not sizing.sizes("rank"):
            raise DataError(rank_rule_refusal(cfg.rank, s_all, independent, usable))
        sized["rank"] = (sized.get("rank", (cfg.rank, 0))[0], supported)
        cfg = replace(cfg, rank=supported)
        u, v = np.ascontiguousarray(u[:, :supported]), np.ascontiguousarray(v[:, :supported])
        s = s[:supported].copy()
    watch.stage("parameters")
    b_star, b_inf = start_and_normaliser(p_h, s, v)
    sums = engine.parameter_sums(start, centres, (u, s, v), cfg, n_actions)
    big_b = action_operators(sums.sums, sums.counts, cfg.action_pooling)
    big_b = big_b.reshape(n_actions, centres.observation.shape[0], cfg.rank, cfg.rank)
    watch.stop()
    fit_info: dict[str, Any] = {
        "episodes": int(survey.episodes),
        **survey.info,
        "training_episodes": int(n_train),
        "independent_episodes": independent,
        "samples_per_action": sums.counts.tolist(),
        "usable_singular_values": usable,
        **({"supported_rank": supported} if sizing is not None else {}),
        "timings": {name: round(sec, 6) for name, sec in watch.timings.items()},
        **engine.info(),
        **({"obs_kernel": kernel} if first_fit else {}),
    }
    if sized:
        fit_info["sized"] = {name: list(change) for name, change in sized.items()}
    unclipped = replace(cfg, state_clip_quantile=0.0)
    model = assemble_model(
        unclipped,
        (whitenings.history, whitenings.test, whitenings.obs),
        centres.observation,
        (b_star, b_inf, big_b),
        s_all,
        fit_info,
    )
    model = replace(model, basis=basis)
    if cfg.state_clip_quantile == 0:
        return model
    watch = Stopwatch(progress)
    watch.stage("state box")
    history, history_actions, action, observation = engine.box_data(
        box_episodes(survey.episodes), cfg
    )
    states = episode_states(model, history, history_actions, action, observation)
    box = state_box(states, cfg.state_clip_quantile)
    watch.stop()
    model.fit_info["timings"].update({k: round(v, 6) for k, v in watch.timings.items()})
    clipped = replace(model.config, state_clip_quantile=cfg.state_clip_quantile)
    return replace(model, config=clipped, state_box=box)


@dataclass
class _Arrays:
    """Episodes' arrays as :class:`~tpsr_ros.core.whitened.EpisodeRows` reads them."""

    history: np.ndarray
    observation: np.ndarray
    action: np.ndarray
    test: np.ndarray
    history_actions: np.ndarray | None
    test_actions: np.ndarray | None


class MemoryEngine:
    """Episodes held in memory: every stage over all rows at once.

    ``history`` ``(E, m k)``, ``observation`` ``(E, k)``, ``action`` ``(E,)`` and ``test``
    ``(E, n k)`` as in :func:`fit_tpsr`; ``history_actions`` and ``test_actions`` are needed
    only by the options that read them (action-aware features, the state box).
    """

    stages: Mapping[str, str | None] = {"survey": "checking data", "features": "features"}

    def __init__(
        self,
        history: np.ndarray,
        observation: np.ndarray,
        action: np.ndarray,
        test: np.ndarray,
        n_actions: int,
        *,
        history_actions: np.ndarray | None = None,
        test_actions: np.ndarray | None = None,
    ) -> None:
        self._data = _Arrays(history, observation, action, test, history_actions, test_actions)
        self.n_actions = n_actions
        self._rows: WhitenedRows | None = None
        self._features: tuple[np.ndarray, ...] = ()

    def survey(self, cfg: TPSRConfig) -> Survey:
        """Validate the episodes (guide table 3.1) against the config: finite, shaped."""
        data = self._data
        observation = check_finite_matrix(data.observation, "current observations")
        n_episodes, k = observation.shape
        history = check_finite_matrix(data.history, "histories")
        test = check_finite_matrix(data.test, "tests")
        if history.shape != (n_episodes, cfg.history_length * k):
            raise DataError(
                f"histories have shape {history.shape}, expected ({n_episodes}, "
                f"{cfg.history_length} x {k}) for history_length {cfg.history_length}"
            )
        if test.shape != (n_episodes, cfg.test_length * k):
            raise DataError(
                f"tests have shape {test.shape}, expected ({n_episodes}, {cfg.test_length} x "
                f"{k}) for test_length {cfg.test_length}"
            )
        if int(self.n_actions) < 1:
            raise ConfigError(f"n_actions must be at least 1, not {self.n_actions}")
        action = as_actions(data.action, n_episodes, int(self.n_actions))
        history_actions = data.history_actions
        if cfg.state_clip_quantile > 0:
            history_actions = _box_actions(history_actions, n_episodes, self.n_actions, cfg)
        self._data = _Arrays(history, observation, action, test, history_actions, data.test_actions)
        return Survey(n_episodes, int(self.n_actions), k)

    def whitenings(self, cfg: TPSRConfig, codes: np.ndarray | None) -> Whitenings:
        """Whitenings fitted on the arrays (their rows kept for :meth:`whiten`)."""
        whitenings, self._rows = Whitenings.fit(self._data, cfg, codes)
        return whitenings

    def whiten(self, whitenings: Whitenings, cfg: TPSRConfig) -> None:
        """Whiten the rows with a basis's whitenings (:meth:`whitenings` whitened them as
        it fitted)."""
        if self._rows is None:
            self._rows = whitenings.rows(self._data, cfg)

    def centre_rows(self) -> WhitenedRows:
        """Every row."""
        assert self._rows is not None
        return self._rows

    def action_counts(self, start: int, n_actions: int) -> np.ndarray:
        """Training episodes per action."""
        return np.bincount(self._data.action[start:], minlength=n_actions)

    def features(self, start: int, centres: Centres, cfg: TPSRConfig) -> None:
        """``phi_H``, ``phi_T``, ``phi_T0`` and ``phi_O`` of every training row."""
        rows = self.centre_rows().rows(start, len(self._data.action))
        phi_h = ht_features(rows.history, centres.history, cfg)
        phi_t = ht_features(rows.test, centres.test, cfg)
        phi_t0 = phi_t if rows.test0 is None else ht_features(rows.test0, centres.test, cfg)
        phi_o = obs_features(rows.observation, centres.observation, cfg)
        self._features = (phi_h, phi_t, phi_t0, phi_o)

    def p_statistics(
        self, start: int, centres: Centres, cfg: TPSRConfig
    ) -> tuple[np.ndarray, np.ndarray, int]:
        """Eqs. 3.1 and 3.2 over ``t`` training rows: ``P_H`` and ``P_TH``."""
        phi_h, _, phi_t0, _ = self._features
        p_h = phi_h.mean(axis=0)  # eq. 3.1, (l_H + 1,)
        p_th = phi_t0.T @ phi_h  # eq. 3.2, (l_T + 1, l_H + 1)
        p_th /= phi_h.shape[0]
        return p_h, p_th, int(phi_h.shape[0])

    def parameter_sums(
        self,
        start: int,
        centres: Centres,
        svd: tuple[np.ndarray, np.ndarray, np.ndarray],
        cfg: TPSRConfig,
        n_actions: int,
    ) -> ActionSums:
        """Eqs. 3.3 and 3.7 unnormalised over every training row at once."""
        phi_h, phi_t, _, phi_o = self._features
        outer = projected_outer(phi_h, phi_t, svd)
        actions = self._data.action[start:]
        counts = np.bincount(actions, minlength=n_actions)
        sums = ActionSums(counts, action_sums(phi_o, outer, actions, counts))
        self._features = ()
        return sums

    def box_data(self, indices: np.ndarray, cfg: TPSRConfig) -> BoxData:
        """The episodes ``indices`` from the arrays."""
        data = self._data
        assert data.history_actions is not None  # checked by the survey
        return (
            data.history[indices],
            data.history_actions[indices],
            data.action[indices],
            data.observation[indices],
        )

    def info(self) -> dict[str, Any]:
        """Nothing beyond the shared entries."""
        return {}


def _observation_kernel(
    cfg: TPSRConfig, rows: np.ndarray, centres: np.ndarray
) -> tuple[TPSRConfig, dict[str, Any]]:
    """The fit's observation kernel: ``cfg`` with ``sigma_obs`` widened where
    ``obs_effective_centres`` asks (:mod:`tpsr_ros.core.kernel_width`), and what
    ``fit_info["obs_kernel"]`` records of it: the width and the median effective number of
    centres an observation's weights spread over (and the width given, where widened)."""
    if cfg.obs_effective_centres == 0:
        spread = median_effective_centres(rows, centres, cfg.sigma_obs)
        return cfg, {"sigma": cfg.sigma_obs, "effective_centres": round(spread, 3)}
    width, spread = widened_sigma(rows, centres, cfg.sigma_obs, cfg.obs_effective_centres)
    kernel: dict[str, Any] = {"sigma": width, "effective_centres": round(spread, 3)}
    if width != cfg.sigma_obs:
        kernel["sigma_given"] = cfg.sigma_obs
    return replace(cfg, sigma_obs=width), kernel


def _box_actions(
    history_actions: np.ndarray | None, n_episodes: int, n_actions: int, cfg: TPSRConfig
) -> np.ndarray:
    """The history actions the state box is tracked with, checked before the fit."""
    if history_actions is None:
        raise ConfigError("state_clip_quantile > 0 needs the history actions of the episodes")
    acts = np.asarray(history_actions)
    if acts.shape != (n_episodes, cfg.history_length) or acts.dtype.kind not in "iu":
        raise DataError(
            f"history actions of shape {acts.shape} and dtype {acts.dtype} are not integer "
            f"indices of {n_episodes} episodes of {cfg.history_length} history steps"
        )
    if acts.size and (acts.min() < 0 or acts.max() >= n_actions):
        raise DataError(f"history action indices must lie in 0 .. {n_actions - 1}")
    return acts


def fit_tpsr(
    history: np.ndarray,
    observation: np.ndarray,
    action: np.ndarray,
    test: np.ndarray,
    *,
    n_actions: int,
    config: TPSRConfig | None = None,
    progress: Progress | None = None,
    history_actions: np.ndarray | None = None,
    test_actions: np.ndarray | None = None,
    action_codes: np.ndarray | None = None,
    sizing: Sizing | None = None,
    basis: FitBasis | None = None,
) -> TPSRModel:
    """Learn a TPSR from ``E`` episodes in memory (guide Algorithms 1-3; :func:`run_fit`).

    Args:
        history: ``(E, m k)`` observations of each history, oldest first, concatenated.
        observation: ``(E, k)`` current observation of each episode.
        action: ``(E,)`` current action indices in ``0 .. n_actions - 1``.
        test: ``(E, n k)`` observations of each test, concatenated.
        n_actions: number of actions; every action must occur among the training episodes.
        config: parameters (default :class:`TPSRConfig`).
        progress: called with the name of each stage as it starts.
        history_actions: ``(E, m)`` action of each history step (the one that led to its
            observation); needed only with ``history_action_weight > 0`` or the state box.
        test_actions: ``(E, n)`` action of each test step; needed only with
            ``test_action_weight > 0``.
        action_codes: ``(n_actions, d)`` command of each action for action-aware features
            (default: the simulator's 25 velocity pairs).
        sizing: size the centres, whitening dimensions and rank to the data
            (:mod:`tpsr_ros.core.sizing`); the model's config and ``fit_info["sized"]``
            record what changed. None: the config's sizes as they are.
        basis: whitenings and kernel centres to keep (a refit; :func:`run_fit`).

    Raises:
        DataError: non-finite or inconsistent data, too few episodes for the kernel
            centres, rank above the usable singular values, an action without samples.
        ConfigError: action weights without the step actions or codes they need.

    """
    engine = MemoryEngine(
        history, observation, action, test, n_actions,
        history_actions=history_actions, test_actions=test_actions,
    )  # fmt: skip
    return run_fit(
        engine, config, progress=progress, sizing=sizing, action_codes=action_codes, basis=basis
    )


class EpisodeArrays(EpisodeRows, Protocol):
    """What :func:`fit_tpsr_episodes` reads (e.g. :class:`tpsr_ros.core.episodes.Episodes`):
    the rows the whitening reads, and the number of actions."""

    @property
    def n_actions(self) -> int: ...


def fit_tpsr_episodes(
    episodes: EpisodeArrays,
    *,
    config: TPSRConfig | None = None,
    progress: Progress | None = None,
    action_codes: np.ndarray | None = None,
    sizing: Sizing | None = None,
    basis: FitBasis | None = None,
) -> TPSRModel:
    """:func:`fit_tpsr` on the arrays of cut episodes (``action_codes``, ``sizing``,
    ``basis``: there)."""
    return fit_tpsr(
        episodes.history,
        episodes.observation,
        episodes.action,
        episodes.test,
        n_actions=episodes.n_actions,
        config=config,
        progress=progress,
        history_actions=episodes.history_actions,
        test_actions=episodes.test_actions,
        action_codes=action_codes,
        sizing=sizing,
        basis=basis,
    )
