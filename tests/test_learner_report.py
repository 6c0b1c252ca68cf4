"""learner report: floors beside the ceiling, margins, and verdicts by fixed rules."""

from __future__ import annotations

import csv
import subprocess
import sys

import numpy as np

from learner.experiment import Row, summarise, write_csv
from learner.report import BETTER, NOT_REPRODUCED, REPRODUCED, judge

ENVIRONMENTS = ("full", "partial", "distractors")


def _rows(environment, scores_by_method, episodes=(2000, 8000)):
    """Rows with the given scores: ``{method: [score, ...]}`` at every data size."""
    rows = []
    for size in episodes:
        for method, scores in scores_by_method.items():
            for k, score in enumerate(scores):
                rows.append(
                    Row(environment, method, size, k, 1, 100, float(score), "", 0.0, 0.01, 0,
                        0.9, 0.9, "ok")
                )
    return rows


def test_a_method_inside_the_floors_reach_supports_no_claim():
    rng = np.random.default_rng(0)
    floors = {"constant": [0.0] * 10, "random": rng.normal(0, 30, 10)}
    ceiling = {"true-position": [469.7] * 10}
    # distractors: TPSR mean about 300 is reproduced only outside the floor's reach
    good = {**floors, "tpsr": rng.normal(310, 20, 10), "pca": rng.normal(10, 20, 10), **ceiling}
    noisy = {**floors, "tpsr": [2000.0, -1400.0] + [300.0] * 8, "pca": [0.0] * 10, **ceiling}
    tables = {"distractors": summarise(_rows("distractors", good))}
    verdicts = [v for f, _, v in judge(tables)]
    assert verdicts == [REPRODUCED, REPRODUCED, REPRODUCED]  # PCA ~0, TPSR ~300, TPSR > PCA
    tables = {"distractors": summarise(_rows("distractors", noisy))}
    table = {(t["method"], t["episodes"]): t for t in tables["distractors"]}
    assert abs(table[("tpsr", 2000)]["margin_sem"]) < 3  # mean 300, but SEM ~ 300
    assert [v for f, _, v in judge(tables)][1:] == [NOT_REPRODUCED, NOT_REPRODUCED]


def test_verdicts_better_and_not_reproduced():
    rng = np.random.default_rng(1)
    floors = {"constant": [0.0] * 10, "random": rng.normal(0, 30, 10)}
    ceiling = {"true-position": [469.7] * 10}
    # full: TPSR clearly above PCA ("better" than the guide's "slightly below PCA"), both near
    # the maximum
    full = {**floors, "tpsr": rng.normal(465, 2, 10), "pca": rng.normal(435, 2, 10), **ceiling}
    # partial: PCA works well here (not "near zero"), TPSR no better than PCA
    partial = {**floors, "tpsr": rng.normal(300, 30, 10), "pca": rng.normal(320, 30, 10),
               **ceiling}
    tables = {"full": summarise(_rows("full", full)),
              "partial": summarise(_rows("partial", partial))}
    verdicts = {f.claim: v for f, _, v in judge(tables)}
    claims = list(verdicts)
    assert verdicts[claims[0]] == NOT_REPRODUCED  # PCA median 435 < 95 % of 469.7
    assert verdicts[claims[1]] == BETTER
    assert verdicts[claims[2]] == REPRODUCED  # TPSR >= 95 % of the ceiling from 5000 on
    assert verdicts[claims[3]] == NOT_REPRODUCED and verdicts[claims[4]] == NOT_REPRODUCED


def test_report_reuse_writes_floors_margins_and_findings(tmp_path):
    rng = np.random.default_rng(2)
    results, docs = tmp_path / "results", tmp_path / "docs"
    results.mkdir()
    docs.mkdir()
    for environment in ENVIRONMENTS:
        scores = {"constant": [0.0] * 3, "random": rng.normal(0, 30, 3),
                  "tpsr": rng.normal(300, 30, 3), "pca": rng.normal(200, 30, 3),
                  "true-position": [469.7] * 3}
        write_csv(_rows(environment, scores), results / f"experiment_{environment}.csv")
    (docs / "results.md").write_text("STALE PAGE\n<!-- discussion -->\nhand-written discussion\n")
    result = subprocess.run(
        [sys.executable, "-m", "learner", "report", "--reuse", "--results", str(results),
         "--docs", str(docs)], capture_output=True, text=True, timeout=120,
    )
    assert result.returncode == 0, result.stderr
    page = (docs / "results.md").read_text()
    assert page.endswith("<!-- discussion -->\nhand-written discussion\n")
    assert "STALE PAGE" not in page.split("<!--")[0]
    for environment in ENVIRONMENTS:
        assert f"## `{environment}`" in page
        assert (docs / f"results_{environment}.png").stat().st_size > 10_000
    assert page.count("| constant (floor) |") == 6 and page.count("| random (floor) |") == 6
    assert page.count("(ceiling) |") == 6 and "over random" in page
    assert page.count("| `distractors` |") == 3
    # every row of the CSVs made it in: 5 methods x 2 sizes x 3 runs
    with (results / "experiment_full.csv").open() as handle:
        assert len(list(csv.DictReader(handle))) == 30
    missing = subprocess.run(
        [sys.executable, "-m", "learner", "report", "--reuse", "--results", str(tmp_path / "no"),
         "--docs", str(docs)], capture_output=True, text=True, timeout=120,
    )
    assert missing.returncode != 0 and "run without --reuse" in missing.stderr


def test_csvs_written_before_the_position_error_column_still_read(tmp_path):
    from learner.report import _read_rows

    path = tmp_path / "experiment_full.csv"
    write_csv(_rows("full", {"tpsr": [400, 410]}, episodes=(2000,)), path)
    lines = path.read_text().splitlines()
    header = lines[0].split(",")
    column = header.index("position_error")
    old = [",".join(v for i, v in enumerate(line.split(",")) if i != column) for line in lines]
    path.write_text("\n".join(old) + "\n")
    rows = _read_rows(path)
    assert [r.score for r in rows] == [400.0, 410.0]
    assert all(np.isnan(r.position_error) for r in rows)
