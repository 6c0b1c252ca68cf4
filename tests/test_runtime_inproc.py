"""The node API on the in-process bus: pub/sub, QoS matching, latching, remaps, timers."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from tpsr_ros.io import messages as m
from tpsr_ros.io.qos import (
    DEFAULT_QOS,
    QoSProfile,
    adapt_to_publishers,
    compatible,
    parse_qos_text,
)
from tpsr_ros.runtime import (
    LATCHED_QOS,
    SENSOR_DATA_QOS,
    Node,
    NodeOptions,
    parse_ros_args,
)
from tpsr_ros.runtime.backend import choose_backend
from tpsr_ros.runtime.inproc import InprocBus, InprocTransport
from tpsr_ros.runtime.transport import pad_cdr


@pytest.fixture
def bus():
    return InprocBus()


def make_node(bus, name="n", *ros_args):
    options = NodeOptions.for_node(Node, parse_ros_args(list(ros_args)))
    options = NodeOptions(
        name=name, namespace=options.namespace, ros_args=options.ros_args,
        log_level=options.log_level,
    )
    return Node(options, transport=InprocTransport("/" + name, bus))


def test_messages_and_raw_bytes_round_trip(bus):
    talker, listener = make_node(bus, "talker"), make_node(bus, "listener")
    got, raw = [], []
    listener.create_subscription("/camera/image_raw", m.IMAGE_TYPE, got.append)
    listener.create_subscription("/camera/image_raw", m.IMAGE_TYPE, raw.append, raw=True)
    pub = talker.create_publisher("/camera/image_raw", m.IMAGE_TYPE)
    assert pub.get_subscription_count() == 2
    image = np.arange(16 * 16 * 3, dtype=np.uint8).reshape(16, 16, 3)
    pub.publish(m.image_msg(5 * 10**9, image))
    assert listener.wait_for(lambda: len(got) == 1 and len(raw) == 1, timeout_s=2)
    assert np.array_equal(m.image_to_array(got[0]), image)
    assert m.stamp_of(got[0]) == 5 * 10**9
    assert raw[0] == pad_cdr(m.serialize(m.image_msg(5 * 10**9, image), m.IMAGE_TYPE))


def test_cdr_is_padded_to_four_bytes_like_the_dds_wire(bus):
    a, b = make_node(bus, "a"), make_node(bus, "b")
    raw = []
    b.create_subscription("/chatter", "std_msgs/msg/String", raw.append, raw=True)
    a.create_publisher("/chatter", "std_msgs/msg/String").publish(
        m.jazzy_typestore().types["std_msgs/msg/String"](data="abc")
    )
    b.wait_for(lambda: raw, 2)
    assert len(raw[0]) % 4 == 0
    assert m.deserialize(raw[0], "std_msgs/msg/String").data == "abc"


def test_best_effort_writer_never_reaches_reliable_reader(bus):
    a, b = make_node(bus, "a"), make_node(bus, "b")
    reliable, best_effort = [], []
    b.create_subscription("/scan", m.CLOCK_TYPE, reliable.append)
    b.create_subscription("/scan", m.CLOCK_TYPE, best_effort.append, SENSOR_DATA_QOS)
    pub = a.create_publisher("/scan", m.CLOCK_TYPE, SENSOR_DATA_QOS)
    assert pub.get_subscription_count() == 1
    pub.publish(m.clock_msg(1))
    b.wait_for(lambda: best_effort, 2)
    b.spin_once(0.05)
    assert len(best_effort) == 1 and reliable == []


def test_endpoints_of_other_types_do_not_match(bus):
    a, b = make_node(bus, "a"), make_node(bus, "b")
    got = []
    sub = b.create_subscription("/x", m.CLOCK_TYPE, got.append)
    pub = a.create_publisher("/x", m.TWIST_TYPE)
    assert pub.get_subscription_count() == 0 and sub.get_publisher_count() == 0


def test_readers_that_join_or_leave_after_a_writer_has_published_are_matched_again(bus):
    """A writer matches its readers once per change of the graph, not at every sample."""
    a, b = make_node(bus, "a"), make_node(bus, "b")
    first, later = [], []
    b.create_subscription("/tick", m.CLOCK_TYPE, first.append)
    pub = a.create_publisher("/tick", m.CLOCK_TYPE)
    pub.publish(m.clock_msg(1))
    joined = b.create_subscription("/tick", m.CLOCK_TYPE, later.append)
    pub.publish(m.clock_msg(2))
    assert b.wait_for(lambda: len(first) == 2 and len(later) == 1, timeout_s=2)
    assert m.stamp_of(later[0]) == 2
    joined.destroy()
    pub.publish(m.clock_msg(3))
    assert b.wait_for(lambda: len(first) == 3, timeout_s=2)
    b.spin_once(0.05)
    assert len(later) == 1


def test_transient_local_replays_to_late_joiners(bus):
    a = make_node(bus, "a")
    pub = a.create_publisher("/sim/episode_start", m.POSE_TYPE, LATCHED_QOS)
    pub.publish(m.pose_msg(1, 1.0, 2.0))
    pub.publish(m.pose_msg(2, 3.0, 4.0))
    b = make_node(bus, "b")
    latched, volatile = [], []
    b.create_subscription("/sim/episode_start", m.POSE_TYPE, latched.append, LATCHED_QOS)
    b.create_subscription("/sim/episode_start", m.POSE_TYPE, volatile.append)
    b.wait_for(lambda: latched, 2)
    assert [m.pose_to_xy(x) for x in latched] == [(3.0, 4.0)]  # depth 1: the last only
    assert volatile == []


def test_keep_last_reader_drops_oldest_when_not_spun(bus):
    a, b = make_node(bus, "a"), make_node(bus, "b")
    got = []
    b.create_subscription("/c", m.CLOCK_TYPE, got.append, QoSProfile(depth=3))
    pub = a.create_publisher("/c", m.CLOCK_TYPE)
    for k in range(10):
        pub.publish(m.clock_msg(k))
    b.spin_once(0.0)
    assert [m.stamp_of(x) for x in got] == [7, 8, 9]


def test_remapping_namespace_and_private_names(bus):
    node = make_node(
        bus, "sim", "-r", "/cmd_vel:=/robot1/cmd_vel", "-r", "chatter:=/talk", "-r", "__ns:=/ns"
    )
    node = Node(
        NodeOptions(name="sim", namespace="/ns", ros_args=node.options.ros_args),
        transport=InprocTransport("/ns/sim", bus),
    )
    assert node.resolve_topic("/cmd_vel") == "/robot1/cmd_vel"
    assert node.resolve_topic("chatter") == "/talk"
    assert node.resolve_topic("other") == "/ns/other"
    assert node.resolve_topic("~/state") == "/ns/sim/state"
    pub = node.create_publisher("/cmd_vel", m.TWIST_TYPE)
    assert pub.topic == "/robot1/cmd_vel"
    assert node.endpoints()[0].topic == "/robot1/cmd_vel"


def test_undecodable_message_is_dropped_with_a_warning(bus, capsys):
    a, b = make_node(bus, "a"), make_node(bus, "b")
    got = []
    b.create_subscription("/img", m.IMAGE_TYPE, got.append)
    a.create_publisher("/img", m.IMAGE_TYPE).publish_raw(b"\x00\x01\x00\x00\xff")
    b.spin_once(0.0)
    assert got == []
    assert "dropped a message on /img" in capsys.readouterr().err


def test_timers_fire_periodically_and_can_be_cancelled(bus):
    node = make_node(bus, "t")
    ticks = []
    timer = node.create_timer(0.01, lambda: ticks.append(time.monotonic()))
    assert node.wait_for(lambda: len(ticks) >= 5, timeout_s=2)
    timer.cancel()
    count = len(ticks)
    node.spin(timeout_s=0.05)
    assert len(ticks) == count
    # ticks are never early nor bunched: each takes a grid point later than the last tick
    # (so n ticks span more than n - 2 periods, however loaded the machine; the period's
    # precision is a benchmark's)
    assert ticks[-1] - ticks[0] > (len(ticks) - 3) * 0.01


def test_a_timer_due_before_the_others_fires_on_time_wherever_it_was_created(bus):
    """Spinning only reads the clock until the earliest deadline, so a timer created after
    a slow one, or from another timer's callback, must move that deadline forward."""
    node = make_node(bus, "timers")
    node.create_timer(30.0, lambda: None)
    fast: list[float] = []
    node.create_timer(0.01, lambda: fast.append(time.monotonic()))
    assert node.wait_for(lambda: len(fast) >= 3, timeout_s=2)
    nested: list[float] = []

    def spawn() -> None:
        spawner.cancel()
        node.create_timer(0.01, lambda: nested.append(time.monotonic()))

    spawner = node.create_timer(0.005, spawn)
    assert node.wait_for(lambda: len(nested) >= 3, timeout_s=2)


def test_request_shutdown_from_another_thread_stops_spin(bus):
    node = make_node(bus, "s")
    threading.Timer(0.05, node.request_shutdown, args=("test",)).start()
    assert node.spin() is True  # returns (a spin that never did would hit the test timeout)
    assert node.shutdown_reason == "test" and not node.ok()


def test_graph_lists_publishers_with_types_and_qos(bus):
    a = make_node(bus, "a")
    a.create_publisher("/x", m.CLOCK_TYPE, LATCHED_QOS)
    b = make_node(bus, "b")
    assert [(e.topic, e.msgtype, e.qos, e.node) for e in b.transport.publishers()] == [
        ("/x", m.CLOCK_TYPE, LATCHED_QOS, "/a")
    ]


def test_logger_respects_level_and_format(bus, capsys):
    node = make_node(bus, "logger_test", "--log-level", "warn")
    node.logger.info("hidden")
    node.logger.warning("shown")
    err = capsys.readouterr().err
    assert "hidden" not in err
    assert "[WARN] [" in err and "] [logger_test]: shown" in err


def test_qos_text_matching_and_adaptation():
    assert str(DEFAULT_QOS) == "reliable, volatile, keep_last(10)"
    assert parse_qos_text(str(LATCHED_QOS)) == LATCHED_QOS
    assert parse_qos_text("best_effort, volatile, keep_all").history.value == "keep_all"
    assert not compatible(SENSOR_DATA_QOS, DEFAULT_QOS)
    assert compatible(DEFAULT_QOS, SENSOR_DATA_QOS)
    assert not compatible(DEFAULT_QOS, LATCHED_QOS)
    adapted = adapt_to_publishers([DEFAULT_QOS, SENSOR_DATA_QOS])
    assert adapted.reliability.value == "best_effort" and adapted.history.value == "keep_all"
    assert adapt_to_publishers([LATCHED_QOS]).durability.value == "transient_local"


def test_backend_selection(monkeypatch):
    monkeypatch.setenv("TPSR_TRANSPORT", "inproc")
    assert choose_backend() == ("inproc", None)
    monkeypatch.setenv("TPSR_TRANSPORT", "zeromq")
    with pytest.raises(Exception, match="not one of rclpy, dds, inproc"):
        choose_backend()
    monkeypatch.delenv("TPSR_TRANSPORT")
    backend, note = choose_backend()
    try:
        import rclpy  # noqa: F401
    except ImportError:
        assert backend == "dds" and "rclpy is not importable" in note
    else:
        assert backend == "rclpy" and note is None
