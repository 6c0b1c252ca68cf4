"""Bag reading against raw MCAP record iteration (target: at most 1.5x), and its memory.

Data: the 24000-step ``full`` bag of ``bench_fit`` (generated once). Timed in this
process, median of 5 rounds that each run the four in turn (a busy machine slows all
alike): iterating every message record with the ``mcap`` library alone, touching each
record's ``.data`` (the reference: no decoding, no pairing); rosbags' own message
iteration (faster than the ``mcap`` library's, and the floor of our reader, which parses
records with it); ``read_trajectory``; and consuming every chunk of
``iter_trajectory_chunks``. Peak RSS (``VmHWM``) is measured in
a fresh child process per reader, on the bag once and listed 4 times (96000 steps): the
chunked reader's peak must not grow with the data, ``read_trajectory``'s holds it all.

Robot bags (``learner fit --step-period``): a 2000-step bgr8 bag of ``sim_node.robot_bag``
(40x40 camera at 4 Hz, ``Twist`` at 2 Hz, ``Odometry`` at 10 Hz), ``read_stream_trajectory``
against the raw iteration of the same bag, the same way (no target: the target names the
simulator bags).
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

from mcap.reader import make_reader

from benchmarks.bench_fit import STEPS
from benchmarks.bench_fit import _bag as generate_full_bag
from sim_node.robot_bag import RobotBagConfig, write_robot_bag
from tpsr_ros.io.streams import FitOptions, fit_stream_spec, read_stream_trajectory
from tpsr_ros.io.trajectory import DEFAULT_CHUNK_STEPS, iter_trajectory_chunks, read_trajectory

REPEATS = 5
TARGET_RATIO = 1.5
COPIES = 4  # the bag listed this many times for the memory figure
ROBOT_STEPS = 2000

_CHILD = """
import json, sys, time
from tpsr_ros.io.trajectory import iter_trajectory_chunks, read_trajectory
def status(key):  # kB; VmHWM is this process's own peak (ru_maxrss keeps the parent's)
    line = next(l for l in open("/proc/self/status") if l.startswith(key + ":"))
    return int(line.split()[1])
bags = sys.argv[2:]
before = status("VmRSS")
start = time.perf_counter()
if sys.argv[1] == "chunks":
    steps = sum(len(chunk) for chunk in iter_trajectory_chunks(bags))
else:
    steps = len(read_trajectory(bags))
seconds = time.perf_counter() - start
peak = status("VmHWM")
print(json.dumps({"steps": steps, "seconds": seconds, "before": before, "peak": peak}))
"""


def raw_mcap_iteration(bag: Path) -> int:
    """Every message record of the bag's MCAP files, ``.data`` touched: the reference."""
    total = 0
    for file in sorted(bag.glob("*.mcap")):
        with file.open("rb") as handle:
            for _, _, message in make_reader(handle).iter_messages():
                total += len(message.data)
    return total


def rosbags_iteration(bag: Path) -> int:
    """rosbags' own message iteration (the record parsing our reader builds on), bytes only."""
    from rosbags.rosbag2 import Reader

    total = 0
    with Reader(bag) as reader:
        for _, _, data in reader.messages():
            total += len(data)
    return total


def _timed(run: Callable[[], object]) -> float:
    start = time.perf_counter()
    run()
    return time.perf_counter() - start


def _interleaved(runs: dict[str, Callable[[], object]]) -> dict[str, list[float]]:
    """Seconds of ``REPEATS`` rounds, each running every reader once in turn (so a busy
    machine slows all of them alike and the ratios stay fair)."""
    times: dict[str, list[float]] = {name: [] for name in runs}
    for _ in range(REPEATS):
        for name, run in runs.items():
            times[name].append(_timed(run))
    return times


def _consume_chunks(bag: Path) -> int:
    return sum(len(chunk) for chunk in iter_trajectory_chunks([bag]))


def _robot_times(directory: str) -> tuple[dict[str, list[float]], int]:
    """Interleaved rounds of raw iteration and ``read_stream_trajectory`` of a robot bag."""
    bag = Path(directory) / "robot_bgr8"
    count = write_robot_bag(bag, RobotBagConfig(steps=ROBOT_STEPS, encoding="bgr8"))
    options = FitOptions(step_period=1.0, image_size=(16, 16), actions=25)
    spec = fit_stream_spec([bag], options, image_topic="/front_camera/image_raw",
                           action_topic="/cmd_vel")
    times = _interleaved({
        "raw": lambda: raw_mcap_iteration(bag),
        "read_stream_trajectory": lambda: read_stream_trajectory([bag], spec, pose_topic="/odom"),
    })
    return times, count


def _child(reader: str, bags: list[Path]) -> dict[str, float]:
    done = subprocess.run(
        [sys.executable, "-c", _CHILD, reader, *map(str, bags)],
        capture_output=True, text=True, check=True,
    )
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    with tempfile.TemporaryDirectory() as directory:
        bag = generate_full_bag(directory)
        size = sum(f.stat().st_size for f in bag.glob("*.mcap")) / 2**20
        times = _interleaved({
            "raw": lambda: raw_mcap_iteration(bag),
            "rosbags": lambda: rosbags_iteration(bag),
            "read_trajectory": lambda: read_trajectory([bag]),
            "chunks": lambda: _consume_chunks(bag),
        })
        memory = {
            (reader, copies): _child(reader, [bag] * copies)
            for reader in ("read_trajectory", "chunks")
            for copies in (1, COPIES)
        }
        robot, robot_messages = _robot_times(directory)
    load = os.getloadavg()
    print(
        f"Reading the generated full bag of {STEPS} steps ({size:.1f} MiB MCAP, 5 topics, "
        f"4 read); median of {REPEATS} rounds; load average {load[0]:.1f} {load[1]:.1f} on "
        f"{os.cpu_count()} CPUs"
    )
    raw = statistics.median(times["raw"])
    print(f"  raw mcap record iteration (reference) {raw:6.3f} s (fastest {min(times['raw']):.3f})")
    floor = statistics.median(times["rosbags"])
    print(
        f"  rosbags' message iteration (no decoding; the floor of our reader, which parses "
        f"records with it) {floor:.3f} s = {floor / raw:.2f}x raw"
    )
    for key, name in (
        ("read_trajectory", "read_trajectory"),
        ("chunks", f"iter_trajectory_chunks ({DEFAULT_CHUNK_STEPS} steps)"),
    ):
        seconds = statistics.median(times[key])
        ratio = seconds / raw
        ratios = [t / r for t, r in zip(times[key], times["raw"], strict=True)]
        verdict = "ok" if ratio <= TARGET_RATIO else "ABOVE TARGET"
        print(
            f"  {name:37s} {seconds:6.3f} s (fastest {min(times[key]):.3f}) = {ratio:.2f}x raw "
            f"(per round {min(ratios):.2f}-{max(ratios):.2f}x; target <= {TARGET_RATIO}x: "
            f"{verdict}); {seconds / floor:.2f}x rosbags' iteration; {STEPS / seconds:,.0f} "
            "steps/s"
        )
    print("  peak RSS of a fresh process reading (VmHWM; after imports in brackets):")
    for (reader, copies), figures in memory.items():
        print(
            f"    {reader:16s} x{copies} ({figures['steps']:6.0f} steps): "
            f"{figures['peak'] / 1024:6.0f} MiB ({figures['before'] / 1024:.0f} MiB), "
            f"{figures['seconds']:.2f} s"
        )
    raw, read = statistics.median(robot["raw"]), statistics.median(robot["read_stream_trajectory"])
    print(
        f"  robot bag ({ROBOT_STEPS} steps, {robot_messages} messages, bgr8 40x40): raw "
        f"{raw:.3f} s, read_stream_trajectory {read:.3f} s = {read / raw:.2f}x raw"
    )


if __name__ == "__main__":
    main()
