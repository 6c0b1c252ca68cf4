"""Record topics into a rosbag2 MCAP bag, like ``ros2 bag record``.

    python -m tpsr_ros.record -o BAG [TOPIC ...]

The node's ROS face around two ROS-free pieces of :mod:`tpsr_ros.io.recording`: the
subscription planner (which topics, which QoS) and the loss ledger (what was recorded and
what was not, per topic).

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
itself), sensor topics with a steady cadence of header stamps show it: messages missing
from the cadence are counted apart (:class:`~tpsr_ros.core.cadence.CadenceGaps`), whoever
lost them. Streams a node derives per step (``/tpsr/state``, commands, rewards) are not
judged (:data:`~tpsr_ros.io.recording.SENSOR_TYPES`): a skipped step is not a lost message;
nor is the step stamp a simulator reset takes (recorded on ``/sim/episode_start``).
The counts go to ``/diagnostics`` every second, to the bag's ``custom_data``
(``recorder.lost_messages``, ``recorder.dropped_messages``, ``recorder.rejected_messages``,
``recorder.missing_by_stamps`` and per topic ``recorder.by_topic``) and to the end-of-run
line.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from tpsr_ros.cli import ArgumentParser, positive_float, positive_int
from tpsr_ros.core.errors import MessageError, TpsrError
from tpsr_ros.io.bag import BagWriter, check_bag_path_free
from tpsr_ros.io.bag_cache import CachedBagWriter
from tpsr_ros.io.messages import (
    IMAGE_TYPE,
    deserialize,
    image_problem,
    peek_stamp,
)
from tpsr_ros.io.recording import (
    LossLedger,
    SubscriptionPlanner,
    is_episode_start,
    judged_by_stamps,
)
from tpsr_ros.runtime import Node, NodeOptions, Subscription, run_node
from tpsr_ros.runtime.diagnostics import (
    DIAGNOSTICS_TYPE,
    OK,
    WARN,
    diagnostic_array,
    diagnostic_status,
)

__all__ = ["RecorderNode", "main"]

PROG = "python -m tpsr_ros.record"
DIAGNOSTICS_TOPIC = "/diagnostics"
# unread samples the middleware may hold per topic while the recorder is busy (DDS backend)
CACHE_SAMPLES = 256
DEFAULT_MAX_MESSAGE_BYTES = 256 * 1024 * 1024
DEFAULT_MAX_CACHE_BYTES = 1024 * 1024 * 1024
_LOGGED_REJECTIONS = 5  # per topic and kind; later ones are counted only


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
        self.planner = SubscriptionPlanner(
            {self.resolve_topic(t) for t in args.topics} or None,
            bool(args.include_hidden_topics),
        )
        self.ledger = LossLedger()
        self.writer = CachedBagWriter(
            BagWriter(args.output, compress=args.compression == "zstd").open(),
            args.max_cache_size,
        )
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
        wanted = self.planner.wanted
        what = "all topics" if wanted is None else ", ".join(sorted(wanted))
        self.logger.info(f"recording {what} to {args.output}")

    @property
    def subscribed(self) -> dict[str, str]:
        """Recorded topics and their types."""
        return self.planner.subscribed

    def _scan_now(self) -> None:
        self._first_scan.cancel()
        self.discover()

    def _warn_once(self, key: tuple[str, str], message: str) -> None:
        if key not in self._warned:
            self._warned.add(key)
            self.logger.warning(message)

    def discover(self) -> None:
        """Subscribe to every selected topic that has publishers and is not recorded yet."""
        self.check_losses()
        publishers = list(self.transport.publishers())
        for e in publishers:  # the recorder's own /diagnostics publisher is not recorded
            if e.topic == DIAGNOSTICS_TOPIC and e.msgtype == DIAGNOSTICS_TYPE and (
                e.qos == self.diagnostics.qos
            ):
                publishers.remove(e)
                break
        planned, warnings = self.planner.plan(publishers)
        for key, message in warnings:
            self._warn_once(key, message)
        for sub in planned:
            self.writer.add_topic(sub.topic, sub.msgtype, sub.offered)
            self.subscriptions[sub.topic] = self.create_subscription(
                sub.topic, sub.msgtype, self._writer_for(sub.topic, sub.msgtype), sub.qos,
                raw=True,
            )  # fmt: skip
            self.logger.info(f"subscribed to {sub.topic} ({sub.msgtype}; {sub.qos})")

    def _writer_for(self, topic: str, msgtype: str) -> Any:
        put, ledger = self.writer.put, self.ledger
        counts, rejected, dropped = ledger.recorded, ledger.rejected, ledger.dropped
        max_size = self.max_message_size
        is_image = msgtype == IMAGE_TYPE
        own_reports = topic == DIAGNOSTICS_TOPIC and msgtype == DIAGNOSTICS_TYPE
        cadence = ledger.add_topic(topic, judged_by_stamps(msgtype))
        episode_starts = is_episode_start(topic, msgtype)

        def on_message(data: bytes) -> None:
            received = self.now_ns()  # the bag's log time: /clock with use_sim_time
            if own_reports and self._is_own_report(data):
                return
            if cadence is not None and (stamp := peek_stamp(data)) is not None:
                cadence.add(stamp)  # every message that arrived, recorded or not
            if episode_starts and (stamp := peek_stamp(data)) is not None:
                ledger.skip_stamp(stamp)  # a reset's step: no camera frame carries it
            problem = None
            if len(data) > max_size:
                problem = f"{len(data)} bytes is over --max-message-size {max_size}"
            elif is_image:
                problem = _image_cdr_problem(data)
            if problem is None and put(topic, received, data):
                counts[topic] += 1
                return
            index = ledger.index(topic)  # this message's
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
        """Log (and count) what the middleware reports lost, and what is missing by stamps."""
        reported = {t: s.get_lost_count() for t, s in self.subscriptions.items()}
        for line in self.ledger.middleware_lost(reported) + self.ledger.new_missing():
            self.logger.warning(line)

    def totals(self) -> tuple[int, int, int, int, int]:
        """(recorded, lost, dropped, rejected, missing by stamps) messages over all topics."""
        return self.ledger.totals()

    def publish_diagnostics(self) -> None:
        """One ``DiagnosticStatus``: WARN once anything was lost or rejected, else OK."""
        self.check_losses()
        values: dict[str, Any] = {
            "bag": str(self.writer.path),
            "cache bytes": self.writer.queued_bytes,
            **self.ledger.diagnostics_values(),
        }
        level = WARN if self.ledger.any_loss() else OK
        message = f"recorded {self.ledger.totals()[0]}; {self.ledger.losses()}"
        status = diagnostic_status(level, self._status_name, message, values)
        self.diagnostics.publish(diagnostic_array(self.now_ns(), [status]))

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
            for key, value in self.ledger.custom_data().items():
                self.writer.set_custom_data(key, value)
        finally:
            self.writer.close()
        line = (
            f"recorded {self.ledger.totals()[0]} messages on {len(self.subscribed)} topics to "
            f"{self.writer.path}; {self.ledger.losses()}"
        )
        (self.logger.warning if self.ledger.any_loss() else self.logger.info)(line)


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
