"""The filter node on robot streams (a model learned with --step-period): a replay of a
robot-shaped bag gives exactly the states of offline tracking, in-process and through
`tpsr_ros.play` over real rclpy; commands come from the codebook in the robot's type;
diagnostics report input rates, silence (WARN/STALE) and lost simulator steps."""

from __future__ import annotations

import io
import time

import numpy as np
import pytest
from graph_support import fresh_domain, rclpy_available
from replay_support import replay_states
from test_filter_node import Harness

from learner.cli import main as learner_main
from sim_node.robot_bag import RobotBagConfig, write_robot_bag
from tpsr_ros.core.episodes import track_trajectory
from tpsr_ros.core.errors import ConfigError
from tpsr_ros.core.fqi import QFunction
from tpsr_ros.filter_node import FilterNode
from tpsr_ros.io import messages as m
from tpsr_ros.io.bag import BagReader
from tpsr_ros.io.model_io import load_model, model_fingerprint, model_stream_spec, read_metadata
from tpsr_ros.io.policy import Policy, save_policy
from tpsr_ros.io.streams import read_stream_trajectory
from tpsr_ros.runtime import Node, NodeOptions, QoSProfile, parse_ros_args
from tpsr_ros.runtime.diagnostics import DIAGNOSTICS_TYPE, OK, STALE, WARN
from tpsr_ros.runtime.inproc import InprocBus, InprocTransport

S = 10**9
CAMERA = "/front_camera/image_raw"


@pytest.fixture(scope="module")
def robot(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("robot_filter")
    train, feed = tmp / "train", tmp / "feed"
    write_robot_bag(train, RobotBagConfig(steps=600, seed=7))
    write_robot_bag(feed, RobotBagConfig(steps=40, seed=9))
    model = tmp / "model.npz"
    argv = ["fit", str(train), "--image-topic", CAMERA, "--action-topic", "/cmd_vel",
            "--step-period", "1", "--image-size", "8", "--actions", "9",
            "--obs-centers", "40", "--ht-centers", "80", "--rank", "3", "-o", str(model)]
    assert learner_main(argv) == 0
    with BagReader(feed) as reader:
        inputs = [(x.topic, x.data) for x in reader.messages([CAMERA, "/cmd_vel"])]
    return {"tmp": tmp, "model": model, "feed": feed, "inputs": inputs, "argv": argv}


def codebook_policy(model_path, out):
    """A greedy policy with random Q weights over the model's states and its K actions."""
    model = load_model(model_path)
    r, k = model.state_dim, model.n_actions
    rng = np.random.default_rng(0)
    q = QFunction(np.zeros(r), np.ones(r), rng.normal(size=(8, r)), 1.0, rng.normal(size=(8, k)))
    save_policy(Policy(q, "tpsr", model_fingerprint(model), None), out)
    return out


def offline(robot) -> dict[int, np.ndarray]:
    """Stamp -> state of `learner plot`'s tracking of the feed bag."""
    spec = model_stream_spec(robot["model"], read_metadata(robot["model"]))
    trajectory = read_stream_trajectory([robot["feed"]], spec)
    track = track_trajectory(load_model(robot["model"]), trajectory)
    return {int(s): track.states[i] for i, s in enumerate(trajectory.stamps)}


class RobotFeed:
    """A filter node for the robot model, and a feeder with the bag's own topics and types."""

    def __init__(self, model, *params: str, policy=None) -> None:
        self.bus = InprocBus()
        self.feeder = Node(NodeOptions(name="feeder"), transport=InprocTransport("/f", self.bus))
        self.pubs = {CAMERA: self.feeder.create_publisher(CAMERA, m.IMAGE_TYPE)}
        if policy is None:
            self.pubs["/cmd_vel"] = self.feeder.create_publisher("/cmd_vel", m.TWIST_TYPE)
        self.states: list = []
        self.commands: list = []
        self.diagnostics: list = []
        self.feeder.create_subscription(
            "/tpsr/state", m.STATE_TYPE,
            lambda x: self.states.append((m.stamp_of(x), m.state_to_array(x))),
        )
        self.feeder.create_subscription(
            "/diagnostics", DIAGNOSTICS_TYPE, lambda x: self.diagnostics.append(x)
        )
        args = ["-p", f"model:={model}"]
        if policy is not None:
            args += ["-p", f"policy:={policy}", "-p", "command_type:=twist_stamped"]
            self.feeder.create_subscription(
                "/cmd_vel", m.ACTION_TYPE, lambda x: self.commands.append(x)
            )
        for p in params:
            args += ["-p", p]
        options = NodeOptions.for_node(FilterNode, parse_ros_args(args))
        self.node = FilterNode(options, transport=InprocTransport("/tpsr_filter", self.bus))
        self.node.logger.stream = io.StringIO()
        if policy is not None:
            deadline = time.monotonic() + 10
            while not self.node.commands_ready and time.monotonic() < deadline:
                self.node.spin_once(0.01)
                self.feeder.spin_once(0.0)

    def send(self, topic: str, data: bytes) -> None:
        self.pubs[topic].publish_raw(data)
        self.node.spin_once(0.0)
        self.feeder.spin_once(0.0)

    def status(self):
        self.node.publish_diagnostics()
        self.feeder.spin_once(0.0)
        return self.diagnostics[-1].status[0]

    def close(self) -> None:
        self.node.close()
        self.feeder.close()


@pytest.mark.slow
def test_a_replayed_robot_bag_gives_the_offline_states(robot):
    feed = RobotFeed(robot["model"])
    try:
        assert feed.node.image_topic == CAMERA and feed.node.action_topic == "/cmd_vel"
        for topic, data in robot["inputs"]:
            feed.send(topic, data)
        expected = offline(robot)
        assert len(expected) == 38
        assert [s for s, _ in feed.states] == sorted(expected)
        for stamp, state in feed.states:
            assert np.array_equal(state, expected[stamp]), stamp
        values = feed.node.diagnostics_values()
        assert values["steps"] == 38 and values["command_gaps"] == 1  # before the 1st command
        book = feed.node.spec.codebook  # 9 codes for 25 pairs: many commands are far
        commands = np.array([
            m.twist_components(m.deserialize(d, m.TWIST_TYPE), book.components)
            for t, d in robot["inputs"] if t == "/cmd_vel"
        ])
        far = int((book.assign(commands)[1] > book.far_distance).sum())
        assert values["camera_gaps"] == 0 and values["far_commands"] == far > 0
        assert values["image_topic"] == CAMERA and values["image_rate_hz"] > 0
    finally:
        feed.close()


def test_a_bad_image_loses_the_steps_that_hold_it_and_only_those(robot):
    # Images are downsampled on arrival; one that cannot be decoded stays on the grid as
    # a hole, so each step holding it is rejected (counted) and the others are untouched.
    expected = offline(robot)
    feed = RobotFeed(robot["model"])
    bad = range(20, 24)  # a second of a 4 Hz camera: some step holds one of them
    try:
        images = 0
        for topic, data in robot["inputs"]:
            if topic == CAMERA:
                images += 1
                if images in bad:
                    msg = m.deserialize(data, m.IMAGE_TYPE)
                    msg.encoding = "yuv422"
                    data = m.serialize(msg, m.IMAGE_TYPE)
            feed.send(topic, data)
        values = feed.node.diagnostics_values()
        lost = len(expected) - len(feed.states)
        assert lost >= 1 and values["rejected_encoding"] == lost
        assert feed.node.ok()
        for stamp, state in feed.states:  # the others as offline, until the hole
            if stamp < min(set(expected) - {s for s, _ in feed.states}):
                assert np.array_equal(state, expected[stamp]), stamp
    finally:
        feed.close()


@pytest.mark.slow
def test_with_a_policy_commands_are_codes_in_the_robots_type(robot, tmp_path):
    # a robot whose commands come in on /teleop: the node's own go out on cmd_vel
    bag = tmp_path / "teleop"
    write_robot_bag(bag, RobotBagConfig(steps=600, seed=7, command_topic="/teleop"))
    model = tmp_path / "teleop.npz"
    argv = [a if a != "/cmd_vel" else "/teleop" for a in robot["argv"]]
    argv[1], argv[-1] = str(bag), str(model)
    assert learner_main(argv) == 0
    policy = codebook_policy(model, tmp_path / "policy.npz")
    feed = RobotFeed(model, policy=policy)
    try:
        teleop = feed.feeder.create_publisher("/teleop", m.TWIST_TYPE)
        feed.pubs["/teleop"] = teleop
        for topic, data in robot["inputs"]:
            feed.send("/teleop" if topic == "/cmd_vel" else topic, data)
        codes = {tuple(code) for code in feed.node.spec.codebook.codes.tolist()}
        states = {s for s, _ in feed.states}
        assert len(states) == 38 and len(feed.commands) == 38
        for command in feed.commands:  # TwistStamped with the step's stamp, one of the codes
            assert (command.twist.linear.x, command.twist.linear.y) in codes
            assert command.twist.angular.z == 0.0 and m.stamp_of(command) in states
    finally:
        feed.close()
    with pytest.raises(ConfigError, match="both /cmd_vel, but of types"):
        RobotFeed(robot["model"], policy=codebook_policy(robot["model"], tmp_path / "p2.npz"))


def test_camera_images_missing_from_the_stamps_count_as_lost(robot):
    # lost on the way without a word from the middleware (Cyclone's keep-last overwrites)
    images = [k for k, (topic, _) in enumerate(robot["inputs"]) if topic == CAMERA]
    skipped = set(images[60:63])
    feed = RobotFeed(robot["model"])
    try:
        for k, (topic, data) in enumerate(robot["inputs"]):
            if k not in skipped:
                feed.send(topic, data)
        assert feed.node.diagnostics_values()["lost_images"] == 3
    finally:
        feed.close()


def test_a_clock_jump_back_restarts_the_grid_and_the_state(robot):
    feed = RobotFeed(robot["model"])
    feed.pubs["/clock"] = feed.feeder.create_publisher("/clock", m.CLOCK_TYPE)
    try:
        for topic, data in robot["inputs"][: len(robot["inputs"]) // 2]:
            feed.send(topic, data)
        newest, reinits = feed.node.grid.last_image_time, feed.node.tracker.reinits
        assert newest is not None
        clock = m.serialize(m.clock_msg(newest - 4 * S), m.CLOCK_TYPE)  # within 5 s: no jump
        feed.send("/clock", clock)
        assert feed.node.diagnostics_values()["time_jumps"] == 0
        feed.send("/clock", m.serialize(m.clock_msg(newest - 6 * S), m.CLOCK_TYPE))
        assert feed.node.diagnostics_values()["time_jumps"] == 1
        assert feed.node.grid.last_image_time is None
        assert feed.node.tracker.reinits == reinits + 1
        np.testing.assert_array_equal(feed.node.tracker.state, feed.node.model.initial_state())
    finally:
        feed.close()


def test_a_simulator_model_cannot_take_its_own_commands_as_executed_actions(tmp_path):
    from test_filter_node import fit_small_model, random_policy

    model = fit_small_model(tmp_path)
    policy = random_policy(model, tmp_path / "policy.npz")
    args = ["-p", f"model:={model}", "-p", f"policy:={policy}",
            "-p", "command_type:=twist_stamped", "-p", "check_topics:=false",
            "-r", "/action:=/cmd_vel"]  # fmt: skip
    options = NodeOptions.for_node(FilterNode, parse_ros_args(args))
    with pytest.raises(ConfigError, match="action the simulator executed for that step"):
        FilterNode(options, transport=InprocTransport("/f", InprocBus()))


def test_silence_makes_diagnostics_warn_then_stale(robot):
    feed = RobotFeed(robot["model"], "input_timeout:=0.3")
    clock = [100.0]  # the health ledger's clock, moved by hand: no race with sleeps
    feed.node.health.clock = lambda: clock[0]
    try:
        assert feed.status().message == "waiting for paired images and actions"
        for topic, data in robot["inputs"][:60]:
            feed.send(topic, data)
        assert feed.status().level in (OK, WARN)  # WARN: far commands (9 codes, 25 pairs)
        clock[0] += 0.4
        images = [d for t, d in robot["inputs"][60:] if t == CAMERA]
        feed.send(CAMERA, images[0])  # the camera goes on, the commands have stopped
        status = feed.status()
        assert status.level == WARN and status.message.startswith("/cmd_vel silent for 0.4")
        clock[0] += 0.4
        status = feed.status()
        assert status.level == STALE and "inputs silent for" in status.message
    finally:
        feed.close()


def test_lost_simulator_steps_are_counted_from_stamp_gaps(tmp_path):
    from test_filter_node import fit_small_model

    from sim_node import SimConfig
    from sim_node.generate import generate_bag

    model = fit_small_model(tmp_path, steps=600)
    bag = tmp_path / "burst"
    generate_bag(bag, SimConfig(environment="full"), 12, seed=1)
    with BagReader(bag) as reader:
        msgs = {(x.topic, m.stamp_of(x.decode())): x.decode()
                for x in reader.messages(["/camera/image_raw", "/action"])}
    h = Harness(model)
    try:
        for k in [3, 4, 7, 8, 12]:  # lost: 1, 2 (steps are k s after 0), 5, 6, 9, 10, 11
            h.step({k * S: msgs[("/camera/image_raw", k * S)]},
                   {k * S: msgs[("/action", k * S)]}, k * S)
        values = h.values()
        assert values["lost_images"] == 7 and values["lost_actions"] == 7
        h.node.publish_diagnostics()
        h.feeder.spin_once(0.0)
        status = h.diagnostics[-1].status[0]
        assert status.level == WARN and "lost_images" in status.message
    finally:
        h.close()
    # 50 steps published without pacing; the subscription keeps the last 10
    burst = tmp_path / "burst50"
    generate_bag(burst, SimConfig(environment="full"), 50, seed=1)
    with BagReader(burst) as reader:
        inputs = [(x.topic, x.decode()) for x in reader.messages(["/camera/image_raw", "/action"])]
    h = Harness(model)
    try:
        for topic, msg in inputs:
            h.pubs[topic].publish(msg)  # nobody spins in between
        for _ in range(100):
            h.node.spin_once(0.0)
        values = h.values()
        assert values["steps"] + values["lost_images"] == 50 and values["steps"] < 50
        h.node.publish_diagnostics()
        h.feeder.spin_once(0.0)
        assert h.diagnostics[-1].status[0].level == WARN
    finally:
        h.close()


@pytest.mark.slow
@pytest.mark.rclpy
@pytest.mark.skipif(not rclpy_available(), reason="rclpy (ROS 2) not importable")
def test_the_node_tracks_a_play_replay_over_rclpy_like_offline(robot, tmp_path, monkeypatch):
    monkeypatch.setenv("ROS_DOMAIN_ID", str(fresh_domain(16)))
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    monkeypatch.setenv("TPSR_TRANSPORT", "rclpy")
    monkeypatch.setenv("PYTHONUNBUFFERED", "1")
    expected = offline(robot)
    states, _ = replay_states(
        robot["model"], robot["feed"], [CAMERA, "/cmd_vel"], "8", len(expected), tmp_path
    )
    assert [s for s, _ in states] == sorted(expected)
    for stamp, state in states:
        assert np.array_equal(state, expected[stamp]), stamp


@pytest.mark.rclpy
@pytest.mark.skipif(not rclpy_available(), reason="rclpy (ROS 2) not importable")
def test_camera_images_the_middleware_overwrote_are_counted_as_lost(robot, monkeypatch):
    # Robot images carry no step numbers; the loss comes from the middleware: the image
    # subscription keeps the last 10, so 25 images sent while the node is busy lose 15.
    from rclpy.duration import Duration

    from tpsr_ros.runtime.rclpy_backend import RclpyTransport

    monkeypatch.setenv("ROS_DOMAIN_ID", str(fresh_domain(19)))
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    camera = Node(NodeOptions(name="camera"), transport=RclpyTransport("camera"))
    pub = camera.create_publisher(CAMERA, m.IMAGE_TYPE, QoSProfile(depth=100))
    options = NodeOptions.for_node(FilterNode, parse_ros_args(["-p", f"model:={robot['model']}"]))
    node = FilterNode(options, transport=RclpyTransport("tpsr_filter"))
    node.logger.stream = io.StringIO()
    images = [data for topic, data in robot["inputs"] if topic == CAMERA][:26]

    def send(batch: list[bytes]) -> None:  # in the node's reader before it spins
        for data in batch:
            pub.publish_raw(data)
        assert pub._handle.publisher.wait_for_all_acked(Duration(seconds=10))

    try:
        assert node.wait_for(lambda: pub.get_subscription_count() == 1, 10)
        send(images[:1])
        assert node.wait_for(lambda: node.diagnostics_values()["image_age_s"] != "never", 10)
        send(images[1:])
        node.spin(timeout_s=0.3)
        assert node.grid is not None and node.grid.stepper.images == 11  # the first, the last 10
        values = node.diagnostics_values()
        assert values["lost_images"] == 15 and values["lost_actions"] == 0
        level, message = node.health_status()
        assert level == WARN and "lost_images" in message
    finally:
        node.close()
        camera.close()
