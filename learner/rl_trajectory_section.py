"""The results page's section on the RL trajectory: one for every run, or one per run.

Every run of an experiment plans on one random RL trajectory, the same for all ten (the
guide's protocol), so the spread of ten runs holds the training data's variation and not the
RL data's. With ``--rl-per-run`` run k plans on its own (RL seed 111 + k on the headline's
seeds; run 0's is the headline's). The section sets the two side by side in every
environment for the TPSR, PCA under the defaults' and the guide's planner (and its own where
one image does not tell where the robot is), the baselines that carry the past, the floors
and the ceiling, and judges the TPSR against each baseline on the runs that each have
their own RL data.
"""

from __future__ import annotations

from typing import Any

from learner.floors import CONSTANT, RANDOM
from learner.jobs import (
    ENVIRONMENTS,
    HEADLINE_SEEDS,
    Job,
    experiment_job,
    guide_job,
    headline_job,
)
from learner.predictive_section import (
    BASELINE_OPTIONS,
    PCA_PLANNER_ENVIRONMENTS,
    PCA_PLANNER_OPTIONS,
    PREDICTIVE_EPISODES,
    baseline_jobs,
    entry_at_size,
    pca_planner_jobs,
    weakest_at_size,
)
from learner.sections import Data, Section, cell, comparison, judged
from tpsr_ros.io.policy import TRUE_POSITION

__all__ = ["RL_TRAJECTORY_SECTION"]

RL_ENVIRONMENTS = ENVIRONMENTS
"""Where the runs were repeated with an RL trajectory each: every environment."""


def _per_run(arm: str, environment: str, *options: str) -> Job:
    """An experiment job at the section's data size on the headline's seeds, each run on its
    own RL trajectory, writing ``results/rl_per_run/<arm>``."""
    return experiment_job(
        f"rl_per_run/{arm}", environment, "--episodes", str(PREDICTIVE_EPISODES),
        "--rl-per-run", *options, *HEADLINE_SEEDS,
    )  # fmt: skip


def _arms(environment: str) -> dict[str, tuple[Job, Job]]:
    """Each arm's job with one RL trajectory for every run (the page's own) and with one
    per run; PCA's own planner only where it has one (:data:`PCA_PLANNER_ENVIRONMENTS`)."""
    arms = {
        "defaults": (
            headline_job(environment),
            _per_run(
                "defaults", environment, "--methods", CONSTANT, RANDOM, "tpsr", "pca", TRUE_POSITION
            ),
        ),
        "baselines": (
            baseline_jobs()[environment],
            _per_run("baselines", environment, *BASELINE_OPTIONS),
        ),
    }
    if environment in PCA_PLANNER_ENVIRONMENTS:
        arms["pca_planner"] = (
            pca_planner_jobs()[environment],
            _per_run("pca_planner", environment, *PCA_PLANNER_OPTIONS),
        )
    arms["guide"] = (
        guide_job(environment),
        _per_run("guide", environment, "--preset", "guide", "--methods", "pca"),
    )
    return arms


_ROWS = (
    ("TPSR", "the defaults'", "defaults", "tpsr", "the TPSR"),
    ("PCA", "the defaults'", "defaults", "pca", "PCA with the defaults' planner"),
    ("PCA", "its own (one member, predictive units)", "pca_planner", "pca",
     "PCA with its own planner"),
    ("PCA", "the guide's (one member, standardised)", "guide", "pca",
     "PCA with the guide's planner"),
    ("stacked-frame PCA (k = 1)", "`best`'s", "baselines", "stacked-pca", "stacked-frame PCA"),
    ("finite-window predictive state (k = 1)", "`best`'s", "baselines", "window",
     "the finite-window predictive state"),
    ("floor: the best constant action", "-", "defaults", CONSTANT, "the best constant action"),
    ("floor: random actions", "-", "defaults", RANDOM, "random actions"),
    ("ceiling: the true position", "the defaults'", "defaults", TRUE_POSITION,
     "the true position"),
)  # fmt: skip
"""The table's rows: (representation, planner, arm, method, name in the verdicts)."""
_BASELINES = _ROWS[1:6]
"""The rows the TPSR is judged against: PCA under each planner and the baselines that
carry the past."""
_RL_SEED = int(HEADLINE_SEEDS[HEADLINE_SEEDS.index("--rl-seed") + 1])


def _render(section: Section, data: Data) -> list[str]:
    lines = [
        f"Ten runs per arm at {PREDICTIVE_EPISODES} episodes on the headline's seeds, every "
        f"setting the page's own: one RL trajectory for every run (RL seed {_RL_SEED}, the "
        "rows of the headline and of the predictive section), and one per run (RL seed "
        f"{_RL_SEED} + k for run k, the same training runs). Cells: mean / median / SEM "
        "(weakest run); the difference of the means.",
        "",
        "| environment | representation | planner | one RL trajectory | one per run | difference |",
        "|---|---|---|---|---|---|",
    ]
    verdicts = []
    for env in RL_ENVIRONMENTS:
        arms = _arms(env)
        entries: dict[str, dict[str, Any] | None] = {}
        moved: dict[str, float] = {}  # each representation's change of mean, by row key
        for label, planner, arm, method, _ in _ROWS:
            if arm not in arms:
                continue
            fixed_job, own_job = arms[arm]
            fixed = entry_at_size(data[fixed_job], method)
            own = entry_at_size(data[own_job], method)
            entries[f"{arm}/{method}"] = own
            difference = "-"
            if fixed is not None and own is not None:
                moved[f"{arm}/{method}"] = own["mean"] - fixed["mean"]
                difference = f"{moved[f'{arm}/{method}']:+.1f}"
            lines.append(
                f"| `{env}` | {label} | {planner} | {cell(fixed)} "
                f"({weakest_at_size(data[fixed_job], method)}) | {cell(own)} "
                f"({weakest_at_size(data[own_job], method)}) | {difference} |"
            )
        ours = entries["defaults/tpsr"]
        if ours is None:
            continue
        against = []
        for _, _, arm, method, name in _BASELINES:
            other = entries.get(f"{arm}/{method}")
            if other is not None:
                against.append(f"{judged(*comparison(ours, other))} against {name}")
        keys = (f"{arm}/{method}" for _, _, arm, method, _ in _BASELINES)
        baselines = [moved[key] for key in keys if key in moved]
        change = ""
        if "defaults/tpsr" in moved and baselines:
            change = (
                f" Against one RL trajectory for every run the TPSR's mean moved by "
                f"{moved['defaults/tpsr']:+.1f}, the baselines' by {min(baselines):+.1f} to "
                f"{max(baselines):+.1f}."
            )
        verdicts.append(
            f"- `{env}`, each run with its own RL trajectory: the TPSR scores "
            f"{ours['mean']:.1f} (SEM {ours['sem']:.1f}), " + "; ".join(against) + "." + change
        )
    return [*lines, "", "**Verdict.**", "", *verdicts]


RL_TRAJECTORY_SECTION = Section(
    "rl-trajectory",
    "The RL trajectory: one for every run, or one per run",
    "Every run of an experiment plans on the same random RL trajectory (as in the guide), "
    "so the spread of its ten runs holds the training data's variation but not the RL "
    "data's. How much does a score owe to that one trajectory, and does the TPSR still lead "
    "the baselines when each run plans on its own? PCA planned as the guide plans it (one "
    "member, standardised units) scored 103.4 on the selection seeds (the study \"PCA's own "
    "planner\" above) and 364.0 on the headline's, where PCA with its own planner, chosen "
    "on the selection seeds, scored 326.0.",
    tuple(job for env in RL_ENVIRONMENTS for pair in _arms(env).values() for job in pair),
    _render,
    "**Commands** (the headline's seeds; the rows with one RL trajectory are the runs at "
    "8000 episodes of the headline's defaults and guide's settings, of the predictive "
    "section's baselines and of PCA's own planner, whose commands those sections give):"
    "\n\n```sh\n"
    + "\n".join(own.command for env in RL_ENVIRONMENTS for _, own in _arms(env).values())
    + "\n```",
)
"""The section, with its jobs (each arm's with one RL trajectory and with one per run)."""
