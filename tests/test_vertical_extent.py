"""The camera's vertical extent as a parameter: geometry, validation, and every place an
environment is chosen (sim_node, the generators, learner experiment/study/info/evaluate)."""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from cli_support import run_entry

from learner.camera_study import wall_fills_up_to
from learner.cli import main as learner_main
from learner.experiment import default_config, experiment_command, run_cell
from learner.simulated import SimSettings, random_trajectory
from sim_node import SimConfig
from sim_node.camera import Camera
from sim_node.config import check_vertical_half_extent
from sim_node.generate import generate_bag
from tpsr_ros.core.errors import ConfigError
from tpsr_ros.io.model_io import open_model

REPOSITORY = Path(__file__).resolve().parents[1]


def _rows_alike(image: np.ndarray) -> bool:
    """Whether every row of the image equals the first (each column one colour)."""
    return bool(np.all(np.abs(image.astype(int) - image[:1].astype(int)) <= 1))


@pytest.mark.parametrize("extent", [0.03, 0.05, 0.1, 0.2])
def test_the_wall_fills_the_strip_exactly_up_to_its_distance(extent):
    """Facing north from the room's centre line, the 60 degree camera sees the north wall
    alone: every row is wall up to ``wall_fills_up_to``, the floor shows beyond."""
    camera = Camera(SimConfig(environment="partial", vertical_half_extent=extent))
    reach = wall_fills_up_to(extent)
    near = 45.0 - min(reach * 0.8, 43.0)  # y of a robot closer than the reach
    assert _rows_alike(camera.render(np.array([(22.5, near)]))[0])
    if reach * 1.25 < 44.0:  # the room lets the robot stand farther away
        far = 45.0 - reach * 1.25
        assert not _rows_alike(camera.render(np.array([(22.5, far)]))[0])


@pytest.mark.parametrize("bad", [0.0, -0.1, 5.5, float("nan"), float("inf"), True])
def test_a_bad_extent_is_a_one_line_error(bad):
    with pytest.raises(ConfigError) as info:
        check_vertical_half_extent(bad)
    assert "\n" not in str(info.value) and "vertical_half_extent" in str(info.value)
    with pytest.raises(ConfigError):
        SimConfig(vertical_half_extent=bad)
    with pytest.raises(ConfigError):
        SimSettings(bad)


def test_the_default_is_the_unchanged_camera():
    default = random_trajectory("partial", 300, seed=4)
    explicit = random_trajectory("partial", 300, seed=4, sim=SimSettings(0.2))
    narrow = random_trajectory("partial", 300, seed=4, sim=SimSettings(0.03))
    np.testing.assert_array_equal(default.observations, explicit.observations)
    np.testing.assert_array_equal(default.positions, narrow.positions)  # the same walk
    assert not np.array_equal(default.observations, narrow.observations)  # other images


@pytest.mark.slow
def test_the_default_experiment_reproduces_a_committed_headline_row():
    """A default run (no --set sim...) scores exactly what results/ records for it."""
    config = default_config("full", seed=11, rl_seed=111, episodes=(2000,), methods=("tpsr",))
    (row,) = run_cell(config, 2000, 0)
    with open(REPOSITORY / "results" / "defaults" / "experiment_full.csv", newline="") as f:
        committed = next(
            r for r in csv.DictReader(f)
            if (r["method"], r["episodes"], r["repetition"]) == ("tpsr", "2000", "0")
        )
    assert row.trial_rewards == committed["trial_rewards"]
    assert row.score == pytest.approx(float(committed["score"]))


def test_experiment_set_sim_names_the_camera_in_rows_and_commands():
    config = default_config(
        "partial", episodes=(40,), methods=("pca",), rl_steps=400,
        sim=SimSettings(0.05), repetitions=1,
    )
    assert "--set sim.vertical_half_extent=0.05" in experiment_command(config)
    assert "sim.vertical_half_extent" not in experiment_command(default_config("partial"))
    (row,) = run_cell(config, 40, 0)
    assert '"sim": {"vertical_half_extent": 0.05}' in row.parameters
    assert row.status == "ok"


def test_set_sim_rejects_a_bad_extent_in_one_line(capsys, tmp_path):
    code, _, err = run_entry(
        ["experiment", "--environment", "full", "--set", "sim.vertical_half_extent=0",
         "-o", str(tmp_path / "unused")],
        capsys,
    )
    assert code != 0 and len(err.strip().splitlines()) == 1 and "vertical_half_extent" in err
    assert not (tmp_path / "unused").exists()


def test_generated_bag_fit_info_and_evaluate_carry_the_camera(tmp_path, capsys):
    bag, rl = tmp_path / "narrow", tmp_path / "rl"
    narrow = SimConfig(environment="partial", vertical_half_extent=0.05)
    generate_bag(bag, narrow, 900, seed=2)
    generate_bag(rl, narrow, 600, seed=3)
    model, policy = tmp_path / "m.npz", tmp_path / "p.npz"
    assert learner_main(["fit", str(bag), "-o", str(model)]) == 0
    assert open_model(model).vertical_half_extent == 0.05
    assert learner_main(["info", str(model)]) == 0
    assert "camera vertical half-extent 0.05" in capsys.readouterr().out
    default_rl = tmp_path / "default_rl"
    generate_bag(default_rl, SimConfig(environment="partial"), 300, seed=3)
    with pytest.raises(ConfigError, match=r"the RL bags' camera has 0\.2"):
        learner_main(["policy", str(model), str(default_rl), "-o", str(policy)])
    assert learner_main(["policy", str(model), str(rl), "-o", str(policy)]) == 0
    # scored in the default camera: refused with the option that fixes it
    with pytest.raises(ConfigError, match=r"--vertical-half-extent 0\.05"):
        learner_main(["evaluate", str(policy), "--environment", "partial"])
    assert learner_main(
        ["evaluate", str(policy), "--environment", "partial", "--vertical-half-extent", "0.05"]
    ) == 0
    assert capsys.readouterr().out.splitlines()[-1].startswith("score: ")


@pytest.mark.parametrize(
    "command",
    [
        [sys.executable, "-m", "sim_node.generate", "--environment", "full", "--steps", "5",
         "-o", "x", "--vertical-half-extent", "0"],
        [sys.executable, "-m", "sim_node", "--ros-args", "-p", "vertical_half_extent:=-1.0"],
    ],
    ids=["generate", "sim_node"],
)
def test_the_commands_refuse_a_bad_extent_in_one_line(command, tmp_path):
    result = subprocess.run(
        command, capture_output=True, text=True, timeout=60, cwd=tmp_path
    )
    assert result.returncode != 0
    assert len(result.stderr.strip().splitlines()) == 1, result.stderr
    assert "vertical_half_extent" in result.stderr or "vertical-half-extent" in result.stderr
    assert not (tmp_path / "x").exists()


def test_partial_strip_is_partial_seen_through_the_strip(tmp_path):
    strip = SimConfig(environment="partial-strip")
    assert (strip.fov_deg, strip.vertical_extent) == (60.0, 0.1)
    assert SimConfig(environment="partial-strip", vertical_half_extent=0.2).vertical_extent == 0.2
    named = random_trajectory("partial-strip", 200, seed=5)
    spelled = random_trajectory("partial", 200, seed=5, sim=SimSettings(0.1))
    np.testing.assert_array_equal(named.observations, spelled.observations)
    generate_bag(tmp_path / "strip", strip, 30, seed=1)  # the extent as rendered is recorded
    from tpsr_ros.io.bag_chunks import survey_bags

    (survey,) = survey_bags([tmp_path / "strip"])
    assert (survey.environment, survey.vertical_half_extent) == ("partial-strip", 0.1)
