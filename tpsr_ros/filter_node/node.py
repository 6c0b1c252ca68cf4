"""The TPSR filter node: tracks the predictive state online and, with a policy, drives the robot.

    python -m tpsr_ros.filter_node --ros-args -p model:=MODEL [-p policy:=POLICY]

Boilerplate around three ROS-free parts (see msgs_doc/filter_node.md for the interface).
A model learned from robot bags (``learner fit --step-period``) brings its own inputs: the
node subscribes its camera and command topics and types, and
:class:`tpsr_ros.core.resample.GridStepper` replaces the pairing below: steps on the model's
grid with the latest image and the command in force, the offline rules one message at a
time (states equal ``learner plot``'s). For simulator models:

- :class:`tpsr_ros.runtime.pairing.ExactTimeSynchronizer` pairs ``/camera/image_raw`` and
  ``/action`` by identical header stamp in a bounded buffer (like message_filters' ExactTime);
- :class:`tpsr_ros.core.online.OnlineTracker` applies Algorithm 4 with the model's stateless
  update, with the offline tracker's rules (start from ``b_*``, restart at gaps), so the
  states published on ``/tpsr/state`` equal offline tracking of the same steps bit for bit;
- the greedy policy (:func:`tpsr_ros.io.policy.load_policy`) turns each state into a
  ``/cmd_vel`` command.

Re-initialisation (state ``b_*``, next step starts a segment): on an episode start
(``/sim/episode_start``, transient-local) newer than the last processed step, and on a
backwards jump of time: a ``/clock``, episode-start, image or action stamp earlier than the
last processed step by more than ``jump_threshold`` seconds. After a re-init the node
publishes the command for ``b_*`` (in lockstep that commands the first step of an episode).
An episode start at or before the last processed step (and not a jump) is stale and ignored.

Faults never stop the node: undecodable messages, images of the wrong encoding, size,
frame or data length, actions that are not finite or not one of the 25 actions are
rejected (counted per reason, at most one warning per topic every 5 s); incomplete,
duplicated, late and out-of-order messages are counted by the synchroniser; degenerate
normalisers are recovered by the guard of :mod:`tpsr_ros.core.filtering` and counted.
``/diagnostics`` reports it all once a second, with the input rates, the time since each
input last delivered (WARN when one is silent, STALE when both are) and the messages lost in
the middleware (gaps in the simulator's stamps, or what the middleware itself knows it lost:
:meth:`~tpsr_ros.runtime.node.Subscription.get_lost_count`).
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from tpsr_ros.core.actions import ACTIONS
from tpsr_ros.core.cadence import CadenceGaps
from tpsr_ros.core.episodes import (
    DEFAULT_ACTION_TOLERANCE,
    image_to_observation,
    velocities_to_actions,
)
from tpsr_ros.core.errors import ConfigError, EncodingError, MessageError, TpsrError
from tpsr_ros.core.images import Preprocessing, preprocess_images
from tpsr_ros.core.online import OnlineTracker
from tpsr_ros.core.resample import GridStep, GridStepper
from tpsr_ros.core.units import NS_PER_S as _NS
from tpsr_ros.io import messages as m
from tpsr_ros.io.filter_inputs import FilterInputs, input_topics, load_filter_inputs
from tpsr_ros.io.images import decode_image
from tpsr_ros.io.stream_spec import TWIST_STAMPED_TYPE
from tpsr_ros.runtime import (
    DEFAULT_QOS,
    LATCHED_QOS,
    Durability,
    History,
    Node,
    NodeOptions,
    QoSProfile,
    Reliability,
    param,
    run_node,
)
from tpsr_ros.runtime.diagnostics import (
    DIAGNOSTICS_TYPE,
    ERROR,
    OK,
    STALE,
    WARN,
    RollingPercentiles,
    diagnostic_array,
    diagnostic_status,
)
from tpsr_ros.runtime.pairing import ExactTimeSynchronizer, Outcome

__all__ = [
    "ACTION_TOPIC",
    "CLOCK_TOPIC",
    "CMD_VEL_TOPIC",
    "DIAGNOSTICS_TOPIC",
    "IMAGE_TOPIC",
    "REJECT_REASONS",
    "RESET_TOPIC",
    "STATE_TOPIC",
    "FilterInputs",
    "FilterNode",
    "FilterNodeParams",
    "load_inputs",
    "main",
]

PROG = "python -m tpsr_ros.filter_node"
# Relative names, so `-r __ns:=/robot1` moves every topic of a robot's filter under
# /robot1/ (next to its simulator's); /diagnostics stays global, as diagnostic
# aggregators expect (each status names its node).
IMAGE_TOPIC = "camera/image_raw"
ACTION_TOPIC = "action"
RESET_TOPIC = "sim/episode_start"
CLOCK_TOPIC = "clock"
STATE_TOPIC = "tpsr/state"
CMD_VEL_TOPIC = "cmd_vel"
DIAGNOSTICS_TOPIC = "/diagnostics"
REJECT_REASONS = ("undecodable", "encoding", "size", "data", "frame", "action")
COMMAND_TYPES = {"twist": m.TWIST_TYPE, "twist_stamped": TWIST_STAMPED_TYPE}
RATE_WINDOW_S = 10.0
"""Input rates on /diagnostics count the messages of the last this many seconds."""
CLOCK_QOS = QoSProfile(Reliability.BEST_EFFORT, Durability.VOLATILE, History.KEEP_LAST, 10)
"""Best effort, so /clock from any publisher matches (rosbag2 publishes it best-effort)."""
WARN_PERIOD_S = 5.0
"""At most one warning per topic and kind (rejection, drop, duplicate...) in this many seconds."""
SETTLE_S = 0.25
"""Once the command's subscribers are matched, time for their side of discovery to finish."""
_RECOVERY_ERROR_RUN = 10


@dataclass(frozen=True)
class FilterNodeParams:
    """Parameters of ``python -m tpsr_ros.filter_node``."""

    model: str = param("", "model file (.npz) written by `learner fit` (required)")
    policy: str = param(
        "", "policy file written by `learner policy` for this model; empty: a pure filter"
    )
    queue_size: int = param(
        10, "incomplete steps (image or action alone) buffered for pairing; the oldest go first"
    )
    step_period: float = param(
        1.0, "s between consecutive steps; a step not one period after the last starts from b_*"
    )
    jump_threshold: float = param(
        5.0, "s; a stamp earlier than the last step by more than this is a backwards time jump"
    )
    image_frame: str = param("camera", "required frame_id of images (empty: any)")
    action_frame: str = param("base_link", "required frame_id of actions (empty: any)")
    sensor_qos: str = param(
        "reliable",
        "reliability of the image and action subscriptions (best_effort also matches "
        "sensor-data publishers)",
        choices=("reliable", "best_effort"),
    )
    check_topics: bool = param(
        True, "refuse a model trained on other image/action topics than the node subscribes"
    )
    wait_for_subscribers: int = param(
        0, "hold the first command until /cmd_vel and /tpsr/state each have this many subscriptions"
    )
    diagnostics_period: float = param(1.0, "s between /diagnostics reports")
    command_type: str = param(
        "twist",
        "type of the /cmd_vel commands: twist (geometry_msgs/Twist) or twist_stamped",
        choices=tuple(COMMAND_TYPES),
    )
    input_timeout: float = param(
        3.0, "s; an input silent for longer makes /diagnostics WARN, all inputs silent STALE"
    )

    def __post_init__(self) -> None:
        if self.queue_size < 1:
            raise ConfigError(f"queue_size must be >= 1, got {self.queue_size}")
        for name in ("step_period", "diagnostics_period", "input_timeout"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(f"{name} must be a positive number of seconds, got {value}")
        if not (math.isfinite(self.jump_threshold) and self.jump_threshold >= 0):
            raise ConfigError(f"jump_threshold must be >= 0 s, got {self.jump_threshold}")
        if self.wait_for_subscribers < 0:
            raise ConfigError("wait_for_subscribers must be >= 0")


# -- loading and the start-up checks ------------------------------------------------------


def load_inputs(
    params: FilterNodeParams,
    image_topic: str = "/" + IMAGE_TOPIC,
    action_topic: str = "/" + ACTION_TOPIC,
    namespace: str = "/",
) -> FilterInputs:
    """:func:`tpsr_ros.io.filter_inputs.load_filter_inputs` with the node's parameters."""
    return load_filter_inputs(
        params.model,
        params.policy,
        check_topics=params.check_topics,
        image_topic=image_topic,
        action_topic=action_topic,
        namespace=namespace,
    )


class _Rejected(Exception):
    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(detail)
        self.reason = reason


def _image(msg: Any, shape: tuple[int, int], frame: str) -> np.ndarray:
    if msg.encoding != "rgb8":
        raise _Rejected("encoding", f"encoding {msg.encoding!r} is not rgb8")
    if (int(msg.height), int(msg.width)) != shape or int(msg.step) != 3 * int(msg.width):
        raise _Rejected(
            "size",
            f"image is {msg.height}x{msg.width} (step {msg.step}), expected "
            f"{shape[0]}x{shape[1]} (step {3 * shape[1]})",
        )
    if len(msg.data) != shape[0] * shape[1] * 3:
        raise _Rejected(
            "data", f"image holds {len(msg.data)} bytes, expected {shape[0] * shape[1] * 3}"
        )
    if frame and msg.header.frame_id != frame:
        raise _Rejected("frame", f"frame {msg.header.frame_id!r} is not {frame!r}")
    return m.image_to_array(msg, shape=shape)


def _action(msg: Any, frame: str, cache: dict[tuple[float, float], int]) -> int:
    """Map a TwistStamped to its action index as offline tracking does (memoised)."""
    if frame and msg.header.frame_id != frame:
        raise _Rejected("frame", f"frame {msg.header.frame_id!r} is not {frame!r}")
    try:
        velocity = m.twist_to_xy(msg)
        index = cache.get(velocity)
        if index is None:
            index = int(velocities_to_actions(np.array([velocity]), DEFAULT_ACTION_TOLERANCE)[0])
            if len(cache) < 1024:
                cache[velocity] = index
        return index
    except TpsrError as exc:
        raise _Rejected("action", str(exc)) from None


class _Frame:
    """A camera image as the grid holds it: its observation, or why it has none."""

    __slots__ = ("detail", "observation", "reason")

    def __init__(self) -> None:
        self.observation: np.ndarray | None = None
        self.reason, self.detail = "data", "not decoded"

    def reduce(self, msg: Any, msgtype: str, preprocessing: Preprocessing) -> None:
        """Decode and preprocess ``msg`` (the offline observation, bit for bit)."""
        try:
            pixels = decode_image(msg, msgtype)
            self.observation = preprocess_images(pixels[None], preprocessing)[0]
        except MessageError as exc:
            self.detail = str(exc)
            self.reason = "encoding" if isinstance(exc, EncodingError) else "data"


class _Throttle:
    """True at most once per key every ``period_s`` (wall clock); counts what it held back."""

    def __init__(self, period_s: float) -> None:
        self.period_s = period_s
        self._last: dict[tuple[str, str], float] = {}
        self.suppressed: dict[tuple[str, str], int] = {}

    def __call__(self, key: tuple[str, str]) -> bool:
        now = time.monotonic()
        last = self._last.get(key)
        if last is not None and now - last < self.period_s:
            self.suppressed[key] = self.suppressed.get(key, 0) + 1
            return False
        self._last[key] = now
        return True

    def take_suppressed(self, key: tuple[str, str]) -> int:
        return self.suppressed.pop(key, 0)


# -- the node -----------------------------------------------------------------------------


class FilterNode(Node):
    """Tracks the TPSR state from images and actions; publishes it and the greedy command."""

    default_name = "tpsr_filter"
    Params = FilterNodeParams
    description = (
        "Track the predictive state online (guide Algorithm 4) and, with a policy, publish "
        "the greedy fitted-Q command."
    )

    @classmethod
    def _resolved_inputs(cls, options: NodeOptions) -> tuple[str, str, str]:
        # Node.resolve_topic needs only the options, name and namespace: use it unbound
        # so the check sees exactly the names setup() will subscribe.
        probe = object.__new__(cls)
        probe.options, probe.name, probe.namespace = options, options.name, options.namespace
        image, action = input_topics(options.params.model) or (IMAGE_TOPIC, ACTION_TOPIC)
        return (probe.resolve_topic(image), probe.resolve_topic(action), options.namespace)

    @classmethod
    def preflight(cls, options: NodeOptions) -> None:
        """Refuse a missing or mismatched model/policy before joining the graph."""
        load_inputs(options.params, *cls._resolved_inputs(options))

    def setup(self) -> None:
        """Load and check the model and policy; create the endpoints and timers."""
        p: FilterNodeParams = self.params
        image_name, action_name = input_topics(p.model) or (IMAGE_TOPIC, ACTION_TOPIC)
        self.image_topic = self.resolve_topic(image_name)
        self.action_topic = self.resolve_topic(action_name)
        self.inputs = load_inputs(p, self.image_topic, self.action_topic, self.namespace)
        self.model = self.inputs.model
        self.policy = self.inputs.policy
        self.spec = self.inputs.spec
        step_ns = self.spec.grid.step_ns if self.spec else round(p.step_period * _NS)
        self.tracker = OnlineTracker(self.model, step_ns)
        self.grid = GridStepper(self.spec.grid) if self.spec else None
        # a robot camera's images the middleware lost without saying show in its stamps
        self.camera_cadence = CadenceGaps() if self.spec else None
        self.lost = {"image": 0, "action": 0}
        self._last_input_stamp: dict[str, int | None] = {"image": None, "action": None}
        self._arrivals: dict[str, deque[float]] = {
            "image": deque(maxlen=100_000),
            "action": deque(maxlen=100_000),
        }
        self._last_arrival: dict[str, float | None] = {"image": None, "action": None}
        self._last_image_arrival_ns: int | None = None
        self.far_commands = 0
        self.sync = ExactTimeSynchronizer(
            2, queue_size=p.queue_size, jump_threshold_ns=round(p.jump_threshold * _NS)
        )
        self.rejected = dict.fromkeys(REJECT_REASONS, 0)
        self.resets = 0
        self.stale_resets = 0
        self.errors = 0
        self.commands = 0
        self.latency = RollingPercentiles(1000)
        self._throttle = _Throttle(WARN_PERIOD_S)
        self._recovery_run = 0
        self._action_cache: dict[tuple[float, float], int] = {}
        self._pending_command: tuple[int, int | None] | None = None
        self._ready_since: float | None = None
        self.commands_ready = self.policy is None

        sensor = QoSProfile(
            Reliability(p.sensor_qos), Durability.VOLATILE, History.KEEP_LAST, DEFAULT_QOS.depth
        )
        self.state_pub = self.create_publisher(STATE_TOPIC, m.STATE_TYPE)
        self.cmd_pub = (
            self.create_publisher(CMD_VEL_TOPIC, COMMAND_TYPES[p.command_type])
            if self.policy is not None
            else None
        )
        self.diagnostics_pub = self.create_publisher(DIAGNOSTICS_TOPIC, DIAGNOSTICS_TYPE)
        if self.cmd_pub is not None and self.cmd_pub.topic == self.action_topic:
            if self.spec is None:  # executed actions stamped per step, not commands
                raise ConfigError(
                    f"the node's commands and its action input are both {self.action_topic}: "
                    "a simulator model pairs each image with the action the simulator "
                    "executed for that step, not with the node's own command; remap one of them"
                )
            if COMMAND_TYPES[p.command_type] != self.spec.action_type:
                raise ConfigError(
                    f"the node's commands and its command input are both {self.action_topic}, "
                    f"but of types {COMMAND_TYPES[p.command_type]} and "
                    f"{self.spec.action_type}: set command_type to the input's type or remap "
                    "one of them"
                )
        if self.spec is None:
            self.image_type, self.action_type = m.IMAGE_TYPE, m.ACTION_TYPE
            on_image, on_action = self._on_image, self._on_action
        else:
            self.image_type, self.action_type = self.spec.image_type, self.spec.action_type
            on_image, on_action = self._on_grid_image, self._on_grid_command
        self.image_sub = self.create_subscription(
            image_name, self.image_type, on_image, sensor, raw=True
        )
        self.action_sub = self.create_subscription(
            action_name, self.action_type, on_action, sensor, raw=True
        )
        self.reset_topic = self.create_subscription(
            RESET_TOPIC, m.POSE_TYPE, self._on_reset, LATCHED_QOS, raw=True
        ).topic
        self.clock_topic = self.create_subscription(
            CLOCK_TOPIC, m.CLOCK_TYPE, self._on_clock, CLOCK_QOS, raw=True
        ).topic
        self._last_report = (time.monotonic(), 0, self._problem_counts())
        self.create_timer(p.diagnostics_period, self.publish_diagnostics)
        if self.policy is not None:
            self._ready_timer = self.create_timer(0.01, self._check_ready)
        what = "pure filter" if self.policy is None else f"policy {p.policy}"
        how = (
            "pairing"
            if self.spec is None
            else f"steps of {self.spec.grid.step_ns / _NS:g} s from"
        )
        self.logger.info(
            f"model {p.model} ({self.model.method}, {self.model.state_dim}-d states, "
            f"{self.inputs.fingerprint[:12]}); {what}; {how} {self.image_topic} and "
            f"{self.action_topic}"
        )

    # -- warnings and counters ------------------------------------------------------------

    def _warn(self, topic: str, kind: str, message: str) -> None:
        key = (topic, kind)
        if self._throttle(key):
            held = self._throttle.take_suppressed(key)
            more = f" ({held} more since the last warning)" if held else ""
            self.logger.warning(f"{topic}: {message}{more}")

    def _reject(self, topic: str, reason: str, detail: str) -> None:
        self.rejected[reason] += 1
        self._warn(topic, "rejected", f"rejected ({reason}): {detail}")

    def _problem_counts(self) -> dict[str, int]:
        stats = self.sync.stats
        counts = {
            "dropped": stats.dropped,
            "duplicates": stats.duplicates,
            "late": stats.late,
            "out_of_order": stats.out_of_order,
            "time_jumps": stats.time_jumps,
            "gaps": self.tracker.gaps,
            "recoveries": self.tracker.recoveries,
            "errors": self.errors,
            # both lower bounds of the same loss: stamp gaps (simulator streams) and what
            # the middleware knows it lost (sequence gaps, lost-sample events)
            "lost_images": max(self.lost["image"], self.image_sub.get_lost_count()),
            "lost_actions": max(self.lost["action"], self.action_sub.get_lost_count()),
        }
        if self.grid is not None:
            counts["dropped"] = self.grid.images_out_of_order
            counts["out_of_order"] = self.grid.images_out_of_order
            counts["camera_gaps"] = self.grid.camera_gaps
            counts["command_gaps"] = self.grid.command_gaps
            counts["far_commands"] = self.far_commands
        counts.update({f"rejected_{reason}": n for reason, n in self.rejected.items()})
        return counts

    # -- callbacks ------------------------------------------------------------------------

    def _decode(self, data: bytes, msgtype: str, topic: str) -> Any | None:
        try:
            return m.deserialize(data, msgtype)
        except MessageError as exc:
            self._reject(topic, "undecodable", str(exc))
            return None

    def _arrived(self, which: str) -> None:
        """Note an input message's arrival (rates and staleness on /diagnostics)."""
        now = time.monotonic()
        self._last_arrival[which] = now
        arrivals = self._arrivals[which]
        arrivals.append(now)
        while arrivals[0] < now - RATE_WINDOW_S:
            arrivals.popleft()

    def _count_lost(self, which: str, stamp: int) -> None:
        """Steps the middleware lost on a simulator stream, from the gaps in its stamps.

        Simulator step k is stamped k periods after time 0 or after its episode start
        (DESIGN.md), so a stamp n periods after the previous one on the topic (or after
        time 0, or the last episode start) means n - 1 lost steps. A backwards jump of
        time starts the count afresh from time 0.
        """
        last = self._last_input_stamp[which]
        if last is None or stamp < last - self.sync.jump_threshold_ns:
            last = 0
        step = self.tracker.step_ns
        if stamp > last and (stamp - last) % step == 0:
            self.lost[which] += (stamp - last) // step - 1
        if stamp > last:
            self._last_input_stamp[which] = stamp

    def _on_image(self, data: bytes) -> None:
        start = time.perf_counter()
        self._arrived("image")
        msg = self._decode(data, m.IMAGE_TYPE, self.image_topic)
        if msg is None:
            return
        try:
            image = _image(msg, self.inputs.image_shape, self.params.image_frame)
        except _Rejected as exc:
            self._reject(self.image_topic, exc.reason, str(exc))
            return
        self._count_lost("image", m.stamp_of(msg))
        self._add(0, m.stamp_of(msg), image, self.image_topic, start)

    def _on_action(self, data: bytes) -> None:
        start = time.perf_counter()
        self._arrived("action")
        msg = self._decode(data, m.ACTION_TYPE, self.action_topic)
        if msg is None:
            return
        try:
            action = _action(msg, self.params.action_frame, self._action_cache)
        except _Rejected as exc:
            self._reject(self.action_topic, exc.reason, str(exc))
            return
        self._count_lost("action", m.stamp_of(msg))
        self._add(1, m.stamp_of(msg), action, self.action_topic, start)

    # -- robot streams on the model's step grid (tpsr_ros.core.resample) ----------------

    def _stream_time(self, msg: Any) -> int:
        """Header stamp, or for unstamped messages the stream time now.

        The stream's clock is the camera's: the newest image stamp plus the time elapsed
        since it arrived (an unstamped command is placed between the images it arrived
        between, as its log time places it in a bag).
        """
        if hasattr(msg, "header") and (stamp := m.stamp_of(msg)) > 0:
            return stamp
        assert self.grid is not None
        last = self.grid.last_image_time
        if last is None or self._last_image_arrival_ns is None:
            return time.time_ns()
        return last + max(1, time.monotonic_ns() - self._last_image_arrival_ns)

    def _on_grid_image(self, data: bytes) -> None:
        start = time.perf_counter()
        assert self.grid is not None and self.spec is not None
        self._arrived("image")
        msg = self._decode(data, self.image_type, self.image_topic)
        if msg is None:
            return
        stamp = self._stream_time(msg)
        if self._grid_time_jumped(stamp):
            self._reinit(f"camera time jumped back to {stamp / _NS:.3f} s")
        assert self.camera_cadence is not None
        self.lost["image"] += self.camera_cadence.add(stamp)
        frame = _Frame()
        steps = self.grid.add_image(stamp, frame)
        self._last_image_arrival_ns = time.monotonic_ns()
        self._grid_steps(steps, start)
        # Downsampled at the input, once: after this image's steps have been published
        # (they hold the previous image), so it adds nothing to their latency, and the
        # node keeps an observation, not the camera's megabytes.
        frame.reduce(msg, self.image_type, self.spec.preprocessing)

    def _grid_time_jumped(self, stamp: int) -> bool:
        """Whether ``stamp`` is a backward jump of the stream's time; if so, restart the grid."""
        assert self.grid is not None
        last = self.grid.last_image_time
        if last is None or stamp >= last - self.sync.jump_threshold_ns:
            return False
        self.grid.reset()
        self.sync.stats.time_jumps += 1
        return True

    def _grid_steps(self, steps: list[GridStep], start: float) -> None:
        """Process the steps one image completed; they all hold the previous image."""
        if not steps:
            return
        frame: _Frame = steps[0].image
        if frame.observation is None:
            for _ in steps:  # one rejection per step, as each step is lost
                self._reject(self.image_topic, frame.reason, frame.detail)
            return
        for step in steps:
            self._process(step.stamp, int(step.command), frame.observation, start)

    def _on_grid_command(self, data: bytes) -> None:
        assert self.grid is not None and self.spec is not None
        self._arrived("action")
        msg = self._decode(data, self.action_type, self.action_topic)
        if msg is None:
            return
        codebook = self.spec.codebook
        try:
            values = m.twist_components(msg, codebook.components)
            index, distance = codebook.assign(values[None])
        except TpsrError as exc:
            self._reject(self.action_topic, "action", str(exc))
            return
        if distance[0] > codebook.far_distance:
            self.far_commands += 1
            self._warn(
                self.action_topic,
                "far",
                f"command {values.tolist()} is {distance[0]:.3g} from its nearest action "
                f"(more than {codebook.far_distance:.3g})",
            )
        self.grid.add_command(self._stream_time(msg), int(index[0]))

    def _add(self, index: int, stamp: int, item: Any, topic: str, start: float) -> None:
        dropped_before = self.sync.stats.dropped
        result = self.sync.add(index, stamp, item)
        if result.jumped:
            self.tracker.reinit()
            self.logger.info(f"time jumped back to {stamp / _NS:.3f} s: state re-initialised")
        if self.sync.stats.dropped > dropped_before:
            self._warn(topic, "dropped", "incomplete steps dropped (image or action missing)")
        if result.outcome is Outcome.DUPLICATE:
            self._warn(topic, "duplicate", f"duplicate message at {stamp / _NS:.3f} s ignored")
        elif result.outcome is Outcome.LATE:
            self._warn(topic, "late", f"late message at {stamp / _NS:.3f} s ignored")
        elif result.outcome is Outcome.PAIRED:
            assert result.items is not None
            image, action = result.items
            self._process(stamp, int(action), image_to_observation(image), start)

    def _process(self, stamp: int, action: int, observation: np.ndarray, start: float) -> None:
        try:
            info = self.tracker.step(stamp, action, observation)
        except Exception as exc:  # never let one step stop the node
            self.errors += 1
            self.tracker.reinit()
            if self._throttle((self.state_pub.topic, "error")):
                self.logger.error(f"update at {stamp / _NS:.3f} s failed ({exc}); state reset")
            return
        if info.recovered:
            self._recovery_run += 1
            self._warn(
                self.state_pub.topic,
                "recovery",
                f"normaliser {info.normalizer:.3g} at {stamp / _NS:.3f} s: restarted from b_*",
            )
        else:
            self._recovery_run = 0
        self.state_pub.publish(m.state_msg(stamp, info.state))
        if self.policy is not None:
            self._command(info.state, stamp)
        self.latency.add(time.perf_counter() - start)

    def _on_reset(self, data: bytes) -> None:
        msg = self._decode(data, m.POSE_TYPE, self.reset_topic)
        if msg is None:
            return
        stamp = m.stamp_of(msg)
        last = self.sync.last_stamp
        if last is not None and stamp <= last and not self.sync.check_time(stamp):
            self.stale_resets += 1
            self.logger.debug(f"episode start at {stamp / _NS:.3f} s is not newer: ignored")
            return
        self.sync.start_after(stamp)
        for which in self._last_input_stamp:  # step 1 of the episode comes one period later
            self._last_input_stamp[which] = stamp
        self._reinit(f"episode start at {stamp / _NS:.3f} s")
        self.resets += 1

    def _on_clock(self, data: bytes) -> None:
        msg = self._decode(data, m.CLOCK_TYPE, self.clock_topic)
        if msg is None:
            return
        stamp = m.stamp_of(msg)
        # simulator streams are paired by stamp, robot streams stepped on the camera's grid
        jumped = self.sync.check_time(stamp) if self.grid is None else self._grid_time_jumped(stamp)
        if jumped:
            self._reinit(f"{self.clock_topic} jumped back to {stamp / _NS:.3f} s")

    def _reinit(self, why: str) -> None:
        self.tracker.reinit()
        self.logger.debug(f"{why}: state re-initialised to b_*")
        if self.policy is not None:
            self._command(self.tracker.state)

    # -- commands -------------------------------------------------------------------------

    def _command(self, state: np.ndarray, stamp: int | None = None) -> None:
        assert self.policy is not None
        self._pending_command = (self.policy.action(state), stamp)
        if self.commands_ready:
            self._send_pending()

    def _send_pending(self) -> None:
        if self._pending_command is None or self.cmd_pub is None:
            return
        action, stamp = self._pending_command
        self._pending_command = None
        if self.spec is None:
            vx, vy = ACTIONS[action]
            twist = m.twist_msg(float(vx), float(vy))
        else:  # the code itself: never outside the codebook
            twist = m.twist_from_components(self.spec.codebook.command(action))
        if self.params.command_type == "twist_stamped":
            msg = m.stamped_twist(stamp if stamp is not None else time.time_ns(), twist)
        else:
            msg = twist
        self.cmd_pub.publish(msg)
        self.commands += 1

    def _subscribers_matched(self) -> bool:
        assert self.cmd_pub is not None
        need = int(self.params.wait_for_subscribers)
        return self.cmd_pub.get_subscription_count() >= max(1, need) and (
            self.state_pub.get_subscription_count() >= need
        )

    def _check_ready(self) -> None:
        if self.commands_ready:
            self._ready_timer.cancel()
            return
        if not self._subscribers_matched():
            self._ready_since = None
            return
        now = time.monotonic()
        if self._ready_since is None:
            self._ready_since = now
        if now - self._ready_since >= SETTLE_S:
            self.commands_ready = True
            self._ready_timer.cancel()
            self.logger.info("command subscribers matched: driving")
            self._send_pending()

    # -- diagnostics ----------------------------------------------------------------------

    def diagnostics_values(self) -> dict[str, Any]:
        """Every diagnostics key-value (also used by tests and the benchmark)."""
        now = time.monotonic()
        since, steps_then, _ = self._last_report
        rate = (self.tracker.steps - steps_then) / max(now - since, 1e-9)
        p50, p99 = self.latency.percentiles(50, 99)
        last = (
            self.tracker.last_stamp
            if self.tracker.last_stamp is not None
            else (self.sync.last_stamp)
        )
        values: dict[str, Any] = {
            "update_rate_hz": rate,
            "latency_p50_ms": p50 * 1e3,
            "latency_p99_ms": p99 * 1e3,
            "steps": self.tracker.steps,
            "commands": self.commands,
            "resets": self.resets,
            "stale_resets": self.stale_resets,
            **self._problem_counts(),
            **self._input_health(now),
            "last_stamp_s": "none" if last is None else f"{last / _NS:.9f}",
            "state_dim": self.model.state_dim,
            "model": self.inputs.fingerprint[:12],
            "policy": "none" if self.policy is None else self.params.policy,
        }
        return values

    def _input_health(self, now: float) -> dict[str, Any]:
        values: dict[str, Any] = {}
        for which, topic in (("image", self.image_topic), ("action", self.action_topic)):
            recent = [t for t in self._arrivals[which] if t >= now - RATE_WINDOW_S]
            span = min(RATE_WINDOW_S, now - recent[0]) if len(recent) > 1 else 0.0
            values[f"{which}_rate_hz"] = (len(recent) - 1) / span if span > 0 else 0.0
            last = self._last_arrival[which]
            values[f"{which}_age_s"] = "never" if last is None else round(now - last, 3)
            values[f"{which}_topic"] = topic
        return values

    def _silent(self) -> list[tuple[str, float]]:
        """Inputs that delivered before but nothing for longer than ``input_timeout``."""
        now = time.monotonic()
        out = []
        for which, topic in (("image", self.image_topic), ("action", self.action_topic)):
            last = self._last_arrival[which]
            if last is not None and now - last > self.params.input_timeout:
                out.append((topic, now - last))
        return out

    def health(self, values: dict[str, Any]) -> tuple[int, str]:
        """Level and message of the report: what got worse since the previous report."""
        _, steps_then, problems_then = self._last_report
        grown = [k for k, v in self._problem_counts().items() if v > problems_then.get(k, 0)]
        rejected_now = sum(
            v - problems_then.get(k, 0)
            for k, v in self._problem_counts().items()
            if k.startswith("rejected_")
        )
        if self._recovery_run >= _RECOVERY_ERROR_RUN:
            return ERROR, f"the last {self._recovery_run} updates all needed recovery"
        if rejected_now and self.tracker.steps == steps_then:
            return ERROR, f"every message rejected ({rejected_now} since the last report)"
        silent = self._silent()
        if silent and len(silent) == 2:
            age = min(a for _, a in silent)
            return STALE, f"inputs silent for {age:.1f} s (no {silent[0][0]}, no {silent[1][0]})"
        if grown:
            return WARN, "since the last report: " + ", ".join(grown)
        if silent:
            return WARN, f"{silent[0][0]} silent for {silent[0][1]:.1f} s"
        if self.tracker.steps == 0:
            return OK, "waiting for paired images and actions"
        return OK, "tracking"

    def publish_diagnostics(self) -> None:
        """Publish one DiagnosticArray (timer callback)."""
        values = self.diagnostics_values()
        level, message = self.health(values)
        status = diagnostic_status(
            level, f"{self.name}: state tracking", message, values, hardware_id="tpsr"
        )
        self.diagnostics_pub.publish(diagnostic_array(time.time_ns(), [status]))
        self._last_report = (time.monotonic(), self.tracker.steps, self._problem_counts())

    def on_parameter_change(self, name: str, value: Any) -> str | None:
        """``ros2 param set /tpsr_filter policy NEW``: swap the policy if it fits the model.

        Checked exactly as at start-up; every other parameter is fixed at start-up.
        """
        if name != "policy":
            return super().on_parameter_change(name, value)
        if self.policy is None or not value:
            return (
                "the policy can only be replaced by another one while the node runs (a pure "
                "filter has no /cmd_vel publisher, and one with a policy keeps it); restart "
                "the node"
            )
        try:
            inputs = load_inputs(
                replace(self.params, policy=str(value)),
                self.image_topic,
                self.action_topic,
                self.namespace,
            )
        except TpsrError as exc:
            return str(exc)
        self.policy = inputs.policy
        self.logger.info(f"policy {value} now chooses the commands")
        return None

    def on_shutdown(self) -> None:
        """Log the totals."""
        problems = ", ".join(f"{k} {v}" for k, v in self._problem_counts().items() if v)
        self.logger.info(
            f"tracked {self.tracker.steps} steps, {self.resets} resets, {self.commands} "
            f"commands" + (f"; {problems}" if problems else "")
        )


def main(argv: list[str] | None = None) -> None:
    """Entry point of ``python -m tpsr_ros.filter_node``."""
    run_node(FilterNode, prog=PROG, argv=argv)


if __name__ == "__main__":
    main()
