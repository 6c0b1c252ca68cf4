"""``learner experiment --environment E``: the guide's learning-planning loop (figure 4.2).

For every data size (training episodes) and repetition: a fresh uniformly random training
trajectory; a TPSR and the PCA baseline learned from it; states tracked with each
model's parameters over one separate random RL trajectory (15000 steps in ``full``,
20000 in ``partial`` and ``distractors``; the same for every run, as in the guide);
fitted Q-iteration on them; the standard evaluation. Beside them stand the floors
(``constant``: the best of the 25 constant actions; ``random``: uniformly random
actions, seeded per run; :mod:`learner.floors`) and the ceiling (``true-position``: the
same RL step on the ground truth). ``--set NAME=VALUE`` changes any fit or fitted-Q
parameter (:mod:`learner.overrides`); the CSV records every parameter of every run.

Every seed is derived from ``--seed``, the data size and the repetition and written to
the CSV, so any row reruns alone (``--episodes N --first-repetition K --repetitions 1``).
Repetitions run in parallel processes (one BLAS thread each). A fitted-Q fit that
diverges or does not converge is refitted with ten times the ridge (up to 1.0,
:func:`learner.planning.fit_q_on`); the ridge used is recorded.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import os
import sys
import time
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from learner.evaluate import Evaluation, evaluate
from learner.floors import CONSTANT, FLOORS, RANDOM, constant_floor, random_floor
from learner.overrides import apply_overrides
from learner.planning import fit_q_on, ridge_ladder
from learner.plots import affine_r2, neighbour_position_error
from learner.representations import ModelTracker, Tracker, TruePositionTracker
from learner.simulated import random_trajectory
from sim_node import Environment
from tpsr_ros.cli import positive_float, positive_int
from tpsr_ros.core.episodes import Trajectory, make_episodes
from tpsr_ros.core.errors import ConfigError, DivergenceError, TpsrError
from tpsr_ros.core.fqi import FQIConfig
from tpsr_ros.core.pca_baseline import PCAConfig, fit_pca
from tpsr_ros.core.tpsr import TPSRConfig, fit_tpsr_episodes
from tpsr_ros.io.model_io import model_fingerprint
from tpsr_ros.io.policy import TRUE_POSITION, Policy

__all__ = [
    "METHODS",
    "ExperimentConfig",
    "Row",
    "add_grid_options",
    "config_from_args",
    "default_config",
    "difference_in_sems",
    "plot_summary",
    "prepare_outputs",
    "register",
    "run",
    "run_experiment",
    "summarise",
]

METHODS = (CONSTANT, RANDOM, "tpsr", "pca", TRUE_POSITION)
RL_STEPS = {"full": 15000, "partial": 20000, "distractors": 20000}
PCA_DIM = {"full": 2, "partial": 3, "distractors": 3}  # guide figure 4.5 / appendix A.2-A.3


@dataclass(frozen=True)
class ExperimentConfig:
    """One environment's experiment grid."""

    environment: str
    episodes: tuple[int, ...] = (2000, 4000, 6000, 8000)
    repetitions: int = 10
    first_repetition: int = 0
    methods: tuple[str, ...] = METHODS
    rl_steps: int = 15000
    rl_seed: int = 100
    seed: int = 0
    tpsr: TPSRConfig = field(default_factory=TPSRConfig)
    pca: PCAConfig = field(default_factory=PCAConfig)
    fqi: FQIConfig = field(default_factory=FQIConfig)
    tune_budget: float | None = None
    """Seconds of ``learner tune`` on each run's own training data (None: no tuning)."""

    def __post_init__(self) -> None:
        Environment.parse(self.environment)
        if self.tune_budget is not None and not self.tune_budget > 0:
            raise ConfigError(f"the tuning budget must be positive, not {self.tune_budget!r}")
        if not self.episodes or min(self.episodes) < 1:
            raise ConfigError("data sizes (--episodes) must be positive")
        if self.repetitions < 1 or self.first_repetition < 0:
            raise ConfigError("--repetitions must be >= 1 and --first-repetition >= 0")
        if unknown := sorted(set(self.methods) - set(METHODS)):
            raise ConfigError(f"unknown methods {unknown}; choose from {list(METHODS)}")
        if self.rl_steps < self.fqi.centers or self.rl_seed < 0 or self.seed < 0:
            raise ConfigError("rl_steps must exceed the fitted-Q centres; seeds must be >= 0")

    def train_seed(self, episodes: int, repetition: int) -> int:
        """Seed of the training trajectory of one (data size, repetition) cell."""
        sequence = np.random.SeedSequence([self.seed, episodes, repetition])
        return int(sequence.generate_state(1)[0])

    def steps_for(self, episodes: int) -> int:
        """Training steps for ``episodes`` non-overlapping episodes (guide: 3 x episodes)."""
        return episodes * (self.tpsr.history_length + 1 + self.tpsr.test_length)


def default_config(environment: str, **overrides: Any) -> ExperimentConfig:
    """The guide's settings for ``environment`` (RL steps, PCA dimension), then overrides."""
    values: dict[str, Any] = {
        "environment": environment,
        "rl_steps": RL_STEPS[environment],
        "pca": PCAConfig(dim=PCA_DIM[environment]),
    }
    values.update(overrides)
    return ExperimentConfig(**values)


@dataclass(frozen=True)
class Row:
    """One learning-planning run: a method at a data size and repetition."""

    environment: str
    method: str
    episodes: int
    repetition: int
    train_seed: int
    rl_seed: int
    score: float
    trial_rewards: str
    fit_seconds: float
    fqi_ridge: float
    recoveries: int
    r2_x: float
    r2_y: float
    status: str
    parameters: str = "{}"
    position_error: float = float("nan")  # median 10-NN error, m (nan in CSVs written before)


def _plan_and_score(
    config: ExperimentConfig, tracker: Tracker, rl: Trajectory, states: np.ndarray
) -> tuple[float, str, float, str]:
    """Fitted Q on the tracked RL states (larger ridges if it diverges), then the standard score."""
    try:
        q, fqi, _ = fit_q_on(states, rl, config.fqi)
    except DivergenceError:
        return float("nan"), "", ridge_ladder(config.fqi.ridge)[-1], "fitted-q-diverged"
    policy = Policy(q, tracker.representation, tracker.fingerprint, config.environment)
    result = evaluate(policy, tracker, config.environment)
    return result.score, _trials(result), fqi.ridge, "ok"


@lru_cache(maxsize=1)
def _rl_trajectory(environment: str, steps: int, seed: int) -> Trajectory:
    """The RL trajectory shared by every run of an environment (built once per process)."""
    return random_trajectory(environment, steps, seed)


def _parameters(config: ExperimentConfig, method: str, extra: dict[str, Any]) -> str:
    """Every parameter of one run as JSON: the method's own config, the RL step's, the rest."""
    values: dict[str, Any] = {"rl_steps": config.rl_steps, **extra}
    if method in ("tpsr", "pca"):
        values[method] = dataclasses.asdict(getattr(config, method))
    if method not in FLOORS:
        values["fqi"] = dataclasses.asdict(config.fqi)
    return json.dumps(values, sort_keys=True)


def _trials(evaluation: Evaluation) -> str:
    return ";".join(f"{t.reward:g}" for t in evaluation.trials)


def _row(
    config: ExperimentConfig,
    method: str,
    episodes: int,
    repetition: int,
    extra: dict[str, Any],
    **result: Any,
) -> Row:
    """A run's row: its identity and seeds, ``result`` and every parameter it used."""
    return Row(
        environment=config.environment,
        method=method,
        episodes=episodes,
        repetition=repetition,
        train_seed=config.train_seed(episodes, repetition),
        rl_seed=config.rl_seed,
        parameters=_parameters(config, method, extra),
        **result,
    )


def _floor_row(config: ExperimentConfig, method: str, episodes: int, repetition: int) -> Row:
    """A floor's run: state-blind, so it needs no training data and no fitted Q."""
    start = time.perf_counter()
    if method == CONSTANT:
        floor = constant_floor(config.environment)
        evaluation, extra = floor.evaluation, {"action": floor.action, "velocity": floor.velocity}
    else:
        policy_seed = config.train_seed(episodes, repetition)
        evaluation, extra = (
            random_floor(config.environment, policy_seed),
            {"policy_seed": policy_seed},
        )
    nan = float("nan")
    return _row(
        config,
        method,
        episodes,
        repetition,
        extra,
        score=evaluation.score,
        trial_rewards=_trials(evaluation),
        fit_seconds=round(time.perf_counter() - start, 3),
        fqi_ridge=nan,
        recoveries=0,
        r2_x=nan,
        r2_y=nan,
        status="ok",
    )


def _tuned(config: ExperimentConfig, train: Trajectory) -> tuple[TPSRConfig, dict[str, Any]]:
    """``config.tpsr``, or with ``tune_budget`` what ``learner tune`` picks from ``train``."""
    if config.tune_budget is None:
        return config.tpsr, {}
    from learner.tune import tune

    result = tune(train, budget=config.tune_budget, seed=config.tpsr.seed, base=config.tpsr)
    return result.best.config, {
        "tune": {
            "criterion": round(result.best.score.value, 6),
            "se": round(result.best.score.se, 6),
            "highest": round(result.top.score.value, 6),
            "candidates": len(result.trials),
            "seconds": round(result.seconds, 1),
            "budget": config.tune_budget,
        }
    }


def _learn_states(
    config: ExperimentConfig, method: str, train: Trajectory, rl: Trajectory
) -> tuple[Tracker, np.ndarray, int]:
    """The method's tracker and its states over the RL trajectory (and filter recoveries)."""
    if method == TRUE_POSITION:
        tracker = TruePositionTracker()
        return tracker, tracker.track(rl), 0
    if method == "tpsr":
        episodes = make_episodes(train, config.tpsr.history_length, config.tpsr.test_length)
        model = fit_tpsr_episodes(episodes, config=config.tpsr)
    else:
        model = fit_pca(train.observations, n_actions=train.n_actions, config=config.pca)
    track = model.track(rl.actions, rl.observations)
    return ModelTracker(model, model_fingerprint(model)), track.states, int(track.recovered.sum())


def run_cell(config: ExperimentConfig, episodes: int, repetition: int) -> list[Row]:
    """Every method at one (data size, repetition): the unit of parallel work."""
    train_seed = config.train_seed(episodes, repetition)
    rows = [_floor_row(config, m, episodes, repetition) for m in config.methods if m in FLOORS]
    learned = [m for m in config.methods if m not in FLOORS]
    if not learned:
        return rows
    rl = _rl_trajectory(config.environment, config.rl_steps, config.rl_seed)
    train = random_trajectory(config.environment, config.steps_for(episodes), train_seed)
    for method in learned:
        start = time.perf_counter()
        run_config, extra = config, {}
        try:
            if method == "tpsr":
                tuned, extra = _tuned(config, train)
                run_config = dataclasses.replace(config, tpsr=tuned)
                start = time.perf_counter()  # the fit alone: the tuning's time is in ``extra``
            tracker, states, recoveries = _learn_states(run_config, method, train, rl)
            fit_seconds = time.perf_counter() - start
            if method == "tpsr":  # the fit's own record, e.g. the d^O that obs_variance chose
                run_config = dataclasses.replace(run_config, tpsr=tracker.model.config)
            r2 = affine_r2(states, rl.positions)
            position_error = neighbour_position_error(states, rl.positions)
            score, trials, ridge, status = _plan_and_score(config, tracker, rl, states)
        except TpsrError as exc:  # a failed fit is a result, not a crash
            fit_seconds, recoveries, r2 = time.perf_counter() - start, 0, np.full(2, np.nan)
            position_error = float("nan")
            score, trials, ridge, status = float("nan"), "", config.fqi.ridge, f"error: {exc}"
        rows.append(
            _row(
                run_config,
                method,
                episodes,
                repetition,
                extra,
                score=score,
                trial_rewards=trials,
                fit_seconds=round(fit_seconds, 3),
                fqi_ridge=ridge,
                recoveries=recoveries,
                r2_x=round(float(r2[0]), 4),
                r2_y=round(float(r2[1]), 4),
                position_error=round(position_error, 3),
                status=status,
            )
        )
    return rows


def _limit_blas_threads() -> None:
    from threadpoolctl import threadpool_limits

    threadpool_limits(1)


def run_experiment(
    config: ExperimentConfig, *, workers: int = 2, progress: bool = True
) -> list[Row]:
    """Every cell of the grid, in parallel over ``workers`` processes; rows in grid order."""
    cells = [
        (episodes, repetition)
        for episodes in config.episodes
        for repetition in range(
            config.first_repetition, config.first_repetition + config.repetitions
        )
    ]
    results: dict[tuple[int, int], list[Row]] = {}
    bar = tqdm(total=len(cells), unit="run", disable=not progress, desc=config.environment)
    if workers <= 1:
        for cell in cells:
            results[cell] = run_cell(config, *cell)
            bar.update()
    else:
        with ProcessPoolExecutor(max_workers=workers, initializer=_limit_blas_threads) as pool:
            futures = {pool.submit(run_cell, config, *cell): cell for cell in cells}
            for future in as_completed(futures):
                results[futures[future]] = future.result()
                bar.update()
    bar.close()
    return [row for cell in cells for row in results[cell]]


def summarise(rows: Sequence[Row]) -> list[dict[str, Any]]:
    """Mean, median, SEM and failures per (method, data size), and each margin over the floor.

    For every method that is not a floor, ``floor`` names the best floor at the same data
    size (highest mean) and ``margin_sem`` is ``(mean - floor mean) / sqrt(SEM^2 + floor
    SEM^2)``: how many standard errors of the difference the method lies above it (NaN
    when no floor ran).
    """
    table = []
    keys = sorted({(r.method, r.episodes) for r in rows}, key=lambda k: (METHODS.index(k[0]), k[1]))
    for method, episodes in keys:
        scores = np.array([r.score for r in rows if (r.method, r.episodes) == (method, episodes)])
        ok = scores[np.isfinite(scores)]
        table.append(
            {
                "method": method,
                "episodes": episodes,
                "runs": len(scores),
                "failed": int(len(scores) - len(ok)),
                "mean": float(ok.mean()) if len(ok) else float("nan"),
                "median": float(np.median(ok)) if len(ok) else float("nan"),
                "sem": float(ok.std(ddof=1) / np.sqrt(len(ok))) if len(ok) > 1 else float("nan"),
            }
        )
    for entry in table:
        floors = [t for t in table if t["method"] in FLOORS and t["episodes"] == entry["episodes"]]
        entry["floor"], entry["margin_sem"] = "", float("nan")
        if entry["method"] in FLOORS or not floors:
            continue
        best = max(floors, key=lambda t: t["mean"])
        entry["floor"] = best["method"]
        entry["margin_sem"] = difference_in_sems(entry, best)
    return table


def difference_in_sems(a: dict[str, Any], b: dict[str, Any]) -> float:
    """``(mean_a - mean_b) / sqrt(SEM_a^2 + SEM_b^2)`` of two summary entries.

    A missing SEM (one run) counts as 0; with both 0 the result is +-inf (or nan when the
    means are equal).
    """
    spread = float(np.hypot(np.nan_to_num(a["sem"]), np.nan_to_num(b["sem"])))
    difference = a["mean"] - b["mean"]
    return difference / spread if spread > 0 else float(np.sign(difference) * np.inf)


def margin_text(entry: dict[str, Any]) -> str:
    """The margin over the best floor in SEMs, as printed in tables (``-`` for floors)."""
    margin = entry.get("margin_sem", float("nan"))
    if not entry.get("floor") or not np.isfinite(entry["mean"]):
        return "-"
    return f"{margin:+.1f} over {entry['floor']}"


def write_csv(rows: Sequence[Row], path: Path) -> None:
    """All rows, one per run, with every seed."""
    with path.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=[f.name for f in dataclasses.fields(Row)])
        writer.writeheader()
        writer.writerows(dataclasses.asdict(r) for r in rows)


def plot_summary(table: Sequence[dict[str, Any]], environment: str, path: Path) -> None:
    """Mean (line), median (dashed) and SEM band per method over data size, like guide 4.5."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colours = {
        CONSTANT: "tab:brown",
        RANDOM: "tab:olive",
        "tpsr": "tab:red",
        "pca": "tab:blue",
        TRUE_POSITION: "tab:gray",
    }
    fig, ax = plt.subplots(figsize=(6.4, 4.8))
    for method in METHODS:
        part = [t for t in table if t["method"] == method]
        if not part:
            continue
        x = np.array([t["episodes"] for t in part])
        mean = np.array([t["mean"] for t in part])
        sem = np.nan_to_num(np.array([t["sem"] for t in part]))
        ax.plot(x, mean, "-o", color=colours[method], label=f"{method} mean")
        ax.plot(
            x, [t["median"] for t in part], "--", color=colours[method], label=f"{method} median"
        )
        ax.fill_between(x, mean - sem, mean + sem, color=colours[method], alpha=0.2)
    ax.set_xlabel("training episodes")
    ax.set_ylabel("mean reward of 10 trials (max ~470)")
    ax.set_title(f"{environment}: learning-planning loop")
    ax.set_ylim(min(-100.0, *(t["mean"] - 20 for t in table if np.isfinite(t["mean"]))), 500)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, ncol=5, loc="upper center", bbox_to_anchor=(0.5, -0.14))
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def format_table(table: Sequence[dict[str, Any]]) -> list[str]:
    """The summary as aligned text lines."""
    lines = [
        f"{'method':14s} {'episodes':>8s} {'runs':>4s} {'mean':>7s} {'median':>7s} "
        f"{'sem':>6s} {'failed':>6s}  margin (SEMs)"
    ]
    for t in table:
        lines.append(
            f"{t['method']:14s} {t['episodes']:8d} {t['runs']:4d} {t['mean']:7.1f} "
            f"{t['median']:7.1f} {t['sem']:6.1f} {t['failed']:6d}  {margin_text(t)}"
        )
    return lines


def add_grid_options(parser: argparse.ArgumentParser) -> None:
    """Options shared by ``experiment`` and ``study``: data sizes, repetitions, seeds, --set."""
    parser.add_argument("--environment", required=True, choices=[e.value for e in Environment])
    parser.add_argument(
        "--episodes",
        type=positive_int,
        nargs="+",
        default=None,
        metavar="N",
        help="data sizes in training episodes (default: 2000 4000 6000 8000)",
    )
    parser.add_argument("--repetitions", type=positive_int, default=10)
    parser.add_argument(
        "--first-repetition",
        type=int,
        default=0,
        metavar="K",
        help="index of the first repetition (rerun rows alone)",
    )
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        dest="assignments",
        help="set a fit or fitted-Q parameter for every run (repeatable): tpsr.<field> "
        "(e.g. rank, sigma_ht, ht_centers), pca.dim, fqi.<field> (e.g. ridge, centers); a "
        "bare name where unambiguous",
    )
    parser.add_argument(
        "--rl-steps",
        type=positive_int,
        default=None,
        help="RL trajectory length (default: 15000 full, 20000 otherwise)",
    )
    parser.add_argument("--rl-seed", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0, help="base of every training seed")
    parser.add_argument("--workers", type=positive_int, default=os.cpu_count() or 1)
    parser.add_argument("--force", action="store_true", help="overwrite existing outputs")
    parser.add_argument(
        "--tune",
        action="store_true",
        help="choose each run's TPSR parameters with learner tune on its own training data "
        "(the --set values are the search's base)",
    )
    parser.add_argument(
        "--tune-budget",
        type=positive_float,
        default=None,
        metavar="SECONDS",
        help="tuning time per run with --tune (default: learner tune's 300)",
    )
    parser.add_argument(
        "--p-th-tests",
        choices=("after-current", "from-current"),
        default="after-current",
        help="TPSR P_TH test window (see learner fit)",
    )


def register(subparsers: Any) -> None:
    """Add the ``experiment`` subcommand."""
    doc = "run the guide's learning-planning loop (figure 4.2) for one environment"
    parser = subparsers.add_parser(
        "experiment",
        help=doc,
        description=doc[0].upper() + doc[1:] + ". " + __doc__.split("\n\n")[1],
    )
    add_grid_options(parser)
    parser.add_argument(
        "--methods",
        nargs="+",
        choices=METHODS,
        default=list(METHODS),
        help="floors (constant, random), learned representations (tpsr, pca) and the "
        "ceiling (true-position); default: all",
    )
    parser.add_argument(
        "-o",
        "--output",
        type=Path,
        default=Path("results"),
        help="directory for experiment_<env>.csv/.png (default: results)",
    )
    parser.set_defaults(run=run)


def config_from_args(
    args: argparse.Namespace, methods: Sequence[str], assignments: Sequence[str]
) -> ExperimentConfig:
    """The grid the options of :func:`add_grid_options` describe, with ``assignments`` applied."""
    overrides: dict[str, Any] = {
        "repetitions": args.repetitions,
        "first_repetition": args.first_repetition,
        "methods": tuple(methods),
        "rl_seed": args.rl_seed,
        "seed": args.seed,
    }
    base = default_config(args.environment)
    configs = {
        "tpsr": dataclasses.replace(base.tpsr, p_th_tests=args.p_th_tests),
        "pca": base.pca,
        "fqi": base.fqi,
    }
    overrides.update(apply_overrides(configs, assignments))
    if args.episodes:
        overrides["episodes"] = tuple(args.episodes)
    if args.rl_steps:
        overrides["rl_steps"] = args.rl_steps
    if args.tune_budget is not None and not args.tune:
        raise ConfigError("--tune-budget needs --tune")
    if args.tune:
        from learner.tune import DEFAULT_BUDGET

        overrides["tune_budget"] = args.tune_budget or DEFAULT_BUDGET
    return default_config(args.environment, **overrides)


def prepare_outputs(directory: Path, stem: str, force: bool) -> tuple[Path, Path]:
    """``(stem.csv, stem.png)`` in ``directory`` (made if missing); existing ones need ``force``.

    Checked before any run, so a refused output never costs the grid's time.
    """
    paths = (directory / f"{stem}.csv", directory / f"{stem}.png")
    for path in paths:
        if path.exists() and not force:
            raise ConfigError(f"{path} already exists; use --force to overwrite it")
    directory.mkdir(parents=True, exist_ok=True)
    return paths


def run(args: argparse.Namespace) -> int:
    """Run the grid, write CSV and PNG, print the summary."""
    config = config_from_args(args, args.methods, args.assignments)
    csv_path, png_path = prepare_outputs(args.output, f"experiment_{args.environment}", args.force)
    start = time.perf_counter()
    rows = run_experiment(config, workers=args.workers)
    elapsed = time.perf_counter() - start
    table = summarise(rows)
    write_csv(rows, csv_path)
    plot_summary(table, args.environment, png_path)
    print("\n".join(format_table(table)))
    print(f"{len(rows)} runs in {elapsed:.0f} s; wrote {csv_path} and {png_path}", file=sys.stderr)
    return 0
