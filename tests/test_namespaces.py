"""Namespaces: ``-r __ns:=/robot1`` moves a node's (relative) topics under /robot1/.

Two simulators and one filter node run side by side as processes (started by the runtime
launcher; every wait is on the graph), on the DDS backend and on real rclpy; the recorder
records a robot's namespaced topics and the learner reads them back.
"""

from __future__ import annotations

import os

import pytest
from graph_support import BACKENDS, LOOPBACK, fresh_domain

from tpsr_ros.io import messages as m
from tpsr_ros.io.trajectory import Topics, read_trajectory
from tpsr_ros.runtime import LATCHED_QOS, Node, NodeOptions, parse_ros_args
from tpsr_ros.runtime.backend import open_transport
from tpsr_ros.runtime.inproc import InprocBus, InprocTransport
from tpsr_ros.runtime.launcher import Launch

S = 10**9




def test_sim_node_topics_follow_its_namespace_and_absolute_names_do_not():
    from sim_node.node import SimNode

    bus = InprocBus()
    options = NodeOptions.for_node(
        SimNode, parse_ros_args(["-r", "__ns:=/robot1", "-p", "mode:=command"])
    )
    sim = SimNode(options, transport=InprocTransport("/robot1/sim_node", bus))
    try:
        assert sim.fully_qualified_name == "/robot1/sim_node"
        topics = {e.topic for e in sim.endpoints()}
        assert topics == {
            "/robot1/camera/image_raw",
            "/robot1/action",
            "/robot1/ground_truth/pose",
            "/robot1/reward",
            "/robot1/clock",
            "/robot1/sim/episode_start",
            "/robot1/sim/cmd_ignored",
            "/robot1/sim/reset",
            "/robot1/cmd_vel",
        }
    finally:
        sim.close()
    # in the root namespace the names are the documented absolute ones
    root = SimNode(NodeOptions.for_node(SimNode), transport=InprocTransport("/sim_node", bus))
    try:
        assert "/camera/image_raw" in {e.topic for e in root.endpoints()}
    finally:
        root.close()


def test_filter_node_in_a_namespace_accepts_a_model_trained_on_root_topics(tmp_path):
    from test_filter_node import fit_small_model

    from tpsr_ros.core.errors import TpsrError
    from tpsr_ros.filter_node import FilterNode

    model = fit_small_model(tmp_path)
    options = NodeOptions.for_node(
        FilterNode, parse_ros_args(["-r", "__ns:=/robot1", "-p", f"model:={model}"])
    )
    FilterNode.preflight(options)
    node = FilterNode(options, transport=InprocTransport("/robot1/tpsr_filter", InprocBus()))
    try:
        topics = {e.topic for e in node.endpoints()}
        assert {"/robot1/camera/image_raw", "/robot1/tpsr/state", "/robot1/clock"} <= topics
        assert "/diagnostics" in topics  # global, for diagnostic aggregators
    finally:
        node.close()
    # another robot's topics are still refused
    elsewhere = NodeOptions.for_node(
        FilterNode,
        parse_ros_args(
            ["-r", "__ns:=/robot1", "-r", "camera/image_raw:=/robot2/camera/image_raw",
             "-p", f"model:={model}"]
        ),
    )
    with pytest.raises(TpsrError, match="node subscribes /robot2/camera/image_raw"):
        FilterNode.preflight(elsewhere)


@pytest.mark.slow
@pytest.mark.parametrize("backend", BACKENDS)
def test_two_robots_run_side_by_side(backend, tmp_path, monkeypatch):
    if backend == "dds":
        pytest.importorskip("cyclonedds")
    from test_filter_node import fit_small_model, random_policy

    model = fit_small_model(tmp_path)
    policy = random_policy(model, tmp_path / "policy.npz")
    domain = fresh_domain(17)  # Cyclone keeps a domain's first configuration
    for key, value in {
        "ROS_DOMAIN_ID": str(domain),
        "TPSR_TRANSPORT": backend,
        "CYCLONEDDS_URI": LOOPBACK,
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST" if backend == "rclpy" else "",
        "PYTHONUNBUFFERED": "1",
    }.items():
        monkeypatch.setenv(key, value)
    debug = ["--log-level", "debug"]
    observer = Node(
        NodeOptions(name="observer"), transport=open_transport(backend, "observer", "/")
    )
    got: dict[str, list[int]] = {}

    def keep(topic):
        got[topic] = []
        return lambda msg: got[topic].append(m.stamp_of(msg))

    for robot in ("robot1", "robot2"):
        for topic, msgtype in (("camera/image_raw", m.IMAGE_TYPE),
                               ("tpsr/state", m.STATE_TYPE)):
            name = f"/{robot}/{topic}"
            observer.create_subscription(name, msgtype, keep(name))
        observer.create_subscription(f"/{robot}/sim/episode_start", m.POSE_TYPE,
                                     keep(f"/{robot}/sim/episode_start"), LATCHED_QOS)
    cmd2 = observer.create_publisher("/robot2/cmd_vel", m.TWIST_TYPE)
    launch = Launch(tmp_path, env=dict(os.environ), spin=observer.spin_once, timeout_s=60)
    try:
        launch.start("recorder", "tpsr_ros.record", [
            "-o", str(tmp_path / "bag"), "camera/image_raw", "action", "ground_truth/pose",
            "reward", "clock", "sim/episode_start", "--ros-args", "-r", "__ns:=/robot1", *debug,
        ])  # fmt: skip
        for name, seed in (("robot1", 1), ("robot2", 2)):
            launch.start(name, "sim_node", [
                "--ros-args", "-r", f"__ns:=/{name}", "-p", "mode:=command",
                "-p", "episode_steps:=5", "-p", f"seed:={seed}",
                "-p", f"wait_for_subscribers:={1 if name == 'robot1' else 0}", *debug,
            ])  # fmt: skip
        # robot1 holds its start-up reset until each of its topics has a subscription: for
        # action, pose, reward and clock only the recorder's, so its episode start means
        # the recorder has subscribed
        launch.wait(
            "both episode starts and robot2's /cmd_vel subscription",
            lambda: bool(got["/robot1/sim/episode_start"] and got["/robot2/sim/episode_start"]
                         and cmd2.get_subscription_count() == 1),
        )
        # robot1's own filter (in /robot1, model trained on root topics) drives it
        launch.start("filter", "tpsr_ros.filter_node", [
            "--ros-args", "-r", "__ns:=/robot1", "-p", f"model:={model}",
            "-p", f"policy:={policy}", "-p", "wait_for_subscribers:=1", *debug,
        ])  # fmt: skip
        launch.wait("robot1's 5 states", lambda: len(got["/robot1/tpsr/state"]) == 5)
        # robot2 only moves when commanded on its own /robot2/cmd_vel
        for _ in range(2):
            before = len(got["/robot2/camera/image_raw"])
            cmd2.publish(m.twist_msg(3.0, 0.0))
            launch.wait(
                "robot2's next image",
                lambda before=before: len(got["/robot2/camera/image_raw"]) == before + 1,
                timeout_s=30,
            )
        observer.spin(timeout_s=0.3)
        assert got["/robot1/camera/image_raw"] == [k * S for k in range(1, 6)]
        assert got["/robot2/camera/image_raw"] == [1 * S, 2 * S]
        assert got["/robot2/tpsr/state"] == []
        # nothing at the root: every topic of the graph's nodes is namespaced
        topics = {e.topic for e in observer.transport.publishers()}
        assert "/robot1/clock" in topics and "/robot2/clock" in topics
        assert not topics & {"/camera/image_raw", "/action", "/clock", "/cmd_vel",
                             "/tpsr/state", "/sim/episode_start"}
    finally:
        observer.close()
        codes = launch.stop(timeout_s=30)  # the filter first, the recorder last
    procs = launch.processes
    assert codes == dict.fromkeys(procs, 0), {n: p.text()[-2000:] for n, p in procs.items()}
    # the recorder got robot1's steps under their namespaced names; the learner reads them
    topics = Topics(image="/robot1/camera/image_raw", action="/robot1/action",
                    pose="/robot1/ground_truth/pose", reward="/robot1/reward")
    trajectory = read_trajectory([tmp_path / "bag"], topics=topics, require_ground_truth=True)
    assert len(trajectory) == 5
    assert list(trajectory.stamps) == [k * S for k in range(1, 6)]
