"""The results page (``docs/results.md``) rendered from the experiment CSVs alone.

The page leads with what works (above the floors, and against the baseline, apart) and what
does not reproduce from the guide, the commands to use, the headline tables (the defaults,
``--preset guide``, PCA with each planner and the ceiling by data size, on fresh seeds; the
floors once, pooled over the data sizes since they use no data), the guide's findings judged by
:mod:`learner.verdicts`, and then the appendix of :mod:`learner.appendix`. Nothing on it is
typed by hand: every number comes from a CSV under ``results/`` that a named command wrote,
and the same CSVs always give the same bytes.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from learner.appendix import SECTIONS
from learner.camera_study import narrowest_camera
from learner.experiment import EPISODE_STEPS
from learner.floors import CONSTANT, DEMO_POLICY_SEED, RANDOM
from learner.jobs import (
    ENVIRONMENTS,
    GUIDE_ENVIRONMENTS,
    HEADLINE_SEEDS,
    SELECTION_SEEDS,
    Job,
    best_job,
    guide_job,
    headline_job,
)
from learner.predictive_section import PREDICTIVE_SECTION, paths_memory, tpsr_job
from learner.sections import Data, cell
from learner.tables import Row, difference_in_sems, pooled_floors, summarise
from learner.verdicts import (
    ABOUT_300,
    BETTER,
    DIFFERENCE_SEMS,
    FLOOR_SEMS,
    GUIDE_RESULTS,
    NEAR_CEILING,
    NEAR_FLOOR,
    NOT_REPRODUCED,
    REPRODUCED,
    SLIGHTLY,
    Table,
    judge,
)
from tpsr_ros.core.errors import ConfigError
from tpsr_ros.core.presets import DEFAULT_PRESET, PRESETS
from tpsr_ros.io.policy import TRUE_POSITION

__all__ = [
    "HEADLINE",
    "all_jobs",
    "readme_summary",
    "readme_table",
    "render",
    "write_page",
    "write_readme_table",
]

HEADLINE: Mapping[str, tuple[Job, ...]] = {
    "defaults": tuple(headline_job(env) for env in ENVIRONMENTS),
    "best": tuple(best_job(env) for env in ENVIRONMENTS),
    "guide": tuple(guide_job(env) for env in ENVIRONMENTS),
}
"""The headline's jobs: every method under the defaults, under ``--preset best`` (what the
defaults refine) and under ``--preset guide``."""

_ROWS = (
    ("TPSR", "defaults", "defaults", "tpsr"),
    ("PCA", "the defaults' planner", "defaults", "pca"),
    ("TPSR", "`--preset best`", "best", "tpsr"),
    ("TPSR", "`--preset guide`", "guide", "tpsr"),
    ("PCA", "the guide's planner", "guide", "pca"),
    ("true position (ceiling)", "the defaults' planner", "defaults", TRUE_POSITION),
    ("true position (ceiling)", "the guide's planner", "guide", TRUE_POSITION),
)
"""Headline table rows: (representation, settings, headline arm, method)."""

_FLOOR_ROWS = (
    ("best constant action (floor)", CONSTANT),
    ("random actions (floor)", RANDOM),
)
"""The floors' rows (label, method): one cell each, pooled over the data sizes
(:func:`learner.tables.pooled_floors`), from the defaults' CSV."""

Floors = Mapping[str, dict[str, Any]]
"""The pooled floors of one CSV by method (:func:`learner.tables.pooled_floors`)."""


def all_jobs() -> list[Job]:
    """Every job of the page, each once, in page order."""
    jobs = [job for arm in HEADLINE.values() for job in arm]
    jobs += [job for section in SECTIONS for job in section.jobs]
    return list(dict.fromkeys(jobs))


def _tables(data: Data, arm: str) -> dict[str, Table]:
    return {env: summarise(data[job]) for env, job in zip(ENVIRONMENTS, HEADLINE[arm], strict=True)}


def _arm_jobs(index: int) -> dict[str, Job]:
    """The headline's job of every arm in the environment ``ENVIRONMENTS[index]``."""
    return {arm: jobs[index] for arm, jobs in HEADLINE.items()}


def _arm_tables(data: Data, index: int) -> dict[str, Table]:
    """The headline's summary of every arm in the environment ``ENVIRONMENTS[index]``."""
    return {arm: summarise(data[job]) for arm, job in _arm_jobs(index).items()}


def _floors(data: Data, arm: str = "defaults") -> dict[str, Floors]:
    """Each environment's floors pooled over all their runs in the arm's CSV."""
    return {
        env: pooled_floors(data[job]) for env, job in zip(ENVIRONMENTS, HEADLINE[arm], strict=True)
    }


def _best_floor(floors: Floors) -> dict[str, Any] | None:
    """The floor with the highest pooled mean, the one every margin is taken over."""
    finite = [f for f in floors.values() if math.isfinite(f["mean"])]
    return max(finite, key=lambda f: f["mean"], default=None)


def _floor_text(floor: Mapping[str, Any] | None) -> str:
    """A pooled floor as ``name mean / median / SEM over N runs``."""
    if floor is None:
        return "no floor"
    name = {CONSTANT: "the best constant action", RANDOM: "random actions"}[floor["method"]]
    return f"{name} ({cell(floor)} over its {floor['runs']} runs)"


def _entry(table: Table, method: str, episodes: int) -> dict[str, Any] | None:
    found = [t for t in table if t["method"] == method and t["episodes"] == episodes]
    return found[0] if found else None


def _sizes(table: Table) -> list[int]:
    return sorted({t["episodes"] for t in table})


def _span(values: Sequence[float], fmt: str = ".1f") -> str:
    finite = [v for v in values if math.isfinite(v)]
    if not finite:
        return "-"
    low, high = format(min(finite), fmt), format(max(finite), fmt)
    return low if low == high else f"{low}-{high}"


def _method(table: Table, method: str) -> list[dict[str, Any]]:
    return [t for t in table if t["method"] == method and math.isfinite(t["mean"])]


def _versus(table: Table, method: str, other: str) -> str:
    """How ``method`` compares with ``other`` at every size, by the page's 2-SEM rule."""
    pairs = [
        (a, b)
        for a in _method(table, method)
        for b in _method(table, other)
        if a["episodes"] == b["episodes"]
    ]
    if not pairs:
        return "not measured"
    sems = [difference_in_sems(a, b) for a, b in pairs]
    above = sum(s > DIFFERENCE_SEMS for s in sems)
    below = sum(s < -DIFFERENCE_SEMS for s in sems)
    sizes = len(pairs)
    parts = []
    if above:
        parts.append(f"above at {above} of {sizes} data sizes")
    if below:
        parts.append(f"below at {below} of {sizes}")
    if sizes - above - below:
        level = sizes - above - below
        parts.append(f"level (within {DIFFERENCE_SEMS:g} SEMs) at {level} of {sizes}")
    return ", ".join(parts)


def _gaps(table: Table, method: str, other: str) -> list[float]:
    """``method`` against ``other`` in SEMs of the difference, at each shared data size."""
    return [
        difference_in_sems(a, b)
        for a in _method(table, method)
        for b in _method(table, other)
        if a["episodes"] == b["episodes"]
    ]


def _count(hits: int, sizes: int) -> str:
    """``at every data size``, ``at no data size`` or ``at H of N data sizes``."""
    if sizes and hits == sizes:
        return f"at every data size ({sizes} of {sizes})"
    return "at no data size" if not hits else f"at {hits} of {sizes} data sizes"


def _environment_summary(env: str, defaults: Table, guide: Table, floors: Floors) -> str:
    """Two separate statements: whether the TPSR is above the floors, and whether it beats
    the baseline (PCA with the same planner); then the guide's settings against the defaults."""
    tpsr = _method(defaults, "tpsr")
    pca = _method(defaults, "pca")
    ceiling = _method(defaults, TRUE_POSITION)
    sizes = _sizes(defaults)
    margins = [t["margin_sem"] for t in tpsr]
    above_floor = sum(m > FLOOR_SEMS for m in margins)
    gaps = _gaps(defaults, "tpsr", "pca")
    beats = sum(g > DIFFERENCE_SEMS for g in gaps)
    below = sum(g < -DIFFERENCE_SEMS for g in gaps)
    return "\n".join(
        [
            f"- **`{env}`**, the defaults from {sizes[0]} to {sizes[-1]} episodes: the TPSR "
            f"scores {_span([t['mean'] for t in tpsr])} (medians "
            f"{_span([t['median'] for t in tpsr])}, SEMs {_span([t['sem'] for t in tpsr])}) "
            f"against a ceiling of {_span([t['mean'] for t in ceiling])}.",
            f"  - *Above the floors* {_count(above_floor, len(tpsr))}, by more than "
            f"{FLOOR_SEMS:g} SEMs: {_span(margins, '.0f')} SEMs above the best floor, "
            f"{_floor_text(_best_floor(floors))}.",
            f"  - *Beats the baseline* (PCA with the same planner, "
            f"{_span([t['mean'] for t in pca])}) {_count(beats, len(gaps))}, by more than "
            f"{DIFFERENCE_SEMS:g} SEMs; level with it at {len(gaps) - beats - below} and below "
            f"it at {below} of {len(gaps)}.",
            f"  - The guide's settings (`--preset guide`) score "
            f"{_span([t['mean'] for t in _method(guide, 'tpsr')])}; against them the defaults "
            f"are {_versus(_merged(defaults, guide), 'tpsr', 'tpsr-guide')}.",
        ]
    )


def _merged(defaults: Table, guide: Table) -> Table:
    """``defaults`` with the guide's TPSR entries renamed ``tpsr-guide`` (to compare them)."""
    return [*defaults, *({**t, "method": "tpsr-guide"} for t in guide if t["method"] == "tpsr")]


def _headline_table(
    env: str, tables: Mapping[str, Table], jobs: Mapping[str, Job], data: Data | None = None
) -> list[str]:
    """One row per representation and settings, a cell per data size; with ``data``, the
    median memory (``learner memory``, in steps) at the largest size where it was measured."""
    sizes = _sizes(tables["defaults"])
    lines = [
        "| representation | settings | "
        + " | ".join(f"{n} episodes" for n in sizes)
        + f" | memory at {sizes[-1]} | command |",
        "|---|---|" + "---|" * len(sizes) + "---|---|",
    ]
    for label, settings, arm, method in _ROWS:
        cells = [cell(_entry(tables[arm], method, n)) for n in sizes]
        memory = "-" if data is None else _median_memory(data[jobs[arm]], method, sizes[-1])
        lines.append(
            f"| {label} | {settings} | " + " | ".join(cells)
            + f" | {memory} | `{jobs[arm].command}` |"
        )
    return lines


def _median_memory(rows: Sequence[Row], method: str, episodes: int) -> str:
    """The median memory in steps of ``method``'s runs at ``episodes`` that measured it."""
    steps = [
        r.memory for r in rows
        if (r.method, r.episodes) == (method, episodes) and math.isfinite(r.memory)
    ]  # fmt: skip
    return f"{float(np.median(steps)):g}" if steps else "-"


def _floor_table(floors: Floors, job: Job) -> list[str]:
    """The floors once each: blind to the state, every run of the CSV is one repetition."""
    lines = [
        "| floor | runs (pooled over the data sizes) | mean / median / SEM | command |",
        "|---|---|---|---|",
    ]
    for label, method in _FLOOR_ROWS:
        floor = floors.get(method)
        runs = "-" if floor is None else f"{floor['runs']} ({floor['sizes']} data sizes)"
        lines.append(f"| {label} | {runs} | {cell(floor)} | `{job.command}` |")
    return lines


def _margins(table: Table) -> str:
    tpsr = _method(table, "tpsr")
    ceiling = {t["episodes"]: t for t in _method(table, TRUE_POSITION)}
    gaps = ", ".join(
        f"{t['episodes']}: {t['mean'] - ceiling[t['episodes']]['mean']:+.1f}"
        for t in tpsr
        if t["episodes"] in ceiling
    )
    return (
        "The defaults' TPSR against the best floor (pooled): "
        + ", ".join(f"{t['episodes']}: {t['margin_sem']:+.1f} SEM" for t in tpsr)
        + f"; against the ceiling: {gaps}."
    )


def _findings(defaults: Mapping[str, Table], guide: Mapping[str, Table]) -> list[str]:
    lines = [
        "| environment | the guide's finding | `--preset guide`: measured | verdict | defaults: "
        "measured | verdict |",
        "|---|---|---|---|---|---|",
    ]
    for (finding, measured_guide, verdict_guide), (_, measured_best, verdict_best) in zip(
        judge(dict(guide)), judge(dict(defaults)), strict=True
    ):
        lines.append(
            f"| `{finding.environment}` | {finding.claim} | {measured_guide} | {verdict_guide} | "
            f"{measured_best} | {verdict_best} |"
        )
    return lines


def _position_error(rows: Sequence[Row], method: str, episodes: int) -> float:
    values = [r.position_error for r in rows if (r.method, r.episodes) == (method, episodes)]
    finite = [v for v in values if math.isfinite(v)]
    return float(np.median(finite)) if finite else math.nan


def _plural(count: int, singular: str, plural: str) -> str:
    """``count`` and the verb or noun that agrees with it."""
    return f"{count} {singular if count == 1 else plural}"


def _verdicts(tables: Mapping[str, Table]) -> dict[str, list[str]]:
    """The guide's findings in its own environments by verdict, each as ``env: claim``."""
    guides = {env: tables[env] for env in GUIDE_ENVIRONMENTS}
    found: dict[str, list[str]] = {REPRODUCED: [], BETTER: [], NOT_REPRODUCED: []}
    for finding, _, verdict in judge(guides):
        found[verdict].append(f"`{finding.environment}`: {finding.claim}")
    return found


def _verdict_counts(verdicts: Mapping[str, list[str]]) -> str:
    """``R reproduce, B are measured better, N do not``."""
    return (
        f"{_plural(len(verdicts[REPRODUCED]), 'reproduces', 'reproduce')}, "
        f"{_plural(len(verdicts[BETTER]), 'is', 'are')} measured better than found and "
        f"{len(verdicts[NOT_REPRODUCED])} {'does' if len(verdicts[NOT_REPRODUCED]) == 1 else 'do'}"
        " not reproduce"
    )


def _summary(defaults: Mapping[str, Table], guide: Mapping[str, Table]) -> str:
    """What the page finds, in one sentence of counts: the guide's findings with its
    settings and with the defaults, and the defaults against the guide's settings and PCA."""
    with_guide, with_defaults = _verdicts(guide), _verdicts(defaults)
    total = sum(len(v) for v in with_guide.values())
    merged = [
        _gaps(_merged(defaults[env], guide[env]), "tpsr", "tpsr-guide") for env in ENVIRONMENTS
    ]
    over_pca = [_gaps(defaults[env], "tpsr", "pca") for env in ENVIRONMENTS]
    pairs = sum(len(g) for g in merged)
    return (
        f"Of the guide's {total} findings, with its own settings "
        f"{_verdict_counts(with_guide)}; with the defaults {_verdict_counts(with_defaults)}. "
        f"Over the {len(ENVIRONMENTS)} environments the defaults' TPSR is above the guide's "
        f"settings at {sum(g > DIFFERENCE_SEMS for m in merged for g in m)} of {pairs} data "
        f"sizes and beats PCA at {sum(g > DIFFERENCE_SEMS for m in over_pca for g in m)} of "
        f"{sum(len(g) for g in over_pca)}"
    )


def _not_reproduced(
    data: Data, defaults: Mapping[str, Table], guide: Mapping[str, Table]
) -> list[str]:
    """What the guide found that does not hold here, with the measurements that say why."""
    partial_rows = data[HEADLINE["defaults"][ENVIRONMENTS.index("partial")]]
    largest = _sizes(defaults["partial"])[-1]
    pca_partial = _entry(defaults["partial"], "pca", largest)
    ceiling = _entry(defaults["partial"], TRUE_POSITION, largest)
    guide_full = _method(guide["full"], "tpsr")
    failed = _verdicts(guide)[NOT_REPRODUCED]  # in the guide's own environments
    pca_share = (
        pca_partial["mean"] / ceiling["mean"] if pca_partial and ceiling else math.nan
    )
    summary = _summary(defaults, guide)  # the README's line says the same
    return [
        f"{summary} (the findings' table below). With the guide's "
        "settings these do not reproduce: " + "; ".join(failed) + ".",
        "",
        f"- **PCA does not fail without memory.** In `partial` PCA of the current image scores "
        f"{pca_partial['mean'] if pca_partial else math.nan:.1f} at {largest} episodes "
        f"({pca_share:.0%} of the ceiling) where the guide's PCA fails. Its states place the "
        f"robot to {_position_error(partial_rows, 'pca', largest):.2f} m (median error of "
        f"the 10 nearest states; the TPSR's: {_position_error(partial_rows, 'tpsr', largest):.2f}"
        " m): the camera's vertical extent (a strip of ±11.3°, which the guide does not give) "
        "shows the floor and the top of any wall farther than 10 m, so the wall's height in "
        "the image tells its distance, and a reactive policy solves the task. A representation "
        "can then beat PCA only by precision, not by memory. The same holds with distractors, "
        "which change only the red channel." + _sentence(narrowest_camera(data)),
        _strip_bullet(defaults["partial-strip"]),
        _memory_bullet(data),
        f"- **The guide's settings fall short of its own figures in `full`**: "
        f"{_span([t['mean'] for t in guide_full])} where its figure 4.11 reaches about 470 from "
        "5000 episodes on. Each action's operators are estimated from a 25th of the data; "
        "pooling them (appendix, Fit: pooled action operators) is the largest single gain of "
        "the defaults.",
    ]


def _memory_bullet(data: Data) -> str:
    """The guide's memory against ours, and which of `learner memory`'s variants keeps the
    defaults' at 0 where the runs recorded both."""
    text = (
        "- **Our TPSRs do not remember.** The guide's memory of 3-4 steps (section 4.4) is not "
        "measured with either preset (appendix, Memory): the states of two runs that saw "
        "different pasts merge at the first identical step."
    )
    paths = paths_memory(data[tpsr_job("partial-strip")])
    if paths is None:
        return text
    return text + (
        f" With the defaults in `partial-strip` (the predictive section) `learner memory`'s "
        f"paths variant alone keeps them apart for a median {paths:g} step(s); in its "
        "stand-still variant, whose two runs differ in one action only, they merge at once, "
        "and from that uninformed start an exact belief over the robot's position stays "
        "under the threshold there too (appendix, Memory)."
    )


def _strip_bullet(table: Table) -> str:
    """What ``partial-strip`` shows: PCA and the TPSR once the range cue is hidden."""
    largest = _sizes(table)[-1]
    pca, tpsr = _entry(table, "pca", largest), _entry(table, "tpsr", largest)
    ceiling = _entry(table, TRUE_POSITION, largest)
    if pca is None or tpsr is None or ceiling is None:
        return "- `partial-strip` was not measured."
    beats = difference_in_sems(tpsr, pca) > DIFFERENCE_SEMS
    solved = pca["mean"] >= NEAR_CEILING * ceiling["mean"]
    title = (
        "With the range cue hidden the TPSR beats PCA."
        if beats
        else "Hiding the range cue does not make the TPSR better than PCA."
    )
    return (
        f"- **{title}** In `partial-strip` (a strip of ±5.7° that a wall fills within 20 m) "
        f"PCA scores {pca['mean']:.1f} at {largest} episodes "
        f"({pca['mean'] / ceiling['mean']:.0%} of the ceiling) and the TPSR "
        f"{tpsr['mean']:.1f}; over the data sizes the TPSR is {_versus(table, 'tpsr', 'pca')}. "
        + (
            "A reactive policy no longer solves the task there."
            if not solved
            else "A reactive policy still solves the task there."
        )
    )


def _sentence(text: str) -> str:
    return f" {text}" if text else ""


def _recommended() -> list[str]:
    preset = PRESETS[DEFAULT_PRESET]
    return [
        f"The defaults (`--preset {preset.name}`: {preset.summary}) serve every "
        "environment; no option beyond the environment is needed. With `E` one of "
        + ", ".join(f"`{env}`" for env in ENVIRONMENTS[:-1])
        + f" and `{ENVIRONMENTS[-1]}`:",
        "",
        "```sh",
        "python -m sim_node.generate --environment E --steps 24000 --seed 0 -o train   # 8000 "
        "episodes",
        "python -m sim_node.generate --environment E --steps 20000 --seed 1 -o rl      # 15000 "
        "in full",
        "python -m learner fit train -o model.npz",
        "python -m learner policy model.npz rl -o policy.npz",
        "python -m learner evaluate policy.npz --environment E",
        "```",
        "",
        "`--preset best` on `fit` and `policy` gives the spectral model alone, without the "
        "refinement through the filter (a quarter of the fit's time; the headline's "
        "`--preset best` rows); `--preset guide` gives the guide's settings, exactly as "
        "they were before the defaults changed (the same models bit for bit).",
    ]


def _plot(env: str, tables: Mapping[str, Table], floors: Floors, path: Path) -> None:
    """Mean (line, SEM band) and median (dashed) over data size for the headline's rows; the
    floors, which use no data, as one level each (dotted, SEM band) across the data sizes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colours = ("tab:red", "tab:blue", "tab:pink", "tab:orange", "tab:cyan", "tab:gray", "silver")
    fig, ax = plt.subplots(figsize=(7.0, 4.8))
    for (label, settings, arm, method), colour in zip(_ROWS, colours, strict=True):
        part = _method(tables[arm], method)
        if not part:
            continue
        x = np.array([t["episodes"] for t in part])
        mean = np.array([t["mean"] for t in part])
        sem = np.nan_to_num(np.array([t["sem"] for t in part]))
        ax.plot(x, mean, "-o", color=colour, label=f"{label}, {settings.replace('`', '')}",
                markersize=4)
        ax.plot(x, [t["median"] for t in part], "--", color=colour, linewidth=0.8)
        ax.fill_between(x, mean - sem, mean + sem, color=colour, alpha=0.2)
    sizes = _sizes(tables["defaults"])
    for (label, method), colour in zip(_FLOOR_ROWS, ("tab:brown", "tab:olive"), strict=True):
        floor = floors.get(method)
        if floor is None or not math.isfinite(floor["mean"]) or not sizes:
            continue
        x = np.array([sizes[0], sizes[-1]])
        level, sem = floor["mean"], float(np.nan_to_num(floor["sem"]))
        ax.plot(x, [level, level], ":", color=colour, label=f"{label}, all {floor['runs']} runs")
        ax.fill_between(x, level - sem, level + sem, color=colour, alpha=0.2)
    ax.set_xlabel("training episodes")
    ax.set_ylabel("mean reward of 10 trials (dashed: median over 10 runs)")
    ax.set_title(f"{env}: the learning-planning loop on fresh seeds")
    ax.set_ylim(-50, 500)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, ncol=2, loc="upper center", bbox_to_anchor=(0.5, -0.14))
    fig.tight_layout()
    fig.savefig(path, dpi=100, metadata={"Software": None})
    plt.close(fig)


def render(data: Data) -> list[str]:
    """The page's lines from every job's rows."""
    defaults, guide = _tables(data, "defaults"), _tables(data, "guide")
    floors = _floors(data)
    lines = [
        "# Results",
        "",
        "Every number on this page comes from the CSVs under `results/` (one row per run, "
        "with its seeds, parameters and command) and is regenerated, byte for byte, by "
        "`python -m learner report --reuse`. `python -m learner report` runs the commands "
        "whose CSV is missing (`--rerun`: all of them; several hours on 2 cores). A single "
        "run reruns alone with its row's command and `--episodes N --first-repetition K "
        "--repetitions 1`.",
        "",
        "## What works",
        "",
        *(
            _environment_summary(env, defaults[env], guide[env], floors[env])
            for env in ENVIRONMENTS
        ),
        "",
        "## What does not reproduce from the guide, and why",
        "",
        *_not_reproduced(data, defaults, guide),
        "",
        "## Recommended commands",
        "",
        *_recommended(),
        "",
        "## Headline: the defaults, `--preset best`, the guide's settings, PCA, floors and ceiling",
        "",
        "Protocol (DESIGN.md, guide 4.1-4.2): for each data size, 10 independent random "
        f"training trajectories of {EPISODE_STEPS} recorded steps per episode whatever the "
        f"preset ({8000 * EPISODE_STEPS} at 8000 episodes; the defaults take a window of "
        "their fit at every step, `best` and the guide's settings one window per episode, "
        "as the guide does); each representation learned from the "
        "same data; states tracked with the model's parameters over one separate random RL "
        "trajectory (15000 steps in `full`, 20000 otherwise), the same for every run, so "
        "a table's SEMs hold the training data's spread but not the RL data's (the appendix's "
        "\"The RL trajectory\" runs each with its own); fitted Q-iteration on them; the "
        "standard evaluation (10 fixed starts, 50 greedy steps; score = mean summed reward, at "
        "most about 470; in `drive`, whose robot drives at most 3 m per step, a start also has "
        "a heading). PCA has 2 components in `full`, 4 in `drive` and 3 otherwise, and plans "
        "with the same planner as the TPSR of its arm. Floors: the best constant action (of "
        "25; of 9 in `drive`) and uniformly random actions; both are blind to the state and "
        "use no training data, so each is shown once per environment, pooled over all its "
        "runs in the CSV (every data size; a random run's policy seed is its cell's training "
        "seed, drawn from `--seed`), and every margin is taken over the better of the two. "
        "`make demo` (`python -m learner.demo`) runs each floor once under the same "
        f"evaluation, random actions with policy seed {DEMO_POLICY_SEED}: a single draw from "
        "the spread of the pooled runs. Ceiling: the same planner on the "
        "true position (and heading, in `drive`). Cells: "
        "mean / median / SEM over the 10 runs; memory: the median of `learner memory` (in "
        "steps) where two places look alike (`partial`, `partial-strip`). The seeds "
        f"(`{' '.join(HEADLINE_SEEDS)}`) are fresh: the defaults were chosen on "
        f"`{' '.join(SELECTION_SEEDS)}` (the appendix's studies).",
        "",
    ]
    for index, env in enumerate(ENVIRONMENTS):
        jobs = _arm_jobs(index)
        lines += [
            f"### `{env}`",
            "",
            *_headline_table(env, _arm_tables(data, index), jobs, data),
            "",
            *_floor_table(floors[env], jobs["defaults"]),
            "",
            _margins(defaults[env]),
            "",
            f"The guide's figures: {GUIDE_RESULTS[env]}",
            "",
            f"![{env}](results_{env}.png)",
            "",
        ]
    lines += [
        "## The guide's findings, measured",
        "",
        f"Verdicts follow fixed rules (`learner/verdicts.py`): a representation *works* only "
        f"more than {FLOOR_SEMS:g} SEMs above the best floor (pooled); one method *beats* "
        f"another by more than {DIFFERENCE_SEMS:g} SEMs of the difference and is *level* "
        f"within them; *close to the maximum* is at least {NEAR_CEILING:.0%} of the ceiling "
        f"(*low SEM*: at most the remaining {1 - NEAR_CEILING:.0%}), *near zero* a mean and a "
        f"median of at most {NEAR_FLOOR:.0%} of it, *slightly below* at least "
        f"{SLIGHTLY:.0%} of the other's mean and nowhere above it, *about 300* a mean from "
        f"{ABOUT_300[0]:g} to {ABOUT_300[1]:g} (*medians above*: a median at least the mean). "
        "A finding must hold at every data size: *reproduced* where it does, *better* where "
        "the measurement is at least as good as the finding at every data size and better at "
        "one or more (a TPSR level with or above PCA everywhere and above it somewhere, for "
        f"\"slightly below PCA\"; a mean and median above {ABOUT_300[1]:g} at some sizes and "
        "about 300 with the median above at the others, for \"about 300\"), *not reproduced* "
        "otherwise.",
        "",
        *_findings(defaults, guide),
        "",
        "## Appendix: studies",
        "",
        "Each study varies one thing around the defaults on the selection seeds "
        f"(`{' '.join(SELECTION_SEEDS)}`), at 2000 episodes in `full` (at 8000 every setting "
        "is at the ceiling there) and 8000 elsewhere.",
        "",
    ]
    for section in SECTIONS:
        lines += section.lines(data)
    return lines


README_BEGIN = "<!-- results: written by python -m learner report -->"
README_END = "<!-- end of results -->"
README_EPISODES = 8000
README_SUMMARY_BEGIN = "<!-- summary: written by python -m learner report -->"
README_SUMMARY_END = "<!-- end of summary -->"


def readme_table(data: Data) -> list[str]:
    """The README's results table: each environment at :data:`README_EPISODES` episodes."""
    defaults, guide = _tables(data, "defaults"), _tables(data, "guide")

    def at(table: Table, method: str) -> str:
        entry = _entry(table, method, README_EPISODES)
        return "-" if entry is None else f"{entry['mean']:.1f} / {entry['sem']:.1f}"

    floors, preset_best = _floors(data), _tables(data, "best")
    predictive: dict[str, Table] = {}  # the predictive section's runs: its baselines
    for job in PREDICTIVE_SECTION.jobs:
        if job in data:
            predictive.setdefault(job.environment, []).extend(summarise(data[job]))
    lines = [
        "| environment | TPSR, defaults | TPSR, `--preset best` | TPSR, `--preset guide` "
        "| PCA, same planner | window state (k = 1) | best floor (all its runs) "
        "| ceiling (true position) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for env in ENVIRONMENTS:
        floor = _best_floor(floors[env])
        floor_cell = "-" if floor is None else f"{floor['mean']:.1f} / {floor['sem']:.1f}"
        lines.append(
            f"| `{env}` | {at(defaults[env], 'tpsr')} | {at(preset_best[env], 'tpsr')} | "
            f"{at(guide[env], 'tpsr')} | {at(defaults[env], 'pca')} | "
            f"{at(predictive.get(env, []), 'window')} | "
            f"{floor_cell} | {at(defaults[env], TRUE_POSITION)} |"
        )
    return lines


def readme_summary(data: Data) -> str:
    """The README's one-line account of the page: the verdicts' counts (as the page says)."""
    return _summary(_tables(data, "defaults"), _tables(data, "guide"))


def _replace(text: str, begin: str, end: str, block: str, readme: Path) -> str:
    """``text`` with what lies between ``begin`` and ``end`` replaced by ``block``."""
    if begin not in text or end not in text:
        raise ConfigError(f"{readme} has no block {begin} ... {end}")
    head, rest = text.split(begin, 1)
    _, tail = rest.split(end, 1)
    return head + begin + block + end + tail


def write_readme_table(data: Data, readme: Path) -> None:
    """Replace the results table (between :data:`README_BEGIN` and :data:`README_END`) and
    the summary of the page (between :data:`README_SUMMARY_BEGIN` and
    :data:`README_SUMMARY_END`, within a line) in ``readme``, so that neither says more or
    less than the page."""
    text = readme.read_text(encoding="utf-8")
    table = "\n".join(["", *readme_table(data), ""])
    text = _replace(text, README_BEGIN, README_END, table, readme)
    text = _replace(text, README_SUMMARY_BEGIN, README_SUMMARY_END, readme_summary(data), readme)
    readme.write_text(text, encoding="utf-8")


def write_page(data: Data, docs: Path) -> Path:
    """Write ``docs/results.md`` and its figures ``docs/results_<env>.png``."""
    for index, env in enumerate(ENVIRONMENTS):
        floors = pooled_floors(data[HEADLINE["defaults"][index]])
        _plot(env, _arm_tables(data, index), floors, docs / f"results_{env}.png")
    page = docs / "results.md"
    page.write_text("\n".join(render(data)).rstrip() + "\n")
    return page
