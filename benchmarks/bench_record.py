"""The recorder's sustained rate without loss, per image size, on each backend.

``python -m tpsr_ros.record`` runs as a child process subscribed to one topic; this process
publishes pre-serialised rgb8 images (16x16, 640x480, 1920x1080) as fast as the
middleware's flow control lets it (reliable, keep-all, so a slow recorder throttles the
publisher instead of losing messages). The rate is end to end: images divided by the time
from the first ``publish`` to the receive time the recorder logged for the last image (one
machine, one clock), so transfer, taking and writing are all included. Large images are
recorded with ``--compression none`` (zstd alone takes 10-35 ms per 1080p image); 16x16
with the default zstd. A run fails if an image is missing or the recorder reports a loss.
Target: >= 2000 16x16 images/s on DDS; 1080p above 60/s (a 60 Hz camera).

    python -m benchmarks.bench_record [--sizes 16x16 1080p] [--backends dds rclpy]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

TOPIC = "/bench/images"
SIZES = {"16x16": (16, 16), "640x480": (480, 640), "1080p": (1080, 1920)}
COUNTS = {"16x16": 20000, "640x480": 300, "1080p": 150}
TARGETS = {"16x16": 2000.0, "1080p": 60.0}


def rclpy_importable() -> bool:
    """Whether real rclpy imports (the rclpy backend can be measured)."""
    try:
        import rclpy  # noqa: F401
    except ImportError:
        return False
    return True


def bag_root() -> str | None:
    """Where the benchmark bags go: tmpfs when there is one, so the disk is not measured.

    A 1080p rgb8 stream is 186 MB/s at 30 Hz and 373 MB/s at 60 Hz; a disk
    takes about 250 MB/s (dd), so on disk it, not the recorder, would set the rate.
    """
    shm = Path("/dev/shm")
    return str(shm) if shm.is_dir() and os.access(shm, os.W_OK) else None


def graph_env() -> dict[str, str]:
    """This run's environment: its own domain, loopback discovery (both backends)."""
    os.environ["ROS_DOMAIN_ID"] = str(os.getpid() % 150 + 50)
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    return dict(os.environ)


def payloads(size: str, count: int, distinct: int = 8) -> list[bytes]:
    """``count`` serialised images of ``size`` (``distinct`` random frames, stamps 1 s apart)."""
    from tpsr_ros.io import messages as m

    height, width = SIZES[size]
    rng = np.random.default_rng(19)
    frames = rng.integers(0, 255, (distinct, height, width, 3), dtype=np.uint8)
    return [
        m.serialize(m.image_msg(k * 10**9, frames[k % distinct]), m.IMAGE_TYPE)
        for k in range(1, count + 1)
    ]


class RecorderRun:
    """A recorder child process on ``backend`` and this process's node beside it."""

    def __init__(self, tmp: Path, backend: str, name: str, *options: str) -> None:
        from tpsr_ros.io import messages as m
        from tpsr_ros.runtime import Node, NodeOptions
        from tpsr_ros.runtime.backend import open_transport
        from tpsr_ros.runtime.diagnostics import DIAGNOSTICS_TYPE, status_values
        from tpsr_ros.runtime.launcher import NodeProcess

        self.bag = tmp / name
        self.node = Node(
            NodeOptions(name=f"bench_{name}"), transport=open_transport(backend, name, "/")
        )
        self.reports: list[dict[str, str]] = []
        self.node.create_subscription(
            "/diagnostics",
            DIAGNOSTICS_TYPE,
            lambda msg: self.reports.extend(status_values(s) for s in msg.status),
        )
        self.recorder = NodeProcess(
            f"rec_{name}",
            "tpsr_ros.record",
            ["-o", str(self.bag), TOPIC, *options],
            log_path=tmp / f"{name}.log",
            env={**os.environ, "TPSR_TRANSPORT": backend},
        )
        self.msgtype = m.IMAGE_TYPE

    def publisher(self, qos):
        """The image publisher, once the recorder has subscribed to it."""
        pub = self.node.create_publisher(TOPIC, self.msgtype, qos)
        if not self.node.wait_for(lambda: pub.get_subscription_count() >= 1, 60):
            raise RuntimeError(f"the recorder did not subscribe:\n{self.recorder.text()}")
        self.node.spin(timeout_s=0.3)  # let discovery settle on both sides
        return pub

    def reported(self) -> tuple[int, int]:
        """(recorded, not recorded) in the recorder's latest /diagnostics report.

        Not recorded: lost or dropped, or missing by the header stamps if that is more (the
        two count the same messages where both see them).
        """
        if not self.reports:
            return 0, 0
        last = self.reports[-1]
        lost = sum(int(last.get(f"{TOPIC} {kind}", 0)) for kind in ("lost", "dropped"))
        missing = int(last.get(f"{TOPIC} missing by stamps", 0))
        return int(last.get(f"{TOPIC} recorded", 0)), max(lost, missing)

    def finish(self, expected: int, timeout_s: float) -> tuple[list[int], int, int]:
        """Wait until ``expected`` images are accounted for, stop; (log times, lost, missing).

        Lost counts what the middleware reported and what the recorder dropped; missing,
        what the recorder found missing from the images' stamps.
        """
        from tpsr_ros.io.bag import BagReader

        try:
            self.node.wait_for(lambda: sum(self.reported()) >= expected, timeout_s)
            if self.recorder.stop(timeout_s=60) != 0:
                raise RuntimeError(f"recorder failed:\n{self.recorder.text()}")
        finally:
            self.node.close()
            self.recorder.kill()
        with BagReader(self.bag) as reader:
            times = [msg.log_time_ns for msg in reader.messages([TOPIC])]
            custom = reader.custom_data
            lost = sum(
                int(custom.get(f"recorder.{kind}_messages", "0")) for kind in ("lost", "dropped")
            )
            missing = int(custom.get("recorder.missing_by_stamps", "0"))
        return times, lost, missing


def one_run(tmp: Path, backend: str, size: str) -> tuple[float, int, int]:
    """(images/s, missing from the bag, reported lost) for one size on one backend."""
    from tpsr_ros.runtime import QoSProfile

    count = COUNTS[size]
    options = ["--compression", "none"] if size != "16x16" else []
    run = RecorderRun(tmp, backend, f"{backend}_{size}", *options)
    data = payloads(size, count)
    pub = run.publisher(QoSProfile(history="keep_all", depth=0))
    start_ns = time.time_ns()
    for payload in data:
        pub.publish_raw(payload)
        run.node.spin_once(0.0)
    times, lost, _ = run.finish(count, timeout_s=120)
    span = (times[-1] - start_ns) / 1e9 if times else float("nan")
    return len(times) / span, count - len(times), lost


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_record")
    parser.add_argument("--sizes", nargs="+", choices=list(SIZES), default=list(SIZES))
    parser.add_argument("--backends", nargs="+", choices=["dds", "rclpy"], default=None)
    args = parser.parse_args([] if argv is None else argv)  # run by benchmarks: defaults
    backends = args.backends or ["dds", *(["rclpy"] if rclpy_importable() else [])]
    graph_env()
    print(f"   load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores", flush=True)
    root = bag_root()
    print(f"   bags in {root or 'the temporary directory'}", flush=True)
    with tempfile.TemporaryDirectory(dir=root) as tmp:
        for size in args.sizes:
            parts, rates = [], {}
            for backend in backends:
                rate, missing, lost = one_run(Path(tmp), backend, size)
                rates[backend] = rate if not missing else 0.0
                print(
                    f"   {size:>8} {backend:>5}: {COUNTS[size]} images, {missing} missing, "
                    f"{lost} reported lost, {rate:.1f} images/s",
                    flush=True,
                )
                parts.append(f"{backend} {rate:.0f}/s" + (f" ({missing} MISSING)" * bool(missing)))
            goal = ""
            if (target := TARGETS.get(size)) is not None and "dds" in rates:
                verdict = "met" if rates["dds"] >= target else "NOT met"
                goal = f" (target dds >= {target:.0f}: {verdict})"
            print(
                f"recorder loss-free rate {size} rgb8 (2 processes, reliable keep-all): "
                f"{', '.join(parts)}{goal}",
                flush=True,
            )


if __name__ == "__main__":
    main(sys.argv[1:])
