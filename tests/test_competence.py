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


@pytest.mark.slow
def test_a_room_change_scores_each_version_in_the_room_of_its_last_step(tmp_path, capsys):
    """With a new basis 300 steps after the one in use: the last version fits one."""
    argv = ["competence", "--environment", "full", "--steps", "600", "--warmup-steps", "300",
            "--refit-steps", "150", "--runs", "1", "--switch-to", "distractors",
            "--switch-at", "400", "--forgetting", "0.995", "--new-basis-steps", "300",
            "-o", str(tmp_path)]  # fmt: skip
    code, _, stderr = run_entry(argv, capsys)
    assert code == 0, stderr
    rows = read_csv(tmp_path / "switch_full_distractors_f0.995_b300.csv")
    parameters = [json.loads(r.parameters) for r in rows]
    assert [(r.episodes, p["room"]) for r, p in zip(rows, parameters, strict=True)] == [
        (300, "full"),
        (450, "distractors"),
        (600, "distractors"),
    ]
    assert {(p["forgetting"], p["switch_to"], p["switch_at"]) for p in parameters} == {
        (0.995, "distractors", 400)
    }
    assert [p["basis_steps"] for p in parameters] == [300, 0, 600]  # the first fit's, a new one
    assert rows[0].command.endswith(
        "--forgetting 0.995 --new-basis-steps 300 --switch-to distractors --switch-at 400"
    )


@pytest.mark.parametrize(
    ("options", "message"),
    [
        (["--switch-to", "distractors"], "go together"),
        (["--switch-to", "distractors", "--switch-at", "500"], "must lie between"),
        (["--switch-to", "moon", "--switch-at", "200"], "moon"),
        (["--switch-to", "drive", "--switch-at", "200"], "same robot"),
        (["--forgetting", "0"], "(0, 1]"),
        (["--new-basis-steps", "-1"], "0 or more"),
    ],
)
def test_learner_competence_refuses_a_room_change_it_cannot_make(
    tmp_path, capsys, options, message
):
    argv = ["competence", "--environment", "full", "--steps", "400", "--warmup-steps", "100",
            *options, "-o", str(tmp_path)]  # fmt: skip
    code, _, stderr = run_entry(argv, capsys)
    assert code != 0 and message in stderr, stderr
    assert not list(tmp_path.iterdir())
