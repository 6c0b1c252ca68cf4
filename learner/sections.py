"""What every section of the results page's appendix shares: the section, its cells, and the
summaries of a ``learner study`` CSV by value.

Pure functions of the rows of :mod:`learner.tables`; :mod:`learner.appendix` and
:mod:`learner.camera_study` build their sections from them.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from learner.jobs import Job
from learner.overrides import convert
from learner.tables import Row, difference_in_sems, summarise
from learner.verdicts import DIFFERENCE_SEMS

__all__ = [
    "SELECTION_EPISODES",
    "Data",
    "Section",
    "cell",
    "comparison",
    "finite_median",
    "judged",
    "mean_text",
    "median_text",
    "row_parameters",
    "study_entries",
    "varied",
]

SELECTION_EPISODES = {
    "full": 2000,
    "partial": 8000,
    "distractors": 8000,
    "partial-strip": 8000,
    "drive": 8000,
}
"""Data size of every study: the smallest of the headline in ``full`` (at 8000 episodes every
setting is at the ceiling there), the largest elsewhere."""

Data = Mapping[Job, list[Row]]


@dataclass(frozen=True)
class Section:
    """One study: its question, the jobs that write its CSVs, and how it is rendered."""

    key: str
    title: str
    question: str
    jobs: tuple[Job, ...]
    render: Callable[[Section, Data], list[str]]
    commands: str = ""
    """What to say instead of listing the commands (when they are another section's)."""

    def lines(self, data: Data) -> list[str]:
        """The section as markdown: title, question, commands, table and verdict."""
        commands = self.commands or "\n".join(
            ["**Commands** (selection seeds):", "", "```sh", *(j.command for j in self.jobs), "```"]
        )
        return [
            f"### {self.title}",
            "",
            f"**Question.** {self.question}",
            "",
            commands,
            "",
            *self.render(self, data),
            "",
        ]


def cell(entry: Mapping[str, Any] | None) -> str:
    """``mean / median / SEM`` of a summary entry (and its failed runs), ``-`` when absent."""
    if entry is None or not math.isfinite(entry["mean"]):
        return "-"
    text = f"{entry['mean']:.1f} / {entry['median']:.1f} / {entry['sem']:.1f}"
    return text + (f" ({entry['failed']} failed)" if entry["failed"] else "")


def row_parameters(row: Row) -> dict[str, Any]:
    """The run's parameters (its CSV column, JSON) as a dict."""
    return json.loads(row.parameters) if row.parameters else {}


def mean_text(values: Sequence[float], fmt: str) -> str:
    """The mean of the finite ``values`` formatted with ``fmt``, ``-`` when there are none."""
    finite = [v for v in values if math.isfinite(v)]
    return format(float(np.mean(finite)), fmt) if finite else "-"


def finite_median(values: Sequence[float]) -> float | None:
    """The median of the finite ``values``, None when there are none."""
    finite = [v for v in values if math.isfinite(v)]
    return float(np.median(finite)) if finite else None


def median_text(values: Sequence[float], fmt: str) -> str:
    """The median of the finite ``values`` formatted with ``fmt``, ``-`` when there are none."""
    median = finite_median(values)
    return "-" if median is None else format(median, fmt)


def comparison(entry: Mapping[str, Any], base: Mapping[str, Any]) -> tuple[float, float]:
    """``(mean difference, its size in SEMs of the difference)`` of two summary entries."""
    return entry["mean"] - base["mean"], difference_in_sems(dict(entry), dict(base))


def judged(difference: float, sems: float) -> str:
    """A difference and its SEMs as a table cell, saying whether it lies outside the noise."""
    if not math.isfinite(difference):
        return "not measured"
    if not math.isfinite(sems):  # every run of both scored alike
        return f"{difference:+.1f} (no spread between runs)"
    noise = "within the noise" if abs(sems) <= DIFFERENCE_SEMS else "outside the noise"
    return f"{difference:+.1f} ({sems:+.1f} SEM, {noise})"


def varied(job: Job) -> tuple[str, list[str]]:
    """The parameter a ``learner study`` job varies and its values, as written."""
    text = str(job.option("--vary"))
    name, values = text.split("=", 1)
    return name, values.split(",")


def r2_text(runs: list[Row]) -> str:
    """The runs' mean affine R² of x / y, and of the heading in brackets where measured (a
    robot that turns)."""
    r2_x, r2_y = (mean_text([getattr(r, a) for r in runs], ".2f") for a in ("r2_x", "r2_y"))
    heading = mean_text([r.r2_heading for r in runs], ".2f")
    return f"{r2_x} / {r2_y}" + ("" if heading == "-" else f" ({heading})")


def study_entries(
    job: Job, rows: list[Row]
) -> tuple[list[dict[str, Any]], dict[tuple[str, str], dict[str, Any]]]:
    """Reference entries (floors, ceiling run once) and ``{(value, method): entry}``."""
    name, values = varied(job)
    group, field = name.split(".", 1)
    typed = {value: convert(name, value) for value in values}
    by_value: dict[tuple[str, str], dict[str, Any]] = {}
    reference = [r for r in rows if field not in row_parameters(r).get(group, {})]
    for value, parsed in typed.items():
        mine = [r for r in rows if row_parameters(r).get(group, {}).get(field, None) == parsed]
        for entry in summarise(mine):
            runs = [r for r in mine if r.method == entry["method"]]
            entry["r2"] = r2_text(runs)
            entry["position_error"] = median_text([r.position_error for r in runs], ".2f")
            entry["memory"] = median_text([r.memory for r in runs], "g")
            entry["memory_paths"] = median_text([r.memory_paths for r in runs], "g")
            by_value[(value, entry["method"])] = entry
    return summarise(reference), by_value
