"""Play a rosbag2 MCAP bag back onto the graph, like ``ros2 bag play``.

    python -m tpsr_ros.play BAG [--rate R] [--loop] [--topics T ...]

Messages are published in log-time order with their original spacing divided by
``--rate``; their stored CDR bytes are published unchanged. Each topic is published with
the QoS its recorded publishers offered (reliable unless one was best-effort,
transient-local only if all were, the largest depth, where a publisher whose depth was
not known when recorded counts as ROS 2's default 10, as ``ros2 bag play`` offers it);
bags without recorded QoS (e.g. from ``sim_node.generate``) use ROS 2's default
(reliable, volatile, keep-last 10).

``/clock``: when the bag contains ``/clock``, its recorded messages are replayed like any
other topic. Otherwise the player publishes ``/clock`` itself before each message whose
time is later than the last clock sent: the message's ``header.stamp`` when its type
starts with a ``std_msgs/Header``, else its log time (``--no-clock`` disables this).

``--wait-for-subscribers N`` holds playback until every played topic has N matched
subscriptions (e.g. a recorder), so nothing is published into the void. DDS completes a
match on each side on its own, so the subscribers' side may still be pending: playback
then waits ``MATCH_SETTLE_S`` more (for best-effort subscribers), and after the first
message on each topic until its reliable subscribers acknowledge it (up to
``FIRST_ACK_TIMEOUT_S`` for all topics together; the schedule resumes from there), so no
keep-last history drops a message a subscriber has not yet matched. Playback ends
at the end of the bag (or on SIGINT/SIGTERM); the player then waits, up to 2 s, for
reliable subscribers to acknowledge everything, and exits.

Lateness: each message's publish starts ``lateness`` after its due time (its log-time
offset divided by ``--rate``); the end line reports its p50, p99 and maximum, so a player
that falls behind (a slow disk, a middleware that cannot take 1080p at camera rate)
says so. A thread reads (decompresses, checks) up to 8 messages ahead, so reading a
1080p image (about 7 ms) overlaps the wait and the publishing of the one before.
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from tpsr_ros.cli import ArgumentParser, non_negative_int, positive_float
from tpsr_ros.core.errors import BagError, TpsrError
from tpsr_ros.core.units import NS_PER_S as _NS
from tpsr_ros.io.bag import BagReader
from tpsr_ros.io.messages import CLOCK_TYPE, clock_msg, peek_stamp, starts_with_header
from tpsr_ros.io.qos import from_bag_qos
from tpsr_ros.runtime import DEFAULT_QOS, Node, NodeOptions, Publisher, run_node
from tpsr_ros.runtime.diagnostics import RollingPercentiles

__all__ = ["PlayerNode", "ReadAhead", "main"]

PROG = "python -m tpsr_ros.play"
CLOCK_TOPIC = "/clock"
MATCH_SETTLE_S = 0.3
"""Seconds playback waits, once every publisher has matched, for the subscribers' side of the
match (DDS discovery completes on each side on its own)."""
FIRST_ACK_TIMEOUT_S = 5.0
"""Seconds the first messages on the topics wait, together, for their reliable subscribers'
acknowledgements (with ``--wait-for-subscribers``)."""


_END = object()


class ReadAhead:
    """The bag's messages, read by a thread up to ``depth`` messages ahead of the player.

    The thread is the only user of the reader while it runs; an error it meets (a damaged
    chunk) is raised in the iterating thread, where it would have been raised without it.
    """

    def __init__(self, messages: Iterable[Any], depth: int = 8) -> None:
        self._queue: queue.Queue[Any] = queue.Queue(maxsize=depth)
        self._stop = threading.Event()
        self._thread = threading.Thread(
            target=self._run, args=(messages,), name="bag-read-ahead", daemon=True
        )
        self._thread.start()

    def _put(self, item: Any) -> bool:
        while not self._stop.is_set():
            try:
                self._queue.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def _run(self, messages: Iterable[Any]) -> None:
        try:
            for message in messages:
                if not self._put(message):
                    return
            self._put(_END)
        except BaseException as exc:  # handed to the player's thread
            self._put(exc)

    def __iter__(self) -> Iterator[Any]:
        while True:
            item = self._queue.get()
            if item is _END:
                return
            if isinstance(item, BaseException):
                raise item
            yield item

    def close(self, timeout_s: float = 5.0) -> None:
        """Stop the thread (it ends at its next message) and wait for it."""
        self._stop.set()
        while True:
            try:
                self._queue.get_nowait()
            except queue.Empty:
                break
        self._thread.join(timeout_s)


class PlayerNode(Node):
    """Publishes a bag's messages with their original timing."""

    default_name = "tpsr_player"
    description = "Play a rosbag2 MCAP bag, like `ros2 bag play`."

    @classmethod
    def argument_parser(cls, prog: str) -> ArgumentParser:
        """``BAG [--rate R] [--loop] [--topics ...]``."""
        parser = ArgumentParser(prog=prog, description=cls.description, add_help=False)
        parser.add_argument("bag", type=Path, help="rosbag2 MCAP bag directory")
        parser.add_argument(
            "--rate", type=positive_float, default=1.0, help="speed factor (default 1.0)"
        )
        parser.add_argument("--loop", action="store_true", help="replay until interrupted")
        parser.add_argument(
            "--topics", nargs="+", metavar="TOPIC", help="play only these topics"
        )
        parser.add_argument(
            "--no-clock",
            action="store_true",
            help="do not publish /clock when the bag has none",
        )
        parser.add_argument(
            "--wait-for-subscribers",
            type=non_negative_int,
            default=0,
            metavar="N",
            help="start once every played topic has N subscriptions (default 0)",
        )
        return parser

    @classmethod
    def preflight(cls, options: NodeOptions) -> None:
        """Refuse a path that is not a rosbag2 MCAP bag before joining the graph."""
        assert options.args is not None
        BagReader(options.args.bag).close()

    def setup(self) -> None:
        """Open the bag and create one publisher per played topic."""
        args = self.options.args
        if args is None:
            raise TpsrError("the player needs its command-line options (BAG)")
        self.args = args
        self.reader = BagReader(args.bag)
        topics = self.reader.topics
        if args.topics:
            missing = sorted(set(args.topics) - set(topics))
            if missing:
                raise BagError(f"bag {str(args.bag)!r} has no topic {', '.join(missing)}")
            topics = {t: topics[t] for t in args.topics}
        self.played = topics
        qos = self.reader.qos_profiles
        self.publishers: dict[str, Publisher] = {
            topic: self.create_publisher(
                topic, msgtype, from_bag_qos(qos.get(topic, [])) or DEFAULT_QOS
            )
            for topic, msgtype in topics.items()
        }
        self.clock: Publisher | None = None
        if CLOCK_TOPIC not in self.reader.topics and not args.no_clock:
            self.clock = self.create_publisher(CLOCK_TOPIC, CLOCK_TYPE)
        self.header_first = {t: starts_with_header(m) for t, m in topics.items()}
        self.published = 0
        self.unconfirmed: set[str] = set()  # topics whose first message awaits acknowledgement
        self.ack_deadline_ns: int | None = None  # when waiting for acknowledgements ends
        # every message's lateness in ms (a bag of a million messages: 8 MB)
        self.lateness_ms = RollingPercentiles(size=10_000_000)
        self.exit_code = 0

    def _wait_for_subscribers(self) -> None:
        needed = self.args.wait_for_subscribers
        if not needed:
            return
        self.logger.info(f"waiting for {needed} subscription(s) on every played topic")
        pubs = list(self.publishers.values())
        self.spin(until=lambda: all(p.get_subscription_count() >= needed for p in pubs))
        # the publisher's side of a match completes first; until the subscriber's side does,
        # a reliable keep-last writer may drop unacknowledged samples it had to overwrite
        self.spin(timeout_s=MATCH_SETTLE_S)
        self.unconfirmed = set(self.publishers)

    def _play_once(self) -> None:
        ahead = ReadAhead(self.reader.messages(self.played))
        try:
            self._publish_on_time(ahead)
        finally:
            ahead.close()

    def _publish_on_time(self, messages: Iterable[Any]) -> None:
        start_wall = time.monotonic_ns()
        first_log: int | None = None
        last_clock = -1
        for message in messages:
            if not self.ok():
                return
            if first_log is None:  # the schedule starts once the first message is in hand
                first_log, start_wall = message.log_time_ns, time.monotonic_ns()
            due = start_wall + (message.log_time_ns - first_log) / self.args.rate
            while self.ok():
                wait_ns = due - time.monotonic_ns()
                if wait_ns <= 0:
                    break
                self.spin_once(wait_ns / _NS)
            if not self.ok():
                return
            self.lateness_ms.add((time.monotonic_ns() - due) / 1e6)
            if self.clock is not None:
                stamp = (
                    peek_stamp(message.data)
                    if self.header_first[message.topic]
                    else message.log_time_ns
                )
                stamp = message.log_time_ns if stamp is None else stamp
                if stamp > last_clock:
                    self.clock.publish(clock_msg(stamp))
                    last_clock = stamp
            self.publishers[message.topic].publish_raw(message.data)
            self.published += 1
            if message.topic in self.unconfirmed:
                start_wall += self._confirm_first(message.topic)

    def _confirm_first(self, topic: str) -> int:
        """Wait until the subscribers acknowledge the first message on ``topic``, within
        :data:`FIRST_ACK_TIMEOUT_S` of the first such wait (a subscriber that never answers
        delays the start once, not once per topic); the ns waited, by which the schedule
        moves on."""
        self.unconfirmed.discard(topic)
        start = time.monotonic_ns()
        if self.ack_deadline_ns is None:
            self.ack_deadline_ns = start + round(FIRST_ACK_TIMEOUT_S * _NS)
        left_s = max(0.0, (self.ack_deadline_ns - start) / _NS)
        if not self.publishers[topic].wait_for_all_acked(left_s):
            self.logger.warning(
                f"{topic}: the first message was not acknowledged within "
                f"{FIRST_ACK_TIMEOUT_S:g} s of the start; playing on (a subscriber may miss "
                "the start)"
            )
        return time.monotonic_ns() - start

    def spin(self, until: Any = None, timeout_s: float | None = None) -> bool:
        """Play the bag (once, or until interrupted with ``--loop``); then request shutdown."""
        if until is not None or timeout_s is not None:
            return super().spin(until, timeout_s)
        self._wait_for_subscribers()
        while self.ok():
            self._play_once()
            if not self.args.loop:
                break
        self.logger.info(f"{self.summary(interrupted=not self.ok())}; {self.lateness()}")
        self.request_shutdown("end of bag")
        return True

    def summary(self, *, interrupted: bool) -> str:
        """What was played: all of the bag, or (``interrupted``: a signal or a shutdown
        stopped it) how much of it, so a stopped replay never reads as a complete one."""
        counts = self.reader.message_counts
        total = sum(counts.get(topic, 0) for topic in self.played)
        bag = self.args.bag
        if not interrupted:
            return f"played {self.published} messages from {bag}"
        why = self.shutdown_reason or "interrupted"
        if self.args.loop:
            passes = self.published // total if total else 0
            return (
                f"interrupted ({why}): played {self.published} messages from {bag} in --loop "
                f"({passes} complete pass(es) of {total})"
            )
        share = f" ({100 * self.published / total:.0f} %)" if total else ""
        return (
            f"interrupted ({why}): played {self.published} of {total} messages{share} "
            f"from {bag}, not the whole bag"
        )

    def lateness(self) -> str:
        """``lateness p50 X ms, p99 Y ms, max Z ms`` over the messages published so far."""
        if not len(self.lateness_ms):
            return "lateness: nothing published"
        p50, p99, worst = self.lateness_ms.percentiles(50, 99, 100)
        return f"lateness p50 {p50:.1f} ms, p99 {p99:.1f} ms, max {worst:.1f} ms"

    def on_shutdown(self) -> None:
        """Close the bag."""
        self.reader.close()


def main(argv: list[str] | None = None) -> None:
    """Entry point of ``python -m tpsr_ros.play``."""
    run_node(PlayerNode, prog=PROG, argv=argv)


if __name__ == "__main__":
    main()
