"""Watch the robot think: the view topics served to Foxglove, and layouts for three viewers.

    python -m tpsr_ros.view [--port P]

The view node (:mod:`~tpsr_ros.view.node`) relays the filter node's view topics (the
state, the predicted image, the state markers, the decoded pose), the simulator's camera,
command and true pose, and ``/diagnostics`` to a Foxglove WebSocket server, as CDR bytes
with their ``ros2msg`` schemas; it prints the server's ``ws://`` address. Its parts:

- :mod:`~tpsr_ros.view.topics`: the topics and their types, one table for the relay and
  the layouts;
- :mod:`~tpsr_ros.view.relays`: which topics to subscribe to, with what QoS (no ROS);
- :mod:`~tpsr_ros.view.server`: the Foxglove server (foxglove-sdk, the ``view`` extra);
- :mod:`~tpsr_ros.view.layouts`: the Foxglove, RViz2 and PlotJuggler layouts that ship,
  built in code and checked in next to it.

Names are imported on first use, so reading the topic table loads neither the node nor
foxglove-sdk.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from tpsr_ros.lazy import lazy_exports

_API = {
    "ViewNode": "tpsr_ros.view.node",
    "ViewParams": "tpsr_ros.view.node",
    "PROG": "tpsr_ros.view.node",
    "main": "tpsr_ros.view.node",
    "MARKER_ARRAY_TYPE": "tpsr_ros.view.topics",
    "VIEW_TOPICS": "tpsr_ros.view.topics",
}

__all__ = ["MARKER_ARRAY_TYPE", "PROG", "VIEW_TOPICS", "ViewNode", "ViewParams", "main"]

if TYPE_CHECKING:
    from tpsr_ros.view.node import PROG, ViewNode, ViewParams, main
    from tpsr_ros.view.topics import MARKER_ARRAY_TYPE, VIEW_TOPICS


__getattr__, __dir__ = lazy_exports(__name__, _API, __all__)
