"""The results page's section on learning on the robot: the learner node's time to competence.

Ten exploring runs per environment (``learner competence``, seeds never used to choose
anything), each version the learner node makes of a run scored by the standard
evaluation, beside the headline's floors and ceiling for the same environment. Competence
is reaching 90 % of the ceiling (fitted Q on the true position): per run, the live steps of
the first version that does; the page gives their median over the runs that reach it and
says how many do.
"""

from __future__ import annotations

import math

import numpy as np

from learner.floors import CONSTANT, RANDOM
from learner.jobs import ENVIRONMENTS, Job, best_job
from learner.sections import Data, Section, cell
from learner.tables import Row, pooled_floors, score_statistics, summarise
from tpsr_ros.io.policy import TRUE_POSITION

__all__ = [
    "COMPETENCE_SECTION",
    "COMPETENT_SHARE",
    "ceiling_entry",
    "competence_jobs",
    "steps_to_competence",
]

COMPETENT_SHARE = 0.9
"""Competence: a score of at least this share of the ceiling."""
STEP_HZ = 10.0
"""A robot's step rate for the minutes the page gives (the guide's 1 s steps, ten times faster)."""
SHOWN_STEPS = (1000, 2000, 3000, 4000, 6000, 8000, 12000)
"""The checkpoints the table shows (every version is in the CSV)."""


def competence_jobs() -> tuple[Job, ...]:
    """One ``learner competence`` job per environment."""
    return tuple(
        Job("competence", ("competence", "--environment", env), f"competence_{env}.csv")
        for env in ENVIRONMENTS
    )


def ceiling_entry(rows: list[Row]) -> dict | None:
    """The headline's true-position entry at its largest data size."""
    entries = [t for t in summarise(rows) if t["method"] == TRUE_POSITION]
    return max(entries, key=lambda t: t["episodes"], default=None)


def steps_to_competence(
    rows: list[Row], threshold: float, *, lasting: bool = False
) -> list[float]:
    """Per run (in run order), the live steps of its first version scoring at least
    ``threshold``; with ``lasting``, of the first from which every later version does too
    (inf: none)."""
    runs: dict[int, list[Row]] = {}
    for row in rows:
        runs.setdefault(row.repetition, []).append(row)
    firsts = []
    for run in sorted(runs):  # in run order
        versions = sorted(runs[run], key=lambda r: r.episodes)
        good = [math.isfinite(r.score) and r.score >= threshold for r in versions]
        if lasting:
            first = len(good)
            while first > 0 and good[first - 1]:
                first -= 1
            good = [k >= first for k in range(len(good))]
        reached = [r.episodes for r, ok in zip(versions, good, strict=True) if ok]
        firsts.append(float(min(reached)) if reached else math.inf)
    return firsts


def _minutes(steps: float) -> str:
    return f"{steps / STEP_HZ / 60:.1f} min"


def _render(section: Section, data: Data) -> list[str]:
    lines = [
        "Cells: mean / median / SEM of the versions' scores over the runs, by the live steps "
        f"they were fitted on (a version every 1000 steps after a warm-up of 1000; minutes at "
        f"{STEP_HZ:g} steps/s). Floors and ceiling: the headline's (pooled floors; the true "
        "position at 8000 episodes). Competence: at least "
        f"{COMPETENT_SHARE:.0%} of the ceiling.",
        "",
        "| environment | " + " | ".join(f"{s} steps ({_minutes(s)})" for s in SHOWN_STEPS)
        + " | floors (constant; random) | ceiling |",
        "|---|" + "---|" * (len(SHOWN_STEPS) + 2),
    ]
    verdicts = []
    for job in competence_jobs():
        env, rows = job.environment, data[job]
        base = data[best_job(env)]
        floors = pooled_floors(base)
        ceiling = ceiling_entry(base)
        cells = []
        for steps in SHOWN_STEPS:
            scores = np.array([r.score for r in rows if r.episodes == steps])
            cells.append(cell(score_statistics(scores)) if scores.size else "-")
        floor_text = "; ".join(cell(floors.get(m)) for m in (CONSTANT, RANDOM))
        lines.append(f"| `{env}` | " + " | ".join(cells) + f" | {floor_text} | {cell(ceiling)} |")
        if ceiling is None:
            continue
        threshold = COMPETENT_SHARE * ceiling["mean"]
        most = max(r.episodes for r in rows)
        first = _reach(steps_to_competence(rows, threshold))
        kept = _reach(steps_to_competence(rows, threshold, lasting=True))
        verdicts.append(
            f"- `{env}` ({threshold:.0f}, {COMPETENT_SHARE:.0%} of {ceiling['mean']:.1f}, within "
            f"{most} steps): reached by {first}; kept at every later version by {kept}; "
            f"{_fallbacks(rows, threshold)} later versions fell back below it."
        )
    return [*lines, "", "**Verdict.**", "", *verdicts, "", *_NOTES]


def _reach(firsts: list[float]) -> str:
    """``K of N runs, median S steps (M min), range A-B`` of the runs that got there."""
    reached = [s for s in firsts if math.isfinite(s)]
    if not reached:
        return f"no run of {len(firsts)}"
    median = float(np.median(reached))
    return (
        f"{len(reached)} of {len(firsts)} runs, median {median:.0f} steps "
        f"({_minutes(median)}), range {min(reached):.0f}-{max(reached):.0f}"
    )


def _fallbacks(rows: list[Row], threshold: float) -> str:
    """``F of L``: of the versions after a run first reached ``threshold``, how many fell
    below it again."""
    reached = dict(zip(sorted({r.repetition for r in rows}),
                       steps_to_competence(rows, threshold), strict=True))  # fmt: skip
    later = [r for r in rows if r.episodes > reached[r.repetition]]
    fell = sum(not (math.isfinite(r.score) and r.score >= threshold) for r in later)
    return f"{fell} of {len(later)}"


_NOTES = (
    "The versions plan on the steps they were fitted on (the node has no other data), "
    "where the headline's runs plan on a separate random run of 15000 or 20000 steps; and "
    "a version's score is not monotone in its steps: a refit can fall back where the one "
    "before reached competence, which is why the page counts the versions that keep it as "
    "well as the first that reaches it.",
)


COMPETENCE_SECTION = Section(
    "competence",
    "Learning on the robot: time to competence",
    "How many live steps does the learner node need before its latest version plans well? "
    "Each run explores the simulator with uniformly random actions; the learner node's "
    "versions of it (msgs_doc/learner_node.md: the first fitted after 1000 steps, then a "
    "refit on its basis every 1000 steps, each with a fitted-Q policy on the same steps) "
    "are scored by the standard evaluation. `learner competence` makes exactly the "
    "versions the node makes of the run's messages, without a middleware "
    "(`tests/test_learner_node.py` holds the node to `learner fit` on a recording).",
    competence_jobs(),
    _render,
    "**Commands** (seeds 31 to 40, fresh):\n\n```sh\n"
    + "\n".join(job.command for job in competence_jobs())
    + "\n```",
)
