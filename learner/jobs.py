"""The commands behind the results page: each writes one CSV under ``results/``.

A :class:`Job` is ``python -m learner ARGV -o results/DIRECTORY``; ``learner report`` runs the
jobs whose CSV is missing (``--rerun``: all) and renders the page from the CSVs alone, so
every number on it comes from a command the page names.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from sim_node import Environment

__all__ = [
    "BEFORE_CARRY_RULE",
    "BEFORE_MEMBER_REFIT",
    "BEFORE_OVERLAP",
    "BEFORE_TWO_IMAGES",
    "BEFORE_WIDE_KERNEL",
    "BEST_PRESET",
    "ENVIRONMENTS",
    "GUIDE_ENVIRONMENTS",
    "HEADLINE_SEEDS",
    "SELECTION_SEEDS",
    "WINDOW_EPISODES",
    "Job",
    "best_job",
    "experiment_job",
    "guide_job",
    "headline_job",
    "memory_option",
    "study_job",
]

GUIDE_ENVIRONMENTS = ("full", "partial", "distractors")
"""The guide's environments: the appendix's studies run in them."""
ENVIRONMENTS = (*GUIDE_ENVIRONMENTS, "partial-strip", "drive")
"""Every environment of the headline."""

SELECTION_SEEDS = ("--seed", "0", "--rl-seed", "100")
"""Training and RL seeds the default configuration was chosen on (the studies use them)."""

HEADLINE_SEEDS = ("--seed", "11", "--rl-seed", "111")
"""Fresh seeds, never used to choose anything: the headline tables run on them."""

BEST_PRESET = ("--preset", "best")
"""The preset the one-parameter studies, the tuner's and the baselines' jobs run under: the
defaults were chosen on it before ``predictive`` refined them."""

WINDOW_EPISODES = ("--episode-steps", "window")
"""How the studies of histories and tests longer than one image ran: an episode of one
window of the fit (m + 1 + n recorded steps), so at a given number of episodes a longer
window learned from more steps (by default an experiment records 3 steps per episode
whatever the fit)."""

# The predictive preset as the studies of it ran, before later studies changed it: each
# departure from today's preset, oldest last (a study that ran earlier ran without the
# changes adopted after it). The CSVs' commands name them too: each row's command gives the
# settings the row recorded.
BEFORE_CARRY_RULE = ("--set", "tpsr.refine_carry_rule=always")
"""Before the carry applied only where the previous image helps (``aliased``)."""
BEFORE_TWO_IMAGES = (*BEFORE_CARRY_RULE, "--set", "tpsr.history_length=1")
"""Before histories held the last two images."""
BEFORE_OVERLAP = (*BEFORE_TWO_IMAGES, "--set", "tpsr.overlapping_episodes=false")
"""Before the spectral start took a window at every step."""
BEFORE_MEMBER_REFIT = (*BEFORE_OVERLAP, "--set", "fqi.refit=ensemble")
"""Before the planner refitted a diverging member alone."""
BEFORE_WIDE_KERNEL = ("--set", "tpsr.obs_effective_centres=0")
"""Before a robot that turns widened its observation kernel (``drive``'s runs only: the
other rooms' kernels are as they were)."""


@dataclass(frozen=True)
class Job:
    """``python -m learner ARGV -o results/DIRECTORY``, which writes ``DIRECTORY/CSV``."""

    directory: str
    argv: tuple[str, ...]
    csv: str

    def option(self, flag: str, default: str | None = None) -> str | None:
        """The value the job's command gives ``flag`` (e.g. ``--environment``), or ``default``."""
        return self.argv[self.argv.index(flag) + 1] if flag in self.argv else default

    @property
    def assignments(self) -> tuple[str, ...]:
        """The ``NAME=VALUE`` of each ``--set`` in the job's command, in order."""
        return tuple(self.argv[i + 1] for i, arg in enumerate(self.argv[:-1]) if arg == "--set")

    @property
    def environment(self) -> str:
        """The job's ``--environment``."""
        return str(self.option("--environment"))

    @property
    def command(self) -> str:
        """The command as a user types it (run from the repository's root)."""
        return " ".join(("python -m learner", *self.argv, "-o", f"results/{self.directory}"))

    def path(self, results: Path) -> Path:
        """Where the job's CSV lies under the results directory ``results``."""
        return results / self.directory / self.csv

    def argv_for(self, results: Path, workers: int) -> list[str]:
        """``learner`` arguments that (re)write the CSV under ``results``."""
        return [
            *self.argv,
            "-o",
            str(results / self.directory),
            "--force",
            "--workers",
            str(workers),
        ]


def experiment_job(directory: str, environment: str, *options: str) -> Job:
    """A ``learner experiment`` job for one environment."""
    return Job(
        directory,
        ("experiment", "--environment", environment, *options),
        f"experiment_{environment}.csv",
    )


def study_job(directory: str, environment: str, vary: str, *options: str) -> Job:
    """A ``learner study --vary NAME=V1,V2...`` job for one environment."""
    name = vary.split("=", 1)[0].replace(".", "_")
    return Job(
        directory,
        ("study", "--environment", environment, "--vary", vary, *options),
        f"study_{environment}_{name}.csv",
    )


def memory_option(environment: str) -> tuple[str, ...]:
    """``--memory`` where two places look alike (the narrow cameras), else nothing."""
    return ("--memory",) if Environment.parse(environment).narrow else ()


def headline_job(environment: str) -> Job:
    """The headline's experiment under the defaults: every method at every data size on the
    fresh seeds, measuring memory where two places look alike."""
    return experiment_job("defaults", environment, *memory_option(environment), *HEADLINE_SEEDS)


def guide_job(environment: str) -> Job:
    """The headline's experiment under ``--preset guide``: the guide's algorithm and planner."""
    return experiment_job("guide", environment, "--preset", "guide", *HEADLINE_SEEDS)


def best_job(environment: str) -> Job:
    """The headline's experiment under ``--preset best``: what the ``predictive`` preset
    refines, and the preset of the online learner's runs."""
    return experiment_job("best", environment, *BEST_PRESET, *HEADLINE_SEEDS)
