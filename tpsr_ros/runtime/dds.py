"""Cyclone DDS transport (PyPI ``cyclonedds``) speaking ROS 2's conventions.

Follows rmw_cyclonedds_cpp (Jazzy) so a real ROS 2 system on the same network sees and
talks to our nodes:

- DDS domain ``ROS_DOMAIN_ID`` (default 0); participant USER_DATA ``enclave=/;``;
- topic ``rt/<fully qualified name>``; type ``pkg::msg::dds_::Name_`` as a keyless final
  struct (XCDR1, i.e. plain ROS 2 CDR), derived from the rosbags typestore
  (:mod:`tpsr_ros.runtime.dds_types`);
- endpoint USER_DATA ``typehash=RIHS01_<hex>;`` (rosidl's type hash, so rclpy does not warn);
- QoS as rmw_cyclonedds maps it: reliable with infinite blocking time, transient-local
  with a durability-service history of the same depth, writers not auto-disposing;
- ``ros_discovery_info`` (``rmw_dds_common/msg/ParticipantEntitiesInfo``, reliable,
  transient-local, depth 1) announces the node and its endpoints, so ``ros2 node list``
  and ``ros2 node info`` see it;
- ``/rosout`` (``rcl_interfaces/msg/Log``, reliable, transient-local, depth 1000, as rcl
  publishes it) carries every log line the node prints, so ``ros2 topic echo /rosout``
  and rqt_console see our nodes' logs.

Samples are written and taken as raw CDR bytes: no per-field conversion happens here.
Discovery follows ROS 2 Jazzy's variables unless ``CYCLONEDDS_URI`` configures Cyclone
(see :func:`discovery_config`): ``ROS_AUTOMATIC_DISCOVERY_RANGE`` = ``SUBNET`` (default:
multicast), ``LOCALHOST`` (or the older ``ROS_LOCALHOST_ONLY=1``: the loopback interface,
unicast discovery of the participants on this host, as rmw_cyclonedds_cpp and
rmw_fastrtps_cpp do, so real ROS 2 nodes with the same setting and ours see each other)
or ``OFF`` (no discovery at all, not even on this host), and ``ROS_STATIC_PEERS``
(``;``-separated addresses also contacted, except with ``OFF``, as in ROS 2).
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable
from typing import Any, ClassVar

from tpsr_ros.core.errors import ConfigError, MessageError, TpsrError
from tpsr_ros.core.units import NS_PER_S
from tpsr_ros.io.messages import jazzy_typestore
from tpsr_ros.io.qos import Durability, History, QoSProfile, Reliability
from tpsr_ros.runtime.dds_discovery import (
    LAST_SAFE_DOMAIN_ID,
    configure_domain,
    discovery_config,
    discovery_port,
    discovery_range_from_env,
    domain_config,
    domain_id_from_env,
    localhost_only_from_env,
    port_hint,
)
from tpsr_ros.runtime.dds_types import idl_struct, ros_type_name
from tpsr_ros.runtime.transport import (
    BytesCallback,
    PublisherHandle,
    SubscriptionHandle,
    TopicEndpoint,
    Transport,
    pad_cdr,
)

__all__ = [
    "LAST_SAFE_DOMAIN_ID",
    "DdsTransport",
    "discovery_config",
    "discovery_port",
    "discovery_range_from_env",
    "domain_config",
    "domain_id_from_env",
    "localhost_only_from_env",
]

_DISCOVERY_TOPIC = "ros_discovery_info"
_DISCOVERY_TYPE = "rmw_dds_common/msg/ParticipantEntitiesInfo"
_ROSOUT_TOPIC = "rt/rosout"
_LOG_TYPE = "rcl_interfaces/msg/Log"
_LOG_LEVELS = {"debug": 10, "info": 20, "warn": 30, "error": 40, "fatal": 50}
_TAKE_BATCH = 256
def _typehash(msgtype: str) -> bytes:
    return f"typehash={jazzy_typestore().hash_rihs01(msgtype)};".encode()


def _dds_qos(
    profile: QoSProfile, userdata: bytes, *, writer: bool, max_samples: int | None = None
) -> Any:
    from cyclonedds.core import Policy, Qos
    from cyclonedds.util import duration

    profile = profile.resolved()  # an unknown history: ROS 2's default keep-last 10
    policies: list[Any] = []
    if profile.reliability is Reliability.RELIABLE:
        policies.append(Policy.Reliability.Reliable(max_blocking_time=duration(infinite=True)))
    else:
        policies.append(Policy.Reliability.BestEffort)
    history = (
        Policy.History.KeepLast(profile.depth)
        if profile.history is History.KEEP_LAST
        else Policy.History.KeepAll
    )
    policies.append(history)
    if profile.durability is Durability.TRANSIENT_LOCAL:
        policies.append(Policy.Durability.TransientLocal)
        policies.append(
            Policy.DurabilityService(
                cleanup_delay=0,
                history=history,
                max_samples=-1,
                max_instances=-1,
                max_samples_per_instance=-1,
            )
        )
    else:
        policies.append(Policy.Durability.Volatile)
    policies.append(Policy.Userdata(data=userdata))
    if writer:
        policies.append(Policy.WriterDataLifecycle(autodispose=False))
    elif max_samples is not None and profile.history is History.KEEP_ALL:
        policies.append(Policy.ResourceLimits(max_samples=max_samples))
    return Qos(*policies)


_CYCLONE_VENDOR = "0110"
"""Eclipse Cyclone DDS's RTPS vendor id, the first two bytes of its GUID prefixes."""


def _profile_from_dds(qos: Any, writer_guid: str = "") -> QoSProfile:
    """The profile a discovered writer offers, its history unknown where discovery hid it.

    DDS discovery need not carry a writer's history: Fast DDS (rmw_fastrtps) never sends
    it, Cyclone DDS sends it only when it is not the DDS default keep-last 1, and Cyclone
    fills in that default for a writer that sent none. So keep-last 1 is known only from a
    Cyclone writer (``writer_guid`` starting with its vendor id); from any other it is
    unknown, as is a missing history.
    """
    from cyclonedds.core import Policy

    reliability = Reliability.BEST_EFFORT
    durability = Durability.VOLATILE
    history, depth = History.UNKNOWN, 0
    for policy in qos:
        if isinstance(policy, Policy.Reliability.Reliable):
            reliability = Reliability.RELIABLE
        elif policy is Policy.Durability.TransientLocal:
            durability = Durability.TRANSIENT_LOCAL
        elif isinstance(policy, Policy.History.KeepLast) and int(policy.depth) >= 1:
            history, depth = History.KEEP_LAST, int(policy.depth)
        elif policy is Policy.History.KeepAll:
            history, depth = History.KEEP_ALL, 0
    cyclone = str(writer_guid).replace("-", "").lower().startswith(_CYCLONE_VENDOR)
    if history is History.KEEP_LAST and depth == 1 and not cyclone:
        history, depth = History.UNKNOWN, 0  # Cyclone's default filled in, or truly 1
    return QoSProfile(reliability, durability, history, depth)


class _Writer(PublisherHandle):
    def __init__(self, owner: DdsTransport, topic: str, writer: Any) -> None:
        self.owner, self.topic, self.writer = owner, topic, writer
        from cyclonedds._clayer import ddspy_write

        self._write = ddspy_write
        self.closed = False

    def write(self, data: bytes) -> None:
        ret = self._write(self.writer._ref, pad_cdr(data))
        if ret < 0:
            raise TpsrError(f"DDS write on {self.topic} failed (code {ret})")

    def matched_count(self) -> int:
        return int(self.writer.get_publication_matched_status().current_count)

    def wait_for_acks(self, timeout_s: float) -> bool:
        # DataWriter.wait_for_acks raises AttributeError on timeout in cyclonedds 11.0.1
        # (it compares with a missing constant); call the C function and read its code.
        return bool(self.writer._wait_for_acks(self.writer._ref, int(timeout_s * 1e9)) == 0)

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self.owner._forget(self)
            self.writer.__del__()


class _LossCounter:
    """Samples Cyclone reports lost for one reader, counted on Cyclone's listener thread.

    SAMPLE_LOST counts always. SAMPLE_REJECTED (the reader's cache is at its resource
    limit) is a loss only for a best-effort reader: a reliable writer sends a rejected
    sample again, so nothing is lost there, only delayed. Cyclone does not report samples
    that a remote writer dropped from its own keep-last history before this reader had
    them (the GAP it receives raises no status), so those cannot be counted here.
    """

    def __init__(self, best_effort: bool) -> None:
        self.best_effort = best_effort
        self.count = 0
        self._lock = threading.Lock()

    def on_lost(self, _reader: Any, status: Any) -> None:
        with self._lock:
            self.count += int(status.total_count_change)

    def on_rejected(self, _reader: Any, status: Any) -> None:
        if self.best_effort:
            with self._lock:
                self.count += int(status.total_count_change)


class _Reader(SubscriptionHandle):
    def __init__(
        self,
        owner: DdsTransport,
        topic: str,
        reader: Any,
        condition: Any,
        cb: BytesCallback,
        losses: _LossCounter,
    ) -> None:
        self.owner, self.topic, self.reader, self.condition = owner, topic, reader, condition
        self.callback = cb
        self.losses = losses
        self.closed = False

    def matched_count(self) -> int:
        return int(self.reader.get_subscription_matched_status().current_count)

    def lost_count(self) -> int:
        return self.losses.count

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self.owner._forget(self)
            self.owner._waitset.detach(self.condition)
            self.condition.__del__()
            self.reader.__del__()


# DDS QosPolicyId_t values (DDS 1.4, section 2.2.2.1.3) of the policies that decide matching
_POLICY_NAMES = {
    2: "durability",
    3: "presentation",
    4: "deadline",
    5: "latency budget",
    6: "ownership",
    8: "liveliness",
    11: "reliability",
    12: "destination order",
}


class DdsTransport(Transport):
    """One DDS participant per node, as rmw_cyclonedds creates one per context."""

    kind: ClassVar[str] = "dds"

    def __init__(
        self,
        node_name: str = "node",
        namespace: str = "/",
        *,
        domain_id: int | None = None,
        enclave: str = "/",
    ) -> None:
        try:
            import cyclonedds  # noqa: F401
        except ImportError:
            raise TpsrError(
                "the dds transport needs Cyclone DDS: pip install 'tpsr-ros[dds]'"
            ) from None
        from cyclonedds._clayer import ddspy_take
        from cyclonedds.builtin import BuiltinDataReader, BuiltinTopicDcpsPublication
        from cyclonedds.core import (
            GuardCondition,
            InstanceState,
            Policy,
            Qos,
            ReadCondition,
            SampleState,
            ViewState,
            WaitSet,
        )
        from cyclonedds.domain import Domain, DomainParticipant

        self._take = ddspy_take
        self._any = SampleState.Any | ViewState.Any | InstanceState.Any
        self._ReadCondition = ReadCondition
        self.node_name, self.namespace = node_name, namespace
        self.domain_id = domain_id_from_env() if domain_id is None else domain_id
        startup_warning = configure_domain(self.domain_id, Domain)
        userdata = f"enclave={enclave};".encode()
        try:
            self._dp = DomainParticipant(self.domain_id, qos=Qos(Policy.Userdata(data=userdata)))
        except Exception as exc:
            raise TpsrError(
                f"cannot join DDS domain {self.domain_id}: {exc}{port_hint(self.domain_id)}"
            ) from None
        self._waitset = WaitSet(self._dp)
        self._guard = GuardCondition(self._dp)
        self._waitset.attach(self._guard)
        self._lock = threading.Lock()
        self._qos_events: queue.SimpleQueue[str] = queue.SimpleQueue()
        if startup_warning:
            self._qos_events.put(startup_warning)
        self._warn: Callable[[str], None] | None = None
        self._topics: dict[str, tuple[str, Any]] = {}
        self._keep_all_limit: int | None = None
        self._writers: list[_Writer] = []
        self._readers: list[_Reader] = []
        self._graph = BuiltinDataReader(self._dp, BuiltinTopicDcpsPublication)
        self._graph_alive = ReadCondition(
            self._graph, SampleState.Any | ViewState.Any | InstanceState.Alive
        )
        self._discovery_writer = self._make_writer(
            _DISCOVERY_TOPIC,
            _DISCOVERY_TYPE,
            QoSProfile(Reliability.RELIABLE, Durability.TRANSIENT_LOCAL, History.KEEP_LAST, 1),
        )
        self._rosout = _Writer(
            self,
            "/rosout",
            self._make_writer(
                _ROSOUT_TOPIC,
                _LOG_TYPE,
                QoSProfile(
                    Reliability.RELIABLE, Durability.TRANSIENT_LOCAL, History.KEEP_LAST, 1000
                ),
            ),
        )
        self._writers.append(self._rosout)
        self._logger_name = (namespace.strip("/") + "/" + node_name).strip("/").replace("/", ".")
        self._closed = False
        self._announce()

    # -- entities -------------------------------------------------------------------

    def _topic(self, dds_name: str, msgtype: str) -> Any:
        from cyclonedds.topic import Topic

        known = self._topics.get(dds_name)
        if known is not None:
            if known[0] != msgtype:
                raise MessageError(
                    f"topic {dds_name[2:] if dds_name.startswith('rt/') else dds_name!r} "
                    f"already has type {known[0]} in this node, not {msgtype}"
                )
            return known[1]
        topic = Topic(self._dp, dds_name, idl_struct(msgtype))
        self._topics[dds_name] = (msgtype, topic)
        return topic

    def _qos_listener(self, topic: str, ours: QoSProfile, **more: Any) -> Any:
        """A listener that reports a peer whose QoS cannot match ours (like rclpy's warning).

        Cyclone calls it on its own thread; the message is queued and logged by
        :meth:`spin_once` on the node's thread.
        """
        from cyclonedds.core import Listener

        def report(side: str, status: Any) -> None:
            policy_id = int(status.last_policy_id)
            policy = _POLICY_NAMES.get(policy_id, f"QoS policy {policy_id}")
            self._qos_events.put(
                f"{topic}: a {side} was discovered whose QoS is incompatible with ours "
                f"({ours}): {policy} does not match, so no data flows between them"
            )

        return Listener(
            on_offered_incompatible_qos=lambda _writer, status: report("subscription", status),
            on_requested_incompatible_qos=lambda _reader, status: report("publisher", status),
            **more,
        )

    def limit_keep_all_readers(self, max_samples: int) -> None:
        """Bound the cache of keep-all subscriptions created from now on (DDS RESOURCE_LIMITS).

        A stalled node then holds at most ``max_samples`` unread samples per subscription
        instead of growing without bound: past it a reliable writer is held back (it sends
        the sample again later), and a best-effort sample is rejected and counted in
        :meth:`SubscriptionHandle.lost_count`. Not for a node that also publishes reliably
        to itself from the thread that spins it: its writer would wait for itself.
        """
        if max_samples < 1:
            raise ConfigError(f"a keep-all subscription needs room for 1 sample, not {max_samples}")
        self._keep_all_limit = int(max_samples)

    def set_warning_sink(self, sink: Callable[[str], None]) -> None:
        """Where warnings (incompatible QoS, host limits) go; the node's logger.

        Warnings queued before the sink was set (at start-up) are passed on now.
        """
        self._warn = sink
        self._flush_warnings()

    def _flush_warnings(self) -> None:
        while not self._qos_events.empty():
            message = self._qos_events.get_nowait()
            if self._warn is not None:
                self._warn(message)

    def _make_writer(
        self, dds_name: str, msgtype: str, qos: QoSProfile, topic_name: str | None = None
    ) -> Any:
        from cyclonedds.pub import DataWriter

        topic = self._topic(dds_name, msgtype)
        listener = self._qos_listener(topic_name, qos) if topic_name else None
        return DataWriter(
            self._dp, topic, _dds_qos(qos, _typehash(msgtype), writer=True), listener=listener
        )

    def create_publisher(self, topic: str, msgtype: str, qos: QoSProfile) -> PublisherHandle:
        writer = _Writer(self, topic, self._make_writer("rt" + topic, msgtype, qos, topic))
        self._writers.append(writer)
        self._announce()
        return writer

    def create_subscription(
        self, topic: str, msgtype: str, qos: QoSProfile, callback: BytesCallback
    ) -> SubscriptionHandle:
        from cyclonedds.sub import DataReader

        dds_topic = self._topic("rt" + topic, msgtype)
        losses = _LossCounter(best_effort=qos.reliability is Reliability.BEST_EFFORT)
        reader = DataReader(
            self._dp,
            dds_topic,
            _dds_qos(
                qos, _typehash(msgtype), writer=False, max_samples=self._keep_all_limit
            ),
            listener=self._qos_listener(
                topic, qos, on_sample_lost=losses.on_lost, on_sample_rejected=losses.on_rejected
            ),
        )
        condition = self._ReadCondition(reader, self._any)
        self._waitset.attach(condition)
        handle = _Reader(self, topic, reader, condition, callback, losses)
        self._readers.append(handle)
        self._announce()
        return handle

    def _forget(self, handle: _Writer | _Reader) -> None:
        if isinstance(handle, _Writer) and handle in self._writers:
            self._writers.remove(handle)
        elif isinstance(handle, _Reader) and handle in self._readers:
            self._readers.remove(handle)
        if not self._closed:
            self._announce()

    # -- /rosout ---------------------------------------------------------------------

    def log(self, level: str, message: str) -> bool:
        """Publish the line on ``/rosout``; False, so the node's logger also prints it."""
        if self._closed:
            return False
        store = jazzy_typestore()
        now = time.time_ns()
        stamp = store.types["builtin_interfaces/msg/Time"](
            sec=now // NS_PER_S, nanosec=now % NS_PER_S
        )
        msg = store.types[_LOG_TYPE](
            stamp=stamp,
            level=_LOG_LEVELS[level],
            name=self._logger_name,
            msg=message,
            file="",
            function="",
            line=0,
        )
        self._rosout.write(bytes(store.serialize_cdr(msg, _LOG_TYPE)))
        return False

    # -- ros_discovery_info -----------------------------------------------------------

    def _announce(self, *, leaving: bool = False) -> None:
        store = jazzy_typestore()
        gid_t = store.types["rmw_dds_common/msg/Gid"]
        node_t = store.types["rmw_dds_common/msg/NodeEntitiesInfo"]
        info_t = store.types[_DISCOVERY_TYPE]
        import numpy as np

        def gid(entity: Any) -> Any:
            return gid_t(data=np.frombuffer(entity.get_guid().bytes, dtype=np.uint8).copy())

        nodes = []
        if not leaving:
            nodes.append(
                node_t(
                    node_namespace=self.namespace,
                    node_name=self.node_name,
                    reader_gid_seq=[gid(r.reader) for r in self._readers],
                    writer_gid_seq=[gid(w.writer) for w in self._writers],
                )
            )
        msg = info_t(gid=gid(self._dp), node_entities_info_seq=nodes)
        data = bytes(store.serialize_cdr(msg, _DISCOVERY_TYPE))
        from cyclonedds._clayer import ddspy_write

        ddspy_write(self._discovery_writer._ref, pad_cdr(data))

    # -- executor ---------------------------------------------------------------------

    def spin_once(self, timeout_s: float) -> int:
        self._waitset.wait(max(0, int(timeout_s * 1e9)))
        self._guard.take()
        self._flush_warnings()
        count = 0
        for handle in list(self._readers):
            while not handle.closed:
                samples = self._take(handle.reader._ref, self._any, _TAKE_BATCH)
                if isinstance(samples, int):
                    raise TpsrError(f"DDS take on {handle.topic} failed (code {samples})")
                if not samples:
                    break
                for data, info in samples:
                    if info.valid_data and not handle.closed:
                        handle.source_ns = int(info.source_timestamp)
                        handle.callback(data)
                        count += 1
                if len(samples) < _TAKE_BATCH:
                    break
        return count

    def wake(self) -> None:
        self._guard.set(True)

    # -- graph ------------------------------------------------------------------------

    def publishers(self) -> list[TopicEndpoint]:
        found = []
        for sample in self._graph.read(N=4096, condition=self._graph_alive):
            name = sample.topic_name
            if not name.startswith("rt/"):
                continue
            msgtype = ros_type_name(sample.type_name)
            if msgtype is None:
                continue
            profile = _profile_from_dds(sample.qos, str(sample.key))
            found.append(TopicEndpoint(name[2:], msgtype, profile))
        return found

    # -- teardown ---------------------------------------------------------------------

    def close(self, ack_timeout_s: float = 2.0) -> None:
        if self._closed:
            return
        deadline = time.monotonic() + ack_timeout_s
        for writer in list(self._writers):
            writer.wait_for_acks(max(0.0, deadline - time.monotonic()))
        self._closed = True
        try:
            self._announce(leaving=True)
            self._discovery_writer._wait_for_acks(self._discovery_writer._ref, int(0.2e9))
        except Exception:
            pass
        self._writers.clear()
        self._readers.clear()
        self._dp.__del__()

