"""Summarise a rosbag2 MCAP bag, like ``ros2 bag info``.

    python -m tpsr_ros.bag_info BAG

Prints files, size, storage, duration, start and end (UTC and seconds), the message count
and, per topic, its type, count, serialization format and the QoS profiles its publishers
offered as recorded (each distinct one once; ``history unknown`` where the recorder could
not learn a publisher's history and depth, never a made-up depth). ``BAG`` is the bag
directory, one of its ``.mcap`` files (the bag it belongs to is shown), or a lone ``.mcap``
file with no ``metadata.yaml`` (summarised from its own summary section; "QoS: not
recorded" where its channels carry none). A path that is none of these is refused with one
line on stderr and exit status 1.
"""

from __future__ import annotations

import datetime as dt
from pathlib import Path

from tpsr_ros.cli import ArgumentParser, run_cli
from tpsr_ros.core.units import NS_PER_S as _NS
from tpsr_ros.io.bag import BagReader
from tpsr_ros.io.qos import offered_text

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
    """The summary of bag ``path`` (a directory, or a ``.mcap`` file) as text."""
    path = Path(path)
    if path.suffix == ".mcap" and path.is_file():
        if not (path.parent / "metadata.yaml").is_file():
            return _lone_mcap_info(path)
        path = path.parent  # a bag's file: the bag it belongs to
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
        offered = offered_text(qos.get(topic, []))
        head = "Topic information: " if i == 0 else " " * 19
        lines.append(
            f"{head}Topic: {topic:<{width}} | Type: {topics[topic]:<{type_width}} | "
            f"Count: {counts.get(topic, 0)} | Serialization Format: cdr | QoS: {offered}"
        )
    if not topics:
        lines.append("Topic information: (none)")
    return "\n".join(lines)


def _lone_mcap_info(path: Path) -> str:
    """The summary of an MCAP file without rosbag2 metadata (its summary section)."""

    from mcap.exceptions import McapError
    from mcap.reader import make_reader
    from rosbags.rosbag2 import ReaderError
    from rosbags.rosbag2.metadata import parse_qos

    from tpsr_ros.io.bag import BagError

    try:
        with path.open("rb") as handle:
            summary = make_reader(handle).get_summary()
    except (McapError, OSError, ValueError) as exc:
        raise BagError(f"cannot read {str(path)!r} as MCAP: {exc}") from None
    if summary is None or summary.statistics is None:
        raise BagError(f"{str(path)!r} has no MCAP summary section (run bag_recover on its bag)")
    stats = summary.statistics
    total = int(stats.message_count)
    start, end = int(stats.message_start_time), int(stats.message_end_time)
    duration = max(0, end - start)
    lines = [
        f"Files:             {path.name} (no metadata.yaml)",
        f"Bag size:          {_size(path.stat().st_size)}",
        "Storage id:        mcap",
        f"Duration:          {duration // _NS}.{duration % _NS:09d}s",
        f"Start:             {_time(start)}" if total else "Start:             (no messages)",
        f"End:               {_time(end)}" if total else "End:               (no messages)",
        f"Messages:          {total}",
    ]
    channels = sorted(summary.channels.values(), key=lambda c: c.topic)
    width = max((len(c.topic) for c in channels), default=0)
    names = {c.id: summary.schemas[c.schema_id].name if c.schema_id in summary.schemas else "?"
             for c in channels}  # fmt: skip
    type_width = max((len(n) for n in names.values()), default=0)
    for i, channel in enumerate(channels):
        text = channel.metadata.get("offered_qos_profiles", "")
        try:
            offered = offered_text(parse_qos(text)) if text else "not recorded"
        except (ReaderError, ValueError, KeyError, TypeError, AttributeError):
            offered = "not recorded"
        head = "Topic information: " if i == 0 else " " * 19
        lines.append(
            f"{head}Topic: {channel.topic:<{width}} | Type: {names[channel.id]:<{type_width}} | "
            f"Count: {stats.channel_message_counts.get(channel.id, 0)} | Serialization Format: "
            f"{channel.message_encoding} | QoS: {offered}"
        )
    if not channels:
        lines.append("Topic information: (none)")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Print the summary of one bag."""
    parser = ArgumentParser(prog=PROG, description=__doc__.split("\n")[0])
    parser.add_argument(
        "bag", type=Path, help="rosbag2 MCAP bag directory, one of its .mcap files, or a lone .mcap"
    )
    args = parser.parse_args(argv)
    print(format_info(args.bag))
    return 0


if __name__ == "__main__":
    run_cli(PROG, main)
