"""The middleware interface every backend implements (inproc, dds, rclpy).

A transport moves CDR bytes (ROS 2 serialisation with its 4-byte encapsulation header)
between endpoints named by fully qualified ROS topic names. It knows nothing about
message classes, parameters or remapping: ``tpsr_ros.runtime.node.Node`` adds those.

Threading: callbacks run only inside :meth:`Transport.spin_once`, on the calling
thread, so a node is single-threaded like rclpy's ``SingleThreadedExecutor``.
:meth:`Transport.wake` may be called from any thread or a signal handler.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar

from tpsr_ros.io.qos import QoSProfile

if TYPE_CHECKING:
    from tpsr_ros.runtime.params import ParamSpec

__all__ = [
    "PublisherHandle",
    "SubscriptionHandle",
    "TopicEndpoint",
    "Transport",
    "TriggerCallback",
    "pad_cdr",
]

BytesCallback = Callable[[bytes], None]
ParameterCheck = Callable[[str, object], "str | None"]
"""``check(name, value)``: None to accept a runtime parameter change, else the reason."""
TriggerCallback = Callable[[], "tuple[bool, str]"]
"""A ``std_srvs/srv/Trigger`` request's handler: ``(success, message)`` of the response."""


def pad_cdr(data: bytes | bytearray | memoryview) -> bytes:
    """CDR bytes padded with zeros to a multiple of 4, as they travel on the DDS wire.

    rmw_cyclonedds_cpp and Cyclone DDS pad every serialised sample to 4 bytes, so a
    subscriber sees the padded length; every backend pads on publish so that all of
    them deliver identical bytes. Deserialisers ignore the trailing zeros.
    """
    data = bytes(data)
    extra = -len(data) % 4
    return data + b"\0" * extra if extra else data


@dataclass(frozen=True)
class TopicEndpoint:
    """A publisher or subscription seen in the graph."""

    topic: str
    msgtype: str
    qos: QoSProfile
    node: str | None = None


class PublisherHandle(ABC):
    """Backend publisher: writes CDR bytes."""

    @abstractmethod
    def write(self, data: bytes) -> None:
        """Publish one serialised message."""

    @abstractmethod
    def matched_count(self) -> int:
        """Number of subscriptions currently matched (any process)."""

    def wait_for_acks(self, timeout_s: float) -> bool:
        """Block, up to ``timeout_s``, until every matched reliable subscription has
        acknowledged everything written; whether it has. A subscription acknowledges only
        once its own side of the match is complete. In process: delivery is immediate."""
        return True

    @abstractmethod
    def close(self) -> None:
        """Destroy the endpoint."""


class SubscriptionHandle(ABC):
    """Backend subscription: its callback receives CDR bytes inside ``spin_once``.

    ``source_ns``: while the callback runs, when the message was published (ns on the
    publisher's clock: the DDS source timestamp; in process, the publish time), or None
    where the middleware does not say. Messages of several topics from one publisher are
    put in send order by it, whatever order the subscriptions are served in.
    """

    source_ns: int | None = None

    @abstractmethod
    def matched_count(self) -> int:
        """Number of publishers currently matched (any process)."""

    def lost_count(self) -> int:
        """Messages known lost on this subscription so far (cumulative).

        What each backend can know: rclpy, the larger of Fast DDS's message-lost events and
        the gaps in the publisher's sequence numbers; Cyclone DDS, its sample-lost status
        and the samples a best-effort subscription had to reject (it exposes no sequence
        numbers, so what a remote keep-last writer dropped before this reader had it is
        not seen). 0 from a backend that cannot lose or cannot tell.
        """
        return 0

    @abstractmethod
    def close(self) -> None:
        """Destroy the endpoint; no callback runs after this returns."""


class Transport(ABC):
    """One node's connection to the middleware."""

    kind: ClassVar[str] = "abstract"

    @abstractmethod
    def create_publisher(self, topic: str, msgtype: str, qos: QoSProfile) -> PublisherHandle:
        """Publisher on fully qualified ``topic`` of ROS type ``msgtype``."""

    @abstractmethod
    def create_subscription(
        self, topic: str, msgtype: str, qos: QoSProfile, callback: BytesCallback
    ) -> SubscriptionHandle:
        """Subscription delivering CDR bytes to ``callback``."""

    @abstractmethod
    def spin_once(self, timeout_s: float) -> int:
        """Wait up to ``timeout_s`` for data, then run the callbacks of what has arrived.

        Returns the number of callbacks run; returns early after :meth:`wake`.
        """

    @abstractmethod
    def wake(self) -> None:
        """Make a blocked or the next :meth:`spin_once` return promptly (thread-safe)."""

    @abstractmethod
    def publishers(self) -> list[TopicEndpoint]:
        """Every publisher currently visible in the graph (remote and local)."""

    def create_trigger_service(self, name: str, callback: TriggerCallback) -> bool:
        """Serve ``std_srvs/srv/Trigger`` on fully qualified ``name``: each request calls
        ``callback()`` in the spinning thread (between callbacks, like a message) and its
        ``(success, message)`` is the response. False: this backend has no services (rclpy
        has; the Cyclone DDS and in-process backends offer topics only)."""
        return False

    def declare_parameters(  # noqa: B027
        self, params: list[tuple[ParamSpec, object]], check: ParameterCheck | None = None
    ) -> None:
        """Expose the parameters (declaration and current value) to the middleware.

        rclpy declares them and serves ROS 2's parameter services; a set request is
        answered by ``check`` (refused, with its reason, unless it returns None). Other
        backends keep parameters to the node.
        """

    def log(self, level: str, message: str) -> bool:
        """Log through the middleware's logger; False if the backend has none."""
        return False

    def set_log_level(self, level: str) -> None:  # noqa: B027
        """Set the middleware logger's severity; a backend without a logger ignores it."""

    def set_warning_sink(self, sink: Callable[[str], None]) -> None:  # noqa: B027
        """Where the middleware's own warnings (incompatible QoS, host limits) go.

        A backend that raises none ignores it.
        """

    def limit_keep_all_readers(self, max_samples: int) -> None:  # noqa: B027
        """Bound the unread samples of keep-all subscriptions created from now on.

        A backend that cannot bound its reader caches ignores it.
        """

    @abstractmethod
    def close(self) -> None:
        """Flush reliable data to matched readers (bounded wait) and leave the graph."""
