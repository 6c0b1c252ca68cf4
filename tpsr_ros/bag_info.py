"""Summarise a rosbag2 MCAP bag, like ``ros2 bag info``.

    python -m tpsr_ros.bag_info BAG

Prints files, size, storage, duration, start and end (UTC and seconds), the message count
and, per topic, its type, count, serialization format and offered QoS. A path that is not
a rosbag2 MCAP bag is refused with one line on stderr and exit status 1.
"""

from __future__ import annotations

import datetime as dt
from pathlib import Path

from tpsr_ros.cli import ArgumentParser, run_cli
from tpsr_ros.core.units import NS_PER_S as _NS
from tpsr_ros.io.bag import BagReader
from tpsr_ros.io.qos import from_bag_qos

__all__ = ["format_info", "main"]

PROG = "python -m tpsr_ros.bag_info"


def _size(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n:.1f} {unit}" if unit != "B" else f"{int(n)} B"
        n /= 1024
    return f"{n:.1f} GiB"


def _time(ns: int) -> str:
    when = dt.datetime.fromtimestamp(ns // _NS, tz=dt.timezone.utc)
    return f"{when:%b %d %Y %H:%M:%S}.{ns % _NS:09d} UTC ({ns // _NS}.{ns % _NS:09d})"


def format_info(path: Path) -> str:
    """The summary of bag ``path`` as text."""
    with BagReader(path) as reader:
        topics = reader.topics
        counts = reader.message_counts
        qos = reader.qos_profiles
        total = sum(counts.values())
        start = reader.start_time_ns if total else 0
        end = reader.end_time_ns - 1 if total else 0
        files = reader.files
    size = sum(p.stat().st_size for p in Path(path).iterdir() if p.is_file())
    duration = max(0, end - start)
    lines = [
        f"Files:             {', '.join(files)}",
        f"Bag size:          {_size(size)}",
        "Storage id:        mcap",  # BagReader refuses any other storage
        f"Duration:          {duration // _NS}.{duration % _NS:09d}s",
        f"Start:             {_time(start)}" if total else "Start:             (no messages)",
        f"End:               {_time(end)}" if total else "End:               (no messages)",
        f"Messages:          {total}",
    ]
    width = max((len(t) for t in topics), default=0)
    type_width = max((len(t) for t in topics.values()), default=0)
    for i, topic in enumerate(sorted(topics)):
        profile = from_bag_qos(qos.get(topic, []))
        offered = str(profile) if profile is not None else "not recorded"
        head = "Topic information: " if i == 0 else " " * 19
        lines.append(
            f"{head}Topic: {topic:<{width}} | Type: {topics[topic]:<{type_width}} | "
            f"Count: {counts.get(topic, 0)} | Serialization Format: cdr | QoS: {offered}"
        )
    if not topics:
        lines.append("Topic information: (none)")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Print the summary of one bag."""
    parser = ArgumentParser(prog=PROG, description=__doc__.split("\n")[0])
    parser.add_argument("bag", type=Path, help="rosbag2 MCAP bag directory")
    args = parser.parse_args(argv)
    print(format_info(args.bag))
    return 0


if __name__ == "__main__":
    run_cli(PROG, main)
