"""learner study: one experiment grid per value of a parameter, floors and ceiling once."""

from __future__ import annotations

import csv
import json

import pytest

from learner.cli import main
from learner.study import parse_values
from tpsr_ros.core.errors import ConfigError

GRID = ["--environment", "full", "--episodes", "300", "--repetitions", "1",
        "--rl-steps", "1000", "--workers", "1"]


@pytest.mark.slow
def test_study_runs_every_value_with_the_same_seeds_as_experiment(tmp_path, capsys):
    out = tmp_path / "results"
    assert main(["study", *GRID, "--vary", "pca.dim=2,3", "-o", str(out)]) == 0
    with (out / "study_full_pca_dim.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    assert [r["method"] for r in rows[:3]] == ["constant", "random", "true-position"]
    studied = [(json.loads(r["parameters"])["pca"]["dim"], r["repetition"], r["score"])
               for r in rows[3:]]
    assert [(d, k) for d, k, _ in studied] == [(2, "0"), (3, "0")]
    assert (out / "study_full_pca_dim.png").stat().st_size > 10_000
    printed = capsys.readouterr().out
    assert "pca.dim" in printed and printed.count(" pca ") == 2  # one line per value

    # the study's runs at dim 3 are exactly those of `experiment --set pca.dim=3`
    exp = tmp_path / "experiment"
    assert main(["experiment", *GRID, "--methods", "pca", "--set", "pca.dim=3",
                 "-o", str(exp)]) == 0
    with (exp / "experiment_full.csv").open() as handle:
        alone = [(3, r["repetition"], r["score"]) for r in csv.DictReader(handle)]
    assert alone == studied[1:]


@pytest.mark.slow
def test_fitted_q_parameters_move_the_ceiling_too(tmp_path):
    out = tmp_path / "results"
    args = ["study", *GRID, "--vary", "fqi.centers=20,40", "-o", str(out)]
    assert main(args) == 0
    with (out / "study_full_fqi_centers.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    assert [r["method"] for r in rows] == [
        "constant", "random", "tpsr", "true-position", "tpsr", "true-position"
    ]
    assert [json.loads(r["parameters"])["fqi"]["centers"] for r in rows[2:]] == [20, 20, 40, 40]


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("pca.dim=2", "two or more distinct values"),
        ("pca.dim=2,2", "two or more distinct values"),
        ("pca.dim=2,,3", "two or more distinct values"),
        ("rnak=2,3", "unknown --set name 'rnak'"),
    ],
)
def test_bad_values_are_refused(text, message):
    with pytest.raises(ConfigError, match=message):
        parse_values(text)


def test_a_bad_value_is_refused_before_any_run(tmp_path, capsys):
    out = tmp_path / "results"
    with pytest.raises(ConfigError, match=r"pca\.dim=0: PCA dim must be a positive integer"):
        main(["study", *GRID, "--vary", "pca.dim=2,0", "-o", str(out)])
    assert "run/s" not in capsys.readouterr().err  # refused before the first grid started
    assert not (out / "study_full_pca_dim.csv").exists()
