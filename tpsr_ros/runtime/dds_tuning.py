"""Cyclone DDS settings for large messages (camera images), and the host limit they need.

Why (measured with ``python -m benchmarks.bench_transport``, two processes, reliable
keep-all, 1920x1080 rgb8 = 6.2 MB per message): with Cyclone's defaults the DDS backend
moved 3 messages/s. A sample leaves as one burst of datagrams; Cyclone asks for a 1 MiB
socket receive buffer, the kernel drops what does not fit (about 250 datagrams per image,
counted as UDP ``RcvbufErrors`` in /proc/net/snmp), and every image then waits for the
reliable protocol's heartbeat/NACK repair. The cure is the one ROS 2's DDS tuning guide
gives for Cyclone: a larger socket receive buffer (``Internal/SocketReceiveBufferSize``),
which the kernel grants only up to ``net.core.rmem_max``. Two further costs per image
were measurable once nothing was dropped: 420 datagrams of 14.7 KB (on loopback, where
nothing limits a datagram to the MTU, 64 KB datagrams need a quarter of the system calls),
and fresh pages for every 6 MB buffer (:mod:`tpsr_ros.runtime.allocator`).
"""

from __future__ import annotations

import re
from pathlib import Path

__all__ = [
    "SOCKET_RCVBUF_NEEDED",
    "SOCKET_RCVBUF_REQUEST",
    "config_is_loopback",
    "large_message_config",
    "socket_buffer_problem",
]

SOCKET_RCVBUF_REQUEST = 16 * 1024 * 1024
"""Socket receive buffer Cyclone asks for; the kernel caps it at net.core.rmem_max."""

SOCKET_RCVBUF_NEEDED = 4 * 1024 * 1024
"""net.core.rmem_max below which 1080p images do not reach camera rate (measured)."""

RMEM_MAX_PATH = Path("/proc/sys/net/core/rmem_max")

_BUFFER_CONFIG = (
    "<CycloneDDS><Domain id='any'><Internal>"
    f"<SocketReceiveBufferSize min='default' max='{SOCKET_RCVBUF_REQUEST}B'/>"
    "</Internal></Domain></CycloneDDS>"
)
# Not used on real networks, where a datagram above the MTU is IP-fragmented and one lost
# piece loses all of it (Cyclone's 14720 B default is its compromise there).
_LOOPBACK_DATAGRAM_CONFIG = (
    "<CycloneDDS><Domain id='any'><General>"
    "<MaxMessageSize>65500B</MaxMessageSize><FragmentSize>62000B</FragmentSize>"
    "</General></Domain></CycloneDDS>"
)
_INTERFACE = re.compile(r"<(?:\w+:)?NetworkInterface\b([^>]*)>", re.IGNORECASE)
_OLD_INTERFACE = re.compile(
    r"<(?:\w+:)?NetworkInterfaceAddress>\s*([^<\s]*)\s*<", re.IGNORECASE
)
_ATTRIBUTE = re.compile(r"\b(address|name)\s*=\s*['\"]([^'\"]*)['\"]", re.IGNORECASE)
_FILE_URI = re.compile(r"file://([^,\s<]+)")
_MAX_CONFIG_BYTES = 1 << 20


def large_message_config(*, loopback: bool) -> str:
    """Cyclone XML fragments for large messages; ``loopback`` adds 64 KB datagrams."""
    return _BUFFER_CONFIG + ("," + _LOOPBACK_DATAGRAM_CONFIG if loopback else "")


def _is_loopback_name(value: str) -> bool:
    value = value.strip().lower()
    return value in {"lo", "lo0", "localhost", "::1"} or value.startswith("127.")


def config_is_loopback(uri: str) -> bool:
    """Whether a ``CYCLONEDDS_URI`` confines Cyclone to the loopback interface.

    True when it names at least one network interface and every one named is loopback
    (``127.x``, ``::1``, ``localhost``, ``lo``). Inline XML is read as it is, ``file://``
    URIs (and a bare file name) from their files; a file that cannot be read counts as
    not loopback, so nothing is assumed about it.
    """
    text = uri
    paths = _FILE_URI.findall(uri)
    if not paths and not uri.lstrip().startswith("<"):
        paths = [uri.strip()]
    for path in paths:
        try:
            with open(path, encoding="utf-8", errors="replace") as handle:
                text += handle.read(_MAX_CONFIG_BYTES)
        except OSError:
            return False
    names = [
        [value for _, value in _ATTRIBUTE.findall(attributes)]
        for attributes in _INTERFACE.findall(text)
    ]
    names += [[address] for address in _OLD_INTERFACE.findall(text)]
    return bool(names) and all(
        any(_is_loopback_name(value) for value in values) for values in names
    )


def socket_buffer_problem(rmem_max_path: Path = RMEM_MAX_PATH) -> str | None:
    """A one-line warning when ``net.core.rmem_max`` is too small for large messages.

    None when the limit is large enough, or cannot be read (not Linux).
    """
    try:
        rmem_max = int(rmem_max_path.read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return None
    if rmem_max >= SOCKET_RCVBUF_NEEDED:
        return None
    return (
        f"net.core.rmem_max is {rmem_max} bytes, below the {SOCKET_RCVBUF_NEEDED} the DDS "
        "backend needs for large messages (camera images): they will arrive slowly, and "
        "keep-last subscribers will lose some; raise it with "
        f"'sudo sysctl -w net.core.rmem_max={2 * SOCKET_RCVBUF_NEEDED}' "
        "(README: large messages)"
    )
