"""The camera's vertical extent: the range cue, and where a reactive policy stops solving the task.

The camera sits 2 m above the floor and the walls are 4 m high, so a wall ``d`` metres away
fills the image rows whose elevation tangent lies within ``±2/d``. With the default strip
(``vertical_half_extent`` 0.2, ±11.3°) every wall farther than 10 m shows its top and the
floor: the wall's height in one image tells the distance to it, and a reactive policy (PCA
of the current image) can locate the robot. A narrower strip hides that cue: at 0.1 up to
20 m, at 0.05 up to 40 m, and at 0.03 up to 67 m, more than the room's diagonal (63.6 m).

The study (one ``learner study`` per environment and preset) measures the floors, PCA,
the TPSR with ``best`` and with the guide's fit (both under ``best``'s planner),
and the true-position ceiling at each extent, with ``learner memory`` on every model in
``partial``. Its verdict says where PCA stops reaching the ceiling, and whether any extent
opens a gap of :data:`GAP` points between PCA and the ceiling in ``partial`` while PCA
still solves ``full`` (what a named environment would need, as in the guide's figures
4.5 and 4.8).
"""

from __future__ import annotations

import math
from typing import Any

from learner.jobs import BEST_PRESET, SELECTION_SEEDS, Job, study_job
from learner.sections import (
    Data,
    Section,
    cell,
    comparison,
    judged,
    median_text,
    row_parameters,
    study_entries,
    varied,
)
from learner.verdicts import NEAR_CEILING
from sim_node import SimConfig
from sim_node.config import STRIP_VERTICAL_HALF_EXTENT
from tpsr_ros.core.presets import PRESETS, departures
from tpsr_ros.io.policy import TRUE_POSITION

__all__ = ["CAMERA_SECTION", "EXTENTS", "GAP", "narrowest_camera", "wall_fills_up_to"]

EXTENTS = ("0.03", "0.05", "0.1", "0.2")
"""The vertical half-extents studied: the default 0.2 down to a strip the wall fills across
the room."""
GAP = 40.0
"""Points between PCA and the ceiling in ``partial`` that would make a camera worth naming
as an environment of its own."""
EPISODES = 8000


def wall_fills_up_to(vertical_half_extent: float, config: SimConfig | None = None) -> float:
    """The distance (m) up to which a wall fills every image row of the strip."""
    config = config or SimConfig()
    below, above = config.robot_height, config.wall_height - config.robot_height
    return min(below, above) / vertical_half_extent


def _best_planner() -> tuple[str, ...]:
    """``--set fqi.NAME=VALUE`` options that give the guide preset ``best``'s planner."""
    best, guide = PRESETS["best"].fqi_config(), PRESETS["guide"].fqi_config()
    return tuple(
        part
        for name, value in departures(best, guide).items()
        for part in ("--set", f"fqi.{name}={value}")
    )


def _jobs() -> tuple[Job, ...]:
    vary = "sim.vertical_half_extent=" + ",".join(EXTENTS)
    jobs = []
    for environment in ("partial", "full"):
        memory = ("--memory",) if environment == "partial" else ()
        common = ("--episodes", str(EPISODES), *SELECTION_SEEDS, *memory)
        jobs.append(study_job("camera/best", environment, vary, *BEST_PRESET, *common))
        jobs.append(
            study_job(
                "camera/guide", environment, vary, "--preset", "guide", *_best_planner(),
                "--methods", "tpsr", *common,
            )
        )
    return tuple(jobs)


def _memory_text(rows: list[Any], value: str, method: str) -> str:
    memory = [
        r.memory
        for r in rows
        if r.method == method
        and math.isfinite(r.memory)
        and row_parameters(r).get("sim", {}).get("vertical_half_extent") == float(value)
    ]
    return f"{median_text(memory, '.0f')}, {max(memory):.0f}" if memory else "-"


def _render(section: Section, data: Data) -> list[str]:
    lines = [
        "Cells: mean / median / SEM of 10 runs at 8000 episodes; the TPSR with `--preset best` "
        "and with the guide's fit (`--preset guide`), both under `best`'s planner; R² "
        "of the true position's affine map from the states (x / y); position error: the "
        "median distance between the robot and where its 10 nearest states place it (m); "
        "memory: `learner memory`'s steps (median, max over the runs; `partial` only). The "
        "last column compares the TPSR with `best` to PCA.",
        "",
    ]
    pca_means: dict[str, dict[str, float]] = {}
    ceilings: dict[str, float] = {}
    for best_job, guide_job in zip(section.jobs[::2], section.jobs[1::2], strict=True):
        environment = best_job.environment
        reference, best = study_entries(best_job, data[best_job])
        _, guide = study_entries(guide_job, data[guide_job])
        _, values = varied(best_job)
        ceiling = next((e for e in reference if e["method"] == TRUE_POSITION), None)
        if ceiling is None:  # a study run without the ceiling: nothing to measure against
            lines += [f"**`{environment}`**: no true-position ceiling in its CSV.", ""]
            continue
        floors = [e for e in reference if e["method"] != TRUE_POSITION]
        lines += [
            f"**`{environment}`** (ceiling, true position: {cell(ceiling)}; floors: "
            + ", ".join(f"{e['method']} {cell(e)}" for e in floors)
            + ")",
            "",
            "| vertical half-extent (wall fills the strip up to) | PCA | TPSR, `best` | "
            "TPSR, the guide's fit | ceiling - PCA | R² x / y: PCA, TPSR | position error: "
            "PCA, TPSR | memory: TPSR, `best` | TPSR - PCA |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        pca_means[environment], ceilings[environment] = {}, ceiling["mean"]
        for value in values:
            pca, tpsr = best.get((value, "pca")), best.get((value, "tpsr"))
            if pca is None or tpsr is None:
                continue
            gap = ceiling["mean"] - pca["mean"]
            pca_means[environment][value] = pca["mean"]
            lines.append(
                f"| `{value}` ({wall_fills_up_to(float(value)):.0f} m) | {cell(pca)} | "
                f"{cell(tpsr)} | {cell(guide.get((value, 'tpsr')))} | {gap:.1f} | "
                f"{pca['r2']}, {tpsr['r2']} | {pca['position_error']}, "
                f"{tpsr['position_error']} | {_memory_text(data[best_job], value, 'tpsr')} | "
                f"{judged(*comparison(tpsr, pca))} |"
            )
        lines.append("")
    memory = [
        r.memory
        for job in section.jobs
        for r in data[job]
        if r.method == "tpsr" and math.isfinite(r.memory)
    ]
    if not memory:
        remembered = "- Memory: not measured."
    else:
        longest = max(memory)
        remembered = (
            f"- Memory (`partial`, every extent, both fits): at most {longest:.0f} step(s); "
            + (
                "hiding the range cue does not make the TPSR remember (the guide: 3-4 steps)."
                if longest < 3
                else "the TPSR remembers where the range cue is hidden."
            )
        )
    return [*lines, "**Verdict.**", "", *_verdict(pca_means, ceilings), remembered]


def _verdict(pca_means: dict[str, dict[str, float]], ceilings: dict[str, float]) -> list[str]:
    """Where PCA stops reaching the ceiling, and whether a camera opens the named gap."""
    if not {"partial", "full"} <= set(pca_means) or not pca_means["partial"]:
        return ["Not measured."]
    bullets = []
    for environment in ("partial", "full"):
        means, ceiling = pca_means[environment], ceilings[environment]
        solved = [v for v, mean in means.items() if mean >= NEAR_CEILING * ceiling]
        unsolved = [v for v in means if v not in solved]
        bullets.append(
            f"- `{environment}`: PCA of the current image reaches {NEAR_CEILING:.0%} of the "
            f"ceiling at vertical half-extent(s) {', '.join(solved) or 'none'}; it falls "
            f"short at {', '.join(unsolved) or 'none'}."
        )
    gaps = {v: ceilings["partial"] - mean for v, mean in pca_means["partial"].items()}
    full_solved = {
        v for v, mean in pca_means["full"].items() if mean >= NEAR_CEILING * ceilings["full"]
    }
    candidates = [(v, gap) for v, gap in gaps.items() if gap >= GAP and v in full_solved]
    if candidates:
        value, gap = max(candidates, key=lambda item: item[1])
        named = (
            " It is the environment `partial-strip` (headline above)."
            if float(value) == STRIP_VERTICAL_HALF_EXTENT
            else ""
        )
        bullets.append(
            f"- **A camera of vertical half-extent {value} opens a gap of {gap:.1f} points** "
            f"between PCA and the ceiling in `partial` while PCA still solves `full`: there a "
            f"reactive policy no longer solves the task.{named}"
        )
    else:
        value, gap = max(gaps.items(), key=lambda item: item[1])
        bullets.append(
            f"- No vertical extent opens a gap of {GAP:.0f} points between PCA and the "
            f"ceiling in `partial` while PCA still solves `full`: the largest gap is "
            f"{gap:.1f} at {value}."
        )
    return bullets


def narrowest_camera(data: Data) -> str:
    """One sentence: PCA and the TPSR in ``partial`` with the narrowest strip studied."""
    job = CAMERA_SECTION.jobs[0]
    if job not in data:
        return ""
    reference, entries = study_entries(job, data[job])
    narrowest = min(EXTENTS, key=float)
    pca, tpsr = entries.get((narrowest, "pca")), entries.get((narrowest, "tpsr"))
    ceiling = next((e for e in reference if e["method"] == TRUE_POSITION), None)
    if pca is None or tpsr is None or ceiling is None:
        return ""
    return (
        f"With a strip the wall fills across the room (vertical half-extent {narrowest}, "
        f"8000 episodes, selection seeds) PCA scores {pca['mean']:.1f} "
        f"({pca['mean'] / ceiling['mean']:.0%} of the ceiling) and the TPSR {tpsr['mean']:.1f} "
        "(appendix, Camera)."
    )


CAMERA_SECTION = Section(
    "camera",
    "Camera: the vertical extent (the range cue)",
    "The default strip shows the floor and the top of any wall farther than 10 m, so one "
    "image tells the distance to the wall. With a narrower strip that hides it, where does "
    "a reactive policy (PCA of the current image) stop solving the task, and does the "
    "TPSR's state then score more than PCA?",
    _jobs(),
    _render,
)
"""The appendix section of this study."""
