"""Where a Cyclone DDS node looks for its peers: ROS 2 Jazzy's discovery variables.

``ROS_DOMAIN_ID`` picks the domain; ``ROS_AUTOMATIC_DISCOVERY_RANGE`` = ``SUBNET``
(default: multicast), ``LOCALHOST`` (or the older ``ROS_LOCALHOST_ONLY=1``: the loopback
interface, unicast discovery of the participants on this host, as rmw_cyclonedds_cpp and
rmw_fastrtps_cpp do) or ``OFF`` (no discovery at all), and ``ROS_STATIC_PEERS``
(``;``-separated addresses also contacted, except with ``OFF``). A ``CYCLONEDDS_URI``
replaces all of it. :func:`domain_config` is the Cyclone configuration a node's domain is
created with (:mod:`tpsr_ros.runtime.dds`).
"""

from __future__ import annotations

import os
from typing import Any

from tpsr_ros.core.errors import ConfigError
from tpsr_ros.runtime.allocator import tune_allocator
from tpsr_ros.runtime.dds_tuning import (
    config_is_loopback,
    large_message_config,
    socket_buffer_problem,
)

__all__ = [
    "LAST_SAFE_DOMAIN_ID",
    "configure_domain",
    "discovery_config",
    "discovery_port",
    "discovery_range_from_env",
    "domain_config",
    "domain_id_from_env",
    "localhost_only_from_env",
    "port_hint",
]

# close() waits (bounded) for reliable data to be acknowledged itself; lingering again in
# every writer's deletion (Cyclone's default: up to 1 s each, one after the other) would
# only delay the exit when a matched reader died without unsubscribing.
_LINGER_CONFIG = (
    "<CycloneDDS><Domain id='any'><Internal>"
    "<WriterLingerDuration>10 ms</WriterLingerDuration>"
    "</Internal></Domain></CycloneDDS>"
)
# Unicast discovery probes the ports of participant indices 0..this on each peer.
_MAX_PARTICIPANT_INDEX = 32
_RANGES = ("SUBNET", "LOCALHOST", "OFF", "SYSTEM_DEFAULT")


def domain_id_from_env() -> int:
    """``ROS_DOMAIN_ID`` as an integer in 0..232 (default 0)."""
    text = os.environ.get("ROS_DOMAIN_ID", "").strip()
    if not text:
        return 0
    try:
        value = int(text)
    except ValueError:
        raise ConfigError(f"ROS_DOMAIN_ID={text!r} is not an integer") from None
    if not 0 <= value <= 232:
        raise ConfigError(f"ROS_DOMAIN_ID={value} is outside 0..232")
    return value


LAST_SAFE_DOMAIN_ID = 101
"""The highest domain id ROS 2 recommends on Linux: above it the discovery port
(:func:`discovery_port`) lies in the kernel's ephemeral port range (32768 and up), where
any socket of the machine may already hold it."""


def discovery_port(domain_id: int) -> int:
    """The domain's multicast discovery port (DDSI-RTPS defaults: ``PB + DG * id``)."""
    return 7400 + 250 * domain_id


def port_hint(domain_id: int) -> str:
    """Why joining ``domain_id`` may fail for reasons outside this process, if it may."""
    if domain_id <= LAST_SAFE_DOMAIN_ID:
        return ""
    return (
        f" (domain {domain_id} listens on UDP port {discovery_port(domain_id)}, inside "
        "Linux's ephemeral port range, where another socket may hold it; ROS 2 recommends "
        "ROS_DOMAIN_ID 0..101)"
    )


def discovery_range_from_env() -> str:
    """``ROS_AUTOMATIC_DISCOVERY_RANGE`` (SUBNET, LOCALHOST, OFF, SYSTEM_DEFAULT).

    Unset or empty: LOCALHOST if the older ``ROS_LOCALHOST_ONLY=1`` is set, else SUBNET.
    """
    text = os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE", "").strip().upper()
    if not text:
        return "LOCALHOST" if os.environ.get("ROS_LOCALHOST_ONLY", "") == "1" else "SUBNET"
    if text not in _RANGES:
        raise ConfigError(
            f"ROS_AUTOMATIC_DISCOVERY_RANGE={text!r} is not one of {', '.join(_RANGES)}"
        )
    return text


def localhost_only_from_env() -> bool:
    """Whether ROS 2's environment asks for loopback-only discovery."""
    return discovery_range_from_env() == "LOCALHOST"


def discovery_config(discovery_range: str, static_peers: list[str]) -> str:
    """Cyclone XML for ROS 2's discovery range and static peers ('' = Cyclone's defaults).

    LOCALHOST: the loopback interface without multicast; each process takes a participant
    index (``auto``) and contacts the indices 0..32 of ``localhost`` and the static peers,
    which is where Fast DDS and rmw_cyclonedds_cpp nodes with LOCALHOST listen. OFF: no
    multicast and no predictable unicast ports, so nothing is discovered (static peers
    are ignored, as ROS 2 does). SUBNET: multicast, plus the static peers.
    """
    if discovery_range == "SYSTEM_DEFAULT" or (discovery_range == "SUBNET" and not static_peers):
        return ""
    if discovery_range == "OFF":
        return (
            "<CycloneDDS><Domain id='any'><General><AllowMulticast>false</AllowMulticast>"
            "</General><Discovery><ParticipantIndex>none</ParticipantIndex></Discovery>"
            "</Domain></CycloneDDS>"
        )
    general = ""
    peers = list(static_peers)
    if discovery_range == "LOCALHOST":
        general = (
            "<General><Interfaces><NetworkInterface address='127.0.0.1'/></Interfaces>"
            "<AllowMulticast>false</AllowMulticast></General>"
        )
        peers.insert(0, "localhost")
    peer_xml = "".join(f"<Peer address='{p}'/>" for p in peers)
    return (
        f"<CycloneDDS><Domain id='any'>{general}<Discovery>"
        f"<ParticipantIndex>auto</ParticipantIndex>"
        f"<MaxAutoParticipantIndex>{_MAX_PARTICIPANT_INDEX}</MaxAutoParticipantIndex>"
        f"<Peers>{peer_xml}</Peers></Discovery></Domain></CycloneDDS>"
    )


def _static_peers_from_env() -> list[str]:
    peers = [p.strip() for p in os.environ.get("ROS_STATIC_PEERS", "").split(";")]
    for peer in filter(None, peers):
        if any(c in peer for c in "<>'\"&") or any(c.isspace() for c in peer):
            raise ConfigError(f"ROS_STATIC_PEERS has an invalid address {peer!r}")
    return [p for p in peers if p]


_DOMAINS: dict[int, Any] = {}


def domain_config() -> str:
    """The Cyclone configuration our domains get: fragments joined by commas, later wins.

    First our large-message tuning (:func:`~tpsr_ros.runtime.dds_tuning.large_message_config`),
    so the user can override any of it; then the user's ``CYCLONEDDS_URI`` (or else what
    ROS 2's discovery variables ask for, :func:`discovery_config`); then our writer-linger
    setting.
    """
    user = os.environ.get("CYCLONEDDS_URI", "").strip()
    if user:
        loopback = config_is_loopback(user)
    else:
        discovery_range = discovery_range_from_env()
        user = discovery_config(discovery_range, _static_peers_from_env())
        loopback = discovery_range == "LOCALHOST"
    fragments = [large_message_config(loopback=loopback), user, _LINGER_CONFIG]
    return ",".join(f for f in fragments if f)


def configure_domain(domain_id: int, domain_cls: Any) -> str | None:
    """Create the process's Cyclone domain ``domain_id`` once, with :func:`domain_config`.

    The domain lives until the process exits: deleting it would delete every participant
    in it, ours or not. If the domain already exists (a participant was created elsewhere
    first) it is left alone. Returns a warning about the host's socket buffer limit when it
    is too small for large messages, the first time only.
    """
    if domain_id in _DOMAINS:
        return None
    config = domain_config()  # a bad environment variable raises ConfigError here
    tune_allocator()
    try:
        _DOMAINS[domain_id] = domain_cls(domain_id, config)
    except Exception:
        _DOMAINS[domain_id] = None
    return socket_buffer_problem()
