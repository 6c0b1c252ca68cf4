"""rclpy transport, written to rclpy's documented Jazzy API.

Used when ``rclpy`` is importable: a sourced ROS 2 Jazzy, or the PyPI wheels of the
``ros`` extra (``ros-jazzy-rclpy``, ``ros-jazzy-common-interfaces``,
``ros-jazzy-rmw-fastrtps-cpp``). Each node gets its own ``rclpy.Context`` (initialised
without rclpy's signal handlers: the runtime installs its own), one ``rclpy`` node and a
``SingleThreadedExecutor``.

Message classes are imported from their generated packages (``sensor_msgs.msg.Image``
for ``sensor_msgs/msg/Image``; the PyPI wheels ship no ``rosidl_runtime_py``). Data
crosses the boundary only as CDR bytes: publishers publish serialised bytes
(``Publisher.publish`` accepts ``bytes``) and subscriptions are created with
``raw=True``, so a node sees exactly the bytes the DDS backend would give it.
:func:`to_rclpy` and :func:`from_rclpy` convert between our rosbags messages and
rclpy's through ``rclpy.serialization`` for code that needs rclpy objects.
"""

from __future__ import annotations

import importlib
import threading
from collections.abc import Sequence
from typing import Any, ClassVar

from tpsr_ros.core.errors import MessageError, TpsrError
from tpsr_ros.io.messages import deserialize, serialize
from tpsr_ros.io.qos import Durability, History, QoSProfile, Reliability
from tpsr_ros.runtime.allocator import tune_allocator
from tpsr_ros.runtime.fastdds_tuning import tune_fastdds
from tpsr_ros.runtime.params import ParamSpec
from tpsr_ros.runtime.transport import (
    BytesCallback,
    ParameterCheck,
    PublisherHandle,
    SubscriptionHandle,
    TopicEndpoint,
    Transport,
    TriggerCallback,
    pad_cdr,
)

__all__ = ["RclpyTransport", "from_rclpy", "message_class", "to_rclpy", "to_rclpy_qos"]

_UNSUPPORTED_SEQUENCE = 2**64 - 1
"""rmw's RMW_MESSAGE_INFO_SEQUENCE_NUMBER_UNSUPPORTED."""
_SEVERITY = {"debug": "DEBUG", "info": "INFO", "warn": "WARN", "error": "ERROR", "fatal": "FATAL"}


def message_class(msgtype: str) -> Any:
    """The rclpy message class of ``pkg/msg/Name``, imported from ``pkg.msg``."""
    parts = msgtype.split("/")
    if len(parts) != 3 or parts[1] != "msg" or not all(p.isidentifier() for p in parts):
        raise MessageError(f"{msgtype!r} is not a message type name like pkg/msg/Name")
    try:
        cls = getattr(importlib.import_module(f"{parts[0]}.msg"), parts[2])
    except (AttributeError, ImportError) as exc:
        raise MessageError(f"ROS 2 has no message type {msgtype!r}: {exc}") from None
    return cls


def to_rclpy(msg: Any, msgtype: str) -> Any:
    """A rosbags message as an rclpy message, through CDR bytes."""
    from rclpy.serialization import deserialize_message

    return deserialize_message(serialize(msg, msgtype), message_class(msgtype))


def from_rclpy(msg: Any, msgtype: str) -> Any:
    """An rclpy message as a rosbags message, through CDR bytes.

    ``rclpy.serialization.serialize_message`` (Fast CDR) can return a few unused bytes
    after the message (it reserves alignment for empty sequences of 8-byte elements, e.g.
    a JointState without velocities); on the wire the sample has its exact size. A CDR
    parse does not depend on what follows the message, so the longest prefix that
    decodes is the message.
    """
    from rclpy.serialization import serialize_message

    data = bytes(serialize_message(msg))
    for end in range(len(data), 3, -4):
        try:
            return deserialize(data[:end], msgtype)
        except MessageError:
            continue
    return deserialize(data, msgtype)  # raises with the full-length reason


def to_rclpy_qos(profile: QoSProfile) -> Any:
    """``rclpy.qos.QoSProfile`` of ``profile`` (an unknown history as ROS 2's default)."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    profile = profile.resolved()
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST
        if profile.history is History.KEEP_LAST
        else HistoryPolicy.KEEP_ALL,
        depth=max(profile.depth, 1) if profile.history is History.KEEP_LAST else 0,
        reliability=ReliabilityPolicy.RELIABLE
        if profile.reliability is Reliability.RELIABLE
        else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL
        if profile.durability is Durability.TRANSIENT_LOCAL
        else DurabilityPolicy.VOLATILE,
    )


def from_rclpy_qos(qos: Any) -> QoSProfile:
    """Our profile of an ``rclpy.qos.QoSProfile``.

    Unknown reliability and durability map to ROS defaults. An unknown history (what
    ``get_publishers_info_by_topic`` reports for every publisher under rmw_fastrtps: DDS
    discovery does not carry it), a system-default one, or keep-last with depth 0 stays
    unknown, never a made-up depth.
    """
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, ReliabilityPolicy

    reliability = (
        Reliability.BEST_EFFORT
        if qos.reliability == ReliabilityPolicy.BEST_EFFORT
        else Reliability.RELIABLE
    )
    durability = (
        Durability.TRANSIENT_LOCAL
        if qos.durability == DurabilityPolicy.TRANSIENT_LOCAL
        else Durability.VOLATILE
    )
    if qos.history == HistoryPolicy.KEEP_ALL:
        return QoSProfile(reliability, durability, History.KEEP_ALL, 0)
    if qos.history == HistoryPolicy.KEEP_LAST and int(qos.depth) >= 1:
        return QoSProfile(reliability, durability, History.KEEP_LAST, int(qos.depth))
    return QoSProfile(reliability, durability, History.UNKNOWN, 0)


class _Publisher(PublisherHandle):
    def __init__(self, owner: RclpyTransport, publisher: Any) -> None:
        self.owner, self.publisher = owner, publisher

    def write(self, data: bytes) -> None:
        self.publisher.publish(pad_cdr(data))

    def matched_count(self) -> int:
        return int(self.publisher.get_subscription_count())

    def wait_for_acks(self, timeout_s: float) -> bool:
        from rclpy.duration import Duration

        return bool(self.publisher.wait_for_all_acked(Duration(nanoseconds=int(timeout_s * 1e9))))

    def close(self) -> None:
        if self.publisher is not None:
            self.owner.node.destroy_publisher(self.publisher)
            self.publisher = None


class _Subscription(SubscriptionHandle):
    """An rclpy subscription and the messages it knows were lost.

    Two counts, each a lower bound of the loss: Fast DDS's MESSAGE_LOST event (samples the
    reader learnt it will never get, e.g. a keep-last writer dropped them before they were
    acknowledged), and the gaps in the publisher's sequence numbers (rclpy's MessageInfo
    ``publication_sequence_number``), which also see samples overwritten in this reader's
    own keep-last history before they were taken. :meth:`lost_count` reports the larger.
    Sequence numbers belong to one publisher and MessageInfo does not say which, so gaps
    are counted only while exactly one publisher is matched, and a MATCHED event (a
    publisher came or went) starts the count afresh. Not counted: the tail of a burst with
    no later message to reveal the gap (unless the event reports it).
    """

    def __init__(self, owner: RclpyTransport) -> None:
        self.owner = owner
        self.subscription: Any = None
        self.lost = 0  # reported by MESSAGE_LOST events
        self.gap_lost = 0  # from gaps in the publisher's sequence numbers
        self._last_sequence: int | None = None
        self._last_matched = 0  # publishers matched when the last sequence number came

    def matched_count(self) -> int:
        return int(self.subscription.get_publisher_count()) if self.subscription else 0

    def lost_count(self) -> int:
        return max(self.lost, self.gap_lost)

    def on_message_lost(self, info: Any) -> None:
        """rclpy's MESSAGE_LOST event (Fast DDS: samples the reader will never get)."""
        self.lost += int(info.total_count_change)

    def on_matched(self, _info: Any) -> None:
        """A publisher came or went: the next sequence number starts a new count."""
        self._last_sequence = None

    def note_sequence(self, info: Any) -> None:
        """Count the publisher's messages skipped before this one (see the class docstring)."""
        sequence = info.get("publication_sequence_number") if isinstance(info, dict) else None
        if not isinstance(sequence, int) or sequence <= 0 or sequence >= _UNSUPPORTED_SEQUENCE:
            return  # an rmw without publication sequence numbers
        # rclpy may run this callback before the MATCHED event of a publisher that came or
        # went in the same pass: a changed publisher count also starts a new count
        matched = self.matched_count()
        last = None if matched != self._last_matched else self._last_sequence
        if last is not None and sequence > last + 1 and matched == 1:
            self.gap_lost += sequence - last - 1
        self._last_sequence, self._last_matched = sequence, matched

    def close(self) -> None:
        if self.subscription is not None:
            self.owner.node.destroy_subscription(self.subscription)
            self.subscription = None


class RclpyTransport(Transport):
    """One rclpy node in its own context, executed by a ``SingleThreadedExecutor``."""

    kind: ClassVar[str] = "rclpy"

    def __init__(
        self,
        node_name: str,
        namespace: str = "/",
        *,
        ros_args: Sequence[str] = (),
        use_sim_time: bool = False,
    ) -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions

        self._rclpy = rclpy
        tune_allocator()
        tune_fastdds()  # before the process's first participant; the user's settings win
        self.context = rclpy.Context()
        try:
            # rcl gets the ROS arguments (logging flags and levels, params files); the node
            # does not apply them again (use_global_arguments=False): ours are checked first
            args = ["tpsr_ros", "--ros-args", *ros_args] if ros_args else []
            rclpy.init(
                args=args, context=self.context, signal_handler_options=SignalHandlerOptions.NO
            )
            from rclpy.parameter import Parameter

            self.node = rclpy.create_node(
                node_name,
                namespace=namespace,
                context=self.context,
                use_global_arguments=False,
                parameter_overrides=[Parameter("use_sim_time", value=use_sim_time)],
            )
        except Exception as exc:
            self.context.try_shutdown()
            raise TpsrError(f"rclpy could not start node {node_name!r}: {exc}") from None
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._guard = self.node.create_guard_condition(lambda: None)
        self._dispatched = 0
        self._lock = threading.Lock()
        self._closed = False

    def create_publisher(self, topic: str, msgtype: str, qos: QoSProfile) -> PublisherHandle:
        publisher = self.node.create_publisher(message_class(msgtype), topic, to_rclpy_qos(qos))
        return _Publisher(self, publisher)

    def create_subscription(
        self, topic: str, msgtype: str, qos: QoSProfile, callback: BytesCallback
    ) -> SubscriptionHandle:
        handle = _Subscription(self)

        def on_raw(data: bytes, info: Any) -> None:
            self._dispatched += 1
            handle.note_sequence(info)
            sent = info.get("source_timestamp") if isinstance(info, dict) else None
            handle.source_ns = sent if isinstance(sent, int) and sent > 0 else None
            callback(data)

        from rclpy.event_handler import SubscriptionEventCallbacks, UnsupportedEventTypeError

        args = (message_class(msgtype), topic, on_raw, to_rclpy_qos(qos))
        try:
            handle.subscription = self.node.create_subscription(
                *args,
                raw=True,
                event_callbacks=SubscriptionEventCallbacks(
                    message_lost=handle.on_message_lost, matched=handle.on_matched
                ),
            )
        except UnsupportedEventTypeError:  # an rmw without the events: gaps only
            handle.subscription = self.node.create_subscription(*args, raw=True)
        return handle

    def create_trigger_service(self, name: str, callback: TriggerCallback) -> bool:
        from std_srvs.srv import Trigger

        def on_request(request: Any, response: Any) -> Any:
            self._dispatched += 1
            response.success, response.message = callback()
            return response

        self.node.create_service(Trigger, name, on_request)
        return True

    def spin_once(self, timeout_s: float) -> int:
        start = self._dispatched
        self.executor.spin_once(timeout_sec=max(0.0, timeout_s))
        while True:  # run whatever else is ready without waiting
            before = self._dispatched
            self.executor.spin_once(timeout_sec=0.0)
            if self._dispatched == before:
                break
        return self._dispatched - start

    def wake(self) -> None:
        if not self._closed:
            self._guard.trigger()

    def publishers(self) -> list[TopicEndpoint]:
        found = []
        for topic, _types in self.node.get_topic_names_and_types():
            for info in self.node.get_publishers_info_by_topic(topic):
                node: str | None = info.node_namespace.rstrip("/") + "/" + info.node_name
                if "_UNKNOWN_" in node:  # the peer's ros_discovery_info has not arrived yet
                    node = None
                found.append(
                    TopicEndpoint(topic, info.topic_type, from_rclpy_qos(info.qos_profile), node)
                )
        return found

    def declare_parameters(
        self, params: list[tuple[ParamSpec, object]], check: ParameterCheck | None = None
    ) -> None:
        """Declare the parameters, their constraints in the descriptors; ``ros2 param set``
        goes through ``check``. Without ``check`` they are read-only.

        rclpy refuses a value of another type; an integer for a double is first made a
        double (as ``-p rate:=20`` is), by a pre-set callback.
        """
        from rcl_interfaces.msg import (
            FloatingPointRange,
            IntegerRange,
            ParameterDescriptor,
            SetParametersResult,
        )
        from rclpy.parameter import Parameter

        doubles = set()
        for spec, value in params:
            if isinstance(value, tuple):
                value = list(value)
            descriptor = ParameterDescriptor(
                description=spec.help,
                read_only=check is None,
                additional_constraints=spec.constraints,
            )
            low, high = spec.range or (None, None)
            if low is not None and high is not None and spec.ros_type == "double":
                descriptor.floating_point_range = [
                    FloatingPointRange(from_value=float(low), to_value=float(high), step=0.0)
                ]
            elif low is not None and high is not None and spec.ros_type == "integer":
                descriptor.integer_range = [
                    IntegerRange(from_value=int(low), to_value=int(high), step=0)
                ]
            if spec.ros_type == "double":
                doubles.add(spec.name)
            self.node.declare_parameter(spec.name, value, descriptor)
        if check is None:
            return

        def to_double(parameters: list[Any]) -> list[Any]:
            return [
                Parameter(p.name, Parameter.Type.DOUBLE, float(p.value))
                if p.name in doubles and p.type_ == Parameter.Type.INTEGER
                else p
                for p in parameters
            ]

        def on_set(parameters: list[Any]) -> Any:
            for parameter in parameters:
                value = parameter.value
                reason = check(parameter.name, tuple(value) if isinstance(value, list) else value)
                if reason is not None:
                    return SetParametersResult(successful=False, reason=reason)
            return SetParametersResult(successful=True)

        # added after declaring: rclpy also runs these callbacks for declarations
        self.node.add_pre_set_parameters_callback(to_double)
        self.node.add_on_set_parameters_callback(on_set)

    def log(self, level: str, message: str) -> bool:
        # rclpy's logger remembers the severity of each call site (function, line,
        # bytecode offset) and raises ValueError if it changes: one call per severity.
        logger = self.node.get_logger()
        if level == "debug":
            logger.debug(message)
        elif level == "info":
            logger.info(message)
        elif level == "warn":
            logger.warning(message)
        elif level == "error":
            logger.error(message)
        elif level == "fatal":
            logger.fatal(message)
        else:
            raise ValueError(f"unknown log level {level!r}")
        return True

    def set_log_level(self, level: str) -> None:
        """Set the rclpy logger's severity (debug, info, warn, error, fatal)."""
        from rclpy.logging import LoggingSeverity

        self.node.get_logger().set_level(getattr(LoggingSeverity, _SEVERITY[level]))

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self.executor.shutdown()
        self.node.destroy_node()
        self.context.try_shutdown()
