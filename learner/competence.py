"""``learner competence``: how soon the learner node's versions plan well (time to competence).

The learner node's version ``n`` is the refit of the first ``warmup + (n - 1) * refit``
live steps on version 1's basis, with the preset's fitted-Q policy on the same tracked
states (msgs_doc/learner_node.md). This command makes exactly those versions without a
middleware and scores each: for every run it generates the simulator's exploring run as a
bag (:func:`sim_node.generate.generate_bag`, the messages ``sim_node`` publishes), feeds
its messages to :class:`~tpsr_ros.io.trajectory.LiveSteps` as the node's subscriptions do,
runs the node's own refit (:func:`tpsr_ros.learner_node.refits.refit`) at every due point
and scores the version's policy by the standard evaluation (``learner evaluate``).

With ``--switch-to ROOM --switch-at N`` the room changes under the robot after ``N`` live
steps (:func:`sim_node.generate.generate_bag`'s ``then``), and each version is scored in the
room of its last step; ``--forgetting F`` and ``--new-basis-steps N`` are the learner node's
parameters. The CSV is then ``switch_<environment>_<room>_f<F>.csv``; with new bases, the
name ends in ``_b<N>`` before ``.csv``.

The CSV (``competence_<environment>.csv``) has the experiments' columns
(:class:`learner.tables.Row`), one row per version: ``method`` ``tpsr``, ``episodes`` the
live steps the version was fitted on, ``repetition`` the run, ``train_seed`` the run's
simulator seed, ``rl_seed`` 0 (the policy plans on the same steps), ``fit_seconds`` the
TPSR fit, and in ``parameters`` the version, the whole refit's seconds, the warm-up, the
refit period, the forgetting factor and, with a switch, the room the version was scored in.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

from learner.tables import Row, write_csv
from sim_node import SimConfig
from tpsr_ros.cli import positive_int
from tpsr_ros.core.errors import ConfigError

__all__ = ["DEFAULTS", "DEFAULT_STEPS", "competence_rows", "register", "run"]

DEFAULT_STEPS = 12000
"""Live steps of a run: 20 minutes at 10 Hz."""
DEFAULTS = {"steps": DEFAULT_STEPS, "warmup_steps": 1000, "refit_steps": 1000, "runs": 10,
            "seed": 31, "forgetting": 1.0, "new_basis_steps": 0, "switch_to": None,
            "switch_at": None}  # fmt: skip
"""The options' defaults: the learner node's, ten runs, fresh seeds, one room."""


def register(subparsers: Any) -> None:
    """Add the ``competence`` subcommand."""
    doc = "score the learner node's versions on the simulator's exploring runs (time to competence)"
    parser = subparsers.add_parser(
        "competence", help=doc, description=doc[0].upper() + doc[1:] + ". "
        + __doc__.split("\n\n")[1].replace("%", "%%"),
    )  # fmt: skip
    parser.add_argument("--environment", required=True, help="the simulator environment")
    parser.add_argument("--steps", type=positive_int, default=DEFAULTS["steps"],
                        help="live steps of each run (default: %(default)s)")  # fmt: skip
    parser.add_argument("--warmup-steps", type=positive_int, default=DEFAULTS["warmup_steps"],
                        help="the learner node's warmup_steps (default: %(default)s)")  # fmt: skip
    parser.add_argument("--refit-steps", type=positive_int, default=DEFAULTS["refit_steps"],
                        help="the learner node's refit_steps (default: %(default)s)")  # fmt: skip
    parser.add_argument("--runs", type=positive_int, default=DEFAULTS["runs"],
                        help="independent runs (default: %(default)s)")  # fmt: skip
    parser.add_argument("--seed", type=int, default=DEFAULTS["seed"],
                        help="simulator seed of the first run; run k uses seed + k "
                        "(default: %(default)s)")  # fmt: skip
    parser.add_argument(
        "--forgetting",
        type=float,
        default=DEFAULTS["forgetting"],
        help="the learner node's forgetting, in (0, 1] (default: %(default)s)",
    )
    parser.add_argument(
        "--new-basis-steps",
        type=int,
        default=DEFAULTS["new_basis_steps"],
        metavar="N",
        help="the learner node's new_basis_steps (default: %(default)s: never a new basis)",
    )
    parser.add_argument(
        "--switch-to",
        default=None,
        metavar="ROOM",
        help="the environment the room changes to after --switch-at steps",
    )
    parser.add_argument(
        "--switch-at",
        type=positive_int,
        default=None,
        metavar="STEPS",
        help="live steps before the room changes (with --switch-to)",
    )
    parser.add_argument("-o", "--output", type=Path, required=True, metavar="DIR")
    parser.add_argument("--force", action="store_true", help="overwrite an existing CSV")
    parser.add_argument("--workers", type=positive_int, default=1,
                        help="runs in parallel processes (default: %(default)s)")  # fmt: skip
    parser.set_defaults(run=run)


def command_of(args: argparse.Namespace) -> str:
    """The command that reruns these runs (recorded in every row)."""
    parts = ["python -m learner competence", "--environment", args.environment]
    for name, default in DEFAULTS.items():
        if getattr(args, name) != default:
            parts += [f"--{name.replace('_', '-')}", str(getattr(args, name))]
    return " ".join(parts)


def competence_rows(
    environment: str,
    steps: int,
    warmup: int,
    refit_every: int,
    run: int,
    seed: int,
    command: str,
    forgetting: float = 1.0,
    switch: tuple[str, int] | None = None,
    new_basis_steps: int = 0,
) -> list[Row]:
    """One run: every version the learner node would make of the run's steps, scored
    (``switch``: the room and the step it changes at)."""
    from learner.evaluate import evaluate
    from learner.representations import ModelTracker
    from sim_node.generate import generate_bag
    from tpsr_ros.io.model_io import open_model
    from tpsr_ros.io.policy import load_policy
    from tpsr_ros.io.trajectory import LiveSteps
    from tpsr_ros.learner_node.refits import RefitChain, refit

    rows = []
    with tempfile.TemporaryDirectory(prefix="competence_") as tmp:
        bag = Path(tmp) / "run"
        first_steps = steps if switch is None else switch[1]
        then = None if switch is None else (SimConfig(environment=switch[0]), steps - switch[1])
        generate_bag(bag, SimConfig(environment=environment), first_steps, seed=seed, then=then)
        live = LiveSteps.of_bag(bag, environment)
        chain = RefitChain.starting_from(
            None, forgetting=forgetting, new_basis_steps=new_basis_steps
        )  # the node's
        for version, due in enumerate(range(warmup, len(live) + 1, refit_every), start=1):
            result = refit(chain.request(live.chunk(due), version, Path(tmp) / "out", "best",
                                         keep=1))  # fmt: skip
            chain.advance(result)  # as the node continues
            room = environment if switch is None or due <= switch[1] else switch[0]
            score, status = float("nan"), result.note or "ok"
            if result.policy is not None:
                model_file = open_model(result.model)
                tracker = ModelTracker(model_file.model, model_file.fingerprint)
                evaluation = evaluate(load_policy(result.policy), tracker, room)
                score = evaluation.score
                trials = ";".join(f"{t.reward:g}" for t in evaluation.trials)
            else:
                trials = ""
            rows.append(Row(
                environment=environment, method="tpsr", episodes=due, repetition=run,
                train_seed=seed, rl_seed=0, score=score, trial_rewards=trials,
                fit_seconds=round(result.fit_seconds, 6), fqi_ridge=float("nan"),
                recoveries=0, r2_x=float("nan"), r2_y=float("nan"), status=status,
                parameters=json.dumps({
                    "version": version, "refit_seconds": round(result.total_seconds, 6),
                    "warmup_steps": warmup, "refit_steps": refit_every,
                    "forgetting": forgetting, "room": room,
                    **({} if not new_basis_steps else {"new_basis_steps": new_basis_steps,
                                                       "basis_steps": result.basis_steps}),
                    **({} if switch is None else {"switch_to": switch[0],
                                                  "switch_at": switch[1]}),
                }),
                preset="best", command=command,
            ))  # fmt: skip
            print(f"learner competence: {environment} run {run} v{version} ({due} steps, "
                  f"{room}): {score:.1f}", file=sys.stderr, flush=True)  # fmt: skip
    return rows


def run(args: argparse.Namespace) -> int:
    """Run every run (in parallel processes), then write the CSV."""
    SimConfig(environment=args.environment)  # an unknown environment is refused here
    if not 0.0 < args.forgetting <= 1.0:
        raise ConfigError(f"--forgetting must lie in (0, 1], not {args.forgetting}")
    if args.new_basis_steps < 0:
        raise ConfigError(f"--new-basis-steps must be 0 or more, not {args.new_basis_steps}")
    suffix = f"_b{args.new_basis_steps}" if args.new_basis_steps else ""
    switch = None
    if (args.switch_to is None) != (args.switch_at is None):
        raise ConfigError("--switch-to and --switch-at go together")
    if args.switch_to is not None:
        if (
            SimConfig(environment=args.switch_to).drives
            != SimConfig(environment=args.environment).drives
        ):
            raise ConfigError(
                "a run changes rooms only between rooms of the same robot and actions"
            )
        if not args.warmup_steps <= args.switch_at < args.steps:
            raise ConfigError(
                f"--switch-at {args.switch_at} must lie between the warm-up "
                f"({args.warmup_steps}) and the run's end ({args.steps})"
            )
        switch = (args.switch_to, args.switch_at)
        name = f"switch_{args.environment}_{args.switch_to}_f{args.forgetting:g}{suffix}.csv"
    else:
        name = f"competence_{args.environment}{suffix}.csv"
    path = args.output / name
    if path.exists() and not args.force:
        raise ConfigError(f"{path} already exists; use --force to overwrite it")
    args.output.mkdir(parents=True, exist_ok=True)
    command = command_of(args)
    jobs = [
        (args.environment, args.steps, args.warmup_steps, args.refit_steps, run, args.seed + run,
         command, args.forgetting, switch, args.new_basis_steps)
        for run in range(args.runs)
    ]  # fmt: skip
    if args.workers == 1:
        results = [competence_rows(*job) for job in jobs]
    else:
        os.environ.setdefault("OMP_NUM_THREADS", "1")  # one BLAS thread per process
        with ProcessPoolExecutor(args.workers) as pool:
            results = list(pool.map(competence_rows, *zip(*jobs, strict=True)))
    rows = [row for run_rows in results for row in run_rows]
    write_csv(rows, path)
    print(f"wrote {path}: {len(rows)} versions of {args.runs} runs", file=sys.stderr)
    return 0
