"""The node base class shared by every node.

A node subclasses :class:`Node`, names its parameter dataclass in ``Params`` and creates
its publishers, subscriptions and timers in :meth:`Node.setup`::

    class Talker(Node):
        default_name = "talker"
        Params = TalkerParams

        def setup(self) -> None:
            self.pub = self.create_publisher("/chatter", "std_msgs/msg/String")
            self.create_timer(1.0 / self.params.rate, self.tick)

    if __name__ == "__main__":
        run_node(Talker, prog="python -m talker")

:func:`~tpsr_ros.runtime.entry.run_node` is the ``python -m`` boilerplate (command line,
transport, signals, exit status).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar, TextIO

from tpsr_ros.cli import ArgumentParser
from tpsr_ros.core.errors import ConfigError, MessageError, TpsrError
from tpsr_ros.core.units import NS_PER_S as _NS
from tpsr_ros.io.messages import CLOCK_TYPE, deserialize, serialize, stamp_of
from tpsr_ros.io.qos import CLOCK_QOS, DEFAULT_QOS, QoSProfile
from tpsr_ros.runtime.backend import choose_backend, open_transport
from tpsr_ros.runtime.params import (
    USE_SIM_TIME,
    NoParameters,
    coerce,
    format_value,
    param_specs,
    resolve_parameters,
    resolve_standard_parameters,
)
from tpsr_ros.runtime.ros_args import (
    LOG_LEVELS,
    RosArgs,
    UsageError,
)
from tpsr_ros.runtime.transport import PublisherHandle, SubscriptionHandle, Transport

__all__ = [
    "EndpointInfo",
    "Logger",
    "Node",
    "NodeOptions",
    "Publisher",
    "Subscription",
    "Timer",
]

_MAX_WAIT_S = 0.1  # bound on one blocking wait, so signals are handled promptly
_NEVER_NS = 2**63  # a deadline later than any monotonic clock reading
TRIGGER_TYPE = "std_srvs/srv/Trigger"
"""The service type of :meth:`Node.create_trigger_service`."""

class Logger:
    """ROS-style console logger: ``[INFO] [1700000000.123456789] [node]: message``."""

    def __init__(
        self,
        name: str,
        level: str = "info",
        *,
        stream: TextIO | None = None,
        enabled: bool = True,
    ) -> None:
        self.name = name
        self.level = level
        self.enabled = enabled
        self.stream = stream
        self.transport: Transport | None = None

    def is_enabled_for(self, level: str) -> bool:
        """Whether a message of ``level`` is printed."""
        return LOG_LEVELS.index(level) >= LOG_LEVELS.index(self.level)

    def _log(self, level: str, message: str) -> None:
        if not self.is_enabled_for(level):
            return
        if self.transport is not None and self.transport.log(level, message):
            return
        if not self.enabled:
            return
        now = time.time_ns()
        stream = self.stream or sys.stderr
        stream.write(
            f"[{level.upper()}] [{now // _NS}.{now % _NS:09d}] [{self.name}]: {message}\n"
        )
        stream.flush()

    def debug(self, message: str) -> None:
        """Log at debug level."""
        self._log("debug", message)

    def info(self, message: str) -> None:
        """Log at info level."""
        self._log("info", message)

    def warning(self, message: str) -> None:
        """Log at warn level."""
        self._log("warn", message)

    warn = warning

    def error(self, message: str) -> None:
        """Log at error level."""
        self._log("error", message)

    def fatal(self, message: str) -> None:
        """Log at fatal level."""
        self._log("fatal", message)


@dataclass(frozen=True)
class EndpointInfo:
    """A publisher or subscription a node created (for msgs_doc checks and tools)."""

    kind: str  # "publisher" | "subscription" | "service"
    topic: str
    msgtype: str
    qos: QoSProfile


@dataclass(frozen=True)
class NodeOptions:
    """Everything a node is started with: name, namespace, parameters, remaps, logging."""

    name: str
    namespace: str = "/"
    params: Any = dataclasses.field(default_factory=NoParameters)
    ros_args: RosArgs = dataclasses.field(default_factory=RosArgs)
    log_level: str = "info"
    transport: str | None = None
    args: argparse.Namespace | None = None
    use_sim_time: bool = False

    @classmethod
    def for_node(
        cls,
        node_cls: type[Node],
        ros_args: RosArgs | None = None,
        *,
        args: argparse.Namespace | None = None,
        transport: str | None = None,
        **params: Any,
    ) -> NodeOptions:
        """Options of ``node_cls`` from parsed ROS arguments (plus ``params`` overrides)."""
        ros_args = ros_args or RosArgs()
        name = ros_args.node_name(node_cls.default_name)
        namespace = ros_args.namespace(name)
        fqn = namespace.rstrip("/") + "/" + name
        values = resolve_parameters(node_cls.Params, ros_args, fqn)
        standard = resolve_standard_parameters(node_cls.Params, ros_args, fqn)
        if params:
            values = dataclasses.replace(values, **params)
        logger = fqn.strip("/").replace("/", ".")
        return cls(
            name=name,
            namespace=namespace,
            params=values,
            ros_args=ros_args,
            log_level=ros_args.log_level(logger),
            transport=transport,
            args=args,
            use_sim_time=bool(standard["use_sim_time"]),
        )


class Publisher:
    """Publishes messages (rosbags objects, serialised here) or raw CDR bytes."""

    def __init__(self, handle: PublisherHandle, topic: str, msgtype: str, qos: QoSProfile):
        self._handle, self.topic, self.msgtype, self.qos = handle, topic, msgtype, qos

    def publish(self, msg: Any) -> None:
        """Serialise ``msg`` (a rosbags message of ``msgtype``) and publish it."""
        self._handle.write(serialize(msg, self.msgtype))

    def publish_raw(self, data: bytes | bytearray | memoryview) -> None:
        """Publish CDR bytes unchanged (e.g. read from a bag)."""
        self._handle.write(bytes(data))

    def get_subscription_count(self) -> int:
        """Subscriptions currently matched, in any process."""
        return self._handle.matched_count()

    def wait_for_all_acked(self, timeout_s: float) -> bool:
        """Wait, up to ``timeout_s``, until every matched reliable subscription has
        acknowledged all that was published (as rclpy's method of this name); whether it has."""
        return self._handle.wait_for_acks(timeout_s)

    def destroy(self) -> None:
        """Remove the publisher from the graph."""
        self._handle.close()


class Subscription:
    """A subscription; its callback runs inside :meth:`Node.spin`."""

    def __init__(self, topic: str, msgtype: str, qos: QoSProfile, raw: bool) -> None:
        self.topic, self.msgtype, self.qos, self.raw = topic, msgtype, qos, raw
        self._handle: SubscriptionHandle | None = None

    def get_publisher_count(self) -> int:
        """Publishers currently matched, in any process."""
        return self._handle.matched_count() if self._handle is not None else 0

    def get_lost_count(self) -> int:
        """Messages the middleware reported lost on this subscription so far."""
        return self._handle.lost_count() if self._handle is not None else 0

    @property
    def source_ns(self) -> int | None:
        """In the callback: the message's publish time (see ``SubscriptionHandle``), or None."""
        return self._handle.source_ns if self._handle is not None else None

    def destroy(self) -> None:
        """Remove the subscription; its callback is not called again."""
        if self._handle is not None:
            self._handle.close()


class Timer:
    """A periodic callback on the node's (monotonic) wall clock; missed ticks are skipped."""

    def __init__(self, period_s: float, callback: Callable[[], None]) -> None:
        self.period_ns = round(period_s * _NS) if period_s > 0 else 0
        if self.period_ns < 1:  # 1/rate for a rate of 2**63 Hz rounds to 0 ns
            raise TpsrError(f"timer period must be at least 1 ns, got {period_s} s")
        self.callback = callback
        self.next_ns = time.monotonic_ns() + self.period_ns
        self.cancelled = False

    def cancel(self) -> None:
        """Stop calling the callback."""
        self.cancelled = True

    def _fire(self, now_ns: int) -> None:
        self.callback()
        self.next_ns += self.period_ns
        if self.next_ns <= now_ns:  # fell behind: skip missed ticks, never burst
            missed = (now_ns - self.next_ns) // self.period_ns + 1
            self.next_ns += missed * self.period_ns


class Node:
    """Base of every tpsr-ros node; subclasses override :meth:`setup` and hooks."""

    default_name: ClassVar[str] = "node"
    Params: ClassVar[type] = NoParameters
    description: ClassVar[str] = ""

    def __init__(
        self,
        options: NodeOptions | None = None,
        *,
        transport: Transport | None = None,
        prepared: Any = None,
    ) -> None:
        self.options = options or NodeOptions.for_node(type(self))
        self.params: Any = self.options.params
        self.prepared = prepared
        """What :meth:`preflight` returned (e.g. a file it opened), for :meth:`setup`."""
        self.name = self.options.name
        self.namespace = self.options.namespace
        self.logger = Logger(
            self.fully_qualified_name.strip("/").replace("/", "."),
            self.options.log_level,
            enabled="--disable-stdout-logs" not in self.options.ros_args.flags,
        )
        self._endpoints: list[EndpointInfo] = []
        self._timers: list[Timer] = []
        self._next_timer_ns = _NEVER_NS  # no timer is due before (a cancelled one may be)
        self._shutdown_reason: str | None = None
        self._closed = False
        if transport is None:
            backend, note = choose_backend(self.options.transport)
            ros_args = self.options.ros_args
            transport = open_transport(
                backend, self.name, self.namespace, enclave=ros_args.enclave or "/",
                ros_args=ros_args.tokens, use_sim_time=self.options.use_sim_time,
            )  # fmt: skip
            if note:
                self.logger.info(note)
            if backend == "inproc":
                self.logger.info("inproc transport: only nodes in this process can talk to it")
        self.transport = transport
        # rclpy logs (console and /rosout) itself; the DDS backend publishes /rosout and
        # lets this logger print
        self.logger.transport = transport
        transport.set_log_level(self.options.log_level)
        transport.set_warning_sink(self.logger.warning)
        try:
            self._sim_time: int | None = None  # the newest /clock (use_sim_time)
            self._clock_sub: Subscription | None = None
            self._follow_clock(self.options.use_sim_time)
            specs = param_specs(type(self.params))
            self.transport.declare_parameters(
                [(spec, getattr(self.params, spec.name)) for spec in specs],
                self._check_parameter_change,
            )
            self.setup()
        except BaseException:
            self.transport.close()
            self._closed = True
            raise

    # -- to override -----------------------------------------------------------------

    def setup(self) -> None:
        """Create publishers, subscriptions and timers (called once by ``__init__``)."""

    def on_shutdown(self) -> None:
        """Called once by :meth:`close` before the transport closes (log totals, close files)."""

    def on_parameter_change(self, name: str, value: Any) -> str | None:
        """Apply a valid runtime change of parameter ``name``; None if applied, else why not.

        The default refuses: the nodes read their parameters once, at start-up.
        """
        return (
            f"parameter {name!r} is fixed at start-up; restart the node with "
            f"-p {name}:={format_value(value)}"
        )

    @property
    def use_sim_time(self) -> bool:
        """Whether :meth:`now_ns` follows ``/clock`` (parameter ``use_sim_time``)."""
        return self._clock_sub is not None

    def now_ns(self) -> int:
        """The node's time: the newest ``/clock`` with ``use_sim_time`` (0 before the first,
        as in ROS 2), else the system clock."""
        if self._clock_sub is None:
            return time.time_ns()
        return self._sim_time or 0

    def _follow_clock(self, enabled: bool) -> None:
        if enabled and self._clock_sub is None:

            def on_clock(msg: Any) -> None:
                self._sim_time = stamp_of(msg)

            self._clock_sub = self.create_subscription("/clock", CLOCK_TYPE, on_clock, CLOCK_QOS)
        elif not enabled and self._clock_sub is not None:
            self._clock_sub.destroy()
            self._clock_sub = None

    def _check_parameter_change(self, name: str, value: object) -> str | None:
        """A runtime set (``ros2 param set``): validated as at start-up, then the node's call."""
        if name == USE_SIM_TIME.name:
            try:
                self._follow_clock(bool(coerce(USE_SIM_TIME, value, "set")))
            except UsageError as exc:
                return str(exc)
            return None
        specs = {s.name: s for s in param_specs(type(self.params))}
        if name not in specs:
            return f"unknown parameter {name!r}"
        try:
            coerced = coerce(specs[name], value, "set")
            changed = dataclasses.replace(self.params, **{name: coerced})
        except (UsageError, ConfigError) as exc:
            return str(exc)
        reason = self.on_parameter_change(name, coerced)
        if reason is None:
            self.params = changed
        return reason

    @classmethod
    def preflight(cls, options: NodeOptions) -> Any:
        """Checks before joining the graph (e.g. an output path); raise a TpsrError.

        What it returns (e.g. a file it had to open to check it) reaches :meth:`setup` as
        ``self.prepared``, so nothing is read twice.
        """
        return None

    @classmethod
    def argument_parser(cls, prog: str) -> ArgumentParser:
        """Parser of the node's own (non-ROS) options; nodes with options override it."""
        return ArgumentParser(prog=prog, description=cls.description, add_help=False)

    # -- names -----------------------------------------------------------------------

    @property
    def fully_qualified_name(self) -> str:
        """``/namespace/name``."""
        return self.namespace.rstrip("/") + "/" + self.name

    def _expand(self, name: str) -> str:
        if name.startswith("~"):
            name = self.fully_qualified_name + "/" + name[1:].lstrip("/")
        elif not name.startswith("/"):
            name = self.namespace.rstrip("/") + "/" + name
        return name.rstrip("/") or "/"

    def resolve_topic(self, name: str) -> str:
        """Fully qualified topic name after namespace expansion and ``-r`` remapping."""
        if not name or any(c.isspace() for c in name) or "//" in name:
            raise TpsrError(f"invalid topic name {name!r}")
        full = self._expand(name)
        for rule in self.options.ros_args.topic_remaps(self.name):
            if self._expand(rule.source) == full:
                return self._expand(rule.target)
        return full

    # -- endpoints -------------------------------------------------------------------

    def create_publisher(
        self, topic: str, msgtype: str, qos: QoSProfile = DEFAULT_QOS
    ) -> Publisher:
        """Publisher of ``msgtype`` (e.g. ``sensor_msgs/msg/Image``) on ``topic``."""
        resolved = self.resolve_topic(topic)
        handle = self.transport.create_publisher(resolved, msgtype, qos)
        self._endpoints.append(EndpointInfo("publisher", resolved, msgtype, qos))
        return Publisher(handle, resolved, msgtype, qos)

    def create_subscription(
        self,
        topic: str,
        msgtype: str,
        callback: Callable[[Any], None],
        qos: QoSProfile = DEFAULT_QOS,
        *,
        raw: bool = False,
    ) -> Subscription:
        """Subscription calling ``callback(msg)``, or ``callback(cdr_bytes)`` when ``raw``.

        A message that cannot be decoded is logged and dropped; the node keeps running.
        """
        resolved = self.resolve_topic(topic)
        sub = Subscription(resolved, msgtype, qos, raw)

        if raw:
            on_bytes: Callable[[bytes], None] = callback
        else:

            def on_bytes(data: bytes) -> None:
                try:
                    msg = deserialize(data, msgtype)
                except MessageError as exc:
                    self.logger.warning(f"dropped a message on {resolved}: {exc}")
                    return
                callback(msg)

        sub._handle = self.transport.create_subscription(resolved, msgtype, qos, on_bytes)
        self._endpoints.append(EndpointInfo("subscription", resolved, msgtype, qos))
        return sub

    def create_trigger_service(
        self, name: str, callback: Callable[[], tuple[bool, str]]
    ) -> str | None:
        """Serve ``std_srvs/srv/Trigger`` on ``name`` (``~/x``: under the node's name) where
        the middleware has services (rclpy); the resolved name, or None without services."""
        resolved = self.resolve_topic(name)
        if not self.transport.create_trigger_service(resolved, callback):
            return None
        self._endpoints.append(EndpointInfo("service", resolved, TRIGGER_TYPE, DEFAULT_QOS))
        return resolved

    def create_timer(self, period_s: float, callback: Callable[[], None]) -> Timer:
        """Call ``callback`` every ``period_s`` seconds while spinning."""
        timer = Timer(period_s, callback)
        self._timers.append(timer)
        self._next_timer_ns = min(self._next_timer_ns, timer.next_ns)
        return timer

    def endpoints(self) -> list[EndpointInfo]:
        """Publishers and subscriptions created so far."""
        return list(self._endpoints)

    # -- executing -------------------------------------------------------------------

    def ok(self) -> bool:
        """False once shutdown was requested."""
        return self._shutdown_reason is None

    def request_shutdown(self, reason: str = "shutdown requested") -> None:
        """Make :meth:`spin` return (safe from signal handlers and other threads)."""
        if self._shutdown_reason is None:
            self._shutdown_reason = reason
        self.transport.wake()

    @property
    def shutdown_reason(self) -> str | None:
        """Why the node is shutting down, or None."""
        return self._shutdown_reason

    def _run_timers(self) -> float:
        """Run due timers; seconds until the next one (inf if none).

        Called twice per :meth:`spin_once`, so when no timer is due yet it only compares
        the clock with the earliest deadline.
        """
        now = time.monotonic_ns()
        if now < self._next_timer_ns:
            return float("inf") if self._next_timer_ns == _NEVER_NS else (
                (self._next_timer_ns - now) / _NS
            )
        self._timers = [t for t in self._timers if not t.cancelled]
        for timer in list(self._timers):
            if not timer.cancelled and timer.next_ns <= now and self.ok():
                timer._fire(now)
        live = [t.next_ns for t in self._timers if not t.cancelled]
        self._next_timer_ns = min(live, default=_NEVER_NS)
        if not live:
            return float("inf")
        return max(0.0, (self._next_timer_ns - time.monotonic_ns()) / _NS)

    def spin_once(self, timeout_s: float = 0.0) -> None:
        """Run due timers, wait for data and run the callbacks of what arrived.

        Waits up to ``timeout_s`` (less if a timer is due, at most 0.1 s).
        """
        until_timer = self._run_timers()
        if self.ok():
            self.transport.spin_once(min(timeout_s, until_timer, _MAX_WAIT_S))
        self._run_timers()

    def spin(
        self, until: Callable[[], bool] | None = None, timeout_s: float | None = None
    ) -> bool:
        """Run callbacks and timers until shutdown, ``until()`` is true or the timeout.

        Returns whether ``until()`` became true (True when spinning until shutdown).
        """
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while self.ok():
            if until is not None and until():
                return True
            remaining = _MAX_WAIT_S if deadline is None else deadline - time.monotonic()
            if remaining <= 0:
                return False
            self.spin_once(min(remaining, _MAX_WAIT_S))
        return until() if until is not None else True

    def wait_for(self, condition: Callable[[], bool], timeout_s: float) -> bool:
        """Spin until ``condition()`` (e.g. the graph connected) or ``timeout_s`` elapses."""
        return self.spin(until=condition, timeout_s=timeout_s)

    def close(self) -> None:
        """Run :meth:`on_shutdown`, then close the transport (bounded wait for acks)."""
        if self._closed:
            return
        self._closed = True
        if self._shutdown_reason is None:
            self._shutdown_reason = "closed"
        try:
            self.on_shutdown()
        finally:
            self.transport.close()

    def __enter__(self) -> Node:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
