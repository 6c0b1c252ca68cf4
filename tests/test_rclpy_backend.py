"""The rclpy backend against the real rclpy (the ``ros`` extra's ros-jazzy wheels, Fast DDS).

Every test gets a ROS_DOMAIN_ID of its own (pid-derived) and keeps discovery on the loopback
interface (``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``), so parallel runs never cross-talk.
Skipped, with the reason, only where rclpy cannot be imported (no wheels for this Python).
"""

from __future__ import annotations

import subprocess
import sys
import time

import numpy as np
import pytest
from rclpy_support import published_samples, rclpy_node, rosout_qos, spin_all

pytest.importorskip("rclpy", reason="rclpy not importable (pip install 'tpsr-ros[ros]')")

from tpsr_ros.core.errors import MessageError
from tpsr_ros.io import messages as m
from tpsr_ros.io.bag import BagReader, BagWriter
from tpsr_ros.runtime import (
    LATCHED_QOS,
    SENSOR_DATA_QOS,
    Node,
    NodeOptions,
    QoSProfile,
)
from tpsr_ros.runtime.backend import choose_backend
from tpsr_ros.runtime.launcher import Launch
from tpsr_ros.runtime.transport import pad_cdr

pytestmark = pytest.mark.rclpy
S = 10**9


def test_rclpy_is_the_default_backend_when_importable(ros_env):
    assert choose_backend() == ("rclpy", None)
    node = rclpy_node("chosen")
    try:
        assert node.transport.kind == "rclpy"
        assert node.transport.node.get_fully_qualified_name() == "/chosen"
        # the node's own context: rclpy's global context stays uninitialised
        import rclpy

        assert not rclpy.ok()
        assert node.transport.context.ok()
    finally:
        node.close()


def test_messages_travel_as_cdr_bytes_both_ways(ros_env):
    talker, listener = rclpy_node("talker"), rclpy_node("listener")
    try:
        got, raw = [], []
        sub = listener.create_subscription("/camera/image_raw", m.IMAGE_TYPE, got.append)
        listener.create_subscription("/camera/image_raw", m.IMAGE_TYPE, raw.append, raw=True)
        pub = talker.create_publisher("/camera/image_raw", m.IMAGE_TYPE)
        nodes = (talker, listener)
        assert spin_all(
            nodes, lambda: pub.get_subscription_count() == 2 and sub.get_publisher_count() == 1
        )
        image = np.arange(16 * 16 * 3, dtype=np.uint8).reshape(16, 16, 3)
        pub.publish(m.image_msg(3 * S, image))
        assert spin_all(nodes, lambda: got and raw)
        assert np.array_equal(m.image_to_array(got[0]), image)
        assert m.stamp_of(got[0]) == 3 * S
        assert raw[0] == pad_cdr(m.serialize(m.image_msg(3 * S, image), m.IMAGE_TYPE))
    finally:
        talker.close()
        listener.close()


def test_messages_overwritten_in_a_keep_last_reader_are_counted_from_sequence_gaps(ros_env):
    # Fast DDS raises no MESSAGE_LOST for what a reader's own keep-last history overwrote;
    # the gaps in the publisher's sequence numbers show it exactly.
    from rclpy.duration import Duration

    talker, listener = rclpy_node("talker"), rclpy_node("listener")
    try:
        got = []
        sub = listener.create_subscription(
            "/ticks", m.CLOCK_TYPE, lambda x: got.append(x.clock.sec), QoSProfile(depth=1)
        )
        pub = talker.create_publisher("/ticks", m.CLOCK_TYPE, QoSProfile(depth=100))
        nodes = (talker, listener)
        assert spin_all(
            nodes, lambda: pub.get_subscription_count() == 1 and sub.get_publisher_count() == 1
        )
        rclpy_pub = pub._handle.publisher

        def burst(seconds: range) -> None:  # all in the reader's history before it spins
            for sec in seconds:
                pub.publish(m.clock_msg(sec * S))
            assert rclpy_pub.wait_for_all_acked(Duration(seconds=10))

        burst(range(1, 2))
        assert spin_all(nodes, lambda: len(got) == 1)
        burst(range(2, 12))
        assert spin_all(nodes, lambda: len(got) == 2)
        listener.spin(timeout_s=0.1)
        assert got == [1, 11]
        assert sub.get_lost_count() == 9  # 2..10, each overwritten by the next in the history
        burst(range(12, 13))
        assert spin_all(nodes, lambda: len(got) == 3)
        assert sub.get_lost_count() == 9  # no gap, nothing more
    finally:
        talker.close()
        listener.close()


def test_qos_maps_to_rclpy_profiles_and_matching_follows_it(ros_env):
    from rclpy.qos import ReliabilityPolicy

    from tpsr_ros.runtime.rclpy_backend import from_rclpy_qos, to_rclpy_qos

    for profile in (LATCHED_QOS, SENSOR_DATA_QOS, QoSProfile(history="keep_all", depth=0)):
        assert from_rclpy_qos(to_rclpy_qos(profile)) == profile
    qos = to_rclpy_qos(SENSOR_DATA_QOS)
    assert qos.reliability == ReliabilityPolicy.BEST_EFFORT and qos.depth == 5
    a, b = rclpy_node("a"), rclpy_node("b")
    try:
        reliable, best_effort = [], []
        b.create_subscription("/scan", m.CLOCK_TYPE, reliable.append)
        b.create_subscription("/scan", m.CLOCK_TYPE, best_effort.append, SENSOR_DATA_QOS)
        pub = a.create_publisher("/scan", m.CLOCK_TYPE, SENSOR_DATA_QOS)
        assert spin_all((a, b), lambda: pub.get_subscription_count() >= 1)
        for k in range(1, 20):  # best effort: publish until one arrives
            pub.publish(m.clock_msg(k * S))
            if spin_all((a, b), lambda: best_effort, timeout=0.1):
                break
        assert best_effort
        assert reliable == [] and pub.get_subscription_count() == 1
    finally:
        a.close()
        b.close()


def test_latched_messages_reach_a_late_subscriber(ros_env):
    a = rclpy_node("announcer")
    try:
        pub = a.create_publisher("/sim/episode_start", m.POSE_TYPE, LATCHED_QOS)
        pub.publish(m.pose_msg(7 * S, 5.0, 6.0))
        b = rclpy_node("late")
        try:
            got = []
            b.create_subscription("/sim/episode_start", m.POSE_TYPE, got.append, LATCHED_QOS)
            assert spin_all((a, b), lambda: got)
            assert m.pose_to_xy(got[0]) == (5.0, 6.0) and m.stamp_of(got[0]) == 7 * S
        finally:
            b.close()
    finally:
        a.close()


def test_graph_endpoints_with_types_qos_and_node_names(ros_env):
    a = rclpy_node("announcer", Node, "-r", "__ns:=/robot1")
    a.create_publisher("/sim/episode_start", m.POSE_TYPE, LATCHED_QOS)
    b = rclpy_node("observer")
    try:
        def found():  # once the node's name is known too (its ros_discovery_info)
            return [
                e for e in b.transport.publishers()
                if e.topic == "/sim/episode_start" and e.node is not None
            ]

        assert spin_all((a, b), found)
        # rmw_fastrtps reports no history for any publisher (discovery does not carry it)
        unknown_history = QoSProfile(
            LATCHED_QOS.reliability, LATCHED_QOS.durability, history="unknown", depth=0
        )
        assert [(e.msgtype, e.qos, e.node) for e in found()] == [
            (m.POSE_TYPE, unknown_history, "/robot1/announcer")
        ]
    finally:
        a.close()
        b.close()


def test_a_real_rclpy_client_gets_parameters_and_sets_are_checked_like_at_start_up(ros_env):
    """ros2 param get/set against a node: rclpy's parameter services, our validation."""
    from rclpy.parameter import Parameter
    from rclpy.parameter_client import AsyncParameterClient

    from sim_node.node import SimNode

    sim = rclpy_node("sim", SimNode, "-p", "mode:=command", "-p", "seed:=4")
    caller = rclpy_node("param_client")
    try:
        (seed,) = sim.transport.node.describe_parameters(["seed"])
        assert "seed of every random stream" in seed.description
        client = AsyncParameterClient(caller.transport.node, "/sim_node")
        assert spin_all((sim, caller), client.services_are_ready)

        def call(future):
            assert spin_all((sim, caller), future.done)
            return future.result()

        got = call(client.get_parameters(["environment", "seed", "rate"])).values
        assert (got[0].string_value, got[1].integer_value, got[2].double_value) == (
            "full", 4, 10.0
        )
        for parameter, reason in (
            (Parameter("environment", value="moon"), "moon is not one of full, partial"),
            (Parameter("rate", value=0.0), "parameter 'rate' (set): 0.0 must be > 0"),
            (Parameter("seed", value="x"), "type"),  # rclpy's own type check
            (Parameter("environment", value="partial"),
             "fixed at start-up; restart the node with -p environment:=partial"),
        ):
            (result,) = call(client.set_parameters([parameter])).results
            assert not result.successful and reason in result.reason, (parameter, result)
        assert sim.params.environment == "full" and sim.params.seed == 4
        got = call(client.get_parameters(["environment"])).values
        assert got[0].string_value == "full"
        # an integer for a double, as `ros2 param set /sim_node rate 20` sends it
        (result,) = call(client.set_parameters([Parameter("rate", value=20)])).results
        assert result.successful and sim.params.rate == 20.0, result.reason
        # the constraints the node enforces are in the descriptors (ros2 param describe)
        described = call(client.describe_parameters(["environment", "rate", "seed"])).descriptors
        assert [d.additional_constraints for d in described] == [
            "one of: full, partial, distractors, partial-strip, drive", "> 0", ">= 0"
        ]
    finally:
        caller.close()
        sim.close()


def test_close_destroys_the_node_and_shuts_the_context_down(ros_env):
    node = rclpy_node("closing")
    node.create_publisher("/x", m.CLOCK_TYPE)
    transport = node.transport
    node.close()
    assert not transport.context.ok()
    node.close()  # idempotent


def test_conversion_to_and_from_rclpy_messages_goes_through_cdr():
    from geometry_msgs.msg import TwistStamped

    from tpsr_ros.runtime.rclpy_backend import from_rclpy, message_class, to_rclpy

    assert message_class(m.ACTION_TYPE) is TwistStamped
    msg = m.twist_stamped_msg(5 * S, 3.0, -6.0)
    ros_msg = to_rclpy(msg, m.ACTION_TYPE)
    assert isinstance(ros_msg, TwistStamped)
    assert (ros_msg.twist.linear.x, ros_msg.twist.linear.y) == (3.0, -6.0)
    assert ros_msg.header.stamp.sec == 5
    back = from_rclpy(ros_msg, m.ACTION_TYPE)
    assert m.twist_to_xy(back) == (3.0, -6.0) and m.stamp_of(back) == 5 * S
    for bad, why in (
        ("nope_msgs/msg/Nothing", "no message type"),
        ("sensor_msgs/msg/Nothing", "no message type"),
        ("sensor_msgs/Image", "not a message type name"),
    ):
        with pytest.raises(MessageError, match=why):
            message_class(bad)


def test_every_type_we_publish_has_an_rclpy_class_with_the_same_cdr():
    """Each message type of the nodes round-trips through rclpy's own (de)serialiser.

    Compared after decoding: Fast CDR leaves alignment padding uninitialised.
    """
    from rclpy.serialization import deserialize_message

    from tpsr_ros.runtime.diagnostics import DIAGNOSTICS_TYPE
    from tpsr_ros.runtime.rclpy_backend import from_rclpy, message_class

    samples = published_samples()
    assert {t for t, _ in samples} >= {m.IMAGE_TYPE, m.ACTION_TYPE, m.POSE_TYPE,
                                        m.REWARD_TYPE, m.CLOCK_TYPE, m.STATE_TYPE,
                                        m.TWIST_TYPE, DIAGNOSTICS_TYPE}
    for msgtype, msg in samples:
        ours = m.serialize(msg, msgtype)
        theirs = deserialize_message(ours, message_class(msgtype))
        assert m.serialize(from_rclpy(theirs, msgtype), msgtype) == ours, msgtype


def test_sim_node_and_recorder_over_rclpy(ros_env, tmp_path):
    """The integration scenario in one process: sim (explore) -> recorder -> bag."""
    from sim_node.node import SimNode
    from tpsr_ros.record import RecorderNode

    args = RecorderNode.argument_parser("record").parse_args(["-o", str(tmp_path / "bag")])
    recorder = RecorderNode(NodeOptions.for_node(RecorderNode, args=args))
    sim = rclpy_node("sim", SimNode, "-p", "rate:=200", "-p", "steps:=15",
                     "-p", "wait_for_subscribers:=1")
    try:
        assert recorder.transport.kind == sim.transport.kind == "rclpy"
        deadline = time.monotonic() + 30
        while sim.steps_published < 15 and time.monotonic() < deadline:
            sim.spin_once(0.005)
            recorder.spin_once(0.0)
        spin_all((recorder,), lambda: False, timeout=0.3)
    finally:
        sim.close()
        recorder.close()
    with BagReader(tmp_path / "bag") as reader:
        counts = reader.message_counts
        images = [m.stamp_of(x.decode()) for x in reader.messages(["/camera/image_raw"])]
    assert counts["/camera/image_raw"] == counts["/action"] == 15
    assert counts["/clock"] == 16 and counts["/sim/episode_start"] == 1
    assert images == [k * S for k in range(1, 16)]


# -- logging ------------------------------------------------------------------------------

_LOG_EVERY_SEVERITY = """\
import sys
from tpsr_ros.runtime import Node, NodeOptions, parse_ros_args
options = NodeOptions.for_node(Node, parse_ros_args(sys.argv[1:]))
node = Node(options)
assert node.transport.kind == "rclpy", node.transport.kind
for round in (1, 2):  # the same call sites again: rclpy remembers each one's severity
    node.logger.debug(f"debug {round}")
    node.logger.info(f"info {round}")
    node.logger.warning(f"warn {round}")
    node.logger.error(f"error {round}")
    node.logger.fatal(f"fatal {round}")
node.close()
print("done")
"""


@pytest.mark.parametrize(
    "level, shown",
    [
        ("debug", ("DEBUG", "INFO", "WARN", "ERROR", "FATAL")),
        ("warn", ("WARN", "ERROR", "FATAL")),
    ],
)
def test_a_node_logs_at_every_severity_through_rclpy(ros_env, level, shown):
    proc = subprocess.run(
        [sys.executable, "-c", _LOG_EVERY_SEVERITY, "-r", "__node:=talker",
         "--log-level", level],
        capture_output=True, text=True, timeout=60, env=ros_env,
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout == "done\n"
    lines = [x for x in proc.stderr.splitlines() if "[talker]" in x]
    expected = [
        (severity, f"{severity.lower()} {r}")
        for r in (1, 2)
        for severity in ("DEBUG", "INFO", "WARN", "ERROR", "FATAL")
        if severity in shown
    ]
    got = [(x.split("]")[0].lstrip("["), x.split("]: ", 1)[1]) for x in lines]
    assert got == expected


def test_logs_reach_rosout(ros_env):
    from rcl_interfaces.msg import Log

    listener = rclpy_node("rosout_listener")
    try:
        got = []
        sub = listener.transport.node.create_subscription(
            Log, "/rosout", got.append, rosout_qos()
        )
        assert sub is not None
        talker = rclpy_node("talker", Node, "--log-level", "debug")
        try:
            talker.logger.debug("a debug line")
            talker.logger.warning("a warning")

            def seen():
                return {(x.name, x.level, x.msg) for x in got} >= {
                    ("talker", Log.DEBUG, "a debug line"),
                    ("talker", Log.WARN, "a warning"),
                }

            assert spin_all((listener, talker), seen)
        finally:
            talker.close()
    finally:
        listener.close()


# -- every node as a process on rclpy -------------------------------------------------------


@pytest.mark.slow
def test_every_node_runs_on_rclpy_and_the_filter_survives_a_rejected_image(ros_env, tmp_path):
    """Every node as a process on rclpy, started by the runtime launcher.

    A probe node waits on the graph: the simulator's ``/sim/cmd_ignored`` for the end of
    the filter's 3 lockstep steps, the recorder's subscription to a topic it discovers,
    the player's ``/clock``. The warnings the nodes log are what the test then checks.
    """
    from test_filter_node import fit_small_model, random_policy

    model = fit_small_model(tmp_path)
    policy = random_policy(model, tmp_path / "policy.npz")
    bag = tmp_path / "small"
    with BagWriter(bag) as writer:
        writer.add_topic("/clock", m.CLOCK_TYPE)
        writer.write_message("/clock", S, m.clock_msg(S))

    def ros_args(*params: str) -> list[str]:
        args = ["--ros-args", "--log-level", "debug"]
        for p in params:
            args += ["-p", p]
        return args

    probe = rclpy_node("feeder")
    ignored: list[str] = []
    ignored_sub = probe.create_subscription(
        "/sim/cmd_ignored", m.HEADER_TYPE, lambda msg: ignored.append(msg.frame_id)
    )
    clocks: list[int] = []
    probe.create_subscription("/clock", m.CLOCK_TYPE, lambda msg: clocks.append(m.stamp_of(msg)))
    image = probe.create_publisher("/camera/image_raw", m.IMAGE_TYPE)
    reset = probe.create_publisher("/sim/reset", m.POSE_TYPE)
    launch = Launch(tmp_path, env=ros_env, spin=probe.spin_once, timeout_s=60)
    try:
        launch.start("sim_node", "sim_node", ros_args("mode:=command", "episode_steps:=3"))
        # the filter starts only once the probe hears the simulator's announcements
        launch.wait("the simulator's /sim/cmd_ignored to match the probe",
                    lambda: ignored_sub.get_publisher_count() >= 1)
        launch.start("tpsr_filter", "tpsr_ros.filter_node",
                     ros_args(f"model:={model}", f"policy:={policy}"))
        launch.start("recorder", "tpsr_ros.record", ["-o", str(tmp_path / "rec"), *ros_args()])
        launch.start("player", "tpsr_ros.play", [str(bag), "--loop", *ros_args()])
        # the filter drove 3 lockstep steps: the simulator ignores its 4th command
        launch.wait("the simulator to ignore the command after step 3",
                    lambda: "episode_steps" in ignored)
        # the recorder runs its discovery: it subscribes the probe's /sim/reset (as does the
        # simulator); the player plays: more /clock messages than the simulator's 4 (its
        # start-up reset and 3 steps)
        launch.wait("the recorder to subscribe /sim/reset",
                    lambda: reset.get_subscription_count() >= 2)
        launch.wait("the player's /clock", lambda: len(clocks) > 4)
        # after info and debug lines, a warning from each: a wrong-sized image for the
        # filter, a reset outside the room for the simulator; both run on (the warnings,
        # which exist only in the logs, are what is tested here)
        procs = launch.processes
        deadline = time.monotonic() + 30
        while not ("[WARN]" in procs["tpsr_filter"].text()
                   and "[WARN]" in procs["sim_node"].text()):
            assert time.monotonic() < deadline, procs["tpsr_filter"].text()
            image.publish(m.image_msg(S, np.zeros((8, 8, 3), np.uint8)))
            reset.publish(m.pose_msg(S, 100.0, 5.0))
            probe.spin_once(0.1)
    finally:
        probe.close()
        codes = {name: proc.stop(30) for name, proc in launch.processes.items()}
    procs = launch.processes
    logs = {name: proc.text() for name, proc in procs.items()}
    assert codes == dict.fromkeys(procs, 0), logs
    for text in logs.values():
        assert "Traceback" not in text, text
        assert "Logger severity cannot be changed" not in text, text
    assert "[WARN]" in logs["tpsr_filter"] and "/camera/image_raw: " in logs["tpsr_filter"]
    assert "reset rejected: (100.0, 5.0) is outside the room" in logs["sim_node"]
    assert "[INFO]" in logs["recorder"] and "[DEBUG]" in logs["player"]


# -- rclpy <-> our DDS backend ------------------------------------------------------------
