"""Cyclone DDS backend in one process: ROS 2 naming, USER_DATA, QoS, discovery info.

The cross-process behaviour is covered by tests/test_record_play.py.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

pytest.importorskip("cyclonedds")

from cyclonedds.builtin import (
    BuiltinDataReader,
    BuiltinTopicDcpsParticipant,
    BuiltinTopicDcpsPublication,
    BuiltinTopicDcpsSubscription,
)
from cyclonedds.core import Policy
from cyclonedds.domain import DomainParticipant
from graph_support import fresh_domain, hold_discovery_port

from tpsr_ros.core.errors import ConfigError, MessageError, TpsrError
from tpsr_ros.io import messages as m
from tpsr_ros.runtime import LATCHED_QOS, SENSOR_DATA_QOS, Node, NodeOptions
from tpsr_ros.runtime.dds import DdsTransport, discovery_port, domain_id_from_env
from tpsr_ros.runtime.dds_types import dds_type_name, idl_struct, ros_type_name

pytestmark = pytest.mark.dds


@pytest.fixture
def domain(monkeypatch):
    """A domain id of its own for each test (:func:`graph_support.fresh_domain`)."""
    value = fresh_domain(5)
    monkeypatch.setenv("ROS_DOMAIN_ID", str(value))
    return value


def node(name: str) -> Node:
    options = NodeOptions(name=name)
    return Node(options, transport=DdsTransport(name, "/"))


def wait(predicate, timeout=5.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.01)
    return predicate()


def test_type_names_follow_rmw_cyclonedds():
    assert dds_type_name("sensor_msgs/msg/Image") == "sensor_msgs::msg::dds_::Image_"
    assert ros_type_name("sensor_msgs::msg::dds_::Image_") == "sensor_msgs/msg/Image"
    assert ros_type_name("DDS::Something") is None
    cls = idl_struct("sensor_msgs/msg/Image")
    assert cls.__idl_typename__ == "sensor_msgs::msg::dds_::Image_"
    assert cls.__idl_annotations__["extensibility"] == "final"


def test_generated_types_serialise_exactly_like_rosbags():
    image = m.image_msg(7 * 10**9 + 5, np.arange(768, dtype=np.uint8).reshape(16, 16, 3))
    data = m.serialize(image, m.IMAGE_TYPE)
    sample = idl_struct(m.IMAGE_TYPE).deserialize(data)
    assert sample.header.stamp.sec == 7 and sample.header.frame_id == "camera"
    assert sample.serialize() == data  # XCDR1 little endian: header 00 01 00 00
    assert data[:4] == b"\x00\x01\x00\x00"
    reward = m.serialize(m.reward_msg(3, m.RewardSample(1.0, True, False)), m.REWARD_TYPE)
    assert idl_struct(m.REWARD_TYPE).deserialize(reward).serialize() == reward


def test_domain_id_from_env(monkeypatch):
    monkeypatch.delenv("ROS_DOMAIN_ID", raising=False)
    assert domain_id_from_env() == 0
    monkeypatch.setenv("ROS_DOMAIN_ID", "42")
    assert domain_id_from_env() == 42
    for bad in ("x", "300"):
        monkeypatch.setenv("ROS_DOMAIN_ID", bad)
        with pytest.raises(ConfigError):
            domain_id_from_env()


def test_a_taken_discovery_port_is_explained(monkeypatch):
    """Above domain 101 the discovery port lies among Linux's ephemeral ports; when another
    socket holds it, the error says so (the CI failure of a test that drew domain 126)."""
    from tpsr_ros.runtime import dds, dds_discovery

    configured = dds_discovery._DOMAINS
    unconfigured = (d for d in range(232, dds.LAST_SAFE_DOMAIN_ID, -1) if d not in configured)
    for domain_id in unconfigured:
        if (holder := hold_discovery_port(monkeypatch, domain_id)) is not None:
            break
    else:
        pytest.skip("no free discovery port above domain 101")
    with holder:
        with pytest.raises(TpsrError) as caught:
            DdsTransport("blocked", "/", domain_id=domain_id)
    assert f"UDP port {discovery_port(domain_id)}" in str(caught.value)
    assert "ROS_DOMAIN_ID 0..101" in str(caught.value)


def test_round_trip_between_two_participants(domain):
    talker, listener = node("talker"), node("listener")
    try:
        got, raw = [], []
        sub = listener.create_subscription("/reward", m.REWARD_TYPE, got.append)
        listener.create_subscription("/reward", m.REWARD_TYPE, raw.append, raw=True)
        pub = talker.create_publisher("/reward", m.REWARD_TYPE)
        assert talker.wait_for(lambda: pub.get_subscription_count() == 2, 5)
        assert wait(lambda: sub.get_publisher_count() == 1)
        pub.publish(m.reward_msg(10**9, m.RewardSample(10.0, False, True)))
        assert listener.wait_for(lambda: got and raw, 5)
        assert m.reward_to_sample(got[0]) == m.RewardSample(10.0, False, True)
        assert raw[0][:4] == b"\x00\x01\x00\x00" and len(raw[0]) % 4 == 0
    finally:
        talker.close()
        listener.close()


def test_ros2_conventions_are_visible_to_a_plain_participant(domain):
    observer = DomainParticipant(domain)
    pubs = BuiltinDataReader(observer, BuiltinTopicDcpsPublication)
    subs = BuiltinDataReader(observer, BuiltinTopicDcpsSubscription)
    parts = BuiltinDataReader(observer, BuiltinTopicDcpsParticipant)
    ours = node("conventions")
    try:
        ours.create_publisher("/camera/image_raw", m.IMAGE_TYPE, SENSOR_DATA_QOS)
        ours.create_subscription("/cmd_vel", m.TWIST_TYPE, lambda msg: None)
        seen_pubs: dict[str, object] = {}
        seen_subs: dict[str, object] = {}

        def collect():
            for s in pubs.take(N=100):
                seen_pubs[s.topic_name] = s
            for s in subs.take(N=100):
                seen_subs[s.topic_name] = s
            return "rt/camera/image_raw" in seen_pubs and "rt/cmd_vel" in seen_subs

        assert wait(collect)
        image = seen_pubs["rt/camera/image_raw"]
        assert image.type_name == "sensor_msgs::msg::dds_::Image_"
        userdata = image.qos[Policy.Userdata].data
        assert userdata == f"typehash={m.jazzy_typestore().hash_rihs01(m.IMAGE_TYPE)};".encode()
        assert isinstance(image.qos[Policy.Reliability], type(Policy.Reliability.BestEffort))
        assert image.qos[Policy.History].depth == 5
        cmd = seen_subs["rt/cmd_vel"]
        assert cmd.type_name == "geometry_msgs::msg::dds_::Twist_"
        assert isinstance(cmd.qos[Policy.Reliability], Policy.Reliability.Reliable)
        assert "ros_discovery_info" in seen_pubs
        enclaves = []
        assert wait(lambda: enclaves.extend(
            p.qos[Policy.Userdata].data for p in parts.take(N=100)
            if Policy.Userdata in p.qos
        ) or b"enclave=/;" in enclaves)
    finally:
        ours.close()


def test_ros_discovery_info_names_the_node_and_its_endpoints(domain):
    from cyclonedds.core import Qos
    from cyclonedds.sub import DataReader
    from cyclonedds.topic import Topic
    from cyclonedds.util import duration

    observer = DomainParticipant(domain)
    info_type = idl_struct("rmw_dds_common/msg/ParticipantEntitiesInfo")
    topic = Topic(observer, "ros_discovery_info", info_type)
    reader = DataReader(observer, topic, Qos(
        Policy.Reliability.Reliable(duration(seconds=1)), Policy.Durability.TransientLocal,
        Policy.History.KeepLast(10),
    ))
    ours = node("announced")
    try:
        ours.create_publisher("/a", m.CLOCK_TYPE)
        ours.create_subscription("/b", m.CLOCK_TYPE, lambda msg: None)
        latest = {}

        def collect():
            for sample in reader.take(N=100):
                for n in sample.node_entities_info_seq:
                    latest[n.node_name] = n
            entry = latest.get("announced")  # writers: /a and /rosout (as rcl nodes have)
            return entry is not None and len(entry.writer_gid_seq) == 2 and len(
                entry.reader_gid_seq) == 1

        assert wait(collect)
        assert latest["announced"].node_namespace == "/"
        assert len(bytes(latest["announced"].writer_gid_seq[0].data)) == 16
    finally:
        ours.close()


def test_best_effort_writer_does_not_reach_reliable_reader(domain, capsys):
    a, b = node("be_writer"), node("reliable_reader")
    try:
        reliable, best_effort = [], []
        b.create_subscription("/scan", m.CLOCK_TYPE, reliable.append)
        b.create_subscription("/scan", m.CLOCK_TYPE, best_effort.append, SENSOR_DATA_QOS)
        pub = a.create_publisher("/scan", m.CLOCK_TYPE, SENSOR_DATA_QOS)
        assert a.wait_for(lambda: pub.get_subscription_count() >= 1, 5)
        pub.publish(m.clock_msg(1))
        assert b.wait_for(lambda: best_effort, 5)
        b.spin(timeout_s=0.1)
        assert reliable == [] and pub.get_subscription_count() == 1
        # both sides are told, as rclpy tells its users: the mismatch is not silent
        a.spin(timeout_s=0.1)
        err = capsys.readouterr().err
        assert "[reliable_reader]: /scan: a publisher was discovered whose QoS" in err
        assert "[be_writer]: /scan: a subscription was discovered whose QoS" in err
        assert err.count("reliability does not match") == 2
    finally:
        a.close()
        b.close()


def test_latched_sample_reaches_late_joiner_and_graph_shows_qos(domain):
    a = node("latcher")
    try:
        pub = a.create_publisher("/sim/episode_start", m.POSE_TYPE, LATCHED_QOS)
        pub.publish(m.pose_msg(3, 1.5, 2.5))
        b = node("late")
        try:
            got = []
            assert wait(lambda: any(
                e.topic == "/sim/episode_start" for e in b.transport.publishers()))
            offered = [e for e in b.transport.publishers() if e.topic == "/sim/episode_start"]
            assert offered[0].qos == LATCHED_QOS and offered[0].msgtype == m.POSE_TYPE
            b.create_subscription("/sim/episode_start", m.POSE_TYPE, got.append, LATCHED_QOS)
            assert b.wait_for(lambda: got, 5)
            assert m.pose_to_xy(got[0]) == (1.5, 2.5)
        finally:
            b.close()
    finally:
        a.close()


def test_one_topic_one_type_per_node(domain):
    a = node("clash")
    try:
        a.create_publisher("/x", m.CLOCK_TYPE)
        with pytest.raises(MessageError, match="already has type"):
            a.create_subscription("/x", m.TWIST_TYPE, lambda msg: None)
    finally:
        a.close()
