"""The recorder's sustained rate without loss, over the DDS backend.

``python -m tpsr_ros.record`` runs as a child process subscribed to one topic; this process
publishes 50000 16x16 rgb8 images as fast as DDS flow control lets it (reliable,
keep-all, so a slow recorder throttles the publisher instead of losing messages). The rate
is end to end: images divided by the time from the first ``publish`` to the receive time
the recorder logged for the last image (one machine, one clock), so network transfer,
taking and writing are all included. The run fails if any image is missing. Three runs;
prints each and the median. Target: >= 2000 images/s.
"""

from __future__ import annotations

import os
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

IMAGES = 50000
RUNS = 3
TOPIC = "/bench/images"
LOOPBACK = (
    "<CycloneDDS><Domain id='any'><General><Interfaces>"
    "<NetworkInterface address='127.0.0.1' multicast='true'/>"
    "</Interfaces></General></Domain></CycloneDDS>"
)


def one_run(tmp: Path, run: int) -> tuple[float, int]:
    from tpsr_ros.io import messages as m
    from tpsr_ros.io.bag import BagReader
    from tpsr_ros.runtime import Node, NodeOptions, QoSProfile
    from tpsr_ros.runtime.dds import DdsTransport
    from tpsr_ros.runtime.launcher import Launch

    bag = tmp / f"bag{run}"
    node = Node(NodeOptions(name="bench_images"), transport=DdsTransport("bench_images"))
    launch = Launch(tmp, env={**os.environ, "TPSR_TRANSPORT": "dds"}, spin=node.spin_once)
    recorder = launch.start(
        f"rec{run}", "tpsr_ros.record",
        ["-o", str(bag), TOPIC, "--ros-args", "--log-level", "debug"],
    )  # fmt: skip
    try:
        pub = node.create_publisher(
            TOPIC, m.IMAGE_TYPE, QoSProfile(history="keep_all", depth=0)
        )
        launch.wait("the recorder to subscribe", lambda: pub.get_subscription_count() >= 1)
        rng = np.random.default_rng(run)
        frames = rng.integers(0, 255, (64, 16, 16, 3), dtype=np.uint8)
        payloads = [
            m.serialize(m.image_msg(k * 10**9, frames[k % 64]), m.IMAGE_TYPE)
            for k in range(1, IMAGES + 1)
        ]
        start_ns = time.time_ns()
        for data in payloads:
            pub.publish_raw(data)
        if not pub._handle.wait_for_acks(60.0):  # DDS writer: every image acknowledged
            raise RuntimeError("the recorder did not acknowledge every image within 60 s")
        if recorder.stop(timeout_s=60) != 0:
            raise RuntimeError(f"recorder failed:\n{recorder.text()}")
    finally:
        node.close()
        recorder.kill()
    with BagReader(bag) as reader:
        times = [msg.log_time_ns for msg in reader.messages([TOPIC])]
    span = (times[-1] - start_ns) / 1e9 if times else float("nan")
    return len(times) / span, IMAGES - len(times)


def main() -> None:
    os.environ["ROS_DOMAIN_ID"] = str(os.getpid() % 150 + 50)
    os.environ.setdefault("CYCLONEDDS_URI", LOOPBACK)
    rates = []
    with tempfile.TemporaryDirectory() as tmp:
        for run in range(RUNS):
            rate, lost = one_run(Path(tmp), run)
            rates.append(rate)
            print(f"   run {run + 1}: {IMAGES} images, {lost} lost, {rate:.0f} images/s",
                  flush=True)
            if lost:
                raise RuntimeError(f"the recorder lost {lost} images")
    median = statistics.median(rates)
    print(f"recorder sustained rate (16x16 images, DDS, no loss): median {median:.0f} images/s "
          f"(target >= 2000: {'met' if median >= 2000 else 'NOT met'})", flush=True)


if __name__ == "__main__":
    main()
