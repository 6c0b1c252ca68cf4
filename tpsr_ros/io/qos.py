"""QoS profiles with ROS 2's defaults, their text form for msgs_doc, and bag conversions.

Only the policies that decide whether two endpoints match or lose data are modelled:
reliability, durability, history and depth. Deadline, lifespan and liveliness keep
ROS 2's defaults (infinite / automatic) in every backend.

Matching follows DDS: a best-effort writer never reaches a reliable reader, and a
volatile writer never serves a transient-local reader. Depth never matters for matching.

A remote publisher's history and depth are often unknown: DDS discovery does not carry
them (rmw_fastrtps reports history UNKNOWN, depth 0, for every publisher; Cyclone DDS fills
in the DDS default keep-last 1 for a writer that did not send them). Such a profile has
``History.UNKNOWN`` (depth 0) and is stored in a bag as ``ros2 bag record`` stores it
(``history: unknown``, ``depth: 0``); it is never turned into a made-up depth.
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
    "DEFAULT_DEPTH",
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
    "offered_text",
    "parse_qos_text",
    "profile_from_bag",
    "to_bag_qos",
]

DEFAULT_DEPTH = 10
"""ROS 2's default history depth (``rmw_qos_profile_default``)."""


class Reliability(str, Enum):
    """Whether lost samples are repaired (``reliable``) or not (``best_effort``)."""

    RELIABLE = "reliable"
    BEST_EFFORT = "best_effort"


class Durability(str, Enum):
    """Whether late-joining readers get the writer's last samples (``transient_local``)."""

    VOLATILE = "volatile"
    TRANSIENT_LOCAL = "transient_local"


class History(str, Enum):
    """Keep the last ``depth`` samples, or all of them; or not known (a discovered publisher
    whose middleware does not announce its history)."""

    KEEP_LAST = "keep_last"
    KEEP_ALL = "keep_all"
    UNKNOWN = "unknown"


@dataclass(frozen=True)
class QoSProfile:
    """A ROS 2 QoS profile (reliability, durability, history, depth).

    ``History.UNKNOWN`` has depth 0: the profile of a publisher whose history was not
    discovered. Endpoints are made with :meth:`resolved`.
    """

    reliability: Reliability = Reliability.RELIABLE
    durability: Durability = Durability.VOLATILE
    history: History = History.KEEP_LAST
    depth: int = DEFAULT_DEPTH

    def __post_init__(self) -> None:
        object.__setattr__(self, "reliability", Reliability(self.reliability))
        object.__setattr__(self, "durability", Durability(self.durability))
        object.__setattr__(self, "history", History(self.history))
        if self.history is History.KEEP_LAST and self.depth < 1:
            raise ConfigError(f"keep_last QoS needs depth >= 1, got {self.depth}")
        if self.history is History.UNKNOWN and self.depth != 0:
            raise ConfigError(f"a QoS of unknown history has depth 0, got {self.depth}")

    def __str__(self) -> str:
        if self.history is History.KEEP_LAST:
            history = f"keep_last({self.depth})"
        elif self.history is History.KEEP_ALL:
            history = "keep_all"
        else:
            history = "history unknown"
        return f"{self.reliability.value}, {self.durability.value}, {history}"

    def resolved(self) -> QoSProfile:
        """The profile an endpoint is made with: an unknown history becomes ROS 2's default
        keep-last 10 (as ``ros2 bag play`` offers); a known one is kept."""
        if self.history is not History.UNKNOWN:
            return self
        return QoSProfile(self.reliability, self.durability, History.KEEP_LAST, DEFAULT_DEPTH)


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
    r"(?:keep_last\(\s*(?P<depth>\d+)\s*\)|(?P<all>keep_all)|(?P<unknown>history unknown))"
    r"\s*$"
)


def parse_qos_text(text: str) -> QoSProfile:
    """Inverse of ``str(profile)``: ``"reliable, volatile, keep_last(10)"``."""
    match = _TEXT.match(text)
    if match is None:
        raise ConfigError(
            f"QoS {text!r} is not '<reliable|best_effort>, <volatile|transient_local>, "
            "<keep_last(N)|keep_all|history unknown>'"
        )
    if match["all"]:
        return QoSProfile(match["rel"], match["dur"], History.KEEP_ALL, 0)
    if match["unknown"]:
        return QoSProfile(match["rel"], match["dur"], History.UNKNOWN, 0)
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

_BAG_HISTORY = {
    History.KEEP_LAST: QosHistory.KEEP_LAST,
    History.KEEP_ALL: QosHistory.KEEP_ALL,
    History.UNKNOWN: QosHistory.UNKNOWN,
}


def to_bag_qos(profile: QoSProfile) -> Qos:
    """Rosbags ``Qos`` (as stored in a bag's ``offered_qos_profiles``) for ``profile``.

    An unknown history is stored as ``ros2 bag record`` stores it: ``UNKNOWN`` (``history:
    unknown`` in metadata version 9, ``3`` before), depth 0.
    """
    return Qos(
        history=_BAG_HISTORY[profile.history],
        depth=profile.depth if profile.history is History.KEEP_LAST else 0,
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


def profile_from_bag(qos: Qos) -> QoSProfile:
    """One recorded offered profile as it was offered.

    History other than keep-last / keep-all (``unknown``, ``system_default``), or keep-last
    with a depth below 1, is ``History.UNKNOWN``: the bag does not say the depth.
    """
    reliability = (
        Reliability.BEST_EFFORT
        if qos.reliability is QosReliability.BEST_EFFORT
        else Reliability.RELIABLE
    )
    durability = (
        Durability.TRANSIENT_LOCAL
        if qos.durability is QosDurability.TRANSIENT_LOCAL
        else Durability.VOLATILE
    )
    if qos.history is QosHistory.KEEP_ALL:
        return QoSProfile(reliability, durability, History.KEEP_ALL, 0)
    if qos.history is QosHistory.KEEP_LAST and int(qos.depth) >= 1:
        return QoSProfile(reliability, durability, History.KEEP_LAST, int(qos.depth))
    return QoSProfile(reliability, durability, History.UNKNOWN, 0)


def offered_text(profiles: Sequence[Qos]) -> str:
    """The recorded offered profiles of one topic as text, each distinct one once, joined by
    ``"; "`` (e.g. ``reliable, volatile, history unknown``); ``not recorded`` when none."""
    texts = list(dict.fromkeys(str(profile_from_bag(q)) for q in profiles))
    return "; ".join(texts) if texts else "not recorded"


def from_bag_qos(profiles: Sequence[Qos]) -> QoSProfile | None:
    """Publisher profile that replays a topic like its recorded publishers offered it.

    Reliable unless any recorded publisher was best-effort, transient-local only if all
    were, keep-last with the largest recorded depth, where a publisher of unknown history
    (or keep-all) counts as ROS 2's default depth 10, as ``ros2 bag play`` offers it.
    ``None`` when nothing was recorded.
    """
    if not profiles:
        return None
    reliable = all(q.reliability is not QosReliability.BEST_EFFORT for q in profiles)
    latched = all(q.durability is QosDurability.TRANSIENT_LOCAL for q in profiles)
    depth = max(
        p.depth if p.history is History.KEEP_LAST else DEFAULT_DEPTH
        for p in map(profile_from_bag, profiles)
    )
    return QoSProfile(
        Reliability.RELIABLE if reliable else Reliability.BEST_EFFORT,
        Durability.TRANSIENT_LOCAL if latched else Durability.VOLATILE,
        History.KEEP_LAST,
        depth,
    )
