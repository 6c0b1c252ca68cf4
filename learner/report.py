"""``learner report``: regenerate ``docs/results.md`` from the three environments' experiments.

Runs ``learner experiment`` for ``full``, ``partial`` and ``distractors`` with the default
grid and every method (or reuses their CSVs with ``--reuse``), then writes the results
page: per environment the floors, the learned representations and the ceiling side by
side (mean, median, SEM, margin over the best floor in SEMs), the plots, and a table of
the guide's findings with what was measured and a verdict computed by fixed rules:

- a learned representation *works* only where its mean lies more than ``FLOOR_SEMS`` (3)
  standard errors of the difference above the best floor: nothing inside the floor's
  reach supports a claim;
- one method *beats* another where its mean lies more than ``DIFFERENCE_SEMS`` (2)
  standard errors of the difference above the other's;
- *close to the ceiling* means a mean of at least ``NEAR_CEILING`` (95 %) of the true
  position's, *near the floor* at most ``NEAR_FLOOR`` (25 %) of it.
"""

from __future__ import annotations

import argparse
import csv
import math
import shutil
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from learner.experiment import (
    Row,
    default_config,
    difference_in_sems,
    margin_text,
    plot_summary,
    run_experiment,
    summarise,
    write_csv,
)
from learner.floors import FLOORS
from tpsr_ros.cli import positive_int
from tpsr_ros.core.errors import ConfigError
from tpsr_ros.io.policy import TRUE_POSITION

__all__ = ["FINDINGS", "GUIDE_RESULTS", "Finding", "judge", "register", "run", "write_page"]

ENVIRONMENTS = ("full", "partial", "distractors")
FLOOR_SEMS = 3.0
DIFFERENCE_SEMS = 2.0
NEAR_CEILING = 0.95
NEAR_FLOOR = 0.25
SLIGHTLY = 0.9

REPRODUCED, NOT_REPRODUCED, BETTER = "reproduced", "not reproduced", "better"

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

Table = list[dict[str, Any]]


def _entries(table: Table, method: str) -> list[dict[str, Any]]:
    return [t for t in table if t["method"] == method and math.isfinite(t["mean"])]


def _works(entry: dict[str, Any]) -> bool:
    return bool(entry.get("floor")) and entry["margin_sem"] > FLOOR_SEMS


def _ceiling(table: Table, episodes: int) -> float:
    found = [t["mean"] for t in _entries(table, TRUE_POSITION) if t["episodes"] == episodes]
    return found[0] if found else math.nan


def _by_size(table: Table, method: str) -> str:
    return ", ".join(
        f"{t['episodes']}: {t['mean']:.0f} (median {t['median']:.0f}, {margin_text(t)})"
        for t in _entries(table, method)
    )


def _pca_near_maximum(table: Table) -> tuple[str, str]:
    pca = _entries(table, "pca")
    ok = pca and all(
        t["median"] >= NEAR_CEILING * _ceiling(table, t["episodes"]) and _works(t) for t in pca
    )
    return f"PCA mean by data size {_by_size(table, 'pca')}", REPRODUCED if ok else NOT_REPRODUCED


def _tpsr_slightly_below_pca(table: Table) -> tuple[str, str]:
    """Reproduced where the TPSR works and lies within ``SLIGHTLY`` of PCA at every size."""
    pairs = _pairs(table, "tpsr", "pca")
    if not pairs:
        return "not measured", NOT_REPRODUCED
    gaps = [difference_in_sems(t, p) for t, p in pairs]
    text = _gap_text(pairs, gaps)
    if not all(_works(t) for t, _ in pairs):
        return text, NOT_REPRODUCED
    if all(g > DIFFERENCE_SEMS for g in gaps):
        return text, BETTER
    close = all(t["mean"] >= SLIGHTLY * p["mean"] for t, p in pairs)
    return text, REPRODUCED if close else NOT_REPRODUCED


def _pairs(table: Table, a: str, b: str) -> list[tuple[dict[str, Any], dict[str, Any]]]:
    """Entries of methods ``a`` and ``b`` at the same data sizes."""
    return [
        (x, y)
        for x in _entries(table, a)
        for y in _entries(table, b)
        if x["episodes"] == y["episodes"]
    ]


def _gap_text(pairs: list[tuple[dict[str, Any], dict[str, Any]]], gaps: list[float]) -> str:
    return "TPSR - PCA by data size: " + ", ".join(
        f"{t['episodes']}: {t['mean'] - p['mean']:+.0f} ({g:+.1f} SEM)"
        for (t, p), g in zip(pairs, gaps, strict=True)
    )


def _tpsr_near_maximum_from_5000(table: Table) -> tuple[str, str]:
    late = [t for t in _entries(table, "tpsr") if t["episodes"] >= 5000]
    if not late:
        return "no data size of 5000 episodes or more", NOT_REPRODUCED
    ok = all(t["mean"] >= NEAR_CEILING * _ceiling(table, t["episodes"]) and _works(t) for t in late)
    text = "TPSR from 5000 episodes: " + ", ".join(
        f"{t['episodes']}: mean {t['mean']:.0f} = {t['mean'] / _ceiling(table, t['episodes']):.0%}"
        f" of the ceiling, SEM {t['sem']:.1f}"
        for t in late
    )
    return text, REPRODUCED if ok else NOT_REPRODUCED


def _pca_near_floor(table: Table) -> tuple[str, str]:
    pca = _entries(table, "pca")
    low = pca and all(t["mean"] <= NEAR_FLOOR * _ceiling(table, t["episodes"]) for t in pca)
    return f"PCA by data size {_by_size(table, 'pca')}", REPRODUCED if low else NOT_REPRODUCED


def _tpsr_beats_pca(table: Table) -> tuple[str, str]:
    """Reproduced where the TPSR works and beats PCA at every data size."""
    pairs = _pairs(table, "tpsr", "pca")
    gaps = [difference_in_sems(t, p) for t, p in pairs]
    ok = pairs and all(
        g > DIFFERENCE_SEMS and _works(t) for (t, _), g in zip(pairs, gaps, strict=True)
    )
    return _gap_text(pairs, gaps), REPRODUCED if ok else NOT_REPRODUCED


def _tpsr_about_300(table: Table) -> tuple[str, str]:
    tpsr = _entries(table, "tpsr")
    if not tpsr:
        return "not measured", NOT_REPRODUCED
    best = max(tpsr, key=lambda t: t["mean"])
    text = f"TPSR by data size {_by_size(table, 'tpsr')}"
    if not _works(best) or best["mean"] < 250:
        return text, NOT_REPRODUCED
    return text, BETTER if best["mean"] > 350 and best["median"] > best["mean"] else REPRODUCED


@dataclass(frozen=True)
class Finding:
    """One finding of the guide and the rule that judges it against a summary table."""

    environment: str
    claim: str
    judge: Callable[[Table], tuple[str, str]]


FINDINGS = (
    Finding(
        "full",
        "PCA (dim 2): median close to the maximum at every data size (fig. 4.5)",
        _pca_near_maximum,
    ),
    Finding("full", "TPSR: works, slightly below PCA (fig. 4.5)", _tpsr_slightly_below_pca),
    Finding(
        "full",
        "5-dim TPSR with many centres: close to the maximum from 5000 episodes "
        "on, low SEM (fig. 4.11)",
        _tpsr_near_maximum_from_5000,
    ),
    Finding(
        "partial",
        "PCA: mean slightly above zero, half of the runs below zero (fig. 4.8)",
        _pca_near_floor,
    ),
    Finding("partial", "TPSR: remarkably better than PCA (fig. 4.8)", _tpsr_beats_pca),
    Finding("distractors", "PCA: barely any reward above zero (fig. 4.7)", _pca_near_floor),
    Finding("distractors", "TPSR: mean about 300, medians above (fig. 4.7)", _tpsr_about_300),
    Finding("distractors", "TPSR better than PCA (fig. 4.7)", _tpsr_beats_pca),
)


def judge(tables: dict[str, Table]) -> list[tuple[Finding, str, str]]:
    """``(finding, measured, verdict)`` for every finding whose environment was run."""
    return [(f, *f.judge(tables[f.environment])) for f in FINDINGS if f.environment in tables]


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


def _table_markdown(table: Table) -> list[str]:
    lines = [
        "| method | episodes | runs | mean | median | SEM | failed | margin over floor (SEMs) |",
        "|---|---:|---:|---:|---:|---:|---:|---|",
    ]
    for t in table:
        role = (
            " (floor)"
            if t["method"] in FLOORS
            else (" (ceiling)" if t["method"] == TRUE_POSITION else "")
        )
        lines.append(
            f"| {t['method']}{role} | {t['episodes']} | {t['runs']} | {t['mean']:.1f} | "
            f"{t['median']:.1f} | {t['sem']:.1f} | {t['failed']} | {margin_text(t)} |"
        )
    return lines


def _findings_markdown(tables: dict[str, Table]) -> list[str]:
    lines = [
        "| environment | guide's finding | measured here | verdict |",
        "|---|---|---|---|",
    ]
    for finding, measured, verdict in judge(tables):
        lines.append(f"| `{finding.environment}` | {finding.claim} | {measured} | {verdict} |")
    return lines


def write_page(tables: dict[str, Table], docs: Path, command: str) -> Path:
    """Write ``docs/results.md`` from per-environment summary tables."""
    lines = [
        "# Results: the guide's learning-planning loop (section 4.2)",
        "",
        f"Regenerate with `{command}` (about 10 minutes on 2 cores; `--reuse` rewrites the",
        "page from existing CSVs in seconds); it also writes",
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
        "at most about 470). Reward (DESIGN.md): +10 for a free step ending within 15 m of",
        "the north-east corner; a step blocked by a wall earns -1 and nothing else, in the",
        "goal zone too.",
        "",
        "Every table puts the learned representations between their floors and their",
        "ceiling. Floors: `constant`, the best of the 25 constant actions under the same",
        "protocol (deterministic: its SEM is 0), and `random`, uniformly random actions",
        "seeded per run. Ceiling: `true-position`, the RL step on the true position. The",
        "margin is `(mean - best floor mean) / sqrt(SEM^2 + floor SEM^2)`.",
        "",
        "## The guide's findings, measured",
        "",
        "Verdicts follow fixed rules (`learner/report.py`): a representation *works* only",
        f"more than {FLOOR_SEMS:g} SEMs above the best floor; one method *beats* another by",
        f"more than {DIFFERENCE_SEMS:g} SEMs of the difference; *close to the maximum* is at",
        f"least {NEAR_CEILING:.0%} of the ceiling, *near zero* at most {NEAR_FLOOR:.0%} of it,",
        f"*slightly below* at least {SLIGHTLY:.0%} of the other's mean; a finding must hold at",
        "every data size.",
        "",
        *_findings_markdown(tables),
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
