"""The filter node: its ROS face around the ROS-free parts of this package.

Each message callback forwards to one of them and publishes what comes back:
:mod:`~tpsr_ros.filter_node.inputs` turns decoded messages into observations and action
indices, a step source of :mod:`~tpsr_ros.filter_node.stepping` turns those into steps,
:class:`~tpsr_ros.core.online.OnlineTracker` into states, which are fed to the observers of
:mod:`~tpsr_ros.filter_node.observers` (the state, the swap replay, the policy's command, the
latency, the view topics), and :mod:`~tpsr_ros.filter_node.health` keeps what
``/diagnostics`` says.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np

from tpsr_ros.core.actions import environment_grid
from tpsr_ros.core.errors import ConfigError, MessageError, TpsrError
from tpsr_ros.core.online import OnlineTracker
from tpsr_ros.core.state_model import StateModel
from tpsr_ros.core.units import NS_PER_S as _NS
from tpsr_ros.filter_node.health import (
    MIN_SHARE_SAMPLES,
    OK,
    STALE,
    WARN,
    HealthLedger,
    Throttle,
)
from tpsr_ros.filter_node.inputs import (
    Frame,
    Rejected,
    robot_command,
)
from tpsr_ros.filter_node.observers import (
    Commander,
    HealthKeeper,
    LatencyMeter,
    StatePublisher,
    StepObserver,
    SwapReplay,
    Tracked,
    ViewPublisher,
)
from tpsr_ros.filter_node.params import (
    ACTION_TOPIC,
    CLOCK_TOPIC,
    CMD_VEL_TOPIC,
    COMMAND_TYPES,
    DIAGNOSTICS_TOPIC,
    IMAGE_TOPIC,
    MODEL_INFO_TOPIC,
    MODEL_UPDATE_TOPIC,
    RESET_TOPIC,
    STATE_TOPIC,
    FilterNodeParams,
)
from tpsr_ros.filter_node.simulator_inputs import SimulatorInputs
from tpsr_ros.filter_node.stepping import (
    Added,
    ExactPairing,
    GridStepping,
    LockstepStepping,
    Step,
)
from tpsr_ros.filter_node.swap import (
    MODEL_MESSAGE_TYPE,
    ModelUpdate,
    checked_inputs,
    model_info,
    parse_update,
    string_msg,
)
from tpsr_ros.io import messages as m
from tpsr_ros.io.filter_inputs import FilterInputs, check_policy, filter_inputs, input_topics
from tpsr_ros.io.model_io import open_model
from tpsr_ros.io.policy import Policy, load_policy
from tpsr_ros.io.qos import CLOCK_QOS
from tpsr_ros.io.view_messages import ViewMessages, ViewSettings
from tpsr_ros.runtime import (
    DEFAULT_QOS,
    LATCHED_QOS,
    Durability,
    History,
    Node,
    NodeOptions,
    QoSProfile,
    Reliability,
    Subscription,
    run_node,
)
from tpsr_ros.runtime.diagnostics import (
    DIAGNOSTICS_TYPE,
    RollingPercentiles,
    diagnostic_array,
    diagnostic_status,
)

__all__ = ["FilterNode", "load_inputs", "main"]

PROG = "python -m tpsr_ros.filter_node"
WARN_PERIOD_S = 5.0
"""At most one warning per topic and kind (rejection, drop, duplicate...) in this many seconds."""
SETTLE_S = 0.25
"""Once the command's subscribers are matched, time for their side of discovery to finish."""
MARKERS_QOS = QoSProfile(
    Reliability.RELIABLE, Durability.TRANSIENT_LOCAL, History.KEEP_LAST, DEFAULT_QOS.depth
)
"""tpsr/state_markers: a viewer that joins late gets the last markers (the trail)."""
RELOAD_SERVICE = "~/reload_model"
"""The ``std_srvs/srv/Trigger`` service that reads the model files again (rclpy only)."""
IMAGE_ERROR_STEPS = 100
"""Steps over which ``/diagnostics`` averages the predicted image's error."""


def load_inputs(
    params: FilterNodeParams,
    image_topic: str | None = None,
    action_topic: str | None = None,
    namespace: str = "/",
) -> FilterInputs:
    """Open the model (once), load the policy and check them for a node subscribing the
    given topics (default: the model's own, or the simulator's, in ``namespace``)."""
    prefix = namespace.rstrip("/")
    return _open_inputs(
        params, lambda name: f"{prefix}/{name}", namespace, image_topic, action_topic
    )


def _open_inputs(
    params: FilterNodeParams,
    resolve: Callable[[str], str],
    namespace: str,
    image_topic: str | None = None,
    action_topic: str | None = None,
) -> FilterInputs:
    """The model opened once and the policy loaded, checked for the input topics: the
    given ones, else the model's (or the simulator's) names as ``resolve`` maps them."""
    if not params.model:
        raise ConfigError("no model given: pass -p model:=MODEL (a file from `learner fit`)")
    model_file = open_model(params.model)
    image, action = input_topics(model_file) or (IMAGE_TOPIC, ACTION_TOPIC)
    policy = (load_policy(params.policy), params.policy) if params.policy else None
    return filter_inputs(
        model_file,
        policy,
        check_topics=params.check_topics,
        image_topic=image_topic or resolve(image),
        action_topic=action_topic or resolve(action),
        namespace=namespace,
    )


class FilterNode(Node):
    """Tracks the TPSR state from images and actions; publishes it and the greedy command."""

    default_name = "tpsr_filter"
    Params = FilterNodeParams
    description = (
        "Track the predictive state online (guide Algorithm 4) and, with a policy, publish "
        "the greedy fitted-Q command."
    )

    @classmethod
    def preflight(cls, options: NodeOptions) -> FilterInputs | None:
        """Open and check the model and policy before joining the graph (once: the node's
        :meth:`setup` takes what this opened); None: no model yet, wait for one."""
        if not options.params.model and options.params.wait_for_model:
            return None
        return cls._checked(options, options.params)

    @classmethod
    def _checked(cls, options: NodeOptions, params: FilterNodeParams) -> FilterInputs:
        # Node.resolve_topic needs only the options, name and namespace: use it unbound
        # so the check sees exactly the names setup() will subscribe.
        probe = object.__new__(cls)
        probe.options, probe.name, probe.namespace = options, options.name, options.namespace
        return _open_inputs(params, probe.resolve_topic, options.namespace)

    def setup(self) -> None:
        """Take the checked model and policy and start; with none (``wait_for_model``),
        wait for the first announced on ``tpsr/model_update``."""
        prepared = self.prepared
        inputs = prepared if isinstance(prepared, FilterInputs) else self.preflight(self.options)
        self.model_version: int | None = None
        if inputs is not None:
            self._start(inputs)
            return
        self._waiting = self.create_subscription(
            MODEL_UPDATE_TOPIC, MODEL_MESSAGE_TYPE, self._on_first_model, LATCHED_QOS, raw=True
        )
        self.diagnostics_pub = self.create_publisher(DIAGNOSTICS_TOPIC, DIAGNOSTICS_TYPE)
        self._waiting_report = self.create_timer(
            self.params.diagnostics_period, self._report_waiting
        )
        self.logger.info(f"no model yet: waiting for one on {self._waiting.topic}")

    def _report_waiting(self) -> None:
        """``/diagnostics`` while no model runs yet: STALE, saying where one is awaited."""
        status = diagnostic_status(
            STALE, f"{self.name}: state tracking",
            f"no model yet: waiting for one on {self._waiting.topic}", {"model": "none"},
            hardware_id="tpsr",
        )  # fmt: skip
        self.diagnostics_pub.publish(diagnostic_array(self.now_ns(), [status]))

    def _on_first_model(self, data: bytes) -> None:
        """The first announced model: open and check it as at start-up, then start."""
        try:
            update = parse_update(str(m.deserialize(data, MODEL_MESSAGE_TYPE).data))
        except TpsrError as exc:
            self.logger.warning(f"{self._waiting.topic}: refused, still waiting: {exc}")
            return
        if (refused := self._first_model(update)) is not None:
            self.logger.warning(f"{self._waiting.topic}: refused, still waiting: {refused}")

    def _first_model(self, update: ModelUpdate) -> str | None:
        """Start with ``update``'s model and policy, checked as at start-up (the reason
        it cannot run, else None)."""
        try:
            params = replace(self.params, model=update.path, policy=update.policy or "")
            inputs = self._checked(self.options, params)
            if update.fingerprint and not inputs.fingerprint.startswith(update.fingerprint):
                raise ConfigError(
                    f"{update.path} has fingerprint {inputs.fingerprint[:12]}, not the "
                    f"announced {update.fingerprint[:12]}"
                )
        except TpsrError as exc:
            return str(exc)
        self._waiting.destroy()
        self._waiting_report.cancel()
        self.params = params
        self.model_version = update.version  # its latched announcement is not a swap
        self._start(inputs)
        return None

    def _start(self, inputs: FilterInputs) -> None:
        """Take the checked model and policy; create the endpoints and timers."""
        p: FilterNodeParams = self.params
        self.inputs = inputs
        image_name, action_name = input_topics(self.inputs.model_file) or (
            IMAGE_TOPIC,
            ACTION_TOPIC,
        )
        self.image_topic = self.resolve_topic(image_name)
        self.action_topic = self.resolve_topic(action_name)
        self.spec = self.inputs.spec
        self.sim_actions = environment_grid(self.inputs.model_file.environment)  # exact pairing's
        jump_ns = round(p.jump_threshold * _NS)
        self.source: ExactPairing | GridStepping | LockstepStepping
        if p.lockstep:
            if self.spec is None or self.inputs.policy is None:
                raise ConfigError(
                    "lockstep needs a model learned with --step-period and a policy (a "
                    "simulator model pairs the simulator's own stamped actions)"
                )
            self.source = LockstepStepping(self.spec.grid, jump_threshold_ns=jump_ns)
        elif self.spec is None:
            self.source = ExactPairing(
                round(p.step_period * _NS), queue_size=p.queue_size, jump_threshold_ns=jump_ns
            )
        else:
            self.source = GridStepping(
                self.spec.grid, jump_threshold_ns=jump_ns,
                max_latency_ns=round(p.max_latency * _NS),
            )  # fmt: skip
        self.tracker = OnlineTracker(self.model, self.source_step_ns)
        self.health = HealthLedger(p.input_timeout)
        self._throttle = Throttle(WARN_PERIOD_S)
        self.resets = self.stale_resets = self.errors = 0
        self.latency = RollingPercentiles(1000)
        self.sim_inputs = SimulatorInputs(
            self.inputs.image_shape, p.image_frame, p.action_frame, self.sim_actions
        )
        self._ready_since: float | None = None
        self.policy_name = p.policy or "none"
        self.swaps = self.refused_swaps = 0
        self.commander: Commander | None = None  # the observers that the node asks
        self.view: ViewPublisher | None = None
        self._create_endpoints(image_name, action_name)
        self._publish_model_info()
        self._far_reported = (0, 0)  # far commands and command messages when last judged
        self._report_done()
        self.create_timer(p.diagnostics_period, self.publish_diagnostics)
        if self.commander is not None and not self.commander.ready:
            self._ready_timer = self.create_timer(0.01, self._check_ready)
        if self.grid is not None:
            self.create_timer(min(0.1, p.max_latency / 4), self._flush_if_idle)
        self._held_since: float | None = None  # lockstep: since when an image is held
        if p.lockstep:
            self.create_timer(min(0.1, p.max_latency / 4), self._flush_held)
        what = "pure filter" if self.policy is None else f"policy {p.policy}"
        how = "pairing"
        if self.spec is not None:
            how = f"steps of {self.spec.grid.step_ns / _NS:g} s from"
        if p.lockstep:
            how = "lockstep: one step per image of"
        self.logger.info(
            f"model {p.model} ({self.model.method}, {self.model.state_dim}-d states, "
            f"{self.inputs.fingerprint[:12]}); {what}; {how} {self.image_topic} and "
            f"{self.action_topic}"
        )

    def _observers(self) -> list[StepObserver]:
        """What is done with each tracked step, in the order of its messages: the health
        ledger, ``/tpsr/state``, the steps a swap re-filters (and the first step's
        ``tpsr/model_info``), the command, the latency, the view topics."""
        p: FilterNodeParams = self.params
        # the steps a swap re-filters (none kept when it restarts from b_*)
        replayed = p.swap_replay_steps if p.swap_state == "replay" else 0
        self.replay = SwapReplay(replayed, self._publish_model_info)
        state_topic = self.state_pub.topic
        observers: list[StepObserver] = [
            HealthKeeper(self.health, lambda text: self._warn(state_topic, "recovery", text)),
            StatePublisher(self.state_pub, self.inputs.model.state_dim),
            self.replay,
        ]
        if self.cmd_pub is not None:
            # the actions' commands themselves: never outside the simulator's grid or the
            # codebook
            codes = self.sim_actions if self.spec is None else self.spec.codebook
            lockstep = self.source if isinstance(self.source, LockstepStepping) else None
            self.commander = Commander(
                self.inputs.policy, self.cmd_pub, codes,
                stamped=p.command_type == "twist_stamped", now_ns=self.now_ns,
                sent=None if lockstep is None else lockstep.command,
            )  # fmt: skip
            observers.append(self.commander)
        observers.append(LatencyMeter(self.latency))  # to the state and the command
        if p.view:
            self.view = ViewPublisher(
                self.inputs, self, ViewSettings(trail=p.view_trail), MARKERS_QOS,
                self.image_errors, self.logger.info,
            )  # fmt: skip
            observers.append(self.view)
        return observers

    @property
    def model(self) -> StateModel:
        """The state model that tracks."""
        return self.inputs.model

    @property
    def policy(self) -> Policy | None:
        """The policy that commands (None: a pure filter, or none for the running model)."""
        return None if self.commander is None else self.commander.policy

    @property
    def commands(self) -> int:
        """Commands published."""
        return 0 if self.commander is None else self.commander.commands

    @property
    def commands_ready(self) -> bool:
        """Commands are published (a pure filter: always; else once subscribers match)."""
        return self.commander is None or self.commander.ready

    @property
    def viewer(self) -> ViewMessages | None:
        """The view topics' messages (``view`` on and a model with the viewer's read-outs)."""
        return None if self.view is None else self.view.viewer

    @property
    def source_step_ns(self) -> int:
        """The step period: the model's grid, or the ``step_period`` parameter."""
        if self.spec is not None:
            return int(self.spec.grid.step_ns)
        return round(float(self.params.step_period) * _NS)

    @property
    def grid(self) -> GridStepping | None:
        """The grid step source of a model learned with ``--step-period`` (else None)."""
        return self.source if isinstance(self.source, GridStepping) else None

    def _create_endpoints(self, image_name: str, action_name: str) -> None:
        p: FilterNodeParams = self.params
        sensor = QoSProfile(
            Reliability(p.sensor_qos), Durability.VOLATILE, History.KEEP_LAST, DEFAULT_QOS.depth
        )
        self.state_pub = self.create_publisher(STATE_TOPIC, m.STATE_TYPE)
        self.cmd_pub = (
            self.create_publisher(CMD_VEL_TOPIC, COMMAND_TYPES[p.command_type])
            if self.inputs.policy is not None
            else None
        )
        if not hasattr(self, "diagnostics_pub"):  # a node that waited for its model has one
            self.diagnostics_pub = self.create_publisher(DIAGNOSTICS_TOPIC, DIAGNOSTICS_TYPE)
        self.image_errors: deque[float] = deque(maxlen=IMAGE_ERROR_STEPS)
        self.observers = self._observers()
        self._new_segment = False  # the next step starts a segment without a restart of its own
        self.model_info_pub = self.create_publisher(
            MODEL_INFO_TOPIC, MODEL_MESSAGE_TYPE, LATCHED_QOS
        )
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
        elif p.lockstep:
            self.image_type, self.action_type = self.spec.image_type, self.spec.action_type
            on_image, on_action = self._on_lockstep_image, self._on_lockstep_command
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
        self.model_update_topic = self.create_subscription(
            MODEL_UPDATE_TOPIC, MODEL_MESSAGE_TYPE, self._on_model_update, LATCHED_QOS, raw=True
        ).topic
        self.reload_service = self.create_trigger_service(RELOAD_SERVICE, self.reload_model)

    # -- warnings and counters ------------------------------------------------------------

    def _warn(self, topic: str, kind: str, message: str) -> None:
        if (text := self._throttle.warning((topic, kind), f"{topic}: {message}")) is not None:
            self.logger.warning(text)

    def _reject(self, topic: str, reason: str, detail: str) -> None:
        self.health.reject(reason)
        self._warn(topic, "rejected", f"rejected ({reason}): {detail}")

    def _problem_counts(self) -> dict[str, int]:
        source = self.source.counts()
        counts = {k: source.pop(k) for k in ("dropped", "duplicates", "late", "out_of_order")}
        counts["time_jumps"] = source.pop("time_jumps")
        counts["gaps"] = self.tracker.gaps
        counts["recoveries"] = self.tracker.recoveries
        counts["errors"] = self.errors
        # both lower bounds of the same loss: stamp gaps (the step source's) and what the
        # middleware knows it lost (sequence gaps, lost-sample events)
        counts["lost_images"] = max(source.pop("lost_images"), self.image_sub.get_lost_count())
        counts["lost_actions"] = max(source.pop("lost_actions"), self.action_sub.get_lost_count())
        counts.update(source)
        counts.update({f"rejected_{reason}": n for reason, n in self.health.rejected.items()})
        return counts

    # -- callbacks ------------------------------------------------------------------------

    def _decode(self, data: bytes, msgtype: str, topic: str) -> Any | None:
        try:
            return m.deserialize(data, msgtype)
        except MessageError as exc:
            self._reject(topic, "undecodable", str(exc))
            return None

    def _on_image(self, data: bytes) -> None:
        start = time.perf_counter()
        self.health.arrived("image")
        try:
            stamp, observation = self.sim_inputs.image(data)
        except Rejected as exc:
            self._reject(self.image_topic, exc.reason, str(exc))
            return
        self._stepped(self.source.add_image(stamp, observation), stamp, self.image_topic, start)

    def _on_action(self, data: bytes) -> None:
        start = time.perf_counter()
        self.health.arrived("action")
        try:
            stamp, action = self.sim_inputs.action(data)
        except Rejected as exc:
            self._reject(self.action_topic, exc.reason, str(exc))
            return
        self._stepped(self.source.add_action(stamp, action), stamp, self.action_topic, start)

    def _stepped(self, added: Added, stamp: int, topic: str, start: float) -> None:
        """Restart on a jump back, warn about what was discarded, track the steps."""
        if added.jumped:  # the step that follows starts a new segment (and is commanded)
            self.tracker.reinit()
            self._new_segment = True
            self.logger.info(f"time jumped back to {stamp / _NS:.3f} s: state re-initialised")
        if added.problem == "dropped":
            self._warn(topic, "dropped", "incomplete steps dropped (image or action missing)")
        elif added.problem in ("duplicate", "late"):
            what = f"{added.problem} message at {stamp / _NS:.3f} s ignored"
            self._warn(topic, added.problem, what)
        for step in added.steps:
            self._process(step, start)

    # -- robot streams on the model's step grid -------------------------------------------

    @staticmethod
    def _sent(subscription: Subscription) -> int:
        """When the message in hand was published: the middleware's source timestamp (the
        publisher's clock), else now. Unstamped commands are dated by this order."""
        sent = subscription.source_ns
        return time.time_ns() if sent is None else sent

    def _on_grid_image(self, data: bytes) -> None:
        start = time.perf_counter()
        sent = self._sent(self.image_sub)
        assert self.grid is not None and self.spec is not None
        self.health.arrived("image")
        msg = self._decode(data, self.image_type, self.image_topic)
        if msg is None:
            return
        stamp = m.stamp_of(msg)
        stamp = stamp if stamp > 0 else sent  # unstamped: offline takes the log time
        frame = Frame(msg, self.image_type, self.spec.preprocessing)
        added = self.grid.add_image(stamp, frame, sent)
        if added.jumped:
            self._reinit(f"camera time jumped back to {stamp / _NS:.3f} s")
        self._grid_steps(added.steps, start)

    def _grid_steps(self, steps: list[Step], start: float) -> None:
        """Process closed steps, each with its image decoded (or rejected with the reason)."""
        for step in steps:
            frame: Frame = step.image
            observation = frame.reduce()
            if observation is None:  # one rejection per step, as each step is lost
                self._reject(self.image_topic, frame.reason, frame.detail)
                continue
            self._process(replace(step, image=observation), start)

    # -- a lockstep robot: one step per image ----------------------------------------------

    def _on_lockstep_image(self, data: bytes) -> None:
        """An image of a lockstep robot: the step of the node's last command."""
        start = time.perf_counter()
        sent = self._sent(self.image_sub)
        assert isinstance(self.source, LockstepStepping) and self.spec is not None
        self.health.arrived("image")
        msg = self._decode(data, self.image_type, self.image_topic)
        if msg is None:
            return
        stamp = m.stamp_of(msg)
        stamp = stamp if stamp > 0 else sent
        added = self.source.add_image(stamp, Frame(msg, self.image_type, self.spec.preprocessing))
        if added.jumped:
            self._reinit(f"camera time jumped back to {stamp / _NS:.3f} s")
        if added.problem is not None:
            self._warn(self.image_topic, "late", f"image at {stamp / _NS:.3f} s makes no step")
        if self.source.held is not None and self._held_since is None:
            self._held_since = time.perf_counter()
        self._grid_steps(added.steps, start)

    def _flush_held(self) -> None:
        """An image held after a gap for ``max_latency`` with no episode start before it:
        step it with the state it follows."""
        assert isinstance(self.source, LockstepStepping)
        if self.source.held is None:
            self._held_since = None
            return
        if self._held_since is not None and (
            time.perf_counter() - self._held_since >= self.params.max_latency
        ):
            self._held_since = None
            self._grid_steps(self.source.flush().steps, time.perf_counter())

    def _on_lockstep_command(self, data: bytes) -> None:
        """The command input in lockstep: not read (the node's own commands are the
        actions), only heard, for the input's health."""
        self.health.arrived("action")

    def _flush_if_idle(self) -> None:
        """Both inputs silent for ``max_latency``: close the steps before the newest image."""
        assert self.grid is not None
        idle = self.health.idle_for()
        if idle is not None and idle >= self.params.max_latency:
            self._grid_steps(self.grid.flush().steps, time.perf_counter())

    def _on_grid_command(self, data: bytes) -> None:
        start = time.perf_counter()
        sent = self._sent(self.action_sub)
        assert self.grid is not None and self.spec is not None
        self.health.arrived("action")
        msg = self._decode(data, self.action_type, self.action_topic)
        if msg is None:
            return
        codebook = self.spec.codebook
        try:
            index, distance, values = robot_command(msg, codebook)
        except Rejected as exc:
            self._reject(self.action_topic, exc.reason, str(exc))
            return
        far = distance > codebook.far_distance
        if far:
            self._warn(
                self.action_topic,
                "far",
                f"command {values.tolist()} is {distance:.3g} from its nearest action (more "
                f"than {codebook.far_distance:.3g})",
            )
        stamp = m.stamp_of(msg) if hasattr(msg, "header") else 0
        added = self.grid.add_action(stamp if stamp > 0 else None, index, sent_ns=sent, far=far)
        self._grid_steps(added.steps, start)

    # -- tracking and commands ------------------------------------------------------------

    def _process(self, step: Step, start: float) -> None:
        """Track one step and hand it to the observers (:meth:`_observers`)."""
        try:
            info = self.tracker.step(step.stamp, step.action, step.image)
        except Exception as exc:  # never let one step stop the node
            self.errors += 1
            self.tracker.reinit()
            self._new_segment = True
            if self._throttle((self.state_pub.topic, "error")):
                self.logger.error(f"update at {step.stamp / _NS:.3f} s failed ({exc}); state reset")
            return
        tracked = Tracked(step, info, start, new_segment=self._new_segment)
        self._new_segment = False
        for observer in self.observers:
            observer.observe(tracked)

    def _on_reset(self, data: bytes) -> None:
        msg = self._decode(data, m.POSE_TYPE, self.reset_topic)
        if msg is None:
            return
        stamp = m.stamp_of(msg)
        lockstep = self.source if isinstance(self.source, LockstepStepping) else None
        if lockstep is not None and lockstep.held is not None and lockstep.held[0] <= stamp:
            self._grid_steps(lockstep.flush().steps, time.perf_counter())  # before the start
        if not self.source.episode_start(stamp):
            self.stale_resets += 1
            self.logger.debug(f"episode start at {stamp / _NS:.3f} s is not newer: ignored")
            return
        self._reinit(f"episode start at {stamp / _NS:.3f} s")
        self.resets += 1
        if lockstep is not None:  # an image after the start that arrived before it
            self._held_since = None
            self._grid_steps(lockstep.release().steps, time.perf_counter())

    def _on_clock(self, data: bytes) -> None:
        msg = self._decode(data, m.CLOCK_TYPE, self.clock_topic)
        if msg is None:
            return
        stamp = m.stamp_of(msg)
        if self.source.clock(stamp):
            self._reinit(f"{self.clock_topic} jumped back to {stamp / _NS:.3f} s")

    def _reinit(self, why: str) -> None:
        self.tracker.reinit()
        self.logger.debug(f"{why}: state re-initialised to b_*")
        for observer in self.observers:
            observer.restarted(self.tracker.state)

    def _subscribers_matched(self) -> bool:
        assert self.cmd_pub is not None
        need = int(self.params.wait_for_subscribers)
        return self.cmd_pub.get_subscription_count() >= max(1, need) and (
            self.state_pub.get_subscription_count() >= need
        )

    def _check_ready(self) -> None:
        assert self.commander is not None
        if self.commander.ready:
            self._ready_timer.cancel()
            return
        if not self._subscribers_matched():
            self._ready_since = None
            return
        now = time.monotonic()
        if self._ready_since is None:
            self._ready_since = now
        if now - self._ready_since >= SETTLE_S:
            self._ready_timer.cancel()
            self.logger.info("command subscribers matched: driving")
            self.commander.go()

    # -- diagnostics ----------------------------------------------------------------------

    def _topics(self) -> dict[str, str]:
        return {"image": self.image_topic, "action": self.action_topic}

    def diagnostics_values(self) -> dict[str, Any]:
        """Every diagnostics key-value (also used by tests and the benchmark)."""
        p50, p99 = self.latency.percentiles(50, 99)
        last = self.tracker.last_stamp
        if last is None and isinstance(self.source, ExactPairing):
            last = self.source.last_stamp
        return {
            "update_rate_hz": self.health.update_rate(self.tracker.steps),
            "latency_p50_ms": p50 * 1e3,
            "latency_p99_ms": p99 * 1e3,
            "steps": self.tracker.steps,
            "commands": self.commands,
            "resets": self.resets,
            "stale_resets": self.stale_resets,
            **self._problem_counts(),
            **({"command_messages": self._command_messages()} if self.grid is not None else {}),
            **self.health.input_values(self._topics()),
            "last_stamp_s": "none" if last is None else f"{last / _NS:.9f}",
            "state_dim": self.model.state_dim,
            "model": self.inputs.fingerprint[:12],
            "policy": "none" if self.policy is None else self.policy_name,
            "model_version": "none" if self.model_version is None else self.model_version,
            "model_swaps": self.swaps,
            "model_swaps_refused": self.refused_swaps,
            **self._view_values(),
        }

    def _view_values(self) -> dict[str, Any]:
        """The predicted image's pixel RMS error against the image that came (the mean over
        the last :data:`IMAGE_ERROR_STEPS` steps), with the view on."""
        if self.viewer is None:
            return {}
        errors = self.image_errors
        return {"predicted_image_rmse": float(np.mean(errors)) if errors else "none"}

    def health_status(self) -> tuple[int, str]:
        """Level and message of the next report: what got worse since the previous one.

        Far commands inform (a key-value); they WARN only when more than
        ``far_commands_warn`` of the command messages since the last judged report were far,
        judged over at least :data:`~tpsr_ros.filter_node.health.MIN_SHARE_SAMPLES` of them.
        """
        counts = self._problem_counts()
        far = counts.pop("far_commands", 0)
        level, message = self.health.assess(counts, self.tracker.steps, self._topics())
        far_then, commands_then = self._far_reported
        new_far, new_commands = far - far_then, self._command_messages() - commands_then
        if (
            level == OK
            and new_commands >= MIN_SHARE_SAMPLES
            and new_far > self.params.far_commands_warn * new_commands
        ):
            level = WARN
            message = (
                f"{new_far} of {new_commands} command messages ({new_far / new_commands:.0%}) "
                f"since the last judged report were far from every action (more than "
                f"far_commands_warn {self.params.far_commands_warn:g})"
            )
        return level, message

    def _command_messages(self) -> int:
        """Command messages put in force so far (robot streams; the unit of far_commands)."""
        return self.grid.command_messages if self.grid is not None else 0

    def publish_diagnostics(self) -> None:
        """Publish one DiagnosticArray (timer callback)."""
        values = self.diagnostics_values()
        level, message = self.health_status()
        status = diagnostic_status(
            level, f"{self.name}: state tracking", message, values, hardware_id="tpsr"
        )
        self.diagnostics_pub.publish(diagnostic_array(self.now_ns(), [status]))
        self._report_done()

    def _report_done(self) -> None:
        """Remember the counters of the report just published."""
        counts = self._problem_counts()
        far, commands = counts.pop("far_commands", 0), self._command_messages()
        if commands - self._far_reported[1] >= MIN_SHARE_SAMPLES:  # judged: start afresh
            self._far_reported = (far, commands)
        self.health.reported(counts, self.tracker.steps)

    def on_parameter_change(self, name: str, value: Any) -> str | None:
        """``ros2 param set /tpsr_filter model NEW`` swaps the model (:meth:`swap_model`),
        ``... policy NEW`` the policy if it fits the model; every other parameter is fixed
        at start-up."""
        if not hasattr(self, "inputs"):  # waiting for a first model
            if name == "model" and value:
                return self._first_model(ModelUpdate(str(value), policy=self.params.policy or None))
            if name == "policy":
                return None  # taken with the model
        if name == "model":
            return self.swap_model(ModelUpdate(str(value))) if value else "model cannot be empty"
        if name != "policy":
            return super().on_parameter_change(name, value)
        if self.cmd_pub is None or not value:
            return (
                "the policy can only be replaced by another one while the node runs (a pure "
                "filter has no /cmd_vel publisher, and one with a policy keeps it); restart "
                "the node"
            )
        try:
            policy = load_policy(str(value))
            check_policy(policy, self.inputs.model_file, str(value))
        except TpsrError as exc:
            return str(exc)
        assert self.commander is not None  # a node with a /cmd_vel publisher
        self.commander.policy, self.policy_name = policy, str(value)
        self.logger.info(f"policy {value} now chooses the commands")
        return None

    # -- model swaps ------------------------------------------------------------------------

    def _on_model_update(self, data: bytes) -> None:
        msg = self._decode(data, MODEL_MESSAGE_TYPE, self.model_update_topic)
        if msg is None:
            return
        try:
            update = parse_update(str(msg.data))
        except TpsrError as exc:
            self.refused_swaps += 1
            self.logger.warning(f"{self.model_update_topic}: refused: {exc}")
            return
        if update.fingerprint is not None and self.inputs.fingerprint.startswith(
            update.fingerprint
        ) and update.version == self.model_version:
            return  # the latched announcement of the model already running
        self.swap_model(update)

    def reload_model(self) -> tuple[bool, str]:
        """``~/reload_model`` (``std_srvs/srv/Trigger``): read the ``model`` (and ``policy``)
        files again and swap them in, e.g. after a refit replaced them; the response says
        what runs, or why the new file was refused and the old model runs on."""
        p: FilterNodeParams = self.params
        before = self.inputs.fingerprint
        refused = self.swap_model(ModelUpdate(p.model, policy=p.policy or None))
        if refused is not None:
            return False, f"refused, {before[:12]} runs on: {refused}"
        now = self.inputs.fingerprint
        same = " (the same model, its state re-filtered)" if now == before else ""
        return True, f"{p.model} runs: {now[:12]}{same}"

    def swap_model(self, update: ModelUpdate) -> str | None:
        """Run the model (and policy) of ``update`` from the next step on, at a step
        boundary (callbacks run one at a time); its state re-filters the last
        ``swap_replay_steps`` steps of the segment (``swap_state`` replay) or starts from
        b_* (restart). A model the node cannot run is refused, the reason returned and
        logged, and the old one keeps running."""
        p: FilterNodeParams = self.params
        current = replace(self.inputs, policy=self.policy)
        try:
            inputs, note = checked_inputs(
                update, current, check_topics=p.check_topics, image_topic=self.image_topic,
                action_topic=self.action_topic, namespace=self.namespace,
            )  # fmt: skip
        except TpsrError as exc:
            self.refused_swaps += 1
            self.logger.warning(
                f"model {update.path} refused, {self.inputs.model_file.path} runs on: {exc}"
            )
            return str(exc)
        replay = self.replay.steps()
        self.inputs = inputs
        self.tracker.swap(inputs.model, replay)
        if self.cmd_pub is not None:
            if update.policy is not None:
                self.policy_name = update.policy
        elif update.policy is not None:
            note = f"a pure filter has no {CMD_VEL_TOPIC} publisher: policy {update.policy} unused"
        running = inputs if self.cmd_pub is not None else replace(inputs, policy=None)
        for observer in self.observers:
            observer.swapped(running)
        self.model_version = update.version
        self.swaps += 1
        self._publish_model_info()
        self.logger.info(
            f"model {update.path} ({inputs.fingerprint[:12]}, version {update.version}) runs "
            f"from the next step; state: {p.swap_state}"
            + (f" of {len(replay)} steps" if p.swap_state == "replay" else "")
        )
        if note is not None:
            self.logger.warning(note)
        return None

    def _publish_model_info(self) -> None:
        """Acknowledge the model in use on the latched ``tpsr/model_info``."""
        text = model_info(
            replace(self.inputs, policy=self.policy), version=self.model_version,
            swaps=self.swaps, first_stamp_ns=self.replay.first_stamp,
        )  # fmt: skip
        self.model_info_pub.publish(string_msg(text))

    def on_shutdown(self) -> None:
        """Log the totals."""
        if not hasattr(self, "tracker"):
            self.logger.info("stopped while waiting for a model")
            return
        problems = ", ".join(f"{k} {v}" for k, v in self._problem_counts().items() if v)
        self.logger.info(
            f"tracked {self.tracker.steps} steps, {self.resets} resets, {self.commands} "
            f"commands" + (f"; {problems}" if problems else "")
        )


def main(argv: list[str] | None = None) -> None:
    """Entry point of ``python -m tpsr_ros.filter_node``."""
    run_node(FilterNode, prog=PROG, argv=argv)
