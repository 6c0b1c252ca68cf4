"""learner report: floors beside the ceiling, verdicts by fixed rules, a page made of CSVs alone."""

from __future__ import annotations

import dataclasses
import itertools
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from learner.appendix import SECTIONS
from learner.jobs import ENVIRONMENTS, GUIDE_ENVIRONMENTS, Job
from learner.overrides import convert
from learner.results_page import HEADLINE, README_SUMMARY_BEGIN, README_SUMMARY_END, all_jobs
from learner.tables import Row, pooled_floors, read_csv, summarise, write_csv
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
    if job.argv[0] == "competence" and "--switch-to" in job.argv:  # each in its room
        switch_at, room = int(_argument(job, "--switch-at")), _argument(job, "--switch-to")
        return [
            row
            for steps in range(1000, 12001, 1000)
            for row in _rows(environment, {"tpsr": rng.normal(420, 30, 3)}, [steps],
                             parameters=json.dumps({"room": environment if steps <= switch_at
                                                    else room}))  # fmt: skip
        ]
    if job.argv[0] == "competence":  # versions every 1000 live steps, three runs
        return _rows(environment, {"tpsr": rng.normal(420, 30, 3)}, range(1000, 12001, 1000))
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


def test_every_job_is_a_command_the_cli_takes_with_the_data_it_ran_on():
    """The page's commands parse as they are written; the grids record 3 steps per training
    episode but for the studies of longer windows, which say ``--episode-steps window``."""
    from learner.cli import build_parser

    windows = set()
    for job in all_jobs():
        args = build_parser().parse_args(job.argv_for(Path("results"), 1))
        if job.argv[0] in ("experiment", "study"):
            assert args.episode_steps == (None if "--episode-steps" in job.argv else 3), job
            if args.episode_steps is None:
                windows.add(job.option("--vary"))
    assert windows == {
        "tpsr.history_length=1,2,3", "tpsr.test_length=1,2", "tpsr.refine_window=16,32",
        "tpsr.action_pooling=0,0.5,1", "tpsr.refine_carry=0.3,0",
    }


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
    link = "- [docs/results.md](docs/results.md): "
    (tmp_path / "README.md").write_text(
        "before\n<!-- results: written by python -m learner report -->\nold\n"
        f"<!-- end of results -->\n{link}{README_SUMMARY_BEGIN}old{README_SUMMARY_END}.\n"
    )
    result = subprocess.run(
        [sys.executable, "-m", "learner", "report", "--reuse", "--results",
         str(REPOSITORY / "results"), "--docs", str(docs)],
        capture_output=True, text=True, timeout=300,
    )
    assert result.returncode == 0, result.stderr
    assert (docs / "results.md").read_text() == (REPOSITORY / "docs" / "results.md").read_text()
    written = (tmp_path / "README.md").read_text().split("\n")
    block, line = written[1:-2], written[-2]
    readme = (REPOSITORY / "README.md").read_text()
    assert "\n".join(block) in readme and "old" not in block and len(block) == 4 + len(ENVIRONMENTS)
    assert line.startswith(link) and "old" not in line and line in readme.splitlines()


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


def _sized(environment, scores_by_cell):
    """Rows with the given scores per cell: ``{(method, episodes): [score, ...]}``."""
    return [
        Row(environment, method, size, k, 1, 100, float(score), "", 0.0, 0.01, 0, 0.9, 0.9, "ok")
        for (method, size), scores in scores_by_cell.items()
        for k, score in enumerate(scores)
    ]


def _spread(centre, half=1.0, runs=10):
    """``runs`` scores evenly spread around ``centre`` (mean = median = centre)."""
    return list(np.linspace(centre - half, centre + half, runs))


def _floors_and_ceiling(sizes, random=(-3.0, 40.0)):
    """A constant floor at 0, a random floor centred on ``random[k]`` at size ``k``, a ceiling."""
    cells = {}
    for size, centre in zip(sizes, itertools.cycle(random)):
        cells[("constant", size)] = [0.0] * 10
        cells[("random", size)] = _spread(centre, 10.0)
        cells[("true-position", size)] = [470.0] * 10
    return cells


def _verdict(environment, cells, claim_start):
    tables = {environment: summarise(_sized(environment, cells))}
    found = [(m, v) for f, m, v in judge(tables) if f.claim.startswith(claim_start)]
    assert len(found) == 1, claim_start
    return found[0][1]


def test_the_floors_are_pooled_over_every_data_size():
    sizes = (2000, 4000)
    rows = _sized("full", {**_floors_and_ceiling(sizes), ("tpsr", 2000): _spread(100.0, 5.0)})
    floors = pooled_floors(rows)
    random_scores = [r.score for r in rows if r.method == "random"]
    assert floors["random"]["runs"] == 20 and floors["random"]["sizes"] == 2
    assert floors["random"]["mean"] == pytest.approx(np.mean(random_scores))  # 18.5, not 40
    assert floors["random"]["median"] == pytest.approx(np.median(random_scores))
    assert floors["random"]["sem"] == pytest.approx(np.std(random_scores, ddof=1) / np.sqrt(20))
    tpsr = next(t for t in summarise(rows) if t["method"] == "tpsr")
    assert tpsr["floor"] == "random"  # pooled, though no random run shares its data size
    expected = (tpsr["mean"] - floors["random"]["mean"]) / np.hypot(
        tpsr["sem"], floors["random"]["sem"]
    )
    assert tpsr["margin_sem"] == pytest.approx(expected)


def test_a_tpsr_above_pca_somewhere_is_not_slightly_below_it():
    sizes = (2000, 4000)
    base = _floors_and_ceiling(sizes)
    claim = "TPSR: works, slightly below PCA"
    pca = {("pca", n): _spread(460.0) for n in sizes}
    # level at 2000, above by far more than 2 SEMs at 4000: better, not "slightly below"
    above = {("tpsr", 2000): _spread(460.0), ("tpsr", 4000): _spread(465.0)}
    assert _verdict("full", {**base, **pca, **above}, claim) == BETTER
    # above at one size, below at the other: neither
    mixed = {("tpsr", 2000): _spread(440.0), ("tpsr", 4000): _spread(465.0)}
    assert _verdict("full", {**base, **pca, **mixed}, claim) == NOT_REPRODUCED
    # slightly below (within 10 %) everywhere: the guide's finding
    below = {("tpsr", 2000): _spread(440.0), ("tpsr", 4000): _spread(455.0)}
    assert _verdict("full", {**base, **pca, **below}, claim) == REPRODUCED


def test_about_300_must_hold_at_every_data_size():
    sizes = (2000, 4000, 8000)
    base = {**_floors_and_ceiling(sizes), **{("pca", n): _spread(5.0) for n in sizes}}
    claim = "TPSR: mean about 300"

    def tpsr(*scores):
        return {("tpsr", n): s for n, s in zip(sizes, scores, strict=True)}

    skewed = [200.0] * 3 + [340.0] * 7  # mean 298, median 340: about 300, medians above
    assert _verdict("distractors", {**base, **tpsr(skewed, skewed, skewed)}, claim) == REPRODUCED
    # one data size far below 300 (mean 186): not reproduced, whatever the others score
    low = _spread(186.0, 20.0)
    high = _spread(420.0, 20.0)
    assert _verdict("distractors", {**base, **tpsr(low, high, high)}, claim) == NOT_REPRODUCED
    # means and medians above 350 everywhere: better, even with medians below the means
    heavy = [470.0] * 2 + [400.0] * 8  # mean 414, median 400
    assert _verdict("distractors", {**base, **tpsr(heavy, high, heavy)}, claim) == BETTER
    # about 300 with medians below the means: the "medians above" half fails
    dented = [420.0] * 3 + [250.0] * 7  # mean 301, median 250
    assert _verdict("distractors", {**base, **tpsr(dented, skewed, skewed)}, claim) == (
        NOT_REPRODUCED
    )


def test_close_to_the_maximum_needs_a_low_sem_and_near_zero_a_low_median():
    sizes = (2000, 6000, 8000)
    base = _floors_and_ceiling(sizes)
    claim = "5-dim TPSR with many centres"
    steady = {("tpsr", n): _spread(460.0, 5.0) for n in sizes}
    assert _verdict("full", {**base, **steady}, claim) == REPRODUCED
    # mean at 96 % of the ceiling, but one run of ten fails: SEM ~ 45 > 5 % of 470
    shaky = {**steady, ("tpsr", 8000): [0.0] + [500.0] * 9}
    assert _verdict("full", {**base, **shaky}, claim) == NOT_REPRODUCED
    claim = "PCA: mean slightly above zero"
    near_zero = {("pca", n): [-40.0] * 5 + [60.0] * 5 for n in sizes}  # mean 10, median 10
    assert _verdict("partial", {**base, **near_zero}, claim) == REPRODUCED
    # mean 94 (20 % of the ceiling) but the median run scores 460: PCA does not fail
    bimodal = {("pca", n): [-300.0] * 4 + [460.0] * 6 for n in sizes}
    assert _verdict("partial", {**base, **bimodal}, claim) == NOT_REPRODUCED


def test_what_works_says_above_the_floors_and_beats_the_baseline_apart():
    from learner.results_page import _environment_summary

    sizes = (2000, 8000)
    rows = _sized(
        "partial",
        {
            **_floors_and_ceiling(sizes),
            **{("pca", n): _spread(460.0) for n in sizes},
            ("tpsr", 2000): _spread(300.0, 20.0),
            ("tpsr", 8000): _spread(459.5),
        },
    )
    table = summarise(rows)
    text = _environment_summary("partial", table, table, pooled_floors(rows))
    (floors_line,) = [line for line in text.splitlines() if "*Above the floors*" in line]
    (baseline_line,) = [line for line in text.splitlines() if "*Beats the baseline*" in line]
    assert "at every data size (2 of 2)" in floors_line and "PCA" not in floors_line
    random = pooled_floors(rows)["random"]
    assert f"{random['mean']:.1f} / {random['median']:.1f} / {random['sem']:.1f}" in floors_line
    assert f"over its {random['runs']} runs" in floors_line
    assert "PCA" in baseline_line and "at no data size" in baseline_line
    assert "level with it at 1 and below it at 1 of 2" in baseline_line


def test_the_headline_shows_each_floor_once_pooled():
    from learner.results_page import _floor_table, _headline_table

    sizes = (2000, 8000)
    tpsr = {("tpsr", n): [400.0] * 3 for n in sizes}
    rows = _sized("full", {**_floors_and_ceiling(sizes), **tpsr})
    tables = {arm: summarise(rows) for arm in HEADLINE}
    jobs = {arm: jobs[0] for arm, jobs in HEADLINE.items()}
    assert not any("(floor)" in line for line in _headline_table("full", tables, jobs))
    lines = _floor_table(pooled_floors(rows), jobs["defaults"])
    (random,) = [line for line in lines if line.startswith("| random actions (floor) |")]
    pooled = pooled_floors(rows)["random"]
    assert f"| 20 (2 data sizes) | {pooled['mean']:.1f} / {pooled['median']:.1f} / " in random


def _headline_data():
    rng = np.random.default_rng(5)
    return {job: _fake_rows(job, rng) for arm in HEADLINE.values() for job in arm}


def test_the_readme_says_what_the_page_says(tmp_path):
    from learner.results_page import readme_summary, write_readme_table

    data = _headline_data()
    tables = {
        arm: {env: summarise(data[job]) for env, job in zip(ENVIRONMENTS, jobs, strict=True)}
        for arm, jobs in HEADLINE.items()
    }
    summary = readme_summary(data)
    for arm, words in (("guide", "with its own settings"), ("defaults", "with the defaults")):
        verdicts = [v for f, _, v in judge(tables[arm]) if f.environment in GUIDE_ENVIRONMENTS]
        counts = (
            f"{words} {verdicts.count(REPRODUCED)} reproduce"
            + ("s" if verdicts.count(REPRODUCED) == 1 else "")
            + f", {verdicts.count(BETTER)} "
        )
        assert counts in summary, (counts, summary)
        assert f"and {verdicts.count(NOT_REPRODUCED)} do" in summary.split(words)[1]
    assert f"Of the guide's {len(verdicts)} findings" in summary
    readme = tmp_path / "README.md"
    readme.write_text(
        "<!-- results: written by python -m learner report -->\n<!-- end of results -->\n"
        f"- [docs/results.md](docs/results.md): {README_SUMMARY_BEGIN}old{README_SUMMARY_END}.\n"
    )
    write_readme_table(data, readme)
    line = readme.read_text().splitlines()[-1]
    assert line == (
        f"- [docs/results.md](docs/results.md): {README_SUMMARY_BEGIN}{summary}"
        f"{README_SUMMARY_END}."
    )
    readme.write_text("<!-- results: written by python -m learner report -->\n"
                      "<!-- end of results -->\n")
    with pytest.raises(Exception, match="summary"):
        write_readme_table(data, readme)


def test_the_committed_readme_link_line_is_written_by_the_report():
    readme = (REPOSITORY / "README.md").read_text()
    (line,) = [x for x in readme.splitlines() if x.startswith("- [docs/results.md]")]
    assert README_SUMMARY_BEGIN in line and README_SUMMARY_END in line
    assert "reproduced and beaten" not in readme


def test_the_demo_names_its_floors_protocol():
    from learner.demo import Bounds, bounds_line
    from learner.evaluate import Evaluation, Trial
    from learner.floors import DEMO_POLICY_SEED, ConstantFloor

    evaluation = Evaluation((Trial((5.0, 5.0), 0.0, None, 0),))
    line = bounds_line(Bounds(ConstantFloor(0, evaluation, (0.0, 0.0)), 38.1, 469.8))
    assert "one run each" in line and f"policy seed {DEMO_POLICY_SEED}" in line
    assert "random actions 38.1" in line and "true position 469.8" in line


def test_the_trials_that_earned_nothing_are_told_where_they_ended():
    """Two runs: one trial stuck 5 m outside the goal zone at the east wall, one stuck
    10 m outside and 5 m from it, one that moved to the end and one that earned something."""
    from learner.predictive_section import failed_trials

    corner = 45.0
    stuck_5 = f"{corner - 1:.2f},{corner - np.sqrt(20.0**2 - 1):.2f},30"  # 20 m from the corner
    stuck_10 = f"{corner - 5:.2f},{corner - np.sqrt(25.0**2 - 25):.2f},50"  # 25 m
    moving, good = "10.00,10.00,0", "44.00,44.00,40"
    first = Row("partial-strip", "tpsr", 8000, 0, 1, 100, 0.0, ";".join(["0"] + ["470"] * 9),
                0.0, 0.01, 0, 0.9, 0.9, "ok", trial_ends=";".join([stuck_5] + [good] * 9))
    second = Row("partial-strip", "tpsr", 8000, 1, 1, 100, 0.0,
                 ";".join(["-3", "0"] + ["470"] * 8), 0.0, 0.01, 0, 0.9, 0.9, "ok",
                 trial_ends=";".join([stuck_10, moving] + [good] * 8))  # fmt: skip
    text = failed_trials([first, second], "partial-strip")
    assert text.startswith("3 of its 20 trials earned nothing; 2 of those did not leave")
    assert "a median 7.5 m outside the goal zone's edge (from 5.0 to 10.0 m;" in text
    assert "a median 3.0 m from the east wall" in text
    # rows written before trials' ends were recorded say nothing
    assert failed_trials([dataclasses.replace(first, trial_ends="")], "partial-strip") is None


def test_the_weakest_run_is_told_how_it_fared_at_the_goal_zone():
    """Three runs: the weakest reaches the goal zone in every trial but is blocked often;
    the others reach it in 19 trials of 20 and are blocked less."""
    from learner.predictive_section import weakest_at_goal

    def run(score: float, goals: list[str]) -> Row:
        return Row("partial-strip", "tpsr", 8000, 0, 1, 100, score, "", 0.0, 0.01, 0, 0.9,
                   0.9, "ok", trial_goal=";".join(goals))  # fmt: skip

    weakest = run(271.7, ["9,13"] * 5 + ["11,15"] * 5)
    others = [run(400.0, ["8,1"] * 9 + ["0,4"]), run(430.0, ["10,2"] * 10)]
    text = weakest_at_goal([others[0], weakest, others[1]], "partial-strip")
    assert text == (
        "in its weakest run (271.7) 10 of 10 trials reached the goal zone (at a median step "
        "10) and a wall blocked a median 14 of a trial's 50 steps; in the other runs 19 of 20 "
        "trials reached it (at a median step 10) and a wall blocked a median 2 (a blocked "
        "step earns -1, a free step in the zone 10; `learner evaluate` prints each trial's)"
    )
    # rows written before the goal zone was recorded, or a single run, say nothing
    assert weakest_at_goal([dataclasses.replace(weakest, trial_goal=""), *others], "full") is None
    assert weakest_at_goal([weakest], "partial-strip") is None


def test_runs_whose_fitted_q_needed_a_larger_ridge_are_named():
    from learner.predictive_section import raised_ridge

    rows = [Row("partial-strip", "tpsr", 8000, k, 1, 100, score, "", 0.0, ridge, 0, 0.9, 0.9,
                "ok") for k, (score, ridge) in enumerate([(5.6, 0.1), (400.0, 0.01),
                                                          (300.0, 1.0), (420.0, 0.01)])]
    assert raised_ridge(rows) == (
        "in 2 of 4 runs the fitted Q diverged at ridge 0.01 and was refitted at a larger "
        "ridge; they score 152.8 on average (lowest 5.6), the other runs 410.0"
    )
    alone = json.dumps({"fqi": {"ridge": 0.01, "refit": "member"}})
    members = [dataclasses.replace(r, parameters=alone) for r in rows]
    assert raised_ridge(members).startswith(
        "in 2 of 4 runs a member of the fitted Q diverged at ridge 0.01 and was refitted "
        "alone at a larger ridge; they score 152.8"
    )
    assert raised_ridge([r for r in rows if r.fqi_ridge == 0.01]) is None


def test_the_loop_position_error_is_told_beside_the_rl_runs_with_the_weakest_run():
    from learner.predictive_section import loop_grip

    rows = [Row("partial-strip", "tpsr", 8000, k, 1, 100, score, "", 0.0, 0.01, 0, 0.9, 0.9,
                "ok", position_error=rl, loop_position_error=loop)
            for k, (score, rl, loop) in enumerate([(400.0, 2.0, 2.5), (20.0, 2.2, 16.9),
                                                   (430.0, 2.4, 3.0)])]  # fmt: skip
    assert loop_grip(rows) == (
        "its states locate the robot to a median 2.20 m on the random RL run and 3.00 m in "
        "the scored trials (the states its policy acted on, among the RL run's); in its "
        "weakest run (20.0) 2.20 m and 16.90 m; 1 of 3 runs place it more than 2 times as "
        "far off in the trials as on the RL run (under the policy's own actions, such as "
        "standing for many steps, which random actions rarely do, their states no longer say "
        "where the robot is), scoring 20.0 on average against the others' 415.0"
    )
    assert loop_grip(rows[:1]).endswith("no run places it more than 2 times as far off in "
                                        "the trials as on the RL run")  # fmt: skip
    # rows written before the loop's error was recorded say nothing
    unrecorded = [dataclasses.replace(r, loop_position_error=float("nan")) for r in rows]
    assert loop_grip(unrecorded) is None


def test_the_fit_lottery_is_measured_on_the_same_data_across_the_fits_own_seeds():
    """Two runs (repetitions) fitted at seeds 0 and 1: one moves from 300 to 420 (fails,
    then succeeds), one from 400 to 410; the range, the flip and the variance split."""
    from learner.appendix import fit_lottery

    def row(repetition: int, seed: int, score: float) -> Row:
        return Row("partial-strip", "tpsr", 8000, repetition, 1, 100, score, "", 0.0, 0.01, 0,
                   0.9, 0.9, "ok", parameters=json.dumps({"tpsr": {"seed": seed}}))  # fmt: skip

    rows = [row(0, 0, 300.0), row(0, 1, 420.0), row(1, 0, 400.0), row(1, 1, 410.0)]
    within = (np.var([300.0, 420.0], ddof=1) + np.var([400.0, 410.0], ddof=1)) / 2
    between = np.var([360.0, 405.0], ddof=1)
    text = fit_lottery(rows, "seed")
    assert text.startswith(
        "the same training data, fitted with another `seed`, scores a range of 65.0 (median "
        "over 2 runs of 2 values each; largest 120.0); 1 of the 2 score below 350 with some "
        "value, 1 of those 400 or more with another; the fit's own seed accounts for "
        f"{100 * within / (within + between):.0f} % of the runs' score variance"
    )
    assert fit_lottery(rows[::2], "seed") is None  # one value per run: nothing to compare


def test_pca_is_planned_with_its_own_planner_where_one_image_is_ambiguous():
    from learner.predictive_section import PCA_PLANNER, PCA_PLANNER_ENVIRONMENTS

    page = (REPOSITORY / "docs" / "results.md").read_text()
    for env in ("full", "partial", "distractors", "partial-strip", "drive"):
        row = f"| `{env}` | PCA, its own planner | "
        assert (row in page) == (env in PCA_PLANNER_ENVIRONMENTS), env
    for env in PCA_PLANNER_ENVIRONMENTS:
        settings = " ".join(f"--set {s}" for s in PCA_PLANNER)
        assert f"--environment {env} --episodes 8000 --preset best --methods pca {settings}" in page
        rows = read_csv(REPOSITORY / "results" / "pca_planner" / f"experiment_{env}.csv")
        planners = [json.loads(r.parameters)["fqi"] for r in rows if r.method == "pca"]
        assert len(planners) == 10
        for setting in PCA_PLANNER:  # every run recorded the planner the page names
            name, value = setting.removeprefix("fqi.").split("=")
            assert {str(p[name]) for p in planners} == {value}


def test_a_study_shows_the_headings_r2_and_each_environments_own_default():
    from learner.appendix import CARRY_STUDY

    def rows(job, heading, memory=float("nan"), paths=float("nan")):
        out = _rows(job.environment, {"constant": [0.0] * 3, "random": [1.0, 2.0, 3.0]},
                    (8000,))  # fmt: skip
        for value in ("0", "0.3", "0.5", "0.7"):
            parameters = json.dumps({"tpsr": {"refine_carry": float(value)}})
            out += _rows(job.environment, {"tpsr": [400.0, 410.0, 420.0]}, (8000,),
                         parameters=parameters, r2_heading=heading, memory=memory,
                         memory_paths=paths)  # fmt: skip
        return out

    headings = {"partial-strip": float("nan"), "drive": 0.8}
    data = {job: rows(job, headings[job.environment]) for job in CARRY_STUDY.jobs}
    text = "\n".join(CARRY_STUDY.render(CARRY_STUDY, data))
    assert "the default's value is `0.3` in `partial-strip` and `0` in `drive`" in text
    assert "in brackets of the heading's unit vector" in text
    assert "| `drive` (8000) | `0` | tpsr | 410.0 / 410.0 / 5.8 | 0.90 / 0.90 (0.80) |" in text
    assert "| `partial-strip` (8000) | `0.3` | tpsr | 410.0 / 410.0 / 5.8 | 0.90 / 0.90 |" in text
    assert "| `drive` (8000) | `0.3` | tpsr |" in text
    no_heading = {job: rows(job, float("nan")) for job in CARRY_STUDY.jobs}
    plain = "\n".join(CARRY_STUDY.render(CARRY_STUDY, no_heading))
    assert "heading" not in plain and "learner memory" not in plain
    remembered = {job: rows(job, float("nan"), memory=2.0) for job in CARRY_STUDY.jobs}
    assert (
        "- `drive`, tpsr: `learner memory`, the median over the runs in steps: `0` 2, `0.3` 2, "
        "`0.5` 2, `0.7` 2." in CARRY_STUDY.render(CARRY_STUDY, remembered)
    )
    both = {job: rows(job, float("nan"), memory=0.0, paths=3.0) for job in CARRY_STUDY.jobs}
    assert (
        "- `drive`, tpsr: `learner memory`, the median over the runs in steps: `0` 0, `0.3` 0, "
        "`0.5` 0, `0.7` 0 (the paths variant alone: `0` 3, `0.3` 3, `0.5` 3, `0.7` 3)."
        in CARRY_STUDY.render(CARRY_STUDY, both)
    )


def test_a_study_run_before_its_preset_changed_says_in_what():
    from learner.appendix import PCA_PLANNER_STUDY, REFIT_STUDY

    def rows(job, tpsr, fqi):
        out = []
        for value in ("ensemble", "member"):
            parameters = json.dumps({"tpsr": tpsr, "fqi": {**fqi, "refit": value}})
            out += _rows(job.environment, {"tpsr": [400.0, 410.0, 420.0]}, (8000,),
                         parameters=parameters)  # fmt: skip
        return out

    # as the preset is now (a setting the rows do not record keeps the preset's value)
    current = {job: rows(job, {}, {}) for job in REFIT_STUDY.jobs}
    assert "predate" not in "\n".join(REFIT_STUDY.render(REFIT_STUDY, current))
    before = {job: rows(job, {"refine_horizon": 20, "overlapping_episodes": False},
                        {"centers": 50})
              for job in REFIT_STUDY.jobs}  # fmt: skip
    text = "\n".join(REFIT_STUDY.render(REFIT_STUDY, before))
    assert (
        "The runs predate the preset's current value of a setting they record: `fqi.centers` "
        "`50` (now `100`); `tpsr.refine_horizon` `20` (now `10`)." in text
    )
    # the varied setting and those the study's command sets are not departures (the page
    # names the latter with the command); nor are the settings of a baseline's rows
    assert (
        "its command sets (`tpsr.refine_carry_rule=always`, `tpsr.history_length=1`, "
        "`tpsr.overlapping_episodes=false`, `tpsr.obs_effective_centres=0` in `drive`)" in text
    )
    ranks = {job: rows(job, {"rank": 12}, {}) for job in REFIT_STUDY.jobs}  # 8 and 16 now
    assert "`tpsr.rank` `12` (now `8` in `partial-strip` and `16` in `drive`)" in "\n".join(
        REFIT_STUDY.render(REFIT_STUDY, ranks)
    )
    planner = {job: _rows(job.environment, {"pca": [300.0, 310.0, 320.0]}, (8000,),
                          parameters=json.dumps({"fqi": {"ensemble": 1}}))
               for job in PCA_PLANNER_STUDY.jobs}  # fmt: skip
    assert "predate" not in "\n".join(PCA_PLANNER_STUDY.render(PCA_PLANNER_STUDY, planner))


def test_the_memory_cells_give_the_paths_variant_alone_where_the_runs_recorded_it():
    from learner.predictive_section import PREDICTIVE_EPISODES, _memory, tpsr_job
    from learner.results_page import _memory_bullet

    sizes = (PREDICTIVE_EPISODES,)
    older = _rows("partial-strip", {"tpsr": [400.0] * 3}, sizes, memory=0.0)
    recorded = [
        dataclasses.replace(row, memory_paths=paths)
        for row, paths in zip(older, (1.0, 2.0, 4.0), strict=True)
    ]
    assert _memory(older, "tpsr") == "0"
    assert _memory(recorded, "tpsr") == "0 (paths 2)"
    assert _memory(recorded, "pca") == "-"
    job = tpsr_job("partial-strip")
    assert "--environment partial-strip" in job.command and "--memory" in job.command
    assert "paths variant" not in _memory_bullet({job: older})
    assert _memory_bullet({job: recorded}).endswith(
        "With the defaults in `partial-strip` (the predictive section) `learner memory`'s "
        "paths variant alone keeps them apart for a median 2 step(s); in its stand-still "
        "variant, whose two runs differ in one action only, they merge at once, and from "
        "that uninformed start an exact belief over the robot's position stays under the "
        "threshold there too (appendix, Memory)."
    )


def test_the_predictive_section_gives_the_headings_r2_of_a_robot_that_turns():
    from learner.predictive_section import PREDICTIVE_EPISODES, _heading

    turning = _rows("drive", {"tpsr": [1.0, 2.0, 3.0]}, (PREDICTIVE_EPISODES,))
    headings = (0.9, 0.6, 0.9)
    turning = [dataclasses.replace(r, r2_heading=h) for r, h in zip(turning, headings, strict=True)]
    assert _heading(turning) == (
        "the affine R² of the heading (its unit vector) from the states is 0.80 on average, "
        "0.60 in the lowest of 3 runs"
    )
    assert _heading(_rows("partial", {"tpsr": [1.0, 2.0]}, (PREDICTIVE_EPISODES,))) is None


def test_the_rl_trajectory_section_sets_one_trajectory_beside_one_per_run():
    """Each arm's runs with one RL trajectory beside those with their own; the TPSR judged
    against every baseline on the latter."""
    from learner.rl_trajectory_section import RL_ENVIRONMENTS, RL_TRAJECTORY_SECTION, _arms

    alternating = [1.0, -1.0] * 5  # +-10 around a mean: SEM sqrt(1000 / 9) / sqrt(10) = 3.33
    own_scores = {"tpsr": 400.0, "pca": 300.0, "stacked-pca": 395.0, "window": 200.0,
                  "constant": 0.0, "random": 5.0, "true-position": 470.0}  # fmt: skip
    shifts = {"tpsr": 20.0, "pca": 30.0, "stacked-pca": -10.0, "window": 50.0}  # one trajectory
    data = {}
    for env in RL_ENVIRONMENTS:
        for arm, (fixed, own) in _arms(env).items():
            after = own.argv[own.argv.index("--methods") + 1 :]
            methods = list(itertools.takewhile(lambda arg: not arg.startswith("--"), after))
            data[own] = _rows(env, {m: [own_scores[m] + 10 * a for a in alternating]
                                    for m in methods}, episodes=(8000,))  # fmt: skip
            data[fixed] = _rows(env, {m: [own_scores[m] + shifts.get(m, 0.0)] * 10
                                      for m in methods}, episodes=(2000, 8000))  # fmt: skip
    lines = RL_TRAJECTORY_SECTION.render(RL_TRAJECTORY_SECTION, data)
    assert (
        "| `partial-strip` | TPSR | the defaults' | 420.0 / 420.0 / 0.0 (420.0) | "
        "400.0 / 400.0 / 3.3 (390.0) | -20.0 |"
    ) in lines
    verdict = next(line for line in lines if line.startswith("- `drive`"))
    assert verdict.startswith(
        "- `drive`, each run with its own RL trajectory: the TPSR scores 400.0 (SEM 3.3), "
        "+100.0 (+21.2 SEM, outside the noise) against PCA with the defaults' planner;"
    )
    assert "+5.0 (+1.1 SEM, within the noise) against stacked-frame PCA;" in verdict
    assert verdict.endswith(
        "+200.0 (+42.4 SEM, outside the noise) against the finite-window predictive state. "
        "Against one RL trajectory for every run the TPSR's mean moved by -20.0, the "
        "baselines' by -50.0 to +10.0."
    )
