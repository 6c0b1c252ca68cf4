"""Experiment runs as rows: their CSV files, summaries (mean, median, SEM, margin over the
best floor per method and data size; the floors pooled over every data size), text tables
and plots.

One :class:`Row` is one learning-planning run of :mod:`learner.experiment`; a CSV holds one
row per run with every seed and parameter, so any run reruns alone.
"""

from __future__ import annotations

import csv
import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from learner.floors import CONSTANT, FLOORS, RANDOM
from tpsr_ros.core.errors import ConfigError
from tpsr_ros.io.policy import TRUE_POSITION

__all__ = [
    "DEFAULT_METHODS",
    "METHODS",
    "PAST_BASELINES",
    "Row",
    "difference_in_sems",
    "format_table",
    "margin_text",
    "plot_summary",
    "pooled_floors",
    "read_csv",
    "score_statistics",
    "summarise",
    "write_csv",
]

PAST_BASELINES = ("stacked-pca", "window")
"""Baselines that carry the past (:mod:`tpsr_ros.core.window_baselines`)."""

METHODS = (CONSTANT, RANDOM, "tpsr", "pca", *PAST_BASELINES, TRUE_POSITION)
"""Every method of an experiment, in table order: floors, learned representations, ceiling."""

DEFAULT_METHODS = (CONSTANT, RANDOM, "tpsr", "pca", TRUE_POSITION)
"""The methods an experiment runs unless ``--methods`` names others: the baselines that
carry the past run on request, so the default grids keep their cost and their CSVs."""


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
    preset: str = ""
    command: str = ""
    """The ``learner experiment`` command of this run's grid (:func:`experiment_command`)."""
    memory: float = float("nan")
    """Steps the model remembers (``--memory``; the smaller of :mod:`learner.memory`'s two
    variants), NaN when not measured."""
    memory_distance: float = float("nan")
    """Relative distance of the two ``paths`` states at their first identical step."""
    criterion: float = float("nan")
    """``learner tune``'s criterion of the run's TPSR configuration (``--criterion``)."""
    trial_ends: str = ""
    """Per trial, ``x,y,n``: where the robot stood after the last step and for how many of
    the last steps it had not moved (``;``-separated; empty in CSVs written before)."""
    r2_heading: float = float("nan")
    """R² of the heading's unit vector (cos, sin) from the states' affine map, both
    components pooled: a robot that turns (``drive``) only, NaN otherwise and in CSVs
    written before."""
    loop_position_error: float = float("nan")
    """Median error (m) of locating the robot among the RL states from the states the
    policy acted on in the scored trials (:func:`learner.plots.loop_position_error`): the
    filter's grip on where the robot is under the policy's own actions, beside
    ``position_error`` on the random RL run. NaN for the floors and in CSVs written
    before."""
    trial_goal: str = ""
    """Per trial, ``s,c``: the step at which the robot first stood in the goal zone (0:
    never) and how many of its steps a wall blocked (``;``-separated; empty in CSVs
    written before)."""
    memory_paths: float = float("nan")
    """Steps the ``paths`` variant of :mod:`learner.memory` alone remembers (``--memory``;
    ``memory`` is the smaller of both variants), NaN when not measured and in CSVs
    written before."""


def score_statistics(scores: np.ndarray) -> dict[str, Any]:
    """Runs, failed runs (non-finite scores), mean, median and SEM of the finite ones."""
    ok = scores[np.isfinite(scores)]
    return {
        "runs": len(scores),
        "failed": int(len(scores) - len(ok)),
        "mean": float(ok.mean()) if len(ok) else float("nan"),
        "median": float(np.median(ok)) if len(ok) else float("nan"),
        "sem": float(ok.std(ddof=1) / np.sqrt(len(ok))) if len(ok) > 1 else float("nan"),
    }


def pooled_floors(rows: Sequence[Row]) -> dict[str, dict[str, Any]]:
    """One entry per floor over all its runs, whatever their data size.

    A floor is blind to the state and learns nothing, so its runs at different data sizes
    are repetitions of one measurement: pooled, they give one mean, median and SEM per
    environment instead of a noise that would read as a trend. ``sizes`` is the number of
    data sizes pooled.
    """
    pooled = {}
    for method in FLOORS:
        scores = np.array([r.score for r in rows if r.method == method])
        if len(scores):
            sizes = len({r.episodes for r in rows if r.method == method})
            pooled[method] = {"method": method, "sizes": sizes, **score_statistics(scores)}
    return pooled


def summarise(rows: Sequence[Row]) -> list[dict[str, Any]]:
    """Mean, median, SEM and failures per (method, data size), and each margin over the floor.

    For every method that is not a floor, ``floor`` names the best floor (highest mean) of
    :func:`pooled_floors`, each floor pooled over all its runs since it uses no data, and
    ``margin_sem`` is ``(mean - floor mean) / sqrt(SEM^2 + floor SEM^2)``: how many
    standard errors of the difference the method lies above it (NaN when no floor ran).
    The floors' own entries stay per data size, as run.
    """
    table = []
    keys = sorted({(r.method, r.episodes) for r in rows}, key=lambda k: (METHODS.index(k[0]), k[1]))
    for method, episodes in keys:
        scores = np.array([r.score for r in rows if (r.method, r.episodes) == (method, episodes)])
        table.append({"method": method, "episodes": episodes, **score_statistics(scores)})
    floors = [f for f in pooled_floors(rows).values() if np.isfinite(f["mean"])]
    best = max(floors, key=lambda t: t["mean"], default=None)
    for entry in table:
        entry["floor"], entry["margin_sem"] = "", float("nan")
        if entry["method"] in FLOORS or best is None:
            continue
        entry["floor"] = best["method"]
        entry["margin_sem"] = difference_in_sems(entry, best)
    return table


def difference_in_sems(a: dict[str, Any], b: dict[str, Any]) -> float:
    """``(mean_a - mean_b) / sqrt(SEM_a^2 + SEM_b^2)`` of two summary entries.

    A missing SEM (one run) counts as 0; with both 0 (up to rounding) the result is +-inf
    (or nan when the means are equal).
    """
    spread = float(np.hypot(np.nan_to_num(a["sem"]), np.nan_to_num(b["sem"])))
    difference = a["mean"] - b["mean"]
    if spread > 1e-9 * max(1.0, abs(a["mean"]), abs(b["mean"])):  # not rounding noise
        return difference / spread
    return float("nan") if difference == 0 else float(np.copysign(np.inf, difference))


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


def read_csv(path: Path) -> list[Row]:
    """The rows :func:`write_csv` wrote; columns added since default to their field's default."""
    converters = {"int": int, "float": float}
    fields = Row.__dataclass_fields__
    with path.open(newline="") as handle:
        reader = csv.DictReader(handle)
        if unknown := sorted(set(reader.fieldnames or ()) - set(fields)):
            raise ConfigError(f"{path}: unknown columns {unknown}; not an experiment CSV")
        rows = []
        for line, raw in enumerate(reader, start=2):
            try:
                typed = {k: converters.get(str(fields[k].type), str)(v) for k, v in raw.items()}
                rows.append(Row(**typed))
            except (TypeError, ValueError) as exc:
                raise ConfigError(f"{path}, line {line}: {exc}") from None
    return rows


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
        "stacked-pca": "tab:cyan",
        "window": "tab:purple",
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
