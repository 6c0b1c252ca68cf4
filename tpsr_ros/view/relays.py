"""Which view topics to subscribe to, with what QoS: the relay's decisions without ROS.

A topic is relayed once a publisher of its type is in the graph, with a reader profile
that every such publisher matches (:func:`~tpsr_ros.io.qos.adapt_to_publishers`: reliable
only when all are, transient-local only when all are, so latched markers reach a viewer
that joins late), keeping the last :data:`RELAY_DEPTH` messages: a viewer that falls
behind drops old frames instead of holding the robot's publishers back. A later
publisher the subscription cannot hear (a volatile one next to a transient-local one)
calls for a new subscription; publishers of another type are named in a warning.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, replace

from tpsr_ros.io.qos import History, QoSProfile, adapt_to_publishers, compatible
from tpsr_ros.runtime.transport import TopicEndpoint

__all__ = ["RELAY_DEPTH", "Relay", "plan_relays"]

RELAY_DEPTH = 10


@dataclass(frozen=True)
class Relay:
    """A subscription to (re)make: the topic, its type and the reader profile."""

    topic: str
    msgtype: str
    qos: QoSProfile


def reader_qos(offered: Iterable[QoSProfile]) -> QoSProfile:
    """Return a keep-last reader profile that every ``offered`` writer profile matches."""
    return replace(adapt_to_publishers(offered), history=History.KEEP_LAST, depth=RELAY_DEPTH)


def plan_relays(
    publishers: Iterable[TopicEndpoint],
    topics: Mapping[str, str],
    current: Mapping[str, QoSProfile],
) -> tuple[list[Relay], list[tuple[tuple[str, str], str]]]:
    """Subscriptions the graph calls for, and warnings ``(key, message)`` to log once.

    ``topics``: resolved topic -> the type relayed; ``current``: the reader profile of each
    topic subscribed so far. A topic is (re)planned when it has a publisher of its type
    and no subscription yet, or one that some such publisher cannot reach.
    """
    offers: dict[str, list[QoSProfile]] = defaultdict(list)
    warnings: list[tuple[tuple[str, str], str]] = []
    for endpoint in publishers:
        expected = topics.get(endpoint.topic)
        if expected is None:
            continue
        if endpoint.msgtype != expected:
            warnings.append((
                (endpoint.topic, endpoint.msgtype),
                f"not relaying the {endpoint.msgtype} publisher(s) on {endpoint.topic}: "
                f"the view relays {endpoint.topic} as {expected}",
            ))  # fmt: skip
            continue
        offers[endpoint.topic].append(endpoint.qos)
    relays = []
    for topic, offered in sorted(offers.items()):
        held = current.get(topic)
        if held is None or not all(compatible(q, held) for q in offered):
            relays.append(Relay(topic, topics[topic], reader_qos(offered)))
    return relays, warnings
