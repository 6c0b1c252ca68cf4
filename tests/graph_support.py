"""What the multi-process graph tests share: the loopback Cyclone configuration, the two
real backends as pytest parameters, and fresh DDS domains."""

from __future__ import annotations

import itertools
import os

import pytest

__all__ = ["BACKENDS", "LOOPBACK", "fresh_domain", "rclpy_available"]

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


# ROS 2 asks for domain ids 0..101 on Linux: a domain's discovery port is 7400 + 250 * id,
# and above id 101 it falls in the kernel's ephemeral port range (32768..60999), where any
# other socket of the machine may already hold it ("failed to bind ... address in use").
# Domain 0 is left to whatever ROS 2 system runs on the machine.
FIRST_TEST_DOMAIN, LAST_TEST_DOMAIN = 1, 101


def fresh_domain(salt: int = 0) -> int:
    """A DDS domain id in 1..101 that no participant of this process has configured yet.

    Cyclone keeps one configuration per domain and process: in a domain an earlier test
    opened (say without the loopback URI, or with other discovery variables), a probe
    would not discover the children and the new variables would never be read. Runs of
    different processes start from different places (the pid), so parallel test runs on
    one machine rarely meet.
    """
    from tpsr_ros.runtime import dds

    span = LAST_TEST_DOMAIN - FIRST_TEST_DOMAIN + 1
    seed = os.getpid() * 7 + 31 * salt + 3 * next(_COUNTER)
    for k in range(span):
        candidate = (seed + k) % span + FIRST_TEST_DOMAIN
        if candidate not in dds._DOMAINS:
            return candidate
    raise RuntimeError(f"this test process has configured all {span} test domains")
