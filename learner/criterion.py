"""A held-out predictive criterion for TPSR fit parameters, from training data alone.

``learner tune`` must rank fit parameters without reward, ground truth or RL. A state is
good when it predicts the future: a predictive state *is* the expected future given the
past (guide 2.2), and for the planner it matters only up to an invertible linear map
(fitted Q with ``fqi.state_scaling=whiten`` is blind to such maps). So:

1. **Split** the trajectory by time: the candidate is fitted on the first
   ``1 - holdout`` of the steps; the rest is held out, never seen by the fit.
2. **Fixed targets**: the top ``feature_dim`` principal components of the raw
   observations of the training part (one PCA, independent of the candidate, so every
   candidate predicts the same numbers). The target of step ``s`` at horizon ``j`` is the
   components of ``o_{s+j}``, for ``j = 1..horizons``.
3. **States**: the candidate's filter tracks the held-out steps (from its start state at
   each segment; the first ``burn_in`` steps of a segment are not scored).
4. **Regression**: per first future action ``a_{s+1}``, an affine ridge regression from the
   *whitened* state to all targets, fitted on one half of the held-out steps and scored
   on the other (and swapped). Under exploration whose actions do not depend on the state
   (the random training policy), ``E[f(o_{s+j}) | b_s, a_{s+1}]`` is exactly linear in a
   predictive state for every feature ``f`` and horizon ``j`` (later actions are averaged
   over), so the regression is the right model class rather than a guess.
5. **Score**: held-out R^2 (``1 - SSE / SST`` pooled over components, so weighted by
   their variance), averaged over horizons. Higher is better; at most 1.
6. **Standard error** of the score, by a delete-one-block jackknife over contiguous blocks
   of scored steps (``se_blocks`` per fold, so ``2 * se_blocks`` blocks): the errors of
   neighbouring steps are correlated (the same robot pose, targets 1..k steps ahead that
   overlap), so steps are not independent samples, but blocks of a few hundred steps,
   much longer than the horizons and the pose's correlation time, nearly are; and the
   jackknife handles the ratio ``SSE / SST`` without a formula for it. The two folds x
   horizons are not used as replicates: the horizons of one state share its errors
   (strongly correlated) and two folds give one degree of freedom. Every candidate is
   scored on the same held-out steps and blocks, so the SE of the *difference* between
   two candidates comes from the same jackknife over their paired block replicates
   (:func:`paired_jackknife_se`): a hard stretch of held-out data lowers every candidate's
   score and cancels out of the difference. ``learner tune`` uses it for the
   one-standard-error rule (:mod:`learner.tune`).

Whitening the state with its own covariance (fitted on the regression's training half)
makes the score invariant to any invertible linear map of the states, so candidates whose
states differ in scale by orders of magnitude compete on what they predict, not on scale;
directions with variance below ``1e-10`` of the largest are dropped as numerically absent.
Whitened states farther than ``clip * sqrt(r)`` from the mean are pulled onto that sphere
(a rotation-invariant bound), so a filter that explodes on a few held-out steps is
penalised for those steps without its linear extrapolation swamping every other step.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from tpsr_ros.core.episodes import Trajectory, track_trajectory
from tpsr_ros.core.errors import ConfigError, DataError, TpsrError
from tpsr_ros.core.fields import option
from tpsr_ros.core.learn import fit_tpsr_trajectory
from tpsr_ros.core.planning import (
    FUTURE_FEATURES,
    FUTURE_HORIZONS,
    ObservationFeatures,
    future_targets,
)
from tpsr_ros.core.sizing import Sizing
from tpsr_ros.core.tpsr import TPSRConfig, TPSRModel, action_sums

__all__ = [
    "CriterionConfig",
    "HeldoutR2",
    "ObservationFeatures",
    "Score",
    "block_jackknife_se",
    "criterion_for",
    "future_targets",
    "jackknife_replicates",
    "paired_jackknife_se",
    "predictive_r2",
    "score_states",
    "score_tpsr",
    "split_trajectory",
]

RELATIVE_EIGENVALUE_FLOOR = 1e-10
"""State directions with less variance than this fraction of the largest are dropped."""


@dataclass(frozen=True)
class CriterionConfig:
    """How the held-out predictive criterion splits, predicts and scores."""

    holdout: float = option(0.25, "fraction of the steps (the last ones) held out of the fit")
    horizons: int = option(
        FUTURE_HORIZONS,
        "k: score predictions of the next 1..k observations (the planner's 1 / (1 - 0.9))",
    )
    feature_dim: int = option(
        FUTURE_FEATURES, "principal components of the observations to predict"
    )
    burn_in: int = option(20, "steps at the start of each held-out segment left unscored")
    ridge: float = option(1e-3, "ridge of the state-to-future regression (whitened units)")
    clip: float = option(
        3.0, "whitened states farther than clip * sqrt(dimensions) from the mean are pulled in"
    )
    se_blocks: int = option(
        10, "contiguous blocks of scored steps per fold for the jackknife standard error"
    )

    def __post_init__(self) -> None:
        if not 0.05 <= self.holdout <= 0.5:
            raise ConfigError(f"holdout must lie in [0.05, 0.5], not {self.holdout!r}")
        for name in ("horizons", "feature_dim", "se_blocks"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ConfigError(f"{name} must be a positive integer, not {value!r}")
        if isinstance(self.burn_in, bool) or not isinstance(self.burn_in, int) or self.burn_in < 0:
            raise ConfigError(f"burn_in must be a non-negative integer, not {self.burn_in!r}")
        if not (np.isfinite(self.ridge) and self.ridge >= 0):
            raise ConfigError(f"ridge must be a non-negative number, not {self.ridge!r}")
        if not (np.isfinite(self.clip) and self.clip > 0):
            raise ConfigError(f"clip must be a positive number, not {self.clip!r}")


@dataclass(frozen=True)
class HeldoutR2:
    """Held-out R^2 per horizon, its mean over horizons, and the mean's standard error.

    ``blocks`` ``(2, B, k)`` holds the summed squared errors and the summed squared
    deviations per block of scored steps and horizon (:func:`paired_jackknife_se`).
    """

    per_horizon: np.ndarray
    se: float
    blocks: np.ndarray | None = None

    @property
    def value(self) -> float:
        """The criterion: R^2 averaged over horizons."""
        return float(np.mean(self.per_horizon))


@dataclass(frozen=True)
class Score:
    """A candidate's criterion: ``value`` (mean held-out R^2, -inf when the fit failed).

    ``se`` is its jackknife standard error over blocks of held-out steps (inf when failed).
    """

    value: float
    per_horizon: tuple[float, ...] = ()
    se: float = np.inf
    seconds: float = 0.0
    error: str = ""
    details: dict[str, float] = field(default_factory=dict)
    blocks: np.ndarray | None = field(default=None, repr=False, compare=False)

    @property
    def ok(self) -> bool:
        """True when the candidate was fitted and scored."""
        return not self.error


MIN_SCORED_STEPS = 8
"""Fewest held-out steps a candidate is scored on (after the burn-in and the horizons)."""


def criterion_for(
    config: CriterionConfig, heldout_steps: int, step_seconds: float | None = None
) -> CriterionConfig:
    """``config``, its burn-in and horizons shortened when they would leave fewer than half
    of ``heldout_steps`` scored (a short robot log): each at most a quarter of them.

    A few hundred held-out steps keep the configured values. Fewer than
    :data:`MIN_SCORED_STEPS` scored steps even then are refused in one line, saying how
    many more steps (seconds, given ``step_seconds``) the recording needs.
    """

    def shortened(steps: int) -> CriterionConfig:
        if steps - config.burn_in - config.horizons >= steps / 2:
            return config
        return replace(
            config,
            burn_in=min(config.burn_in, steps // 4),
            horizons=min(config.horizons, max(1, steps // 4)),
        )

    def enough(steps: int) -> bool:
        chosen = shortened(steps)
        return steps - chosen.burn_in - chosen.horizons >= MIN_SCORED_STEPS

    steps = int(heldout_steps)
    if not enough(steps):
        needed = next(n for n in range(steps + 1, steps + 10 * MIN_SCORED_STEPS) if enough(n))
        more = int(np.ceil(needed / config.holdout - steps / config.holdout))
        extra = "" if step_seconds is None else f", {more * step_seconds:.0f} s"
        raise DataError(
            f"{steps} held-out steps are too few to score a candidate (at least "
            f"{MIN_SCORED_STEPS} after a burn-in and the horizons): record at least {more} "
            f"more steps{extra}"
        )
    return shortened(steps)


def split_trajectory(trajectory: Trajectory, holdout: float) -> tuple[Trajectory, Trajectory]:
    """``(training part, held-out part)``: the first ``1 - holdout`` of the steps, the rest."""
    cut = round(len(trajectory) * (1.0 - holdout))
    if cut < 2 or len(trajectory) - cut < 2:
        raise DataError(
            f"{len(trajectory)} steps are too few to hold out {holdout:.0%} of them for tuning"
        )
    return trajectory.rows(0, cut), trajectory.rows(cut, len(trajectory))


def _state_whitener(fit_states: np.ndarray, clip: float) -> Callable[[np.ndarray], np.ndarray]:
    """Whiten states with the mean and covariance of ``fit_states`` and pull outliers in.

    Rows farther than ``clip * sqrt(r')`` from the mean (in whitened units) are scaled back
    onto that sphere: a norm, so orthogonal maps (and thus any invertible linear map of
    the raw states) leave the result unchanged. Like the planner's RBF features, which
    fade to zero far from every centre, a rare exploded state then costs a bounded error
    instead of dominating the score through unbounded linear extrapolation.
    """
    mean = fit_states.mean(axis=0)
    cov = np.cov(fit_states - mean, rowvar=False).reshape(fit_states.shape[1], -1)
    values, vectors = np.linalg.eigh(cov)
    largest = float(values[-1]) if values.size else 0.0
    if not largest > 0:
        raise DataError("the tracked states do not vary")
    keep = values > RELATIVE_EIGENVALUE_FLOOR * largest
    matrix = vectors[:, keep] / np.sqrt(values[keep])
    radius = clip * np.sqrt(matrix.shape[1])

    def whiten(states: np.ndarray) -> np.ndarray:
        white: np.ndarray = (states - mean) @ matrix
        norms = np.linalg.norm(white, axis=1, keepdims=True)
        white *= np.minimum(1.0, radius / np.maximum(norms, 1e-300))
        return white

    return whiten


def _ridge_by_action(
    inputs: np.ndarray, actions: np.ndarray, targets: np.ndarray, n_actions: int, ridge: float
) -> np.ndarray:
    """Per-action affine ridge weights ``(n_actions, 1 + p, q)``; the intercept is free."""
    n, p = inputs.shape
    design = np.concatenate([np.ones((n, 1)), inputs], axis=1)
    counts = np.bincount(actions, minlength=n_actions)
    grams = action_sums(design, design, actions, counts)  # one product per action
    moments = action_sums(design, targets, actions, counts)
    penalty = np.eye(p + 1)
    penalty[0, 0] = 0.0
    grams += (ridge * np.maximum(counts, 1.0) + 1e-12)[:, None, None] * penalty
    grams[counts == 0, 0, 0] = 1.0  # unseen action: predicts 0 (scored against the mean)
    weights: np.ndarray = np.linalg.solve(grams, moments)
    return weights


def jackknife_replicates(sse: np.ndarray, sst: np.ndarray) -> np.ndarray:
    """``theta_-b`` ``(B,)``: ``mean_k (1 - SSE_k / SST_k)`` recomputed without block ``b``.

    ``sse`` and ``sst`` are per-block sums ``(B, k)``; NaN where a replicate is undefined.
    """
    left_sse = sse.sum(axis=0) - sse
    left_sst = sst.sum(axis=0) - sst
    with np.errstate(divide="ignore", invalid="ignore"):
        theta: np.ndarray = np.mean(1.0 - left_sse / left_sst, axis=1)
    return theta


def _jackknife_se(theta: np.ndarray) -> float:
    """``sqrt((B - 1) / B * sum_b (theta_-b - mean theta_-)^2)``; inf when undefined."""
    blocks = theta.shape[0]
    if blocks < 2 or not np.isfinite(theta).all():
        return float("inf")
    return float(np.sqrt((blocks - 1) / blocks * np.sum((theta - theta.mean()) ** 2)))


def block_jackknife_se(sse: np.ndarray, sst: np.ndarray) -> float:
    """Standard error of ``mean_k (1 - SSE_k / SST_k)`` from per-block sums ``(B, k)``.

    Delete-one-block jackknife: ``sqrt((B - 1) / B * sum_b (theta_-b - mean theta_-)^2)``,
    where ``theta_-b`` is the criterion recomputed without block ``b`` (Efron & Tibshirani,
    An Introduction to the Bootstrap, 11.5; blocks for dependent data: Kuensch 1989).
    """
    return _jackknife_se(jackknife_replicates(sse, sst))


def paired_jackknife_se(a: np.ndarray, b: np.ndarray) -> float:
    """Standard error of the difference of two criteria scored on the same blocks.

    ``a`` and ``b`` are :attr:`HeldoutR2.blocks` ``(2, B, k)`` of two candidates; the
    jackknife runs over the differences of their paired replicates ``theta_-b``. Blocks
    of unequal shape cannot be paired: inf.
    """
    if a.shape != b.shape:
        return float("inf")
    return _jackknife_se(jackknife_replicates(*a) - jackknife_replicates(*b))


def predictive_r2(
    states: np.ndarray,
    next_actions: np.ndarray,
    targets: np.ndarray,
    scored: np.ndarray,
    n_actions: int,
    ridge: float,
    clip: float = 3.0,
    se_blocks: int = 10,
) -> HeldoutR2:
    """Two-fold held-out R^2 per horizon of predicting ``targets (T, k, d)`` from ``states``.

    Rows with ``scored`` False are neither fitted nor scored; the scored rows are split
    into their first and second halves in time, each fitted on one and scored on the other.
    The errors are summed per contiguous block (``se_blocks`` per half) for the standard
    error of the mean over horizons (:func:`block_jackknife_se`).
    """
    rows = np.flatnonzero(scored)
    if rows.size < 4:
        raise DataError(f"only {rows.size} held-out steps can be scored; hold out more steps")
    horizons, d = targets.shape[1], targets.shape[2]
    halves = np.array_split(rows, 2)
    block_sse, block_sst = [], []
    flat = targets.reshape(len(targets), horizons * d)
    for fit_rows, test_rows in ((halves[0], halves[1]), (halves[1], halves[0])):
        whiten = _state_whitener(states[fit_rows], clip)
        weights = _ridge_by_action(
            whiten(states[fit_rows]), next_actions[fit_rows], flat[fit_rows], n_actions, ridge
        )
        design = np.concatenate([np.ones((test_rows.size, 1)), whiten(states[test_rows])], axis=1)
        predicted = np.einsum("np,npq->nq", design, weights[next_actions[test_rows]])
        error = (flat[test_rows] - predicted).reshape(-1, horizons, d)
        spread = targets[test_rows] - targets[test_rows].mean(axis=0)
        # per-step sums over components, then per contiguous block of steps
        step_sse = np.einsum("nkd,nkd->nk", error, error)
        step_sst = np.einsum("nkd,nkd->nk", spread, spread)
        blocks = min(se_blocks, test_rows.size)
        starts = np.arange(blocks) * test_rows.size // blocks
        block_sse.append(np.add.reduceat(step_sse, starts, axis=0))
        block_sst.append(np.add.reduceat(step_sst, starts, axis=0))
    sse, sst = np.concatenate(block_sse), np.concatenate(block_sst)
    r2: np.ndarray = 1.0 - sse.sum(axis=0) / sst.sum(axis=0)
    return HeldoutR2(r2, block_jackknife_se(sse, sst), np.stack([sse, sst]))


def score_states(
    states: np.ndarray,
    heldout: Trajectory,
    features: ObservationFeatures,
    config: CriterionConfig,
) -> HeldoutR2:
    """Held-out R^2 per horizon (and its SE) of states ``(T, r)`` tracked over ``heldout``."""
    if not np.isfinite(states).all():
        raise DataError("the tracked states hold non-finite values")
    targets, valid = future_targets(
        features.transform(heldout.observations), heldout.segments, config.horizons
    )
    since_start = np.arange(len(heldout)) - np.searchsorted(
        heldout.segments, heldout.segments, side="left"
    )
    scored = valid & (since_start >= config.burn_in)
    next_actions = np.zeros(len(heldout), dtype=np.int64)
    next_actions[:-1] = heldout.actions[1:]
    return predictive_r2(
        states, next_actions, targets, scored, heldout.n_actions, config.ridge, config.clip,
        config.se_blocks,
    )


def score_tpsr(
    tpsr: TPSRConfig,
    train: Trajectory,
    heldout: Trajectory,
    features: ObservationFeatures,
    config: CriterionConfig,
    *,
    sizing: Sizing | None = None,
) -> tuple[Score, TPSRModel | None]:
    """Fit ``tpsr`` on ``train``, track ``heldout``, score; a failed fit scores -inf.

    ``sizing`` as in :func:`~tpsr_ros.core.learn.fit_tpsr_trajectory` (with it the fit
    holds the rank to the singular values the data support); None: ``tpsr`` as given.
    """
    start = time.perf_counter()
    try:
        model = fit_tpsr_trajectory(train, tpsr, sizing=sizing)
        states = track_trajectory(model, heldout).states
        r2 = score_states(states, heldout, features, config)
    except TpsrError as exc:
        message = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        return Score(-np.inf, seconds=time.perf_counter() - start, error=message), None
    score = Score(
        r2.value,
        per_horizon=tuple(float(v) for v in r2.per_horizon),
        se=r2.se,
        seconds=time.perf_counter() - start,
        blocks=r2.blocks,
    )
    return score, model
