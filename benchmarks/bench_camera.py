"""A 1080p rgb8 camera at 60 Hz into the recorder, on each backend (the large-camera check).

This process is the camera: reliable, keep-last 30 (a camera driver's usual QoS), one
1920x1080 rgb8 image every 1/60 s on a fixed schedule (a late image is sent at once, the
schedule is never shifted) for 300 images; ``python -m tpsr_ros.record --compression none``
records it in a child process. Prints, per backend, the images in the bag, those missing,
those the recorder reported lost or dropped (they must match), those it found missing from
the images' stamps (each image is stamped on the camera's schedule), and the rate the
camera actually kept (a reliable DDS writer waits for a slow recorder instead of dropping,
so a recorder that cannot keep up shows as a camera below 60 Hz, not as loss), and the UDP
datagrams the host
dropped at full socket receive buffers meanwhile (a burst larger than the buffer, which
the kernel caps at net.core.rmem_max, overflows it when the receiving thread is not
scheduled in time, and the reliable protocol's repairs then fall behind).
Target: 300 recorded at 60 Hz.
"""

from __future__ import annotations

import argparse
import os
import struct
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.bench_record import (
    RecorderRun,
    bag_root,
    graph_env,
    payloads,
    rclpy_importable,
)

RATE_HZ = 60.0
IMAGES = 300


def udp_receive_buffer_errors() -> int | None:
    """This host's UDP datagrams dropped at a full socket receive buffer so far (Linux).

    Host-wide (every process, ours or not), from ``RcvbufErrors`` in /proc/net/snmp; None
    where it cannot be read.
    """
    try:
        lines = [x.split() for x in Path("/proc/net/snmp").read_text().splitlines()]
        names, values = (x for x in lines if x and x[0] == "Udp:")
        return int(values[names.index("RcvbufErrors")])
    except (OSError, ValueError, IndexError):
        return None


def restamped(data: bytes, stamp_ns: int) -> bytes:
    """Serialised little-endian CDR of a message starting with a Header, with a new stamp."""
    out = bytearray(data)
    struct.pack_into("<iI", out, 4, *divmod(stamp_ns, 10**9))
    return bytes(out)


def one_run(tmp: Path, backend: str, rate_hz: float) -> tuple[int, int, int, int, float]:
    """(recorded, missing, reported lost, missing by stamps, camera rate) for one backend."""
    from tpsr_ros.runtime import QoSProfile

    run = RecorderRun(tmp, backend, f"camera_{backend}", "--compression", "none")
    frames = payloads("1080p", 8)
    pub = run.publisher(QoSProfile(depth=30))
    period_ns = round(1e9 / rate_hz)
    start = time.monotonic_ns()
    for k in range(IMAGES):
        due = start + k * period_ns
        data = restamped(frames[k % len(frames)], 10**12 + k * period_ns)  # a new buffer
        while (wait := due - time.monotonic_ns()) > 0:
            run.node.spin_once(wait / 1e9)
        pub.publish_raw(data)
    camera_rate = (IMAGES - 1) / ((time.monotonic_ns() - start) / 1e9)
    times, lost, by_stamps = run.finish(IMAGES, timeout_s=30)
    return len(times), IMAGES - len(times), lost, by_stamps, camera_rate


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_camera")
    parser.add_argument("--rate", type=float, default=RATE_HZ, help="camera rate (Hz)")
    parser.add_argument("--backends", nargs="+", choices=["dds", "rclpy"], default=None)
    args = parser.parse_args([] if argv is None else argv)  # run by benchmarks: defaults
    graph_env()
    print(f"   load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores", flush=True)
    backends = args.backends or ["dds", *(["rclpy"] if rclpy_importable() else [])]
    root = bag_root()
    print(f"   bags in {root or 'the temporary directory'}", flush=True)
    with tempfile.TemporaryDirectory(dir=root) as tmp:
        for backend in backends:
            drops_before = udp_receive_buffer_errors()
            recorded, missing, lost, by_stamps, rate = one_run(Path(tmp), backend, args.rate)
            drops_after = udp_receive_buffer_errors()
            met = recorded == IMAGES and rate >= 0.97 * args.rate
            print(
                f"camera 1080p rgb8 at {args.rate:.0f} Hz, {IMAGES} images, {backend}: "
                f"{recorded} recorded, {missing} missing: {lost} reported lost by the "
                f"middleware, {by_stamps} found missing by the stamps ("
                f"{'all' if max(lost, by_stamps) == missing else 'NOT all'} accounted for), "
                "camera kept "
                f"{rate:.1f} Hz (target {IMAGES} recorded at {args.rate:.0f} Hz: "
                f"{'met' if met else 'NOT met'})",
                flush=True,
            )
            if drops_before is not None and drops_after is not None:
                print(
                    f"   UDP datagrams this host dropped at full socket receive buffers during "
                    f"the run: {drops_after - drops_before} (net.core.rmem_max caps the buffer)",
                    flush=True,
                )
            if backend == "dds" and missing > lost:
                print(
                    "   (the DDS backend cannot count these as lost: the camera's keep-last 30 "
                    "history overwrote them before the recorder's Cyclone reader had them, "
                    "Cyclone raises no sample-lost status for that and gives no sequence "
                    "numbers; the recorder finds them missing from the stamps instead)",
                    flush=True,
                )


if __name__ == "__main__":
    main(sys.argv[1:])
