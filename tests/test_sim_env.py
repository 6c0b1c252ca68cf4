"""Simulator physics, reward, noise, actions and determinism against ground truth."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sim_node import ACTIONS, VELOCITIES, RobotEnv, SimConfig, action_index, random_rollout
from sim_node.env import step_reward
from tpsr_ros.core.actions import action_indices
from tpsr_ros.core.errors import ConfigError

L, R = 45.0, 1.0
ENVIRONMENTS = ("full", "partial", "distractors")


@pytest.fixture(scope="module")
def long_run():
    return random_rollout(SimConfig(environment="full"), 20000, seed=11)


def _previous_positions(run, start):
    return np.vstack([start, run.positions[:-1]])


@pytest.mark.slow
def test_robot_never_leaves_the_room(long_run):
    assert long_run.positions.min() >= R - 1e-3
    assert long_run.positions.max() <= L - R + 1e-3


@pytest.mark.slow
def test_robot_cannot_tunnel_when_driven_hard_into_walls_and_corners():
    env = RobotEnv(SimConfig(), seed=0)
    env.reset(options={"position": (22.5, 22.5)})
    fastest = [i for i, (vx, vy) in enumerate(ACTIONS) if abs(vx) == 6 or abs(vy) == 6]
    rng = np.random.default_rng(1)
    for _ in range(3000):
        env.step(int(rng.choice(fastest)))
        x, y = env.position
        assert R - 1e-3 <= x <= L - R + 1e-3 and R - 1e-3 <= y <= L - R + 1e-3


def _start_of(seed):
    env = RobotEnv(SimConfig(), seed=seed)
    _, info = env.reset(seed=seed)
    return info["position"]


def test_wall_penalty_exactly_on_blocked_steps(long_run):
    run = long_run
    previous = _previous_positions(run, _start_of(11))
    free_end = previous + run.executed  # where the robot would be without walls
    # how far the free motion would carry the robot beyond a wall it drives towards
    beyond_low = np.where(run.executed < 0, R - free_end, -np.inf)
    beyond_high = np.where(run.executed > 0, free_end - (L - R), -np.inf)
    excess = np.maximum(beyond_low, beyond_high).max(axis=1)
    clear = np.abs(excess) > 1e-3  # leave out steps that graze a wall within 1 mm
    assert clear.mean() > 0.999
    assert np.array_equal(run.wall_contact[clear], excess[clear] > 0)
    assert np.array_equal(run.rewards == -1.0, run.wall_contact)
    # sliding along a wall without pushing into it is not a contact
    touching = (np.abs(previous - R) < 1e-3) | (np.abs(previous - (L - R)) < 1e-3)
    sliding = touching.any(axis=1) & (excess < 0)
    assert sliding.any() and not run.wall_contact[sliding].any()
    # a blocked step ends on the wall: the clipped free motion, to the 1e-4 m contact slop
    expected = np.clip(free_end, R, L - R)
    assert np.abs(run.positions[clear] - expected[clear]).max() < 2e-3


def test_goal_reward_exactly_inside_the_zone(long_run):
    run = long_run
    inside = np.linalg.norm(run.positions - [L, L], axis=1) < 15.0
    assert np.array_equal(run.goal_zone, inside)
    expected = np.where(run.wall_contact, -1.0, np.where(inside, 10.0, 0.0))
    assert np.array_equal(run.rewards, expected)
    both = inside & run.wall_contact
    assert both.any(), "the run should contain blocked steps inside the zone"
    assert np.all(run.rewards[both] == -1.0)  # a collision overrides the goal reward
    assert set(np.unique(run.rewards)) == {-1.0, 0.0, 10.0}


def test_a_blocked_step_earns_the_wall_reward_and_nothing_else():
    config = SimConfig()
    positions = np.array([[44.0, 44.0], [44.0, 44.0], [5.0, 5.0], [1.0, 5.0]])
    contact = np.array([True, False, False, True])
    rewards, goal = step_reward(config, positions, contact)
    assert list(goal) == [True, True, False, False]
    assert list(rewards) == [-1.0, 10.0, 0.0, -1.0]


def test_execution_noise_is_ten_percent_of_each_component(long_run):
    run = long_run
    moving = run.commands != 0
    relative = (run.executed[moving] - run.commands[moving]) / np.abs(run.commands[moving])
    n = relative.size
    assert abs(relative.mean()) < 4 * 0.1 / np.sqrt(n)
    assert abs(relative.std() - 0.1) < 4 * 0.1 / np.sqrt(2 * n)
    assert np.array_equal(run.executed[~moving], run.commands[~moving])  # no noise at rest
    # the noise really moves the robot: unobstructed displacement equals executed velocity x 1 s
    previous = _previous_positions(run, _start_of(11))
    inside = np.abs(previous + run.executed - L / 2).max(axis=1) < L / 2 - R - 0.1
    free = ~run.wall_contact & inside
    assert np.abs(run.positions[free] - previous[free] - run.executed[free]).max() < 1e-6


def test_all_25_actions_move_the_robot_by_their_command():
    assert ACTIONS.shape == (25, 2)
    assert {tuple(a) for a in ACTIONS} == {(x, y) for x in VELOCITIES for y in VELOCITIES}
    env = RobotEnv(SimConfig(noise_fraction=0.0), seed=0)
    for index, command in enumerate(ACTIONS):
        env.reset(options={"position": (22.5, 22.5)})
        _, reward, *_ , info = env.step(index)
        assert np.allclose(info["position"], np.array([22.5, 22.5]) + command, atol=1e-9)
        assert np.array_equal(info["command"], command)
        assert action_index(*command) == index
        assert reward == 0.0


def test_exploration_is_uniform_over_the_25_actions(long_run):
    counts = np.bincount(long_run.actions, minlength=25)
    expected = len(long_run) / 25
    chi2 = ((counts - expected) ** 2 / expected).sum()
    assert chi2 < 60  # 24 degrees of freedom: p < 1e-4 beyond this


def test_velocity_commands_snap_to_the_nearest_action():
    assert action_index(2.0, -4.4) == action_index(3.0, -3.0)
    assert action_index(100.0, 0.0) == action_index(6.0, 0.0)
    assert list(action_indices(np.array([[0, 0], [-6, 6]]))) == [12, 4]
    with pytest.raises(ConfigError, match="farther than"):
        action_index(4.5, 0.0, tolerance=1.0)
    with pytest.raises(ConfigError, match="not finite"):
        action_index(float("nan"), 0.0)


@pytest.mark.parametrize("environment", ENVIRONMENTS)
def test_same_seed_same_rollout_and_batch_equals_stepping(environment):
    config = SimConfig(environment=environment)

    def step_by_step(seed):
        env = RobotEnv(config, seed=99)
        obs, info = env.reset(seed=seed)
        frames, positions, rewards = [obs], [info["position"]], []
        for _ in range(200):
            obs, reward, terminated, truncated, info = env.step(env.sample_action())
            assert not terminated and not truncated
            frames.append(obs)
            positions.append(info["position"])
            rewards.append(reward)
        return np.array(frames), np.array(positions), np.array(rewards)

    first, second = step_by_step(5), step_by_step(5)
    for a, b in zip(first, second, strict=True):
        assert np.array_equal(a, b)
    other = step_by_step(6)
    assert not np.array_equal(first[1], other[1])
    batch = random_rollout(config, 200, seed=5)
    assert np.array_equal(batch.images, first[0][1:])
    assert np.array_equal(batch.positions, first[1][1:])
    assert np.array_equal(batch.rewards, first[2])


def test_all_environments_follow_the_same_trajectory_for_a_seed():
    runs = [random_rollout(SimConfig(environment=e), 500, seed=3) for e in ENVIRONMENTS]
    for run in runs[1:]:
        assert np.array_equal(run.positions, runs[0].positions)
        assert np.array_equal(run.actions, runs[0].actions)
        assert np.array_equal(run.rewards, runs[0].rewards)
    assert not np.array_equal(runs[0].images, runs[1].images)  # 300 vs 60 degrees


def test_stamps_are_one_second_apart_from_the_start_time():
    config = dataclasses.replace(SimConfig(), start_time_ns=5_000_000_000)
    run = random_rollout(config, 50, seed=0)
    assert run.stamps_ns[0] == 6_000_000_000
    assert np.all(np.diff(run.stamps_ns) == 1_000_000_000)
    env = RobotEnv(config)
    _, info = env.reset()
    assert info["stamp_ns"] == 5_000_000_000
    assert env.step(0)[4]["stamp_ns"] == 6_000_000_000


def test_bad_configuration_and_calls_are_refused():
    with pytest.raises(ConfigError, match="unknown environment 'moon'"):
        SimConfig(environment="moon")
    with pytest.raises(ConfigError, match="field of view"):
        SimConfig(field_of_view_deg=400)
    env = RobotEnv(SimConfig())
    with pytest.raises(ConfigError, match="reset"):
        env.step(0)
    env.reset()
    with pytest.raises(ConfigError, match="action must be"):
        env.step(25)
    with pytest.raises(ConfigError, match="steps must be"):
        random_rollout(SimConfig(), 0, seed=0)
    with pytest.raises(ConfigError, match="seed"):
        RobotEnv(SimConfig(), seed=-1)


@pytest.mark.parametrize("environment", ["distractors", "drive"])
def test_an_environment_that_does_not_render_moves_and_rewards_the_same(environment):
    """Controllers that never look (the floors, the true position) skip the camera: the
    poses, rewards and random streams are those of the rendering simulator."""
    config = SimConfig(environment=environment)
    seen, blind = RobotEnv(config, seed=5), RobotEnv(config, seed=5, render=False)
    for env in (seen, blind):
        env.reset()
    rng = np.random.default_rng(0)
    for _ in range(60):
        action = int(rng.integers(seen.num_actions))
        image, reward, _, _, info = seen.step(action)
        empty, reward_blind, _, _, info_blind = blind.step(action)
        assert reward == reward_blind and np.array_equal(info["pose"], info_blind["pose"])
        assert image.size > 0 and empty.size == 0
