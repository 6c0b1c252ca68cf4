"""The messages of one simulator step, shared by the bag generator and the node.

Every message of step k carries exactly the stamp t_k (DESIGN.md, "Time and steps").
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np

from tpsr_ros.io import messages as m

__all__ = ["CMD_IGNORED_TOPIC", "SimTopics", "step_messages"]

CMD_IGNORED_TOPIC = "sim/cmd_ignored"
"""The node's announcement of a ``cmd_vel`` that took no step.

A ``std_msgs/msg/Header``; the name is relative (it follows the node's namespace).
"""


@dataclass(frozen=True)
class SimTopics:
    """Topic names of the simulator (defaults from DESIGN.md; remappable).

    Bags use these absolute names; the node uses :meth:`relative` ones, which resolve in
    its namespace (the same names in the root namespace).
    """

    image: str = "/camera/image_raw"
    action: str = "/action"
    pose: str = "/ground_truth/pose"
    reward: str = "/reward"
    clock: str = "/clock"

    def relative(self) -> SimTopics:
        """Return the same names without the leading ``/`` (resolved in a node's namespace)."""
        return replace(self, **{f.name: getattr(self, f.name).lstrip("/") for f in fields(self)})

    def types(self) -> dict[str, str]:
        """Topic name to ROS message type."""
        return {
            self.image: m.IMAGE_TYPE,
            self.action: m.ACTION_TYPE,
            self.pose: m.POSE_TYPE,
            self.reward: m.REWARD_TYPE,
            self.clock: m.CLOCK_TYPE,
        }


def step_messages(
    topics: SimTopics,
    stamp_ns: int,
    image: np.ndarray,
    command: np.ndarray,
    position: np.ndarray,
    reward: m.RewardSample,
    *,
    components: tuple[str, ...] = ("linear.x", "linear.y"),
    heading: float | None = None,
) -> list[tuple[str, str, Any]]:
    """``(topic, type, message)`` for o_k, a_k (as commanded), true pose, r_k and clock.

    ``command`` holds the action's ``components`` (``drive``: linear.x and angular.z); the
    pose carries ``heading`` (rad about z) when the robot turns, else the identity.
    """
    twist = m.twist_from_components(dict(zip(components, command, strict=True)))
    return [
        (topics.image, m.IMAGE_TYPE, m.image_msg(stamp_ns, image)),
        (topics.action, m.ACTION_TYPE, m.stamped_twist(stamp_ns, twist)),
        (
            topics.pose,
            m.POSE_TYPE,
            m.pose_msg(stamp_ns, position[0], position[1], heading=heading),
        ),
        (topics.reward, m.REWARD_TYPE, m.reward_msg(stamp_ns, reward)),
        (topics.clock, m.CLOCK_TYPE, m.clock_msg(stamp_ns)),
    ]
