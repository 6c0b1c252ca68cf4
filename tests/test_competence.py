"""learner competence: the learner node's versions of an exploring run, scored; competence."""

from __future__ import annotations

import json
import math

import pytest
from cli_support import run_entry

from learner.competence_section import steps_to_competence
from learner.tables import Row, read_csv


def _row(run: int, steps: int, score: float) -> Row:
    return Row("full", "tpsr", steps, run, 31 + run, 0, score, "", 0.1, math.nan, 0,
               math.nan, math.nan, "ok")  # fmt: skip


def test_steps_to_competence_is_each_runs_first_version_at_the_threshold():
    rows = [
        _row(0, 1000, 100.0), _row(0, 2000, 430.0), _row(0, 3000, 300.0),  # reached, then lost
        _row(1, 1000, 425.0), _row(1, 2000, 470.0),
        _row(2, 1000, 10.0), _row(2, 2000, math.nan),  # never (a version without a policy)
    ]  # fmt: skip
    assert steps_to_competence(rows, 423.0) == [2000.0, 1000.0, math.inf]
    assert steps_to_competence(rows, 423.0, lasting=True) == [math.inf, 1000.0, math.inf]
    rows.append(_row(0, 4000, 450.0))  # run 0 regains it, and keeps it to its last version
    assert steps_to_competence(rows, 423.0, lasting=True) == [4000.0, 1000.0, math.inf]


@pytest.mark.slow
def test_learner_competence_scores_every_version_of_each_run(tmp_path, capsys):
    argv = ["competence", "--environment", "full", "--steps", "500", "--warmup-steps", "300",
            "--refit-steps", "200", "--runs", "2", "-o", str(tmp_path)]  # fmt: skip
    code, _, stderr = run_entry(argv, capsys)
    assert code == 0, stderr
    rows = read_csv(tmp_path / "competence_full.csv")
    assert [(r.repetition, r.episodes) for r in rows] == [
        (run, steps) for run in (0, 1) for steps in (300, 500)
    ]
    assert [r.train_seed for r in rows] == [31] * 2 + [32] * 2
    assert all(math.isfinite(r.score) and len(r.trial_rewards.split(";")) == 10 for r in rows)
    assert [json.loads(r.parameters)["version"] for r in rows[:2]] == [1, 2]
    assert rows[0].command == (
        "python -m learner competence --environment full --steps 500 --warmup-steps 300 "
        "--refit-steps 200 --runs 2"
    )
    code, _, stderr = run_entry(argv, capsys)  # the CSV exists: refused without --force
    assert code != 0 and "--force" in stderr


def test_learner_competence_refuses_an_unknown_environment(tmp_path, capsys):
    code, _, stderr = run_entry(
        ["competence", "--environment", "moon", "-o", str(tmp_path)], capsys
    )
    assert code != 0 and "moon" in stderr
    assert not list(tmp_path.iterdir())
