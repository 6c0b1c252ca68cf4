"""``learner view-study``: does the state predict the next image better than a guess?

The filter node's ``tpsr/predicted_image`` is the image the model expects next
(:mod:`tpsr_ros.core.view_readout`). This study measures it on held-out steps: for each run
it fits the default model on a fresh random training trajectory (24000 steps, as the
headline), learns the read-outs as ``learner fit`` does, tracks a separate random
trajectory of another seed and scores, per pixel value (0-255, root mean square over the
held-out step pairs), four predictions of the image o_{k+1}:

- ``predicted``: the read-out of b_k after the action actually taken (what the node shows
  with a policy, whose action it knows);
- ``action_blind``: the read-out of b_k without the action (what a pure filter shows);
- ``mean_image``: the training images' mean (no state at all);
- ``last_image``: o_k itself (the camera's persistence, a strong guess for small moves).

``--output DIR`` writes ``view_prediction.csv`` (one row per run) there; ``--reuse`` reads
it back; both render ``view_prediction.png`` and ``view_prediction.md`` into ``--docs``.
"""

from __future__ import annotations

import argparse
import csv
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from learner.experiment import default_config
from learner.simulated import random_trajectory
from tpsr_ros.cli import positive_int
from tpsr_ros.core.errors import ConfigError
from tpsr_ros.core.learn import fit_tpsr_trajectory
from tpsr_ros.core.sizing import Sizing
from tpsr_ros.core.view_readout import fit_view_readout, next_step_pairs
from tpsr_ros.io.atomic import atomic_file

__all__ = ["PREDICTORS", "register", "run", "score_run"]

PREDICTORS = ("predicted", "action_blind", "mean_image", "last_image")
ENVIRONMENTS = ("full", "drive")
CSV_NAME = "view_prediction.csv"
COMMAND = "python -m learner view-study"


@dataclass(frozen=True)
class StudyConfig:
    """What one run of the study uses."""

    environment: str
    training_steps: int = 24_000
    held_out_steps: int = 2_000
    seed: int = 0


def score_run(config: StudyConfig) -> dict[str, Any]:
    """Fit, learn the read-outs, track the held-out run and score the four predictions."""
    experiment = default_config(config.environment)
    train = random_trajectory(config.environment, config.training_steps, config.seed)
    held = random_trajectory(config.environment, config.held_out_steps, config.seed + 10_000)
    codes = experiment.sim_config().actions.codes
    model = fit_tpsr_trajectory(train, experiment.tpsr, sizing=Sizing(), action_codes=codes)
    tracked = model.track(train.actions, train.observations)
    view = fit_view_readout(
        tracked.states, train.actions, train.observations, train.segments, train.n_actions
    )
    states = model.track(held.actions, held.observations).states
    pairs = next_step_pairs(held.segments)
    after = held.observations[pairs + 1]
    design = states[pairs]
    per_action = np.stack(
        [view.predicted_observation(s, int(a)) for s, a in zip(design, held.actions[pairs + 1],
                                                                strict=True)]
    )  # fmt: skip
    blind = design @ view.image[-1][:-1] + view.image[-1][-1]
    guesses = {
        "predicted": np.clip(per_action, 0.0, 1.0),
        "action_blind": np.clip(blind, 0.0, 1.0),
        "mean_image": np.broadcast_to(train.observations.mean(axis=0), after.shape),
        "last_image": held.observations[pairs],
    }
    row: dict[str, Any] = {
        "environment": config.environment,
        "seed": config.seed,
        "training_steps": config.training_steps,
        "held_out_pairs": len(pairs),
        "state_dim": model.state_dim,
    }
    for name, guess in guesses.items():
        row[name] = float(np.sqrt(np.mean((guess - after) ** 2)) * 255.0)
    return row


def _write_csv(path: Path, rows: list[dict[str, Any]]) -> None:
    with atomic_file(path, "w") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


def _read_csv(path: Path) -> list[dict[str, Any]]:
    if not path.is_file():
        raise ConfigError(f"{path} does not exist: run `{COMMAND} --output {path.parent}` first")
    with path.open(newline="") as handle:
        rows = list(csv.DictReader(handle))
    missing = {"environment", *PREDICTORS} - set(rows[0] if rows else {})
    if not rows or missing:
        raise ConfigError(f"{path} is not a view-study table (missing {sorted(missing)})")
    for row in rows:
        for name in PREDICTORS:
            row[name] = float(row[name])
    return rows


def _summary(values: np.ndarray) -> tuple[float, float, float]:
    """Mean, median and standard error of the mean."""
    sem = float(values.std(ddof=1) / np.sqrt(len(values))) if len(values) > 1 else float("nan")
    return float(values.mean()), float(np.median(values)), sem


def render_page(rows: list[dict[str, Any]], csv_path: Path, figure: Path) -> str:
    """The markdown page of the study's table (every number from ``rows``)."""
    lines = [
        "# What the state predicts: the next image on held-out steps",
        "",
        f"Generated by `{COMMAND} --reuse` from `{csv_path.as_posix()}` (written by "
        f"`{COMMAND} --output {csv_path.parent.as_posix()}`). Per run: the default model fitted "
        "on a fresh random training run, its read-outs learned as `learner fit` learns them, "
        "then a random run of another seed tracked; root-mean-square error per pixel value "
        "(0-255) of four guesses of the next image (see `learner/view_study.py`).",
        "",
        "| environment | runs | predicted (after the action) | action-blind | mean image | "
        "last image | predicted / mean image |",
        "|---|---|---|---|---|---|---|",
    ]
    for environment in dict.fromkeys(row["environment"] for row in rows):
        chosen = [row for row in rows if row["environment"] == environment]
        cells = []
        for name in PREDICTORS:
            mean, median, sem = _summary(np.array([row[name] for row in chosen]))
            cells.append(f"{mean:.2f} ± {sem:.2f} (median {median:.2f})")
        ratio = np.array([row["predicted"] / row["mean_image"] for row in chosen])
        cells.append(f"{np.median(ratio):.2f} (median; {ratio.min():.2f}-{ratio.max():.2f})")
        lines.append(f"| {environment} | {len(chosen)} | " + " | ".join(cells) + " |")
    lines += ["", "Mean ± SEM over runs (median in brackets).", "", f"![]({figure.name})", ""]
    return "\n".join(lines)


def render_figure(rows: list[dict[str, Any]], path: Path) -> None:
    """Bars of each guess's error per environment, each run a dot."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    environments = list(dict.fromkeys(row["environment"] for row in rows))
    fig, axes = plt.subplots(1, len(environments), figsize=(4.2 * len(environments), 3.4))
    for ax, environment in zip(np.atleast_1d(axes), environments, strict=True):
        chosen = [row for row in rows if row["environment"] == environment]
        for i, name in enumerate(PREDICTORS):
            values = np.array([row[name] for row in chosen])
            mean, _, sem = _summary(values)
            ax.bar(i, mean, yerr=sem, color=f"C{i}", alpha=0.7, capsize=3)
            ax.plot(np.full(len(values), i), values, "k.", markersize=3)
        ax.set_xticks(range(len(PREDICTORS)), [n.replace("_", "\n") for n in PREDICTORS])
        ax.set_title(f"{environment}: error of the next image ({len(chosen)} runs)")
        ax.set_ylabel("RMS error per pixel value (0-255)")
    fig.tight_layout()
    with atomic_file(path, "wb") as handle:
        fig.savefig(handle, format="png", dpi=110)
    plt.close(fig)


def register(subparsers: Any) -> None:
    """Add the ``view-study`` subcommand."""
    doc = "measure the predicted next image against guesses without a state, on held-out runs"
    parser = subparsers.add_parser("view-study", help=doc, description=__doc__)
    parser.add_argument("--output", type=Path, metavar="DIR", help="run the study: CSV here")
    parser.add_argument("--reuse", type=Path, metavar="DIR", help="render from DIR's CSV")
    parser.add_argument("--docs", type=Path, default=Path("docs"), metavar="DIR",
                        help="where the page and figure go (default: %(default)s)")  # fmt: skip
    parser.add_argument("--runs", type=positive_int, default=10, help="runs per environment")
    parser.add_argument("--first-seed", type=int, default=0, help="seed of the first run")
    parser.add_argument("--training-steps", type=positive_int, default=24_000)
    parser.add_argument("--environments", nargs="+", default=list(ENVIRONMENTS))
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Run (or reuse) the study and render its page and figure."""
    if (args.output is None) == (args.reuse is None):
        raise ConfigError("give --output DIR (run the study) or --reuse DIR (render it)")
    if args.reuse is not None:
        csv_path = args.reuse / CSV_NAME
        rows = _read_csv(csv_path)
    else:
        csv_path = args.output / CSV_NAME
        rows = []
        for environment in args.environments:
            for seed in range(args.first_seed, args.first_seed + args.runs):
                row = score_run(StudyConfig(environment, args.training_steps, seed=seed))
                print(
                    f"{environment} seed {seed}: "
                    + ", ".join(f"{n} {row[n]:.2f}" for n in PREDICTORS),
                    file=sys.stderr,
                    flush=True,
                )
                rows.append(row)
        args.output.mkdir(parents=True, exist_ok=True)
        _write_csv(csv_path, rows)
    args.docs.mkdir(parents=True, exist_ok=True)
    figure = args.docs / "view_prediction.png"
    render_figure(rows, figure)
    page = args.docs / "view_prediction.md"
    with atomic_file(page, "w") as handle:
        handle.write(render_page(rows, csv_path, figure))
    print(f"wrote {page} and {figure}")
    return 0
