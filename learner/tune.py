"""``learner tune BAG... -o CONFIG.yaml``: TPSR fit parameters from the training data alone.

No reward, no ground truth, no RL: candidates are ranked by the held-out predictive
criterion of :mod:`learner.criterion` (fit on the first 75 % of the steps, track the rest,
held-out R^2 of predicting the next 1..10 observations' principal components from the
whitened state). The search tries the guide's defaults, then data-driven kernel widths
(the median pairwise distance of the whitened observations and histories, on a seeded
sample), then walks a coarse grid one parameter at a time around the best so far
(observation whitening dimensions, widths, normalised features, action pooling, rank,
history/test length, P_TH window, centres, a finer width and rank, then the three ranks
below the best), within ``--budget`` seconds: a candidate is started only if the longest
one so far would still end within the budget.
The choice among the candidates tried follows the one-standard-error rule (Hastie,
Tibshirani & Friedman, The Elements of Statistical Learning, 7.10): the simplest
candidate (lowest rank, then fewest centres, then shortest histories/tests) whose
criterion lies within one standard error of the highest. The standard error is that of
the difference between the two, paired over the held-out blocks every candidate is
scored on (:func:`learner.criterion.paired_jackknife_se`), not the highest one's own:
noise that every candidate shares (a hard stretch of held-out data) does not make two
candidates indistinguishable. Every
candidate, its criterion and SE is printed and written into the config's ``tune.tried``
list; ``learner fit --config`` reads the file.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from learner.config_file import changed_parameters, describe, write_fit_config
from learner.criterion import (
    CriterionConfig,
    criterion_for,
    ObservationFeatures,
    Score,
    paired_jackknife_se,
    score_tpsr,
    split_trajectory,
)
from tpsr_ros.cli import positive_float, positive_int
from tpsr_ros.core.episodes import Trajectory, episode_starts, make_episodes
from tpsr_ros.core.errors import ConfigError, DataError, TpsrError
from tpsr_ros.core.features import median_distance
from tpsr_ros.core.learn import fit_tpsr_trajectory
from tpsr_ros.core.sizing import Sizing, describe_sizing, size_to_data
from tpsr_ros.core.tpsr_stages import singular_value_floor
from tpsr_ros.core.tpsr import TPSRConfig
from tpsr_ros.core.whitening import Whitening
from tpsr_ros.io.model_io import check_output_path

__all__ = [
    "DEFAULT_BUDGET",
    "Trial",
    "TuneResult",
    "complexity",
    "difference_se",
    "median_widths",
    "one_standard_error_choice",
    "register",
    "run",
    "tune",
]

DEFAULT_BUDGET = 300.0
WIDTH_FACTORS = (0.25, 0.5, 1.0, 2.0)
RANKS = (3, 5, 8, 12, 16)
CENTRES = (500, 1000, 2000)
REFINE_FACTORS = (0.7, 1.4)
POOLING = (0.0, 0.5, 1.0)
"""Shrinkage of the per-action operators toward their pooled mean (``action_pooling``)."""
OBS_VARIANCE = (0.0, 0.95)
"""Observation whitening: the base's ``d^O``, or the dimensions keeping 95 % of the variance
(``obs_variance``; docs/results.md, "Observation whitening dimensions")."""
MESSAGE_CHARS = 200
"""A candidate's failure is said in at most this many characters (:func:`brief`)."""
AS_GIVEN = Sizing(f.name for f in dataclasses.fields(TPSRConfig))
"""Every size as given (as ``learner fit --config`` fits a tuned config): the fit holds
the rank to the supported singular values by refusing a candidate above them."""
LOWER_RANKS = 3
"""The last stage tries this many ranks below the best at its other parameters, so the
one-standard-error rule compares simpler candidates that differ from the best in rank only."""

Clock = Callable[[], float]
Report = Callable[[str], None]


@dataclass(frozen=True)
class Trial:
    """One candidate: its parameters, the stage that proposed it, and its criterion."""

    config: TPSRConfig
    stage: str
    score: Score


def complexity(config: TPSRConfig) -> tuple[int, int, int, int]:
    """How complex a candidate is, for parsimony: rank, centres, then history + test length."""
    return (
        config.rank,
        config.ht_centers,
        config.obs_centers,
        config.history_length + config.test_length,
    )


def difference_se(trial: Trial, top: Trial) -> float:
    """Standard error of ``top``'s criterion minus ``trial``'s.

    Paired over their held-out blocks when both have them (:mod:`learner.criterion`);
    otherwise ``top``'s own standard error (the textbook rule's).
    """
    if trial is top:
        return 0.0
    a, b = trial.score.blocks, top.score.blocks
    if a is not None and b is not None and a.shape == b.shape:
        return paired_jackknife_se(b, a)
    return top.score.se


def one_standard_error_choice(trials: Sequence[Trial]) -> Trial:
    """The simplest trial whose criterion is within one SE of the highest (ESL 7.10).

    The SE is that of the difference to the highest (:func:`difference_se`); among
    equally simple trials within reach, the higher criterion wins. Failed trials never do.
    """
    fitted = [t for t in trials if t.score.ok]
    if not fitted:
        raise DataError("no candidate could be fitted")
    top = max(fitted, key=lambda t: t.score.value)

    def within_reach(trial: Trial) -> bool:
        se = difference_se(trial, top)
        return bool(np.isfinite(se) and trial.score.value >= top.score.value - se)

    within = [t for t in fitted if within_reach(t)]
    return min(within, key=lambda t: (complexity(t.config), -t.score.value))


@dataclass(frozen=True)
class TuneResult:
    """The chosen candidate (one-SE rule), the highest-scoring one, everything tried (in
    order), the median widths and why it stopped."""

    best: Trial
    top: Trial
    trials: tuple[Trial, ...]
    widths: dict[str, float]
    stopped: str
    seconds: float
    criterion: CriterionConfig = field(default_factory=CriterionConfig)


def median_widths(train: Trajectory, base: TPSRConfig, *, seed: int = 0) -> dict[str, float]:
    """Median pairwise distances of whitened current observations and histories.

    The whitenings are those a fit with ``base`` computes (``d^O`` and ``d^H``
    dimensions), on a seeded sample of at most 1000 episodes.
    """
    episodes = make_episodes(
        train, base.history_length, base.test_length, stride=base.episode_stride
    )
    obs = Whitening.fit(
        episodes.observation,
        base.obs_dim,
        what="current observations",
        variance=base.obs_variance,
    )
    hist = Whitening.fit(episodes.history, base.ht_dim, what="histories")
    return {
        "sigma_obs": median_distance(obs.transform(episodes.observation), seed=seed),
        "sigma_ht": median_distance(hist.transform(episodes.history), seed=seed),
    }


Changes = dict[str, Any]


def _stage_changes(
    widths: dict[str, float], episodes: int
) -> list[tuple[str, Callable[[TPSRConfig], list[Changes]]]]:
    """The coarse grid, one parameter per stage, each around the best config so far: each
    stage proposes changes to the best config (applied, and checked, by :func:`_candidates`)."""

    def replace_each(name: str, values: Sequence[Any]) -> Callable[[TPSRConfig], list[Changes]]:
        return lambda best: [{name: v} for v in values]

    def lengths(best: TPSRConfig) -> list[Changes]:
        return [{"history_length": k, "test_length": k} for k in (1, 2)]

    def centres(best: TPSRConfig) -> list[Changes]:
        usable = [c for c in CENTRES if c < episodes // 2]
        return [{"ht_centers": c, "obs_centers": c // 2} for c in usable]

    def refine(name: str) -> Callable[[TPSRConfig], list[Changes]]:
        return lambda best: [{name: float(getattr(best, name) * f)} for f in REFINE_FACTORS]

    def refine_rank(best: TPSRConfig) -> list[Changes]:
        return [
            {"rank": r} for r in (best.rank - 1, best.rank + 2) if 1 <= r <= best.ht_centers + 1
        ]

    def lower_ranks(best: TPSRConfig) -> list[Changes]:
        return [{"rank": r} for r in range(best.rank - 1, max(0, best.rank - 1 - LOWER_RANKS), -1)]

    def scaled(name: str) -> list[float]:
        return [f * widths[name] for f in WIDTH_FACTORS]

    return [
        ("observation dimensions", replace_each("obs_variance", OBS_VARIANCE)),
        ("history/test width", replace_each("sigma_ht", scaled("sigma_ht"))),
        ("observation width", replace_each("sigma_obs", scaled("sigma_obs"))),
        ("normalised features", replace_each("normalize_ht_features", (False, True))),
        ("action pooling", replace_each("action_pooling", POOLING)),
        ("rank", replace_each("rank", RANKS)),
        ("history/test length", lengths),
        ("P_TH window", replace_each("p_th_tests", ("after-current", "from-current"))),
        ("centres", centres),
        ("finer history/test width", refine("sigma_ht")),
        ("finer observation width", refine("sigma_obs")),
        ("finer rank", refine_rank),
        ("lower ranks", lower_ranks),
    ]


def _stages(
    widths: dict[str, float], episodes: int
) -> list[tuple[str, Callable[[TPSRConfig], list[TPSRConfig]]]]:
    """:func:`_stage_changes` applied to the best config (changes it cannot take left out)."""

    def applied(
        propose: Callable[[TPSRConfig], list[Changes]],
    ) -> Callable[[TPSRConfig], list[TPSRConfig]]:
        def configs(best: TPSRConfig) -> list[TPSRConfig]:
            found = [_applied(best, changes) for changes in propose(best)]
            return [c for c in found if isinstance(c, TPSRConfig)]

        return configs

    return [(name, applied(propose)) for name, propose in _stage_changes(widths, episodes)]


def _applied(config: TPSRConfig, changes: Changes) -> TPSRConfig | str:
    """``config`` with ``changes``, or why it cannot take them (one short line)."""
    try:
        return dataclasses.replace(config, **changes)
    except ConfigError as exc:
        return f"{_changes_text(changes)}: {brief(str(exc))}"


def _planned(widths: dict[str, float], episodes: int) -> int:
    """Upper bound on the number of candidates (for the progress bar)."""
    probe = TPSRConfig()
    return 2 + sum(len(propose(probe)) for _, propose in _stage_changes(widths, episodes))


def _candidates(
    base: TPSRConfig, widths: dict[str, float], episodes: int, best: Callable[[], TPSRConfig]
) -> Iterator[tuple[str, TPSRConfig | str]]:
    """The base (a preset's settings) first, median widths second, then each stage around
    the best: ``(stage, config)``, or ``(stage, reason)`` for changes no config can take.

    The base comes first so that a budget that allows one candidate returns a model no
    worse than an untuned fit: at the median observation width the filter of a `full`
    bag explodes (docs/results.md, "Tuning").
    """
    yield "base", base
    yield "median widths", dataclasses.replace(best(), **widths)  # the base as fitted
    for stage, propose in _stage_changes(widths, episodes):
        current = best()
        for changes in propose(current):
            yield stage, _applied(current, changes)


def _departures_text(config: TPSRConfig, base: TPSRConfig) -> str:
    """``sigma_ht=3.08 rank=5``: what ``config`` changes in ``base`` (``as the base``)."""
    changed = {
        f.name: getattr(config, f.name)
        for f in dataclasses.fields(config)
        if getattr(config, f.name) != getattr(base, f.name)
    }
    return _changes_text(changed) or "as the base"


def _changes_text(changes: Changes) -> str:
    return " ".join(
        f"{k}={v:.3g}" if isinstance(v, float) else f"{k}={v}" for k, v in changes.items()
    )


def brief(message: str, limit: int = MESSAGE_CHARS) -> str:
    """The first line of ``message``, cut to ``limit`` characters (an ellipsis marks a cut)."""
    line = message.strip().splitlines()[0] if message.strip() else "failed"
    return line if len(line) <= limit else line[: limit - 1].rstrip() + "\u2026"


@dataclass(frozen=True)
class Support:
    """What the training part of the data can carry, checked before a candidate is fitted.

    ``obs_size`` values per observation; ``max_rank``: the singular values of ``P_TH`` the
    base candidate's fit found supported (:func:`tpsr_ros.core.tpsr_stages.supported_rank`),
    None when unknown.
    """

    train: Trajectory
    obs_size: int
    max_rank: int | None = None

    def episodes(self, config: TPSRConfig) -> int:
        """Episodes ``config`` cuts from the training part."""
        return int(episode_starts(self.train, config.window_steps, config.episode_stride).size)

    def refusal(self, config: TPSRConfig) -> str | None:
        """Why the data cannot carry ``config`` (one short phrase), or None."""
        episodes = self.episodes(config)
        if episodes < 2:
            return f"no 2 episodes of {config.history_length} + 1 + {config.test_length} steps"
        _, changes = size_to_data(config, episodes, self.obs_size, Sizing())
        too_large = [f"{name} {old} > {new}" for name, (old, new) in changes.items()]
        if self.max_rank is not None and config.rank > self.max_rank:
            too_large.append(
                f"rank {config.rank} > the {self.max_rank} supported singular values of P_TH"
            )
        if not too_large:
            return None
        return f"{episodes} episodes cannot carry {', '.join(too_large)}"


def tune(
    trajectory: Trajectory,
    *,
    budget: float = DEFAULT_BUDGET,
    candidates: int | None = None,
    seed: int = 0,
    base: TPSRConfig | None = None,
    criterion: CriterionConfig | None = None,
    report: Report | None = None,
    progress: bool = False,
    clock: Clock = time.perf_counter,
    started: float | None = None,
) -> TuneResult:
    """Search fit parameters for ``trajectory`` within ``budget`` seconds (from ``started``)
    and at most ``candidates`` candidates (None: no count limit).

    ``report`` gets one line per candidate (parameters, criterion, best so far) and the
    reason the search stopped. The first candidate always runs, whatever the budget. A
    count limit makes the search reproducible whatever the machine's speed: with a budget
    long enough, the same data and seed give the same candidates and choice.
    """
    if candidates is not None and candidates < 1:
        raise ConfigError(f"candidates must be at least 1, not {candidates}")
    start = clock() if started is None else started
    say = report or (lambda _line: None)
    crit = criterion or CriterionConfig()
    base = dataclasses.replace(base or TPSRConfig(), seed=seed)
    train, heldout = split_trajectory(trajectory, crit.holdout)
    stamps = np.asarray(trajectory.stamps, dtype=np.float64)
    step_seconds = float(np.median(np.diff(stamps))) * 1e-9 if stamps.size > 1 else None
    sized_crit = criterion_for(crit, len(heldout), step_seconds)
    if sized_crit != crit:
        crit = sized_crit
        say(
            f"criterion sized to {len(heldout)} held-out steps: burn-in {crit.burn_in}, "
            f"horizons 1..{crit.horizons}"
        )
    features = ObservationFeatures.fit(train.observations, crit.feature_dim)
    support = Support(train, train.observations.shape[1])
    episodes = support.episodes(base)
    if episodes < 2:
        raise DataError(f"{len(train)} training steps cut into {episodes} episodes: too few to tune")
    base, sized = size_to_data(base, episodes, support.obs_size, Sizing())
    try:  # the rank the data support, from the sized base's P_TH (spectral fit only)
        probe = fit_tpsr_trajectory(train, dataclasses.replace(base, refine_epochs=0), sizing=Sizing())
    except TpsrError as exc:
        raise DataError(
            f"the base settings cannot be fitted on {len(train)} training steps ({brief(str(exc))})"
        ) from None
    n_train = int(probe.fit_info["independent_episodes"])  # what the rank rule counted
    support = dataclasses.replace(support, max_rank=int(probe.fit_info["supported_rank"]))
    if probe.config.rank < base.rank:
        sized["rank"] = (sized.get("rank", (base.rank, 0))[0], probe.config.rank)
        base = dataclasses.replace(base, rank=probe.config.rank)
    if sized:
        say(describe_sizing(episodes, sized, n_train if "rank" in sized else None))
    say(
        f"the data support rank {support.max_rank} at most (singular values of P_TH at least "
        f"{singular_value_floor(1.0, n_train):.2g} of the largest, {n_train} training "
        "episodes); candidates the data cannot carry are skipped"
    )
    try:
        widths = median_widths(train, base, seed=seed)  # whitened as the sized base whitens
    except DataError as exc:
        widths = {"sigma_obs": base.sigma_obs, "sigma_ht": base.sigma_ht}
        say(f"median widths unavailable ({brief(str(exc))}); the grid scales the base's")
    say(
        f"median widths: sigma_obs {widths['sigma_obs']:.3g}, sigma_ht {widths['sigma_ht']:.3g} "
        f"({len(train)} steps fitted, {len(heldout)} held out)"
    )
    trials: list[Trial] = []
    seen: set[TPSRConfig] = set()
    skipped: set[str] = set()
    stopped = "every candidate of the grid was tried"

    def best() -> Trial:
        return max(trials, key=lambda t: t.score.value)

    def best_config() -> TPSRConfig:
        return best().config if trials else base

    bar = tqdm(
        total=_planned(widths, episodes),
        unit="fit",
        desc="tune",
        disable=None if progress else True,  # None: only on a terminal
        file=sys.stderr,
    )
    for stage, candidate in _candidates(base, widths, episodes, best_config):
        reason = candidate if isinstance(candidate, str) else support.refusal(candidate)
        if reason is not None:
            if reason not in skipped:  # the data cannot carry it: not fitted, said once
                skipped.add(reason)
                say(f"skipped ({stage}): {reason}")
            continue
        assert not isinstance(candidate, str)
        if candidate in seen:
            continue
        if candidates is not None and len(trials) >= candidates:
            stopped = f"the limit of {candidates} candidate(s) was reached"
            break
        elapsed = clock() - start
        longest = max((t.score.seconds for t in trials), default=0.0)
        if trials and elapsed + longest > budget:
            stopped = (
                f"budget of {budget:g} s reached after {len(trials)} candidate(s) "
                f"({elapsed:.1f} s; the next could take {longest:.1f} s)"
            )
            break
        seen.add(candidate)
        # fitted as given: a rank above the singular values its P_TH supports is refused
        score, _ = score_tpsr(candidate, train, heldout, features, crit, sizing=AS_GIVEN)
        trials.append(Trial(candidate, stage, score))
        top = best()
        result = (
            f"{score.value:.4f} ± {score.se:.4f}" if score.ok else f"failed ({brief(score.error)})"
        )
        what = describe(candidate) if len(trials) == 1 else _departures_text(candidate, base)
        say(
            f"[{len(trials)}] {stage}: {what} -> criterion {result} ({score.seconds:.1f} s); "
            f"best {top.score.value:.4f} [{trials.index(top) + 1}]"
        )
        bar.update()
        bar.set_postfix(best=f"{top.score.value:.4f}")
    bar.close()
    if not trials or not best().score.ok:
        why = brief(best().score.error) if trials else "every candidate was skipped"
        raise DataError(
            f"no candidate could be fitted on {len(train)} training steps ({why}); record more "
            "data or a shorter --step-period"
        )
    say(stopped)
    top, chosen = best(), one_standard_error_choice(trials)
    if chosen is not top:
        say(
            f"one-standard-error rule: {describe(chosen.config)} (criterion "
            f"{chosen.score.value:.4f}) is the simplest within one standard error "
            f"({difference_se(chosen, top):.4f}, of the difference) of the highest, "
            f"{top.score.value:.4f} ({describe(top.config)})"
        )
    return TuneResult(chosen, top, tuple(trials), widths, stopped, clock() - start, crit)


def fit_check(trajectory: Trajectory, result: TuneResult, report: Report | None = None) -> Trial:
    """The candidate to write: the chosen one if ``learner fit --config`` can fit it on all of
    ``trajectory`` (every size as given, the rank held to the supported singular values),
    else the next fitted candidate in the rule's order that it can.

    The spectral fit is checked (refinement, where configured, cannot refuse).
    """
    say = report or (lambda _line: None)
    fitted = [t for t in result.trials if t.score.ok]
    order = [result.best] + sorted(
        (t for t in fitted if t is not result.best),
        key=lambda t: (-t.score.value, complexity(t.config)),
    )
    reasons: list[str] = []
    for trial in order:
        try:
            fit_tpsr_trajectory(
                trajectory, dataclasses.replace(trial.config, refine_epochs=0), sizing=AS_GIVEN
            )
        except TpsrError as exc:
            reasons.append(brief(str(exc)))
            say(f"{describe(trial.config)} cannot be fitted on all {len(trajectory)} steps: {reasons[-1]}")
            continue
        if trial is not result.best:
            say(f"writing instead {describe(trial.config)} (criterion {trial.score.value:.4f})")
        return trial
    raise DataError(
        f"no tuned candidate can be fitted on all {len(trajectory)} steps ({reasons[0]}); "
        "record more data"
    )


def tune_record(result: TuneResult) -> dict[str, Any]:
    """The ``tune`` section of the config file: criterion, widths, every candidate."""

    def trial(t: Trial) -> dict[str, Any]:
        entry: dict[str, Any] = {"stage": t.stage, **_rounded(changed_parameters(t.config))}
        if t.score.ok:
            entry["criterion"] = round(t.score.value, 6)
            entry["se"] = round(t.score.se, 6)
        else:
            entry["error"] = brief(t.score.error)
        entry["seconds"] = round(t.score.seconds, 2)
        return entry

    return {
        "criterion": round(result.best.score.value, 6),
        "criterion_se": round(result.best.score.se, 6),
        "criterion_per_horizon": [round(v, 6) for v in result.best.score.per_horizon],
        "rule": (
            "one standard error: the simplest candidate within one SE of the difference "
            "to the highest"
        ),
        "criterion_difference_se": round(difference_se(result.best, result.top), 6),
        "highest_criterion": round(result.top.score.value, 6),
        "highest_criterion_se": round(result.top.score.se, 6),
        "criterion_settings": dataclasses.asdict(result.criterion),
        "median_widths": _rounded(result.widths),
        "seconds": round(result.seconds, 1),
        "stopped": result.stopped,
        "tried": [trial(t) for t in result.trials],
    }


def _rounded(values: dict[str, Any]) -> dict[str, Any]:
    return {k: round(v, 6) if isinstance(v, float) else v for k, v in values.items()}


def register(subparsers: Any) -> None:
    """Add the ``tune`` subcommand."""
    doc = "choose TPSR fit parameters from the training data alone (held-out prediction)"
    parser = subparsers.add_parser(
        "tune", help=doc, description=doc[0].upper() + doc[1:] + ". " + __doc__.split("\n\n")[1]
    )
    parser.add_argument("bags", nargs="+", type=Path, metavar="BAG", help="rosbag2 MCAP bag(s)")
    parser.add_argument(
        "-o", "--output", type=Path, required=True, metavar="CONFIG",
        help="config file to write (.yaml), for learner fit --config",
    )
    parser.add_argument(
        "--budget", type=positive_float, default=DEFAULT_BUDGET, metavar="SECONDS",
        help="time for reading and the search (default: %(default)s); the first candidate "
        "always runs",
    )
    parser.add_argument(
        "--candidates", type=positive_int, default=None, metavar="N",
        help="try at most N candidates (reproducible on any machine, given the time; "
        "default: as many as the budget allows)",
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of sampling and fits")
    parser.add_argument(
        "--steps", type=positive_int, default=None, metavar="N",
        help="use only the first N steps (default: all)",
    )
    parser.add_argument("--force", action="store_true", help="overwrite an existing CONFIG")
    from learner.fit import add_topic_options
    from learner.inputs import add_stream_options
    from learner.options import add_preset_option

    add_preset_option(parser, "fit (the search starts from it)")
    add_topic_options(parser.add_argument_group("topics"))
    add_stream_options(
        parser.add_argument_group(
            "robot bags (written into CONFIG, which learner fit --config reads): camera and "
            "commands resampled onto a step grid"
        )
    )
    parser.set_defaults(run=run)


def _say(line: str) -> None:
    tqdm.write(f"learner tune: {line}", file=sys.stderr)


def run(args: argparse.Namespace) -> int:
    """Read the bags, tune within the budget, write CONFIG.yaml, print the best."""
    from learner.fit import read_training_bags
    from learner.inputs import (
        fit_options_from_args,
        require_given_topics,
        robot_turns,
        stream_inputs,
        topics_from_args,
    )
    from learner.options import preset_from_args

    start = time.perf_counter()
    if args.seed < 0:
        raise ConfigError(f"--seed must be >= 0, not {args.seed}")
    check_output_path(args.output, force=args.force)  # refused before the search, not after
    require_given_topics(args.bags, args)
    _say(f"reading {len(args.bags)} bag(s)")
    stream_options = fit_options_from_args(args)
    trajectory, spec = read_training_bags(args, topics_from_args(args), stream_options, _say)
    if args.steps is not None:
        trajectory = trajectory.rows(0, min(len(trajectory), args.steps))
    # the search starts from what learner fit would fit with the same preset
    turning = robot_turns(spec, trajectory.summary().get("environment"))
    base = preset_from_args(args).tpsr_config(robot=spec is not None, turning=turning)
    result = tune(
        trajectory, budget=args.budget, candidates=args.candidates, seed=args.seed, base=base,
        report=_say, progress=True, started=start,
    )
    header = (
        f"learner tune {' '.join(map(str, args.bags))} (seed {args.seed}, budget "
        f"{args.budget:g} s)\n"
        "TPSR fit parameters chosen by the held-out predictive criterion (docs/results.md, "
        "'Tuning'),\nand the options the bags were read with;\nuse with: learner fit BAG... "
        "--config THIS_FILE -o MODEL"
    )
    best = fit_check(trajectory, result, _say)
    result = dataclasses.replace(result, best=best)
    print(
        f"chosen: {describe(best.config)} (criterion {best.score.value:.4f} ± "
        f"{best.score.se:.4f}; highest {result.top.score.value:.4f})"
    )
    if not best.score.value > 0:
        held = round(len(trajectory) * result.criterion.holdout)
        _say(
            f"warning: the best criterion {best.score.value:.3g} is not above 0 (no candidate "
            f"predicted the held-out observations better than their mean): {held} held-out "
            f"steps over {trajectory.n_actions} actions are too few for the criterion's "
            "per-action regressions, or the data carry no state these settings learn; the "
            "choice is unsupported (record more steps or give fewer --actions)"
        )
    write_fit_config(
        args.output,
        best.config,
        tune_record(result),
        inputs=stream_inputs(args, spec),
        header=header,
        force=args.force,
    )
    print(
        f"{len(result.trials)} candidate(s) in {time.perf_counter() - start:.1f} s; "
        f"wrote {args.output}"
    )
    return 0
