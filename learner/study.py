"""``learner study --environment E --vary NAME=V1,V2,...``: a parameter study (guide 4.3).

One :mod:`learner.experiment` grid per value of one fit, fitted-Q or simulator parameter
(any ``--set`` name), everything else held fixed: the learned method the parameter belongs
to (``tpsr.*`` and ``fqi.*``: the TPSR; ``pca.*``: PCA; ``stacked.*`` and ``window.*``:
those baselines; ``sim.*``, the camera: TPSR and PCA;
``--methods`` for others, e.g. PCA under each fitted-Q setting too) at every value, and
once beside them
the floors (best constant action, random actions) and the ceiling (true position; at every
value when the parameter is a fitted-Q one, since the ceiling plans with it too). Writes
``study_<env>_<name>.csv`` (every run, its parameters as JSON) and ``.png`` (score and the
affine R² of the true position against the value, like guide figures 4.9-4.12), and
prints one line per value and data size.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from learner.experiment import (
    add_grid_options,
    config_from_args,
    prepare_outputs,
    run_experiment,
)
from learner.floors import CONSTANT, RANDOM
from learner.overrides import parse_assignment, resolve
from learner.tables import summarise, write_csv
from tpsr_ros.core.errors import ConfigError
from tpsr_ros.io.policy import TRUE_POSITION

__all__ = ["StudyPoint", "parse_values", "register", "run", "run_study"]

StudyPoint = tuple[str, list[Any]]
"""A value of the varied parameter and the runs made with it (``Row`` objects)."""


def parse_values(text: str) -> tuple[str, list[str]]:
    """``"NAME=V1,V2,..."`` -> ``(qualified NAME, [V1, V2, ...])``, at least two values."""
    name, values = parse_assignment(text)
    group, field = resolve(name)
    items = [v.strip() for v in values.split(",")]
    if len(items) < 2 or not all(items) or len(set(items)) != len(items):
        raise ConfigError(f"--vary {text!r}: give two or more distinct values, comma-separated")
    return f"{group}.{field}", items


def run_study(
    args: argparse.Namespace, name: str, values: Sequence[str], *, workers: int
) -> tuple[list[Any], list[StudyPoint]]:
    """Floors (and the ceiling) once, then the parameter's method at every value."""
    group = name.split(".", 1)[0]
    default = {
        "pca": ["pca"],
        "sim": ["tpsr", "pca"],
        "stacked": ["stacked-pca"],
        "window": ["window"],
    }.get(group, ["tpsr"])
    learned = list(args.methods or default)
    once = [CONSTANT, RANDOM] if group == "fqi" else [CONSTANT, RANDOM, TRUE_POSITION]
    if group == "fqi" and TRUE_POSITION not in learned:
        learned.append(TRUE_POSITION)
    # validate every value before any run: a typo must not cost the first values' hours
    configs = [config_from_args(args, learned, [*args.assignments, f"{name}={v}"]) for v in values]
    reference = run_experiment(config_from_args(args, once, args.assignments), workers=workers)
    points = [(v, run_experiment(c, workers=workers)) for v, c in zip(values, configs, strict=True)]
    return reference, points


def _table(points: Sequence[StudyPoint]) -> list[dict[str, Any]]:
    """Summary rows per (value, method, data size) with the mean affine R² in x and y."""
    table = []
    for value, rows in points:
        for entry in summarise(rows):
            key = (entry["method"], entry["episodes"])
            mine = [r for r in rows if (r.method, r.episodes) == key]
            r2 = np.array([(r.r2_x, r.r2_y) for r in mine], dtype=float)
            r2_mean = np.nanmean(r2, axis=0) if np.isfinite(r2).any() else np.full(2, np.nan)
            table.append({**entry, "value": value, "r2_x": r2_mean[0], "r2_y": r2_mean[1]})
    return table


def format_lines(
    name: str, reference: list[dict[str, Any]], table: list[dict[str, Any]]
) -> list[str]:
    """Aligned text: the floors and ceiling, then one line per value and data size."""
    lines = [f"{'method':14s} {'episodes':>8s} {'mean':>7s} {'median':>7s} {'sem':>6s}"]
    lines += [
        f"{t['method']:14s} {t['episodes']:8d} {t['mean']:7.1f} {t['median']:7.1f} {t['sem']:6.1f}"
        for t in reference
    ]
    lines.append(
        f"{name:>22s} {'method':14s} {'episodes':>8s} {'runs':>4s} {'mean':>7s} {'median':>7s} "
        f"{'sem':>6s} {'failed':>6s} {'R2 x':>5s} {'R2 y':>5s}"
    )
    lines += [
        f"{t['value']:>22s} {t['method']:14s} {t['episodes']:8d} {t['runs']:4d} {t['mean']:7.1f} "
        f"{t['median']:7.1f} {t['sem']:6.1f} {t['failed']:6d} {t['r2_x']:5.2f} {t['r2_y']:5.2f}"
        for t in table
    ]
    return lines


def plot_study(
    name: str,
    environment: str,
    reference: list[dict[str, Any]],
    table: list[dict[str, Any]],
    path: Path,
) -> None:
    """Score (mean with SEM bars, median) and R² against the value, per data size."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    values = list(dict.fromkeys(t["value"] for t in table))
    x = np.arange(len(values))
    fig, (score_ax, r2_ax) = plt.subplots(1, 2, figsize=(10, 4.2))
    for episodes in sorted({t["episodes"] for t in table}):
        for method in dict.fromkeys(t["method"] for t in table):
            part = {
                t["value"]: t for t in table if (t["method"], t["episodes"]) == (method, episodes)
            }
            rows = [part[v] for v in values]
            label = f"{method}, {episodes} episodes"
            mean = np.array([t["mean"] for t in rows])
            score_ax.errorbar(
                x, mean, yerr=np.nan_to_num([t["sem"] for t in rows]), fmt="-o", capsize=3,
                label=f"{label}: mean ± SEM",
            )
            score_ax.plot(x, [t["median"] for t in rows], "x--", label=f"{label}: median")
            if method != TRUE_POSITION:
                r2_ax.plot(x, [t["r2_x"] for t in rows], "-o", label=f"{label}: x")
                r2_ax.plot(x, [t["r2_y"] for t in rows], "-s", label=f"{label}: y")
    for entry, style in zip(reference, ("--", ":", "-."), strict=False):
        score_ax.axhline(
            entry["mean"], color="gray", ls=style, lw=1,
            label=f"{entry['method']} ({entry['episodes']}): {entry['mean']:.1f}",
        )
    for ax, ylabel in ((score_ax, "mean reward of 10 trials"), (r2_ax, "affine R² of position")):
        ax.set_xticks(x, values)
        ax.set_xlabel(name)
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=6)
    r2_ax.set_ylim(0, 1)
    fig.suptitle(f"{environment}: {name}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def register(subparsers: Any) -> None:
    """Add the ``study`` subcommand."""
    doc = "vary one fit, fitted-Q or simulator parameter over experiment grids (guide 4.3)"
    parser = subparsers.add_parser(
        "study", help=doc, description=doc[0].upper() + doc[1:] + ". " + __doc__.split("\n\n")[1]
    )
    add_grid_options(parser)
    parser.add_argument(
        "--vary",
        required=True,
        metavar="NAME=V1,V2,...",
        help="the parameter (any --set name) and its values, e.g. tpsr.sigma_ht=1,2,4",
    )
    parser.add_argument(
        "--methods",
        nargs="+",
        choices=("tpsr", "pca"),
        default=None,
        help="learned representations run at every value (default: the one the parameter "
        "belongs to, the TPSR for fitted-Q parameters, both for the simulator's)",
    )
    parser.add_argument(
        "-o", "--output", type=Path, default=Path("results"),
        help="directory for study_<env>_<name>.csv/.png (default: results)",
    )
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Run the study, write CSV and PNG, print the table."""
    name, values = parse_values(args.vary)
    stem = f"study_{args.environment}_{name.replace('.', '_')}"
    csv_path, png_path = prepare_outputs(args.output, stem, args.force)
    start = time.perf_counter()
    reference_rows, points = run_study(args, name, values, workers=args.workers)
    reference, table = summarise(reference_rows), _table(points)
    write_csv(reference_rows + [row for _, rows in points for row in rows], csv_path)
    plot_study(name, args.environment, reference, table, png_path)
    print("\n".join(format_lines(name, reference, table)))
    runs = len(reference_rows) + sum(len(rows) for _, rows in points)
    elapsed = time.perf_counter() - start
    print(f"{runs} runs in {elapsed:.0f} s; wrote {csv_path} and {png_path}", file=sys.stderr)
    return 0
