"""QoS profiles with ROS 2's defaults, their text form for msgs_doc, and bag conversions.

Only the policies that decide whether two endpoints match or lose data are modelled:
reliability, durability, history and depth. Deadline, lifespan and liveliness keep
ROS 2's defaults (infinite / automatic) in every backend.

Matching follows DDS: a best-effort writer never reaches a reliable reader, and a
volatile writer never serves a transient-local reader. Depth never matters for matching.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from enum import Enum

from rosbags.interfaces import (
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)

from tpsr_ros.core.errors import ConfigError

__all__ = [
    "CLOCK_QOS",
    "DEFAULT_QOS",
    "LATCHED_QOS",
    "SENSOR_DATA_QOS",
    "Durability",
    "History",
    "QoSProfile",
    "Reliability",
    "adapt_to_publishers",
    "compatible",
    "from_bag_qos",
    "parse_qos_text",
    "to_bag_qos",
]


class Reliability(str, Enum):
    """Whether lost samples are repaired (``reliable``) or not (``best_effort``)."""

    RELIABLE = "reliable"
    BEST_EFFORT = "best_effort"


class Durability(str, Enum):
    """Whether late-joining readers get the writer's last samples (``transient_local``)."""

    VOLATILE = "volatile"
    TRANSIENT_LOCAL = "transient_local"


class History(str, Enum):
    """Keep the last ``depth`` samples, or all of them."""

    KEEP_LAST = "keep_last"
    KEEP_ALL = "keep_all"


@dataclass(frozen=True)
class QoSProfile:
    """A ROS 2 QoS profile (reliability, durability, history, depth)."""

    reliability: Reliability = Reliability.RELIABLE
    durability: Durability = Durability.VOLATILE
    history: History = History.KEEP_LAST
    depth: int = 10

    def __post_init__(self) -> None:
        object.__setattr__(self, "reliability", Reliability(self.reliability))
        object.__setattr__(self, "durability", Durability(self.durability))
        object.__setattr__(self, "history", History(self.history))
        if self.history is History.KEEP_LAST and self.depth < 1:
            raise ConfigError(f"keep_last QoS needs depth >= 1, got {self.depth}")

    def __str__(self) -> str:
        history = (
            f"keep_last({self.depth})" if self.history is History.KEEP_LAST else "keep_all"
        )
        return f"{self.reliability.value}, {self.durability.value}, {history}"


DEFAULT_QOS = QoSProfile()
"""ROS 2's default: reliable, volatile, keep-last 10."""

SENSOR_DATA_QOS = QoSProfile(Reliability.BEST_EFFORT, Durability.VOLATILE, History.KEEP_LAST, 5)
"""ROS 2's sensor-data profile: best-effort, volatile, keep-last 5."""

LATCHED_QOS = QoSProfile(Reliability.RELIABLE, Durability.TRANSIENT_LOCAL, History.KEEP_LAST, 1)
"""Reliable, transient-local, depth 1: late joiners get the last sample."""

CLOCK_QOS = QoSProfile(Reliability.BEST_EFFORT, Durability.VOLATILE, History.KEEP_LAST, 10)
"""What ``/clock`` is read with: best effort, so /clock from any publisher matches (rosbag2
publishes it best-effort)."""

_TEXT = re.compile(
    r"^\s*(?P<rel>reliable|best_effort)\s*,\s*(?P<dur>volatile|transient_local)\s*,\s*"
    r"(?:keep_last\(\s*(?P<depth>\d+)\s*\)|(?P<all>keep_all))\s*$"
)


def parse_qos_text(text: str) -> QoSProfile:
    """Inverse of ``str(profile)``: ``"reliable, volatile, keep_last(10)"``."""
    match = _TEXT.match(text)
    if match is None:
        raise ConfigError(
            f"QoS {text!r} is not '<reliable|best_effort>, <volatile|transient_local>, "
            "<keep_last(N)|keep_all>'"
        )
    if match["all"]:
        return QoSProfile(match["rel"], match["dur"], History.KEEP_ALL, 0)
    return QoSProfile(match["rel"], match["dur"], History.KEEP_LAST, int(match["depth"]))


def compatible(offered: QoSProfile, requested: QoSProfile) -> bool:
    """Whether a writer offering ``offered`` matches a reader requesting ``requested``."""
    if requested.reliability is Reliability.RELIABLE and (
        offered.reliability is Reliability.BEST_EFFORT
    ):
        return False
    return not (
        requested.durability is Durability.TRANSIENT_LOCAL
        and offered.durability is Durability.VOLATILE
    )


def adapt_to_publishers(offered: Iterable[QoSProfile]) -> QoSProfile:
    """Reader profile that matches every offered profile while losing as little as possible.

    Like rosbag2's recorder: reliable only when every publisher is reliable, transient-local
    only when every publisher is; history keep-all so a slow reader never overwrites.
    """
    offered = list(offered)
    reliable = bool(offered) and all(q.reliability is Reliability.RELIABLE for q in offered)
    latched = bool(offered) and all(q.durability is Durability.TRANSIENT_LOCAL for q in offered)
    return QoSProfile(
        Reliability.RELIABLE if reliable else Reliability.BEST_EFFORT,
        Durability.TRANSIENT_LOCAL if latched else Durability.VOLATILE,
        History.KEEP_ALL,
        0,
    )


_INFINITE = QosTime(sec=2147483647, nsec=4294967295)


def to_bag_qos(profile: QoSProfile) -> Qos:
    """Rosbags ``Qos`` (as stored in a bag's ``offered_qos_profiles``) for ``profile``."""
    return Qos(
        history=QosHistory.KEEP_LAST
        if profile.history is History.KEEP_LAST
        else QosHistory.KEEP_ALL,
        depth=profile.depth,
        reliability=QosReliability.RELIABLE
        if profile.reliability is Reliability.RELIABLE
        else QosReliability.BEST_EFFORT,
        durability=QosDurability.TRANSIENT_LOCAL
        if profile.durability is Durability.TRANSIENT_LOCAL
        else QosDurability.VOLATILE,
        deadline=_INFINITE,
        lifespan=_INFINITE,
        liveliness=QosLiveliness.AUTOMATIC,
        liveliness_lease_duration=_INFINITE,
        avoid_ros_namespace_conventions=False,
    )


def from_bag_qos(profiles: Sequence[Qos]) -> QoSProfile | None:
    """Publisher profile that replays a topic like its recorded publishers offered it.

    Reliable unless any recorded publisher was best-effort, transient-local only if all
    were, depth the largest recorded. ``None`` when nothing was recorded.
    """
    if not profiles:
        return None
    reliable = all(q.reliability is not QosReliability.BEST_EFFORT for q in profiles)
    latched = all(q.durability is QosDurability.TRANSIENT_LOCAL for q in profiles)
    depth = max((int(q.depth) for q in profiles if q.history is QosHistory.KEEP_LAST), default=0)
    return QoSProfile(
        Reliability.RELIABLE if reliable else Reliability.BEST_EFFORT,
        Durability.TRANSIENT_LOCAL if latched else Durability.VOLATILE,
        History.KEEP_LAST,
        depth if depth > 0 else DEFAULT_QOS.depth,
    )
