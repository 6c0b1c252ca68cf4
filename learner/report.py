"""``learner report``: regenerate ``docs/results.md`` from the three environments' experiments.

Runs ``learner experiment`` for ``full``, ``partial`` and ``distractors`` with the default
grid (or reuses their CSVs with ``--reuse``), then writes the results page: the summary
table of every environment next to what the guide reports, and the plots.
"""

from __future__ import annotations

import argparse
import csv
import shutil
import sys
import time
from pathlib import Path
from typing import Any

from learner.experiment import (
    Row,
    default_config,
    plot_summary,
    run_experiment,
    summarise,
    write_csv,
)
from tpsr_ros.cli import positive_int
from tpsr_ros.core.errors import ConfigError

__all__ = ["GUIDE_RESULTS", "register", "run", "write_page"]

ENVIRONMENTS = ("full", "partial", "distractors")

GUIDE_RESULTS = {
    "full": "TPSR (dim 3): good mean reward and a consistently high median, slightly below "
    "PCA; PCA (dim 2): median close to the maximum at every data size, means dented by "
    "single failures (figure 4.5). 5-dimensional TPSRs with many centres: reliably close "
    "to the maximum of ~470 from 5000 episodes on (figure 4.11).",
    "partial": "PCA: half of the trials below zero, mean slightly above zero; TPSR: "
    "remarkably better, best around 6000 episodes, but volatile (figure 4.8).",
    "distractors": "PCA: barely any reward above zero; TPSR: mean about 300, medians above "
    "(figure 4.7).",
}


def _read_rows(path: Path) -> list[Row]:
    with path.open() as handle:
        rows = []
        for raw in csv.DictReader(handle):
            typed: dict[str, Any] = {}
            for name, value in raw.items():
                field_type = Row.__dataclass_fields__[name].type
                typed[name] = {"int": int, "float": float}.get(str(field_type), str)(value)
            rows.append(Row(**typed))
    return rows


def _table_markdown(table: list[dict[str, Any]]) -> list[str]:
    lines = [
        "| method | episodes | runs | mean | median | SEM | failed |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for t in table:
        lines.append(
            f"| {t['method']} | {t['episodes']} | {t['runs']} | {t['mean']:.1f} | "
            f"{t['median']:.1f} | {t['sem']:.1f} | {t['failed']} |"
        )
    return lines


def write_page(tables: dict[str, list[dict[str, Any]]], docs: Path, command: str) -> Path:
    """Write ``docs/results.md`` from per-environment summary tables."""
    lines = [
        "# Results: the guide's learning-planning loop (section 4.2)",
        "",
        f"Regenerate with `{command}` (about 6 minutes on 2 cores); it also writes",
        "`results/experiment_<environment>.csv`, one row per run with all its seeds, from",
        "which any run reruns alone: `python -m learner experiment --environment E",
        "--episodes N --first-repetition K --repetitions 1`.",
        "",
        "Protocol (DESIGN.md, guide 4.1-4.2): for each data size, 10 independent random",
        "training trajectories (3 steps per episode); a TPSR with the guide's fully observable",
        "settings and rank 5 (section 4.3), and the PCA baseline (2 components in `full`, 3",
        "otherwise), each learned from the same data; states tracked with the model's",
        "parameters over one separate random RL trajectory (15000 steps in `full`, 20000",
        "otherwise); fitted Q-iteration (100 RBF centres, ridge 1e-2, discount 0.9); the",
        "standard evaluation (10 fixed starts, 50 greedy steps; score = mean summed reward,",
        "at most about 470). The true position is the upper bound of the RL step.",
        "",
    ]
    for environment, table in tables.items():
        lines += [f"## `{environment}`", "", *_table_markdown(table), ""]
        lines += [f"Guide: {GUIDE_RESULTS[environment]}", ""]
        lines += [f"![{environment}](results_{environment}.png)", ""]
    target = docs / "results.md"
    existing = target.read_text() if target.exists() else ""
    marker = "<!-- discussion -->"
    discussion = existing[existing.index(marker) :] if marker in existing else f"{marker}\n"
    target.write_text("\n".join(lines) + "\n" + discussion)
    return target


def register(subparsers: Any) -> None:
    """Add the ``report`` subcommand."""
    doc = "run the experiments of all three environments and regenerate docs/results.md"
    parser = subparsers.add_parser("report", help=doc, description=doc[0].upper() + doc[1:] + ".")
    parser.add_argument(
        "--results",
        type=Path,
        default=Path("results"),
        help="directory of the experiment CSVs (default: results)",
    )
    parser.add_argument("--docs", type=Path, default=Path("docs"), help="(default: docs)")
    parser.add_argument(
        "--reuse",
        action="store_true",
        help="reuse existing experiment_<env>.csv instead of running",
    )
    parser.add_argument("--workers", type=positive_int, default=2)
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Run or reuse the experiments, then write the page and its plots."""
    if not args.docs.is_dir():
        raise ConfigError(f"docs directory {str(args.docs)!r} does not exist")
    args.results.mkdir(parents=True, exist_ok=True)
    tables = {}
    for environment in ENVIRONMENTS:
        path = args.results / f"experiment_{environment}.csv"
        if args.reuse:
            if not path.exists():
                raise ConfigError(f"{path} does not exist; run without --reuse")
            rows = _read_rows(path)
        else:
            start = time.perf_counter()
            rows = run_experiment(default_config(environment), workers=args.workers)
            write_csv(rows, path)
            print(f"{environment}: {time.perf_counter() - start:.0f} s", file=sys.stderr)
        tables[environment] = summarise(rows)
        plot = args.results / f"experiment_{environment}.png"
        plot_summary(tables[environment], environment, plot)
        shutil.copyfile(plot, args.docs / f"results_{environment}.png")
    page = write_page(tables, args.docs, "python -m learner report")
    print(f"wrote {page}", file=sys.stderr)
    return 0
