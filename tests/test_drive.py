"""The ``drive`` environment: a robot that turns, checked against geometry and ground truth."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest
from test_sim_node import Probe, spin_both, start_sim

from sim_node import RobotEnv, SimConfig, random_rollout
from sim_node.camera import Camera
from sim_node.generate import generate_bag
from sim_node.robot_bag import RobotBagConfig, write_robot_bag
from sim_node.world import RoomWorld
from tpsr_ros.core.actions import DRIVE_SPEEDS, PLANAR, drive_grid
from tpsr_ros.core.codebook import sim_codebook
from tpsr_ros.core.errors import ConfigError
from tpsr_ros.filter_node.inputs import Rejected, simulator_action
from tpsr_ros.io import messages as m
from tpsr_ros.io.streams import FitOptions, fit_stream_spec, read_stream_trajectory
from tpsr_ros.io.trajectory import read_trajectory
from tpsr_ros.runtime.inproc import InprocBus

DRIVE = SimConfig(environment="drive")


def test_drive_actions_are_speed_and_turn_rate_pairs():
    grid = drive_grid()
    assert grid.components == ("linear.x", "angular.z") and len(grid) == 9
    assert sorted(set(grid.codes[:, 0])) == list(DRIVE_SPEEDS)
    np.testing.assert_allclose(sorted(set(grid.codes[:, 1])), np.radians([-45, 0, 45]))
    # every code maps back to itself, and a nearby command to the nearest code
    np.testing.assert_array_equal(grid.indices(grid.codes), np.arange(9))
    assert grid.indices(np.array([[2.6, 0.7]]))[0] == 8
    assert DRIVE.actions.components == ("linear.x", "angular.z")
    assert SimConfig().actions is PLANAR


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"turn_rate_deg": 0.0}, "turn rate must be in"),
        ({"turn_rate_deg": 120.0}, "turn rate must be in"),
        ({"field_of_view_deg": 0.0}, "field of view must be in"),
        ({"field_of_view_deg": 400.0}, "field of view must be in"),
    ],
)
def test_a_turn_rate_or_field_of_view_out_of_range_is_refused(kwargs, message):
    with pytest.raises(ConfigError, match=message):
        SimConfig(environment="drive", **kwargs)


@pytest.mark.parametrize("option", [["--turn-rate", "200"], ["--field-of-view", "0"]])
def test_the_generators_refuse_them_in_one_line(tmp_path, option):
    done = subprocess.run(
        [sys.executable, "-m", "sim_node.robot_bag", "--environment", "drive", *option,
         "-o", str(tmp_path / "bag")],
        capture_output=True, text=True, check=False,
    )  # fmt: skip
    assert done.returncode == 2 and not (tmp_path / "bag").exists()
    assert len(done.stderr.strip().splitlines()) == 1 and "must be in" in done.stderr


def test_the_robot_drives_along_its_heading_and_turns_at_the_commanded_rate():
    world = RoomWorld(45.0, 1.0, 10)
    world.place(20.0, 20.0, math.radians(30))
    assert not world.drive(3.0, 0.0, 1.0)
    np.testing.assert_allclose(
        world.position, [20 + 3 * math.cos(math.radians(30)), 20 + 3 * math.sin(math.radians(30))]
    )
    world.place(20.0, 20.0, 0.0)
    world.drive(0.0, math.radians(45), 1.0)  # turning in place does not move
    np.testing.assert_allclose(world.position, [20.0, 20.0])
    assert world.heading == pytest.approx(math.radians(45))
    # a step of constant speed and turn rate follows its arc: the chord of radius v / w
    world.place(20.0, 20.0, 0.0)
    speed, rate = 3.0, math.radians(45)
    world.drive(speed, rate, 1.0)
    radius = speed / rate
    np.testing.assert_allclose(
        world.position, [20 + radius * math.sin(rate), 20 + radius * (1 - math.cos(rate))],
        atol=1e-9,
    )  # fmt: skip


def test_a_wall_blocks_the_drive_and_counts_as_contact():
    world = RoomWorld(45.0, 1.0, 10)
    world.place(43.5, 20.0, 0.0)  # facing east, half a metre from the wall
    assert world.drive(3.0, 0.0, 1.0)
    assert world.position[0] <= 44.0 + 1e-3  # pymunk's collision slop: 1e-4 m


def test_the_camera_turns_with_the_robot():
    positions = np.array([[10.0, 20.0], [30.0, 5.0]])
    north = Camera(SimConfig()).render(positions)
    np.testing.assert_array_equal(
        Camera(DRIVE).render(positions, headings=np.full(2, np.pi / 2)), north
    )
    # a full circle of 16 columns: turning by four columns' angle shifts the image by four
    camera = Camera(SimConfig(environment="drive", field_of_view_deg=360))
    east = camera.render(positions, headings=np.zeros(2))
    turned = camera.render(positions, headings=np.full(2, 2 * np.pi * 4 / 16))
    np.testing.assert_array_equal(np.roll(east, 4, axis=2), turned)


def test_env_and_batch_rollout_agree_and_report_the_pose():
    run = random_rollout(DRIVE, 200, seed=3)
    env = RobotEnv(DRIVE, seed=3)
    _, info = env.reset()
    assert info["pose"].shape == (4,)
    for k in range(200):
        image, _, _, _, info = env.step(int(run.actions[k]))
        np.testing.assert_array_equal(image, run.images[k])
        np.testing.assert_array_equal(info["pose"], run.poses[k])
    assert np.ptp(run.headings) > 1.0  # it turned
    np.testing.assert_allclose(run.poses[:, 2:], np.c_[np.cos(run.headings), np.sin(run.headings)])
    assert len(np.unique(run.actions)) == 9
    with pytest.raises(ConfigError, match=r"\[0, 9\)"):
        env.step(9)
    with pytest.raises(ConfigError, match="cannot turn"):
        RobotEnv(SimConfig()).reset(options={"position": (5.0, 5.0), "heading": 0.0})


def test_a_generated_drive_bag_reads_back_as_its_rollout(tmp_path):
    generate_bag(tmp_path / "bag", DRIVE, 300, seed=4)
    run = random_rollout(DRIVE, 300, seed=4)
    trajectory = read_trajectory([tmp_path / "bag"])
    assert trajectory.n_actions == 9
    np.testing.assert_array_equal(trajectory.actions, run.actions)
    np.testing.assert_array_equal(trajectory.velocities, run.commands)
    np.testing.assert_allclose(trajectory.positions, run.poses, atol=1e-12)


def test_a_drive_robot_bag_codebook_finds_the_9_commands_and_odometry_the_heading(tmp_path):
    config = RobotBagConfig(steps=400, seed=2, environment="drive", timeline="step-start")
    write_robot_bag(tmp_path / "bag", config)
    bags = [tmp_path / "bag"]
    spec = fit_stream_spec(
        bags, FitOptions(step_period=1.0, actions=9), image_topic="/front_camera/image_raw",
        action_topic="/cmd_vel",
    )  # fmt: skip
    trajectory = read_stream_trajectory(bags, spec, pose_topic="/odom")
    assert spec.codebook.components == ("linear.x", "angular.z")
    assert len(spec.codebook) == 9
    nearest, distance = spec.codebook.assign(drive_grid().codes)
    assert len(set(nearest.tolist())) == 9 and distance.max() < 0.1  # one code per command
    assert trajectory.positions.shape[1] == 4
    known = np.isfinite(trajectory.positions).all(axis=1)
    run = random_rollout(config.sim_config(), 400, seed=2)
    # the robot's path: step k ends at k s after the run's start (100 s into the bag)
    at = (trajectory.stamps[known] - 100 * 10**9) / 1e9
    ends = np.arange(1, 401)
    heading = np.interp(at, ends, np.unwrap(run.headings))
    truth = np.c_[
        np.interp(at, ends, run.positions[:, 0]), np.interp(at, ends, run.positions[:, 1]),
        np.cos(heading), np.sin(heading),
    ]  # fmt: skip
    assert known.sum() > 390
    np.testing.assert_allclose(trajectory.positions[known, :2], truth[:, :2], atol=1e-6)
    # cos and sin are interpolated between 4 Hz samples, at most 11 degrees apart
    np.testing.assert_allclose(trajectory.positions[known, 2:], truth[:, 2:], atol=0.01)


def test_the_sim_codebook_of_drive_and_the_filter_nodes_mapping():
    book = sim_codebook("drive")
    assert book.kind == "sim" and len(book) == 9
    assert book.assign(np.array([[1.4, -0.8]]))[0].tolist() == [3]
    msg = m.stamped_twist(5, m.twist_from_components({"linear.x": 3.0, "angular.z": -0.78}))
    assert simulator_action(msg, "", {}, drive_grid()) == 6
    far = m.stamped_twist(5, m.twist_from_components({"linear.x": 3.0, "angular.z": 9.0}))
    with pytest.raises(Rejected, match="farther than"):
        simulator_action(far, "", {}, drive_grid())


def test_sim_node_drive_takes_twist_turns_and_publishes_the_heading():
    bus = InprocBus()
    probe = Probe(bus)
    sim = start_sim(bus, "-p", "environment:=drive", "-p", "mode:=command", "-p", "seed:=1")
    assert spin_both(sim, probe, lambda: len(probe.got["/sim/episode_start"]) == 1)
    heading = math.radians(90)
    probe.reset.publish(m.pose_msg(0, 20.0, 20.0, heading=heading))
    assert spin_both(sim, probe, lambda: len(probe.got["/sim/episode_start"]) == 2)
    start = probe.got["/sim/episode_start"][-1]
    assert m.pose_to_planar(start)[2:] == pytest.approx((0.0, 1.0), abs=1e-12)
    for _ in range(2):  # turn left twice at 45 degrees: west
        probe.cmd.publish(m.twist_from_components({"angular.z": math.radians(45)}))
        count = len(probe.got["/reward"])
        assert spin_both(sim, probe, lambda c=count: len(probe.got["/reward"]) == c + 1)
    action = probe.got["/action"][-1]
    assert m.twist_components(action, ("linear.x", "angular.z")).tolist() == pytest.approx(
        [0.0, math.radians(45)]
    )
    pose = m.pose_to_planar(probe.got["/ground_truth/pose"][-1])
    assert pose[:2] == pytest.approx((20.0, 20.0))
    assert pose[2] < -0.95  # facing west, give or take the turn rate's 10 % noise
    probe.cmd.publish(m.twist_from_components({"angular.z": 3.0}))  # 172 deg/s: refused
    sim.spin(timeout_s=0.05)
    probe.node.spin_once(0.0)
    assert sim.steps_published == 2
    sim.close()


@pytest.mark.slow
def test_fit_policy_and_closed_loop_on_drive_bags(tmp_path, monkeypatch, capsys):
    """A drive model gets the turning robot's settings, and its closed loop over the nodes
    scores exactly what the headless evaluation scores (three starts, ten steps)."""
    pytest.importorskip("cyclonedds")
    from graph_support import LOOPBACK, fresh_domain

    from learner.cli import main as learner_main
    from learner.closed_loop import run_closed_loop
    from learner.evaluate import START_POSITIONS, evaluate
    from learner.representations import load_tracker
    from tpsr_ros.io.model_io import open_model
    from tpsr_ros.io.policy import load_policy

    generate_bag(tmp_path / "train", DRIVE, 3000, seed=0)
    generate_bag(tmp_path / "rl", DRIVE, 1000, seed=1)  # a policy to run, not a good one
    model, policy = tmp_path / "model.npz", tmp_path / "policy.npz"
    small = ["--obs-centers", "60", "--ht-centers", "120"]
    assert learner_main(["fit", str(tmp_path / "train"), "-o", str(model), *small]) == 0
    said = capsys.readouterr().err
    turning = "ht_dim=20 rank=16 action_pooling=0.5 refine_carry=0.0 obs_effective_centres=2.0"
    assert f"with its turning robot's settings ({turning})" in said
    opened = open_model(model)
    config = opened.model.config
    assert (config.rank, config.ht_dim, config.action_pooling) == (16, 20, 0.5)
    assert opened.environment == "drive" and opened.model.n_actions == 9
    assert opened.metadata["preset"]["turning"] is True
    assert learner_main(["policy", str(model), str(tmp_path / "rl"), "-o", str(policy)]) == 0
    starts, steps = START_POSITIONS[:3], 10
    tracker, seen = load_tracker(model), []

    class Recording:  # the headless run's states after every step, in order
        representation, fingerprint = tracker.representation, tracker.fingerprint
        start = tracker.start

        def step(self, *args):
            seen.append(tracker.step(*args))
            return seen[-1]

    headless = evaluate(load_policy(policy), Recording(), "drive", starts=starts, steps=steps)
    monkeypatch.setenv("CYCLONEDDS_URI", LOOPBACK)
    result = run_closed_loop(
        policy, "drive", model_path=model, starts=starts, steps=steps, transport="dds",
        domain_id=fresh_domain(),
    )  # fmt: skip
    assert result.evaluation == headless
    # the states the filter node published are the headless ones: the nodes turned the
    # robot to each start's heading and executed (speed, turn rate) commands alike
    published = [result.states[stamp] for stamp in sorted(result.states)]
    assert len(published) == len(seen) == 30
    assert max(np.abs(a - b).max() for a, b in zip(published, seen, strict=True)) <= 1e-9


def test_learner_track_writes_the_heading_columns_of_a_robot_that_turns(tmp_path):
    from learner.track import write_states

    stamps = np.arange(3, dtype=np.int64)
    states, recovered = np.zeros((3, 2)), np.zeros(3, dtype=bool)
    poses = random_rollout(DRIVE, 3, seed=0).poses
    write_states(tmp_path / "s.csv", stamps, states, recovered, poses)
    lines = (tmp_path / "s.csv").read_text().splitlines()
    assert lines[0] == "stamp_ns,b0,b1,x,y,cos_heading,sin_heading"
    np.testing.assert_array_equal(np.loadtxt(tmp_path / "s.csv", delimiter=",", skiprows=1)[:, 3:],
                                  poses)  # fmt: skip


def test_a_recording_without_its_environment_reads_with_the_models(tmp_path):
    """A recorder's bag of sim_node in drive names no environment: the model's says it."""
    from sim_node.batch_cdr import chunk_payloads
    from sim_node.topics import SimTopics
    from tpsr_ros.core.errors import DataError
    from tpsr_ros.io.bag import BagWriter

    run = random_rollout(DRIVE, 200, seed=6)
    topics = SimTopics()
    payloads = chunk_payloads(topics, run, DRIVE)
    with BagWriter(tmp_path / "recorded") as writer:  # no custom data, as the recorder writes
        for topic, msgtype in topics.types().items():
            writer.add_topic(topic, msgtype)
        for i, stamp in enumerate(run.stamps_ns.tolist()):
            for topic in topics.types():
                writer.write(topic, stamp, payloads[topic][i])
    trajectory = read_trajectory([tmp_path / "recorded"], environment="drive")
    np.testing.assert_array_equal(trajectory.actions, run.actions)
    assert trajectory.positions.shape == (200, 4)
    with pytest.raises(DataError, match="farther than"):  # as planar: 1.5 m/s is no action
        read_trajectory([tmp_path / "recorded"])
    generate_bag(tmp_path / "full", SimConfig(), 50, seed=1)
    with pytest.raises(DataError, match="comes from environment 'full'"):
        read_trajectory([tmp_path / "full"], environment="drive")
