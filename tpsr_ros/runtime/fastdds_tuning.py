"""Fast DDS settings under rclpy (rmw_fastrtps_cpp), the way ROS 2 tunes it: large
messages, quick discovery and quick acknowledgements.

Why (measured with ``python -m benchmarks.bench_camera --backends rclpy``: a 1080p rgb8
camera at 60 Hz, reliable keep-last 30, into ``tpsr_ros.record``, 2-core machine at load
average 2-4): with Fast DDS's defaults the recorder got 122-236 of 300 images (the rest
reported lost); with a 16 MiB shared-memory segment, 300 of 300 in eight runs of eight
(also with 32 and 64 MiB).
On one host Fast DDS moves data through shared memory, and each participant writes its
samples into its own segment, 512 KiB by default: a 6.2 MB image does not fit, so its
fragments wait for the reader to free room, the writer falls behind, and a keep-last
writer overwrites what was not delivered. A larger segment is the remedy Fast DDS's
documentation gives for large data; it is an XML profile (``segment_size`` of the SHM
transport), loaded from ``FASTRTPS_DEFAULT_PROFILES_FILE``.

Discovery: a participant re-announces itself every ``leaseAnnouncement`` (Fast DDS: 3 s).
With ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` a node started after another was found
only at the older one's next announcement, up to 3 s later; the profile announces every
:data:`ANNOUNCEMENT_S` (measured on three rclpy graph tests, a closed loop, two robots side by
side and a replay, 44.5 s -> 31.5 s). The cost is one small discovery message per
participant per period.

Acknowledgements: a reliable writer asks its subscribers for them with a heartbeat, which
Fast DDS repeats every 3 s while something is unacknowledged, so waiting for them (the
player's first message on each topic) and repairing a lost sample took up to 3 s; the
profile's writers repeat it every :data:`HEARTBEAT_S` (measured: a test that records a sim
for 5 s and replays the recording, eight topics, into a second recorder over rclpy took
27.6 s with the player's acknowledged start and 3 s heartbeats, 10.3 s with 0.1 s).

:func:`tune_fastdds` writes that profile (shared memory with the larger segment, and UDPv4
as without it, so other hosts and other participants are reached as before; the shorter
announcement and heartbeat periods) and points the variable at it, before the process's
first ``rclpy.init``. The user's own Fast DDS configuration always wins: nothing is changed
when a profile file or ``FASTDDS_BUILTIN_TRANSPORTS`` is set, a
``DEFAULT_FASTRTPS_PROFILES.xml`` is in the working directory, or another RMW is selected.
"""

from __future__ import annotations

import os
import stat
import tempfile
from collections.abc import MutableMapping
from pathlib import Path

from tpsr_ros.io.atomic import atomic_file

__all__ = ["ANNOUNCEMENT_S", "HEARTBEAT_S", "SHM_SEGMENT_BYTES", "profile_xml", "tune_fastdds"]

ANNOUNCEMENT_S = 0.5
"""Seconds between a participant's discovery announcements (Fast DDS's default: 3)."""

HEARTBEAT_S = 0.1
"""Seconds between a reliable writer's heartbeats while a subscriber has not acknowledged
all it was sent (Fast DDS's default: 3)."""

SHM_SEGMENT_BYTES = 16 * 1024 * 1024
"""Shared-memory segment per participant (allocated in /dev/shm while the node runs);
holds two 1080p rgb8 images in flight."""

PROFILE_VARIABLE = "FASTRTPS_DEFAULT_PROFILES_FILE"
_USER_SETTINGS = (PROFILE_VARIABLE, "FASTDDS_DEFAULT_PROFILES_FILE", "FASTDDS_BUILTIN_TRANSPORTS")
_WORKING_DIRECTORY_PROFILE = "DEFAULT_FASTRTPS_PROFILES.xml"
_UID = os.getuid() if hasattr(os, "getuid") else 0


def _duration(seconds: float) -> str:
    """A Fast DDS XML duration: whole seconds and nanoseconds."""
    return f"<sec>{int(seconds)}</sec><nanosec>{round(seconds % 1 * 1e9)}</nanosec>"


def profile_xml(segment_bytes: int = SHM_SEGMENT_BYTES) -> str:
    """Fast DDS XML: the default participant uses SHM with ``segment_bytes`` and UDPv4, and
    announces itself every :data:`ANNOUNCEMENT_S`; the default writer's heartbeat comes
    every :data:`HEARTBEAT_S`."""
    return f"""<?xml version="1.0" encoding="UTF-8" ?>
<!-- written by tpsr_ros.runtime.fastdds_tuning: large messages (camera images) -->
<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <transport_descriptors>
    <transport_descriptor>
      <transport_id>tpsr_shm</transport_id>
      <type>SHM</type>
      <segment_size>{int(segment_bytes)}</segment_size>
    </transport_descriptor>
    <transport_descriptor>
      <transport_id>tpsr_udp</transport_id>
      <type>UDPv4</type>
    </transport_descriptor>
  </transport_descriptors>
  <participant profile_name="tpsr_ros_large_messages" is_default_profile="true">
    <rtps>
      <userTransports>
        <transport_id>tpsr_shm</transport_id>
        <transport_id>tpsr_udp</transport_id>
      </userTransports>
      <useBuiltinTransports>false</useBuiltinTransports>
      <builtin>
        <discovery_config>
          <leaseAnnouncement>{_duration(ANNOUNCEMENT_S)}</leaseAnnouncement>
        </discovery_config>
      </builtin>
    </rtps>
  </participant>
  <data_writer profile_name="tpsr_ros_writers" is_default_profile="true">
    <times>
      <heartbeatPeriod>{_duration(HEARTBEAT_S)}</heartbeatPeriod>
    </times>
  </data_writer>
</profiles>
"""


def _ours(path: Path) -> bool:
    """A regular file (not a link) of this user that only this user can write.

    In a shared temporary directory another user could create the path first, with our
    text, and change it after it was checked; such a file is replaced (or, if the
    directory forbids that, nothing is tuned).
    """
    try:
        info = path.lstat()
    except OSError:
        return False
    return stat.S_ISREG(info.st_mode) and info.st_uid == _UID and not info.st_mode & 0o022


def tune_fastdds(
    environ: MutableMapping[str, str] | None = None, directory: Path | None = None
) -> Path | None:
    """Point ``FASTRTPS_DEFAULT_PROFILES_FILE`` at our profile unless the user configured Fast DDS.

    Returns the profile's path, or None when nothing was changed (a profile file or
    ``FASTDDS_BUILTIN_TRANSPORTS`` is set, the working directory has Fast DDS's
    ``DEFAULT_FASTRTPS_PROFILES.xml``, ``RMW_IMPLEMENTATION`` names another RMW, or the
    file cannot be written). Fast DDS reads the variable when the process creates its
    first participant, so this must run before the first ``rclpy.init``; children inherit
    it. ``directory`` defaults to the temporary directory.
    """
    env = os.environ if environ is None else environ
    if any(env.get(name, "").strip() for name in _USER_SETTINGS):
        return None
    if Path(_WORKING_DIRECTORY_PROFILE).is_file():  # Fast DDS loads it when no variable is set
        return None
    if env.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp").strip() not in ("", "rmw_fastrtps_cpp"):
        return None
    folder = Path(tempfile.gettempdir()) if directory is None else Path(directory)
    path = folder / f"tpsr_ros_fastdds_{_UID}.xml"
    text = profile_xml()
    try:
        if not _ours(path) or path.read_text(encoding="utf-8") != text:
            # a new file of ours (exclusive, never through a link), renamed over the old:
            # a concurrent reader sees the old profile or the new one; only we may write it
            with atomic_file(path, "w", sync=False, permissions=0o644) as handle:
                handle.write(text)
    except OSError:
        return None
    env[PROFILE_VARIABLE] = str(path)
    return path
