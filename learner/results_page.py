"""The results page (``docs/results.md``) rendered from the experiment CSVs alone.

The page leads with what works and what does not reproduce from the guide, the commands to
use, the headline tables (the defaults, ``--preset guide``, PCA with each planner, floors and
ceiling, by data size, on fresh seeds), the guide's findings judged by
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
from learner.floors import CONSTANT, FLOORS, RANDOM
from learner.jobs import (
    ENVIRONMENTS,
    GUIDE_ENVIRONMENTS,
    HEADLINE_SEEDS,
    SELECTION_SEEDS,
    Job,
    experiment_job,
)
from learner.sections import Data, cell
from learner.tables import Row, difference_in_sems, summarise
from learner.verdicts import (
    DIFFERENCE_SEMS,
    FLOOR_SEMS,
    GUIDE_RESULTS,
    NEAR_CEILING,
    Table,
    judge,
)
from tpsr_ros.core.errors import ConfigError
from tpsr_ros.core.presets import DEFAULT_PRESET, PRESETS
from tpsr_ros.io.policy import TRUE_POSITION

__all__ = [
    "HEADLINE",
    "all_jobs",
    "readme_table",
    "render",
    "write_page",
    "write_readme_table",
]

HEADLINE: Mapping[str, tuple[Job, ...]] = {
    "defaults": tuple(experiment_job("defaults", env, *HEADLINE_SEEDS) for env in ENVIRONMENTS),
    "guide": tuple(
        experiment_job("guide", env, "--preset", "guide", *HEADLINE_SEEDS) for env in ENVIRONMENTS
    ),
}
"""The headline's jobs: every method under the defaults and under ``--preset guide``."""

_ROWS = (
    ("TPSR", "defaults", "defaults", "tpsr"),
    ("PCA", "the defaults' planner", "defaults", "pca"),
    ("TPSR", "`--preset guide`", "guide", "tpsr"),
    ("PCA", "the guide's planner", "guide", "pca"),
    ("true position (ceiling)", "the defaults' planner", "defaults", TRUE_POSITION),
    ("true position (ceiling)", "the guide's planner", "guide", TRUE_POSITION),
    ("best constant action (floor)", "-", "defaults", CONSTANT),
    ("random actions (floor)", "-", "defaults", RANDOM),
)
"""Headline table rows: (representation, settings, headline arm, method)."""


def all_jobs() -> list[Job]:
    """Every job of the page, each once, in page order."""
    jobs = [job for arm in HEADLINE.values() for job in arm]
    jobs += [job for section in SECTIONS for job in section.jobs]
    return list(dict.fromkeys(jobs))


def _tables(data: Data, arm: str) -> dict[str, Table]:
    return {env: summarise(data[job]) for env, job in zip(ENVIRONMENTS, HEADLINE[arm], strict=True)}


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


def _environment_summary(env: str, best: Table, guide: Table) -> str:
    tpsr = _method(best, "tpsr")
    ceiling = _method(best, TRUE_POSITION)
    floors = [t for t in best if t["method"] in FLOORS]
    weakest = min((t["margin_sem"] for t in tpsr), default=math.nan)
    sizes = _sizes(best)
    return (
        f"- **`{env}`**: with the defaults the TPSR scores {_span([t['mean'] for t in tpsr])} "
        f"(medians {_span([t['median'] for t in tpsr])}, SEMs {_span([t['sem'] for t in tpsr])}) "
        f"from {sizes[0]} to {sizes[-1]} episodes, against a ceiling of "
        f"{_span([t['mean'] for t in ceiling])} and floors of "
        f"{_span([t['mean'] for t in floors])} (at least {weakest:.0f} SEMs above the best "
        f"floor). PCA with the same planner scores "
        f"{_span([t['mean'] for t in _method(best, 'pca')])}: "
        f"the TPSR is {_versus(best, 'tpsr', 'pca')}. The guide's settings "
        f"(`--preset guide`) score {_span([t['mean'] for t in _method(guide, 'tpsr')])}; "
        f"against them the defaults are {_versus(_merged(best, guide), 'tpsr', 'tpsr-guide')}."
    )


def _merged(best: Table, guide: Table) -> Table:
    """``best`` with the guide's TPSR entries renamed ``tpsr-guide`` (to compare them)."""
    return [*best, *({**t, "method": "tpsr-guide"} for t in guide if t["method"] == "tpsr")]


def _headline_table(env: str, tables: Mapping[str, Table], jobs: Mapping[str, Job]) -> list[str]:
    sizes = _sizes(tables["defaults"])
    lines = [
        "| representation | settings | "
        + " | ".join(f"{n} episodes" for n in sizes)
        + " | command |",
        "|---|---|" + "---|" * len(sizes) + "---|",
    ]
    for label, settings, arm, method in _ROWS:
        cells = [cell(_entry(tables[arm], method, n)) for n in sizes]
        lines.append(
            f"| {label} | {settings} | " + " | ".join(cells) + f" | `{jobs[arm].command}` |"
        )
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
        "The defaults' TPSR against the best floor: "
        + ", ".join(f"{t['episodes']}: {t['margin_sem']:+.1f} SEM" for t in tpsr)
        + f"; against the ceiling: {gaps}."
    )


def _findings(best: Mapping[str, Table], guide: Mapping[str, Table]) -> list[str]:
    lines = [
        "| environment | the guide's finding | `--preset guide`: measured | verdict | defaults: "
        "measured | verdict |",
        "|---|---|---|---|---|---|",
    ]
    for (finding, measured_guide, verdict_guide), (_, measured_best, verdict_best) in zip(
        judge(dict(guide)), judge(dict(best)), strict=True
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


def _not_reproduced(data: Data, best: Mapping[str, Table], guide: Mapping[str, Table]) -> list[str]:
    """What the guide found that does not hold here, with the measurements that say why."""
    partial_rows = data[HEADLINE["defaults"][ENVIRONMENTS.index("partial")]]
    largest = _sizes(best["partial"])[-1]
    pca_partial = _entry(best["partial"], "pca", largest)
    ceiling = _entry(best["partial"], TRUE_POSITION, largest)
    guide_full = _method(guide["full"], "tpsr")
    guides = {env: guide[env] for env in GUIDE_ENVIRONMENTS}  # the guide's own environments
    failed = [
        f"`{finding.environment}`: {finding.claim}"
        for finding, _, verdict in judge(guides)
        if verdict != "reproduced"
    ]
    pca_share = (
        pca_partial["mean"] / ceiling["mean"] if pca_partial and ceiling else math.nan
    )
    return [
        f"Of the guide's {len(judge(guides))} findings (table below), "
        f"{len(failed)} do not reproduce with its own settings: " + "; ".join(failed) + ".",
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
        _strip_bullet(best["partial-strip"]),
        "- **Our TPSRs do not remember.** The guide's memory of 3-4 steps (section 4.4) is not "
        "measured with either preset (appendix, Memory): the states of two runs that saw "
        "different pasts merge at the first identical step.",
        f"- **The guide's settings fall short of its own figures in `full`**: "
        f"{_span([t['mean'] for t in guide_full])} where its figure 4.11 reaches about 470 from "
        "5000 episodes on. Each action's operators are estimated from a 25th of the data; "
        "pooling them (appendix, Fit: pooled action operators) is the largest single gain of "
        "the defaults.",
    ]


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
        "`--preset guide` on `fit` and `policy` gives the guide's settings instead, exactly as "
        "they were before the defaults changed (the same models bit for bit).",
    ]


def _plot(env: str, tables: Mapping[str, Table], path: Path) -> None:
    """Mean (line, SEM band) and median (dashed) over data size for the headline's rows."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colours = ("tab:red", "tab:blue", "tab:orange", "tab:cyan", "tab:gray", "silver", "tab:brown",
               "tab:olive")
    fig, ax = plt.subplots(figsize=(7.0, 4.8))
    for (label, settings, arm, method), colour in zip(_ROWS, colours, strict=True):
        part = _method(tables[arm], method)
        if not part:
            continue
        x = np.array([t["episodes"] for t in part])
        mean = np.array([t["mean"] for t in part])
        sem = np.nan_to_num(np.array([t["sem"] for t in part]))
        name = label if settings == "-" else f"{label}, {settings.replace('`', '')}"
        ax.plot(x, mean, "-o", color=colour, label=name, markersize=4)
        ax.plot(x, [t["median"] for t in part], "--", color=colour, linewidth=0.8)
        ax.fill_between(x, mean - sem, mean + sem, color=colour, alpha=0.2)
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
    best, guide = _tables(data, "defaults"), _tables(data, "guide")
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
        *(_environment_summary(env, best[env], guide[env]) for env in ENVIRONMENTS),
        "",
        "## What does not reproduce from the guide, and why",
        "",
        *_not_reproduced(data, best, guide),
        "",
        "## Recommended commands",
        "",
        *_recommended(),
        "",
        "## Headline: the defaults, the guide's settings, PCA, floors and ceiling",
        "",
        "Protocol (DESIGN.md, guide 4.1-4.2): for each data size, 10 independent random "
        "training trajectories (3 steps per episode); each representation learned from the "
        "same data; states tracked with the model's parameters over one separate random RL "
        "trajectory (15000 steps in `full`, 20000 otherwise); fitted Q-iteration on them; the "
        "standard evaluation (10 fixed starts, 50 greedy steps; score = mean summed reward, at "
        "most about 470; in `drive`, whose robot drives at most 3 m per step, a start also has "
        "a heading). PCA has 2 components in `full`, 4 in `drive` and 3 otherwise, and plans "
        "with the same planner as the TPSR of its arm. Floors: the best constant action (of "
        "25; of 9 in `drive`) and uniformly random actions; ceiling: the same planner on the "
        "true position (and heading, in `drive`). Cells: "
        "mean / median / SEM over the 10 runs. The seeds "
        f"(`{' '.join(HEADLINE_SEEDS)}`) are fresh: the defaults were chosen on "
        f"`{' '.join(SELECTION_SEEDS)}` (the appendix's studies).",
        "",
    ]
    for env, defaults_job, guide_job in zip(
        ENVIRONMENTS, HEADLINE["defaults"], HEADLINE["guide"], strict=True
    ):
        tables = {"defaults": best[env], "guide": guide[env]}
        jobs = {"defaults": defaults_job, "guide": guide_job}
        lines += [
            f"### `{env}`",
            "",
            *_headline_table(env, tables, jobs),
            "",
            _margins(best[env]),
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
        f"more than {FLOOR_SEMS:g} SEMs above the best floor; one method *beats* another by "
        f"more than {DIFFERENCE_SEMS:g} SEMs of the difference; *close to the maximum* is at "
        "least 95 % of the ceiling, *near zero* at most 25 % of it, *slightly below* at least "
        "90 % of the other's mean; a finding must hold at every data size.",
        "",
        *_findings(best, guide),
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


def readme_table(data: Data) -> list[str]:
    """The README's results table: each environment at :data:`README_EPISODES` episodes."""
    best, guide = _tables(data, "defaults"), _tables(data, "guide")

    def at(table: Table, method: str) -> str:
        entry = _entry(table, method, README_EPISODES)
        return "-" if entry is None else f"{entry['mean']:.1f} / {entry['sem']:.1f}"

    lines = [
        "| environment | TPSR, defaults | TPSR, `--preset guide` | PCA, same planner | best "
        "floor | ceiling (true position) |",
        "|---|---|---|---|---|---|",
    ]
    for env in ENVIRONMENTS:
        floors = [
            e for m in FLOORS if (e := _entry(best[env], m, README_EPISODES)) is not None
        ]
        floor = max(floors, key=lambda e: e["mean"], default=None)
        floor_cell = "-" if floor is None else f"{floor['mean']:.1f} / {floor['sem']:.1f}"
        lines.append(
            f"| `{env}` | {at(best[env], 'tpsr')} | {at(guide[env], 'tpsr')} | "
            f"{at(best[env], 'pca')} | {floor_cell} | {at(best[env], TRUE_POSITION)} |"
        )
    return lines


def write_readme_table(data: Data, readme: Path) -> None:
    """Replace the lines between :data:`README_BEGIN` and :data:`README_END` in ``readme``."""
    text = readme.read_text(encoding="utf-8")
    if README_BEGIN not in text or README_END not in text:
        raise ConfigError(f"{readme} has no results block ({README_BEGIN} ... {README_END})")
    head, rest = text.split(README_BEGIN, 1)
    _, tail = rest.split(README_END, 1)
    block = "\n".join([README_BEGIN, *readme_table(data), README_END])
    readme.write_text(head + block + tail, encoding="utf-8")


def write_page(data: Data, docs: Path) -> Path:
    """Write ``docs/results.md`` and its figures ``docs/results_<env>.png``."""
    for env, defaults_job, guide_job in zip(
        ENVIRONMENTS, HEADLINE["defaults"], HEADLINE["guide"], strict=True
    ):
        tables = {"defaults": summarise(data[defaults_job]), "guide": summarise(data[guide_job])}
        _plot(env, tables, docs / f"results_{env}.png")
    page = docs / "results.md"
    page.write_text("\n".join(render(data)).rstrip() + "\n")
    return page
