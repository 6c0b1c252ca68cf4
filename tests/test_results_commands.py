"""The committed results name what they ran: every row's command gives the settings the row
recorded, and every job on the page gives the commands of its CSV's rows, although the
presets have changed since many of them ran. (Settings only: a row recorded before a change
of the code that no setting names can rerun to other figures; the page says where.)"""

from __future__ import annotations

import csv
import dataclasses
import json
import shlex
from functools import cache
from pathlib import Path

import pytest

from learner.cli import build_parser
from learner.experiment import ExperimentConfig, config_from_args
from learner.floors import FLOORS
from learner.results_page import all_jobs
from learner.study import parse_values
from tpsr_ros.core.fqi import FQIConfig
from tpsr_ros.core.tpsr import TPSRConfig
from tpsr_ros.core.tpsr_config import chosen_by_the_fit

REPOSITORY = Path(__file__).resolve().parents[1]
EXPERIMENT = "python -m learner experiment "
NEWER_FIELDS = {"tpsr": TPSRConfig(), "fqi": FQIConfig()}
"""A setting a row does not record is newer than the row: the field's default, which is the
behaviour before the field existed, is what the row ran with."""


@cache
def _parser():
    return build_parser("experiment")


@cache
def _config(command: str) -> ExperimentConfig:
    """The configuration a row's ``learner experiment`` command runs (methods aside)."""
    args = _parser().parse_args(shlex.split(command.removeprefix("python -m learner ")))
    return dataclasses.replace(config_from_args(args, (), args.assignments), methods=())


def _same(ran, recorded) -> bool:
    """Equal settings; a recorded int and a configured float (or back) of one value too."""
    if isinstance(ran, bool) or isinstance(recorded, bool):
        return ran == recorded
    if isinstance(ran, int | float) and isinstance(recorded, int | float):
        return float(ran) == float(recorded)
    return ran == recorded


def _committed_rows() -> list[tuple[str, dict[str, str]]]:
    rows = []
    for path in sorted((REPOSITORY / "results").rglob("*.csv")):
        with path.open(newline="") as f:
            for row in csv.DictReader(f):
                if row.get("command", "").startswith(EXPERIMENT):
                    rows.append((str(path.relative_to(REPOSITORY)), row))
    return rows


def test_every_committed_row_reruns_with_the_settings_it_recorded():
    rows = _committed_rows()
    assert len(rows) > 5000  # every results directory was read
    checked, wrong = 0, []
    for path, row in rows:
        if "--tune" in row["command"] or not row["parameters"]:
            continue  # the tuner chose the settings from the data; the floors record none
        config = _config(row["command"])
        recorded = json.loads(row["parameters"])
        for group, newer in NEWER_FIELDS.items():
            if group not in recorded:
                continue
            ran = {**dataclasses.asdict(newer), **recorded[group]}
            chosen = chosen_by_the_fit(ran) if group == "tpsr" else frozenset()
            for name, value in dataclasses.asdict(getattr(config, group)).items():
                checked += 1
                if name not in chosen and not _same(value, ran[name]):
                    wrong.append((path, row["command"], f"{group}.{name}", value, ran[name]))
    assert checked > 100_000
    assert not wrong, wrong[:5]


def test_a_row_that_ran_before_a_preset_changed_says_so_in_its_command():
    """What the check above would catch: a study row of one image of history whose command
    does not say it would rerun with the preset's two."""
    command = "python -m learner experiment --environment partial-strip --preset predictive"
    assert _config(command).tpsr.history_length == 2
    assert _config(f"{command} --set tpsr.history_length=1").tpsr.history_length == 1
    studies = [
        row for path, row in _committed_rows()
        if path.endswith("study_partial-strip_tpsr_seed.csv") and row["method"] == "tpsr"
    ]  # fmt: skip
    assert studies and all(
        json.loads(row["parameters"])["tpsr"]["history_length"] == 1
        and "--set tpsr.history_length=1" in row["command"]
        for row in studies
    )


@pytest.mark.parametrize(
    "job",
    [j for j in all_jobs() if j.argv[0] in ("experiment", "study")],
    ids=lambda job: f"{job.directory}/{job.csv}",
)
def test_every_job_gives_the_commands_of_its_rows(job):
    """Rerun, the job writes its CSV's rows again: each learned run's command is one of the
    grids it runs (a study: the floors' grid and one per value)."""
    args = build_parser().parse_args(job.argv_for(Path("results"), 1))
    assignments = [args.assignments]
    if job.argv[0] == "study":
        name, values = parse_values(args.vary)
        assignments += [[*args.assignments, f"{name}={value}"] for value in values]
    grids = {
        dataclasses.replace(config_from_args(args, (), given), methods=()) for given in assignments
    }
    with job.path(REPOSITORY / "results").open(newline="") as f:
        commands = {row["command"] for row in csv.DictReader(f) if row["method"] not in FLOORS}
    assert commands
    assert {c for c in commands if _config(c) not in grids} == set()
