"""What the filter node does with each tracked step: observers, one job each.

The tracker turns a step into a state; the node wraps both in a :class:`Tracked` and hands
it to its observers in order (:meth:`FilterNode._process`). Each observer does one thing with
it: keep the health ledger, publish the state, keep the steps a swap re-filters,
command the policy's greedy action, measure the latency, publish the view topics. A new
consumer of steps (a learner, a recorder) is one more observer, not an edit of the step.

Observers that depend on the model or the policy are told when they change
(:meth:`StepObserver.swapped`, a model swap at a step boundary) and when the state is
re-initialised to ``b_*`` (:meth:`StepObserver.restarted`: an episode start, a clock jump).
Their order is the order of the messages of a step: ``/tpsr/state``, the first step's
``tpsr/model_info``, ``/cmd_vel``, then the view topics.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from tpsr_ros.core.online import StepInfo
from tpsr_ros.core.units import NS_PER_S
from tpsr_ros.filter_node.health import HealthLedger
from tpsr_ros.filter_node.stepping import Step
from tpsr_ros.io import messages as m
from tpsr_ros.io.filter_inputs import FilterInputs
from tpsr_ros.io.policy import Policy
from tpsr_ros.io.view_messages import (
    DECODED_POSE_TOPIC,
    MARKERS_TYPE,
    PREDICTED_IMAGE_TOPIC,
    STATE_MARKERS_TOPIC,
    ViewMessages,
    ViewSettings,
    view_messages,
)
from tpsr_ros.runtime import Publisher, QoSProfile
from tpsr_ros.runtime.diagnostics import RollingPercentiles

__all__ = [
    "Commander",
    "HealthKeeper",
    "LatencyMeter",
    "StatePublisher",
    "StepObserver",
    "SwapReplay",
    "Tracked",
    "ViewPublisher",
]


@dataclass
class Tracked:
    """One step as the tracker took it, and what its observers share about it.

    Attributes:
        step: the step (stamp, action index, observation).
        info: what the tracker's update did (the new state first).
        start: ``time.perf_counter()`` when the message that closed the step arrived.
        q_values: the policy's values of the new state, once the command computed them
            (None: no policy runs); a later observer reads them instead of computing them.
        new_segment: the state was re-initialised to ``b_*`` just before this step (time
            jumped back, or the update before failed), without a restart of its own: the
            step starts a new segment.

    """

    step: Step
    info: StepInfo
    start: float
    q_values: np.ndarray | None = None
    new_segment: bool = False


class StepObserver:
    """Something done with every tracked step (the base: nothing on a swap or restart)."""

    def observe(self, tracked: Tracked) -> None:
        """Take one tracked step."""
        raise NotImplementedError

    def restarted(self, state: np.ndarray) -> None:
        """The state was re-initialised to ``state`` (``b_*``); the next step starts from it."""

    def swapped(self, inputs: FilterInputs) -> None:
        """``inputs`` (model, and the policy that runs) track from the next step on."""


class _Publishers(Protocol):
    """The part of a node that creates publishers."""

    def create_publisher(self, topic: str, msgtype: str, qos: QoSProfile = ...) -> Publisher: ...


class HealthKeeper(StepObserver):
    """The health ledger's update count and recovery run; a throttled warning per recovery
    (the normaliser guard restarted the update from ``b_*``)."""

    def __init__(self, health: HealthLedger, warn: Callable[[str], None]) -> None:
        self.health = health
        self._warn = warn

    def observe(self, tracked: Tracked) -> None:
        info = tracked.info
        self.health.update(bool(info.recovered))
        if info.recovered:
            self._warn(
                f"normaliser {info.normalizer:.3g} at {tracked.step.stamp / NS_PER_S:.3f} s: "
                "restarted from b_*"
            )


class StatePublisher(StepObserver):
    """Each new state on ``/tpsr/state`` (a template's bytes: the stamp and values written
    in); a swap to another state size takes a new template."""

    def __init__(self, publisher: Publisher, state_dim: int) -> None:
        self.publisher = publisher
        self._encode = m.StateEncoder(state_dim)

    def observe(self, tracked: Tracked) -> None:
        self.publisher.publish_raw(self._encode(tracked.step.stamp, tracked.info.state))

    def swapped(self, inputs: FilterInputs) -> None:
        self._encode = m.StateEncoder(inputs.model.state_dim)


class SwapReplay(StepObserver):
    """The last steps of the segment, which a swap re-filters with the new model (none kept
    for ``swap_state`` restart), and the stamp of the first step tracked with the model in
    use: ``acknowledge`` announces it (``tpsr/model_info``) when that step comes."""

    def __init__(self, keep: int, acknowledge: Callable[[], None]) -> None:
        self._recent: deque[tuple[int, int, Any]] = deque(maxlen=keep)
        self._acknowledge = acknowledge
        self.first_stamp: int | None = None
        """Stamp of the first step tracked with the model in use (None: none yet)."""

    def observe(self, tracked: Tracked) -> None:
        step = tracked.step
        if tracked.new_segment:  # a swap re-filters the current segment only
            self._recent.clear()
        self._recent.append((step.stamp, step.action, step.image))
        if self.first_stamp is None:
            self.first_stamp = step.stamp
            self._acknowledge()

    def steps(self) -> list[tuple[int, int, Any]]:
        """The steps a swap re-filters, oldest first."""
        return list(self._recent)

    def restarted(self, state: np.ndarray) -> None:
        self._recent.clear()  # a swap re-filters the current segment only

    def swapped(self, inputs: FilterInputs) -> None:
        self.first_stamp = None


class Commander(StepObserver):
    """The policy's greedy action of each state on ``/cmd_vel`` (with no policy, nothing).

    A command waits (the latest one only) until :meth:`go`: the node's subscribers are
    matched. The Q-values are computed once per step and left in :attr:`Tracked.q_values`
    for the view. ``codes`` give each action's command; a ``Twist``'s bytes are the same
    for every command of an action, so they are serialised once.
    """

    def __init__(
        self,
        policy: Policy | None,
        publisher: Publisher,
        codes: Any,
        *,
        stamped: bool,
        now_ns: Callable[[], int],
        sent: Callable[[int], None] | None = None,
    ) -> None:
        """``stamped``: ``TwistStamped`` commands (stamped with the step's, else ``now_ns``);
        ``sent``: told each action commanded, before it is published."""
        self.policy = policy
        self.publisher = publisher
        self._stamped = stamped
        self._now_ns = now_ns
        self._sent = sent
        self._twists = [m.twist_from_components(codes.command(a)) for a in range(len(codes))]
        self._twist_cdr = [m.serialize(twist, m.TWIST_TYPE) for twist in self._twists]
        self._pending: tuple[int, int | None] | None = None
        self.ready = policy is None
        """Commands are published (else the latest is held until :meth:`go`)."""
        self.commands = 0
        """Commands published."""

    def observe(self, tracked: Tracked) -> None:
        if self.policy is None:
            return
        state = tracked.info.state
        q_values = self.policy.q.values(state)[0]
        # the greedy action of finite values is the policy's; otherwise the policy decides
        # (and refuses a non-finite state)
        greedy = int(np.argmax(q_values)) if np.isfinite(q_values).all() else None
        tracked.q_values = q_values
        self.command(state, tracked.step.stamp, greedy)

    def restarted(self, state: np.ndarray) -> None:
        if self.policy is not None:
            self.command(state)

    def swapped(self, inputs: FilterInputs) -> None:
        self.policy = inputs.policy

    def command(self, state: np.ndarray, stamp: int | None = None,
                greedy: int | None = None) -> None:  # fmt: skip
        """Command the greedy action of ``state`` (``greedy`` when already known)."""
        assert self.policy is not None
        action = self.policy.action(state) if greedy is None else greedy
        self._pending = (action, stamp)
        if self.ready:
            self._send_pending()

    def go(self) -> None:
        """The subscribers are matched: publish from now on, the held command first."""
        self.ready = True
        self._send_pending()

    def _send_pending(self) -> None:
        if self._pending is None:
            return
        action, stamp = self._pending
        self._pending = None
        if self._stamped:
            when = stamp if stamp is not None else self._now_ns()
            cdr = m.serialize(m.stamped_twist(when, self._twists[action]), self.publisher.msgtype)
        else:
            cdr = self._twist_cdr[action]
        if self._sent is not None:  # lockstep: before the robot can answer it
            self._sent(action)
        self.publisher.publish_raw(cdr)
        self.commands += 1


class LatencyMeter(StepObserver):
    """The time from a step's closing message to here (after the state and the command)."""

    def __init__(self, latency: RollingPercentiles) -> None:
        self.latency = latency

    def observe(self, tracked: Tracked) -> None:
        self.latency.add(time.perf_counter() - tracked.start)


class ViewPublisher(StepObserver):
    """The view topics of each step (:mod:`tpsr_ros.io.view_messages`), for a model with
    the viewer's read-outs; rebuilt for each swapped-in model (its read-outs, and a fresh
    trail). The predicted images' errors go to ``image_errors`` (``/diagnostics``)."""

    def __init__(
        self,
        inputs: FilterInputs,
        node: _Publishers,
        settings: ViewSettings,
        markers_qos: QoSProfile,
        image_errors: deque[float],
        inform: Callable[[str], None],
    ) -> None:
        """The view of ``inputs``' model; ``node`` creates the publishers (each once, when a
        model first needs it); ``inform`` logs why a model shows no view."""
        self._node = node
        self._settings = settings
        self._markers_qos = markers_qos
        self.image_errors = image_errors
        self._inform = inform
        self.viewer: ViewMessages | None = None
        self._predicted: Publisher | None = None
        self._markers: Publisher | None = None
        self._pose: Publisher | None = None
        self.swapped(inputs)

    def swapped(self, inputs: FilterInputs) -> None:
        model_file = inputs.model_file
        if model_file.view is None:
            self._inform(
                f"{model_file.path} has no viewer read-outs (written before them): no view "
                "topics; refit it with `learner fit` to see them"
            )
            self.viewer = None
            return
        self.viewer = view_messages(model_file, self._settings)
        if self._predicted is None:
            self._predicted = self._node.create_publisher(PREDICTED_IMAGE_TOPIC, m.IMAGE_TYPE)
            self._markers = self._node.create_publisher(
                STATE_MARKERS_TOPIC, MARKERS_TYPE, self._markers_qos
            )
        if self._pose is None and self.viewer.view.pose is not None:
            self._pose = self._node.create_publisher(DECODED_POSE_TOPIC, m.POSE_TYPE)

    def observe(self, tracked: Tracked) -> None:
        if self.viewer is None:
            return
        assert self._markers is not None and self._predicted is not None
        step = tracked.step
        view = self.viewer.step(step.stamp, tracked.info.state, step.image, tracked.q_values)
        for markers in view.markers:
            self._markers.publish_raw(markers)
        self._predicted.publish_raw(view.predicted_image)
        if self._pose is not None and view.decoded_pose is not None:
            self._pose.publish_raw(view.decoded_pose)
        if view.image_error is not None:
            self.image_errors.append(view.image_error)

