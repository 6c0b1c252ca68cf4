"""Our Cyclone DDS backend and real rclpy side by side, and the filter node on rclpy.

Messages of every type cross between the two backends in both directions, logs of a
DDS-backend node reach real rclpy's ``/rosout``, and the filter node swaps its policy at
runtime over rclpy's parameter services. Skipped where rclpy cannot be imported.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
from graph_support import LOOPBACK, fresh_domain
from rclpy_support import published_samples, rclpy_node, rosout_qos, spin_all

pytest.importorskip("rclpy", reason="rclpy not importable (pip install 'tpsr-ros[ros]')")

from tpsr_ros.io import messages as m
from tpsr_ros.runtime import Node, NodeOptions, QoSProfile

pytestmark = pytest.mark.rclpy
S = 10**9


@pytest.fixture
def mixed_pair(monkeypatch):
    """A node on our Cyclone DDS backend and a real rclpy (Fast DDS) node, one domain.

    Default discovery on both sides (Cyclone kept on the loopback interface): see
    test_localhost_discovery_range_* for ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``.
    """
    pytest.importorskip("cyclonedds")
    from tpsr_ros.runtime.dds import DdsTransport
    from tpsr_ros.runtime.rclpy_backend import RclpyTransport

    monkeypatch.setenv("ROS_DOMAIN_ID", str(fresh_domain()))
    monkeypatch.delenv("ROS_AUTOMATIC_DISCOVERY_RANGE", raising=False)
    monkeypatch.setenv("CYCLONEDDS_URI", LOOPBACK)
    dds = Node(NodeOptions(name="dds_side"), transport=DdsTransport("dds_side", "/"))
    ros = Node(NodeOptions(name="rclpy_side"), transport=RclpyTransport("rclpy_side", "/"))
    yield dds, ros
    ros.close()
    dds.close()


@pytest.mark.slow
@pytest.mark.parametrize("reliability", ["reliable", "best_effort"])
@pytest.mark.parametrize("direction", ["dds_to_rclpy", "rclpy_to_dds"])
def test_every_published_type_crosses_between_rclpy_and_the_dds_backend(
    mixed_pair, direction, reliability
):
    """Our DDS backend's bytes reach typed rclpy subscriptions, and rclpy's typed
    publishers (Fast DDS's own serialisation) reach our DDS backend, field for field."""
    from tpsr_ros.io.qos import Durability, History, Reliability
    from tpsr_ros.runtime.rclpy_backend import from_rclpy, message_class, to_rclpy, to_rclpy_qos

    dds, ros = mixed_pair
    qos = QoSProfile(Reliability(reliability), Durability.VOLATILE, History.KEEP_LAST, 10)
    samples = published_samples()
    received: dict[int, object] = {}
    send = []
    for i, (msgtype, msg) in enumerate(samples):
        topic = f"/matrix/t{i}"

        def keep(x, i=i):
            received.setdefault(i, x)

        if direction == "dds_to_rclpy":
            ros.transport.node.create_subscription(
                message_class(msgtype), topic, keep, to_rclpy_qos(qos)
            )
            pub = dds.create_publisher(topic, msgtype, qos)
            send.append(lambda pub=pub, msg=msg: pub.publish(msg))
        else:
            dds.create_subscription(topic, msgtype, keep, qos)
            pub = ros.transport.node.create_publisher(
                message_class(msgtype), topic, to_rclpy_qos(qos)
            )
            ros_msg = to_rclpy(msg, msgtype)
            send.append(lambda pub=pub, ros_msg=ros_msg: pub.publish(ros_msg))
    deadline = time.monotonic() + 20
    sent = 0
    while len(received) < len(samples) and time.monotonic() < deadline:
        # best effort loses what is sent before matching: send until everything arrived
        for i, publish in enumerate(send):
            if i not in received:
                publish()
        sent += 1
        spin_all((dds, ros), lambda: len(received) == len(samples), timeout=0.2)
    assert sorted(received) == list(range(len(samples))), (direction, reliability, sent)
    for i, (msgtype, msg) in enumerate(samples):
        got = received[i]
        if direction == "dds_to_rclpy":
            assert isinstance(got, message_class(msgtype))
            got = from_rclpy(got, msgtype)
        assert m.serialize(got, msgtype) == m.serialize(msg, msgtype), msgtype


@pytest.mark.slow
def test_a_dds_backend_node_logs_reach_rosout_of_real_rclpy(mixed_pair):
    """rqt_console / ros2 topic echo /rosout: our DDS node's log lines, as rcl_interfaces Log."""
    from rcl_interfaces.msg import Log

    dds, ros = mixed_pair
    got = []
    ros.transport.node.create_subscription(Log, "/rosout", got.append, rosout_qos())
    dds.logger.info("hello from the DDS backend")  # before matching: transient-local keeps it
    assert spin_all((dds, ros), lambda: got)
    dds.logger.warning("careful")
    dds.logger.debug("not at info level")

    def seen():
        return {(x.name, x.level, x.msg) for x in got} >= {
            ("dds_side", Log.INFO, "hello from the DDS backend"),
            ("dds_side", Log.WARN, "careful"),
        }

    assert spin_all((dds, ros), seen)
    spin_all((dds, ros), lambda: False, timeout=0.3)
    assert all(x.msg != "not at info level" for x in got)
    assert all(x.stamp.sec > 1_600_000_000 for x in got if x.name == "dds_side")  # wall time


@pytest.mark.slow
def test_the_filter_node_swaps_its_policy_at_runtime_only_for_one_that_fits(ros_env, tmp_path):
    from rclpy.parameter import Parameter
    from rclpy.parameter_client import AsyncParameterClient
    from test_filter_node import fit_small_model, random_policy

    from tpsr_ros.filter_node import FilterNode

    model = fit_small_model(tmp_path)
    first = random_policy(model, tmp_path / "first.npz", seed=0)
    second = random_policy(model, tmp_path / "second.npz", seed=1)
    foreign = random_policy(model, tmp_path / "foreign.npz", fingerprint="f" * 64)
    node = rclpy_node("f", FilterNode, "-p", f"model:={model}", "-p", f"policy:={first}")
    caller = rclpy_node("param_client")
    try:
        client = AsyncParameterClient(caller.transport.node, "/tpsr_filter")
        assert spin_all((node, caller), client.services_are_ready)

        def set_policy(path) -> object:
            future = client.set_parameters([Parameter("policy", value=str(path))])
            assert spin_all((node, caller), future.done)
            (result,) = future.result().results
            return result

        before = node.policy
        refused = set_policy(foreign)
        assert not refused.successful and "ffffffffffff" in refused.reason
        assert node.policy is before and node.params.policy == str(first)
        refused = set_policy(tmp_path / "missing.npz")
        assert not refused.successful and "missing.npz" in refused.reason
        assert set_policy(second).successful
        assert node.policy is not before and node.params.policy == str(second)
        state = np.ones(node.model.state_dim)
        from tpsr_ros.io.policy import load_policy

        assert node.policy.action(state) == load_policy(second).action(state)
        assert not set_policy("").successful  # a pure filter has no /cmd_vel publisher
    finally:
        caller.close()
        node.close()


@pytest.mark.slow
def test_ros2_param_set_of_model_swaps_it_and_refuses_a_bad_one(ros_env, tmp_path):
    """`ros2 param set /tpsr_filter model NEW` over real rclpy: a corrupt file is refused
    with its reason and the old model runs on; a model of the same inputs is swapped in."""
    from rclpy.parameter import Parameter
    from rclpy.parameter_client import AsyncParameterClient
    from test_filter_node import fit_small_model

    from tpsr_ros.filter_node import FilterNode

    first, second = fit_small_model(tmp_path), fit_small_model(tmp_path, seed=4)
    corrupt = tmp_path / "corrupt.npz"
    corrupt.write_bytes(b"not a model")
    node = rclpy_node("f", FilterNode, "-p", f"model:={first}")
    caller = rclpy_node("param_client")
    try:
        client = AsyncParameterClient(caller.transport.node, "/tpsr_filter")
        assert spin_all((node, caller), client.services_are_ready)

        def set_model(path) -> object:
            future = client.set_parameters([Parameter("model", value=str(path))])
            assert spin_all((node, caller), future.done)
            (result,) = future.result().results
            return result

        running = node.inputs.fingerprint
        refused = set_model(corrupt)
        assert not refused.successful and "corrupt.npz" in refused.reason
        assert node.inputs.fingerprint == running and node.refused_swaps == 1
        assert set_model(second).successful
        assert node.inputs.fingerprint != running and node.swaps == 1
        assert node.params.model == str(second)
    finally:
        caller.close()
        node.close()


def _trigger(nodes, caller, service: str) -> object:
    """Call a ``std_srvs/srv/Trigger`` service over rclpy; its response."""
    from std_srvs.srv import Trigger

    client = caller.transport.node.create_client(Trigger, service)
    assert spin_all((*nodes, caller), client.service_is_ready)
    future = client.call_async(Trigger.Request())
    assert spin_all((*nodes, caller), future.done, timeout=60)
    return future.result()


@pytest.mark.slow
def test_reload_model_reads_the_model_file_again_and_refuses_a_corrupt_one(ros_env, tmp_path):
    """The filter node's ``~/reload_model`` Trigger over real rclpy: after the file at its
    ``model`` path is replaced, the new model runs; a corrupt file is refused with its
    reason in the response and the old model runs on."""
    import shutil

    from test_filter_node import fit_small_model

    from tpsr_ros.filter_node import FilterNode

    first, second = fit_small_model(tmp_path), fit_small_model(tmp_path, seed=4)
    path = tmp_path / "live.npz"
    shutil.copyfile(first, path)
    node = rclpy_node("f", FilterNode, "-p", f"model:={path}")
    caller = rclpy_node("trigger_client")
    try:
        assert node.reload_service == "/tpsr_filter/reload_model"
        running = node.inputs.fingerprint
        shutil.copyfile(second, path)
        response = _trigger((node,), caller, "/tpsr_filter/reload_model")
        assert response.success and node.inputs.fingerprint != running
        assert node.inputs.fingerprint[:12] in response.message
        path.write_bytes(b"not a model")
        refused = _trigger((node,), caller, "/tpsr_filter/reload_model")
        assert not refused.success and "not a readable model file" in refused.message
        assert node.swaps == 1 and node.refused_swaps == 1
    finally:
        caller.close()
        node.close()


@pytest.mark.slow
def test_the_learner_nodes_refit_service_refits_on_the_steps_so_far(ros_env, tmp_path):
    """The learner node's ``~/refit`` Trigger over real rclpy, with steps fed in-process."""
    from test_learner_node import TOPICS, _messages

    from sim_node import SimConfig
    from sim_node.generate import generate_bag
    from tpsr_ros.io.trajectory import LiveSteps
    from tpsr_ros.learner_node import LearnerNode

    generate_bag(tmp_path / "run", SimConfig(environment="full"), 700, seed=2)
    node = rclpy_node("l", LearnerNode, "-p", f"output:={tmp_path / 'out'}",
                      "-p", "warmup_steps:=5000")  # fmt: skip
    caller = rclpy_node("trigger_client")
    try:
        kinds = dict(zip(TOPICS, (LiveSteps.IMAGE, LiveSteps.ACTION, LiveSteps.POSE,
                                  LiveSteps.REWARD), strict=True))  # fmt: skip
        for topic, data in _messages(tmp_path / "run"):
            node.live.add(kinds[topic], data)
        node.live.flush()
        response = _trigger((node,), caller, "/tpsr_learner/refit")
        assert response.success and "refit of 700 steps started (v1)" in response.message
        busy = _trigger((node,), caller, "/tpsr_learner/refit")
        assert not busy.success and "is running" in busy.message
        assert spin_all((node, caller), lambda: node.last_result is not None, timeout=60)
        assert node.last_result.steps == 700 and node.next_due == 700 + 1000
    finally:
        caller.close()
        node.close()


@pytest.mark.slow
def test_why_the_dds_backend_serves_no_ros2_services_to_fast_dds_clients(mixed_pair):
    """A real rclpy (Fast DDS) service request reaches a plain Cyclone DDS reader of the
    service's request topic as the bare request: no correlation header in the payload, as
    rmw_cyclonedds_cpp would put there. Fast DDS carries the request's identity out of band
    (RTPS sample identities), and a reply would have to echo it the same way, which the
    Python Cyclone API cannot write; so the DDS backend serves no parameter services
    (msgs_doc/README.md), and ``ros2 param`` needs the rclpy backend."""
    from cyclonedds.core import Policy, Qos
    from cyclonedds.idl import make_idl_struct
    from cyclonedds.idl.annotations import final
    from cyclonedds.idl.types import sequence
    from cyclonedds.sub import DataReader
    from cyclonedds.topic import Topic
    from cyclonedds.util import duration
    from rcl_interfaces.srv import GetParameters

    Request = final(make_idl_struct(
        "GetParameters_Request", "rcl_interfaces::srv::dds_::GetParameters_Request_",
        {"names": sequence[str]}, dataclassify=True,
    ))

    dds, ros = mixed_pair
    topic = Topic(dds.transport._dp, "rq/sim_node/get_parametersRequest", Request)
    reader = DataReader(dds.transport._dp, topic, Qos(
        Policy.Reliability.Reliable(duration(seconds=1)), Policy.History.KeepLast(10)))
    client = ros.transport.node.create_client(GetParameters, "/sim_node/get_parameters")
    got: list = []
    deadline = time.monotonic() + 20
    while not got and time.monotonic() < deadline:
        if reader.get_subscription_matched_status().current_count:
            client.call_async(GetParameters.Request(names=["environment"]))
        spin_all((ros,), lambda: False, timeout=0.2)
        got = reader.take(N=10)
    assert got and got[0].names == ["environment"]  # the bare request, nothing before it
    assert not client.service_is_ready()  # a reader alone is no service for Fast DDS
    ros.transport.node.destroy_client(client)
