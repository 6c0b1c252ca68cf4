"""Rebuild a readable bag from one whose recorder was killed hard (no metadata.yaml).

    python -m tpsr_ros.bag_recover BAG [--keep-original]

A recorder killed with SIGKILL (or a power cut) leaves ``BAG/BAG.mcap`` truncated: it has
no summary section, and no ``metadata.yaml`` was written. The recorder flushes the bag
every second, closing an MCAP chunk each time, so the file holds complete chunks up to
the last flush followed by at most one partial record.

Recovery reads the file front to back with the ``mcap`` library's non-seeking
``StreamReader`` (which needs no summary), keeps every schema, channel and message record
of the complete chunks and stops at the first truncated or damaged record. It writes them
into a fresh bag with ``tpsr_ros.io.bag.BagWriter`` (same topics, types, offered QoS and
log times), then replaces the damaged ``.mcap`` with it and adds ``metadata.yaml``. With
``--keep-original`` the damaged file is kept as ``BAG.mcap.truncated``. A bag that
already has ``metadata.yaml`` is left untouched.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader
from rosbags.rosbag2.metadata import parse_qos

from tpsr_ros.cli import ArgumentParser, run_cli
from tpsr_ros.core.errors import BagError
from tpsr_ros.io.bag import BagWriter

__all__ = ["RecoveryReport", "main", "recover_bag"]

PROG = "python -m tpsr_ros.bag_recover"


@dataclass(frozen=True)
class RecoveryReport:
    """What a recovery kept."""

    path: Path
    messages: int
    topics: dict[str, int]
    stopped_early: str | None  # why reading stopped before the end of the file


def _mcap_file(bag: Path) -> Path:
    if not bag.is_dir():
        raise BagError(f"{str(bag)!r} is not a bag directory")
    files = sorted(p for p in bag.iterdir() if p.suffix == ".mcap" and p.is_file())
    if len(files) != 1:
        raise BagError(f"{str(bag)!r} holds {len(files)} .mcap files; expected exactly one")
    return files[0]


def recover_bag(bag: Path | str, *, keep_original: bool = False) -> RecoveryReport:
    """Rebuild ``bag`` in place from its truncated MCAP file."""
    bag = Path(bag)
    if (bag / "metadata.yaml").is_file():
        raise BagError(f"{str(bag)!r} already has metadata.yaml; nothing to recover")
    source = _mcap_file(bag)
    work = bag / ".recovering"
    if work.exists():
        shutil.rmtree(work)
    work.mkdir()
    target = work / bag.name
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    counts: dict[str, int] = {}
    stopped: str | None = None
    try:
        with source.open("rb") as stream, BagWriter(target) as writer:
            try:
                for record in StreamReader(stream, skip_magic=False).records:
                    if isinstance(record, Schema):
                        schemas[record.id] = record
                    elif isinstance(record, Channel):
                        channels[record.id] = record
                        schema = schemas.get(record.schema_id)
                        if schema is None:
                            raise BagError(f"channel {record.topic} has no schema")
                        qos = parse_qos(record.metadata.get("offered_qos_profiles", ""))
                        writer.add_topic(record.topic, schema.name, qos)
                    elif isinstance(record, Message):
                        channel = channels.get(record.channel_id)
                        if channel is None:
                            continue
                        writer.write(channel.topic, record.log_time, record.data)
                        counts[channel.topic] = counts.get(channel.topic, 0) + 1
            except Exception as exc:
                stopped = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
            for topic in (c.topic for c in channels.values()):
                counts.setdefault(topic, 0)
    except BaseException:
        shutil.rmtree(work, ignore_errors=True)
        raise
    if keep_original:
        source.rename(source.with_name(source.name + ".truncated"))
    else:
        source.unlink()
    (target / f"{bag.name}.mcap").rename(bag / f"{bag.name}.mcap")
    (target / "metadata.yaml").rename(bag / "metadata.yaml")
    shutil.rmtree(work)
    return RecoveryReport(bag, sum(counts.values()), counts, stopped)


def main(argv: list[str] | None = None) -> int:
    """Recover one bag and print what it holds."""
    parser = ArgumentParser(prog=PROG, description=__doc__.split("\n")[0])
    parser.add_argument("bag", type=Path, help="bag directory without metadata.yaml")
    parser.add_argument(
        "--keep-original", action="store_true", help="keep the damaged file as .truncated"
    )
    args = parser.parse_args(argv)
    report = recover_bag(args.bag, keep_original=args.keep_original)
    print(f"recovered {report.messages} messages on {len(report.topics)} topics into {args.bag}")
    for topic, count in sorted(report.topics.items()):
        print(f"  {topic}: {count}")
    if report.stopped_early:
        print(f"  (reading stopped at a truncated record: {report.stopped_early})")
    return 0


if __name__ == "__main__":
    run_cli(PROG, main)
