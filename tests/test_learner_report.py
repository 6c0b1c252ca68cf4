"""learner report: floors beside the ceiling, verdicts by fixed rules, a page made of CSVs alone."""

from __future__ import annotations

import itertools
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from learner.appendix import SECTIONS
from learner.jobs import ENVIRONMENTS, Job
from learner.overrides import convert
from learner.results_page import HEADLINE, all_jobs
from learner.tables import Row, read_csv, summarise, write_csv
from learner.verdicts import BETTER, NOT_REPRODUCED, REPRODUCED, judge

REPOSITORY = Path(__file__).resolve().parents[1]


def _rows(environment, scores_by_method, episodes=(2000, 8000), **fields):
    """Rows with the given scores: ``{method: [score, ...]}`` at every data size."""
    rows = []
    for size in episodes:
        for method, scores in scores_by_method.items():
            for k, score in enumerate(scores):
                rows.append(
                    Row(environment, method, size, k, 1, 100, float(score), "", 0.0, 0.01, 0,
                        0.9, 0.9, "ok", **fields)
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


def _argument(job: Job, name: str, default: str = "") -> str:
    return job.argv[job.argv.index(name) + 1] if name in job.argv else default


def _fake_rows(job: Job, rng: np.random.Generator) -> list[Row]:
    """Rows shaped like those the job's command writes, with random scores."""
    environment = _argument(job, "--environment")
    sizes = (2000, 8000) if job.argv[0] == "experiment" and "--episodes" not in job.argv else (
        int(_argument(job, "--episodes")),
    )
    methods = ["constant", "random", "tpsr", "pca", "true-position"]
    if "--methods" in job.argv:
        start = job.argv.index("--methods") + 1
        methods = list(itertools.takewhile(lambda m: not m.startswith("--"), job.argv[start:]))
    extra = {"memory": 0.0, "memory_distance": 0.01} if "--memory" in job.argv else {}
    if job.argv[0] == "experiment":
        tune = {"tune": {"candidates": 24, "seconds": 50.0}} if "--tune" in job.argv else {}
        parameters = json.dumps({"tpsr": {"rank": 8}, **tune})
        scores = {m: rng.normal(400, 20, 3) for m in methods}
        return _rows(environment, scores, sizes, parameters=parameters, **extra)
    name, values = _argument(job, "--vary").split("=")
    group, field = name.split(".")
    rows = _rows(environment, {"constant": [0.0] * 3, "random": rng.normal(5, 5, 3)}, sizes)
    for value in values.split(","):
        parameters = json.dumps({group: {field: convert(name, value)}})
        learned = {m: rng.normal(420, 20, 3) for m in methods[:2] if m in ("tpsr", "pca")}
        default = ("tpsr", "pca") if group == "sim" else ("tpsr",)  # what learner study runs
        learned = learned or {m: rng.normal(420, 20, 3) for m in default}
        rows += _rows(environment, learned, sizes, parameters=parameters, criterion=0.3)
    return rows


@pytest.fixture()
def fake_results(tmp_path):
    rng = np.random.default_rng(3)
    results = tmp_path / "results"
    for job in all_jobs():
        path = job.path(results)
        path.parent.mkdir(parents=True, exist_ok=True)
        write_csv(_fake_rows(job, rng), path)
    return results


@pytest.mark.slow
def test_report_reuse_renders_every_job_and_is_reproducible(fake_results, tmp_path):
    docs = tmp_path / "docs"
    docs.mkdir()
    command = [sys.executable, "-m", "learner", "report", "--reuse", "--results",
               str(fake_results), "--docs", str(docs)]
    first = subprocess.run(command, capture_output=True, text=True, timeout=120)
    assert first.returncode == 0, first.stderr
    page = (docs / "results.md").read_text()
    figures = {env: (docs / f"results_{env}.png").read_bytes() for env in ENVIRONMENTS}
    second = subprocess.run(command, capture_output=True, text=True, timeout=120)
    assert second.returncode == 0, second.stderr
    assert (docs / "results.md").read_text() == page  # the CSVs alone decide the bytes
    assert {env: (docs / f"results_{env}.png").read_bytes() for env in ENVIRONMENTS} == figures
    for job in all_jobs():  # every table names the command that made it
        assert job.command in page, job.command
    for section in SECTIONS:
        assert f"### {section.title}" in page
    for env in ENVIRONMENTS:
        assert f"### `{env}`" in page and f"![{env}](results_{env}.png)" in page
    assert page.count("| random actions (floor) |") == len(ENVIRONMENTS) and "(ceiling)" in page
    assert "session" not in page.lower() and "issue" not in page.lower()


@pytest.mark.slow
def test_report_reuse_names_the_command_of_a_missing_csv(fake_results, tmp_path):
    missing = HEADLINE["guide"][1]
    missing.path(fake_results).unlink()
    docs = tmp_path / "docs"
    docs.mkdir()
    result = subprocess.run(
        [sys.executable, "-m", "learner", "report", "--reuse", "--results", str(fake_results),
         "--docs", str(docs)], capture_output=True, text=True, timeout=120,
    )
    assert result.returncode != 0 and missing.command in result.stderr
    assert result.stderr.count("\n") == 1  # one line, no traceback


@pytest.mark.slow
def test_the_committed_page_is_what_the_committed_csvs_give(tmp_path):
    """A fresh clone's ``learner report --reuse`` rewrites docs/results.md and the README's
    results table byte for byte."""
    docs = tmp_path / "docs"
    docs.mkdir()
    (tmp_path / "README.md").write_text(
        "before\n<!-- results: written by python -m learner report -->\nold\n"
        "<!-- end of results -->\nafter\n"
    )
    result = subprocess.run(
        [sys.executable, "-m", "learner", "report", "--reuse", "--results",
         str(REPOSITORY / "results"), "--docs", str(docs)],
        capture_output=True, text=True, timeout=300,
    )
    assert result.returncode == 0, result.stderr
    assert (docs / "results.md").read_text() == (REPOSITORY / "docs" / "results.md").read_text()
    block = (tmp_path / "README.md").read_text().split("\n")[1:-2]
    readme = (REPOSITORY / "README.md").read_text()
    assert "\n".join(block) in readme and "old" not in block and len(block) == 4 + len(ENVIRONMENTS)


def test_csvs_written_before_new_columns_still_read(tmp_path):
    path = tmp_path / "experiment_full.csv"
    write_csv(_rows("full", {"tpsr": [400, 410]}, episodes=(2000,)), path)
    lines = path.read_text().splitlines()
    header = lines[0].split(",")
    keep = [i for i, name in enumerate(header) if name not in ("position_error", "criterion")]
    old = [",".join(line.split(",")[i] for i in keep) for line in lines]
    path.write_text("\n".join(old) + "\n")
    rows = read_csv(path)
    assert [r.score for r in rows] == [400.0, 410.0]
    assert all(np.isnan(r.position_error) and np.isnan(r.criterion) for r in rows)
    path.write_text("environment,nonsense\nfull,1\n")
    with pytest.raises(Exception, match="unknown columns"):
        read_csv(path)
    shutil.rmtree(tmp_path)
