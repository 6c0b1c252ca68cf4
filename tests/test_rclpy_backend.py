"""The rclpy backend against a fake of rclpy's documented Jazzy API (tests/fake_rclpy.py).

The same code path runs against the real rclpy in tests/test_record_play.py wherever
ROS 2 is installed (those tests skip cleanly where it is not).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
import fake_rclpy

from tpsr_ros.io import messages as m
from tpsr_ros.io.bag import BagReader
from tpsr_ros.runtime import (
    LATCHED_QOS,
    SENSOR_DATA_QOS,
    Node,
    NodeOptions,
    QoSProfile,
    parse_ros_args,
)
from tpsr_ros.runtime.backend import choose_backend
from tpsr_ros.runtime.transport import pad_cdr


@pytest.fixture
def rclpy(monkeypatch):
    fake = fake_rclpy.install(monkeypatch)
    monkeypatch.delenv("TPSR_TRANSPORT", raising=False)
    return fake


def rclpy_node(name: str, node_cls=Node, *ros_args: str, **kwargs):
    options = NodeOptions.for_node(node_cls, parse_ros_args(list(ros_args)), **kwargs)
    if node_cls is Node:
        options = NodeOptions(name=name, ros_args=options.ros_args,
                              log_level=options.log_level)
    return node_cls(options)  # the transport comes from choose_backend -> rclpy


def test_rclpy_is_chosen_when_importable(rclpy):
    assert choose_backend() == ("rclpy", None)
    node = rclpy_node("chosen")
    assert node.transport.kind == "rclpy"
    # our own signal handlers stay: rclpy.init is told not to install any
    assert rclpy.INIT_CALLS[-1]["signal_handler_options"] == fake_rclpy.SignalHandlerOptions.NO
    assert rclpy.INIT_CALLS[-1]["args"] == []
    node.close()


def test_messages_travel_as_cdr_bytes_both_ways(rclpy):
    talker, listener = rclpy_node("talker"), rclpy_node("listener")
    got, raw = [], []
    sub = listener.create_subscription("/camera/image_raw", m.IMAGE_TYPE, got.append)
    listener.create_subscription("/camera/image_raw", m.IMAGE_TYPE, raw.append, raw=True)
    pub = talker.create_publisher("/camera/image_raw", m.IMAGE_TYPE)
    assert pub.get_subscription_count() == 2 and sub.get_publisher_count() == 1
    image = np.full((16, 16, 3), 7, dtype=np.uint8)
    pub.publish(m.image_msg(3 * 10**9, image))
    assert listener.wait_for(lambda: got and raw, 2)
    assert np.array_equal(m.image_to_array(got[0]), image)
    assert raw[0] == pad_cdr(m.serialize(m.image_msg(3 * 10**9, image), m.IMAGE_TYPE))
    talker.close()
    listener.close()


def test_qos_maps_to_rclpy_profiles_and_matching_follows_it(rclpy):
    from tpsr_ros.runtime.rclpy_backend import from_rclpy_qos, to_rclpy_qos

    for profile in (LATCHED_QOS, SENSOR_DATA_QOS, QoSProfile(history="keep_all", depth=0)):
        assert from_rclpy_qos(to_rclpy_qos(profile)) == profile
    qos = to_rclpy_qos(SENSOR_DATA_QOS)
    assert qos.reliability == fake_rclpy.ReliabilityPolicy.BEST_EFFORT and qos.depth == 5
    a, b = rclpy_node("a"), rclpy_node("b")
    reliable = []
    b.create_subscription("/scan", m.CLOCK_TYPE, reliable.append)
    pub = a.create_publisher("/scan", m.CLOCK_TYPE, SENSOR_DATA_QOS)
    pub.publish(m.clock_msg(1))
    b.spin(timeout_s=0.05)
    assert reliable == [] and pub.get_subscription_count() == 0
    a.close()
    b.close()


def test_graph_endpoints_with_types_qos_and_node_names(rclpy):
    a = rclpy_node("announcer")
    a.create_publisher("/sim/episode_start", m.POSE_TYPE, LATCHED_QOS)
    b = rclpy_node("observer")
    found = [e for e in b.transport.publishers() if e.topic == "/sim/episode_start"]
    assert [(e.msgtype, e.qos, e.node) for e in found] == [
        (m.POSE_TYPE, LATCHED_QOS, "/announcer")
    ]
    a.close()
    b.close()


def test_parameters_are_declared_read_only_with_their_help(rclpy):
    from sim_node.node import SimNode

    sim = rclpy_node("sim", SimNode, "-p", "mode:=command", "-p", "seed:=4")
    params = sim.transport.node.parameters
    assert params["seed"].value == 4 and params["mode"].value == "command"
    assert params["rate"].value == 10.0
    assert params["seed"].descriptor.read_only
    assert "seed of every random stream" in params["seed"].descriptor.description
    sim.close()


def test_logging_goes_through_the_rclpy_logger_at_the_requested_level(rclpy):
    node = rclpy_node("logs", Node, "--log-level", "debug")
    node.logger.debug("details")
    node.logger.warning("careful")
    records = node.transport.node.get_logger().records
    assert ("DEBUG", "details") in records and ("WARN", "careful") in records
    assert node.transport.node.get_logger().level == fake_rclpy.LoggingSeverity.DEBUG
    node.close()


def test_close_destroys_the_node_and_shuts_the_context_down(rclpy):
    node = rclpy_node("closing")
    node.create_publisher("/x", m.CLOCK_TYPE)
    transport = node.transport
    node.close()
    assert transport.node.destroyed and not transport.context.ok()
    assert rclpy.GRAPH.publishers == []


def test_conversion_to_and_from_rclpy_messages_goes_through_cdr(rclpy):
    from tpsr_ros.runtime.rclpy_backend import from_rclpy, message_class, to_rclpy

    msg = m.twist_stamped_msg(5 * 10**9, 3.0, -6.0)
    ros_msg = to_rclpy(msg, m.ACTION_TYPE)
    assert isinstance(ros_msg, message_class(m.ACTION_TYPE))
    back = from_rclpy(ros_msg, m.ACTION_TYPE)
    assert m.twist_to_xy(back) == (3.0, -6.0) and m.stamp_of(back) == 5 * 10**9
    with pytest.raises(Exception, match="no message type"):
        message_class("nope_msgs/msg/Nothing")


def test_sim_node_and_recorder_over_rclpy(rclpy, tmp_path):
    """The integration scenario in one process: sim (explore) -> recorder -> bag."""
    from sim_node.node import SimNode
    from tpsr_ros.record import RecorderNode

    args = RecorderNode.argument_parser("record").parse_args(["-o", str(tmp_path / "bag")])
    recorder = RecorderNode(NodeOptions.for_node(RecorderNode, args=args))
    sim = rclpy_node("sim", SimNode, "-p", "rate:=200", "-p", "steps:=15",
                     "-p", "wait_for_subscribers:=1")
    while sim.steps_published < 15:
        sim.spin_once(0.005)
        recorder.spin_once(0.0)
    recorder.spin(timeout_s=0.05)
    sim.close()
    recorder.close()
    with BagReader(tmp_path / "bag") as reader:
        counts = reader.message_counts
        images = [m.stamp_of(x.decode()) for x in reader.messages(["/camera/image_raw"])]
    assert counts["/camera/image_raw"] == counts["/action"] == 15
    assert counts["/clock"] == 16 and counts["/sim/episode_start"] == 1
    assert images == [k * 10**9 for k in range(1, 16)]
