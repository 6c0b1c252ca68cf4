"""The topics the view relays, with their types: one table for the relay and the layouts.

Names are relative (resolved in the view's namespace, like the filter node's and the
simulator's) except ``/diagnostics``, which stays global as diagnostic aggregators expect.
The shipped layouts name these topics in the default namespace (``/tpsr/state``...).
"""

from __future__ import annotations

from types import MappingProxyType
from typing import Final

from tpsr_ros.io.messages import IMAGE_TYPE, POSE_TYPE, STATE_TYPE, TWIST_TYPE
from tpsr_ros.runtime.diagnostics import DIAGNOSTICS_TYPE

__all__ = ["MAP_FRAME", "MARKER_ARRAY_TYPE", "STATE_FRAME", "VIEW_TOPICS", "default_topic"]

MARKER_ARRAY_TYPE: Final = "visualization_msgs/msg/MarkerArray"
STATE_FRAME: Final = "tpsr"
"""Frame of the state and its markers: the three leading principal coordinates of the
training states, scaled to unit spread (:mod:`tpsr_ros.core.view_readout`)."""
MAP_FRAME: Final = "map"
"""Frame of the simulator's poses and of the pose decoded from the state."""

VIEW_TOPICS: Final = MappingProxyType(
    {
        "tpsr/state": STATE_TYPE,  # b_k: name b0..b{r-1}, values in position, frame tpsr
        "tpsr/predicted_image": IMAGE_TYPE,  # the expected next camera image, rgb8
        "tpsr/state_markers": MARKER_ARRAY_TYPE,  # trail, state, training states, actions
        "tpsr/decoded_pose": POSE_TYPE,  # the pose read out of the state, frame map
        "camera/image_raw": IMAGE_TYPE,  # o_k, rgb8
        "cmd_vel": TWIST_TYPE,  # the command in force
        "ground_truth/pose": POSE_TYPE,  # the simulator's true pose, frame map
        "/diagnostics": DIAGNOSTICS_TYPE,  # health, with predicted_image_rmse
    }
)
"""Topic name -> ROS 2 type of everything ``python -m tpsr_ros.view`` relays."""


def default_topic(name: str) -> str:
    """``name`` resolved in the default namespace ``/``, as the layouts name it."""
    return name if name.startswith("/") else "/" + name
