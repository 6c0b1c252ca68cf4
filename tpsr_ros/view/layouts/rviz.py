"""The RViz2 configuration: fixed frame ``tpsr``, the state markers and both images.

Open it with ``rviz2 -d share/tpsr_ros/layouts/tpsr_view.rviz`` on a machine with ROS 2.
The markers are read reliable and transient-local, as the filter node offers them (a late
RViz gets the latest), the images best-effort, which matches any camera.
"""

from __future__ import annotations

from typing import Any

import yaml

from tpsr_ros.view.layouts import topic
from tpsr_ros.view.topics import STATE_FRAME

__all__ = ["rviz_config"]


def _topic(name: str, *, reliable: bool, latched: bool = False) -> dict[str, Any]:
    return {
        "Depth": 5,
        "Durability Policy": "Transient Local" if latched else "Volatile",
        "History Policy": "Keep Last",
        "Reliability Policy": "Reliable" if reliable else "Best Effort",
        "Value": topic(name),
    }


def _image(title: str, name: str) -> dict[str, Any]:
    return {
        "Class": "rviz_default_plugins/Image",
        "Enabled": True,
        "Max Value": 1,
        "Median window": 5,
        "Min Value": 0,
        "Name": title,
        "Normalize Range": True,
        "Topic": _topic(name, reliable=False),
        "Value": True,
    }


def _displays() -> list[dict[str, Any]]:
    grid = {
        "Alpha": 0.5,
        "Cell Size": 1,
        "Class": "rviz_default_plugins/Grid",
        "Color": "160; 160; 164",
        "Enabled": True,
        "Name": "Grid",
        "Plane": "XY",
        "Plane Cell Count": 10,
        "Reference Frame": "<Fixed Frame>",
        "Value": True,
    }
    markers = {
        "Class": "rviz_default_plugins/MarkerArray",
        "Enabled": True,
        "Name": "state markers",
        "Namespaces": {"trail": True, "state": True, "training_states": True,
                       "action_values": True},
        "Topic": _topic("tpsr/state_markers", reliable=True, latched=True),
        "Value": True,
    }  # fmt: skip
    return [
        grid,
        markers,
        _image("camera", "camera/image_raw"),
        _image("predicted next image", "tpsr/predicted_image"),
    ]


def rviz_config() -> str:
    """Build the ``.rviz`` file (YAML)."""
    config = {
        "Panels": [
            {"Class": "rviz_common/Displays", "Name": "Displays"},
            {"Class": "rviz_common/Views", "Name": "Views"},
        ],
        "Visualization Manager": {
            "Class": "",
            "Displays": _displays(),
            "Enabled": True,
            "Global Options": {
                "Background Color": "48; 48; 48",
                "Fixed Frame": STATE_FRAME,
                "Frame Rate": 30,
            },
            "Name": "root",
            "Tools": [
                {"Class": "rviz_default_plugins/Interact", "Hide Inactive Objects": True},
                {"Class": "rviz_default_plugins/MoveCamera"},
                {"Class": "rviz_default_plugins/Select"},
                {"Class": "rviz_default_plugins/FocusCamera"},
                {"Class": "rviz_default_plugins/Measure", "Line color": "128; 128; 0"},
            ],
            "Transformation": {"Current": {"Class": "rviz_default_plugins/TF"}},
            "Value": True,
            "Views": {
                "Current": {
                    "Class": "rviz_default_plugins/Orbit",
                    "Distance": 12.0,
                    "Focal Point": {"X": 0.0, "Y": 0.0, "Z": 0.0},
                    "Name": "Current View",
                    "Pitch": 0.6,
                    "Target Frame": "<Fixed Frame>",
                    "Value": "Orbit (rviz_default_plugins)",
                    "Yaw": 0.8,
                },
                "Saved": None,
            },
        },
    }
    header = "# tpsr-ros view for RViz2 (written by python -m tpsr_ros.view.layouts)\n"
    return header + str(yaml.safe_dump(config, sort_keys=False, default_flow_style=False))
