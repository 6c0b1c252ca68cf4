"""Publish-to-callback latency over the DDS backend between two processes at 100 Hz.

A child process publishes 16x16 rgb8 images (the simulator's) at 100 Hz, each stamped
with the wall-clock time just before ``publish``; this process subscribes and takes
``time_ns() - stamp`` in the callback. Three runs of 300 messages; prints p50 and p99
per run and their medians. Target: p99 < 5 ms.
"""

from __future__ import annotations

import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

RATE_HZ = 100.0
MESSAGES = 300
RUNS = 3
TOPIC = "/bench/latency"
LOOPBACK = (
    "<CycloneDDS><Domain id='any'><General><Interfaces>"
    "<NetworkInterface address='127.0.0.1' multicast='true'/>"
    "</Interfaces></General></Domain></CycloneDDS>"
)


def _node(name: str):
    from tpsr_ros.runtime import Node, NodeOptions
    from tpsr_ros.runtime.dds import DdsTransport

    return Node(NodeOptions(name=name), transport=DdsTransport(name))


def publisher(count: int) -> None:
    """Child process: wait for the subscriber, then publish ``count`` images at 100 Hz."""
    from tpsr_ros.io import messages as m

    node = _node("bench_publisher")
    pub = node.create_publisher(TOPIC, m.IMAGE_TYPE)
    node.wait_for(lambda: pub.get_subscription_count() >= 1, timeout_s=30)
    node.spin(timeout_s=0.5)  # let discovery settle on both sides
    image = np.random.default_rng(0).integers(0, 255, (16, 16, 3), dtype=np.uint8)
    sent = 0

    def tick() -> None:
        nonlocal sent
        pub.publish(m.image_msg(time.time_ns(), image))
        sent += 1
        if sent >= count:
            node.request_shutdown("done")

    node.create_timer(1.0 / RATE_HZ, tick)
    node.spin()
    node.close()


def one_run(env: dict[str, str]) -> np.ndarray:
    from tpsr_ros.io import messages as m
    from tpsr_ros.runtime.launcher import NodeProcess

    node = _node("bench_subscriber")
    latencies: list[int] = []

    def on_image(msg: object) -> None:
        latencies.append(time.time_ns() - m.stamp_of(msg))

    node.create_subscription(TOPIC, m.IMAGE_TYPE, on_image)
    log = Path(tempfile.mkdtemp(prefix="bench_dds_")) / "publisher.log"
    child = NodeProcess(
        "publisher", "benchmarks.bench_dds", ["--publish", str(MESSAGES)], log_path=log, env=env
    )
    try:
        node.wait_for(lambda: len(latencies) >= MESSAGES, timeout_s=MESSAGES / RATE_HZ + 30)
        child.wait(30)
    finally:
        child.kill()
        node.close()
        shutil.rmtree(log.parent, ignore_errors=True)
    if len(latencies) < MESSAGES:
        raise RuntimeError(f"received {len(latencies)} of {MESSAGES} messages")
    return np.array(latencies) / 1e6


def main() -> None:
    domain = os.getpid() % 150 + 50
    os.environ["ROS_DOMAIN_ID"] = str(domain)
    os.environ.setdefault("CYCLONEDDS_URI", LOOPBACK)
    env = dict(os.environ)
    p50s, p99s = [], []
    for run in range(RUNS):
        ms = one_run(env)
        p50, p99 = np.percentile(ms, [50, 99])
        p50s.append(p50)
        p99s.append(p99)
        print(f"   run {run + 1}: {len(ms)} msgs at {RATE_HZ:.0f} Hz  "
              f"p50 {p50:.2f} ms  p99 {p99:.2f} ms  max {ms.max():.2f} ms", flush=True)
    p99 = statistics.median(p99s)
    print(f"dds latency (16x16 image, 2 processes, 100 Hz): median p50 "
          f"{statistics.median(p50s):.2f} ms, median p99 {p99:.2f} ms "
          f"(target p99 < 5 ms: {'met' if p99 < 5 else 'NOT met'})", flush=True)


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "--publish":
        publisher(int(sys.argv[2]))
    else:
        main()
