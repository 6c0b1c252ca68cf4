"""Large-message throughput between two processes: the DDS backend next to real rclpy.

For each image size (16x16, 640x480, 1920x1080 rgb8) and each backend, a child process
publishes pre-serialised ``sensor_msgs/msg/Image`` samples as fast as the middleware's
flow control lets it (reliable, keep-all: a slow reader throttles the writer, nothing is
dropped), and this process subscribes (reliable, keep-all) and counts what arrives. The rate
is messages received divided by the time from the first to the last arrival; a message
not received is lost. Both backends run on the same machine in the same run, so real
rclpy's (Fast DDS) rate is the reference for ours. Target: >= 60 1080p images/s on DDS.

    python -m benchmarks.bench_transport                 # every size, every backend
    python -m benchmarks.bench_transport --sizes 1080p --backends dds
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.bench_record import SIZES, graph_env, payloads, rclpy_importable

TOPIC = "/bench/throughput"
# enough messages for about a second of traffic at the expected rates, bounded in bytes
COUNTS = {"16x16": 5000, "640x480": 300, "1080p": 120}
TARGET_1080P = 60.0


def _node(name: str, backend: str):
    from tpsr_ros.runtime import Node, NodeOptions
    from tpsr_ros.runtime.backend import open_transport

    return Node(NodeOptions(name=name), transport=open_transport(backend, name, "/"))


def publisher(backend: str, size: str, count: int) -> None:
    """Child process: publish ``count`` images of ``size`` as fast as flow control allows."""
    from tpsr_ros.io import messages as m
    from tpsr_ros.runtime import QoSProfile

    node = _node("bench_tx", backend)
    pub = node.create_publisher(TOPIC, m.IMAGE_TYPE, QoSProfile(history="keep_all", depth=0))
    frames = payloads(size, 4, distinct=4)
    node.wait_for(lambda: pub.get_subscription_count() >= 1, timeout_s=30)
    node.spin(timeout_s=0.3)  # let discovery settle on both sides
    cpu_start = time.process_time()
    for k in range(count):
        pub.publish_raw(frames[k % 4])
    print(f"publish cpu_s={time.process_time() - cpu_start:.4f}", flush=True)
    node.spin(timeout_s=5.0, until=lambda: False)  # keep serving retransmissions
    node.close()


def one_run(backend: str, size: str, count: int, env: dict[str, str]) -> tuple[float, int]:
    """(messages/s, lost) for ``count`` images of ``size`` over ``backend``."""
    from tpsr_ros.io import messages as m
    from tpsr_ros.runtime import QoSProfile
    from tpsr_ros.runtime.launcher import NodeProcess

    node = _node("bench_rx", backend)
    arrivals: list[int] = []
    cpu: list[float] = []

    def on_data(data: bytes) -> None:
        arrivals.append(time.perf_counter_ns())
        cpu.append(time.process_time())

    node.create_subscription(
        TOPIC,
        m.IMAGE_TYPE,
        on_data,
        QoSProfile(history="keep_all", depth=0),
        raw=True,
    )
    log = Path(tempfile.mkdtemp(prefix="bench_transport_")) / "publisher.log"
    child = NodeProcess(
        "publisher",
        "benchmarks.bench_transport",
        ["--publish", backend, size, str(count)],
        log_path=log,
        env={**env, "TPSR_TRANSPORT": backend},
    )
    try:
        deadline = time.monotonic() + 60 + count * 0.05
        idle_since = time.monotonic()
        seen = 0
        while len(arrivals) < count and time.monotonic() < deadline:
            node.spin_once(0.05)
            if len(arrivals) != seen:
                seen, idle_since = len(arrivals), time.monotonic()
            elif seen and time.monotonic() - idle_since > 5.0:
                break  # nothing for 5 s after traffic began: the rest is lost
    finally:
        child.kill()
        node.close()
    received = len(arrivals)
    text = log.read_text() if log.exists() else ""
    shutil.rmtree(log.parent, ignore_errors=True)
    pub_cpu = [float(w[6:]) for w in text.split() if w.startswith("cpu_s=")]
    if received > 1:
        rx_ms = (cpu[-1] - cpu[0]) / (received - 1) * 1e3
        tx_ms = pub_cpu[0] / count * 1e3 if pub_cpu else float("nan")
        print(f"      cpu per message: publisher {tx_ms:.2f} ms, subscriber {rx_ms:.2f} ms",
              flush=True)
    span = (arrivals[-1] - arrivals[0]) / 1e9 if received > 1 else float("nan")
    rate = (received - 1) / span if received > 1 and span > 0 else float("nan")
    return rate, count - received


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_transport")
    parser.add_argument("--sizes", nargs="+", choices=list(SIZES), default=list(SIZES))
    parser.add_argument("--backends", nargs="+", choices=["dds", "rclpy"], default=None)
    parser.add_argument("--runs", type=int, default=1)
    args = parser.parse_args([] if argv is None else argv)  # run by benchmarks: defaults
    backends = args.backends or ["dds", *(["rclpy"] if rclpy_importable() else [])]
    env = graph_env()
    print(f"   load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores", flush=True)
    for size in args.sizes:
        rates: dict[str, float] = {}
        for backend in backends:
            for run in range(args.runs):
                rate, lost = one_run(backend, size, COUNTS[size], env)
                rates[backend] = rate
                print(
                    f"   {size:>8} {backend:>5} run {run + 1}: {COUNTS[size]} sent, "
                    f"{lost} lost, {rate:.1f} messages/s",
                    flush=True,
                )
        line = "  ".join(f"{b} {r:.1f}/s" for b, r in rates.items())
        print(f"transport rate {size} rgb8 (2 processes, reliable keep-all): {line}", flush=True)


if __name__ == "__main__":
    if len(sys.argv) == 5 and sys.argv[1] == "--publish":
        publisher(sys.argv[2], sys.argv[3], int(sys.argv[4]))
    else:
        main(sys.argv[1:])
