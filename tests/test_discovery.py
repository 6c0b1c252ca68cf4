"""ROS 2 Jazzy's discovery variables on the DDS backend, against real rclpy (Fast DDS).

``ROS_AUTOMATIC_DISCOVERY_RANGE`` (SUBNET, LOCALHOST, OFF) and ``ROS_STATIC_PEERS`` as in
Jazzy's "Improved Dynamic Discovery" (OFF: nothing, not even on this host, static peers or
not; LOCALHOST: this host, plus static peers): with LOCALHOST on both sides, a real
rclpy node and a sim_node process on our DDS backend see each other, in both directions.
Each test has its own ROS_DOMAIN_ID and sets no CYCLONEDDS_URI (it would override them).
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest
from graph_support import fresh_domain, rclpy_available

pytest.importorskip("cyclonedds")

from tpsr_ros.core.errors import ConfigError
from tpsr_ros.io import messages as m
from tpsr_ros.runtime import Node, NodeOptions
from tpsr_ros.runtime.dds import DdsTransport, discovery_config, discovery_range_from_env
from tpsr_ros.runtime.launcher import NodeProcess

pytestmark = pytest.mark.dds
SIM_TOPICS = {"/camera/image_raw", "/action", "/ground_truth/pose", "/reward", "/clock",
              "/sim/episode_start"}


needs_rclpy = pytest.mark.skipif(not rclpy_available(), reason="rclpy not importable")




@pytest.fixture
def ros_env(monkeypatch):
    monkeypatch.setenv("ROS_DOMAIN_ID", str(fresh_domain(23)))
    monkeypatch.delenv("CYCLONEDDS_URI", raising=False)
    monkeypatch.delenv("ROS_LOCALHOST_ONLY", raising=False)
    monkeypatch.delenv("ROS_STATIC_PEERS", raising=False)
    monkeypatch.setenv("PYTHONUNBUFFERED", "1")
    return monkeypatch


def test_the_range_and_static_peers_become_cyclone_configuration(monkeypatch):
    monkeypatch.delenv("ROS_LOCALHOST_ONLY", raising=False)
    monkeypatch.delenv("ROS_AUTOMATIC_DISCOVERY_RANGE", raising=False)
    assert discovery_range_from_env() == "SUBNET"
    monkeypatch.setenv("ROS_LOCALHOST_ONLY", "1")
    assert discovery_range_from_env() == "LOCALHOST"
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "off")
    assert discovery_range_from_env() == "OFF"
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LAN")
    with pytest.raises(ConfigError, match="'LAN' is not one of SUBNET, LOCALHOST, OFF"):
        discovery_range_from_env()
    assert discovery_config("SUBNET", []) == "" and discovery_config("SYSTEM_DEFAULT", ["x"]) == ""
    local = discovery_config("LOCALHOST", ["10.0.0.2"])
    assert "<NetworkInterface address='127.0.0.1'/>" in local
    assert "<AllowMulticast>false</AllowMulticast>" in local
    assert "<Peer address='localhost'/><Peer address='10.0.0.2'/>" in local
    off = discovery_config("OFF", ["10.0.0.2"])  # static peers do not count with OFF
    assert "<ParticipantIndex>none</ParticipantIndex>" in off and "AllowMulticast>false" in off
    assert "10.0.0.2" not in off
    assert "<Peer address='10.0.0.2'/>" in discovery_config("SUBNET", ["10.0.0.2"])


def test_a_bad_static_peer_is_refused_in_one_line(ros_env):
    ros_env.setenv("ROS_STATIC_PEERS", "127.0.0.1;<evil/>")
    with pytest.raises(ConfigError, match="ROS_STATIC_PEERS has an invalid address '<evil/>'"):
        DdsTransport("bad_peer", "/")


def start_sim(tmp: Path, backend: str) -> NodeProcess:
    """sim_node in explore mode as a process on a given backend (the runtime launcher)."""
    return NodeProcess(
        f"sim_{backend}", "sim_node", ["--ros-args", "-p", "rate:=20"],
        log_path=tmp / f"sim_{backend}.log", env={**os.environ, "TPSR_TRANSPORT": backend},
    )  # fmt: skip


def _observe(node: Node, seconds: float) -> tuple[set[str], list[int]]:
    images: list[int] = []
    node.create_subscription("/camera/image_raw", m.IMAGE_TYPE,
                             lambda msg: images.append(m.stamp_of(msg)))
    deadline = time.monotonic() + seconds
    topics: set[str] = set()
    while time.monotonic() < deadline and not (len(images) >= 3 and SIM_TOPICS <= topics):
        node.spin_once(0.05)
        topics = {e.topic for e in node.transport.publishers()}
    return topics, images


@pytest.mark.slow
@needs_rclpy
def test_localhost_on_both_sides_a_real_rclpy_node_sees_our_dds_sim(ros_env, tmp_path):
    ros_env.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    from tpsr_ros.runtime.rclpy_backend import RclpyTransport

    sim = start_sim(tmp_path, "dds")
    observer = Node(NodeOptions(name="observer"), transport=RclpyTransport("observer", "/"))
    try:
        topics, images = _observe(observer, 30)
        listed = dict(observer.transport.node.get_topic_names_and_types())  # as ros2 topic list
        nodes = observer.transport.node.get_node_names_and_namespaces()  # as ros2 node list
    finally:
        observer.close()
        assert sim.stop() == 0
    assert SIM_TOPICS <= topics and SIM_TOPICS <= set(listed), (topics, sim.text())
    assert listed["/camera/image_raw"] == ["sensor_msgs/msg/Image"]
    assert ("sim_node", "/") in nodes
    assert len(images) >= 3 and images == sorted(images)


@pytest.mark.slow
@needs_rclpy
def test_localhost_on_both_sides_our_dds_node_sees_a_real_rclpy_sim(ros_env, tmp_path):
    ros_env.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    sim = start_sim(tmp_path, "rclpy")
    observer = Node(NodeOptions(name="observer"), transport=DdsTransport("observer", "/"))
    try:
        topics, images = _observe(observer, 30)
    finally:
        observer.close()
        assert sim.stop() == 0
    assert SIM_TOPICS <= topics, (topics, sim.text())
    assert len(images) >= 3


@pytest.mark.slow
@pytest.mark.parametrize("discovery, peers, found", [
    ("LOCALHOST", "", True),
    ("SUBNET", "127.0.0.1", True),
    ("OFF", "", False),
    ("OFF", "127.0.0.1", False),
])
def test_our_dds_nodes_across_processes_follow_the_range(ros_env, tmp_path, discovery, peers,
                                                         found):
    ros_env.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", discovery)
    ros_env.setenv("ROS_STATIC_PEERS", peers)
    sim = start_sim(tmp_path, "dds")
    observer = Node(NodeOptions(name="observer"), transport=DdsTransport("observer", "/"))
    try:
        if found:
            topics, images = _observe(observer, 15)
        else:  # once the simulator steps, 2 s in which nothing of it may arrive
            deadline = time.monotonic() + 30
            while "episode starts at" not in sim.text() and time.monotonic() < deadline:
                observer.spin_once(0.05)
            assert "episode starts at" in sim.text(), sim.text()
            topics, images = _observe(observer, 2)
    finally:
        observer.close()
        assert sim.stop() == 0
    assert (SIM_TOPICS <= topics and len(images) >= 3) is found, (topics, images)
