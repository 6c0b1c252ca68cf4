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
    ObservationFeatures,
    Score,
    paired_jackknife_se,
    score_tpsr,
    split_trajectory,
)
from tpsr_ros.cli import positive_float, positive_int
from tpsr_ros.core.episodes import Trajectory, make_episodes
from tpsr_ros.core.errors import ConfigError, DataError
from tpsr_ros.core.features import median_distance
from tpsr_ros.core.sizing import Sizing, describe_sizing, size_to_data
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


def _stages(
    widths: dict[str, float], episodes: int
) -> list[tuple[str, Callable[[TPSRConfig], list[TPSRConfig]]]]:
    """The coarse grid, one parameter per stage, each around the best config so far."""

    def replace_each(name: str, values: Sequence[Any]) -> Callable[[TPSRConfig], list[TPSRConfig]]:
        return lambda best: [dataclasses.replace(best, **{name: v}) for v in values]

    def lengths(best: TPSRConfig) -> list[TPSRConfig]:
        return [dataclasses.replace(best, history_length=k, test_length=k) for k in (1, 2)]

    def centres(best: TPSRConfig) -> list[TPSRConfig]:
        usable = [c for c in CENTRES if c < episodes // 2]
        return [dataclasses.replace(best, ht_centers=c, obs_centers=c // 2) for c in usable]

    def refine(name: str) -> Callable[[TPSRConfig], list[TPSRConfig]]:
        return lambda best: [
            dataclasses.replace(best, **{name: float(getattr(best, name) * f)})
            for f in REFINE_FACTORS
        ]

    def refine_rank(best: TPSRConfig) -> list[TPSRConfig]:
        return [
            dataclasses.replace(best, rank=r)
            for r in (best.rank - 1, best.rank + 2)
            if 1 <= r <= best.ht_centers + 1
        ]

    def lower_ranks(best: TPSRConfig) -> list[TPSRConfig]:
        return [
            dataclasses.replace(best, rank=r)
            for r in range(best.rank - 1, max(0, best.rank - 1 - LOWER_RANKS), -1)
        ]

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


def _planned(widths: dict[str, float], episodes: int) -> int:
    """Upper bound on the number of candidates (for the progress bar)."""
    probe = TPSRConfig()
    return 2 + sum(len(propose(probe)) for _, propose in _stages(widths, episodes))


def _candidates(
    base: TPSRConfig, widths: dict[str, float], episodes: int, best: Callable[[], TPSRConfig]
) -> Iterator[tuple[str, TPSRConfig]]:
    """The base (a preset's settings) first, median widths second, then each stage around
    the best.

    The base comes first so that a budget that allows one candidate returns a model no
    worse than an untuned fit: at the median observation width the filter of a `full`
    bag explodes (docs/results.md, "Tuning").
    """
    yield "base", base
    yield "median widths", dataclasses.replace(base, **widths)
    for stage, propose in _stages(widths, episodes):
        for candidate in propose(best()):
            yield stage, candidate


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
    features = ObservationFeatures.fit(train.observations, crit.feature_dim)
    widths = median_widths(train, base, seed=seed)
    span = base.history_length + 1 + base.test_length
    episodes = len(train) // span
    base, sized = size_to_data(base, episodes, train.observations.shape[1], Sizing())
    if sized:
        say(describe_sizing(episodes, sized))
    say(
        f"median widths: sigma_obs {widths['sigma_obs']:.3g}, sigma_ht {widths['sigma_ht']:.3g} "
        f"({len(train)} steps fitted, {len(heldout)} held out)"
    )
    trials: list[Trial] = []
    seen: set[TPSRConfig] = set()
    stopped = "every candidate of the grid was tried"

    def best() -> Trial:
        return max(trials, key=lambda t: t.score.value)

    bar = tqdm(
        total=_planned(widths, episodes),
        unit="fit",
        desc="tune",
        disable=None if progress else True,  # None: only on a terminal
        file=sys.stderr,
    )
    for stage, candidate in _candidates(base, widths, episodes, lambda: best().config):
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
        score, _ = score_tpsr(candidate, train, heldout, features, crit)
        trials.append(Trial(candidate, stage, score))
        top = best()
        result = f"{score.value:.4f} ± {score.se:.4f}" if score.ok else f"failed ({score.error})"
        say(
            f"[{len(trials)}] {stage}: {describe(candidate)} -> criterion {result} "
            f"({score.seconds:.1f} s); best {top.score.value:.4f}: {describe(top.config)}"
        )
        bar.update()
        bar.set_postfix(best=f"{top.score.value:.4f}")
    bar.close()
    if not best().score.ok:
        raise DataError(f"no candidate could be fitted: {best().score.error}")
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


def tune_record(result: TuneResult) -> dict[str, Any]:
    """The ``tune`` section of the config file: criterion, widths, every candidate."""

    def trial(t: Trial) -> dict[str, Any]:
        entry: dict[str, Any] = {"stage": t.stage, **_rounded(changed_parameters(t.config))}
        if t.score.ok:
            entry["criterion"] = round(t.score.value, 6)
            entry["se"] = round(t.score.se, 6)
        else:
            entry["error"] = t.score.error
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
    best = result.best
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
