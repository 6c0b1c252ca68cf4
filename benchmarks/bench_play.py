"""The player at camera rate: a 1080p rgb8 bag replayed at 1x, on each backend.

A bag of 90 1920x1080 rgb8 images 1/30 s apart (zstd chunks, as the recorder writes by
default) is played by ``python -m tpsr_ros.play --wait-for-subscribers 1`` in a child
process; this process subscribes (reliable, keep-all) and counts what arrives. Prints the
images received and the lateness the player reports in its end line (how long after its
due time each publish started). Target: all received, p99 lateness below one frame (33 ms).
"""

from __future__ import annotations

import argparse
import os
import re
import sys
import tempfile
from pathlib import Path

from benchmarks.bench_record import bag_root, graph_env, payloads, rclpy_importable

TOPIC = "/camera/image_raw"
IMAGES = 90
PERIOD_NS = 10**9 // 30
_LATENESS = re.compile(r"lateness p50 ([\d.]+) ms, p99 ([\d.]+) ms, max ([\d.]+) ms")


def write_bag(path: Path) -> None:
    from tpsr_ros.io import messages as m
    from tpsr_ros.io.bag import BagWriter

    with BagWriter(path) as writer:
        writer.add_topic(TOPIC, m.IMAGE_TYPE)
        for k, data in enumerate(payloads("1080p", IMAGES)):
            writer.write(TOPIC, 10**9 + k * PERIOD_NS, data)


def one_run(tmp: Path, bag: Path, backend: str) -> tuple[int, tuple[float, ...] | None]:
    """(images received, (p50, p99, max) lateness in ms from the player's end line)."""
    from tpsr_ros.io import messages as m
    from tpsr_ros.runtime import Node, NodeOptions, QoSProfile
    from tpsr_ros.runtime.backend import open_transport
    from tpsr_ros.runtime.launcher import NodeProcess

    node = Node(NodeOptions(name="bench_viewer"), transport=open_transport(backend, "v", "/"))
    received: list[int] = []
    node.create_subscription(
        TOPIC, m.IMAGE_TYPE, lambda data: received.append(len(data)),
        QoSProfile(history="keep_all", depth=0), raw=True,
    )  # fmt: skip
    player = NodeProcess(
        f"play_{backend}",
        "tpsr_ros.play",
        [str(bag), "--no-clock", "--wait-for-subscribers", "1"],
        log_path=tmp / f"play_{backend}.log",
        env={**os.environ, "TPSR_TRANSPORT": backend},
    )
    try:
        node.wait_for(lambda: player.popen.poll() is not None, 60)
        node.spin(timeout_s=1.0)  # what is still on its way
    finally:
        player.kill()
        node.close()
    found = _LATENESS.search(player.text())
    return len(received), tuple(float(x) for x in found.groups()) if found else None


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_play")
    parser.add_argument("--backends", nargs="+", choices=["dds", "rclpy"], default=None)
    args = parser.parse_args([] if argv is None else argv)  # run by benchmarks: defaults
    backends = args.backends or ["dds", *(["rclpy"] if rclpy_importable() else [])]
    graph_env()
    print(f"   load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores", flush=True)
    with tempfile.TemporaryDirectory(dir=bag_root()) as tmp:
        bag = Path(tmp) / "camera_1080p"
        write_bag(bag)
        for backend in backends:
            count, lateness = one_run(Path(tmp), bag, backend)
            if lateness is None:
                print(f"player 1080p at 1x, {backend}: no end line (see its log)", flush=True)
                continue
            p50, p99, worst = lateness
            met = count == IMAGES and p99 < PERIOD_NS / 1e6
            print(
                f"player 1080p rgb8 bag at 1x (30 Hz), {backend}: {count} of {IMAGES} "
                f"received, lateness p50 {p50:.1f} ms, p99 {p99:.1f} ms, max {worst:.1f} ms "
                f"(target all received, p99 < 33 ms: {'met' if met else 'NOT met'})",
                flush=True,
            )


if __name__ == "__main__":
    main(sys.argv[1:])
