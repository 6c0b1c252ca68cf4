"""In-process transport: nodes of one Python process exchange CDR bytes through a bus.

It behaves like the DDS backend where it matters to nodes and tests: the same padded
CDR bytes, QoS matching (a best-effort writer never reaches a reliable reader; a volatile
writer never serves a transient-local reader), endpoints of different types on one topic
never match, transient-local writers replay their last ``depth`` samples to late
joiners, and a keep-last reader drops its oldest undelivered sample when full.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from typing import ClassVar

from tpsr_ros.io.qos import Durability, History, QoSProfile, compatible
from tpsr_ros.runtime.transport import (
    BytesCallback,
    PublisherHandle,
    SubscriptionHandle,
    TopicEndpoint,
    Transport,
    pad_cdr,
)

__all__ = ["InprocBus", "InprocTransport"]


class InprocBus:
    """The shared registry of endpoints; one per process unless a test makes its own."""

    def __init__(self) -> None:
        self.lock = threading.RLock()
        self.publishers: dict[str, list[_Publisher]] = {}
        self.subscriptions: dict[str, list[_Subscription]] = {}
        self.generation = 0
        """Counts changes of ``subscriptions``: a publisher matches its readers again only
        after one (as DDS matches at discovery, not at every sample)."""


_DEFAULT_BUS = InprocBus()


class _Publisher(PublisherHandle):
    def __init__(self, owner: InprocTransport, topic: str, msgtype: str, qos: QoSProfile):
        self.owner, self.topic, self.msgtype, self.qos = owner, topic, msgtype, qos
        keep = qos.depth if qos.history is History.KEEP_LAST else None
        self.history: deque[tuple[bytes, int]] | None = (  # (data, publish time)
            deque(maxlen=keep) if qos.durability is Durability.TRANSIENT_LOCAL else None
        )
        self.closed = False
        self._targets: list[_Subscription] = []
        self._generation = -1  # the bus's generation _targets were matched at

    def matches(self, sub: _Subscription) -> bool:
        return self.msgtype == sub.msgtype and compatible(self.qos, sub.qos)

    def write(self, data: bytes) -> None:
        if self.closed:
            raise RuntimeError(f"publisher on {self.topic} is closed")
        data = pad_cdr(data)
        bus = self.owner.bus
        with bus.lock:
            sent = time.time_ns()  # under the lock: publish times follow publish order
            if self.history is not None:
                self.history.append((data, sent))
            if self._generation != bus.generation:
                subscriptions = bus.subscriptions.get(self.topic, ())
                self._targets = [s for s in subscriptions if self.matches(s)]
                self._generation = bus.generation
            targets = self._targets
        for sub in targets:
            sub.deliver(data, sent)

    def matched_count(self) -> int:
        bus = self.owner.bus
        with bus.lock:
            return sum(1 for s in bus.subscriptions.get(self.topic, ()) if self.matches(s))

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            with self.owner.bus.lock:
                self.owner.bus.publishers[self.topic].remove(self)


class _Subscription(SubscriptionHandle):
    def __init__(
        self,
        owner: InprocTransport,
        topic: str,
        msgtype: str,
        qos: QoSProfile,
        callback: BytesCallback,
    ):
        self.owner, self.topic, self.msgtype, self.qos = owner, topic, msgtype, qos
        self.callback = callback
        keep = qos.depth if qos.history is History.KEEP_LAST else None
        self.queue: deque[tuple[bytes, int]] = deque(maxlen=keep)  # (data, publish time)
        self.closed = False

    def deliver(self, data: bytes, sent: int) -> None:
        with self.owner.ready:
            if not self.closed:
                self.queue.append((data, sent))
                self.owner.ready.notify_all()

    def matched_count(self) -> int:
        bus = self.owner.bus
        with bus.lock:
            return sum(1 for p in bus.publishers.get(self.topic, ()) if p.matches(self))

    def close(self) -> None:
        if not self.closed:
            with self.owner.ready:
                self.closed = True
                self.queue.clear()
            with self.owner.bus.lock:
                self.owner.bus.subscriptions[self.topic].remove(self)
                self.owner.bus.generation += 1


class InprocTransport(Transport):
    """A node on the in-process bus."""

    kind: ClassVar[str] = "inproc"

    def __init__(self, node: str = "/node", bus: InprocBus | None = None) -> None:
        self.node = node
        self.bus = bus or _DEFAULT_BUS
        self.ready = threading.Condition(threading.RLock())
        self._woken = False
        self._pubs: list[_Publisher] = []
        self._subs: list[_Subscription] = []

    def create_publisher(self, topic: str, msgtype: str, qos: QoSProfile) -> PublisherHandle:
        pub = _Publisher(self, topic, msgtype, qos.resolved())
        with self.bus.lock:
            self.bus.publishers.setdefault(topic, []).append(pub)
        self._pubs.append(pub)
        return pub

    def create_subscription(
        self, topic: str, msgtype: str, qos: QoSProfile, callback: BytesCallback
    ) -> SubscriptionHandle:
        sub = _Subscription(self, topic, msgtype, qos.resolved(), callback)
        with self.bus.lock:
            self.bus.subscriptions.setdefault(topic, []).append(sub)
            self.bus.generation += 1
            history = [
                list(p.history)
                for p in self.bus.publishers.get(topic, ())
                if p.history is not None and p.matches(sub)
            ]
        if qos.durability is Durability.TRANSIENT_LOCAL:
            for samples in history:
                for data, sent in samples:
                    sub.deliver(data, sent)
        self._subs.append(sub)
        return sub

    def spin_once(self, timeout_s: float) -> int:
        with self.ready:
            if not self._woken and not any(s.queue for s in self._subs):
                self.ready.wait(max(0.0, timeout_s))
            self._woken = False
            batches = [(s, list(s.queue)) for s in self._subs if s.queue]
            for s, _ in batches:
                s.queue.clear()
        count = 0
        for sub, items in batches:
            for data, sent in items:
                if sub.closed:
                    break
                sub.source_ns = sent
                sub.callback(data)
                count += 1
        return count

    def wake(self) -> None:
        with self.ready:
            self._woken = True
            self.ready.notify_all()

    def publishers(self) -> list[TopicEndpoint]:
        with self.bus.lock:
            return [
                TopicEndpoint(p.topic, p.msgtype, p.qos, p.owner.node)
                for pubs in self.bus.publishers.values()
                for p in pubs
            ]

    def close(self) -> None:
        for pub in list(self._pubs):
            pub.close()
        for sub in list(self._subs):
            sub.close()
        self._pubs.clear()
        self._subs.clear()
