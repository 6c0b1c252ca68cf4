"""A fake of rclpy's documented Jazzy API, for testing the rclpy backend without ROS 2.

Only what tpsr_ros.runtime.rclpy_backend uses is implemented, with the documented
signatures (keyword-only where rclpy has them), so a call the real rclpy would reject
fails here too. Nodes of every fake context share one in-memory graph, like a DDS
domain: endpoints match when types are equal and QoS is compatible (a best-effort writer
never reaches a reliable reader). Messages travel as CDR bytes; ``get_message`` returns
classes whose instances wrap those bytes, which is all rclpy.serialization needs.

Use :func:`install` (with pytest's ``monkeypatch``) to put the fake modules in
``sys.modules`` as ``rclpy``, ``rclpy.qos``, ``rclpy.executors``, ``rclpy.serialization``,
``rclpy.signals``, ``rclpy.logging``, ``rosidl_runtime_py.utilities`` and
``rcl_interfaces.msg``.
"""

from __future__ import annotations

import enum
import threading
import types
from collections import deque
from dataclasses import dataclass, field
from typing import Any

# -- rclpy.qos -------------------------------------------------------------------------


class ReliabilityPolicy(enum.IntEnum):
    SYSTEM_DEFAULT = 0
    RELIABLE = 1
    BEST_EFFORT = 2
    UNKNOWN = 3
    BEST_AVAILABLE = 4


class DurabilityPolicy(enum.IntEnum):
    SYSTEM_DEFAULT = 0
    TRANSIENT_LOCAL = 1
    VOLATILE = 2
    UNKNOWN = 3
    BEST_AVAILABLE = 4


class HistoryPolicy(enum.IntEnum):
    SYSTEM_DEFAULT = 0
    KEEP_LAST = 1
    KEEP_ALL = 2
    UNKNOWN = 3


class QoSProfile:
    """rclpy.qos.QoSProfile(**kwargs): needs history or depth, like rclpy."""

    _KEYS = ("history", "depth", "reliability", "durability", "lifespan", "deadline",
             "liveliness", "liveliness_lease_duration", "avoid_ros_namespace_conventions")

    def __init__(self, **kwargs: Any) -> None:
        unknown = set(kwargs) - set(self._KEYS)
        if unknown:
            raise TypeError(f"unexpected QoSProfile arguments {sorted(unknown)}")
        if "history" not in kwargs and "depth" not in kwargs:
            raise TypeError("QoSProfile requires history and/or depth")
        self.history = HistoryPolicy(kwargs.get("history", HistoryPolicy.KEEP_LAST))
        self.depth = int(kwargs.get("depth", 0))
        if self.history == HistoryPolicy.KEEP_LAST and self.depth < 1:
            raise ValueError("keep-last history needs depth >= 1")
        self.reliability = ReliabilityPolicy(kwargs.get("reliability", ReliabilityPolicy.RELIABLE))
        self.durability = DurabilityPolicy(kwargs.get("durability", DurabilityPolicy.VOLATILE))


def _compatible(offered: QoSProfile, requested: QoSProfile) -> bool:
    if (requested.reliability == ReliabilityPolicy.RELIABLE
            and offered.reliability == ReliabilityPolicy.BEST_EFFORT):
        return False
    return not (requested.durability == DurabilityPolicy.TRANSIENT_LOCAL
                and offered.durability == DurabilityPolicy.VOLATILE)


# -- messages (rosidl) -----------------------------------------------------------------


class FakeMessage:
    """An rclpy message of some type; carries its CDR bytes."""

    _type = ""

    def __init__(self, _cdr: bytes = b"") -> None:
        self._cdr = bytes(_cdr)


_CLASSES: dict[str, type] = {}


def get_message(identifier: str) -> type:
    """rosidl_runtime_py.utilities.get_message('pkg/msg/Name')."""
    from tpsr_ros.io.messages import jazzy_typestore

    parts = identifier.split("/")
    if len(parts) != 3 or parts[1] != "msg":
        raise ValueError(f"Expected the full name of a message, got '{identifier}'")
    if identifier not in jazzy_typestore().fielddefs:
        raise ModuleNotFoundError(f"No module named '{parts[0]}'")
    if identifier not in _CLASSES:
        _CLASSES[identifier] = type(parts[2], (FakeMessage,), {"_type": identifier})
    return _CLASSES[identifier]


def serialize_message(message: Any) -> bytes:
    """rclpy.serialization.serialize_message(message) -> bytes."""
    if not isinstance(message, FakeMessage):
        raise TypeError("serialize_message needs a ROS message")
    return message._cdr


def deserialize_message(serialized_message: bytes, message_type: type) -> Any:
    """rclpy.serialization.deserialize_message(serialized_message, message_type)."""
    if not isinstance(serialized_message, bytes):
        raise TypeError("serialized_message must be bytes")
    return message_type(serialized_message)


# -- rcl_interfaces.msg ----------------------------------------------------------------


@dataclass
class ParameterDescriptor:
    name: str = ""
    type: int = 0
    description: str = ""
    additional_constraints: str = ""
    read_only: bool = False
    dynamic_typing: bool = False


# -- logging, signals --------------------------------------------------------------------


class LoggingSeverity(enum.IntEnum):
    UNSET = 0
    DEBUG = 10
    INFO = 20
    WARN = 30
    ERROR = 40
    FATAL = 50


class SignalHandlerOptions(enum.IntEnum):
    NO = 0
    SIGINT = 1
    SIGTERM = 2
    ALL = 3


class RcutilsLogger:
    def __init__(self, name: str) -> None:
        self.name = name
        self.level = LoggingSeverity.INFO
        self.records: list[tuple[str, str]] = []

    def set_level(self, level: LoggingSeverity) -> None:
        self.level = LoggingSeverity(level)

    def _log(self, severity: LoggingSeverity, message: str) -> bool:
        if severity >= self.level:
            self.records.append((severity.name, message))
            return True
        return False

    def debug(self, message: str, **kwargs: Any) -> bool:
        return self._log(LoggingSeverity.DEBUG, message)

    def info(self, message: str, **kwargs: Any) -> bool:
        return self._log(LoggingSeverity.INFO, message)

    def warning(self, message: str, **kwargs: Any) -> bool:
        return self._log(LoggingSeverity.WARN, message)

    def error(self, message: str, **kwargs: Any) -> bool:
        return self._log(LoggingSeverity.ERROR, message)

    def fatal(self, message: str, **kwargs: Any) -> bool:
        return self._log(LoggingSeverity.FATAL, message)


# -- graph, context, node ----------------------------------------------------------------


class _Graph:
    def __init__(self) -> None:
        self.lock = threading.RLock()
        self.publishers: list[Publisher] = []
        self.subscriptions: list[Subscription] = []


GRAPH = _Graph()
INIT_CALLS: list[dict[str, Any]] = []


class Context:
    def __init__(self) -> None:
        self._ok = False
        self.cond = threading.Condition(threading.RLock())

    def ok(self) -> bool:
        return self._ok

    def try_shutdown(self) -> None:
        self._ok = False

    def shutdown(self) -> None:
        if not self._ok:
            raise RuntimeError("Context must be initialized before it can be shutdown")
        self._ok = False


def init(*, args: list[str] | None = None, context: Context | None = None,
         domain_id: int | None = None, signal_handler_options: Any = None) -> None:
    if context is None:
        raise RuntimeError("the fake supports explicit contexts only")
    if context._ok:
        raise RuntimeError("Context.init() must only be called once")
    if args is not None and not isinstance(args, list):
        raise TypeError("args must be a list of strings")
    INIT_CALLS.append({"args": args, "domain_id": domain_id,
                       "signal_handler_options": signal_handler_options})
    context._ok = True


@dataclass
class TopicEndpointInfo:
    node_name: str
    node_namespace: str
    topic_type: str
    qos_profile: QoSProfile
    endpoint_type: str = "PUBLISHER"


class Publisher:
    def __init__(self, node: Node, msg_type: type, topic: str, qos: QoSProfile) -> None:
        self.node, self.msg_type, self.topic, self.qos_profile = node, msg_type, topic, qos
        self.history: deque[bytes] = deque(
            maxlen=qos.depth if qos.history == HistoryPolicy.KEEP_LAST else None)

    @property
    def topic_name(self) -> str:
        return self.topic

    def _matches(self, sub: Subscription) -> bool:
        return (sub.topic == self.topic and sub.msg_type._type == self.msg_type._type
                and _compatible(self.qos_profile, sub.qos_profile))

    def publish(self, msg: Any) -> None:
        if isinstance(msg, self.msg_type):
            data = serialize_message(msg)
        elif isinstance(msg, bytes):
            data = msg
        else:
            raise TypeError(f"Expected {self.msg_type}, got {type(msg)}")
        if self.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL:
            self.history.append(data)
        with GRAPH.lock:
            targets = [s for s in GRAPH.subscriptions if self._matches(s)]
        for sub in targets:
            sub._deliver(data)

    def get_subscription_count(self) -> int:
        with GRAPH.lock:
            return sum(1 for s in GRAPH.subscriptions if self._matches(s))


class Subscription:
    def __init__(self, node: Node, msg_type: type, topic: str, callback: Any,
                 qos: QoSProfile, raw: bool) -> None:
        self.node, self.msg_type, self.topic = node, msg_type, topic
        self.callback, self.qos_profile, self.raw = callback, qos, raw
        keep = qos.depth if qos.history == HistoryPolicy.KEEP_LAST else None
        self.queue: deque[bytes] = deque(maxlen=keep)

    @property
    def topic_name(self) -> str:
        return self.topic

    def _deliver(self, data: bytes) -> None:
        with self.node.context.cond:
            self.queue.append(data)
            self.node.context.cond.notify_all()

    def get_publisher_count(self) -> int:
        with GRAPH.lock:
            return sum(1 for p in GRAPH.publishers if p._matches(self))


class GuardCondition:
    def __init__(self, node: Node, callback: Any) -> None:
        self.node, self.callback, self.triggered = node, callback, False

    def trigger(self) -> None:
        with self.node.context.cond:
            self.triggered = True
            self.node.context.cond.notify_all()


@dataclass
class Parameter:
    name: str
    value: Any
    descriptor: ParameterDescriptor = field(default_factory=ParameterDescriptor)


class Node:
    def __init__(self, node_name: str, *, context: Context | None = None,
                 cli_args: list[str] | None = None, namespace: str | None = None,
                 use_global_arguments: bool = True, enable_rosout: bool = True,
                 start_parameter_services: bool = True,
                 parameter_overrides: list[Any] | None = None,
                 allow_undeclared_parameters: bool = False,
                 automatically_declare_parameters_from_overrides: bool = False) -> None:
        if context is None or not context.ok():
            raise RuntimeError("the context is not initialized")
        self.context = context
        self._name = node_name
        self._namespace = namespace or "/"
        self.publishers: list[Publisher] = []
        self.subscriptions: list[Subscription] = []
        self.guards: list[GuardCondition] = []
        self.parameters: dict[str, Parameter] = {}
        self._logger = RcutilsLogger(node_name)
        self.destroyed = False

    def get_name(self) -> str:
        return self._name

    def get_namespace(self) -> str:
        return self._namespace

    def create_publisher(self, msg_type: type, topic: str, qos_profile: QoSProfile, *,
                         callback_group: Any = None, event_callbacks: Any = None,
                         qos_overriding_options: Any = None,
                         publisher_class: Any = None) -> Publisher:
        if not isinstance(qos_profile, QoSProfile):
            raise TypeError("qos_profile must be a QoSProfile (or a depth)")
        pub = Publisher(self, msg_type, topic, qos_profile)
        with GRAPH.lock:
            GRAPH.publishers.append(pub)
        self.publishers.append(pub)
        return pub

    def create_subscription(self, msg_type: type, topic: str, callback: Any,
                            qos_profile: QoSProfile, *, callback_group: Any = None,
                            event_callbacks: Any = None, qos_overriding_options: Any = None,
                            raw: bool = False) -> Subscription:
        sub = Subscription(self, msg_type, topic, callback, qos_profile, raw)
        with GRAPH.lock:
            GRAPH.subscriptions.append(sub)
            history = [list(p.history) for p in GRAPH.publishers if p._matches(sub)]
        if qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL:
            for samples in history:
                for data in samples:
                    sub._deliver(data)
        self.subscriptions.append(sub)
        return sub

    def create_guard_condition(self, callback: Any, callback_group: Any = None) -> GuardCondition:
        guard = GuardCondition(self, callback)
        self.guards.append(guard)
        return guard

    def declare_parameter(self, name: str, value: Any = None,
                          descriptor: ParameterDescriptor | None = None,
                          ignore_override: bool = False) -> Parameter:
        if name in self.parameters:
            raise RuntimeError(f"parameter {name!r} already declared")
        param = Parameter(name, value, descriptor or ParameterDescriptor())
        self.parameters[name] = param
        return param

    def get_parameter(self, name: str) -> Parameter:
        return self.parameters[name]

    def get_logger(self) -> RcutilsLogger:
        return self._logger

    def count_publishers(self, topic_name: str) -> int:
        with GRAPH.lock:
            return sum(1 for p in GRAPH.publishers if p.topic == topic_name)

    def count_subscribers(self, topic_name: str) -> int:
        with GRAPH.lock:
            return sum(1 for s in GRAPH.subscriptions if s.topic == topic_name)

    def get_topic_names_and_types(self, no_demangle: bool = False) -> list[tuple[str, list[str]]]:
        names: dict[str, set[str]] = {}
        with GRAPH.lock:
            for e in [*GRAPH.publishers, *GRAPH.subscriptions]:
                names.setdefault(e.topic, set()).add(e.msg_type._type)
        return [(t, sorted(ts)) for t, ts in sorted(names.items())]

    def get_publishers_info_by_topic(self, topic_name: str,
                                     no_mangle: bool = False) -> list[TopicEndpointInfo]:
        with GRAPH.lock:
            return [
                TopicEndpointInfo(p.node._name, p.node._namespace, p.msg_type._type,
                                  p.qos_profile)
                for p in GRAPH.publishers if p.topic == topic_name
            ]

    def destroy_publisher(self, publisher: Publisher) -> bool:
        with GRAPH.lock:
            if publisher in GRAPH.publishers:
                GRAPH.publishers.remove(publisher)
        return True

    def destroy_subscription(self, subscription: Subscription) -> bool:
        with GRAPH.lock:
            if subscription in GRAPH.subscriptions:
                GRAPH.subscriptions.remove(subscription)
        return True

    def destroy_node(self) -> None:
        for pub in list(self.publishers):
            self.destroy_publisher(pub)
        for sub in list(self.subscriptions):
            self.destroy_subscription(sub)
        self.destroyed = True


def create_node(node_name: str, *, context: Context | None = None, **kwargs: Any) -> Node:
    return Node(node_name, context=context, **kwargs)


class SingleThreadedExecutor:
    """spin_once runs at most one ready callback (or clears one triggered guard)."""

    def __init__(self, *, context: Context | None = None) -> None:
        self.context = context
        self.nodes: list[Node] = []
        self.is_shutdown = False

    def add_node(self, node: Node) -> bool:
        self.nodes.append(node)
        return True

    def _ready(self) -> Any:
        for node in self.nodes:
            for guard in node.guards:
                if guard.triggered:
                    return guard
            for sub in node.subscriptions:
                if sub.queue and sub in GRAPH.subscriptions:
                    return sub
        return None

    def spin_once(self, timeout_sec: float | None = None) -> None:
        if self.is_shutdown:
            raise RuntimeError("executor is shut down")
        cond = self.context.cond
        with cond:
            ready = self._ready()
            if ready is None and (timeout_sec is None or timeout_sec > 0):
                cond.wait(timeout_sec)
                ready = self._ready()
            if ready is None:
                return
            if isinstance(ready, GuardCondition):
                ready.triggered = False
                callback, args = ready.callback, ()
            else:
                data = ready.queue.popleft()
                payload = data if ready.raw else deserialize_message(data, ready.msg_type)
                callback, args = ready.callback, (payload,)
        callback(*args)

    def shutdown(self, timeout_sec: float | None = None) -> bool:
        self.is_shutdown = True
        return True


# -- installing ----------------------------------------------------------------------------


def install(monkeypatch: Any) -> types.ModuleType:
    """Put the fake modules into ``sys.modules``; returns the fake ``rclpy``."""
    GRAPH.publishers.clear()
    GRAPH.subscriptions.clear()
    INIT_CALLS.clear()

    def module(name: str, **attrs: Any) -> types.ModuleType:
        mod = types.ModuleType(name)
        mod.__dict__.update(attrs)
        monkeypatch.setitem(__import__("sys").modules, name, mod)
        return mod

    qos = module("rclpy.qos", QoSProfile=QoSProfile, ReliabilityPolicy=ReliabilityPolicy,
                 DurabilityPolicy=DurabilityPolicy, HistoryPolicy=HistoryPolicy)
    executors = module("rclpy.executors", SingleThreadedExecutor=SingleThreadedExecutor)
    serialization = module("rclpy.serialization", serialize_message=serialize_message,
                           deserialize_message=deserialize_message)
    signals = module("rclpy.signals", SignalHandlerOptions=SignalHandlerOptions)
    logging = module("rclpy.logging", LoggingSeverity=LoggingSeverity)
    rclpy = module("rclpy", init=init, create_node=create_node, Context=Context,
                   qos=qos, executors=executors, serialization=serialization,
                   signals=signals, logging=logging, GRAPH=GRAPH, INIT_CALLS=INIT_CALLS)
    utilities = module("rosidl_runtime_py.utilities", get_message=get_message)
    module("rosidl_runtime_py", utilities=utilities)
    msg = module("rcl_interfaces.msg", ParameterDescriptor=ParameterDescriptor)
    module("rcl_interfaces", msg=msg)
    return rclpy
