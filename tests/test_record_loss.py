"""The recorder never loses silently: induced loss is counted exactly, bad input is refused.

Loss is induced the two ways a real recorder meets it, on the backend where the
middleware reports it: a recorder that stops taking samples while a best-effort camera
keeps publishing (DDS backend: Cyclone rejects what does not fit the recorder's bounded
cache and says so), and a recorder process stalled (SIGSTOP) while a reliable keep-last-1
publisher moves on (rclpy: Fast DDS's message-lost event). Each test checks the count the
recorder reports (log, end-of-run line, bag metadata) against the count actually missing
from the bag.
"""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest
from graph_support import LOOPBACK, fresh_domain, rclpy_available

from tpsr_ros import record
from tpsr_ros.io import messages as m
from tpsr_ros.io.bag import BagReader
from tpsr_ros.runtime import SENSOR_DATA_QOS, Node, NodeOptions, QoSProfile
from tpsr_ros.runtime.diagnostics import DIAGNOSTICS_TYPE, status_values
from tpsr_ros.runtime.launcher import NodeProcess

TOPIC = "/camera/image_raw"


def _images(count: int, height: int, width: int) -> list[bytes]:
    rng = np.random.default_rng(19)
    frame = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
    return [m.serialize(m.image_msg(k * 10**6 + 1, frame), m.IMAGE_TYPE) for k in range(count)]


def _recorder(transport, bag: Path, *extra: str) -> record.RecorderNode:
    args = record.RecorderNode.argument_parser("record").parse_args(
        ["-o", str(bag), TOPIC, *extra]
    )
    options = NodeOptions.for_node(record.RecorderNode, args=args)
    return record.RecorderNode(options, transport=transport)


def _reported(bag: Path) -> tuple[int, int, int, dict]:
    """(recorded in the bag, lost and rejected per metadata, per-topic metadata)."""
    with BagReader(bag) as reader:
        recorded = reader.message_counts.get(TOPIC, 0)
        custom = reader.custom_data
    return (
        recorded,
        int(custom["recorder.lost_messages"]),
        int(custom["recorder.rejected_messages"]),
        json.loads(custom["recorder.by_topic"]),
    )


def test_dds_recorder_that_falls_behind_a_best_effort_camera_reports_each_lost_image(
    tmp_path, monkeypatch, capfd
):
    pytest.importorskip("cyclonedds")
    from tpsr_ros.runtime.dds import DdsTransport

    monkeypatch.setenv("CYCLONEDDS_URI", LOOPBACK)
    monkeypatch.setattr(record, "CACHE_SAMPLES", 8)
    domain = fresh_domain(23)
    camera = Node(NodeOptions(name="camera"), transport=DdsTransport("camera", domain_id=domain))
    pub = camera.create_publisher(TOPIC, m.IMAGE_TYPE, SENSOR_DATA_QOS)
    bag = tmp_path / "bag"
    rec = _recorder(DdsTransport("rec", domain_id=domain), bag)
    try:
        assert rec.wait_for(lambda: pub.get_subscription_count() >= 1, 10)
        sent = 40
        for data in _images(sent, 48, 64):  # the recorder does not spin meanwhile: stalled
            pub.publish_raw(data)
        rec.spin(timeout_s=0.3)
    finally:
        rec.close()
        camera.close()
    recorded, lost, rejected, by_topic = _reported(bag)
    assert 0 < recorded < sent and rejected == 0
    assert lost == sent - recorded  # exactly what is missing from the bag
    assert by_topic[TOPIC] == {
        "recorded": recorded,
        "lost": lost,
        "dropped": 0,
        "rejected": 0,
        "missing_by_stamps": by_topic[TOPIC]["missing_by_stamps"],
    }
    err = capfd.readouterr().err
    assert f"lost {lost} messages on {TOPIC} before they reached the recorder" in err
    assert f"recorded {recorded} messages on 1 topics to {bag}; lost {lost}" in err


def _stall_recorder(
    tmp_path: Path, node: Node, env: dict[str, str], sent: int, first: int, last: int,
    counted: str,
) -> tuple[Path, str]:
    """Record ``sent`` images from ``node``'s reliable keep-last(1) publisher while the
    recorder process is stopped (SIGSTOP) between the ``first`` and the ``last`` ones, until
    the recorder's /diagnostics account for all (recorded + ``counted``); (bag, its log).
    """
    bag = tmp_path / "bag"
    pub = node.create_publisher(TOPIC, m.IMAGE_TYPE, QoSProfile(depth=1))
    reports: list[dict[str, str]] = []
    node.create_subscription(
        "/diagnostics",
        DIAGNOSTICS_TYPE,
        lambda msg: reports.extend(status_values(s) for s in msg.status),
    )
    recorder = NodeProcess(
        "rec", "tpsr_ros.record", ["-o", str(bag), TOPIC], log_path=tmp_path / "rec.log", env=env
    )

    def accounted(count: int) -> bool:
        return any(
            int(r.get(f"{TOPIC} recorded", 0)) + int(r.get(f"{TOPIC} {counted}", 0)) >= count
            for r in reports
        )

    images = _images(sent, 480, 640)  # stamped 1 ms apart
    try:
        assert node.wait_for(lambda: pub.get_subscription_count() >= 1, 30), recorder.text()
        for data in images[:first]:
            pub.publish_raw(data)
            time.sleep(0.002)
        assert node.wait_for(lambda: accounted(first), 20), recorder.text()
        os.kill(recorder.popen.pid, signal.SIGSTOP)
        try:
            for data in images[first:-last]:
                pub.publish_raw(data)
                time.sleep(0.002)
        finally:
            os.kill(recorder.popen.pid, signal.SIGCONT)
        node.spin(timeout_s=0.5)
        for data in images[-last:]:  # reveal the gap before them, if the tail was lost
            pub.publish_raw(data)
        assert node.wait_for(lambda: accounted(sent), 20), recorder.text()
        assert recorder.stop(timeout_s=20) == 0, recorder.text()
    finally:
        recorder.kill()
        node.close()
    return bag, recorder.text()


@pytest.mark.slow
@pytest.mark.skipif(not rclpy_available(), reason="rclpy (ROS 2) not importable")
def test_rclpy_recorder_stalled_behind_a_keep_last_publisher_reports_each_lost_image(
    tmp_path, monkeypatch
):
    from tpsr_ros.runtime.rclpy_backend import RclpyTransport

    env = {
        **os.environ,
        "ROS_DOMAIN_ID": str(fresh_domain(29)),
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        "TPSR_TRANSPORT": "rclpy",
    }
    for name in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE"):  # this process's node
        monkeypatch.setenv(name, env[name])
    node = Node(NodeOptions(name="camera"), transport=RclpyTransport("camera"))
    bag, log = _stall_recorder(tmp_path, node, env, 42, first=1, last=1, counted="lost")
    recorded, lost, rejected, _ = _reported(bag)
    assert lost > 0 and rejected == 0
    assert lost == 42 - recorded, log
    assert f"recorded {recorded} messages on 1 topics to {bag}; lost {lost}" in log


@pytest.mark.slow
def test_dds_recorder_stalled_behind_a_keep_last_camera_counts_the_missing_by_stamps(
    tmp_path, monkeypatch
):
    # Cyclone raises no status for samples a keep-last writer dropped before the stalled
    # recorder had them; the camera's steady stamps show them (12 images teach the cadence).
    pytest.importorskip("cyclonedds")
    from tpsr_ros.runtime.dds import DdsTransport

    domain = fresh_domain(31)
    env = {**os.environ, "TPSR_TRANSPORT": "dds", "ROS_DOMAIN_ID": str(domain),
           "CYCLONEDDS_URI": LOOPBACK}  # fmt: skip
    monkeypatch.setenv("CYCLONEDDS_URI", LOOPBACK)
    node = Node(NodeOptions(name="camera"), transport=DdsTransport("camera", domain_id=domain))
    sent = 60
    bag, log = _stall_recorder(
        tmp_path, node, env, sent, first=12, last=4, counted="missing by stamps"
    )
    recorded, _, rejected, by_topic = _reported(bag)
    assert 12 < recorded < sent and rejected == 0
    assert by_topic[TOPIC]["missing_by_stamps"] == sent - recorded, log
    with BagReader(bag) as reader:
        assert reader.custom_data["recorder.missing_by_stamps"] == str(sent - recorded)
    assert f"{sent - recorded} messages missing on {TOPIC} by its header stamps" in log
    assert f"missing {sent - recorded} by header stamps" in log


def test_bad_images_are_refused_counted_and_logged_and_the_bag_stays_readable(
    tmp_path, capfd
):
    from tpsr_ros.runtime.inproc import InprocBus, InprocTransport

    bus = InprocBus()
    camera = Node(NodeOptions(name="camera"), transport=InprocTransport("/camera", bus))
    pub = camera.create_publisher(TOPIC, m.IMAGE_TYPE)
    bag = tmp_path / "bag"
    rec = _recorder(InprocTransport("/rec", bus), bag, "--max-message-size", "100000")
    assert rec.wait_for(lambda: TOPIC in rec.subscribed, 5)
    good = m.image_msg(1, np.zeros((48, 64, 3), dtype=np.uint8))
    big = m.serialize(m.image_msg(2, np.zeros((200, 200, 3), dtype=np.uint8)), m.IMAGE_TYPE)
    truncated = m.serialize(good, m.IMAGE_TYPE)[:-1000]
    short_rows = m.jazzy_typestore().types[m.IMAGE_TYPE](
        header=good.header, height=48, width=64, encoding="rgb8", is_bigendian=0,
        step=64 * 2, data=np.zeros(48 * 64 * 2, dtype=np.uint8),
    )  # fmt: skip
    pub.publish(good)
    pub.publish_raw(big)
    pub.publish_raw(truncated)
    pub.publish(short_rows)
    pub.publish(good)
    rec.spin(timeout_s=0.1)
    assert rec.ok()  # still running
    rec.close()
    recorded, lost, rejected, _ = _reported(bag)
    assert (recorded, lost, rejected) == (2, 0, 3)
    lines = [line for line in capfd.readouterr().err.splitlines() if "rejected message" in line]
    assert len(lines) == 3
    assert "message 1 on /camera/image_raw:" in lines[0] and "--max-message-size 100000" in lines[0]
    assert "message 2 on" in lines[1] and "cannot decode sensor_msgs/msg/Image" in lines[1]
    assert "message 3 on" in lines[2] and "step 128 is less than width 64 x 3" in lines[2]


def test_messages_past_a_full_write_cache_are_dropped_counted_and_logged(tmp_path, capfd):
    from tpsr_ros.runtime.inproc import InprocBus, InprocTransport

    bus = InprocBus()
    camera = Node(NodeOptions(name="camera"), transport=InprocTransport("/camera", bus))
    pub = camera.create_publisher(TOPIC, m.IMAGE_TYPE)
    bag = tmp_path / "bag"
    images = _images(12, 120, 160)  # 57.6 kB each
    rec = _recorder(InprocTransport("/rec", bus), bag, "--max-cache-size", str(4 * 60_000))
    assert rec.wait_for(lambda: TOPIC in rec.subscribed, 5)
    with rec.writer._bag:  # the disk stalls: nothing is written meanwhile
        for data in images:
            pub.publish_raw(data)
        rec.spin(timeout_s=0.1)
    assert rec.ok()
    rec.close()
    with BagReader(bag) as reader:
        recorded = reader.message_counts[TOPIC]
        custom = reader.custom_data
    dropped = int(custom["recorder.dropped_messages"])
    assert (recorded, dropped) == (4, 8)  # the cache held 4 images; the 8 after are counted
    assert json.loads(custom["recorder.by_topic"])[TOPIC]["dropped"] == 8
    err = capfd.readouterr().err
    assert "dropped message 4 on /camera/image_raw: the write cache holds" in err
    assert "dropped 8 (write cache full)" in err


def test_a_write_error_in_the_cache_thread_reaches_the_caller(tmp_path):
    from tpsr_ros.core.errors import BagError
    from tpsr_ros.io.bag import BagWriter
    from tpsr_ros.io.bag_cache import CachedBagWriter

    cache = CachedBagWriter(BagWriter(tmp_path / "bag").open(), max_bytes=10**6)
    assert cache.put("/undeclared", 1, b"\0" * 8)  # queued; the thread's write fails
    with pytest.raises(BagError, match="topic '/undeclared' was not declared"):
        cache.close()
    with pytest.raises(BagError, match="was not declared"):
        cache.put("/undeclared", 2, b"\0" * 8)
    with BagReader(tmp_path / "bag") as reader:  # closed, readable
        assert reader.message_counts == {}
