"""The TPSR filter node: tracks the predictive state online and, with a policy, drives the robot.

    python -m tpsr_ros.filter_node --ros-args -p model:=MODEL [-p policy:=POLICY]

Subscribes a camera and an action (or command) topic, publishes the state on
``/tpsr/state``, the greedy fitted-Q command on ``/cmd_vel`` and its health on
``/diagnostics`` (msgs_doc/filter_node.md is the interface). Its parts, the first three
free of ROS (they import neither rclpy, cyclonedds, rosbags nor mcap):

- :mod:`~tpsr_ros.filter_node.inputs`: decoded messages to observations and action indices,
  as offline tracking reads them from a bag, or a rejection with its reason;
- :mod:`~tpsr_ros.filter_node.stepping`: the two step sources, exact-stamp pairing of the
  simulator's streams and the step grid of models learned from robot bags;
- :mod:`~tpsr_ros.filter_node.health`: counters, input rates, warning throttles and the
  level of each ``/diagnostics`` report;
- :mod:`~tpsr_ros.filter_node.observers`: what is done with each tracked step, one
  observer per job (the health ledger, ``/tpsr/state``, the steps a model swap re-filters,
  the command, the latency, the view topics), told of swaps and re-initialisations;
- :mod:`~tpsr_ros.filter_node.params` and :mod:`~tpsr_ros.filter_node.node`: the parameters
  and the node itself, boilerplate around one call per message: a step is tracked, then
  fed to the observers.

Tracking is :class:`~tpsr_ros.core.online.OnlineTracker` (guide Algorithm 4 with the offline
tracker's rules: start from ``b_*``, restart at gaps), so the states published equal offline
tracking of the same steps bit for bit.

Re-initialisation (state ``b_*``, next step starts a segment): on an episode start
(``/sim/episode_start``, transient-local) newer than the last processed step, and on a
backwards jump of time: a ``/clock``, episode-start, image or action stamp earlier than the
last processed step by more than ``jump_threshold`` seconds. After a re-init the node
publishes the command for ``b_*`` (in lockstep that commands the first step of an episode).
An episode start at or before the last processed step (and not a jump) is stale and ignored.

Faults never stop the node: undecodable messages, images of the wrong encoding, size,
frame or data length, actions that are not finite or not one of the 25 actions are
rejected (counted per reason, at most one warning per topic every 5 s); incomplete,
duplicated, late and out-of-order messages are counted by the step source; degenerate
normalisers are recovered by the guard of :mod:`tpsr_ros.core.filtering` and counted.

Names are imported on first use, so importing a ROS-free part does not load the node.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from tpsr_ros.lazy import lazy_exports

_API = {
    "FilterNode": "tpsr_ros.filter_node.node",
    "load_inputs": "tpsr_ros.filter_node.node",
    "main": "tpsr_ros.filter_node.node",
    "PROG": "tpsr_ros.filter_node.node",
    "FilterNodeParams": "tpsr_ros.filter_node.params",
    "ACTION_TOPIC": "tpsr_ros.filter_node.params",
    "CLOCK_TOPIC": "tpsr_ros.filter_node.params",
    "CMD_VEL_TOPIC": "tpsr_ros.filter_node.params",
    "DIAGNOSTICS_TOPIC": "tpsr_ros.filter_node.params",
    "IMAGE_TOPIC": "tpsr_ros.filter_node.params",
    "RESET_TOPIC": "tpsr_ros.filter_node.params",
    "STATE_TOPIC": "tpsr_ros.filter_node.params",
    "REJECT_REASONS": "tpsr_ros.filter_node.inputs",
}

__all__ = [
    "ACTION_TOPIC",
    "CLOCK_TOPIC",
    "CMD_VEL_TOPIC",
    "DIAGNOSTICS_TOPIC",
    "IMAGE_TOPIC",
    "PROG",
    "REJECT_REASONS",
    "RESET_TOPIC",
    "STATE_TOPIC",
    "FilterNode",
    "FilterNodeParams",
    "load_inputs",
    "main",
]

if TYPE_CHECKING:
    from tpsr_ros.filter_node.inputs import REJECT_REASONS
    from tpsr_ros.filter_node.node import PROG, FilterNode, load_inputs, main
    from tpsr_ros.filter_node.params import (
        ACTION_TOPIC,
        CLOCK_TOPIC,
        CMD_VEL_TOPIC,
        DIAGNOSTICS_TOPIC,
        IMAGE_TOPIC,
        RESET_TOPIC,
        STATE_TOPIC,
        FilterNodeParams,
    )


__getattr__, __dir__ = lazy_exports(__name__, _API, __all__)
