"""Fits and tunes sized to what a short robot log supports.

Phone-like bags (``sim_node.robot_bag --timeline phone``: a 14 Hz JPEG camera, a ``Twist``
per frame, commands lasting 0.3 s) of about 20 s: the rank rule holds every fit's kept
singular values above the floor, ``learner tune`` writes a config ``learner fit --config``
uses or exits with one line at any step period, ``learner fit`` says when the data are
too little, and ``learner plot`` prints its judgement.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from cli_support import run_entry

from learner.adequacy import MIN_EPISODES_PER_ACTION, Adequacy
from learner.cli import main
from learner.plots import judge_states
from sim_node.robot_bag import RobotBagConfig, write_robot_bag
from tpsr_ros.core.episodes import Trajectory
from tpsr_ros.core.errors import DataError
from tpsr_ros.core.learn import fit_tpsr_trajectory
from tpsr_ros.core.sizing import Sizing
from tpsr_ros.core.tpsr import TPSRConfig
from tpsr_ros.core.tpsr_stages import independent_episodes, singular_value_floor, supported_rank
from tpsr_ros.io.model_io import open_model

TOPICS = ["--image-topic", "/front_camera/image_raw/compressed", "--action-topic", "/cmd_vel"]


@pytest.fixture(scope="module")
def phone_bags(tmp_path_factory: pytest.TempPathFactory) -> dict[int, Path]:
    """Two phone-like bags of 70 simulator steps (21 s), seeds 0 and 1."""
    root = tmp_path_factory.mktemp("phone")
    bags = {}
    for seed in (0, 1):
        bags[seed] = root / f"phone{seed}"
        write_robot_bag(bags[seed], RobotBagConfig(steps=70, seed=seed, timeline="phone"))
    return bags


def _kept_above_floor(model_path: Path) -> tuple[int, float, float]:
    """The model's rank, its smallest kept singular value over the largest, and the floor."""
    model = open_model(model_path).model
    s, r = model.singular_values, model.state_dim
    floor = singular_value_floor(1.0, int(model.fit_info["independent_episodes"]))
    return r, float(s[r - 1] / s[0]), floor


def test_supported_rank_counts_the_values_above_the_floor() -> None:
    values = np.array([1.0, 0.5, 0.02, 0.009, 1e-4])
    assert singular_value_floor(1.0, 100) == pytest.approx(0.005)
    assert supported_rank(values, 100, usable=5) == 4  # 0.009 >= 0.005 > 1e-4
    assert supported_rank(values, 25, usable=5) == 3  # floor 0.01
    assert supported_rank(values, 25, usable=2) == 2  # never above the numerical rank
    assert supported_rank(np.array([1.0, 0.04]), 1, usable=2) == 1  # floor 0.05
    assert supported_rank(np.array([1.0, 1e-9]), 10**6, usable=2) == 1  # the largest passes


def test_overlapping_windows_count_as_the_episodes_that_share_no_step() -> None:
    """The rank rule's sampling error counts independent samples: a window at every step
    adds one image, not a window's worth."""
    guide = TPSRConfig()
    overlapping = TPSRConfig(history_length=2, overlapping_episodes=True)
    assert independent_episodes(8000, guide) == 8000
    assert independent_episodes(23997, overlapping) == 5999  # one in every 2 + 1 + 1
    assert independent_episodes(3, overlapping) == 1 and independent_episodes(0, guide) == 0
    rng = np.random.default_rng(0)
    steps = 240  # a 3-symbol chain; cut every step, the same steps are 237 windows
    actions = rng.integers(2, size=steps)
    symbols = np.cumsum(actions + rng.integers(2, size=steps)) % 3
    obs = np.eye(3)[symbols] + 0.01 * rng.normal(size=(steps, 3))
    trajectory = Trajectory.from_arrays(actions, obs, n_actions=2)
    config = TPSRConfig(obs_dim=3, ht_dim=3, obs_centers=20, ht_centers=20, rank=12,
                        history_length=2, overlapping_episodes=True)  # fmt: skip
    model = fit_tpsr_trajectory(trajectory, config, sizing=Sizing())
    info = model.fit_info
    assert info["independent_episodes"] == info["training_episodes"] // 4
    s, r = model.singular_values, model.state_dim
    floor = singular_value_floor(float(s[0]), info["independent_episodes"])
    assert r < 12 and s[r - 1] >= floor > s[r]  # the rule, at the independent count


def test_a_sized_fit_lowers_the_rank_and_a_fixed_rank_is_refused() -> None:
    rng = np.random.default_rng(0)
    steps = 240  # 80 episodes of a 3-symbol chain: a weak spectrum beyond rank 2
    actions = rng.integers(2, size=steps)
    symbols = np.cumsum(actions + rng.integers(2, size=steps)) % 3
    obs = np.eye(3)[symbols] + 0.01 * rng.normal(size=(steps, 3))
    trajectory = Trajectory.from_arrays(actions, obs, n_actions=2)
    config = TPSRConfig(obs_dim=3, ht_dim=3, obs_centers=20, ht_centers=20, rank=12)
    model = fit_tpsr_trajectory(trajectory, config, sizing=Sizing())
    s, r = model.singular_values, model.state_dim
    floor = singular_value_floor(float(s[0]), int(model.fit_info["training_episodes"]))
    assert r < 12 and model.fit_info["sized"]["rank"] == [12, r]
    assert s[r - 1] >= floor > s[r]  # every kept value passes, the next does not
    with pytest.raises(DataError, match=f"rank 12 is above the {r} singular value"):
        fit_tpsr_trajectory(trajectory, config, sizing=Sizing({"rank"}))
    given = fit_tpsr_trajectory(trajectory, dataclasses.replace(config, rank=r + 1))
    assert given.state_dim == r + 1  # a config given in code is used as given


@pytest.mark.slow
@pytest.mark.parametrize("period", ["0.075", "0.25"])
def test_fit_never_keeps_a_singular_value_below_the_rule(phone_bags, tmp_path, capsys, period):
    presets = ("predictive", "best") if period == "0.25" else ("predictive",)
    for seed, bag in phone_bags.items():
        for preset in presets:  # best where its rank is checked below
            model = tmp_path / f"m{seed}{preset}.npz"
            code, _, err = run_entry(
                ["fit", str(bag), *TOPICS, "--step-period", period, "--preset", preset, "-o",
                 str(model)], capsys,
            )  # fmt: skip
            assert code == 0, err
            rank, weakest, floor = _kept_above_floor(model)
            assert weakest >= floor, (seed, preset, rank, weakest, floor)
        if period == "0.25":  # best's turning rank 16 cannot be carried by 27 episodes
            assert "rank 16 -> " in err and "training episodes support" in err
    code, _, err = run_entry(
        ["fit", str(phone_bags[0]), *TOPICS, "--step-period", "0.25", "--preset", "best",
         "--rank", "12", "-o", str(tmp_path / "x.npz")], capsys,
    )  # fmt: skip
    last = err.splitlines()[-1]
    assert code == 1 and last.startswith("learner: error: rank 12 is above the 8"), err
    assert "Traceback" not in err and not (tmp_path / "x.npz").exists()


@pytest.mark.slow
def test_too_little_data_is_said_with_what_to_record(phone_bags, tmp_path, capsys):
    model = tmp_path / "m.npz"
    code, _, err = run_entry(
        ["fit", str(phone_bags[0]), *TOPICS, "--step-period", "0.25", "-o", str(model)], capsys
    )
    assert code == 0, err
    warning = next(line for line in err.splitlines() if "too little data" in line)
    assert "per action" in warning and "record at least" in warning
    assert "tracking the training data restarts at" in err
    code, out, _ = run_entry(["info", str(model)], capsys)
    assert code == 0 and "recovery rate" in out and "too little data" in out
    code, out, err = run_entry(
        ["plot", str(model), str(phone_bags[1]), *TOPICS, "-o", str(tmp_path / "p.png")], capsys
    )
    assert code == 0, err
    assert "judgement: " in out and "held-out R^2" in out and "recovery rate" in out
    assert (tmp_path / "p.png").stat().st_size > 10_000


def test_adequacy_asks_for_the_seconds_that_reach_the_minimum() -> None:
    few = Adequacy(training_episodes=28, n_actions=25, steps=84, recoveries=32, seconds=21.0)
    assert few.too_few_episodes and few.too_many_recoveries
    wanted = MIN_EPISODES_PER_ACTION * 25 / 28
    assert few.more_seconds() == pytest.approx(21.0 * (wanted - 1))
    assert "1.1 per action" in (few.judgement() or "")
    enough = Adequacy(training_episodes=1000, n_actions=25, steps=3000, recoveries=3, seconds=3e3)
    assert not enough.too_little and enough.judgement() is None


def test_the_judgement_tells_a_predictive_state_from_noise() -> None:
    rng = np.random.default_rng(1)
    steps = 400  # images that drift with a hidden position the good states carry
    position = np.cumsum(rng.normal(size=steps)) * 0.3
    obs = np.column_stack([np.sin(position + k) for k in range(6)])
    obs += 0.05 * rng.normal(size=obs.shape)
    trajectory = Trajectory.from_arrays(np.zeros(steps, dtype=np.int64), obs, n_actions=1)
    good = judge_states(np.column_stack([np.sin(position), np.cos(position)]), trajectory)
    noise = judge_states(rng.normal(size=(steps, 2)), trajectory)
    assert good.value > 0.4 and good.word == "good"
    assert noise.value < 0.05 and noise.word in ("poor", "worse than the mean")


@pytest.mark.slow
@pytest.mark.parametrize("period", ["0.05", "0.25", "0.5"])
def test_tune_writes_a_usable_config_or_one_line(phone_bags, tmp_path, capsys, period):
    for seed, bag in phone_bags.items():
        config = tmp_path / f"t{seed}.yaml"
        code, _, err = run_entry(
            ["tune", str(bag), *TOPICS, "--step-period", period, "--candidates", "4", "-o",
             str(config)], capsys,
        )  # fmt: skip
        assert "Traceback" not in err
        assert max(len(line) for line in err.splitlines()) < 700  # summarised, no value lists
        if code == 1:
            last = err.splitlines()[-1]
            assert last.startswith("learner: error: ") and not config.exists()
            assert "record" in last  # says what would do
            continue
        assert code == 0 and config.exists(), err
        model = tmp_path / f"m{seed}.npz"
        code, _, err = run_entry(
            ["fit", str(bag), "--config", str(config), "-o", str(model)], capsys
        )
        assert code == 0, err
        rank, weakest, floor = _kept_above_floor(model)
        assert weakest >= floor
