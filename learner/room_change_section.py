"""The results page's section on a room that changes while the learner node learns.

Ten exploring runs (``learner competence --switch-to``, seeds 31 to 40) in ``full`` whose room
becomes ``distractors`` after 6000 live steps; the learner node's versions of each run are
scored in the room of their last step, under four settings of the node: the defaults,
``forgetting``, ``new_basis_steps``, and both. Recovery is a version reaching 90 % of the new
room's ceiling again, counted in live steps after the change. The arms share their runs
(the same seeds, the same steps), so each is compared with the defaults run by run. A new
basis is also measured where the room stays (the time-to-competence runs of the
environments where one image is ambiguous), to say whether it could be the default.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass

import numpy as np

from learner.competence_section import (
    COMPETENT_SHARE,
    ceiling_entry,
    competence_jobs,
    steps_to_competence,
)
from learner.floors import CONSTANT, RANDOM
from learner.jobs import Job, best_job
from learner.sections import Data, Section, cell
from learner.tables import Row, pooled_floors, score_statistics
from learner.verdicts import DIFFERENCE_SEMS

__all__ = ["ROOM_CHANGE_SECTION", "room_change_jobs"]

BEFORE, AFTER, SWITCH_AT = "full", "distractors", 6000
SHOWN_STEPS = (5000, 6000, 7000, 8000, 9000, 10000, 12000)


@dataclass(frozen=True)
class Arm:
    """One setting of the learner node: its ``forgetting`` and ``new_basis_steps``."""

    forgetting: str
    new_basis_steps: int

    @property
    def label(self) -> str:
        forgetting = "no forgetting" if self.forgetting == "1" else f"forgetting {self.forgetting}"
        basis = (
            "version 1's basis" if not self.new_basis_steps
            else f"a new basis every {self.new_basis_steps} steps"
        )  # fmt: skip
        return f"{forgetting}, {basis}"


ARMS = (Arm("1", 0), Arm("0.999", 0), Arm("1", 2000), Arm("0.999", 2000))
"""The defaults first (the reference of every comparison), then each change and both."""
STAYING = ("partial", "partial-strip")
"""Rooms that stay, where a new basis every 2000 steps is compared with the defaults."""
NEW_BASIS = 2000


def _job(arm: Arm) -> Job:
    """The ``learner competence --switch-to`` job of one arm (its command as the command
    records it: no option at its default)."""
    argv = ["competence", "--environment", BEFORE]
    if arm.forgetting != "1":
        argv += ["--forgetting", arm.forgetting]
    if arm.new_basis_steps:
        argv += ["--new-basis-steps", str(arm.new_basis_steps)]
    argv += ["--switch-to", AFTER, "--switch-at", str(SWITCH_AT)]
    suffix = f"_b{arm.new_basis_steps}" if arm.new_basis_steps else ""
    return Job("competence", tuple(argv), f"switch_{BEFORE}_{AFTER}_f{arm.forgetting}{suffix}.csv")


def _staying_job(environment: str) -> Job:
    """The time-to-competence job of ``environment`` with a new basis every 2000 steps."""
    argv = ("competence", "--environment", environment, "--new-basis-steps", str(NEW_BASIS))
    return Job("competence", argv, f"competence_{environment}_b{NEW_BASIS}.csv")


def room_change_jobs() -> tuple[Job, ...]:
    """One ``learner competence --switch-to`` job per arm, then the rooms that stay."""
    return (*(_job(arm) for arm in ARMS), *(_staying_job(env) for env in STAYING))


def _headline(data: Data) -> list[Row]:
    """The new room's headline runs (its floors and ceiling)."""
    return data[best_job(AFTER)]


def _ceiling(data: Data) -> float:
    """The new room's ceiling: the headline's true position at its largest data size."""
    entry = ceiling_entry(_headline(data))
    assert entry is not None, f"the headline of {AFTER} has no true-position runs"
    return float(entry["mean"])


def _fresh(data: Data) -> list[Row]:
    """The time-to-competence runs of a node started in the new room."""
    return data[_defaults_competence(AFTER)]


def _after(rows: list[Row]) -> list[Row]:
    return [r for r in rows if json.loads(r.parameters)["room"] == AFTER]


def _run_means(rows: list[Row], room: str | None = AFTER) -> np.ndarray:
    """Per run (in run order), the mean score of its versions in ``room`` (None: all; a
    version without a policy: 0)."""
    runs: dict[int, list[float]] = {}
    for row in _after(rows) if room is not None else rows:
        runs.setdefault(row.repetition, []).append(row.score if math.isfinite(row.score) else 0.0)
    return np.array([np.mean(runs[run]) for run in sorted(runs)])


def _scores_at(rows: list[Row], steps: int) -> np.ndarray:
    return np.array([r.score for r in rows if r.episodes == steps])


def _render(section: Section, data: Data) -> list[str]:
    ceiling = _ceiling(data)
    threshold = COMPETENT_SHARE * ceiling
    lines = [
        f"Cells: mean / median / SEM over the runs of the versions' scores by live steps (a "
        f"version every 1000 steps; the room is `{BEFORE}` up to {SWITCH_AT} steps and "
        f"`{AFTER}` after); after the change: the mean of each run's versions after it, over "
        f"the runs; recovery: the live steps after the change until a version scores "
        f"{COMPETENT_SHARE:.0%} of `{AFTER}`'s ceiling ({ceiling:.1f}) or more.",
        "",
        "| the learner node | "
        + " | ".join(f"{s} steps" for s in SHOWN_STEPS)
        + " | after the change | recovery |",
        "|---|" + "---|" * (len(SHOWN_STEPS) + 2),
    ]
    means = {}
    for job, arm in zip(section.jobs[: len(ARMS)], ARMS, strict=True):
        rows = data[job]
        cells = [_cell(_scores_at(rows, steps)) for steps in SHOWN_STEPS]
        means[arm] = _run_means(rows)
        recovery = _recovery(_after(rows), threshold)
        lines.append(
            f"| {arm.label} | " + " | ".join(cells)
            + f" | {cell(score_statistics(means[arm]))} | {recovery} |"
        )  # fmt: skip
    fresh = _fresh(data)
    cells = [_cell(_scores_at(fresh, steps - SWITCH_AT)) for steps in SHOWN_STEPS]
    lines.append(
        f"| started in `{AFTER}` at the change (time to competence; defaults) | "
        + " | ".join(cells) + " | - | - |"
    )  # fmt: skip
    floors = pooled_floors(_headline(data))
    lines += ["", f"`{AFTER}`'s floors (pooled): the best constant action "
              f"{cell(floors.get(CONSTANT))}, random actions {cell(floors.get(RANDOM))}; its "
              f"ceiling {ceiling:.1f}."]  # fmt: skip
    reference = ARMS[0]
    verdicts = [
        _paired(f"{arm.label} against the defaults", means[arm], means[reference])
        for arm in ARMS[1:]
    ]
    best = max(ARMS, key=lambda arm: float(means[arm].mean()))
    verdicts += _against_fresh(data, fresh, best)
    verdicts += [_staying(data, env) for env in STAYING]
    return [*lines, "", "**Verdict.**", "", *verdicts, "", *_NOTES]


def _staying(data: Data, environment: str) -> str:
    """A new basis against the defaults in a room that stays, run by run, over the versions
    from the first that can fit one on."""
    first = 1000 + NEW_BASIS  # the warm-up's basis, then the first new one
    ours, theirs = (
        _run_means([r for r in data[job] if r.episodes >= first], room=None)
        for job in (_staying_job(environment), _defaults_competence(environment))
    )
    return _paired(
        f"In `{environment}`, where the room stays (the versions from {first} to 12000 steps), "
        f"a new basis every {NEW_BASIS} steps against the defaults",
        ours, theirs, after=False,
    )  # fmt: skip


def _defaults_competence(environment: str) -> Job:
    """The time-to-competence job of ``environment`` (the learner node's defaults)."""
    return next(job for job in competence_jobs() if job.environment == environment)


def _cell(scores: np.ndarray) -> str:
    return cell(score_statistics(scores)) if scores.size else "-"


def _paired(what: str, ours: np.ndarray, theirs: np.ndarray, *, after: bool = True) -> str:
    """The mean of the per-run differences, in SEMs of the difference."""
    diff = ours - theirs
    sem = float(diff.std(ddof=1) / np.sqrt(diff.size))
    mean = float(diff.mean())
    noise = "within" if abs(mean) <= DIFFERENCE_SEMS * sem else "outside"
    return (
        f"- {'After the change, ' if after else ''}{what}: {ours.mean():.1f} against "
        f"{theirs.mean():.1f}, "
        f"{mean:+.1f} ({mean / sem:+.1f} SEM of the per-run differences, {noise} the noise)."
    )


def _against_fresh(data: Data, fresh: list[Row], arm: Arm) -> list[str]:
    """How a node that lived through the change (``arm``, the best after it) compares with
    one started in the new room, a little and long after the change."""
    lived = data[_job(arm)]
    out = []
    for steps in (SWITCH_AT + 1000, SWITCH_AT + 3000, max(SHOWN_STEPS)):
        old, new = _scores_at(lived, steps), _scores_at(fresh, steps - SWITCH_AT)
        if old.size < 2 or new.size < 2:
            continue
        diff = float(old.mean() - new.mean())
        sem = float(
            np.hypot(old.std(ddof=1) / np.sqrt(old.size), new.std(ddof=1) / np.sqrt(new.size))
        )
        noise = "within" if abs(diff) <= DIFFERENCE_SEMS * sem else "outside"
        out.append(
            f"- {steps - SWITCH_AT} steps after the change, the node that learned in `{BEFORE}` "
            f"first ({arm.label}) scores {old.mean():.1f} against {new.mean():.1f} for a node "
            f"started in `{AFTER}` as many steps before, {diff:+.1f} ({diff / sem:+.1f} SEM of "
            f"the difference, {noise} the noise)."
        )
    return out


def _recovery(rows: list[Row], threshold: float) -> str:
    """``K of N runs, median S steps`` after the change, of the runs that recover."""
    firsts = [s - SWITCH_AT for s in steps_to_competence(rows, threshold)]
    reached = [s for s in firsts if math.isfinite(s)]
    if not reached:
        return f"no run of {len(firsts)}"
    return f"{len(reached)} of {len(firsts)} runs, median {np.median(reached):.0f} steps"


_NOTES = (
    "Without a new basis the whitenings, kernel centres and sketch of `P_TH` are version "
    f"1's, fitted on the first 1000 steps in `{BEFORE}`: forgetting re-weighs the "
    "statistics, it does not choose them anew. A new basis is fitted as `learner fit` fits "
    "the last 3 / (1 - forgetting) steps (every step without forgetting), in the state "
    "coordinates of the version it replaces (msgs_doc/learner_node.md). With forgetting the "
    "policy plans on the last 3 / (1 - forgetting) steps only; without, on every step, both "
    "rooms' alike. A node started in the new room is the time-to-competence run of the same "
    "seed, on other steps: it is compared over the runs, not run by run. Where the room "
    "stays, a new basis is compared with the time-to-competence runs of the same seeds, "
    "which are the same steps. 2000 steps is the only period measured.",
)


ROOM_CHANGE_SECTION = Section(
    "room-change",
    "Learning on the robot: a room that changes",
    f"When the room changes under the robot (`{BEFORE}` to `{AFTER}` after {SWITCH_AT} live "
    "steps), how soon do the learner node's versions plan well again, and do its "
    "`forgetting` and `new_basis_steps` make them recover sooner?",
    room_change_jobs(),
    _render,
    "**Commands** (seeds 31 to 40, fresh):\n\n```sh\n"
    + "\n".join(job.command for job in room_change_jobs())
    + "\n```",
)
