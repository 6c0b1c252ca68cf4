"""The recorder's decisions without ROS: what to subscribe to, and the ledger of what was lost.

:class:`SubscriptionPlanner` turns the publishers found in the graph into subscriptions to
make: which topics are selected, refusals of a topic published with two types, and the QoS
each subscription takes from its publishers (as rosbag2 adapts it). :class:`LossLedger`
counts, per topic, what was recorded and what was not: lost in the middleware, dropped at
a full write cache, rejected, and missing from a steady cadence of header stamps
(:class:`~tpsr_ros.core.cadence.CadenceGaps`); it gives the totals, the report line and the
values of ``/diagnostics`` and of the bag's ``custom_data``. The node
(:mod:`tpsr_ros.record`) feeds both and does the I/O.
"""

from __future__ import annotations

import json
from collections import defaultdict
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any, Protocol

from tpsr_ros.core.cadence import CadenceGaps
from tpsr_ros.core.errors import BagError
from tpsr_ros.io.messages import jazzy_typestore
from tpsr_ros.io.qos import QoSProfile, adapt_to_publishers, compatible, to_bag_qos

__all__ = [
    "EXCLUDED_BY_DEFAULT",
    "LossLedger",
    "PlannedSubscription",
    "PublisherInfo",
    "SubscriptionPlanner",
]

EXCLUDED_BY_DEFAULT = ("/rosout", "/parameter_events")


class PublisherInfo(Protocol):
    """A publisher as the graph shows it: its topic, type and offered QoS."""

    @property
    def topic(self) -> str: ...
    @property
    def msgtype(self) -> str: ...
    @property
    def qos(self) -> QoSProfile: ...


@dataclass(frozen=True)
class PlannedSubscription:
    """A subscription to make: the topic, its type, the QoS to ask for, the offers to store."""

    topic: str
    msgtype: str
    qos: QoSProfile
    offered: list[dict[str, Any]]


def _hidden(topic: str) -> bool:
    return any(part.startswith("_") for part in topic.split("/"))


class SubscriptionPlanner:
    """Which discovered topics to record, with what QoS (rosbag2's rules).

    ``wanted``: the topics named on the command line (None: all but the hidden ones and
    :data:`EXCLUDED_BY_DEFAULT`).
    """

    def __init__(self, wanted: set[str] | None, include_hidden: bool = False) -> None:
        self.wanted = wanted
        self.include_hidden = include_hidden
        self.subscribed: dict[str, str] = {}
        self.qos: dict[str, QoSProfile] = {}

    def selected(self, topic: str) -> bool:
        """Whether ``topic`` is to be recorded."""
        if self.wanted is not None:
            return topic in self.wanted
        if topic in EXCLUDED_BY_DEFAULT:
            return False
        return self.include_hidden or not _hidden(topic)

    def plan(
        self, publishers: Iterable[PublisherInfo]
    ) -> tuple[list[PlannedSubscription], list[tuple[tuple[str, str], str]]]:
        """The new subscriptions the publishers call for, and warnings ``(key, message)``.

        A topic published with two types, or whose publisher changes the recorded type, is
        a :class:`~tpsr_ros.core.errors.BagError`. A new subscription is remembered here
        once planned.
        """
        by_topic: dict[str, list[PublisherInfo]] = defaultdict(list)
        for endpoint in publishers:
            if self.selected(endpoint.topic):
                by_topic[endpoint.topic].append(endpoint)
        planned: list[PlannedSubscription] = []
        warnings: list[tuple[tuple[str, str], str]] = []
        for topic, endpoints in sorted(by_topic.items()):
            types = sorted({e.msgtype for e in endpoints})
            if len(types) > 1:
                raise BagError(f"topic type clash: {topic} is published as {' and '.join(types)}")
            msgtype = types[0]
            if topic in self.subscribed:
                if self.subscribed[topic] != msgtype:
                    raise BagError(
                        f"topic type clash: {topic} is recorded as {self.subscribed[topic]} "
                        f"but a publisher now offers {msgtype}"
                    )
                for e in endpoints:
                    if not compatible(e.qos, self.qos[topic]):
                        warnings.append((
                            (topic, "qos"),
                            f"a publisher on {topic} offers {e.qos}, which the recorder's "
                            f"{self.qos[topic]} subscription cannot receive",
                        ))  # fmt: skip
                continue
            if msgtype not in jazzy_typestore().fielddefs:
                warnings.append(
                    ((topic, "type"), f"not recording {topic}: unknown message type {msgtype}")
                )
                continue
            qos = adapt_to_publishers(e.qos for e in endpoints)
            offered = [to_bag_qos(e.qos) for e in endpoints]
            self.subscribed[topic] = msgtype
            self.qos[topic] = qos
            planned.append(PlannedSubscription(topic, msgtype, qos, offered))
        return planned, warnings


SENSOR_TYPES = frozenset(
    {
        "sensor_msgs/msg/Image",
        "sensor_msgs/msg/CompressedImage",
        "sensor_msgs/msg/CameraInfo",
        "sensor_msgs/msg/Imu",
        "sensor_msgs/msg/LaserScan",
        "sensor_msgs/msg/PointCloud2",
        "sensor_msgs/msg/NavSatFix",
        "sensor_msgs/msg/Range",
        "sensor_msgs/msg/MagneticField",
        "nav_msgs/msg/Odometry",
    }
)
"""Types whose header stamps follow a sensor's clock, judged for missing messages. Streams
a node derives per step (``/tpsr/state``, commands, rewards) are not: a step the node
skipped (a grid gap) is a gap, not a lost message."""


def judged_by_stamps(msgtype: str) -> bool:
    """Whether messages missing from ``msgtype``'s stamp cadence are counted."""
    return msgtype in SENSOR_TYPES


def is_episode_start(topic: str, msgtype: str) -> bool:
    """``sim_node``'s ``sim/episode_start`` (in any namespace): its stamps are step stamps
    the simulator's sensors leave out on purpose."""
    return topic.endswith("/sim/episode_start") and msgtype == "geometry_msgs/msg/PoseStamped"


class LossLedger:
    """Per topic: recorded, lost, dropped, rejected and missing-by-stamps messages."""

    def __init__(self) -> None:
        self.topics: list[str] = []
        self.recorded: dict[str, int] = defaultdict(int)
        self.lost: dict[str, int] = defaultdict(int)
        self.dropped: dict[str, int] = defaultdict(int)
        self.rejected: dict[str, int] = defaultdict(int)
        self.cadence: dict[str, CadenceGaps] = {}
        self._missing_said: dict[str, int] = defaultdict(int)

    def add_topic(self, topic: str, stamped: bool) -> CadenceGaps | None:
        """Start counting ``topic``; ``stamped``: its messages carry a header stamp to judge."""
        self.topics.append(topic)
        if stamped:
            self.cadence[topic] = CadenceGaps()
            return self.cadence[topic]
        return None

    def skip_stamp(self, stamp_ns: int) -> None:
        """A step stamp no sensor message carries on purpose (a reset): not a loss anywhere."""
        for cadence in self.cadence.values():
            cadence.skip(stamp_ns)

    def index(self, topic: str) -> int:
        """The index of the next message on ``topic`` (recorded or not)."""
        return self.recorded[topic] + self.rejected[topic] + self.dropped[topic]

    def middleware_lost(self, totals: Mapping[str, int]) -> list[str]:
        """What the middleware now reports lost per topic (growing totals); log lines."""
        lines = []
        for topic, total in totals.items():
            if total > self.lost[topic]:
                lines.append(
                    f"lost {total - self.lost[topic]} messages on {topic} before they reached "
                    f"the recorder (reported by the middleware; {total} on this topic so far)"
                )
                self.lost[topic] = total
        return lines

    def new_missing(self) -> list[str]:
        """Log lines for the messages found missing by stamps since the last call."""
        lines = []
        for topic, cadence in self.cadence.items():
            if cadence.missing > self._missing_said[topic]:
                rate = f"{1e9 / cadence.period_ns:.3g} Hz" if cadence.period_ns else "steady"
                lines.append(
                    f"{cadence.missing - self._missing_said[topic]} messages missing on "
                    f"{topic} by its header stamps (a {rate} stream; lost before the recorder, "
                    f"by the publisher or the middleware; {cadence.missing} on this topic so far)"
                )
                self._missing_said[topic] = cadence.missing
            elif cadence.missing < self._missing_said[topic]:
                lines.append(
                    f"{self._missing_said[topic] - cadence.missing} of the messages counted "
                    f"missing on {topic} were stretched frames after all (the stream stretches "
                    f"its frames; {cadence.missing} on this topic so far)"
                )
                self._missing_said[topic] = cadence.missing
        return lines

    def missing_by_stamps(self, topic: str | None = None) -> int:
        """Messages missing from steady header-stamp cadences (one topic, or all)."""
        if topic is not None:
            return self.cadence[topic].missing if topic in self.cadence else 0
        return sum(c.missing for c in self.cadence.values())

    def totals(self) -> tuple[int, int, int, int, int]:
        """(recorded, lost, dropped, rejected, missing by stamps) messages over all topics."""
        return (
            sum(self.recorded.values()),
            sum(self.lost.values()),
            sum(self.dropped.values()),
            sum(self.rejected.values()),
            self.missing_by_stamps(),
        )

    def losses(self) -> str:
        """``lost L (reported by the middleware), dropped D (write cache full), rejected R;
        missing M by header stamps``."""
        _, lost, dropped, rejected, missing = self.totals()
        return (
            f"lost {lost} (reported by the middleware), "
            f"dropped {dropped} (write cache full), rejected {rejected}; "
            f"missing {missing} by header stamps"
        )

    def any_loss(self) -> bool:
        """Whether anything was lost, dropped, rejected or missing."""
        return any(self.totals()[1:])

    def per_topic(self) -> dict[str, dict[str, int]]:
        """Every count per topic (the bag's ``recorder.by_topic``)."""
        return {
            t: {
                "recorded": self.recorded[t],
                "lost": self.lost[t],
                "dropped": self.dropped[t],
                "rejected": self.rejected[t],
                "missing_by_stamps": self.missing_by_stamps(t),
            }
            for t in sorted(self.topics)
        }

    def diagnostics_values(self) -> dict[str, int]:
        """``<topic> recorded`` / ``lost`` / ``dropped`` / ``rejected`` / ``missing by stamps``."""
        values: dict[str, int] = {}
        for topic, counts in self.per_topic().items():
            for name, value in counts.items():
                values[f"{topic} {name.replace('_', ' ')}"] = value
        return values

    def custom_data(self) -> dict[str, str]:
        """The bag's ``recorder.*`` entries."""
        _, lost, dropped, rejected, missing = self.totals()
        return {
            "recorder.lost_messages": str(lost),
            "recorder.dropped_messages": str(dropped),
            "recorder.rejected_messages": str(rejected),
            "recorder.missing_by_stamps": str(missing),
            "recorder.by_topic": json.dumps(self.per_topic()),
        }
