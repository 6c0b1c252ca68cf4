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

Receiving never waits for the disk: messages go to an in-memory cache of at most
``--max-cache-size`` bytes that a thread writes to the bag
(:class:`~tpsr_ros.io.bag_cache.CachedBagWriter`); past it new messages are dropped.

Nothing is lost silently. Messages the middleware reports lost before the recorder got
them (DDS sample-lost events; under rclpy Fast DDS's message-lost event or the gaps in the
publisher's sequence numbers; best-effort samples Cyclone rejected because the recorder
fell 256 samples behind) and messages
dropped at a full cache are counted per topic and logged; messages the recorder refuses
(larger than ``--max-message-size``, or an ``Image`` that cannot be a whole image:
truncated data, rows shorter than width x bytes per pixel) are logged with their index
and counted. Where the middleware cannot say (Cyclone DDS raises no status for samples a
keep-last writer dropped before the recorder had them; a camera driver drops frames
itself), topics with a steady cadence of header stamps show it: messages missing from the
cadence are counted apart (:class:`~tpsr_ros.core.cadence.CadenceGaps`), whoever lost them.
The counts go to ``/diagnostics`` every second, to the bag's ``custom_data``
(``recorder.lost_messages``, ``recorder.dropped_messages``, ``recorder.rejected_messages``,
``recorder.missing_by_stamps`` and per topic ``recorder.by_topic``) and to the end-of-run
line.
"""

from __future__ import annotations

import json
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

from tpsr_ros.cli import ArgumentParser, positive_float, positive_int
from tpsr_ros.core.cadence import CadenceGaps
from tpsr_ros.core.errors import BagError, MessageError, TpsrError
from tpsr_ros.io.bag import BagWriter, check_bag_path_free
from tpsr_ros.io.bag_cache import CachedBagWriter
from tpsr_ros.io.messages import (
    IMAGE_TYPE,
    deserialize,
    image_problem,
    jazzy_typestore,
    peek_stamp,
    starts_with_header,
)
from tpsr_ros.io.qos import adapt_to_publishers, compatible, to_bag_qos
from tpsr_ros.runtime import Node, NodeOptions, QoSProfile, Subscription, run_node
from tpsr_ros.runtime.diagnostics import (
    DIAGNOSTICS_TYPE,
    OK,
    WARN,
    diagnostic_array,
    diagnostic_status,
)

__all__ = ["RecorderNode", "main"]

PROG = "python -m tpsr_ros.record"
EXCLUDED_BY_DEFAULT = ("/rosout", "/parameter_events")
DIAGNOSTICS_TOPIC = "/diagnostics"
# unread samples the middleware may hold per topic while the recorder is busy (DDS backend)
CACHE_SAMPLES = 256
DEFAULT_MAX_MESSAGE_BYTES = 256 * 1024 * 1024
DEFAULT_MAX_CACHE_BYTES = 1024 * 1024 * 1024
_LOGGED_REJECTIONS = 5  # per topic and kind; later ones are counted only


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
            "--compression",
            choices=("zstd", "none"),
            default="zstd",
            help="MCAP chunk compression (default zstd); 'none' writes camera images at "
            "camera rate (zstd takes 10-35 ms per 1080p image)",
        )
        parser.add_argument(
            "--max-message-size",
            type=positive_int,
            default=DEFAULT_MAX_MESSAGE_BYTES,
            metavar="BYTES",
            help="refuse (count and log) larger messages (default 256 MiB)",
        )
        parser.add_argument(
            "--max-cache-size",
            type=positive_int,
            default=DEFAULT_MAX_CACHE_BYTES,
            metavar="BYTES",
            help="messages received but not yet written, at most (default 1 GiB); "
            "past it new messages are dropped, counted and logged",
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
        self.writer = CachedBagWriter(
            BagWriter(args.output, compress=args.compression == "zstd").open(),
            args.max_cache_size,
        )
        self.subscribed: dict[str, str] = {}
        self.qos: dict[str, QoSProfile] = {}
        self.counts: dict[str, int] = defaultdict(int)
        self.lost: dict[str, int] = defaultdict(int)
        self.rejected: dict[str, int] = defaultdict(int)
        self.dropped: dict[str, int] = defaultdict(int)
        self.cadence: dict[str, CadenceGaps] = {}
        self._missing_logged: dict[str, int] = defaultdict(int)
        self.subscriptions: dict[str, Subscription] = {}
        self.max_message_size = int(args.max_message_size)
        self._warned: set[tuple[str, str]] = set()
        self._closed_bag = False
        self.exit_code = 0
        # a busy recorder holds back reliable publishers instead of buffering without bound
        self.transport.limit_keep_all_readers(CACHE_SAMPLES)
        self.diagnostics = self.create_publisher(DIAGNOSTICS_TOPIC, DIAGNOSTICS_TYPE)
        self._first_scan = self.create_timer(0.001, self._scan_now)
        self.create_timer(args.polling_interval / 1000.0, self.discover)
        self.create_timer(args.flush_interval, self.writer.flush)
        self.create_timer(1.0, self.publish_diagnostics)
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
        self.check_losses()
        by_topic: dict[str, list[Any]] = defaultdict(list)
        for endpoint in self.transport.publishers():
            if self._selected(endpoint.topic):
                by_topic[endpoint.topic].append(endpoint)
        own = by_topic.get(DIAGNOSTICS_TOPIC, [])
        for e in own:  # the recorder's own /diagnostics publisher is not recorded
            if e.msgtype == DIAGNOSTICS_TYPE and e.qos == self.diagnostics.qos:
                own.remove(e)
                break
        for topic, endpoints in sorted(by_topic.items()):
            if not endpoints:
                continue
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
            offered = [to_bag_qos(e.qos) for e in endpoints]
            self.writer.add_topic(topic, msgtype, offered)
            self.subscriptions[topic] = self.create_subscription(
                topic, msgtype, self._writer_for(topic, msgtype), qos, raw=True
            )
            self.subscribed[topic] = msgtype
            self.qos[topic] = qos
            self.logger.info(f"subscribed to {topic} ({msgtype}; {qos})")

    def _writer_for(self, topic: str, msgtype: str) -> Any:
        put = self.writer.put
        counts, rejected, dropped = self.counts, self.rejected, self.dropped
        max_size = self.max_message_size
        is_image = msgtype == IMAGE_TYPE
        own_reports = topic == DIAGNOSTICS_TOPIC and msgtype == DIAGNOSTICS_TYPE
        cadence = None
        if starts_with_header(msgtype) and not own_reports:
            cadence = self.cadence[topic] = CadenceGaps()

        def on_message(data: bytes) -> None:
            received = time.time_ns()
            if own_reports and self._is_own_report(data):
                return
            if cadence is not None and (stamp := peek_stamp(data)) is not None:
                cadence.add(stamp)  # every message that arrived, recorded or not
            problem = None
            if len(data) > max_size:
                problem = f"{len(data)} bytes is over --max-message-size {max_size}"
            elif is_image:
                problem = _image_cdr_problem(data)
            if problem is None and put(topic, received, data):
                counts[topic] += 1
                return
            index = counts[topic] + rejected[topic] + dropped[topic]  # this message's
            if problem is not None:
                rejected[topic] += 1
                self._log_refusal("rejected", topic, index, rejected[topic], problem)
            else:
                dropped[topic] += 1
                if dropped[topic] <= _LOGGED_REJECTIONS:  # the reason only for those logged
                    self._log_refusal(
                        "dropped", topic, index, dropped[topic],
                        f"the write cache holds {self.writer.queued_bytes} bytes "
                        "(--max-cache-size): the bag is written more slowly than messages "
                        "arrive",
                    )  # fmt: skip

        return on_message

    @property
    def _status_name(self) -> str:
        return f"{self.fully_qualified_name.lstrip('/')}: recording"

    def _is_own_report(self, data: bytes) -> bool:
        """Whether a /diagnostics message is this recorder's own (not recorded)."""
        try:
            statuses = deserialize(data, DIAGNOSTICS_TYPE).status
        except MessageError:
            return False
        return bool(statuses) and all(s.name == self._status_name for s in statuses)

    def _log_refusal(self, kind: str, topic: str, index: int, count: int, why: str) -> None:
        """Log the first few messages not recorded on a topic, one line each."""
        if count <= _LOGGED_REJECTIONS:
            more = f" (further {kind} messages on {topic} are only counted)" * (
                count == _LOGGED_REJECTIONS
            )
            self.logger.warning(f"{kind} message {index} on {topic}: {why}; not recorded{more}")

    def check_losses(self) -> None:
        """Log (and count) what the middleware reports lost since the last check."""
        for topic, subscription in self.subscriptions.items():
            total = subscription.get_lost_count()
            if total > self.lost[topic]:
                self.logger.warning(
                    f"lost {total - self.lost[topic]} messages on {topic} before they reached "
                    f"the recorder (reported by the middleware; {total} on this topic so far)"
                )
                self.lost[topic] = total
        for topic, cadence in self.cadence.items():
            if cadence.missing > self._missing_logged[topic]:
                rate = f"{1e9 / cadence.period_ns:.3g} Hz" if cadence.period_ns else "steady"
                self.logger.warning(
                    f"{cadence.missing - self._missing_logged[topic]} messages missing on "
                    f"{topic} by its header stamps (a {rate} stream; lost before the recorder, "
                    f"by the publisher or the middleware; {cadence.missing} on this topic so far)"
                )
                self._missing_logged[topic] = cadence.missing

    def missing_by_stamps(self, topic: str | None = None) -> int:
        """Messages missing from steady header-stamp cadences (one topic, or all)."""
        if topic is not None:
            return self.cadence[topic].missing if topic in self.cadence else 0
        return sum(c.missing for c in self.cadence.values())

    def totals(self) -> tuple[int, int, int, int, int]:
        """(recorded, lost, dropped, rejected, missing by stamps) messages over all topics."""
        return (
            sum(self.counts.values()),
            sum(self.lost.values()),
            sum(self.dropped.values()),
            sum(self.rejected.values()),
            self.missing_by_stamps(),
        )

    @staticmethod
    def losses(totals: tuple[int, int, int, int, int]) -> str:
        """``lost L (reported by the middleware), dropped D (write cache full), rejected R;
        missing M by header stamps`` of :meth:`totals`."""
        _, lost, dropped, rejected, missing = totals
        return (
            f"lost {lost} (reported by the middleware), "
            f"dropped {dropped} (write cache full), rejected {rejected}; "
            f"missing {missing} by header stamps"
        )

    def publish_diagnostics(self) -> None:
        """One ``DiagnosticStatus``: WARN once anything was lost or rejected, else OK."""
        self.check_losses()
        totals = self.totals()
        values: dict[str, Any] = {
            "bag": str(self.writer.path),
            "cache bytes": self.writer.queued_bytes,
        }
        for topic in sorted(self.subscribed):
            values[f"{topic} recorded"] = self.counts[topic]
            values[f"{topic} lost"] = self.lost[topic]
            values[f"{topic} dropped"] = self.dropped[topic]
            values[f"{topic} rejected"] = self.rejected[topic]
            values[f"{topic} missing by stamps"] = self.missing_by_stamps(topic)
        level = WARN if any(totals[1:]) else OK
        message = f"recorded {totals[0]}; {self.losses(totals)}"
        status = diagnostic_status(level, self._status_name, message, values)
        self.diagnostics.publish(diagnostic_array(time.time_ns(), [status]))

    def on_shutdown(self) -> None:
        """Write what has already arrived, then close the bag (it stays readable)."""
        if self._closed_bag:
            return
        self._closed_bag = True
        try:
            for _ in range(1000):  # drain everything the middleware already holds
                if self.transport.spin_once(0.0) == 0:
                    break
            self.check_losses()
            _, lost, dropped, rejected, missing = self.totals()
            by_topic = {
                t: {
                    "recorded": self.counts[t],
                    "lost": self.lost[t],
                    "dropped": self.dropped[t],
                    "rejected": self.rejected[t],
                    "missing_by_stamps": self.missing_by_stamps(t),
                }
                for t in sorted(self.subscribed)
            }
            for key, value in (
                ("lost_messages", str(lost)),
                ("dropped_messages", str(dropped)),
                ("rejected_messages", str(rejected)),
                ("missing_by_stamps", str(missing)),
                ("by_topic", json.dumps(by_topic)),
            ):
                self.writer.set_custom_data(f"recorder.{key}", value)
        finally:
            self.writer.close()
        totals = self.totals()
        line = (
            f"recorded {totals[0]} messages on {len(self.subscribed)} topics to "
            f"{self.writer.path}; {self.losses(totals)}"
        )
        (self.logger.warning if any(totals[1:]) else self.logger.info)(line)


def _image_cdr_problem(data: bytes) -> str | None:
    """Why CDR bytes of an ``Image`` are not a whole image (cheap: pixels are not copied)."""
    try:
        return image_problem(deserialize(data, IMAGE_TYPE))
    except MessageError as exc:
        return str(exc)


def main(argv: list[str] | None = None) -> None:
    """Entry point of ``python -m tpsr_ros.record``."""
    run_node(RecorderNode, prog=PROG, argv=argv)


if __name__ == "__main__":
    main()
