"""learner view-study and view-figure: the predicted image against guesses without a state,
and one picture drawn from a view bag's messages."""

from __future__ import annotations

import csv

import pytest
from cli_support import run_entry
from test_filter_node import small  # noqa: F401  (the module fixture)

from learner.cli import main as learner_main
from learner.view_study import PREDICTORS, StudyConfig, score_run


def test_a_small_run_predicts_the_next_image_better_than_no_state():
    row = score_run(StudyConfig("full", training_steps=1500, held_out_steps=300, seed=1))
    assert row["held_out_pairs"] == 299
    assert row["predicted"] < row["action_blind"] < row["mean_image"]


def test_the_page_is_rendered_from_the_table_alone(tmp_path, capsys):
    rows = [
        {"environment": env, "seed": seed, **{n: 10.0 + i + seed for i, n in enumerate(PREDICTORS)}}
        for env in ("full", "drive") for seed in range(3)
    ]  # fmt: skip
    (tmp_path / "results").mkdir()
    with (tmp_path / "results" / "view_prediction.csv").open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    docs = tmp_path / "docs"
    args = ["view-study", "--reuse", str(tmp_path / "results"), "--docs", str(docs)]
    assert learner_main(args) == 0
    page = (docs / "view_prediction.md").read_text()
    assert "| full | 3 | 11.00 ± 0.58 (median 11.00) |" in page
    assert (docs / "view_prediction.png").stat().st_size > 0
    code, _, err = run_entry(["view-study", "--reuse", str(tmp_path), "--docs", str(docs)],
                             capsys)  # fmt: skip
    assert code == 1 and "does not exist" in err


def test_the_figure_is_drawn_from_a_view_bag(small, tmp_path, capsys):  # noqa: F811
    bag = tmp_path / "view"
    track = ["track", str(small["model"]), str(small["tmp"] / "feed"), "--mcap", str(bag),
             "--policy", str(small["policy"])]  # fmt: skip
    assert learner_main(track) == 0
    png = tmp_path / "view.png"
    capsys.readouterr()
    code, _, err = run_entry(["view-figure", str(bag), "-o", str(png), "--step", "5"], capsys)
    assert code == 0 and png.stat().st_size > 10_000 and "the step at 6 s" in err, err
    code, _, err = run_entry(["view-figure", str(bag), "-o", str(png)], capsys)
    assert code == 1 and "--force" in err
    feed = str(small["tmp"] / "feed")
    code, _, err = run_entry(["view-figure", feed, "-o", str(tmp_path / "x.png")], capsys)
    assert code == 1 and "has no view topics" in err


@pytest.mark.parametrize("argv", [["view-study"], ["view-study", "--output", "a", "--reuse", "b"]])
def test_view_study_wants_one_of_output_and_reuse(argv, capsys):
    code, _, err = run_entry(argv, capsys)
    assert code == 1 and "--output DIR" in err
