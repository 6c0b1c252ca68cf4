"""learner policy / evaluate / experiment: the RL step, the standard protocol, the grid."""

from __future__ import annotations

import csv
import subprocess
import sys

import numpy as np
import pytest

from learner.evaluate import EVALUATION_SEED, START_POSITIONS, STEPS, evaluate
from learner.experiment import default_config, run_cell, run_experiment, summarise
from learner.planning import fit_policy, transitions
from learner.representations import TruePositionTracker
from learner.simulated import random_trajectory
from sim_node import RobotEnv, SimConfig
from sim_node.generate import generate_bag
from tpsr_ros.core.fqi import FQIConfig
from tpsr_ros.core.pca_baseline import PCAConfig
from tpsr_ros.core.tpsr import TPSRConfig
from tpsr_ros.io.policy import Policy

SMALL_FIT = ["--ht-centers", "150", "--obs-centers", "100"]


def _learner(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "learner", *args], capture_output=True, text=True, timeout=300
    )


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    root = tmp_path_factory.mktemp("planning")
    generate_bag(root / "train", SimConfig(environment="full"), 3000, seed=1)
    generate_bag(root / "rl", SimConfig(environment="full"), 4000, seed=2)
    return root


def test_transitions_follow_steps_and_never_cross_a_gap():
    traj = random_trajectory("full", 10, seed=0)
    segments = np.array([0, 0, 0, 1, 1, 1, 1, 2, 3, 3])
    traj = type(traj)(**{**traj.__dict__, "segments": segments})
    states = np.arange(10, dtype=float)[:, None]
    s, a, r, s_next = transitions(states, traj)
    assert list(s[:, 0]) == [0, 1, 3, 4, 5, 8]
    assert list(s_next[:, 0]) == [1, 2, 4, 5, 6, 9]
    assert np.array_equal(a, traj.actions[[1, 2, 4, 5, 6, 9]])
    assert np.array_equal(r, traj.rewards[[1, 2, 4, 5, 6, 9]])


@pytest.mark.slow
@pytest.mark.parametrize("environment", ["full", "partial", "distractors"])
def test_true_position_baseline_scores_at_least_450(environment):
    steps = 15000 if environment == "full" else 20000
    rl = random_trajectory(environment, steps, seed=100)
    tracker = TruePositionTracker()
    policy = fit_policy(tracker, rl, FQIConfig(), environment=environment)
    result = evaluate(policy, tracker, environment)
    assert len(result.trials) == 10
    assert result.score >= 450, [t.reward for t in result.trials]
    assert all(t.goal_step is not None for t in result.trials)


def test_evaluation_follows_the_documented_protocol():
    # a policy that always stands still: every trial stays at its start and earns nothing
    rl = random_trajectory("full", 3000, seed=5)
    policy = fit_policy(TruePositionTracker(), rl, FQIConfig(), environment="full")
    weights = np.zeros_like(policy.q.weights)
    weights[:, 12] = 1.0  # action 12 = (0, 0)
    still = Policy(type(policy.q)(**{**policy.q.__dict__, "weights": weights}), "true-position",
                   "true-position", "full")
    result = evaluate(still, TruePositionTracker(), "full")
    assert [t.start for t in result.trials] == list(START_POSITIONS)
    assert all(t.reward == 0 and t.goal_step is None for t in result.trials)
    # the simulator sequence is: seeded env, start-up reset, one reset per start, 50 steps
    env = RobotEnv(SimConfig(), seed=EVALUATION_SEED)
    env.reset()
    for start in START_POSITIONS:
        env.reset(options={"position": start})
        for _ in range(STEPS):
            env.step(12)
    assert env.step_count == STEPS


def test_policy_and_evaluate_commands(bags, tmp_path):
    model, policy = tmp_path / "model.npz", tmp_path / "policy.npz"
    assert _learner("fit", str(bags / "train"), "-o", str(model), *SMALL_FIT).returncode == 0
    result = _learner("policy", str(model), str(bags / "rl"), "-o", str(policy))
    assert result.returncode == 0, result.stderr
    result = _learner("evaluate", str(policy), "--environment", "full")
    assert result.returncode == 0, result.stderr
    lines = result.stdout.strip().splitlines()
    assert len(lines) == 11 and all(line.startswith("trial") for line in lines[:10])
    score = float(lines[-1].removeprefix("score: "))
    trials = [float(line.split("reward")[1].split()[0]) for line in lines[:10]]
    assert score == pytest.approx(np.mean(trials), abs=0.05)
    # the recorded model path is used when --model is not given; both agree
    again = _learner("evaluate", str(policy), "--environment", "full", "--model", str(model))
    assert again.stdout == result.stdout


def test_bad_input_to_policy_and_evaluate(bags, tmp_path):
    model, other = tmp_path / "model.npz", tmp_path / "other.npz"
    policy = tmp_path / "policy.npz"
    _learner("fit", str(bags / "train"), "-o", str(model), *SMALL_FIT)
    _learner("fit", str(bags / "train"), "-o", str(other), "--method", "pca")
    assert _learner("policy", str(model), str(bags / "rl"), "-o", str(policy)).returncode == 0
    cases = [
        (["evaluate", str(policy), "--environment", "full", "--model", str(other)],
         "trained for model"),
        (["evaluate", str(policy), "--environment", "partial"],
         "trained in environment 'full', not 'partial'"),
        (["policy", str(model), str(bags / "rl"), "-o", str(tmp_path / "p2.npz"),
          "--steps", "5000"], "has 4000 steps, fewer than the 5000 requested"),
        (["policy", str(model), str(bags / "rl"), "-o", str(policy)], "already exists"),
        (["evaluate", str(tmp_path / "missing.npz"), "--environment", "full"], "does not exist"),
    ]
    for args, message in cases:
        result = _learner(*args)
        assert result.returncode != 0, args
        assert message in result.stderr and result.stderr.count("\n") == 1, result.stderr
    model.rename(tmp_path / "moved.npz")  # the model the policy records is gone
    result = _learner("evaluate", str(policy), "--environment", "full")
    assert result.returncode != 0 and "pass --model MODEL" in result.stderr


def _small_grid(**overrides):
    settings = {
        "episodes": (400,),
        "repetitions": 2,
        "rl_steps": 3000,
        "tpsr": TPSRConfig(ht_centers=150, obs_centers=100),
        "pca": PCAConfig(dim=2),
    }
    return default_config("full", **{**settings, **overrides})


def test_experiment_grid_rows_seeds_and_rerun_of_one_row(tmp_path):
    config = _small_grid()
    rows = run_experiment(config, workers=2, progress=False)
    assert [(r.method, r.repetition) for r in rows] == [
        (m, k) for k in (0, 1) for m in ("tpsr", "pca", "true-position")
    ]
    assert all(r.status == "ok" and np.isfinite(r.score) for r in rows)
    assert len({r.train_seed for r in rows}) == 2  # one training run per repetition
    # any row reruns alone from its recorded seeds, with the same result
    again = run_cell(_small_grid(first_repetition=1, repetitions=1), 400, 1)
    assert [(r.score, r.train_seed) for r in again] == [
        (r.score, r.train_seed) for r in rows if r.repetition == 1
    ]
    table = {(t["method"], t["episodes"]): t for t in summarise(rows)}
    tpsr = np.array([r.score for r in rows if r.method == "tpsr"])
    assert table[("tpsr", 400)]["mean"] == pytest.approx(tpsr.mean())
    assert table[("tpsr", 400)]["sem"] == pytest.approx(tpsr.std(ddof=1) / np.sqrt(2))


def test_experiment_command_writes_csv_and_plot(tmp_path):
    out = tmp_path / "results"
    args = ["experiment", "--environment", "full", "--episodes", "300", "--repetitions", "1",
            "--methods", "pca", "true-position", "--rl-steps", "2000", "--workers", "1",
            "-o", str(out)]
    result = _learner(*args)
    assert result.returncode == 0, result.stderr
    with (out / "experiment_full.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    assert [r["method"] for r in rows] == ["pca", "true-position"]
    assert (out / "experiment_full.png").stat().st_size > 10_000
    assert "already exists" in _learner(*args).stderr
