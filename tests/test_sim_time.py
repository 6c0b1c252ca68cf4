"""``use_sim_time``: every node takes the standard ROS 2 parameter, from ``-p``, a params
file (as ``ros2 launch`` passes it) or ``ros2 param set``, and then follows ``/clock``."""

from __future__ import annotations

import pytest
from graph_support import rclpy_available

from tpsr_ros.io import messages as m
from tpsr_ros.io.qos import DEFAULT_QOS, SENSOR_DATA_QOS
from tpsr_ros.record import RecorderNode
from tpsr_ros.runtime import Node, NodeOptions, parse_ros_args
from tpsr_ros.runtime.inproc import InprocBus, InprocTransport

S = 10**9


def _recorder(tmp_path, bus, *ros) -> RecorderNode:
    args = parse_ros_args(list(ros))
    options = NodeOptions.for_node(RecorderNode, args, args=RecorderNode.argument_parser(
        "record").parse_args(["-o", str(tmp_path / "bag"), "/chatter"]))  # fmt: skip
    return RecorderNode(options, transport=InprocTransport("/tpsr_recorder", bus))


@pytest.mark.parametrize(
    "clock_qos", [DEFAULT_QOS, SENSOR_DATA_QOS], ids=["reliable", "best-effort"]
)
def test_a_node_with_use_sim_time_follows_clock_and_can_be_switched(tmp_path, clock_qos):
    """A best-effort /clock (rosbag2's player) is followed as well as a reliable one."""
    bus = InprocBus()
    source = Node(NodeOptions(name="source"), transport=InprocTransport("/source", bus))
    clock = source.create_publisher("/clock", m.CLOCK_TYPE, clock_qos)
    params = tmp_path / "p.yaml"
    params.write_text("/**:\n  ros__parameters:\n    use_sim_time: true\n")
    node = _recorder(tmp_path, bus, "--params-file", str(params))
    try:
        assert node.use_sim_time and node.now_ns() == 0  # no /clock yet, as in ROS 2
        clock.publish(m.clock_msg(42 * S))
        node.spin_once(0.0)
        assert node.now_ns() == 42 * S
        assert node._check_parameter_change("use_sim_time", False) is None  # ros2 param set
        assert not node.use_sim_time and node.now_ns() > 10**18  # the system clock again
        assert "expects a bool" in node._check_parameter_change("use_sim_time", 3)
    finally:
        node.close()
        source.close()
    with pytest.raises(Exception, match="unknown parameter 'use_sim_tim'"):
        _recorder(tmp_path, bus, "-p", "use_sim_tim:=true")


def test_the_recorder_logs_at_sim_time(tmp_path):
    from tpsr_ros.io.bag import BagReader

    bus = InprocBus()
    source = Node(NodeOptions(name="source"), transport=InprocTransport("/source", bus))
    clock = source.create_publisher("/clock", m.CLOCK_TYPE)
    chatter = source.create_publisher("/chatter", m.HEADER_TYPE)
    node = _recorder(tmp_path, bus, "-p", "use_sim_time:=true")
    try:
        assert node.wait_for(lambda: node.subscribed, 10)
        for k in (5, 6, 7):
            clock.publish(m.clock_msg(k * S))
            node.spin_once(0.0)
            chatter.publish(m.header_msg(k * S, "x"))
            node.spin_once(0.0)
    finally:
        node.close()
        source.close()
    with BagReader(tmp_path / "bag") as reader:
        assert [x.log_time_ns for x in reader.messages(["/chatter"])] == [5 * S, 6 * S, 7 * S]


@pytest.mark.rclpy
@pytest.mark.skipif(not rclpy_available(), reason="rclpy (ROS 2) not importable")
def test_rclpy_nodes_declare_use_sim_time_as_given(ros_env):
    from tpsr_ros.runtime.rclpy_backend import RclpyTransport

    options = NodeOptions.for_node(Node, parse_ros_args(["-p", "use_sim_time:=true"]))
    assert options.use_sim_time
    transport = RclpyTransport("timed", use_sim_time=options.use_sim_time)
    try:
        assert transport.node.get_parameter("use_sim_time").value is True  # ros2 param get
    finally:
        transport.close()
