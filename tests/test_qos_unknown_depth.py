"""A publisher's history depth that discovery does not carry is recorded as unknown.

DDS discovery does not announce a writer's history: rmw_fastrtps reports history UNKNOWN,
depth 0, for every publisher, and Cyclone DDS fills in the DDS default keep-last 1 for a
writer that sent none. The recorder stores such a profile as ``ros2 bag record`` does
(``history: unknown``, ``depth: 0``), ``bag_info`` shows ``history unknown`` (never a
made-up depth 1) and the player offers ROS 2's default depth 10 for it; bags that hold
depth 1 still read.
"""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from tpsr_ros.bag_info import format_info
from tpsr_ros.io import messages as m
from tpsr_ros.io.bag import BagReader, BagWriter
from tpsr_ros.io.qos import (
    DEFAULT_QOS,
    History,
    QoSProfile,
    Reliability,
    from_bag_qos,
    offered_text,
    parse_qos_text,
    to_bag_qos,
)

UNKNOWN = QoSProfile(Reliability.RELIABLE, history=History.UNKNOWN, depth=0)
DATA = Path(__file__).parent / "data" / "rosbag2"


def _bag(path: Path, *profiles: QoSProfile) -> Path:
    with BagWriter(path) as writer:
        writer.add_topic("/talk", m.CLOCK_TYPE, [to_bag_qos(p) for p in profiles])
        writer.write("/talk", 1, m.serialize(m.clock_msg(1), m.CLOCK_TYPE))
    return path


def test_an_unknown_history_is_stored_as_rosbag2_stores_it_and_read_back(tmp_path):
    bag = _bag(tmp_path / "bag", UNKNOWN)
    meta = (bag / "metadata.yaml").read_text()
    assert "history: unknown" in meta and "depth: 0" in meta
    from rosbags.rosbag2 import Reader  # the rosbags library reads it too

    with Reader(bag) as reader:
        (qos,) = reader.connections[0].ext.offered_qos_profiles
    assert qos.history.name == "UNKNOWN" and qos.depth == 0
    assert "QoS: reliable, volatile, history unknown" in format_info(bag)
    assert parse_qos_text(str(UNKNOWN)) == UNKNOWN
    with pytest.raises(Exception, match="unknown history has depth 0"):
        QoSProfile(history=History.UNKNOWN, depth=1)


def test_the_player_offers_the_default_depth_for_an_unknown_one():
    assert from_bag_qos([to_bag_qos(UNKNOWN)]) == DEFAULT_QOS
    depth_5 = QoSProfile(depth=5)
    assert from_bag_qos([to_bag_qos(depth_5), to_bag_qos(UNKNOWN)]).depth == 10
    assert from_bag_qos([to_bag_qos(QoSProfile(depth=20)), to_bag_qos(UNKNOWN)]).depth == 20
    assert UNKNOWN.resolved() == DEFAULT_QOS


def test_the_player_node_publishes_an_unknown_depth_as_keep_last_10(tmp_path):
    from tpsr_ros.play import PlayerNode
    from tpsr_ros.runtime import NodeOptions
    from tpsr_ros.runtime.inproc import InprocBus, InprocTransport

    bag = _bag(tmp_path / "bag", UNKNOWN)
    args = PlayerNode.argument_parser("play").parse_args([str(bag)])
    player = PlayerNode(
        NodeOptions.for_node(PlayerNode, args=args), transport=InprocTransport("/p", InprocBus())
    )
    try:
        assert player.publishers["/talk"].qos == DEFAULT_QOS
    finally:
        player.close()


def test_bags_with_depth_1_and_real_rosbag2_bags_still_read(tmp_path):
    bag = _bag(tmp_path / "old", QoSProfile(depth=1))
    assert "QoS: reliable, volatile, keep_last(1)" in format_info(bag)
    with BagReader(bag) as reader:
        assert from_bag_qos(reader.qos_profiles["/talk"]).depth == 1
    # ros2 bag record (metadata version 4, integer policies): history 3 (unknown), depth 0
    text = format_info(DATA / "talker")
    assert "/topic" in text and "QoS: reliable, volatile, history unknown" in text
    with BagReader(DATA / "talker") as reader:
        assert offered_text(reader.qos_profiles["/topic"]) == "reliable, volatile, history unknown"
        assert from_bag_qos(reader.qos_profiles["/topic"]) == DEFAULT_QOS


def test_dds_discovery_gives_a_depth_only_where_the_writer_sent_it():
    pytest.importorskip("cyclonedds")
    from cyclonedds.core import Policy, Qos

    from tpsr_ros.runtime.dds import _profile_from_dds

    cyclone = "0110c87f-541b-6daf-21a5-3fc900000203"  # GUIDs start with the vendor id
    fastdds = "010f78fd-c969-9977-0000-000000001303"
    reliable = Policy.Reliability.Reliable(max_blocking_time=0)
    # Cyclone fills in keep-last 1 for a Fast DDS writer, which never sends its history
    assert _profile_from_dds(Qos(reliable, Policy.History.KeepLast(1)), fastdds) == UNKNOWN
    assert _profile_from_dds(Qos(reliable, Policy.History.KeepLast(1)), cyclone).depth == 1
    assert _profile_from_dds(Qos(reliable, Policy.History.KeepLast(10)), fastdds).depth == 10
    assert _profile_from_dds(Qos(reliable), cyclone) == UNKNOWN


def test_rclpy_graph_profiles_of_unknown_history_stay_unknown():
    pytest.importorskip("rclpy")
    from rclpy.qos import HistoryPolicy
    from rclpy.qos import QoSProfile as RclpyQoS

    from tpsr_ros.runtime.rclpy_backend import from_rclpy_qos

    # what get_publishers_info_by_topic reports under rmw_fastrtps for any publisher
    assert from_rclpy_qos(RclpyQoS(history=HistoryPolicy.UNKNOWN, depth=0)) == UNKNOWN
    assert from_rclpy_qos(RclpyQoS(history=HistoryPolicy.KEEP_LAST, depth=10)) == DEFAULT_QOS


@pytest.mark.rclpy
def test_a_depth_10_fast_dds_publisher_is_recorded_with_its_depth_unknown(monkeypatch, tmp_path):
    """A real rclpy (Fast DDS) publisher of depth 10, recorded by the DDS-backend recorder
    and by the rclpy-backend one: neither bag says depth 1."""
    pytest.importorskip("rclpy")
    pytest.importorskip("cyclonedds")
    from graph_support import LOOPBACK, fresh_domain

    from tpsr_ros.record import RecorderNode
    from tpsr_ros.runtime import Node, NodeOptions, parse_ros_args
    from tpsr_ros.runtime.dds import DdsTransport
    from tpsr_ros.runtime.rclpy_backend import RclpyTransport

    monkeypatch.setenv("ROS_DOMAIN_ID", str(fresh_domain()))
    monkeypatch.delenv("ROS_AUTOMATIC_DISCOVERY_RANGE", raising=False)
    monkeypatch.setenv("CYCLONEDDS_URI", LOOPBACK)
    talker = Node(NodeOptions(name="talker"), transport=RclpyTransport("talker", "/"))
    talker.create_publisher("/talk", m.CLOCK_TYPE, DEFAULT_QOS)
    recorders = []
    for name, transport in (("dds", DdsTransport), ("rclpy", RclpyTransport)):
        args = RecorderNode.argument_parser("record").parse_args(
            ["-o", str(tmp_path / name), "/talk"]
        )
        ros_args = parse_ros_args(["-r", f"__node:=rec_{name}"])
        options = NodeOptions.for_node(RecorderNode, ros_args, args=args)
        recorders.append(RecorderNode(options, transport=transport(f"rec_{name}", "/")))
    try:
        deadline = time.monotonic() + 15
        while time.monotonic() < deadline and not all("/talk" in r.subscribed for r in recorders):
            for node in (talker, *recorders):
                node.spin_once(0.01)
        assert all("/talk" in r.subscribed for r in recorders)
    finally:
        for node in (*recorders, talker):
            node.close()
    for name in ("dds", "rclpy"):
        with BagReader(tmp_path / name) as reader:
            (qos,) = reader.qos_profiles["/talk"]
        assert (qos.history.name, qos.depth) == ("UNKNOWN", 0), name
        text = format_info(tmp_path / name)
        assert "QoS: reliable, volatile, history unknown" in text and "keep_last(1)" not in text
