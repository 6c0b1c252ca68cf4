"""The guide's findings (section 4.2) and the fixed rules that judge them against measured tables.

A table is :func:`learner.tables.summarise`'s: one entry per (method, data size) with
mean, median, SEM and the margin over the best floor (the floors pooled over every data
size: they use no data). The rules:

- a learned representation *works* only where its mean lies more than ``FLOOR_SEMS`` (3)
  standard errors of the difference above the best floor: nothing inside the floor's
  reach supports a claim;
- one method *beats* another where its mean lies more than ``DIFFERENCE_SEMS`` (2)
  standard errors of the difference above the other's, is *level* with it within them;
- *close to the ceiling* means a mean of at least ``NEAR_CEILING`` (95 %) of the true
  position's, with an SEM (*low SEM*) of at most the remaining 5 % of it; *near the
  floor* a mean and a median of at most ``NEAR_FLOOR`` (25 %) of it; *slightly below* at
  least ``SLIGHTLY`` (90 %) of the other's mean and nowhere above it; *about 300* a mean
  within ``ABOUT_300`` (250 to 350), *medians above* a median at least the mean;
- a finding must hold at every data size: *reproduced* when it holds at every one,
  *better* when the measurement is at least as good as the finding at every data size and
  better at one or more (a TPSR level with or above PCA everywhere and above it somewhere
  is better than "slightly below PCA"; a mean and median above 350 at one or more data
  sizes, about 300 with the median above at the others, is better than "about 300"), *not
  reproduced* otherwise, mixed cases included.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from learner.tables import difference_in_sems, margin_text
from tpsr_ros.io.policy import TRUE_POSITION

__all__ = [
    "BETTER",
    "DIFFERENCE_SEMS",
    "FINDINGS",
    "FLOOR_SEMS",
    "GUIDE_RESULTS",
    "NEAR_CEILING",
    "NEAR_FLOOR",
    "ABOUT_300",
    "NOT_REPRODUCED",
    "REPRODUCED",
    "SLIGHTLY",
    "Finding",
    "Table",
    "judge",
]

FLOOR_SEMS = 3.0
DIFFERENCE_SEMS = 2.0
NEAR_CEILING = 0.95
NEAR_FLOOR = 0.25
SLIGHTLY = 0.9
ABOUT_300 = (250.0, 350.0)

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
    "partial-strip": "Not in the guide: partial's camera with a strip that hides the walls' "
    "distance; the guide's findings for partial (figure 4.8) are judged here too.",
    "drive": "Not in the guide: a differential-drive robot (9 actions: forward speed 0, 1.5 or "
    "3 m/s times turn rate -45, 0 or +45 degrees per step) whose 300 degree camera turns with "
    "it; the ceiling plans on the true x, y and heading (cos, sin).",
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
    """Reproduced where the TPSR works, lies within ``SLIGHTLY`` of PCA and nowhere above it;
    better where it works, is nowhere below PCA and above it at one or more data sizes."""
    pairs = _pairs(table, "tpsr", "pca")
    if not pairs:
        return "not measured", NOT_REPRODUCED
    gaps = [difference_in_sems(t, p) for t, p in pairs]
    text = _gap_text(pairs, gaps)
    if not all(_works(t) for t, _ in pairs):
        return text, NOT_REPRODUCED
    above = [g > DIFFERENCE_SEMS for g in gaps]
    below = [g < -DIFFERENCE_SEMS for g in gaps]
    if any(above):
        return text, BETTER if not any(below) else NOT_REPRODUCED
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
    ok = all(
        t["mean"] >= NEAR_CEILING * _ceiling(table, t["episodes"])
        and t["sem"] <= (1 - NEAR_CEILING) * _ceiling(table, t["episodes"])
        and _works(t)
        for t in late
    )
    text = "TPSR from 5000 episodes: " + ", ".join(
        f"{t['episodes']}: mean {t['mean']:.0f} = {t['mean'] / _ceiling(table, t['episodes']):.0%}"
        f" of the ceiling, SEM {t['sem']:.1f}"
        for t in late
    )
    return text, REPRODUCED if ok else NOT_REPRODUCED


def _pca_near_floor(table: Table) -> tuple[str, str]:
    """Reproduced where PCA's mean and median stay near the floor at every data size."""
    pca = _entries(table, "pca")
    low = pca and all(
        max(t["mean"], t["median"]) <= NEAR_FLOOR * _ceiling(table, t["episodes"]) for t in pca
    )
    return f"PCA by data size {_by_size(table, 'pca')}", REPRODUCED if low else NOT_REPRODUCED


def _tpsr_beats_pca(table: Table) -> tuple[str, str]:
    """Reproduced where the TPSR works and beats PCA at every data size."""
    pairs = _pairs(table, "tpsr", "pca")
    if not pairs:
        return "not measured", NOT_REPRODUCED
    gaps = [difference_in_sems(t, p) for t, p in pairs]
    ok = all(
        g > DIFFERENCE_SEMS and _works(t) for (t, _), g in zip(pairs, gaps, strict=True)
    )
    return _gap_text(pairs, gaps), REPRODUCED if ok else NOT_REPRODUCED


def _tpsr_about_300(table: Table) -> tuple[str, str]:
    """Reproduced where the TPSR works with a mean about 300 and its median above the mean at
    every data size; better where every size has that or a mean and median above 350."""
    tpsr = _entries(table, "tpsr")
    if not tpsr:
        return "not measured", NOT_REPRODUCED
    low, high = ABOUT_300
    text = f"TPSR by data size {_by_size(table, 'tpsr')}"
    about = [low <= t["mean"] <= high and t["median"] >= t["mean"] for t in tpsr]
    above = [t["mean"] > high and t["median"] > high for t in tpsr]
    at_least = all(a or b for a, b in zip(about, above, strict=True))
    if not all(_works(t) for t in tpsr) or not at_least:
        return text, NOT_REPRODUCED
    return text, BETTER if any(above) else REPRODUCED


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
    Finding(
        "partial-strip",
        "PCA: mean slightly above zero, half of the runs below zero (fig. 4.8, partial)",
        _pca_near_floor,
    ),
    Finding(
        "partial-strip", "TPSR: remarkably better than PCA (fig. 4.8, partial)", _tpsr_beats_pca
    ),
    Finding("distractors", "PCA: barely any reward above zero (fig. 4.7)", _pca_near_floor),
    Finding("distractors", "TPSR: mean about 300, medians above (fig. 4.7)", _tpsr_about_300),
    Finding("distractors", "TPSR better than PCA (fig. 4.7)", _tpsr_beats_pca),
)


def judge(tables: dict[str, Table]) -> list[tuple[Finding, str, str]]:
    """``(finding, measured, verdict)`` for every finding whose environment was run."""
    return [(f, *f.judge(tables[f.environment])) for f in FINDINGS if f.environment in tables]


