"""Helpers of the tests against the real rclpy (the ``ros`` extra's ros-jazzy wheels);
their ``ros_env`` fixture is in ``conftest.py``."""

from __future__ import annotations

import time

import numpy as np

from tpsr_ros.io import messages as m
from tpsr_ros.runtime import Node, NodeOptions, parse_ros_args

S = 10**9


def rclpy_node(name: str, node_cls=Node, *ros_args: str, **kwargs):
    options = NodeOptions.for_node(node_cls, parse_ros_args(list(ros_args)), **kwargs)
    if node_cls is Node:
        options = NodeOptions(
            name=name, namespace=options.namespace, ros_args=options.ros_args,
            log_level=options.log_level,
        )
    return node_cls(options)  # the transport comes from choose_backend -> rclpy


def spin_all(nodes, condition, timeout=10.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        for node in nodes:
            node.spin_once(0.01)
    return bool(condition())


def published_samples() -> list[tuple[str, object]]:
    """One message of every type our nodes publish."""
    from tpsr_ros.runtime.diagnostics import (
        DIAGNOSTICS_TYPE,
        OK,
        diagnostic_array,
        diagnostic_status,
    )

    image = np.arange(16 * 16 * 3, dtype=np.uint8).reshape(16, 16, 3)
    return [
        (m.IMAGE_TYPE, m.image_msg(2 * S, image)),
        (m.ACTION_TYPE, m.twist_stamped_msg(2 * S, 3.0, -6.0)),
        (m.POSE_TYPE, m.pose_msg(2 * S, 5.5, 40.25)),
        (m.REWARD_TYPE, m.reward_msg(2 * S, m.RewardSample(10.0, False, True))),
        (m.CLOCK_TYPE, m.clock_msg(2 * S)),
        (m.STATE_TYPE, m.state_msg(2 * S, np.array([1.0, -0.5, 0.25]))),
        (m.TWIST_TYPE, m.twist_msg(-3.0, 6.0)),
        (DIAGNOSTICS_TYPE, diagnostic_array(
            2 * S, [diagnostic_status(OK, "tpsr_filter: state", "ok", {"updates": 3})]
        )),
    ]


def rosout_qos():
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(
        depth=100, reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
    )
