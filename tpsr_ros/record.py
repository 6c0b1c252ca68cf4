"""Record topics into a rosbag2 MCAP bag, like ``ros2 bag record``.

    python -m tpsr_ros.record -o BAG [TOPIC ...]

With no topic, every topic found in the graph is recorded (except hidden ones and
``/rosout``, ``/parameter_events``); topics are discovered every ``--polling-interval``
ms, so publishers that appear later are recorded from then on. Each subscription adapts to
what the publishers offer, as rosbag2 does: reliable when every publisher is reliable,
transient-local when every publisher is (so latched messages are recorded), history
keep-all so the recorder never overwrites what it has not written yet. The offered QoS
profiles are stored in the bag, where ``python -m tpsr_ros.play`` reuses them.

Messages are written as the CDR bytes received (``raw=True``), with the receive time as
log time, through ``tpsr_ros.io.bag.BagWriter`` (the generator's bag module). The output
path must not exist; it is checked before anything subscribes. SIGINT or SIGTERM drains
what has arrived and closes the bag cleanly. The bag is flushed every
``--flush-interval`` seconds (default 1), so after a hard kill (SIGKILL, power loss)
``python -m tpsr_ros.bag_recover BAG`` rebuilds a readable bag holding everything up to
the last flush. A topic published with two types is an error: the recorder stops and
closes the bag (what it holds stays readable) and exits with status 1.
"""

from __future__ import annotations

import time
from collections import defaultdict
from pathlib import Path
from typing import Any

from tpsr_ros.cli import ArgumentParser, positive_float
from tpsr_ros.core.errors import BagError, TpsrError
from tpsr_ros.io.bag import BagWriter, check_bag_path_free
from tpsr_ros.io.messages import jazzy_typestore
from tpsr_ros.io.qos import adapt_to_publishers, compatible, to_bag_qos
from tpsr_ros.runtime import Node, NodeOptions, QoSProfile, run_node

__all__ = ["RecorderNode", "main"]

PROG = "python -m tpsr_ros.record"
EXCLUDED_BY_DEFAULT = ("/rosout", "/parameter_events")


def _hidden(topic: str) -> bool:
    return any(part.startswith("_") for part in topic.split("/"))


class RecorderNode(Node):
    """Subscribes to discovered topics and writes what arrives into a bag."""

    default_name = "tpsr_recorder"
    description = "Record topics into a rosbag2 MCAP bag, like `ros2 bag record`."

    @classmethod
    def argument_parser(cls, prog: str) -> ArgumentParser:
        """``-o BAG [TOPIC ...]`` and recording options."""
        parser = ArgumentParser(prog=prog, description=cls.description, add_help=False)
        parser.add_argument("-o", "--output", required=True, type=Path, help="new bag directory")
        parser.add_argument("topics", nargs="*", help="topics to record (default: all)")
        parser.add_argument(
            "--polling-interval",
            type=positive_float,
            default=100.0,
            help="ms between graph scans for new topics (default 100)",
        )
        parser.add_argument(
            "--flush-interval",
            type=positive_float,
            default=1.0,
            help="s between flushes to disk; a hard kill loses at most this much (default 1)",
        )
        parser.add_argument(
            "--include-hidden-topics",
            action="store_true",
            help="also record topics with a component starting with '_'",
        )
        return parser

    @classmethod
    def preflight(cls, options: NodeOptions) -> None:
        """Refuse an existing or unwritable output path before joining the graph."""
        assert options.args is not None
        check_bag_path_free(options.args.output)

    def setup(self) -> None:
        """Open the bag, scan the graph now and every polling interval, flush every second."""
        args = self.options.args
        if args is None:
            raise TpsrError("the recorder needs its command-line options (-o BAG)")
        self.wanted = {self.resolve_topic(t) for t in args.topics} or None
        self.include_hidden = bool(args.include_hidden_topics)
        self.writer = BagWriter(args.output).open()
        self.subscribed: dict[str, str] = {}
        self.qos: dict[str, QoSProfile] = {}
        self.counts: dict[str, int] = defaultdict(int)
        self._warned: set[tuple[str, str]] = set()
        self._closed_bag = False
        self.exit_code = 0
        self._first_scan = self.create_timer(0.001, self._scan_now)
        self.create_timer(args.polling_interval / 1000.0, self.discover)
        self.create_timer(args.flush_interval, self.writer.flush)
        what = "all topics" if self.wanted is None else ", ".join(sorted(self.wanted))
        self.logger.info(f"recording {what} to {args.output}")

    def _scan_now(self) -> None:
        self._first_scan.cancel()
        self.discover()

    def _warn_once(self, key: tuple[str, str], message: str) -> None:
        if key not in self._warned:
            self._warned.add(key)
            self.logger.warning(message)

    def _selected(self, topic: str) -> bool:
        if self.wanted is not None:
            return topic in self.wanted
        if topic in EXCLUDED_BY_DEFAULT:
            return False
        return self.include_hidden or not _hidden(topic)

    def discover(self) -> None:
        """Subscribe to every selected topic that has publishers and is not recorded yet."""
        by_topic: dict[str, list[Any]] = defaultdict(list)
        for endpoint in self.transport.publishers():
            if self._selected(endpoint.topic):
                by_topic[endpoint.topic].append(endpoint)
        for topic, endpoints in sorted(by_topic.items()):
            types = sorted({e.msgtype for e in endpoints})
            if len(types) > 1:
                raise BagError(f"topic type clash: {topic} is published as {' and '.join(types)}")
            msgtype = types[0]
            if topic in self.subscribed:
                if self.subscribed[topic] != msgtype:
                    raise BagError(
                        f"topic type clash: {topic} is recorded as {self.subscribed[topic]} "
                        f"but a publisher now offers {msgtype}"
                    )
                for e in endpoints:
                    if not compatible(e.qos, self.qos[topic]):
                        self._warn_once(
                            (topic, "qos"),
                            f"a publisher on {topic} offers {e.qos}, which the recorder's "
                            f"{self.qos[topic]} subscription cannot receive",
                        )
                continue
            if msgtype not in jazzy_typestore().fielddefs:
                self._warn_once(
                    (topic, "type"), f"not recording {topic}: unknown message type {msgtype}"
                )
                continue
            qos = adapt_to_publishers(e.qos for e in endpoints)
            self.writer.add_topic(topic, msgtype, [to_bag_qos(e.qos) for e in endpoints])
            self.create_subscription(
                topic, msgtype, self._writer_for(topic), qos, raw=True
            )
            self.subscribed[topic] = msgtype
            self.qos[topic] = qos
            self.logger.info(f"subscribed to {topic} ({msgtype}; {qos})")

    def _writer_for(self, topic: str) -> Any:
        write = self.writer.write
        counts = self.counts

        def on_message(data: bytes) -> None:
            write(topic, time.time_ns(), data)
            counts[topic] += 1

        return on_message

    def on_shutdown(self) -> None:
        """Write what has already arrived, then close the bag (it stays readable)."""
        if self._closed_bag:
            return
        self._closed_bag = True
        try:
            for _ in range(1000):  # drain everything the middleware already holds
                if self.transport.spin_once(0.0) == 0:
                    break
        finally:
            self.writer.close()
        total = sum(self.counts.values())
        self.logger.info(
            f"recorded {total} messages on {len(self.subscribed)} topics to {self.writer.path}"
        )


def main(argv: list[str] | None = None) -> None:
    """Entry point of ``python -m tpsr_ros.record``."""
    run_node(RecorderNode, prog=PROG, argv=argv)


if __name__ == "__main__":
    main()
