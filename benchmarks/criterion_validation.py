"""Does the tuning criterion rank configurations like the RL score? (issue 14, docs "Tuning")

``python -m benchmarks.criterion_validation DIR... [--per-run OUT.csv]`` reads the
``experiment_*.csv`` of ``learner experiment`` / ``study`` output directories (one TPSR
configuration per directory, its planner the same in all), rebuilds each TPSR run's own
training trajectory from its recorded seed, computes the criterion of
:mod:`learner.criterion` on it exactly as ``learner tune`` would (fit on the first 75 %,
held-out R^2 on the rest; no reward, no ground truth), and prints per configuration the
mean, median and SEM of the RL score, the mean affine R^2 of the true position and the
median criterion, then the Spearman rank correlations across configurations
(``scipy.stats.spearmanr``) of the criterion with the mean score, the median score and
the position R^2.
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path
from typing import Any

import numpy as np
from scipy.stats import spearmanr

from learner.criterion import CriterionConfig, ObservationFeatures, score_tpsr, split_trajectory
from learner.simulated import random_trajectory
from tpsr_ros.core.tpsr import TPSRConfig


def criterion_rows(directory: Path, criterion: CriterionConfig) -> list[dict[str, Any]]:
    """One entry per TPSR run of the directory's CSVs: score, R^2 and the criterion."""
    entries = []
    for path in sorted(directory.glob("experiment_*.csv")):
        with path.open() as handle:
            runs = [r for r in csv.DictReader(handle) if r["method"] == "tpsr"]
        for run in runs:
            tpsr = TPSRConfig(**json.loads(run["parameters"])["tpsr"])
            steps = int(run["episodes"]) * (tpsr.history_length + 1 + tpsr.test_length)
            trajectory = random_trajectory(run["environment"], steps, int(run["train_seed"]))
            train, heldout = split_trajectory(trajectory, criterion.holdout)
            features = ObservationFeatures.fit(train.observations, criterion.feature_dim)
            score, _ = score_tpsr(tpsr, train, heldout, features, criterion)
            entries.append(
                {
                    "configuration": directory.name,
                    "environment": run["environment"],
                    "episodes": int(run["episodes"]),
                    "repetition": int(run["repetition"]),
                    "score": float(run["score"]),
                    "r2": (float(run["r2_x"]) + float(run["r2_y"])) / 2,
                    "criterion": score.value,
                }
            )
            print(
                f"  {directory.name} run {run['repetition']}: score {run['score']}, "
                f"criterion {score.value:.4f}",
                flush=True,
            )
    return entries


def summary(entries: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per configuration: score mean/median/SEM, mean R^2, median criterion."""
    table = []
    for name in dict.fromkeys(e["configuration"] for e in entries):
        mine = [e for e in entries if e["configuration"] == name]
        scores = np.array([e["score"] for e in mine])
        scores = scores[np.isfinite(scores)]
        table.append(
            {
                "configuration": name,
                "runs": len(mine),
                "mean": float(scores.mean()),
                "median": float(np.median(scores)),
                "sem": (
                    float(scores.std(ddof=1) / np.sqrt(len(scores)))
                    if len(scores) > 1
                    else float("nan")
                ),
                "r2": float(np.nanmean([e["r2"] for e in mine])),
                # a failed fit is -inf: the median stays defined
                "criterion": float(np.median([e["criterion"] for e in mine])),
            }
        )
    return table


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.criterion_validation")
    parser.add_argument("directories", nargs="+", type=Path)
    parser.add_argument("--per-run", type=Path, default=None, help="write every run here")
    args = parser.parse_args(argv)
    entries = [e for d in args.directories for e in criterion_rows(d, CriterionConfig())]
    if args.per_run is not None:
        with args.per_run.open("w", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=list(entries[0]))
            writer.writeheader()
            writer.writerows(entries)
    table = summary(entries)
    print(f"{'configuration':40s} {'runs':>4s} {'mean':>6s} {'median':>6s} {'SEM':>5s} "
          f"{'R2':>5s} {'criterion':>9s}")
    for t in table:
        print(f"{t['configuration']:40s} {t['runs']:4d} {t['mean']:6.1f} {t['median']:6.1f} "
              f"{t['sem']:5.1f} {t['r2']:5.3f} {t['criterion']:9.4f}")
    crit = [t["criterion"] for t in table]
    for label, key in (("mean score", "mean"), ("median score", "median"), ("position R2", "r2")):
        rho, p = spearmanr(crit, [t[key] for t in table])
        print(f"Spearman(criterion, {label}) = {rho:+.2f} (p = {p:.3f}, n = {len(table)})")


if __name__ == "__main__":
    main()
