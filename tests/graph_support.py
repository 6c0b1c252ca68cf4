"""What the multi-process graph tests share: the loopback Cyclone configuration, the two
real backends as pytest parameters, and fresh DDS domains."""

from __future__ import annotations

import itertools
import os
import socket

import pytest

__all__ = ["BACKENDS", "LOOPBACK", "fresh_domain", "hold_discovery_port", "rclpy_available"]

LOOPBACK = (
    "<CycloneDDS><Domain id='any'><General><Interfaces>"
    "<NetworkInterface address='127.0.0.1' multicast='true'/>"
    "</Interfaces></General></Domain></CycloneDDS>"
)
_COUNTER = itertools.count()


def rclpy_available() -> bool:
    """Whether real rclpy (the ros-jazzy wheels or a sourced ROS 2) imports."""
    try:
        import rclpy  # noqa: F401
    except ImportError:
        return False
    return True


BACKENDS = [
    pytest.param("dds", marks=pytest.mark.dds),
    pytest.param(
        "rclpy",
        marks=[
            pytest.mark.rclpy,
            pytest.mark.skipif(not rclpy_available(), reason="rclpy (ROS 2) not importable"),
        ],
    ),
]


def fresh_domain(salt: int = 0) -> int:
    """A DDS domain id in 1..101 that no participant of this process has configured yet.

    Above 101 (``dds.LAST_SAFE_DOMAIN_ID``) another socket of the machine may hold the
    discovery port; domain 0 is left to whatever ROS 2 system runs on the machine.

    Cyclone keeps one configuration per domain and process: in a domain an earlier test
    opened (say without the loopback URI, or with other discovery variables), a probe
    would not discover the children and the new variables would never be read. The
    workers of one ``pytest -n N`` run draw from disjoint residues (domain - 1 mod N), so
    their tests never share a graph; separate runs start from different places (the pid),
    so they rarely meet.
    """
    from tpsr_ros.runtime import dds_discovery

    span = dds_discovery.LAST_SAFE_DOMAIN_ID
    index, workers = _xdist_worker()
    seed = os.getpid() * 7 + 31 * salt + 3 * next(_COUNTER)
    for k in range(span):
        candidate = (seed + k) % span + 1
        # the workers of one run share the domains out: never two tests' graphs in one
        if (candidate - 1) % workers == index and candidate not in dds_discovery._DOMAINS:
            return candidate
    raise RuntimeError(f"this test process has configured all its {span // workers} domains")


def _xdist_worker() -> tuple[int, int]:
    """``(index, count)`` of this pytest-xdist worker; ``(0, 1)`` without workers."""
    name = os.environ.get("PYTEST_XDIST_WORKER", "")  # gw0, gw1, ...
    count = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1") or 1)
    index = int(name[2:]) if name.startswith("gw") and name[2:].isdigit() else 0
    return index % max(count, 1), max(count, 1)


def hold_discovery_port(monkeypatch: pytest.MonkeyPatch, domain_id: int) -> socket.socket | None:
    """Bind ``domain_id``'s discovery port as another program would (None if already taken).

    Clears the discovery variables first, so that the domain gets Cyclone's default
    multicast discovery on every interface, which needs that port.
    """
    from tpsr_ros.runtime.dds import discovery_port

    for name in ("CYCLONEDDS_URI", "ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_LOCALHOST_ONLY"):
        monkeypatch.delenv(name, raising=False)
    holder = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        holder.bind(("0.0.0.0", discovery_port(domain_id)))
    except OSError:
        holder.close()
        return None
    return holder
