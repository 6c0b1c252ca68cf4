"""``learner experiment --environment E``: the guide's learning-planning loop (figure 4.2).

For every data size (training episodes of ``--episode-steps`` recorded steps each, the
guide's 3 by default, whatever the method and preset) and repetition: a fresh uniformly
random training trajectory; a TPSR and the PCA baseline learned from it; states tracked with each
model's parameters over one separate random RL trajectory (15000 steps in ``full``,
20000 in ``partial`` and ``distractors``; the same for every run, as in the guide, or with
``--rl-per-run`` one of each run's own);
fitted Q-iteration on them; the standard evaluation. Beside them stand the floors
(``constant``: the best of the 25 constant actions; ``random``: uniformly random
actions, seeded per run; :mod:`learner.floors`) and the ceiling (``true-position``: the
same RL step on the ground truth). On request (``--methods stacked-pca window``) the
baselines that carry the past (:mod:`tpsr_ros.core.window_baselines`): PCA frames stacked
over the last ``k`` steps, and a finite-window predictive state, whose fitted Q sees its
predictive part only (:func:`tpsr_ros.core.fqi.ignore_trailing`). ``--set NAME=VALUE``
changes any fit or fitted-Q parameter (:mod:`learner.overrides`); the CSV records every
parameter of every run.

Every seed is derived from ``--seed``, the data size and the repetition and written to
the CSV, so any row reruns alone (``--episodes N --first-repetition K --repetitions 1``).
Repetitions run in parallel processes (one BLAS thread each). A fitted-Q fit that
diverges or does not converge is refitted with ten times the ridge (up to 1.0,
:func:`tpsr_ros.core.planning.fit_q_on`); the ridge used is recorded.
"""

from __future__ import annotations

import argparse
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

from learner.evaluate import Evaluation, evaluate
from learner.floors import CONSTANT, FLOORS, constant_floor, random_floor
from learner.inputs import robot_turns
from learner.measures import NOT_MEASURED, criterion_of, memory_of, tuned
from learner.options import add_preset_option
from learner.overrides import apply_overrides
from learner.plots import affine_r2, loop_position_error, neighbour_position_error
from learner.representations import ModelTracker, Tracker, TruePositionTracker
from learner.simulated import SimSettings, random_trajectory
from learner.tables import (
    DEFAULT_METHODS,
    METHODS,
    PAST_BASELINES,
    Row,
    format_table,
    plot_summary,
    summarise,
    write_csv,
)
from sim_node import Environment, SimConfig
from tpsr_ros.cli import positive_float, positive_int
from tpsr_ros.core.episodes import Trajectory
from tpsr_ros.core.errors import ConfigError, DivergenceError, TpsrError
from tpsr_ros.core.fqi import FQIConfig, ignore_trailing
from tpsr_ros.core.learn import fit_tpsr_trajectory
from tpsr_ros.core.pca_baseline import PCAConfig, fit_pca
from tpsr_ros.core.planning import fit_q_on, ridge_ladder
from tpsr_ros.core.presets import DEFAULT_PRESET, departures, get_preset
from tpsr_ros.core.sizing import Sizing
from tpsr_ros.core.state_model import planner_dim
from tpsr_ros.core.tpsr import TPSRConfig
from tpsr_ros.core.window_baselines import (
    StackedPCAConfig,
    WindowConfig,
    fit_stacked_pca,
    fit_window,
)
from tpsr_ros.io.model_io import model_fingerprint
from tpsr_ros.io.policy import TRUE_POSITION, Policy
from tpsr_ros.progress import progress_bar

__all__ = [
    "ExperimentConfig",
    "add_grid_options",
    "config_from_args",
    "EPISODE_STEPS",
    "WINDOW_STEPS",
    "default_config",
    "experiment_command",
    "prepare_outputs",
    "register",
    "run",
    "run_experiment",
]

RL_STEPS = {
    "full": 15000,
    "partial": 20000,
    "distractors": 20000,
    "partial-strip": 20000,
    "drive": 20000,
}
EPISODE_STEPS = 3
"""Recorded steps of a training episode: the guide's (one image of history, the current
step, one of test), so 8000 episodes are 24000 steps for every method and preset."""
WINDOW_STEPS = "window"
"""``--episode-steps``' value for one window of the TPSR's fit per episode (``m + 1 + n``)."""

# guide figure 4.5 / appendix A.2-A.3; partial-strip as partial
PCA_DIM = {"full": 2, "partial": 3, "distractors": 3, "partial-strip": 3, "drive": 4}
"""The PCA baseline's dimension: the guide's 2 and 3; ``drive``'s 4 for x, y and the
heading's cosine and sine."""


@dataclass(frozen=True)
class ExperimentConfig:
    """One environment's experiment grid."""

    environment: str
    episodes: tuple[int, ...] = (2000, 4000, 6000, 8000)
    repetitions: int = 10
    first_repetition: int = 0
    methods: tuple[str, ...] = DEFAULT_METHODS
    rl_steps: int = 15000
    rl_seed: int = 100
    rl_per_run: bool = False
    """Each run plans on its own random RL trajectory, seeded ``rl_seed`` plus its
    repetition, so that the runs' spread holds the RL data's too (False: every run plans
    on the one trajectory of ``rl_seed``, as in the guide)."""
    seed: int = 0
    tpsr: TPSRConfig = field(default_factory=TPSRConfig)
    pca: PCAConfig = field(default_factory=PCAConfig)
    stacked: StackedPCAConfig = field(default_factory=StackedPCAConfig)
    """The ``stacked-pca`` baseline (its images' dimension follows the PCA baseline's)."""
    window: WindowConfig = field(default_factory=WindowConfig)
    """The ``window`` baseline (its images' components follow the PCA baseline's)."""
    fqi: FQIConfig = field(default_factory=FQIConfig)
    sim: SimSettings = field(default_factory=SimSettings)
    """The simulator's settings (the camera's vertical extent) for training, RL and scoring."""
    tune_budget: float | None = None
    """Seconds of ``learner tune`` on each run's own training data (None: no tuning)."""
    tune_candidates: int | None = None
    """At most this many tuning candidates per run (None: as many as the budget allows)."""
    preset: str = "guide"
    """The preset ``tpsr`` and ``fqi`` started from (:mod:`tpsr_ros.core.presets`); the
    dataclass defaults are the guide's."""
    memory: bool = False
    """Also measure each learned model's memory (:mod:`learner.memory`, in ``partial``)."""
    criterion: bool = False
    """Also score each TPSR run's configuration by ``learner tune``'s held-out criterion on
    its own training data (:mod:`learner.criterion`; no reward, no ground truth)."""
    episode_steps: int | None = EPISODE_STEPS
    """Recorded training steps per episode, the same for every method and preset, so that
    a data size means as much data whatever the fit; None: one window of the TPSR's fit
    (``m + 1 + n``), as the guide's episodes were (then a fit with longer histories or
    tests learns from more steps at the same number of episodes)."""

    def __post_init__(self) -> None:
        environment = Environment.parse(self.environment)
        get_preset(self.preset)
        if self.memory and not environment.narrow:
            raise ConfigError(
                "--memory needs --environment partial or partial-strip: only there do two "
                "places look alike"
            )
        if self.tune_budget is not None and not self.tune_budget > 0:
            raise ConfigError(f"the tuning budget must be positive, not {self.tune_budget!r}")
        if self.tune_candidates is not None and (
            self.tune_budget is None or self.tune_candidates < 1
        ):
            raise ConfigError("tune_candidates needs a tuning budget and must be >= 1")
        if not self.episodes or min(self.episodes) < 1:
            raise ConfigError("data sizes (--episodes) must be positive")
        if self.episode_steps is not None and self.episode_steps < 1:
            raise ConfigError(f"--episode-steps must be positive, not {self.episode_steps}")
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

    def run_rl_seed(self, repetition: int) -> int:
        """Seed of the RL trajectory repetition ``repetition`` plans on (:attr:`rl_per_run`)."""
        return self.rl_seed + repetition if self.rl_per_run else self.rl_seed

    def sim_config(self) -> SimConfig:
        """The simulator every run of the grid learns in and is scored in."""
        return self.sim.config(self.environment)

    def steps_for(self, episodes: int) -> int:
        """Recorded training steps of ``episodes`` episodes (:attr:`episode_steps` each)."""
        return episodes * (self.episode_steps or self.tpsr.window_steps)


def preset_tpsr(preset: str, environment: str) -> TPSRConfig:
    """The fit ``preset`` gives in ``environment``: with the turning robot's changes where the
    actions turn the robot (``drive``), as ``learner fit`` gives them."""
    return get_preset(preset).tpsr_config(turning=robot_turns(None, environment))


def default_config(
    environment: str, preset: str = DEFAULT_PRESET, **overrides: Any
) -> ExperimentConfig:
    """The guide's protocol for ``environment`` (RL steps, PCA dimension) with the fit and
    planner of ``preset`` (its turning robot's fit in ``drive``), then ``overrides``."""
    chosen = get_preset(preset)
    values: dict[str, Any] = {
        "environment": environment,
        "rl_steps": RL_STEPS[environment],
        "pca": PCAConfig(dim=PCA_DIM[environment]),
        "stacked": StackedPCAConfig(dim=PCA_DIM[environment]),
        "window": WindowConfig(components=PCA_DIM[environment]),
        "tpsr": preset_tpsr(chosen.name, environment),
        "fqi": chosen.fqi_config(),
        "preset": chosen.name,
    }
    values.update(overrides)
    return ExperimentConfig(**values)


def _setting(value: Any) -> str:
    return str(value).lower() if isinstance(value, bool) else str(value)


def experiment_command(config: ExperimentConfig, episodes: Sequence[int] | None = None) -> str:
    """The ``learner experiment`` command that runs ``config`` (at ``episodes``, default all).

    Settings are written as they depart from the preset's (``--set``) and from the
    protocol's defaults, so the command is as short as the configuration allows.
    """
    reference = default_config(config.environment, config.preset)
    parts = [f"python -m learner experiment --environment {config.environment}"]
    if config.preset != DEFAULT_PRESET:
        parts.append(f"--preset {config.preset}")
    sizes = tuple(episodes or config.episodes)
    if sizes != ExperimentConfig.__dataclass_fields__["episodes"].default:
        parts.append("--episodes " + " ".join(map(str, sizes)))
    for name in ("repetitions", "first_repetition", "seed", "rl_seed", "rl_steps"):
        if getattr(config, name) != getattr(reference, name):
            parts.append(f"--{name.replace('_', '-')} {getattr(config, name)}")
    for group in ("sim", "tpsr", "pca", "stacked", "window", "fqi"):
        changed = departures(getattr(config, group), getattr(reference, group))
        parts += [f"--set {group}.{k}={_setting(v)}" for k, v in changed.items()]
    if config.tune_budget is not None:
        parts.append(f"--tune --tune-budget {config.tune_budget:g}")
    if config.tune_candidates is not None:
        parts.append(f"--tune-candidates {config.tune_candidates}")
    if config.rl_per_run:
        parts.append("--rl-per-run")
    if config.memory:
        parts.append("--memory")
    if config.criterion:
        parts.append("--criterion")
    if config.episode_steps != EPISODE_STEPS:
        parts.append(f"--episode-steps {config.episode_steps or WINDOW_STEPS}")
    return " ".join(parts)


@dataclass(frozen=True)
class _Scored:
    """What planning and scoring one run gave (the CSV's columns of it)."""

    score: float
    trials: str
    ends: str
    ridge: float
    status: str
    loop_position_error: float = float("nan")
    goal: str = ""


def _plan_and_score(
    config: ExperimentConfig, tracker: Tracker, rl: Trajectory, states: np.ndarray
) -> _Scored:
    """Fitted Q on the tracked RL states (larger ridges if it diverges), then the standard
    score, and how well the states the policy acted on locate the robot among the RL ones.

    A model whose state carries a buffer for its updates only (``window``) is planned on
    its leading ``planner_dim`` coordinates; the Q-function ignores the rest.
    """
    seen = _planner_dim(tracker, states)
    try:
        q, fqi, _ = fit_q_on(states[:, :seen], rl, config.fqi)
    except DivergenceError:
        ridge = ridge_ladder(config.fqi.ridge)[-1]
        return _Scored(float("nan"), "", "", ridge, "fitted-q-diverged")
    q = ignore_trailing(q, states.shape[1])
    policy = Policy(q, tracker.representation, tracker.fingerprint, config.environment)
    result = evaluate(policy, tracker, config.sim_config())
    assert result.states is not None and result.positions is not None
    loop_error = loop_position_error(
        states[:, :seen], rl.positions[:, :2], result.states[:, :seen], result.positions
    )
    return _Scored(
        result.score,
        _trials(result),
        _trial_ends(result),
        fqi.ridge,
        "ok",
        loop_error,
        _trial_goal(result),
    )


def _planner_dim(tracker: Tracker, states: np.ndarray) -> int:
    """Leading state coordinates the planner (and the position measures) see."""
    if isinstance(tracker, ModelTracker):
        return planner_dim(tracker.model)
    return int(states.shape[1])


_CONFIG_GROUP = {"tpsr": "tpsr", "pca": "pca", "stacked-pca": "stacked", "window": "window"}
"""The experiment's configuration of each learned method."""


@lru_cache(maxsize=1)
def _rl_trajectory(environment: str, steps: int, seed: int, sim: SimSettings) -> Trajectory:
    """The RL trajectory of a run, shared by every run of an environment unless each has
    its own (built once per process and seed)."""
    return random_trajectory(environment, steps, seed, sim)


def _parameters(config: ExperimentConfig, method: str, extra: dict[str, Any]) -> str:
    """Every parameter of one run as JSON: the method's own config, the RL step's, the rest."""
    values: dict[str, Any] = {"rl_steps": config.rl_steps, **extra}
    if method in _CONFIG_GROUP:
        values[method] = dataclasses.asdict(getattr(config, _CONFIG_GROUP[method]))
        values["sim"] = dataclasses.asdict(config.sim)  # what the camera shows them
    if method not in FLOORS:
        values["fqi"] = dataclasses.asdict(config.fqi)
    return json.dumps(values, sort_keys=True)


def _trials(evaluation: Evaluation) -> str:
    return ";".join(f"{t.reward:g}" for t in evaluation.trials)


def _trial_ends(evaluation: Evaluation) -> str:
    return ";".join(
        f"{t.end[0]:.2f},{t.end[1]:.2f},{t.standing}" for t in evaluation.trials if t.end
    )


def _trial_goal(evaluation: Evaluation) -> str:
    return ";".join(f"{t.goal_step or 0},{t.wall_contacts}" for t in evaluation.trials)


def _row(
    config: ExperimentConfig,
    method: str,
    episodes: int,
    repetition: int,
    extra: dict[str, Any],
    command_config: ExperimentConfig | None = None,
    **result: Any,
) -> Row:
    """A run's row: its identity and seeds, ``result``, every parameter it used and the
    command of its grid (from ``command_config``, the grid's configuration, default
    ``config``)."""
    return Row(
        environment=config.environment,
        method=method,
        episodes=episodes,
        repetition=repetition,
        train_seed=config.train_seed(episodes, repetition),
        rl_seed=config.run_rl_seed(repetition),
        parameters=_parameters(config, method, extra),
        preset=config.preset,
        command=experiment_command(command_config or config),
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
        trial_ends=_trial_ends(evaluation),
        trial_goal=_trial_goal(evaluation),
        fit_seconds=round(time.perf_counter() - start, 3),
        fqi_ridge=nan,
        recoveries=0,
        r2_x=nan,
        r2_y=nan,
        status="ok",
    )


def _learn_states(
    config: ExperimentConfig, method: str, train: Trajectory, rl: Trajectory
) -> tuple[Tracker, np.ndarray, int]:
    """The method's tracker and its states over the RL trajectory (and filter recoveries)."""
    if method == TRUE_POSITION:
        tracker = TruePositionTracker()
        return tracker, tracker.track(rl), 0
    codes = config.sim_config().actions.codes  # the commands of the simulator's actions
    if method == "tpsr":
        # sizes set with --set stay as set; the preset's follow the data (core.sizing)
        given = departures(config.tpsr, preset_tpsr(config.preset, config.environment))
        model = fit_tpsr_trajectory(
            train, config.tpsr, sizing=Sizing(given), action_codes=codes
        )
    elif method == "stacked-pca":
        model = fit_stacked_pca(
            train.observations,
            train.actions,
            n_actions=train.n_actions,
            config=config.stacked,
            action_codes=codes,
        )
    elif method == "window":
        model = fit_window(
            train.observations,
            train.actions,
            n_actions=train.n_actions,
            segments=train.segments,
            config=config.window,
            action_codes=codes,
        )
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
    rl_seed = config.run_rl_seed(repetition)
    rl = _rl_trajectory(config.environment, config.rl_steps, rl_seed, config.sim)
    train = random_trajectory(
        config.environment, config.steps_for(episodes), train_seed, config.sim
    )
    for method in learned:
        start = time.perf_counter()
        run_config, extra = config, {}
        try:
            if method == "tpsr":
                tuned_config, extra = tuned(
                    config.tpsr, train, config.tune_budget, config.tune_candidates
                )
                run_config = dataclasses.replace(config, tpsr=tuned_config)
                start = time.perf_counter()  # the fit alone: the tuning's time is in ``extra``
            tracker, states, recoveries = _learn_states(run_config, method, train, rl)
            fit_seconds = time.perf_counter() - start
            if method == "tpsr":  # the fit's own record, e.g. the d^O that obs_variance chose
                run_config = dataclasses.replace(run_config, tpsr=tracker.model.config)
            seen = states[:, : _planner_dim(tracker, states)]  # what the planner sees
            r2 = _pose_r2(seen, rl.positions)
            position_error = neighbour_position_error(seen, rl.positions[:, :2])
            memory = (
                memory_of(tracker, config.environment, config.sim)
                if config.memory
                else NOT_MEASURED
            )
            criterion = (
                criterion_of(run_config.tpsr, train)
                if config.criterion and method == "tpsr"
                else float("nan")
            )
            scored = _plan_and_score(config, tracker, rl, states)
        except TpsrError as exc:  # a failed fit is a result, not a crash
            fit_seconds, recoveries, r2 = time.perf_counter() - start, 0, np.full(3, np.nan)
            position_error, memory = float("nan"), NOT_MEASURED
            criterion = float("nan")
            scored = _Scored(float("nan"), "", "", config.fqi.ridge, f"error: {exc}")
        rows.append(
            _row(
                run_config,
                method,
                episodes,
                repetition,
                extra,
                command_config=config,
                score=scored.score,
                trial_rewards=scored.trials,
                trial_ends=scored.ends,
                trial_goal=scored.goal,
                fit_seconds=round(fit_seconds, 3),
                fqi_ridge=scored.ridge,
                recoveries=recoveries,
                r2_x=round(float(r2[0]), 4),
                r2_y=round(float(r2[1]), 4),
                r2_heading=round(float(r2[2]), 4),
                position_error=round(position_error, 3),
                loop_position_error=round(scored.loop_position_error, 3),
                status=scored.status,
                memory=memory.steps,
                memory_distance=round(memory.paths_distance, 6),
                memory_paths=memory.paths_steps,
                criterion=round(criterion, 6),
            )
        )
    return rows


def _pose_r2(states: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """R² of the affine maps from ``states`` to x, to y and to the heading's unit vector
    (cos and sin pooled: their R² weighted by their variances, the share of the unit
    vector's variance explained; NaN for poses without a heading)."""
    r2 = affine_r2(states, poses)
    if poses.shape[1] < 4:
        return np.array([*r2[:2], np.nan])
    return np.array([*r2[:2], np.average(r2[2:4], weights=poses[:, 2:4].var(axis=0))])


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
    bar = progress_bar(
        total=len(cells), unit="run", disable=not progress, desc=config.environment
    )
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


def _episode_steps(text: str) -> int | None:
    """``--episode-steps``: a positive count, or ``window`` (None)."""
    if text == WINDOW_STEPS:
        return None
    try:
        return positive_int(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(
            f"{text!r} is neither a positive number of steps nor {WINDOW_STEPS!r}"
        ) from None


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
    parser.add_argument(
        "--episode-steps",
        type=_episode_steps,
        default=EPISODE_STEPS,
        metavar="N|window",
        help="recorded training steps per episode, for every method (default: the guide's "
        f"%(default)s); {WINDOW_STEPS}: one window of the TPSR's fit (m + 1 + n), so a fit "
        "with longer histories or tests learns from more steps",
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
        help="set a fit, fitted-Q or simulator parameter for every run (repeatable): "
        "tpsr.<field> (e.g. rank, sigma_ht, ht_centers), pca.dim, fqi.<field> (e.g. ridge, "
        "centers), sim.vertical_half_extent (the camera's), stacked.<field> (k, dim, "
        "actions) and window.<field> (k, dim, components, actions, ridge) of the baselines "
        "that carry the past; a bare name where unambiguous",
    )
    parser.add_argument(
        "--rl-steps",
        type=positive_int,
        default=None,
        help="RL trajectory length (default: 15000 full, 20000 otherwise)",
    )
    parser.add_argument("--rl-seed", type=int, default=100)
    parser.add_argument(
        "--rl-per-run",
        action="store_true",
        help="each run plans on its own random RL trajectory, seeded --rl-seed plus its "
        "repetition (default: every run plans on the one trajectory of --rl-seed, as in the "
        "guide)",
    )
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
        "--tune-candidates",
        type=positive_int,
        default=None,
        metavar="N",
        help="with --tune: at most N candidates per run (reproducible whatever the machine's "
        "speed, given the budget)",
    )
    parser.add_argument(
        "--criterion",
        action="store_true",
        help="also score each TPSR run's configuration by learner tune's held-out criterion "
        "on its own training data (the criterion column)",
    )
    parser.add_argument(
        "--memory",
        action="store_true",
        help="also measure each learned model's memory (learner memory, in partial): the "
        "memory, memory_distance and memory_paths columns",
    )
    parser.add_argument(
        "--p-th-tests",
        choices=("after-current", "from-current"),
        default=None,
        help="TPSR P_TH test window (see learner fit; default: the preset's)",
    )
    add_preset_option(parser)


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
        default=list(DEFAULT_METHODS),
        help="floors (constant, random), learned representations (tpsr, pca), baselines "
        "that carry the past (stacked-pca: PCA of the last k images with their actions; "
        "window: a finite-window predictive state of the last k steps; set k with --set "
        "stacked.k=K, window.k=K) and the ceiling (true-position); default: all but "
        + " and ".join(PAST_BASELINES),
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
        "memory": args.memory,
        "criterion": args.criterion,
        "repetitions": args.repetitions,
        "first_repetition": args.first_repetition,
        "methods": tuple(methods),
        "rl_seed": args.rl_seed,
        "rl_per_run": args.rl_per_run,
        "seed": args.seed,
        "episode_steps": args.episode_steps,
    }
    base = default_config(args.environment, args.preset)
    tpsr = base.tpsr
    if args.p_th_tests is not None:
        tpsr = dataclasses.replace(tpsr, p_th_tests=args.p_th_tests)
    configs = {
        "tpsr": tpsr,
        "pca": base.pca,
        "fqi": base.fqi,
        "sim": base.sim,
        "stacked": base.stacked,
        "window": base.window,
    }
    overrides.update(apply_overrides(configs, assignments))
    if args.episodes:
        overrides["episodes"] = tuple(args.episodes)
    if args.rl_steps:
        overrides["rl_steps"] = args.rl_steps
    if (args.tune_budget is not None or args.tune_candidates is not None) and not args.tune:
        raise ConfigError("--tune-budget and --tune-candidates need --tune")
    overrides["tune_candidates"] = args.tune_candidates
    if args.tune:
        from learner.tune import DEFAULT_BUDGET

        overrides["tune_budget"] = args.tune_budget or DEFAULT_BUDGET
    return default_config(args.environment, args.preset, **overrides)


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
