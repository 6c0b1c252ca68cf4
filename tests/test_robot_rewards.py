"""Rewards a real robot can give ``learner policy``: a reward topic of each stock type summed
onto the model's step grid, a goal region on the poses, the one-line refusal of a bag with
neither, and (slow) a robot bag without ``/reward`` planned to the simulator's goal."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from cli_support import run_entry

from learner.rewards import REWARD_WAYS, RewardSource, apply_rewards, check_reward_topic
from tpsr_ros.core.episodes import Trajectory
from tpsr_ros.core.errors import ConfigError, DataError, MessageError
from tpsr_ros.core.planning import transitions
from tpsr_ros.core.rewards import GoalRegion, step_reward_sums
from tpsr_ros.io import messages as msgs
from tpsr_ros.io.bag import BagReader, BagWriter
from tpsr_ros.io.policy import load_policy
from tpsr_ros.io.reward_messages import (
    BOOL_TYPE,
    FLOAT32_TYPE,
    FLOAT64_TYPE,
    REWARD_TYPES,
    decode_reward,
    reward_message,
)
from tpsr_ros.io.streams import FitOptions, fit_stream_spec, read_stream_trajectory

S = 10**9
MS = 10**6
T0 = 100 * S
CAMERA, COMMANDS, ODOM = "/camera", "/cmd", "/odom"
FRAME_NS = 100 * MS  # a 10 Hz camera
FRAMES = 80
STEP = 0.5  # s
GRID = FitOptions(step_period=STEP, step_offset=0.05, image_size=(2, 2), actions=2)
SPEED = 2.0  # m/s along x, so the pose at t is (SPEED * (t - T0), 1)


def write_bag(path, rewards=None, *, poses=True, pose_start_ns=T0):
    """A small robot bag: a 4x4 bgr8 camera at 10 Hz from T0, a TwistStamped 20 ms after
    each frame (linear.x -1 or +1), odometry at 20 Hz moving along x at SPEED from
    ``pose_start_ns``, and ``rewards``: ``{topic: (msgtype, [(log_ns, stamp_ns, value)])}``."""
    rng = np.random.default_rng(3)
    types = msgs.jazzy_typestore().types
    records = []
    for i in range(FRAMES):
        stamp = T0 + i * FRAME_NS
        pixels = rng.integers(0, 256, size=(4, 4, 3), dtype=np.uint8)
        image = types[msgs.IMAGE_TYPE](
            header=msgs.header_msg(stamp, "camera"), height=4, width=4, encoding="bgr8",
            is_bigendian=0, step=12, data=pixels.reshape(-1),
        )  # fmt: skip
        records.append((stamp + MS, CAMERA, msgs.IMAGE_TYPE, image))
        command = msgs.twist_stamped_msg(stamp + 20 * MS, float(rng.choice([-1.0, 1.0])), 0.0)
        records.append((stamp + 21 * MS, COMMANDS, msgs.ACTION_TYPE, command))
    if poses:
        for stamp in range(pose_start_ns, T0 + FRAMES * FRAME_NS, 50 * MS):
            x = SPEED * (stamp - T0) / S
            records.append((stamp + MS, ODOM, msgs.POSE_TYPE, msgs.pose_msg(stamp, x, 1.0)))
    for topic, (msgtype, events) in (rewards or {}).items():
        for log, stamp, value in events:
            records.append((log, topic, msgtype, reward_message(msgtype, value, stamp)))
    records.sort(key=lambda r: r[0])
    with BagWriter(path) as writer:
        for topic, msgtype in {(r[1], r[2]) for r in records}:
            writer.add_topic(topic, msgtype)
        for log, topic, msgtype, msg in records:
            writer.write(topic, log, msgs.serialize(msg, msgtype))
    return path


def read(path, **topics) -> Trajectory:
    spec = fit_stream_spec([path], GRID, image_topic=CAMERA, action_topic=COMMANDS)
    return read_stream_trajectory([path], spec, **topics)


def expected_sums(stamps, times, values, step_ns):
    """The rule written out step by step: the rewards timed in (t - step, t]."""
    return np.array(
        [sum(v for time, v in zip(times, values) if t - step_ns < time <= t) for t in stamps],
        dtype=np.float64,
    )


# -- the rules ---------------------------------------------------------------------------------


def test_rewards_are_summed_over_each_step_window():
    stamps = np.array([10, 20, 30, 50, 60]) * S  # a gap between 30 and 50
    times = np.array([10, 3, 15, 20, 20, 25, 40, 45, 59, 61, 0]) * S
    values = np.array([1.0, 7.0, 2.0, 0.5, 0.25, -1.0, 9.0, 4.0, 3.0, 8.0, 6.0])
    got = step_reward_sums(times, values, stamps, 10 * S)
    # step 10 takes (0, 10]: 1 and 7 (0 s lies outside, on the window's open end)
    np.testing.assert_array_equal(got, [8.0, 2.75, -1.0, 4.0, 3.0])  # 40 s: gap; 61 s: after
    np.testing.assert_array_equal(got, expected_sums(stamps, times, values, 10 * S))
    assert np.array_equal(step_reward_sums([], [], stamps, 10 * S), np.zeros(5))
    with pytest.raises(ConfigError, match="at least the step period"):
        step_reward_sums(times, values, np.array([10, 15]) * S, 10 * S)
    with pytest.raises(ConfigError, match="finite"):
        step_reward_sums([1], [np.nan], stamps, 10 * S)


def test_goal_region_rewards_steps_ending_strictly_inside():
    region = GoalRegion.parse(" 45, 45 ,15")
    assert region == GoalRegion(45.0, 45.0, 15.0, 10.0)
    poses = np.array([[45, 45, 0, 1], [30.0, 45.0, 1, 0], [35, 35, 0, 0], [30, 30, 0, 0],
                      [np.nan, np.nan, 0, 0], [44, 31, 0, 0]])  # fmt: skip
    # distances 0, 15 (on the edge: outside, as the simulator's zone), 14.1, 21.2, ?, 14.04
    np.testing.assert_array_equal(region.rewards(poses), [10, 0, 10, 0, np.nan, 10])
    assert region.describe() == "+10 within 15 m of (45, 45)"
    for bad in ("45,45", "a,b,c", "1,2,3,4", "1,2,0", "1,2,-3", "nan,1,1", "1,inf,2"):
        with pytest.raises(ConfigError, match="goal region"):
            GoalRegion.parse(bad)


@pytest.mark.parametrize("msgtype", REWARD_TYPES)
def test_each_reward_type_gives_its_value_and_time(msgtype):
    value = 1.0 if msgtype == BOOL_TYPE else -2.5
    data = msgs.serialize(reward_message(msgtype, value, 7 * S), msgtype)
    time, got = decode_reward(data, msgtype, 9 * S)
    assert got == value
    assert time == (7 * S if msgtype == msgs.REWARD_TYPE else 9 * S)  # stamp, else log time
    if msgtype == BOOL_TYPE:
        false = msgs.serialize(reward_message(msgtype, 0.0), msgtype)
        assert decode_reward(false, msgtype, 9 * S) == (9 * S, 0.0)
        with pytest.raises(MessageError, match="not 0 .false. or 1 .true."):
            decode_reward(data[:4] + bytes([2]) + data[5:], msgtype, 9 * S)
    else:
        infinite = msgs.serialize(reward_message(msgtype, np.inf, 7 * S), msgtype)
        with pytest.raises(MessageError, match="not finite"):
            decode_reward(infinite, msgtype, 9 * S)
    if msgtype == msgs.REWARD_TYPE:  # an unset stamp: the log time
        unstamped = msgs.serialize(reward_message(msgtype, value, 0), msgtype)
        assert decode_reward(unstamped, msgtype, 9 * S) == (9 * S, value)
        named = msgs.serialize(msgs.state_msg(7 * S, np.array([1.0])), msgtype)  # 'b0'
        with pytest.raises(MessageError, match="names 'reward' first"):
            decode_reward(named, msgtype, 9 * S)


# -- read from bags onto the grid -------------------------------------------------------------


@pytest.mark.parametrize("msgtype", REWARD_TYPES)
def test_reward_topic_of_each_type_is_summed_onto_the_grid(tmp_path, msgtype):
    rng = np.random.default_rng(11)
    span = FRAMES * FRAME_NS
    stamps = T0 + np.sort(rng.integers(0, span, size=40))
    logs = stamps + rng.integers(1, 300 * MS, size=40)  # a std_msgs reward's time is its log
    values = rng.choice([0.0, 1.0], size=40) if msgtype == BOOL_TYPE else rng.normal(size=40)
    if msgtype == FLOAT32_TYPE:
        values = values.astype(np.float32).astype(np.float64)  # what a Float32 holds
    events = list(zip(logs.tolist(), stamps.tolist(), values.tolist()))
    bag = write_bag(tmp_path / "bag", {"/reward_in": (msgtype, events)})
    trajectory = read(bag, reward_topic="/reward_in")
    assert len(trajectory) == 16 and trajectory.stamps[0] == T0 + 50 * MS
    times = stamps if msgtype == msgs.REWARD_TYPE else logs
    expected = expected_sums(trajectory.stamps, times, values, round(STEP * S))
    np.testing.assert_allclose(trajectory.rewards, expected, rtol=0, atol=1e-12)
    assert np.count_nonzero(expected) >= 8  # the check has teeth
    # the same bag read without its reward topic: unknown rewards, not zeros
    assert np.isnan(read(bag).rewards).all()


def test_boundaries_belong_to_the_step_they_close(tmp_path):
    first = T0 + 50 * MS  # the first step time
    events = [
        (first, first, 1.0),  # at a step time: that step's
        (first + 1, first + 1, 2.0),  # just after: the next step's
        (first + STEP * S, first + STEP * S, 4.0),  # at the next step time: the next step's
        (first - 10 * MS, first - 10 * MS, 8.0),  # before the first step, inside its window
        (first - STEP * S, first - STEP * S, 16.0),  # on the open end of the first window
    ]
    bag = write_bag(tmp_path / "bag", {"/r": (FLOAT64_TYPE, [(int(a), int(b), v)
                                                             for a, b, v in events])})
    rewards = read(bag, reward_topic="/r").rewards
    np.testing.assert_array_equal(rewards[:3], [9.0, 6.0, 0.0])
    assert rewards[3:].sum() == 0


def test_goal_region_rewards_follow_the_ground_truth(tmp_path):
    bag = write_bag(tmp_path / "bag")
    trajectory = read(bag, pose_topic=ODOM)
    truth = SPEED * (trajectory.stamps - T0) / S  # the pose at each step's end
    np.testing.assert_allclose(trajectory.positions[:, 0], truth, atol=1e-9)
    region = GoalRegion(8.0, 1.0, 3.0)
    source = RewardSource(topic="/reward", region=region)
    got, line = apply_rewards(trajectory, source, ODOM)
    np.testing.assert_array_equal(got.rewards, np.where(np.abs(truth - 8.0) < 3.0, 10.0, 0.0))
    assert int((got.rewards == 10).sum()) == 6  # x = 5.1, 6.1, ... 10.1 m
    assert line == f"rewards: +10 within 3 m of (8, 1) on {ODOM}: 6 of 16 steps end inside"
    # poses from 2 s on: the first steps have no pose, no reward, and no transition
    late = read(write_bag(tmp_path / "late", pose_start_ns=T0 + 2 * S), pose_topic=ODOM)
    got, line = apply_rewards(late, source, ODOM)
    unknown = np.isnan(got.rewards)
    assert unknown.tolist() == [True] * 4 + [False] * 12
    assert "4 steps without a pose (their transitions left out)" in line
    states = np.arange(len(got), dtype=np.float64)[:, None]
    s, _, r, s_next = transitions(states, got, skip_unknown=True)
    assert s[:, 0].tolist() == list(range(3, 15)) and np.isfinite(r).all()
    assert np.array_equal(s_next[:, 0], s[:, 0] + 1)
    with pytest.raises(DataError, match="lacks rewards for 3 of 15 transitions"):
        transitions(states, got)
    none = read(write_bag(tmp_path / "none", poses=False), pose_topic=ODOM)
    with pytest.raises(DataError, match="no pose on /odom at any step"):
        apply_rewards(none, source, ODOM)


def test_reward_topic_types_are_checked_before_reading(tmp_path):
    bag = write_bag(tmp_path / "bag", {"/flag": (BOOL_TYPE, [(T0, T0, 1.0)])})
    check_reward_topic([bag], RewardSource("/flag", given=True), resampled=True)
    with pytest.raises(ConfigError, match="carries geometry_msgs/msg/PoseStamped, not one of"):
        check_reward_topic([bag], RewardSource(ODOM, given=True), resampled=True)
    with pytest.raises(ConfigError, match="no stamp, but this model pairs steps by identical"):
        check_reward_topic([bag], RewardSource("/flag", given=True), resampled=False)
    with pytest.raises(DataError, match="have no messages on /reward; give --reward-topic"):
        check_reward_topic([bag], RewardSource("/reward"), resampled=True)


# -- learner policy ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def small_model(tmp_path_factory):
    """A model of the small bag's grid (fitted in-process, tiny sizes)."""
    from learner.cli import main

    tmp = tmp_path_factory.mktemp("rewards")
    bag = write_bag(tmp / "train")
    model = tmp / "model.npz"
    main([
        "fit", str(bag), "-o", str(model), "--image-topic", CAMERA, "--action-topic", COMMANDS,
        "--pose-topic", ODOM, "--step-period", str(STEP), "--step-offset", "0.05",
        "--image-size", "2", "--actions", "2", "--obs-centers", "5", "--ht-centers", "5",
        "--rank", "2", "--ht-dim", "3", "--obs-dim", "3", "--preset", "best",
    ])  # fmt: skip
    return model


def test_a_bag_without_rewards_is_refused_in_one_line(tmp_path, capsys, small_model):
    bag = write_bag(tmp_path / "bag")
    status, out, err = run_entry(["policy", str(small_model), str(bag), "-o",
                                  str(tmp_path / "p.npz")], capsys)  # fmt: skip
    assert status == 1 and out == ""
    assert err.count("\n") == 1 and "Traceback" not in err, err
    assert err.startswith("learner: error: no rewards: the RL bag(s) ")
    assert err.rstrip("\n").endswith(REWARD_WAYS)
    for way in ("--reward-topic TOPIC", "std_msgs/msg/Bool", "--goal-region X,Y,R --pose-topic"):
        assert way in err
    assert not (tmp_path / "p.npz").exists()
    both = ["--reward-topic", "/r", "--goal-region", "1,1,1"]
    status, _, err = run_entry(["policy", str(small_model), str(bag), "-o",
                                str(tmp_path / "p.npz"), *both], capsys)  # fmt: skip
    assert status == 1 and "--reward-topic and --goal-region" in err and err.count("\n") == 1
    status, _, err = run_entry(["policy", str(small_model), str(bag), "-o",
                                str(tmp_path / "p.npz"), "--goal-region", "1,1"], capsys)
    assert status == 2 and "X,Y,R" in err and err.count("\n") == 1


def test_policy_takes_a_bool_topic_or_a_goal_region(tmp_path, capsys, small_model):
    flags = [(T0 + k * 300 * MS, 0, 1.0) for k in range(5, 20)]  # a flag every 0.3 s
    bag = write_bag(tmp_path / "bag", {"/at_goal": (BOOL_TYPE, flags)})
    out = tmp_path / "p.npz"
    small = ["--centers", "4", "--ensemble", "1", "--state-scaling", "standardise"]
    status, _, err = run_entry(["policy", str(small_model), str(bag), "-o", str(out),
                                "--reward-topic", "/at_goal", *small], capsys)  # fmt: skip
    assert status == 0, err
    expected = expected_sums(read(bag).stamps, [f[0] for f in flags], [1.0] * 15, STEP * S)
    assert f"non-zero, total {expected.sum():g}" in err and expected.sum() == 15
    assert f"/at_goal: {np.count_nonzero(expected)} of 16 steps" in err
    assert load_policy(out).metadata["rewards"] == {"topic": "/at_goal"}
    status, _, err = run_entry(["policy", str(small_model), str(bag), "-o", str(out), "--force",
                                "--goal-region", "8,1,3", "--pose-topic", ODOM, *small],
                               capsys)  # fmt: skip
    assert status == 0, err
    assert "+10 within 3 m of (8, 1) on /odom: 6 of 16 steps end inside" in err
    metadata = load_policy(out).metadata
    assert metadata["rewards"] == {
        "goal_region": {"x": 8.0, "y": 1.0, "radius": 3.0, "reward": 10.0}, "pose_topic": ODOM
    }
    assert json.dumps(metadata)  # JSON, no pickles


# -- a robot bag without /reward, planned to the simulator's goal ------------------------------


def test_robot_bag_without_reward_has_no_reward_topic(tmp_path):
    from sim_node.robot_bag import RobotBagConfig, write_robot_bag

    write_robot_bag(tmp_path / "bag", RobotBagConfig(steps=3, reward=False))
    with BagReader(tmp_path / "bag") as reader:
        assert "/reward" not in reader.topics
        assert set(reader.topics) == {"/front_camera/image_raw", "/cmd_vel", "/odom"}
    assert dataclasses.asdict(RobotBagConfig())["reward"] is True


@pytest.mark.slow
def test_goal_region_policy_of_a_bag_without_reward_reaches_the_goal(tmp_path, capsys):
    from robot_sim_support import evaluate_robot_policy

    from learner.floors import constant_floor, random_floor
    from sim_node.robot_bag import main as robot_bag
    from tpsr_ros.io.model_io import open_model

    bag, model, policy = tmp_path / "robot", tmp_path / "model.npz", tmp_path / "policy.npz"
    # 2000 steps: every trial reaches the goal, 357 (4000: about 410; 6000: 420) against
    # floors of 38
    assert robot_bag(["--steps", "2000", "--seed", "0", "--no-reward", "-o", str(bag)]) == 0
    fit = ["fit", str(bag), "--image-topic", "/front_camera/image_raw", "--action-topic",
           "/cmd_vel", "--pose-topic", "/odom", "--step-period", "1.0", "-o", str(model)]
    assert run_entry(fit, capsys)[0] == 0
    status, _, err = run_entry(["policy", str(model), str(bag), "-o", str(policy)], capsys)
    assert status == 1 and "no rewards" in err  # a real robot's bag: no /reward
    region = ["--goal-region", "37,37,6", "--pose-topic", "/odom"]  # clear of the walls
    status, _, err = run_entry(["policy", str(model), str(bag), "-o", str(policy), *region],
                               capsys)  # fmt: skip
    assert status == 0, err
    result = evaluate_robot_policy(load_policy(policy), open_model(model))
    floors = max(
        constant_floor("full").evaluation.score, random_floor("full", policy_seed=0).score
    )
    assert all(trial.goal_step is not None for trial in result.trials), result
    assert result.score > floors + 200, (result.score, floors)
