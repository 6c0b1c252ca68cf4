"""Fast DDS's shared-memory segment for large messages, its discovery announcements and its
writers' heartbeats (tpsr_ros.runtime.fastdds_tuning).

The profile is checked against the real Fast DDS of the rclpy wheels: a node started in a
fresh process allocates a shared-memory segment of the profile's size, and the user's own
Fast DDS settings leave Fast DDS at its default (512 KiB); a subscriber in another process
acknowledges each message within a heartbeat of the profile's, not Fast DDS's 3 s.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from graph_support import fresh_domain, rclpy_available

from tpsr_ros.runtime.fastdds_tuning import (
    HEARTBEAT_S,
    PROFILE_VARIABLE,
    SHM_SEGMENT_BYTES,
    profile_xml,
    tune_fastdds,
)


def test_the_profile_is_written_once_and_the_variable_points_at_it(tmp_path):
    env: dict[str, str] = {}
    path = tune_fastdds(env, tmp_path)
    assert path is not None and env == {PROFILE_VARIABLE: str(path)}
    text = path.read_text()
    assert text == profile_xml() and f"<segment_size>{SHM_SEGMENT_BYTES}<" in text
    assert "<type>UDPv4</type>" in text  # other hosts are reached as without it
    stamp = path.stat().st_mtime_ns
    assert tune_fastdds({}, tmp_path) == path and path.stat().st_mtime_ns == stamp
    assert list(tmp_path.iterdir()) == [path]  # no temporary file left


def test_a_profile_others_can_change_or_a_link_is_replaced_not_trusted(tmp_path):
    # in a shared /tmp another user could plant the path with our text and edit it later
    path = tune_fastdds({}, tmp_path)
    assert path is not None
    path.chmod(0o666)  # right text, but writable by anyone
    assert tune_fastdds({}, tmp_path) == path and not path.stat().st_mode & 0o022
    elsewhere = tmp_path / "planted.xml"
    elsewhere.write_text(profile_xml())
    path.unlink()
    path.symlink_to(elsewhere)  # right text, behind a link
    assert tune_fastdds({}, tmp_path) == path and not path.is_symlink()
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([path.name, "planted.xml"])


@pytest.mark.parametrize(
    "setting",
    [
        {PROFILE_VARIABLE: "/etc/my_fastdds.xml"},
        {"FASTDDS_DEFAULT_PROFILES_FILE": "/etc/my_fastdds.xml"},
        {"FASTDDS_BUILTIN_TRANSPORTS": "LARGE_DATA"},
        {"RMW_IMPLEMENTATION": "rmw_cyclonedds_cpp"},
    ],
)
def test_the_users_fast_dds_configuration_wins(tmp_path, setting):
    env = dict(setting)
    assert tune_fastdds(env, tmp_path) is None
    assert env == setting and not list(tmp_path.iterdir())


def test_a_profile_in_the_working_directory_wins(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "DEFAULT_FASTRTPS_PROFILES.xml").write_text("<profiles/>")
    env: dict[str, str] = {}
    assert tune_fastdds(env, tmp_path / "out") is None and env == {}


def test_an_unwritable_directory_changes_nothing(tmp_path):
    env: dict[str, str] = {}
    assert tune_fastdds(env, tmp_path / "missing") is None and env == {}


_PROBE = """
import json, os
from tpsr_ros.runtime.rclpy_backend import RclpyTransport
transport = RclpyTransport("segment_probe")
with open("/proc/self/maps") as maps:  # this process's own segments, not other processes'
    mapped = {line.split()[-1] for line in maps if "/dev/shm/fastrtps_" in line}
sizes = [os.path.getsize(f) for f in mapped if "_port" not in f and not f.endswith("_el")]
transport.close()
print(json.dumps(sizes))
"""

@pytest.mark.rclpy
@pytest.mark.skipif(not rclpy_available(), reason="rclpy (ROS 2) not importable")
@pytest.mark.skipif(not os.path.isfile("/proc/self/maps"), reason="Linux only")
@pytest.mark.parametrize("users_own", [False, True])
def test_a_node_gets_the_larger_segment_unless_the_user_configured_fast_dds(users_own):
    env = {k: v for k, v in os.environ.items() if k != PROFILE_VARIABLE}
    env.update(ROS_DOMAIN_ID=str(fresh_domain(41)), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    env["PYTHONPATH"] = os.pathsep.join([str(Path(__file__).parents[1]), *sys.path])
    if users_own:
        env["FASTDDS_BUILTIN_TRANSPORTS"] = "DEFAULT"
    done = subprocess.run(
        [sys.executable, "-c", _PROBE], env=env, capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 0, done.stderr
    sizes = json.loads(done.stdout.splitlines()[-1])
    assert sizes, "no Fast DDS segment mapped"  # its own, and any it reads from
    if users_own:
        assert max(sizes) < 1024 * 1024  # Fast DDS's own 512 KiB (plus its bookkeeping)
    else:
        assert SHM_SEGMENT_BYTES <= max(sizes) < 2 * SHM_SEGMENT_BYTES


def test_the_profile_announces_participants_every_half_second():
    """A node started after another is discovered at the older one's next announcement."""
    import xml.etree.ElementTree as ET

    from tpsr_ros.runtime.fastdds_tuning import ANNOUNCEMENT_S, profile_xml

    ns = {"f": "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"}
    root = ET.fromstring(profile_xml())
    lease = root.find("f:participant/f:rtps/f:builtin/f:discovery_config/f:leaseAnnouncement", ns)
    assert lease is not None
    seconds = int(lease.find("f:sec", ns).text) + int(lease.find("f:nanosec", ns).text) / 1e9
    assert seconds == ANNOUNCEMENT_S == 0.5


_SUBSCRIBER = """
import sys
from tpsr_ros.io import messages as m
from tpsr_ros.runtime import Node, NodeOptions
node = Node(NodeOptions(name="ack_subscriber"))
node.create_subscription("/acked", m.CLOCK_TYPE, lambda _: None)
print("ready", flush=True)
node.wait_for(lambda: False, timeout_s=float(sys.argv[1]))
node.close()
"""

_PUBLISHER = """
import json, time
from tpsr_ros.io import messages as m
from tpsr_ros.runtime import Node, NodeOptions
node = Node(NodeOptions(name="ack_publisher"))
pub = node.create_publisher("/acked", m.CLOCK_TYPE)
assert node.wait_for(lambda: pub.get_subscription_count() > 0, timeout_s=20)
waits = []
for k in range(4):
    pub.publish(m.clock_msg(k + 1))
    start = time.monotonic()
    waits.append((pub.wait_for_all_acked(1.5), time.monotonic() - start))
    time.sleep(0.05)
node.close()
print(json.dumps(waits))
"""


@pytest.mark.rclpy
@pytest.mark.skipif(not rclpy_available(), reason="rclpy (ROS 2) not importable")
def test_a_subscriber_in_another_process_acknowledges_within_a_heartbeat():
    """Fast DDS repeats a heartbeat every 3 s by default, so a reliable writer's unacknowledged
    message (the player's first on a topic, a lost fragment) waited up to 3 s."""
    assert HEARTBEAT_S == 0.1
    env = {k: v for k, v in os.environ.items() if k != PROFILE_VARIABLE}
    env.update(
        ROS_DOMAIN_ID=str(fresh_domain(43)), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
        TPSR_TRANSPORT="rclpy",
        PYTHONPATH=os.pathsep.join([str(Path(__file__).parents[1]), *sys.path]),
    )  # fmt: skip
    subscriber = subprocess.Popen(
        [sys.executable, "-c", _SUBSCRIBER, "30"], env=env, stdout=subprocess.PIPE, text=True
    )
    try:
        assert subscriber.stdout is not None and subscriber.stdout.readline() == "ready\n"
        done = subprocess.run(
            [sys.executable, "-c", _PUBLISHER], env=env, capture_output=True, text=True,
            timeout=60,
        )  # fmt: skip
    finally:
        subscriber.kill()
        subscriber.wait()
    assert done.returncode == 0, done.stderr
    waits = json.loads(done.stdout.splitlines()[-1])
    # each acknowledged well within 1.5 s; with Fast DDS's default, all but the first took ~2.8 s
    assert all(acked for acked, _ in waits), waits
